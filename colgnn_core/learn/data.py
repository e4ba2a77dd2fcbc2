"""Training data: the ground-truth sequences of a dataset folder as (sequence, t) transitions.

A dataset folder (``colgnn generate``) holds ``train_XXXX.npz`` / ``test_XXXX.npz``
contract sequences and a ``manifest.json``. :class:`FrameDataset` loads one split
into memory, checks every file against the scene it is trained for (vertex and
face counts, faces, tool mesh, dt, and, where the files or the manifest carry
them, scene name, resolution, rest positions and mesh fingerprint) and gives the
transition t -> t+1 of any sample as model inputs.

Sample order: :func:`sample_at` maps a global step to a sample with a seeded
permutation per epoch, a pure function of (seed, step, rank). Resuming needs no
sampler state, and the ranks of a data-parallel run take disjoint shards of each
epoch (rank r of W takes stream positions ``step * W + r``).
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from colgnn_core.errors import InputError
from colgnn_core.io import load_sequence
from colgnn_core.learn.graph import GraphTemplate
from colgnn_core.learn.model import Frame, frame_from_sequence


@dataclass
class SeqArrays:
    """The arrays of one sequence the training loop needs (float64, metres)."""

    name: str
    object_positions: np.ndarray  # [T,N_mesh,3]
    tool_positions: np.ndarray    # [T,M,3]
    tool_poses: np.ndarray        # [T,7]

    @property
    def frames(self) -> int:
        return int(self.object_positions.shape[0])


def dataset_files(data_dir: str | Path, split: str) -> list[Path]:
    """Sorted ``{split}_XXXX.npz`` files of a dataset folder; InputError if there are none."""
    data_dir = Path(data_dir)
    if not data_dir.is_dir():
        raise InputError(f"no such dataset folder: {data_dir}")
    files = sorted(data_dir.glob(f"{split}_[0-9][0-9][0-9][0-9].npz"))
    if not files:
        raise InputError(f"{data_dir}: no {split}_XXXX.npz sequence files (generate them with `colgnn generate`)")
    return files


def read_manifest(data_dir: str | Path) -> dict | None:
    """The dataset manifest, or None when the folder has none."""
    path = Path(data_dir) / "manifest.json"
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as exc:
        raise InputError(f"{path}: unreadable manifest ({exc})") from exc


def check_manifest(manifest: dict | None, scene, source: str) -> None:
    """InputError when the manifest names another scene, resolution, mesh or physics fingerprint."""
    if not manifest:
        return
    for key, want in (("scene", scene.name), ("resolution", scene.resolution)):
        if key in manifest and manifest[key] != want:
            raise InputError(f"{source}: dataset is for {key} {manifest[key]!r}, not {want!r}")
    fp = manifest.get("object_fingerprint")
    if fp is not None and fp != scene.object.fingerprint():
        raise InputError(f"{source}: dataset was generated on a different {scene.name!r} mesh (fingerprint mismatch)")
    fp = manifest.get("physics_fingerprint")
    if fp is not None and not scene.accepts_physics(fp):
        raise InputError(f"{source}: dataset was simulated with other {scene.name!r} physics (material, glued "
                         f"vertices, ground, friction, dt or tool changed since; physics fingerprint mismatch)")


def load_checked_sequence(path: Path, scene) -> SeqArrays:
    """Load one sequence file and check it belongs to ``scene``; InputError naming the file otherwise."""
    try:
        seq = load_sequence(path)
    except InputError:
        raise
    except Exception as exc:  # zlib / zipfile errors inside a damaged member
        raise InputError(f"{path}: not a readable sequence file (truncated or corrupt?): {exc}") from exc
    n_mesh = scene.object.vertices.shape[0]
    n_tool = scene.tool.vertices.shape[0]
    op = seq.object_positions
    if op.shape[1] != n_mesh:
        raise InputError(f"{path}: {op.shape[1]} object vertices, but scene {scene.name}/{scene.resolution} has "
                         f"{n_mesh}")
    if seq.object_faces.shape != scene.object.faces.shape or not np.array_equal(seq.object_faces, scene.object.faces):
        raise InputError(f"{path}: object faces differ from scene {scene.name}/{scene.resolution}")
    if seq.tool_positions.shape[1] != n_tool or seq.tool_faces.shape != scene.tool.faces.shape:
        raise InputError(f"{path}: tool mesh ({seq.tool_positions.shape[1]} vertices) differs from scene "
                         f"{scene.name}/{scene.resolution} ({n_tool})")
    if not np.isclose(seq.dt, scene.dt, rtol=1e-9, atol=0.0):
        raise InputError(f"{path}: dt={seq.dt} s, scene {scene.name} uses dt={scene.dt} s")
    for key, want in (("scene", scene.name), ("resolution", scene.resolution)):
        if key in seq.extra and str(seq.extra[key]) != want:
            raise InputError(f"{path}: sequence of {key} {str(seq.extra[key])!r}, not {want!r}")
    rest = seq.extra.get("object_rest")
    if rest is not None and (rest.shape != scene.object.vertices.shape
                             or not np.allclose(rest, scene.object.vertices, rtol=0.0, atol=1e-9)):
        raise InputError(f"{path}: rest mesh differs from scene {scene.name}/{scene.resolution}")
    if seq.frames < 2:
        raise InputError(f"{path}: needs at least 2 frames, has {seq.frames}")
    return SeqArrays(path.name, op, seq.tool_positions, seq.tool_poses)


class FrameDataset:
    """All transitions t -> t+1 of one split of a dataset folder, checked against ``scene``.

    Sample ``i`` is ``index[i] = (sequence, t)``, in file order then time order.
    """

    def __init__(self, scene, data_dir: str | Path, split: str = "train"):
        self.scene = scene
        self.data_dir = Path(data_dir)
        self.split = split
        check_manifest(read_manifest(self.data_dir), scene, str(self.data_dir / "manifest.json"))
        self.sequences = [load_checked_sequence(p, scene) for p in dataset_files(self.data_dir, split)]
        self.index = np.array([(s, t) for s, seq in enumerate(self.sequences) for t in range(seq.frames - 1)],
                              dtype=np.int64).reshape(-1, 2)
        self.priors: list[np.ndarray] | None = None  # per sequence [T,N,3] float32 (m), see attach_priors

    def attach_priors(self, prior_of: Callable[[SeqArrays], np.ndarray], progress: bool = False) -> None:
        """Give every sample a physics prior: ``prior_of(sequence)`` [T,N,3] (m), computed once per sequence here
        and kept as float32 (a prior may depend on the tool's path, so it is computed along whole sequences)."""
        seqs = self.sequences
        if progress:
            from tqdm import tqdm  # lazy: an optional progress bar

            seqs = tqdm(seqs, desc="physics prior", unit="seq")
        self.priors = [np.asarray(prior_of(seq), dtype=np.float32) for seq in seqs]

    def __len__(self) -> int:
        return int(self.index.shape[0])

    def sample(self, template: GraphTemplate, i: int) -> tuple[Frame, torch.Tensor, np.ndarray]:
        """``(frame, x_next [N,3], pose_t [7])`` of sample ``i`` (graph nodes of ``template``)."""
        s, t = (int(v) for v in self.index[i])
        seq = self.sequences[s]
        priors = None if self.priors is None else self.priors[s]
        frame, x_next = frame_from_sequence(template, seq.object_positions, seq.tool_positions, seq.tool_poses, t,
                                            priors)
        return frame, x_next, np.asarray(seq.tool_poses[t])

    def displacements(self, nodes: np.ndarray, rest: np.ndarray, max_frames: int = 4000) -> np.ndarray:
        """Every frame's displacement of the given mesh nodes from ``rest`` [N,3] (m): [F,N,3] float64.

        With more than ``max_frames`` frames in all, an evenly spaced subset of them (memory: F x N x 24 bytes)."""
        frames = [(s, t) for s, seq in enumerate(self.sequences) for t in range(seq.frames)]
        if len(frames) > max_frames:
            frames = [frames[i] for i in np.linspace(0, len(frames) - 1, max_frames).round().astype(int)]
        rest = np.asarray(rest, dtype=np.float64)
        return np.stack([self.sequences[s].object_positions[t][nodes] - rest for s, t in frames])

    def displacement_stats(self, nodes: np.ndarray, free: np.ndarray | None = None) -> dict[str, float]:
        """Per-frame displacement |x_{t+1} - x_t| (m) of the given mesh nodes over every transition.

        Returns ``rms`` (over nodes and frames), ``rms_moving`` (over frames whose largest displacement is
        at least 10% of the largest in the data: frames where something happens), ``max``, and
        ``max_deviation``, the largest distance of a node from its rest position.
        """
        free_nodes = nodes if free is None else nodes[free]
        rest = np.asarray(self.scene.object.vertices)[free_nodes]
        per_frame_sq, per_frame_max, dev = [], [], 0.0
        for seq in self.sequences:
            x = seq.object_positions[:, free_nodes]
            d = np.linalg.norm(np.diff(x, axis=0), axis=2)  # [T-1,N]
            per_frame_sq.append((d ** 2).mean(axis=1))
            per_frame_max.append(d.max(axis=1))
            dev = max(dev, float(np.linalg.norm(x - rest, axis=2).max()))
        sq = np.concatenate(per_frame_sq)
        mx = np.concatenate(per_frame_max)
        moving = mx >= 0.1 * mx.max() if mx.max() > 0 else np.ones_like(mx, dtype=bool)
        return {"rms": float(np.sqrt(sq.mean())), "rms_moving": float(np.sqrt(sq[moving].mean())),
                "max": float(mx.max()), "max_deviation": dev}


@lru_cache(maxsize=4)
def _permutation(seed: int, epoch: int, n: int) -> np.ndarray:
    return np.random.default_rng([int(seed), int(epoch)]).permutation(n)


def sample_at(step: int, n: int, seed: int, rank: int = 0, world: int = 1) -> int:
    """Sample index for global ``step`` on ``rank`` of ``world``: a seeded permutation per epoch.

    The stream position is ``step * world + rank``; epoch = position // n. Within an epoch every sample is
    used once, and the ranks' samples at one step are distinct whenever ``world <= n``.
    """
    if n <= 0:
        raise ValueError("empty dataset")
    pos = int(step) * int(world) + int(rank)
    return int(_permutation(seed, pos // n, n)[pos % n])
