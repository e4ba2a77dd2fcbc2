"""Scene definition: object tet mesh + rigid tool + material + trajectory family.

Each scene is one TOML file (``<name>.toml``), read with ``tomllib``: the built-in scenes next to this module,
a user's scenes (``colgnn scene new``) in the folders of ``COLGNN_SCENE_PATH`` (a path list, like ``PATH``).
:func:`build_scene` turns a config and a resolution into a :class:`Scene` with the object in world coordinates
(z up, metres). Mesh files named in a scene's TOML are looked up beside that TOML first, then in the package's
``assets/meshes``.
"""

from __future__ import annotations

import hashlib
import json
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from colgnn_core.errors import InputError
from colgnn_core.geometry.procedural import banana_mesh, mat_mesh, torus_mesh
from colgnn_core.geometry.tetmesh import TetMesh, load_msh, load_npz
from colgnn_core.geometry.tools import Tool, make_tool
from colgnn_core.geometry.transforms import axis_angle_quat, quat_multiply, quat_to_matrix, validate_pose

RESOLUTIONS = ("full", "ci")
SCENE_DIR = Path(__file__).resolve().parent
MESH_DIR = SCENE_DIR.parent / "assets" / "meshes"
BUILTIN_SCENES = ("cone_bunny", "knife_torus", "sphere_mat", "cylinder_banana")  # the paper's order
SCENE_PATH_ENV = "COLGNN_SCENE_PATH"


@dataclass
class Material:
    """Linear-elastic constants used by the stable Neo-Hookean model."""

    youngs_modulus: float  # Pa
    poisson_ratio: float  # -
    density: float  # kg/m^3


