"""The contract file formats, in one place: read, validate, atomic write.

* Sequence / rollout ``.npz`` (ground truth and predictions share the keys):
  ``object_positions`` [T,N,3] m, ``object_faces`` [F,3], ``tool_positions``
  [T,M,3] m, ``tool_faces`` [G,3], ``tool_poses`` [T,7] (px,py,pz,qx,qy,qz,qw),
  ``dt`` seconds. Extra keys are kept.
* The motion from frame t-1 to frame t is the straight one (every vertex linear), unless the file records
  intermediate states for frame t (``subframe_frame`` [K] = t, ``subframe_object_positions`` [K,N,3],
  ``subframe_tool_positions`` [K,M,3], in order): then it is the piecewise-linear path through them.
  :meth:`Sequence.motion` gives the states of either. The ground-truth solver records them where its straight
  frame-to-frame motion is not collision-free; the Predictor never does (its straight motion is).
* Poses ``.csv`` with the header ``t,px,py,pz,qx,qy,qz,qw``.

Every writer goes through :func:`atomic_write`, so a crash never leaves a
half-written file under the final name.
"""

from __future__ import annotations

import contextlib
import io
import os
import tempfile
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Iterator

import numpy as np

from colgnn_core.errors import InputError
from colgnn_core.geometry.transforms import validate_pose

POSE_COLUMNS = ("t", "px", "py", "pz", "qx", "qy", "qz", "qw")
_UMASK = os.umask(0)
os.umask(_UMASK)
SEQUENCE_KEYS = ("object_positions", "object_faces", "tool_positions", "tool_faces", "tool_poses", "dt")
SUBFRAME_KEYS = ("subframe_frame", "subframe_object_positions", "subframe_tool_positions")


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike, mode: str = "wb") -> Iterator[io.IOBase]:
    """Open a temporary file beside ``path``; rename it over ``path`` on success.

    The folder must exist and be writable, otherwise :class:`InputError`.
    """
    path = Path(path)
    folder = path.parent if str(path.parent) else Path(".")
    if not folder.is_dir():
        raise InputError(f"output folder does not exist: {folder}")
    try:
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=folder)
    except OSError as exc:
        raise InputError(f"cannot write to {folder}: {exc.strerror}") from exc
    try:
        os.chmod(tmp, 0o666 & ~_UMASK)  # mkstemp makes 0600 files; give the usual permissions
        with os.fdopen(fd, mode) as fh:
            yield fh
            fh.flush()
            os.fsync(fh.fileno())
        os.replace(tmp, path)
    except BaseException:
        with contextlib.suppress(OSError):
            os.unlink(tmp)
        raise


def ensure_writable_dir(path: str | os.PathLike) -> Path:
    """Create ``path`` if needed and check that files can be written in it."""
    path = Path(path)
    try:
        path.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create output folder {path}: {exc.strerror}") from exc
    if not os.access(path, os.W_OK | os.X_OK):
        raise InputError(f"output folder is not writable: {path}")
    return path


def write_generated_section(path: str | os.PathLike, name: str, text: str) -> Path:
    """Replace the block between ``<!-- begin NAME -->`` and ``<!-- end NAME -->`` in the markdown file ``path``
    with ``text`` (atomically), so that a page can mix hand-written prose with a table its command writes.

    A missing file is created with just the block; a file without the markers gets the block appended. Two begin
    markers, or a begin without its end, raise :class:`InputError` (the file is left as it was).
    """
    path = Path(path)
    begin, end = f"<!-- begin {name} -->", f"<!-- end {name} -->"
    block = f"{begin}\n{text.strip()}\n{end}"
    old = path.read_text() if path.exists() else ""
    if old.count(begin) > 1 or old.count(begin) != old.count(end) or old.find(end) < old.find(begin):
        raise InputError(f"{path}: the markers {begin!r} / {end!r} must each appear once, or not at all")
    if begin in old:
        head, rest = old.split(begin, 1)
        _, tail = rest.split(end, 1)
        new = head + block + tail
    else:
        new = (old.rstrip() + "\n\n" if old.strip() else "") + block + "\n"
    with atomic_write(path, "w") as fh:
        fh.write(new)
    return path


