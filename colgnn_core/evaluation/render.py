"""Pictures of sequences and rollouts: object and tool, coloured by tool distance.

Works on any contract ``.npz`` (ground truth or rollout); the signed distance of
each object vertex to the tool surface is measured on the tool mesh stored in
the file, so no scene is needed. Penetrating vertices (distance < 0) are drawn
in a saturated red so a person can spot them at a glance.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import trimesh

from colgnn_core.errors import InputError
from colgnn_core.geometry.transforms import quat_to_matrix
from colgnn_core.io import Sequence, atomic_write, load_sequence
from colgnn_core.scenes import sample_poses

_TOOL_COLOR = (0.55, 0.58, 0.62, 0.35)
_PENETRATION_COLOR = np.array([0.85, 0.05, 0.05, 1.0])


def save_png(fig, path: str | Path) -> Path:
    """Lay out ``fig``, write it to ``path`` as PNG (atomically) and close it."""
    import matplotlib.pyplot as plt  # lazy: matplotlib is heavy and only the pictures need it

    fig.tight_layout()
    with atomic_write(path, "wb") as fh:
        fig.savefig(fh, format="png")
    plt.close(fig)
    return Path(path)


def tool_signed_distance(points: np.ndarray, tool_vertices: np.ndarray, tool_faces: np.ndarray) -> np.ndarray:
    """Signed distance [N] (m) of ``points`` [N,3] to a closed tool mesh; negative inside."""
    mesh = trimesh.Trimesh(tool_vertices, tool_faces, process=False)
    _, dist, _ = trimesh.proximity.closest_point(mesh, points)
    inside = mesh.contains(points) if mesh.is_watertight else np.zeros(len(points), bool)
    return np.where(inside, -dist, dist)


def plane_section(vertices: np.ndarray, faces: np.ndarray, origin: np.ndarray, normal: np.ndarray) -> np.ndarray:
    """Segments [K,2,3] where a triangle mesh crosses the plane through ``origin`` with unit ``normal``."""
    d = (vertices - origin) @ normal
    tri_d = d[faces]                                   # [F,3]
    # Sides are "d < 0" and "d >= 0", so a vertex lying exactly on the plane belongs to one side and a triangle
    # touching the plane there still yields its segment (no gaps on symmetric meshes).
    cut = (tri_d.min(1) < 0) & (tri_d.max(1) >= 0)
    tri, td = vertices[faces[cut]], tri_d[cut]        # [K,3,3], [K,3]
    points = []
    for i, j in ((0, 1), (1, 2), (2, 0)):
        crosses = (td[:, i] < 0) != (td[:, j] < 0)
        s = np.where(crosses, td[:, i] / np.where(crosses, td[:, i] - td[:, j], 1.0), np.nan)
        points.append(tri[:, i] + s[:, None] * (tri[:, j] - tri[:, i]))
    points = np.stack(points, axis=1)                  # [K,3,3] with one NaN row per triangle
    ok = ~np.isnan(points[..., 0])
    order = np.argsort(~ok, axis=1, kind="stable")[:, :2]
    return np.take_along_axis(points, order[..., None], axis=1)


def section_plane(seq: Sequence, frames: list[int]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(origin, normal, in-plane horizontal axis) of a vertical plane through the tool's working point.

    The normal is the tool frame's x axis made horizontal, so a knife is cut across its blade.
    """
    pose = seq.tool_poses[frames[len(frames) // 2]]
    normal = quat_to_matrix(pose[3:])[:, 0].copy()
    normal[2] = 0.0
    if np.linalg.norm(normal) < 1e-6:
        normal = np.array([0.0, 1.0, 0.0])
    normal /= np.linalg.norm(normal)
    axis = np.cross([0.0, 0.0, 1.0], normal)
    return pose[:3], normal, axis / np.linalg.norm(axis)


def pick_frames(total: int, count: int) -> list[int]:
    """``count`` evenly spaced frame indices in [0, total), always including the last."""
    count = max(1, min(count, total))
    return sorted({int(round(i)) for i in np.linspace(0, total - 1, count)})


def _face_colors(seq: Sequence, frame: int, scale: float) -> np.ndarray:
    import matplotlib  # lazy: matplotlib is heavy and only the pictures need it

    faces = seq.object_faces
    verts = seq.object_positions[frame]
    dist = tool_signed_distance(verts, seq.tool_positions[frame], seq.tool_faces)
    face_dist = dist[faces].min(axis=1)
    colors = matplotlib.colormaps["viridis"](np.clip(face_dist / scale, 0.0, 1.0))
    colors[face_dist < 0] = _PENETRATION_COLOR
    return colors


def _draw_frame(ax, seq: Sequence, frame: int, scale: float, limits: tuple[np.ndarray, np.ndarray], title: str) -> None:
    from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # lazy: part of matplotlib (heavy, pictures only)

    obj = seq.object_positions[frame][seq.object_faces]
    tool = seq.tool_positions[frame][seq.tool_faces]
    ax.add_collection3d(Poly3DCollection(obj, facecolors=_face_colors(seq, frame, scale), edgecolor="none",
                                         linewidth=0))
    ax.add_collection3d(Poly3DCollection(tool, facecolors=_TOOL_COLOR, edgecolor="none", linewidth=0))
    lo, hi = limits
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect(hi - lo)
    ax.view_init(elev=22, azim=-60)
    ax.set_axis_off()
    ax.set_title(title, fontsize=9)


def _draw_section(ax, seq: Sequence, frame: int, plane, window: tuple[np.ndarray, np.ndarray]) -> None:
    """Cross-section through the contact: object outline (blue), tool outline (grey), crossings in red."""
    from matplotlib.collections import LineCollection  # lazy: matplotlib is heavy and only the pictures need it
    from matplotlib.ticker import MaxNLocator

    origin, normal, axis = plane
    to2d = lambda seg: np.stack([(seg - origin) @ axis, seg[..., 2]], axis=-1)
    obj = to2d(plane_section(seq.object_positions[frame], seq.object_faces, origin, normal))
    tool = to2d(plane_section(seq.tool_positions[frame], seq.tool_faces, origin, normal))
    ax.add_collection(LineCollection(tool, colors="0.35", linewidths=1.2))
    ax.add_collection(LineCollection(obj, colors="tab:blue", linewidths=0.9))
    lo, hi = window
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_aspect("equal")
    ax.tick_params(labelsize=6)
    ax.xaxis.set_major_locator(MaxNLocator(4))  # a 20 cm window at the default density ran its labels together


def _section_window(seqs: list[Sequence], frames: list[int], planes) -> tuple[np.ndarray, np.ndarray]:
    """A common 2-D window (in-plane axis, z) around the object outline, in metres."""
    pts = []
    for seq, (origin, normal, axis) in zip(seqs, planes):
        for f in frames:
            seg = plane_section(seq.object_positions[f], seq.object_faces, origin, normal).reshape(-1, 3)
            pts.append(np.stack([(seg - origin) @ axis, seg[:, 2]], axis=1))
    pts = np.concatenate(pts) if pts else np.zeros((1, 2))
    lo, hi = pts.min(0), pts.max(0)
    # zoom on the contact: the tool's working point is at in-plane coordinate 0
    half = max(0.3 * (hi - lo)[0], (hi - lo)[1])
    lo[0], hi[0] = max(lo[0], -half), min(hi[0], half)
    pad = 0.1 * (hi - lo).max()
    lo, hi = lo - pad, hi + pad
    hi[1] = max(hi[1], lo[1] + 0.6 * (hi[0] - lo[0]))  # room above for the tool
    return lo, hi


def _limits(seqs: list[Sequence], frames: list[int]) -> tuple[np.ndarray, np.ndarray]:
    """A common view box around the objects, extended to the tool where it is near."""
    obj = np.concatenate([s.object_positions[frames].reshape(-1, 3) for s in seqs])
    lo, hi = obj.min(0), obj.max(0)
    pad = 0.05 * (hi - lo).max()
    lo, hi = lo - pad, hi + pad
    tool = np.concatenate([s.tool_positions[frames].reshape(-1, 3) for s in seqs])
    near = tool[np.all((tool > lo) & (tool < hi + pad), axis=1)]
    if len(near):
        lo, hi = np.minimum(lo, near.min(0)), np.maximum(hi, near.max(0))
    return lo, hi


def render_strip(seqs: list[Sequence], labels: list[str], out: str | Path, frames: list[int] | None = None,
                 count: int = 5,
                 dpi: int = 90) -> Path:
    """Write a PNG grid: per sequence, a row of 3-D views and a row of cross-sections through the contact."""
    import matplotlib  # lazy: matplotlib is heavy and only the pictures need it

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out)
    total = min(s.frames for s in seqs)
    frames = frames or pick_frames(total, count)
    limits = _limits(seqs, frames)
    scale = 0.1 * float(np.linalg.norm(limits[1] - limits[0]))
    planes = [section_plane(s, frames) for s in seqs]
    window = _section_window(seqs, frames, planes)
    rows, cols = 2 * len(seqs), len(frames)
    fig = plt.figure(figsize=(2.8 * cols, 2.5 * rows), dpi=dpi)
    for r, (seq, label, plane) in enumerate(zip(seqs, labels, planes)):
        for c, f in enumerate(frames):
            ax = fig.add_subplot(rows, cols, 2 * r * cols + c + 1, projection="3d")
            _draw_frame(ax, seq, f, scale, limits, f"{label}  t={f}" if label else f"t={f}")
            ax = fig.add_subplot(rows, cols, (2 * r + 1) * cols + c + 1)
            _draw_section(ax, seq, f, plane, window)
    return save_png(fig, out)


def render_gif(seq: Sequence, out: str | Path, stride: int = 1, fps: int = 10) -> Path:
    """Write an animated GIF of ``seq`` (every ``stride``-th frame)."""
    import matplotlib  # lazy: matplotlib and pillow are heavy and only the pictures need them

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
        images.append(Image.fromarray(np.asarray(fig.canvas.buffer_rgba())[..., :3])
                      .convert("P", palette=Image.ADAPTIVE))
    plt.close(fig)
    with atomic_write(out) as fh:
        images[0].save(fh, format="GIF", save_all=True, append_images=images[1:], duration=int(1000 / fps), loop=0)
    return out


def render_file(path: str | Path, out: str | Path, count: int = 5, stride: int = 1) -> Path:
    """Render a sequence/rollout file to ``out`` (.png strip or .gif animation)."""
    out = Path(out)
    suffix = out.suffix.lower()
    if suffix not in (".png", ".gif"):
        raise InputError(f"--out must end in .png or .gif, got {out.name!r}")
    seq = load_sequence(path)
    if suffix == ".gif":
        return render_gif(seq, out, stride=stride)
    return render_strip([seq], [""], out, count=count)


def render_scene(scene, out: str | Path, seed: int = 2, frames: int = 60, count: int = 4) -> Path:
    """A picture of a scene before any simulation: the object at rest and the tool at its rest pose, then along
    one trajectory of the scene's family at poses where it has not yet reached the object (nothing is simulated,
    so deeper poses would show the undeformed object pierced). Colours: distance to the tool."""
    poses = sample_poses(scene, seed, frames)
    rest = np.asarray(scene.object.vertices)
    surface = rest[np.unique(scene.object.faces)]
    clear = [t for t, p in enumerate(poses) if scene.tool.sdf(surface, p).min() > 0]
    distance = [float(scene.tool.sdf(surface, poses[t]).min()) for t in clear]
    # the rest pose, the closest approach and evenly spread frames in between
    pick = sorted({clear[0], clear[int(np.argmin(distance))], *clear[:: max(1, len(clear) // max(1, count - 1))]})
    pick = [pick[i] for i in np.unique(np.linspace(0, len(pick) - 1, count).round().astype(int))]
    seq = Sequence(object_positions=np.repeat(rest[None], len(pick), axis=0),
                   object_faces=np.asarray(scene.object.faces), tool_positions=np.stack(
                       [scene.tool.world_vertices(poses[t]) for t in pick]), tool_faces=np.asarray(scene.tool.faces),
                   tool_poses=poses[pick], dt=scene.dt)
    return render_strip([seq], [f"{scene.name} ({scene.resolution})"], out, frames=list(range(len(pick))),
                        count=len(pick))