@dataclass
class Scene:
    """A tool–object scene at one resolution. Treat as read-only (it is cached).

    Attributes beyond the interface spec:
        pinned: [P] int64 object vertices glued in place (e.g. to a table); empty if none.
        target: [3] world point on the object's top surface that the trajectory family aims at.
        config: the parsed TOML (for reference / reports).
    """

    name: str
    resolution: str
    dt: float
    material: Material
    object: TetMesh
    tool: Tool
    tool_rest_pose: np.ndarray
    workspace_min: np.ndarray
    workspace_max: np.ndarray
    ground_height: float | None
    gravity: np.ndarray
    dhat: float
    friction: float
    family: dict
    model: dict
    pinned: np.ndarray = field(default_factory=lambda: np.zeros(0, dtype=np.int64))
    target: np.ndarray = field(default_factory=lambda: np.zeros(3))
    config: dict = field(default_factory=dict, repr=False)

    def physics_fingerprint(self, exact: bool = False) -> str:
        """sha256 hex over what the ground truth depends on besides the object mesh: dt, material, glued vertices,
        ground, gravity, dhat, friction, the tool's shape and mesh. A sequence records it, so that data simulated
        before a scene's physics changed (say, its mat glued down or its material stiffened) is not reused.

        Numbers enter at 12 significant digits and tool coordinates at 1 nm: dhat comes from the mesh's bounding-box
        diagonal, which another numpy build (a cluster worker, another machine) can compute one ulp apart, and that
        is no change of physics. ``exact``: the digest of the exact floats, which data written before session 30
        records."""
        return self._physics_digest(float if exact else (lambda x: float(f"{float(x):.12g}")))

    def accepts_physics(self, fingerprint: str | None) -> bool:
        """Was data recorded with ``fingerprint`` simulated with this scene's physics? Data written before session
        30 records the fingerprint of the exact floats (this machine's); both forms are accepted."""
        return fingerprint in (self.physics_fingerprint(), self.physics_fingerprint(exact=True))

    def _physics_digest(self, num) -> str:
        h = hashlib.sha256()
        h.update(json.dumps({"dt": num(self.dt), "E": num(self.material.youngs_modulus),
                             "nu": num(self.material.poisson_ratio), "rho": num(self.material.density),
                             "ground": None if self.ground_height is None else num(self.ground_height),
                             "gravity": [num(g) for g in np.asarray(self.gravity, float)],
                             "dhat": num(self.dhat), "friction": num(self.friction),
                             "tool": [self.tool.shape, {k: num(v) for k, v in self.tool.params.items()}]},
                            sort_keys=True).encode())
        h.update(np.ascontiguousarray(self.pinned, dtype=np.int64).tobytes())
        h.update(np.ascontiguousarray(np.round(self.tool.vertices, 9) + 0.0).tobytes())
        return h.hexdigest()

    def object_bbox(self) -> tuple[np.ndarray, np.ndarray]:
        """(min [3], max [3]) of the object's rest vertices, world (m)."""
        return self.object.bbox()

    def bbox_diagonal(self) -> float:
        """Length (m) of the object's rest bounding-box diagonal."""
        lo, hi = self.object_bbox()
        return float(np.linalg.norm(hi - lo))

    def check_pose(self, pose: np.ndarray) -> np.ndarray:
        """Validated copy of a tool pose [7]; InputError if malformed or outside the workspace."""
        p = validate_pose(pose)
        if np.any(p[:3] < self.workspace_min - 1e-9) or np.any(p[:3] > self.workspace_max + 1e-9):
            raise InputError(
                f"tool position {np.array2string(p[:3], precision=4)} is outside the {self.name} workspace "
                f"[{', '.join(f'{v:.4g}' for v in self.workspace_min)}] .. "
                f"[{', '.join(f'{v:.4g}' for v in self.workspace_max)}] m"
            )
        return p

    def check_poses(self, poses: np.ndarray) -> np.ndarray:
        """Validate poses [T,7]; InputError naming the first bad row."""
        poses = np.asarray(poses, dtype=np.float64)
        if poses.ndim != 2 or poses.shape[1] != 7:
            raise InputError(f"poses must be [T,7], got shape {poses.shape}")
        out = np.empty_like(poses)
        for i, p in enumerate(poses):
            try:
                out[i] = self.check_pose(p)
            except InputError as e:
                raise InputError(f"pose {i}: {e}") from None
        return out

    def to_json(self) -> dict[str, Any]:
        """The `colgnn scenes --json` record (docs/ARCHITECTURE.md, "Contracts") plus a few counts."""
        lo, hi = self.object_bbox()
        return {
            "name": self.name,
            "resolution": self.resolution,
            "dt": self.dt,
            "object_bbox_min": lo.tolist(),
            "object_bbox_max": hi.tolist(),
            "tool_shape": self.tool.shape,
            "tool_params": dict(self.tool.params),
            "tool_rest_pose": self.tool_rest_pose.tolist(),
            "workspace_min": self.workspace_min.tolist(),
            "workspace_max": self.workspace_max.tolist(),
            "object_vertices": int(self.object.num_vertices),
            "object_faces": int(len(self.object.faces)),
            "object_surface_vertices": int(len(self.object.surface_vertices)),
            "object_edges": int(len(self.object.edges)),
            "object_tets": int(len(self.object.tets)),
            "tool_vertices": int(len(self.tool.vertices)),
            "tool_faces": int(len(self.tool.faces)),
            "ground_height": self.ground_height,
            "pinned_vertices": int(len(self.pinned)),
            "dhat": self.dhat,
            "friction": self.friction,
            "material": {
                "youngs_modulus": self.material.youngs_modulus,
                "poisson_ratio": self.material.poisson_ratio,
                "density": self.material.density,
            },
        }


# --------------------------------------------------------------------------------------
# Building
# --------------------------------------------------------------------------------------
def scene_dirs() -> list[Path]:
    """The user's scene folders: the entries of ``COLGNN_SCENE_PATH`` (``os.pathsep``-separated), in order."""
    return [Path(p).expanduser() for p in os.environ.get(SCENE_PATH_ENV, "").split(os.pathsep) if p.strip()]


def custom_scene_files() -> dict[str, Path]:
    """name -> TOML file of every user scene on ``COLGNN_SCENE_PATH`` (the first folder that has a name wins; a
    built-in scene's name is not shadowed)."""
    out: dict[str, Path] = {}
    for folder in scene_dirs():
        if not folder.is_dir():
            continue
        for path in sorted(folder.glob("*.toml")):
            if path.stem not in out and path.stem not in BUILTIN_SCENES:
                out[path.stem] = path
    return out


def scene_file(name: str) -> Path | None:
    """The TOML file of scene ``name`` (built-in or on ``COLGNN_SCENE_PATH``); None if there is none."""
    if name in BUILTIN_SCENES:
        return SCENE_DIR / f"{name}.toml"
    return custom_scene_files().get(name)