@dataclass
class Sequence:
    """One ground-truth sequence or rollout (see module docstring for units)."""

    object_positions: np.ndarray
    object_faces: np.ndarray
    tool_positions: np.ndarray
    tool_faces: np.ndarray
    tool_poses: np.ndarray
    dt: float
    extra: dict[str, np.ndarray] = field(default_factory=dict)

    @property
    def frames(self) -> int:
        return int(self.object_positions.shape[0])

    def motion(self, t: int) -> list[tuple[np.ndarray, np.ndarray]]:
        """The states (object [N,3], tool [M,3]) the motion from frame t-1 to frame t passes through, both frames
        included: two for a straight motion, more where intermediate states are recorded (module docstring)."""
        if not 1 <= t < self.frames:
            raise IndexError(f"frame {t} has no motion into it (frames 1..{self.frames - 1})")
        states = [(self.object_positions[t - 1], self.tool_positions[t - 1])]
        if "subframe_frame" in self.extra:
            for k in np.flatnonzero(np.asarray(self.extra["subframe_frame"]) == t):
                states.append((self.extra["subframe_object_positions"][k], self.extra["subframe_tool_positions"][k]))
        states.append((self.object_positions[t], self.tool_positions[t]))
        return states

    def validate(self, source: str = "sequence") -> "Sequence":
        """Check shapes, index ranges and finiteness; raise :class:`InputError`."""
        op, tp = self.object_positions, self.tool_positions
        if op.ndim != 3 or op.shape[2] != 3 or op.shape[0] < 1 or op.shape[1] < 1:
            raise InputError(f"{source}: object_positions must be [T,N,3], got {op.shape}")
        if tp.ndim != 3 or tp.shape[2] != 3 or tp.shape[0] != op.shape[0]:
            raise InputError(f"{source}: tool_positions must be [T,M,3] with T={op.shape[0]}, got {tp.shape}")
        if self.tool_poses.shape != (op.shape[0], 7):
            raise InputError(f"{source}: tool_poses must be [{op.shape[0]},7], got {self.tool_poses.shape}")
        for name, faces, n in (("object_faces", self.object_faces, op.shape[1]),
                               ("tool_faces", self.tool_faces, tp.shape[1])):
            if faces.ndim != 2 or faces.shape[1] != 3 or faces.shape[0] < 1:
                raise InputError(f"{source}: {name} must be [F,3], got {faces.shape}")
            if faces.min() < 0 or faces.max() >= n:
                raise InputError(f"{source}: {name} index out of range [0,{n})")
        for name in ("object_positions", "tool_positions", "tool_poses"):
            if not np.all(np.isfinite(getattr(self, name))):
                raise InputError(f"{source}: {name} contains NaN or inf")
        present = [k for k in SUBFRAME_KEYS if k in self.extra]
        if present:
            if len(present) != len(SUBFRAME_KEYS):
                raise InputError(f"{source}: {', '.join(present)} without the other subframe keys")
            sf = np.asarray(self.extra["subframe_frame"])
            so = np.asarray(self.extra["subframe_object_positions"])
            st = np.asarray(self.extra["subframe_tool_positions"])
            K = len(sf)
            if (sf.ndim != 1 or so.shape != (K, *op.shape[1:]) or st.shape != (K, *tp.shape[1:])
                    or (K and (sf.min() < 1 or sf.max() >= op.shape[0] or np.any(np.diff(sf) < 0)))):
                raise InputError(f"{source}: subframe keys must be [K] frame ids in 1..T-1 (non-decreasing), "
                                 f"[K,N,3] and [K,M,3]")
            if not (np.all(np.isfinite(so)) and np.all(np.isfinite(st))):
                raise InputError(f"{source}: subframe positions contain NaN or inf")
        if not (np.isfinite(self.dt) and self.dt > 0):
            raise InputError(f"{source}: dt must be a positive number, got {self.dt}")
        return self


def save_sequence(path: str | os.PathLike, seq: Sequence) -> None:
    """Validate and write ``seq`` atomically as a compressed ``.npz``."""
    seq.validate(str(path))
    arrays = {
        "object_positions": np.asarray(seq.object_positions, dtype=np.float64),
        "object_faces": np.asarray(seq.object_faces, dtype=np.int64),
        "tool_positions": np.asarray(seq.tool_positions, dtype=np.float64),
        "tool_faces": np.asarray(seq.tool_faces, dtype=np.int64),
        "tool_poses": np.asarray(seq.tool_poses, dtype=np.float64),
        "dt": np.float64(seq.dt),
    }
    for key, value in seq.extra.items():
        if key in arrays:
            raise ValueError(f"extra key {key!r} shadows a contract key")
        arrays[key] = np.asarray(value)
    with atomic_write(path) as fh:
        np.savez_compressed(fh, **arrays)


