"""A sequence being simulated, frame by frame, and its partial file: an interrupted run continues where it stopped.

A full-resolution held-out trajectory can take the IPC solver hours (the torus's 62-frame press and drag took about
six on two cores), longer than a working session or a CI job. :class:`FrameRecord` keeps the frames solved so far;
every ``every_s`` seconds it is written, with the simulator's :meth:`~colgnn_core.sim.ipc.IPCSimulator.state`, to
``<sequence file>.partial`` (atomically; the name does not end in ``.npz``, so no ``*.npz`` listing of a dataset
folder picks it up). A later run of the same job finds it and continues from the saved frame. The file is used only
when its key matches: the same scene mesh and physics, the same poses up to their last row, and the same solver
options; otherwise it is ignored and overwritten.

A continued sequence is a verified simulation of the same poses. It agrees with an uninterrupted run to the linear
solver's tolerance, not bit for bit, because the lagged factor that preconditions the solves is not saved.
"""

from __future__ import annotations

import hashlib
import json
import os
import time
from pathlib import Path

import numpy as np

from colgnn_core.io import SUBFRAME_KEYS, atomic_write

PARTIAL_SUFFIX = ".partial"
PARTIAL_EVERY_S = 60.0  # a full-resolution frame takes seconds to minutes; a save costs well under a second


def partial_path(sequence_file: str | os.PathLike) -> Path:
    """Where the partial file of the sequence written to ``sequence_file`` lives."""
    p = Path(sequence_file)
    return p.with_name(p.name + PARTIAL_SUFFIX)


def partial_key(stamp: dict[str, str], poses: np.ndarray, sim_options: dict) -> str:
    """What a partial file must have been made with to be continued: the scene stamp (mesh and physics
    fingerprints), the poses [T,7] and the solver options."""
    h = hashlib.sha256(np.ascontiguousarray(poses, dtype=np.float64).tobytes()).hexdigest()
    return json.dumps({**stamp, "poses_sha256": h, "sim_options": sim_options}, sort_keys=True, default=str)


class FrameRecord:
    """The frames of one sequence as they are solved: positions, solver statistics and recorded motion paths."""

    def __init__(self, frames: int, n_obj: int, n_tool: int) -> None:
        self.object_positions = np.empty((frames, n_obj, 3))
        self.tool_positions = np.empty((frames, n_tool, 3))
        self.newton_iterations = np.zeros(frames, dtype=np.int64)
        self.step_ms = np.zeros(frames)
        self.min_distance = np.zeros(frames)
        self.kappa = np.zeros(frames)
        self.subframes = np.ones(frames, dtype=np.int64)
        self.path_frame: list[int] = []
        self.path_obj: list[np.ndarray] = []
        self.path_tool: list[np.ndarray] = []
        self.done = 0  # frames 0..done are filled

    def first(self, obj: np.ndarray, tool: np.ndarray, distance: float) -> None:
        """Frame 0: the settled object [N,3], the tool [M,3] (m) and their distance (m)."""
        self.object_positions[0], self.tool_positions[0], self.min_distance[0] = obj, tool, distance
        self.done = 0

    def add(self, k: int, obj: np.ndarray, tool: np.ndarray, st) -> None:
        """Frame ``k`` from the simulator's positions and its :class:`~colgnn_core.sim.ipc.StepStats`."""
        self.object_positions[k], self.tool_positions[k] = obj, tool
        self.newton_iterations[k], self.step_ms[k] = st.newton_iterations, st.ms
        self.min_distance[k], self.kappa[k], self.subframes[k] = st.min_distance, st.kappa, st.subframes
        for xo, xt in st.path:
            self.path_frame.append(k)
            self.path_obj.append(xo)
            self.path_tool.append(xt)
        self.done = k

    def extras(self) -> dict[str, np.ndarray]:
        """The solver statistics and, where any frame recorded a path, its :data:`SUBFRAME_KEYS` arrays."""
        out = {"newton_iterations": self.newton_iterations, "step_ms": self.step_ms,
               "min_distance": self.min_distance, "kappa": self.kappa, "subframes": self.subframes}
        if self.path_frame:
            out.update(zip(SUBFRAME_KEYS, (np.asarray(self.path_frame, dtype=np.int64), np.asarray(self.path_obj),
                                           np.asarray(self.path_tool))))
        return out

    def save(self, path: Path, key: str, sim_state: dict[str, np.ndarray]) -> None:
        """Write frames 0..done and the simulator state to ``path`` atomically."""
        n = self.done + 1
        arrays = {"key": np.asarray(key), "done": np.int64(self.done),
                  "object_positions": self.object_positions[:n], "tool_positions": self.tool_positions[:n],
                  "newton_iterations": self.newton_iterations[:n], "step_ms": self.step_ms[:n],
                  "min_distance": self.min_distance[:n], "kappa": self.kappa[:n], "subframes": self.subframes[:n],
                  "path_frame": np.asarray(self.path_frame, dtype=np.int64),
                  "path_obj": np.asarray(self.path_obj).reshape(-1, *self.object_positions.shape[1:]),
                  "path_tool": np.asarray(self.path_tool).reshape(-1, *self.tool_positions.shape[1:]),
                  **{f"sim_{k}": v for k, v in sim_state.items()}}
        with atomic_write(path, "wb") as fh:
            np.savez(fh, **arrays)

    def load(self, path: Path, key: str) -> dict[str, np.ndarray] | None:
        """Take the frames of a partial file made with ``key``; return its simulator state, or None (nothing
        taken) when there is no such file, it is unreadable, or it was made with another key or mesh."""
        try:
            with np.load(path, allow_pickle=False) as z:
                data = {k: z[k] for k in z.files}
        except (OSError, ValueError, EOFError):
            return None
        try:
            n = int(data["done"]) + 1
            if (str(data["key"]) != key or not 1 <= n <= len(self.object_positions)
                    or data["object_positions"].shape != (n, *self.object_positions.shape[1:])
                    or data["tool_positions"].shape != (n, *self.tool_positions.shape[1:])):
                return None
            for name in ("object_positions", "tool_positions", "newton_iterations", "step_ms", "min_distance",
                         "kappa", "subframes"):
                getattr(self, name)[:n] = data[name]
            self.path_frame = [int(f) for f in data["path_frame"]]
            self.path_obj, self.path_tool = list(data["path_obj"]), list(data["path_tool"])
            self.done = n - 1
            return {k[len("sim_"):]: v for k, v in data.items() if k.startswith("sim_")}
        except KeyError:
            return None


class PartialSaver:
    """Saves a :class:`FrameRecord` to its partial file at most every ``every_s`` seconds (``path`` None: never)."""

    def __init__(self, path: Path | None, key: str, every_s: float = PARTIAL_EVERY_S) -> None:
        self.path, self.key, self.every_s = path, key, float(every_s)
        self.last = time.monotonic()

    def maybe_save(self, record: FrameRecord, sim_state) -> bool:
        """Save if the interval has passed; ``sim_state`` is called only then. True when it saved."""
        if self.path is None or time.monotonic() - self.last < self.every_s:
            return False
        record.save(self.path, self.key, sim_state())
        self.last = time.monotonic()
        return True