def read_config(name: str) -> dict:
    """Parse scene ``name``'s TOML (see :func:`scene_file`); InputError naming the file if it is malformed."""
    path = scene_file(name)
    if path is None:
        raise InputError(f"unknown scene {name!r}")
    return read_config_file(path)


def read_config_file(path: Path) -> dict:
    """Parse a scene TOML; InputError naming the file and the problem if it is malformed."""
    try:
        with open(path, "rb") as f:
            return tomllib.load(f)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"{path}: not valid TOML ({exc})") from None


def _euler_xyz(deg: list[float]) -> np.ndarray:
    """Rotation matrix of extrinsic x, then y, then z rotations (degrees)."""
    q = np.array([0.0, 0.0, 0.0, 1.0])
    for axis, a in zip(np.eye(3), deg):
        if a:
            q = quat_multiply(axis_angle_quat(axis, np.deg2rad(a)), q)
    return quat_to_matrix(q)


def _mesh_file(name: str, base_dir: Path | None) -> Path:
    """A scene's mesh file: beside its TOML (``base_dir``) if there, else in the package's assets."""
    if base_dir is not None and (base_dir / name).is_file():
        return base_dir / name
    if (MESH_DIR / name).is_file():
        return MESH_DIR / name
    raise InputError(f"mesh file {name!r} not found in {base_dir or MESH_DIR}")


def build_object(spec: dict, base_dir: Path | None = None) -> TetMesh:
    """Object tet mesh in its own frame from an ``[object]`` table merged with its resolution table."""
    gen = spec["generator"]
    if gen == "msh":
        mesh = load_msh(_mesh_file(spec["file"], base_dir))
    elif gen == "npz":
        mesh = load_npz(_mesh_file(spec["file"], base_dir))
    elif gen == "torus":
        mesh = torus_mesh(spec["major_radius"], spec["minor_radius"], int(spec["around"]), int(spec["segments"]),
                          float(spec.get("growth", 1.25)))
    elif gen == "mat":
        mesh = mat_mesh(spec["size_x"], spec["size_y"], spec["thickness"], int(spec["nx"]), int(spec["ny"]),
                        int(spec["nz"]))
    elif gen == "banana":
        mesh = banana_mesh(
            spec["length"], spec["radius"], spec["bend"], spec["end_radius_ratio"], int(spec["around"]),
                int(spec["segments"]), float(spec.get("growth", 1.25))
        )
    else:
        raise ValueError(f"unknown object generator {gen!r}")
    rot = _euler_xyz(spec.get("rotate_deg", [0.0, 0.0, 0.0]))
    mesh = mesh.transformed(rotation=rot)
    if "size" in spec:  # scale so the largest bbox extent equals `size` metres
        lo, hi = mesh.bbox()
        mesh = mesh.transformed(scale=float(spec["size"]) / float((hi - lo).max()))
    return mesh


def place_on(mesh: TetMesh, center_xy: list[float], bottom_z: float) -> TetMesh:
    """Translate so the bbox centre is at ``center_xy`` and the lowest vertex at ``bottom_z``."""
    lo, hi = mesh.bbox()
    shift = np.array([center_xy[0] - 0.5 * (lo[0] + hi[0]), center_xy[1] - 0.5 * (lo[1] + hi[1]), bottom_z - lo[2]])
    return mesh.transformed(translation=shift)