def load_sequence(path: str | os.PathLike) -> Sequence:
    """Read and validate a sequence/rollout ``.npz``; bad files raise :class:`InputError`."""
    path = Path(path)
    if not path.is_file():
        raise InputError(f"no such sequence file: {path}")
    try:
        with np.load(path, allow_pickle=False) as data:
            missing = [k for k in SEQUENCE_KEYS if k not in data.files]
            if missing:
                raise InputError(f"{path}: missing keys {', '.join(missing)}")
            arrays = {k: data[k] for k in data.files}
    except (zipfile.BadZipFile, OSError, ValueError, EOFError) as exc:
        if isinstance(exc, InputError):
            raise
        raise InputError(f"{path}: not a readable .npz file ({exc})") from exc
    seq = Sequence(
        object_positions=arrays.pop("object_positions").astype(np.float64),
        object_faces=arrays.pop("object_faces").astype(np.int64),
        tool_positions=arrays.pop("tool_positions").astype(np.float64),
        tool_faces=arrays.pop("tool_faces").astype(np.int64),
        tool_poses=arrays.pop("tool_poses").astype(np.float64),
        dt=float(arrays.pop("dt")),
        extra=arrays,
    )
    return seq.validate(str(path))


def read_poses_csv(path: str | os.PathLike) -> tuple[np.ndarray, np.ndarray]:
    """Read a poses CSV. Returns ``(t [T] s, poses [T,7])``.

    Checks the header, the column count, numbers, finiteness and unit
    quaternions (|‖q‖−1| ≤ 1e-3; smaller errors are normalised). Workspace
    bounds are scene-specific and checked by the caller.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError(f"no such poses file: {path}")
    lines = [ln.strip() for ln in path.read_text().splitlines() if ln.strip()]
    if not lines:
        raise InputError(f"{path}: empty poses file")
    header = tuple(c.strip() for c in lines[0].split(","))
    if header != POSE_COLUMNS:
        missing = [c for c in POSE_COLUMNS if c not in header]
        detail = f"missing column(s) {', '.join(missing)}" if missing else f"columns must be {','.join(POSE_COLUMNS)}"
        raise InputError(f"{path}: bad header ({detail})")
    rows = []
    for i, line in enumerate(lines[1:], start=2):
        cells = line.split(",")
        if len(cells) != len(POSE_COLUMNS):
            raise InputError(f"{path}:{i}: expected {len(POSE_COLUMNS)} values, got {len(cells)}")
        try:
            rows.append([float(c) for c in cells])
        except ValueError as exc:
            raise InputError(f"{path}:{i}: not a number ({exc})") from exc
    if not rows:
        raise InputError(f"{path}: no pose rows")
    table = np.asarray(rows, dtype=np.float64)
    bad = ~np.all(np.isfinite(table), axis=1)
    if bad.any():
        raise InputError(f"{path}:{int(np.argmax(bad)) + 2}: NaN or inf value")
    poses = np.empty((len(table), 7))
    for i, row in enumerate(table):
        try:
            poses[i] = validate_pose(row[1:])
        except InputError as exc:
            raise InputError(f"{path}:{i + 2}: {exc}") from exc
    return table[:, 0], poses


def write_poses_csv(path: str | os.PathLike, t: np.ndarray, poses: np.ndarray) -> None:
    """Write ``poses`` [T,7] with times ``t`` [T] (seconds) atomically."""
    poses = np.asarray(poses, dtype=np.float64)
    if poses.ndim != 2 or poses.shape[1] != 7 or len(t) != len(poses):
        raise ValueError(f"poses must be [T,7] matching t, got {poses.shape} and {len(t)}")
    body = [",".join(POSE_COLUMNS)]
    body += [",".join(repr(float(v)) for v in (ti, *p)) for ti, p in zip(t, poses)]
    with atomic_write(path, "w") as fh:
        fh.write("\n".join(body) + "\n")
