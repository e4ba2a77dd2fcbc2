"""Pictures of sequences and rollouts: object and tool, coloured by tool distance.

Works on any contract ``.npz`` (ground truth or rollout); the signed distance of
each object vertex to the tool surface is measured on the tool mesh stored in
the file, so no scene is needed. Penetrating vertices (distance < 0) are drawn
in a saturated red so a person can spot them at a glance.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from colgnn_core.errors import InputError
from colgnn_core.io import Sequence, atomic_write

_TOOL_COLOR = (0.55, 0.58, 0.62, 0.35)
_PENETRATION_COLOR = np.array([0.85, 0.05, 0.05, 1.0])


def tool_signed_distance(points: np.ndarray, tool_vertices: np.ndarray, tool_faces: np.ndarray) -> np.ndarray:
    """Signed distance [N] (m) of ``points`` [N,3] to a closed tool mesh; negative inside."""
    import trimesh

    mesh = trimesh.Trimesh(tool_vertices, tool_faces, process=False)
    _, dist, _ = trimesh.proximity.closest_point(mesh, points)
    inside = mesh.contains(points) if mesh.is_watertight else np.zeros(len(points), bool)
    return np.where(inside, -dist, dist)


def pick_frames(total: int, count: int) -> list[int]:
    """``count`` evenly spaced frame indices in [0, total), always including the last."""
    count = max(1, min(count, total))
    return sorted({int(round(i)) for i in np.linspace(0, total - 1, count)})


def _face_colors(seq: Sequence, frame: int, scale: float) -> np.ndarray:
    import matplotlib

    faces = seq.object_faces
    verts = seq.object_positions[frame]
    dist = tool_signed_distance(verts, seq.tool_positions[frame], seq.tool_faces)
    face_dist = dist[faces].min(axis=1)
    colors = matplotlib.colormaps["viridis"](np.clip(face_dist / scale, 0.0, 1.0))
    colors[face_dist < 0] = _PENETRATION_COLOR
    return colors


def _draw_frame(ax, seq: Sequence, frame: int, scale: float, limits: tuple[np.ndarray, np.ndarray], title: str) -> None:
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection

    obj = seq.object_positions[frame][seq.object_faces]
    tool = seq.tool_positions[frame][seq.tool_faces]
    ax.add_collection3d(Poly3DCollection(obj, facecolors=_face_colors(seq, frame, scale), edgecolor="none", linewidth=0))
    ax.add_collection3d(Poly3DCollection(tool, facecolors=_TOOL_COLOR, edgecolor="none", linewidth=0))
    lo, hi = limits
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect(hi - lo)
    ax.view_init(elev=22, azim=-60)
    ax.set_axis_off()
    ax.set_title(title, fontsize=9)


def _limits(seqs: list[Sequence], frames: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """A common view box around the objects, extended to the tool where it is near."""
    obj = np.concatenate([s.object_positions[frames].reshape(-1, 3) for s in seqs])
    lo, hi = obj.min(0), obj.max(0)
    pad = 0.25 * (hi - lo).max()
    lo, hi = lo - pad, hi + pad
    tool = np.concatenate([s.tool_positions[frames].reshape(-1, 3) for s in seqs])
    near = tool[np.all((tool > lo) & (tool < hi + pad), axis=1)]
    if len(near):
        lo, hi = np.minimum(lo, near.min(0)), np.maximum(hi, near.max(0))
    return lo, hi


def render_strip(seqs: list[Sequence], labels: list[str], out: str | Path, frames: list[int] | None = None, count: int = 5) -> Path:
    """Write a PNG grid: one row per sequence, one column per frame."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    total = min(s.frames for s in seqs)
    frames = frames or pick_frames(total, count)
    limits = _limits(seqs, frames)
    scale = 0.1 * float(np.linalg.norm(limits[1] - limits[0]))
    fig = plt.figure(figsize=(2.6 * len(frames), 2.6 * len(seqs)), dpi=90)
    for r, (seq, label) in enumerate(zip(seqs, labels)):
        for c, f in enumerate(frames):
            ax = fig.add_subplot(len(seqs), len(frames), r * len(frames) + c + 1, projection="3d")
            _draw_frame(ax, seq, f, scale, limits, f"{label}  t={f}" if label else f"t={f}")
    fig.tight_layout()
    with atomic_write(out) as fh:
        fig.savefig(fh, format="png")
    plt.close(fig)
    return out


def render_gif(seq: Sequence, out: str | Path, stride: int = 1, fps: int = 10) -> Path:
    """Write an animated GIF of ``seq`` (every ``stride``-th frame)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from PIL import Image

    out = Path(out)
    frames = list(range(0, seq.frames, max(1, stride)))
    limits = _limits([seq], frames)
    scale = 0.1 * float(np.linalg.norm(limits[1] - limits[0]))
    images = []
    fig = plt.figure(figsize=(4, 4), dpi=80)
    for f in frames:
        fig.clf()
        ax = fig.add_subplot(1, 1, 1, projection="3d")
        _draw_frame(ax, seq, f, scale, limits, f"t={f}")
        fig.canvas.draw()
        images.append(Image.fromarray(np.asarray(fig.canvas.buffer_rgba())[..., :3]).convert("P", palette=Image.ADAPTIVE))
    plt.close(fig)
    with atomic_write(out) as fh:
        images[0].save(fh, format="GIF", save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)
    return out


def render_file(path: str | Path, out: str | Path, count: int = 5, stride: int = 1) -> Path:
    """Render a sequence/rollout file to ``out`` (.png strip or .gif animation)."""
    from colgnn_core.io import load_sequence

    out = Path(out)
    suffix = out.suffix.lower()
    if suffix not in (".png", ".gif"):
        raise InputError(f"--out must end in .png or .gif, got {out.name!r}")
    seq = load_sequence(path)
    if suffix == ".gif":
        return render_gif(seq, out, stride=stride)
    return render_strip([seq], [""], out, count=count)