def surface_height(mesh: TetMesh, xy: np.ndarray, near_xy: np.ndarray | None = None,
                   radius: float = np.inf) -> np.ndarray:
    """Height [Q] of the object's top surface above points xy [Q,2] (vertical ray cast); NaN off the object.

    ``near_xy``/``radius`` optionally restrict the faces to those with a vertex
    within ``radius`` (horizontally) of ``near_xy`` (all queries must lie there).
    """
    xy = np.atleast_2d(np.asarray(xy, dtype=np.float64))
    x = mesh.vertices[mesh.faces]  # [F,3,3]
    if near_xy is not None and np.isfinite(radius):
        longest = float(np.linalg.norm(x - np.roll(x, 1, axis=1), axis=2).max())
        d = np.linalg.norm(x[:, :, :2] - np.asarray(near_xy)[None, None, :2], axis=2).min(axis=1)
        x = x[d <= radius + longest]
    out = np.full(len(xy), np.nan)
    if len(x) == 0:
        return out
    a, b, c = x[:, 0], x[:, 1], x[:, 2]
    det = (b[:, 0] - a[:, 0]) * (c[:, 1] - a[:, 1]) - (c[:, 0] - a[:, 0]) * (b[:, 1] - a[:, 1])
    ok = np.abs(det) > 1e-16
    a, b, c, det = a[ok], b[ok], c[ok], det[ok]
    for start in range(0, len(xy), 64):  # chunks keep the [q,F] temporaries small
        q = xy[start : start + 64]
        dx = q[:, None, 0] - a[None, :, 0]
        dy = q[:, None, 1] - a[None, :, 1]
        u = (dx * (c[None, :, 1] - a[None, :, 1]) - dy * (c[None, :, 0] - a[None, :, 0])) / det
        v = (dy * (b[None, :, 0] - a[None, :, 0]) - dx * (b[None, :, 1] - a[None, :, 1])) / det
        inside = (u >= 0) & (v >= 0) & (u + v <= 1)
        z = a[None, :, 2] + u * (b[None, :, 2] - a[None, :, 2]) + v * (c[None, :, 2] - a[None, :, 2])
        z = np.where(inside, z, -np.inf)
        h = z.max(axis=1)
        out[start : start + 64] = np.where(np.isfinite(h), h, np.nan)
    return out


def tool_contact_height(mesh: TetMesh, tool: Tool, xy: np.ndarray, quat: np.ndarray, step: float = 1e-3) -> float:
    """Height (m) of the tool origin at which ``tool``, lowered vertically at ``xy`` [2] with
    orientation ``quat`` [4], first touches the rest surface of ``mesh``; NaN if it never does.

    Two vertex-face bounds, the larger wins: (a) object surface vertices against
    the tool SDF: scan downward in ``step`` increments (64 candidate heights per
    vectorised SDF call), then refine (4 rounds of 64 heights); (b) tool mesh vertices
    dropped onto the object's faces (vertical ray cast), which catches a sharp
    tip or edge that would slip between object vertices. Trajectory depths are
    measured from this height, so they mean the same for a sharp cone, a knife
    edge and a sphere, tilted or not.
    """
    xy = np.asarray(xy, dtype=np.float64)
    quat = np.asarray(quat, dtype=np.float64)
    sv = mesh.vertices[mesh.surface_vertices]
    rot = quat_to_matrix(quat)
    tv_rel = tool.vertices @ rot.T
    tz = tv_rel[:, 2]
    # Only vertices under the tool's footprint (its xy box, padded for the inscribed mesh) can touch it.
    pad = 0.05 * tool.bounding_radius() + 1e-4
    rel = sv[:, :2] - xy[None, :2]
    inside = np.all((rel >= tv_rel[:, :2].min(0) - pad) & (rel <= tv_rel[:, :2].max(0) + pad), axis=1)
    near = sv[inside]
    above = float("nan")
    if len(near):
        above = _vertex_contact_height(tool, near, xy, rot, tz, step)
    # (b) tool vertices (at origin height 0) dropped onto the faces below them.
    tv = tv_rel + np.array([xy[0], xy[1], 0.0])
    h = surface_height(mesh, tv[:, :2], near_xy=xy, radius=tool.bounding_radius())
    ok = np.isfinite(h)
    if ok.any():
        above = float(np.nanmax([above, float((h[ok] - tv[ok, 2]).max())]))
    return above


def _vertex_contact_height(tool: Tool, near: np.ndarray, xy: np.ndarray, rot: np.ndarray, tz: np.ndarray,
                           step: float) -> float:
    """Part (a) of :func:`tool_contact_height`: first contact of the tool SDF with points ``near`` [K,3]."""
    base = (near - np.array([xy[0], xy[1], 0.0])) @ rot  # local coords at origin height 0
    down = rot[2]  # local coordinates of world +z: raising the tool by z shifts locals by -z*down

    def touching(zs: np.ndarray) -> np.ndarray:
        local = base[None, :, :] - zs[:, None, None] * down[None, None, :]
        return tool.sdf_local(local.reshape(-1, 3)).reshape(len(zs), -1).min(axis=1) <= 0.0

    hi = float(near[:, 2].max() - tz.min() + step)  # tool entirely above every nearby vertex
    lo = float(near[:, 2].min() - tz.max() - step)  # tool entirely below
    top = hi
    while top > lo:
        zs = top - step * np.arange(1, 65)
        hit = touching(zs)
        if hit.any():
            k = int(np.argmax(hit))
            below, above = float(zs[k]), float(zs[k - 1]) if k > 0 else top
            break
        top = float(zs[-1])
    else:
        return float("nan")
    for _ in range(4):  # each round splits [below, above] into 65: 1 mm / 65^4 < 1e-10 m
        zs = np.linspace(above, below, 66)[1:-1]
        hit = touching(zs)
        k = int(np.argmax(hit)) if hit.any() else len(zs)
        above, below = (float(zs[k - 1]) if k > 0 else above), (float(zs[k]) if k < len(zs) else below)
    return above


def at_resolution(table: dict, resolution: str) -> dict:
    """A TOML table with its ``[table.<resolution>]`` sub-table merged in (the other resolutions dropped)."""
    out = {k: v for k, v in table.items() if k not in RESOLUTIONS}
    out.update(table.get(resolution, {}))
    return out


def build_scene(name: str, resolution: str, cfg: dict, base_dir: Path | None = None) -> Scene:
    """Build a :class:`Scene` from a parsed config at ``resolution``; mesh files are looked up in ``base_dir``
    (the TOML's folder) first."""
    obj_cfg = at_resolution(cfg["object"], resolution)
    mesh = build_object(obj_cfg, base_dir)
    lo, hi = mesh.bbox()
    diag = float(np.linalg.norm(hi - lo))
    dhat = float(cfg.get("dhat", cfg.get("dhat_rel", 1e-3) * diag))
    ground = cfg.get("ground", {})
    ground_height = float(ground["height"]) if "height" in ground else None
    bottom = float(obj_cfg.get("bottom_z", 0.0))
    if ground_height is not None:
        # Start clear of the ground by a few dhat: frame 0 is contact-free.
        bottom = ground_height + float(ground.get("gap_dhat", 3.0)) * dhat
    mesh = place_on(mesh, obj_cfg.get("center_xy", [0.0, 0.0]), bottom)
    mesh.validate()

    pinned = np.zeros(0, dtype=np.int64)
    if "pin_height" in obj_cfg:
        z = mesh.vertices[:, 2]
        pinned = np.flatnonzero(z <= z.min() + float(obj_cfg["pin_height"])).astype(np.int64)

    tool_cfg = dict(cfg["tool"])
    shape = tool_cfg.pop("shape")
    q_rest = np.asarray(tool_cfg.pop("rest_orientation", [0.0, 0.0, 0.0, 1.0]), dtype=np.float64)
    clearance = float(tool_cfg.pop("rest_clearance"))
    tool_res = tool_cfg.pop(resolution, {})
    tool_cfg.update(tool_res)
    for k in ("full", "ci"):
        tool_cfg.pop(k, None)
    tool = make_tool(shape, tool_cfg, resolution)

    fam = at_resolution(cfg["family"], resolution)  # a [family.full] / [family.ci] sub-table overrides keys
    txy = np.asarray(fam["target_xy"], dtype=np.float64)
    h = surface_height(mesh, txy[None])[0]
    if not np.isfinite(h):
        raise ValueError(f"{name}: family.target_xy {txy.tolist()} is not above the object")
    target = np.array([txy[0], txy[1], h])
    q_rest = q_rest / np.linalg.norm(q_rest)
    rest = np.concatenate([[txy[0], txy[1], tool_contact_height(mesh, tool, txy, q_rest) + clearance], q_rest])

    ws = cfg["workspace"]
    mat = cfg["material"]
    scene = Scene(
        name=name,
        resolution=resolution,
        dt=float(cfg.get("dt", 0.04)),
        material=Material(float(mat["youngs_modulus"]), float(mat["poisson_ratio"]), float(mat["density"])),
        object=mesh,
        tool=tool,
        tool_rest_pose=rest,
        workspace_min=np.asarray(ws["min"], dtype=np.float64),
        workspace_max=np.asarray(ws["max"], dtype=np.float64),
        ground_height=ground_height,
        gravity=np.asarray(cfg.get("gravity", [0.0, 0.0, -9.81]), dtype=np.float64),
        dhat=dhat,
        friction=float(cfg.get("friction", 0.0)),
        family=fam,
        model=at_resolution(cfg.get("model", {}), resolution),
        pinned=pinned,
        target=target,
        config=cfg,
    )
    scene.check_pose(rest)
    return scene
