"""A user's own scene from a mesh file and a tool shape (``colgnn scene new``).

:func:`create_scene` imports the surface (repaired, checked, z up, longest side ``size`` m:
:mod:`colgnn_core.geometry.mesh_import`), tetrahedralizes it with fTetWild at both resolutions
(:func:`colgnn_core.geometry.tetrahedralize.tetrahedralize_for`, tet quality checked), derives every other value of
a scene from the geometry (:func:`derive_config`) and writes, atomically, into ``out_dir``::

    NAME.toml          the scene (every derived value is a plain TOML value with a comment: edit it to override)
    NAME-ci.npz        the ci tet mesh (~300 surface vertices)
    NAME-full.npz      the full tet mesh (~3000 surface vertices)
    NAME-surface.obj   the repaired surface in metres, z up (what was tetrahedralized)

The TOML is written last, so a scene appears on ``COLGNN_SCENE_PATH`` only once it is complete. What is derived
and how (L: the longest side, H: the height, T: the smallest side, e: a resolution's mean surface edge length):

* tool: sphere radius 0.15 L; cylinder radius 0.08 L, length 0.5 L, axis horizontal; cone radius 0.09 L, height
  0.35 L, tip down; blade length 0.45 L, height 0.18 L, thickness 0.012 L, bevel 0.045 L, edge down
  (``--tool shape:key=value`` overrides any of them); the tool's mesh, which the IPC ground truth presses with, fine
  enough that its facets dip at most dhat inside the analytic shape that the model uses (``segments``; the summary
  also gives how far its faces turn from the shape's normal);
* rest pose: the tool above ``family.target_xy`` (the upward-facing surface point nearest the centroid of the
  upward-facing area), ``rest_clearance`` 0.08 L above first contact;
* support: with ``--ground`` a static ground plane under the object (friction 0.3); otherwise the bottom band of
  height max(0.03 H, 0.6 e_ci) is glued in place (``pin_height``, as cone_bunny), and an object that stands on
  separate feet is held by them up to where they join (:func:`feet_height`);
* dhat = min(1e-3 x bbox diagonal, 0.05 e_full); the network's world radius r_W = 2 e per resolution
  (``[model.ci]``, ``[model.full]``);
* workspace: the object's bounding box in xy, widened by the tool's reach and 0.1 L; in z from the top of the
  support band (plus the tool's depth below its origin) to above the object by the tool's size, the clearance and
  0.25 L;
* trajectory family: presses, drags and plunges anywhere over the tool-facing surface (``region = "surface"``),
  depth 4-12% of T, speed 1-2% of L per step, drags of 5-20% of L, tilts by tool (sphere none, cylinder 8 deg,
  cone 20 deg, blade 10 deg);
* material: the ``--material`` preset;
* network (:func:`derive_model`): glued, a quasi-static 16/2/1 network with a coarse level (about 16 surface
  vertices a cluster) on top of a physics prior (a sharp cone: ``tip_prior``; a sphere, cylinder or rounded cone:
  ``contact_prior``, at full resolution solved on the ``ci`` mesh); on the ground, the dynamic 32/5/1 network.
"""

from __future__ import annotations

import io
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from colgnn_core.errors import InputError
from colgnn_core.geometry.mesh_import import SurfaceImport, import_surface, obj_text
from colgnn_core.geometry.tetmesh import TetMesh
from colgnn_core.geometry.tetrahedralize import tetrahedralize_for
from colgnn_core.geometry.tools import TOOL_SHAPES, facet_depth, facet_tilt, make_tool, mesh_density
from colgnn_core.geometry.transforms import quat_to_matrix
from colgnn_core.io import atomic_write, ensure_writable_dir
from colgnn_core.scenes.scene import (BUILTIN_SCENES, RESOLUTIONS, Scene, build_scene, place_on, read_config_file,
                                      surface_height, tool_contact_height)
from colgnn_core.scenes.trajectories import sample_poses, split_seeds

NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_-]{0,63}$")

#: name -> (Young's modulus Pa, Poisson ratio, density kg/m^3)
MATERIALS = {
    "rubber": (1.0e5, 0.4, 1000.0),   # the built-in scenes' soft rubber
    "gel": (3.0e4, 0.45, 1050.0),     # soft, nearly incompressible (silicone / ballistic gel, tissue phantoms)
    "foam": (5.0e4, 0.25, 150.0),     # light and compressible
}

#: shape -> parameter -> factor of the longest side L
TOOL_SIZES = {
    "sphere": {"radius": 0.15},
    "cylinder": {"radius": 0.08, "height": 0.5},
    "cone": {"radius": 0.09, "height": 0.35},
    "blade": {"length": 0.45, "height": 0.18, "thickness": 0.012, "bevel": 0.045},
}
TOOL_OPTIONAL = {"cone": ("tip_radius",)}
TOOL_ORIENTATION = {  # rest orientation (xyzw): the cylinder lies across y, the others point down
    "sphere": [0.0, 0.0, 0.0, 1.0], "cone": [0.0, 0.0, 0.0, 1.0], "blade": [0.0, 0.0, 0.0, 1.0],
    "cylinder": [-0.7071067811865476, 0.0, 0.0, 0.7071067811865476],
}
TOOL_MOTION = {  # kind, tilt range (deg), yaw range (deg)
    "sphere": ("press", [0.0, 0.0], [0.0, 0.0]),
    "cylinder": ("press", [0.0, 8.0], [-25.0, 25.0]),
    "cone": ("stab", [0.0, 20.0], [0.0, 0.0]),
    "blade": ("cut", [0.0, 10.0], [-25.0, 25.0]),
}
FACET_DEPTH = 1.0  # x dhat: how far the tool mesh may dip inside its analytic shape (geometry.tools.mesh_density)
SMOOTH_TOOLS = ("sphere", "cylinder", "cone")  # tools whose contact prior is sim.contact_prior (a rounded cone)
FAMILY_CHECK_SEEDS = 4  # family trajectories checked against the workspace before anything is written


@dataclass
class ToolSpec:
    shape: str
    overrides: dict[str, float] = field(default_factory=dict)


def parse_tool(text: str) -> ToolSpec:
    """``shape[:key=value,...]`` (e.g. ``sphere:radius=0.02``); InputError naming the problem."""
    shape, _, rest = str(text).partition(":")
    shape = shape.strip()
    if shape not in TOOL_SHAPES:
        raise InputError(f"--tool: unknown shape {shape!r}; valid: {', '.join(TOOL_SHAPES)}")
    allowed = (*TOOL_SIZES[shape], *TOOL_OPTIONAL.get(shape, ()))
    overrides: dict[str, float] = {}
    for item in filter(None, (s.strip() for s in rest.split(","))):
        key, eq, value = item.partition("=")
        if not eq or key.strip() not in allowed:
            raise InputError(f"--tool {shape}: expected key=value with key in {', '.join(allowed)}, got {item!r}")
        try:
            v = float(value)
        except ValueError:
            raise InputError(f"--tool {shape}: {key.strip()} must be a number in metres, got {value!r}") from None
        if not (np.isfinite(v) and (v > 0 or (key.strip() == "tip_radius" and v >= 0))):
            raise InputError(f"--tool {shape}: {key.strip()} must be positive, got {value}")
        overrides[key.strip()] = v
    return ToolSpec(shape, overrides)


def parse_material(text: str) -> tuple[str, tuple[float, float, float]]:
    """A preset name or ``E,nu,rho``: (label, (E Pa, nu, rho kg/m^3)); InputError naming the problem."""
    text = str(text).strip()
    if text in MATERIALS:
        return text, MATERIALS[text]
    parts = text.split(",")
    try:
        e, nu, rho = (float(p) for p in parts)
    except ValueError:
        raise InputError(f"--material: expected one of {', '.join(MATERIALS)} or E,nu,rho (Pa, -, kg/m^3), "
                         f"got {text!r}") from None
    if not (e > 0 and 0.0 <= nu < 0.5 and rho > 0):
        raise InputError(f"--material: need E > 0, 0 <= nu < 0.5 and rho > 0, got {text!r}")
    return "custom", (e, nu, rho)


def check_name(name: str) -> str:
    if not NAME_RE.match(str(name)):
        raise InputError(f"scene name {name!r}: use a letter, then letters, digits, '_' or '-' (at most 64)")
    if name in BUILTIN_SCENES:
        raise InputError(f"scene name {name!r} is a built-in scene; choose another")
    return name


def _mean_edge(mesh: TetMesh) -> float:
    x = mesh.vertices[mesh.edges]
    return float(np.linalg.norm(x[:, 1] - x[:, 0], axis=1).mean())


def _target_xy(mesh: TetMesh) -> np.ndarray:
    """The upward-facing surface point nearest the area-weighted centroid of the upward-facing faces (xy)."""
    x = mesh.vertices[mesh.faces]
    n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    area = 0.5 * np.linalg.norm(n, axis=1)
    up = n[:, 2] > 0.5 * np.linalg.norm(n, axis=1)
    centre = x.mean(axis=1)
    if not up.any():
        up = n[:, 2] > 0
    c = (centre[up] * area[up, None]).sum(0) / area[up].sum()
    # Of the upward faces that are the top surface at their centre (visible from above), the nearest to c.
    cand = centre[up][np.argsort(np.linalg.norm(centre[up, :2] - c[:2], axis=1))[:64]]
    top = surface_height(mesh, cand[:, :2])
    visible = np.isclose(top, cand[:, 2], atol=1e-9 + 1e-6 * float(np.ptp(mesh.vertices)))
    pick = cand[int(np.argmax(visible))] if visible.any() else cand[0]
    return np.round(pick[:2], 6)


FEET_JOINED = 0.9   # share of the bottom band's vertices in one connected piece: the object's feet have joined
FEET_LIMIT = 0.5    # of the height: feet that join only higher up are not held (the plain band is glued)


def feet_height(mesh: TetMesh, band: float) -> float:
    """Height above the bottom (m) from which an object's feet are one piece: the lowest level z such that the
    surface below z holds at least FEET_JOINED of the vertices within ``band`` m of the bottom in one connected
    piece (of the surface edges with both ends below z). ``band`` when they already are (a pebble, a lying banana);
    ``band`` too when they join only above FEET_LIMIT of the height.

    The edges are added in order of their upper end's height to a union-find that counts band vertices per piece,
    so every level is tried exactly (O(E log E))."""
    z = mesh.vertices[:, 2] - mesh.vertices[:, 2].min()
    in_band = z <= band
    need = FEET_JOINED * int(in_band.sum())
    parent = np.arange(len(z))
    count = in_band.astype(np.int64)

    def root(i: int) -> int:
        while parent[i] != i:
            parent[i] = parent[parent[i]]
            i = parent[i]
        return i

    if count.max() >= need:
        return band
    edges = mesh.edges
    top = z[edges].max(axis=1)
    for k in np.argsort(top, kind="stable"):
        if top[k] > FEET_LIMIT * float(z.max()):
            break
        a, b = root(int(edges[k, 0])), root(int(edges[k, 1]))
        if a != b:
            parent[b] = a
            count[a] += count[b]
            if count[a] >= need:
                return max(band, float(top[k]))
    return band


def coarse_clusters(surface_vertices: int) -> int:
    """Clusters of the coarse level for a surface graph of ``surface_vertices`` nodes: about 12-16 nodes a cluster
    (the glued banana and mat: 128 for 2-6k surface vertices), at least 8 and at most 128."""
    return int(np.clip(round(surface_vertices / 16), 8, 128))


def derive_model(ground: bool, meshes: dict[str, TetMesh], edge: dict[str, float], tool_shape: str = "sphere",
                 tool_params: dict[str, float] | None = None) -> dict:
    """The network a fit trains (the TOML's ``[model]``; ``edge``: mean surface edge length per resolution, m).

    A glued object (no ``--ground``) comes back to the same shape for the same tool pose, whatever the path (the
    glued mat and banana, ``docs/FIDELITY.md``), so it gets the recipe that beats both trivial baselines there: a
    quasi-static 16/2/1 network (the shape as a function of the tool's pose, on the settled rest) with a coarse
    level of 4 steps that carries the contact across the object. Its output is added to a physics prior where one
    was measured to help: a sharp cone's ``tip_prior`` (the bunny), and a smooth tool's ``contact_prior`` (the cow
    with a sphere). At full resolution that prior is solved on the ``ci`` mesh (``prior_mesh``), because on the full
    mesh its first contact needs hundreds of back-substitutions. An object loose on the ground slides, so its shape
    depends on the path: it keeps the dynamic 32/5/1 network (not measured on a user's scene yet)."""
    common = {"surface_only": True, "contact_tests": ["vertex_face", "edge_edge"]}
    per_res = {res: {"world_radius": round(2.0 * edge[res], 6)} for res in ("ci", "full")}
    if ground:
        return {"latent": 32, "message_passing_steps": 5, "mlp_layers": 1, **common, **per_res}
    for res in per_res:
        per_res[res]["coarse_nodes"] = coarse_clusters(len(meshes[res].surface_vertices))
    prior = {}
    if tool_shape == "cone" and float((tool_params or {}).get("tip_radius", 0.0)) == 0.0:
        prior = {"tip_prior": True}
    elif tool_shape in SMOOTH_TOOLS:
        per_res["ci"]["contact_prior"] = True
        # At full resolution the exact prior's first contact costs seconds (hundreds of back-substitutions); solved
        # on the ci mesh and carried onto the full graph's nodes (sim.coarse_prior) it costs milliseconds (cow: 10 ms).
        per_res["full"].update(contact_prior=True, prior_mesh="ci")
    return {"latent": 16, "message_passing_steps": 2, "mlp_layers": 1, "order": 0, "quasi_static": True,
            "coarse_steps": 4, **prior, **common, **per_res}


def derive_config(name: str, surface: SurfaceImport, meshes: dict[str, TetMesh], tool: ToolSpec,
                  material: tuple[str, tuple[float, float, float]], ground: bool) -> dict:
    """The scene config (the TOML's content) derived from the geometry; see the module docstring."""
    full = place_on(meshes["full"], [0.0, 0.0], 0.0)
    ci = place_on(meshes["ci"], [0.0, 0.0], 0.0)
    lo, hi = full.bbox()
    ext = hi - lo
    L, H, T = float(ext.max()), float(ext[2]), float(ext.min())
    e = {res: _mean_edge(m) for res, m in (("ci", ci), ("full", full))}
    diag = float(np.linalg.norm(ext))
    dhat = min(1e-3 * diag, 0.05 * e["full"])
    params = {k: round(f * L, 6) for k, f in TOOL_SIZES[tool.shape].items()}
    params.update(tool.overrides)
    if tool.shape == "blade" and params["bevel"] >= params["height"]:
        raise InputError("--tool blade: bevel must be smaller than height")
    # The ground truth presses with the tool's mesh: its facets within FACET_DEPTH dhat of the analytic shape that
    # the model and the correction use (one density for both resolutions; the blade's flat sides need none). Their
    # normals still turn a few degrees (the cow's sphere: 4.6), which can lean a press on a ridge the wrong way; a
    # finer mesh cost more than it gained in a 30-minute fit (docs/OWN_OBJECT.md, session 58), so the summary
    # reports the turn and the user may raise ``segments``.
    if tool.shape != "blade":
        params["segments"] = mesh_density(tool.shape, params, FACET_DEPTH * dhat)
    q_rest = TOOL_ORIENTATION[tool.shape]
    kind, tilt, yaw = TOOL_MOTION[tool.shape]
    probe = make_tool(tool.shape, params, "ci")
    reach = probe.bounding_radius()
    below = max(0.0, -float((probe.vertices @ quat_to_matrix(np.asarray(q_rest)).T)[:, 2].min()))
    clearance = round(0.08 * L, 6)

    support: dict = {}
    if ground:
        support_top = 3.0 * dhat  # the object starts 3 dhat above the ground (build_scene's gap_dhat)
        ground_cfg = {"height": 0.0, "gap_dhat": 3.0}
    else:
        pin = max(0.03 * H, 0.6 * e["ci"])
        for mesh in (ci, full):  # at least three vertices glued at both resolutions
            z = np.sort(mesh.vertices[:, 2])
            pin = max(pin, float(z[min(2, len(z) - 1)] - z[0]) + 1e-6)
        # An object on separate feet (a cow on its legs) is held by them up to where they join, as on a stand:
        # free, its body tips sideways and swings under a press on top (the stiff cow: 5-6 mm sideways for a 4 mm
        # press, the side set by which flank of the back the tool meets, swinging past rest after the tool left),
        # which a model of the shape as a function of the tool's pose cannot learn (docs/OWN_OBJECT.md).
        feet = max(feet_height(mesh, pin) for mesh in (ci, full))
        if feet > pin:
            pin = feet + 1e-6  # the vertices at the joining level are glued too
        support = {"pin_height": round(pin, 6)}
        support_top, ground_cfg = pin, None
    top = float(hi[2]) + (support_top if ground else 0.0)
    ws_min = [round(float(lo[0]) - reach - 0.1 * L, 6), round(float(lo[1]) - reach - 0.1 * L, 6),
              round(support_top + below, 6)]
    ws_max = [round(float(hi[0]) + reach + 0.1 * L, 6), round(float(hi[1]) + reach + 0.1 * L, 6),
              round(top + reach + clearance + 0.25 * L, 6)]
    txy = _target_xy(ci)
    xy = np.sort(ext[:2])
    fam = {
        "kind": kind,
        "target_xy": [float(v) for v in txy],
        "target_jitter": round(0.1 * float(xy[0]), 6),
        "depth": [round(0.04 * T, 6), round(0.12 * T, 6)],
        "speed": [round(0.01 * L, 6), round(0.02 * L, 6)],
        "retract_speed_factor": [1.0, 1.25],
        "drift": [0.0, round(0.03 * L, 6)],
        "tilt_deg": tilt,
        "yaw_deg": yaw,
        "hold": [0, 3],
        "region": "surface",
        "region_margin": 0.0,
        "stroke_weights": [0.45, 0.35, 0.2],
        "drag": [round(0.05 * L, 6), round(0.2 * L, 6)],
        "settle": [2, 8],
    }
    if tool.shape == "cone":
        fam["retract_along_tool_axis"] = True
    if tool.shape == "blade":
        fam["drift_along_tool_x"] = True
    e_lab, nu, rho = material[1]
    cfg = {
        "name": name,
        "dt": 0.04,
        "dhat": float(f"{dhat:.4g}"),
        "friction": 0.3 if ground else 0.0,
        "gravity": [0.0, 0.0, -9.81],
        "object": {"generator": "npz", "source": surface.source, "up": surface.up,
                   "size": float(f"{L:.6g}"), "center_xy": [0.0, 0.0], "bottom_z": 0.0, **support,
                   "ci": {"file": f"{name}-ci.npz"}, "full": {"file": f"{name}-full.npz"}},
        "material": {"preset": material[0], "youngs_modulus": e_lab, "poisson_ratio": nu, "density": rho},
        "tool": {"shape": tool.shape, **params, "rest_orientation": q_rest, "rest_clearance": clearance},
        "workspace": {"min": ws_min, "max": ws_max},
        "family": fam,
        "model": derive_model(ground, {"ci": ci, "full": full}, e, tool.shape, params),
    }
    if ground_cfg is not None:
        cfg["ground"] = ground_cfg
    return cfg


# ------------------------------------------------------------------------------------------------- TOML
COMMENTS = {
    "dt": "s per frame (25 fps)",
    "dhat": "m, IPC barrier distance: min(1e-3 x bbox diagonal, 0.05 x full mean edge length)",
    "friction": "tool and ground friction (0 when the bottom is glued)",
    "object.source": "the user's mesh file (repaired copy: <name>-surface.obj)",
    "object.up": "the file's axis that became +z",
    "object.size": "m, longest side (--size)",
    "object.pin_height": "m: vertices this close to the bottom are glued in place (max(0.03 H, 0.6 x ci edge), "
                         "or up to where the object's feet join)",
    "material.preset": "--material",
    "tool.segments": "tool mesh density for the IPC ground truth (icosphere subdivisions, or segments around): "
                     "its facets within dhat of the analytic shape",
    "tool.rest_clearance": "m between the tool and the object at frame 0 (0.08 L)",
    "workspace.min": "valid tool-origin positions, m: the object's bbox widened by the tool's reach",
    "family.target_xy": "first stroke aims here: the top surface point nearest the upward-facing area's centroid",
    "family.depth": "m below the surface point hit: 4-12% of the smallest side",
    "family.speed": "m per step: 1-2% of the longest side",
    "family.region": "strokes anywhere over the tool-facing surface",
    "model.quasi_static": "glued: the shape is a function of the tool's pose (remove order/quasi_static/coarse_*, "
                          "set 32/5/1, for the dynamic network)",
    "model.ci.world_radius": "m, r_W = 2 x the ci mean surface edge length",
    "model.ci.coarse_nodes": "clusters of the coarse level: about 16 surface vertices each (8-128)",
    "model.ci.contact_prior": "the output is added to linear elasticity pushed out of the tool (sim/contact_prior.py)",
    "model.tip_prior": "the output is added to linear elasticity with the tip carrying a surface point "
                       "(sim/tip_prior.py)",
    "model.full.world_radius": "m, r_W = 2 x the full mean surface edge length",
    "model.full.contact_prior": "the same prior, solved on the ci mesh (prior_mesh) and carried onto the full mesh",
    "model.full.prior_mesh": "ci: the full mesh's exact prior costs seconds at a first contact (sim/coarse_prior.py)",
}


def _value(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_value(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def toml_text(cfg: dict, header: str = "") -> str:
    """The scene config as TOML with a comment on each derived value (tables, then sub-tables)."""
    out = io.StringIO()
    out.write(header)

    def table(prefix: str, d: dict) -> None:
        subs = []
        for k, v in d.items():
            if isinstance(v, dict):
                subs.append((k, v))
                continue
            line = f"{k} = {_value(v)}"
            note = COMMENTS.get(f"{prefix}{k}")
            out.write(f"{line:<40} # {note}\n" if note else line + "\n")
        for k, v in subs:
            out.write(f"\n[{prefix}{k}]\n")
            table(f"{prefix}{k}.", v)

    table("", cfg)
    return out.getvalue()


# ------------------------------------------------------------------------------------------------- create
@dataclass
class NewScene:
    """What :func:`create_scene` wrote and measured."""

    name: str
    toml: Path
    files: list[Path]
    config: dict
    surface: dict
    meshes: dict[str, dict]
    scene: Scene  # the new scene at ci, read back from the written files
    checks: list[str] = field(default_factory=list)  # what the caller's ``check`` reported (summary lines)


def create_scene(name: str, object_path: str | Path, size: float, tool: str | ToolSpec = "sphere",
                 material: str = "rubber", ground: bool = False, out_dir: str | Path = "scenes",
                 up: str | None = None, force: bool = False, threads: int = 1,
                 check: Callable[[Scene], str] | None = None) -> NewScene:
    """Make scene ``name`` from a mesh file (see the module docstring); InputError naming any problem, before
    anything is written.

    ``check``: called with the derived scene at ci before anything is written (e.g. the settling check of
    :mod:`colgnn_core.sim.settle`, which this layer cannot import); it raises InputError to refuse the scene, or
    returns a line for the summary.
    """
    name = check_name(name)
    spec = parse_tool(tool) if isinstance(tool, str) else tool
    mat = parse_material(material)
    out = ensure_writable_dir(out_dir)
    toml_path = out / f"{name}.toml"
    if toml_path.exists() and not force:
        raise InputError(f"{toml_path} exists; pass --force to replace the scene")
    surface = import_surface(object_path, size, up)
    meshes: dict[str, TetMesh] = {}
    info: dict[str, dict] = {}
    for res in ("ci", "full"):
        try:
            mesh, how = tetrahedralize_for(surface.vertices, surface.faces, surface.area(), res, num_threads=threads)
        except ValueError as exc:
            raise InputError(f"{Path(object_path).name}: {exc}") from None
        meshes[res] = mesh
        info[res] = {"vertices": mesh.num_vertices, "surface_vertices": int(len(mesh.surface_vertices)),
                     "tets": int(len(mesh.tets)), "mean_edge": _mean_edge(mesh), **how}
    cfg = derive_config(name, surface, meshes, spec, mat, ground)
    checks = _check(name, cfg, meshes, check)

    files = {f"{name}-ci.npz": meshes["ci"], f"{name}-full.npz": meshes["full"]}
    for fname, mesh in files.items():
        with atomic_write(out / fname, "wb") as fh:
            np.savez_compressed(fh, vertices=mesh.vertices, tets=mesh.tets.astype(np.int32))
    with atomic_write(out / f"{name}-surface.obj", "w") as fh:
        fh.write(f"# {name}: {surface.source} repaired, z up, longest side {size:g} m (colgnn scene new)\n")
        fh.write(obj_text(surface.vertices, surface.faces))
    header = (f"# {name}: made by `colgnn scene new` from {surface.source}. Every value below was derived from the "
              "geometry\n# (docs/OWN_OBJECT.md); edit any of them to override, then run `colgnn fit` again.\n")
    with atomic_write(toml_path, "w") as fh:  # last: the scene exists only once its files do
        fh.write(toml_text(cfg, header))
    surf_info = {"source": surface.source, "up": surface.up, "scale": surface.scale, "repairs": surface.repairs,
                 "vertices": int(len(surface.vertices)), "faces": int(len(surface.faces)),
                 "extents": surface.extents.tolist()}
    scene = build_scene(name, "ci", read_config_file(toml_path), base_dir=out)
    return NewScene(name, toml_path, [out / f for f in (*files, f"{name}-surface.obj", f"{name}.toml")], cfg,
                    surf_info, info, scene, checks)


def _check(name: str, cfg: dict, meshes: dict[str, TetMesh], check: Callable[[Scene], str] | None = None
           ) -> list[str]:
    """Build the scene at both resolutions from the derived config (meshes in memory) and check that its family's
    trajectories stay in the workspace, then run the caller's ``check`` on the ci scene: a derivation that does not
    work is refused before anything is written. Returns the ``check``'s summary lines."""
    import tempfile

    lines: list[str] = []
    with tempfile.TemporaryDirectory(prefix="colgnn-scene-") as tmp:
        for res in RESOLUTIONS:
            meshes[res].save_npz(Path(tmp) / cfg["object"][res]["file"])
        for res in RESOLUTIONS:
            try:
                scene = build_scene(name, res, cfg, base_dir=Path(tmp))
                for seed in split_seeds("train", FAMILY_CHECK_SEEDS):
                    scene.check_poses(sample_poses(scene, seed, 60, clip=False))
            except (ValueError, InputError) as exc:
                raise InputError(f"the derived {res} scene does not work ({exc}); edit the TOML by hand") from None
            if not np.isfinite(tool_contact_height(scene.object, scene.tool, np.asarray(cfg["family"]["target_xy"]),
                                                   scene.tool_rest_pose[3:])):
                raise InputError(f"the derived {res} scene's tool misses the object at its target")
            if check is not None and res == "ci":
                lines.append(check(scene))
    return lines


def format_summary(new: NewScene) -> str:
    """A readable summary of a new scene: files, repairs, meshes and the derived values."""
    c, s = new.config, new.surface
    lines = [f"scene {new.name}: {new.toml}",
             f"  object   {s['source']} ({s['vertices']} vertices, {s['faces']} faces after repair), up axis "
             f"{s['up']}, scaled x{s['scale']:.4g} -> " + " x ".join(f"{e:.4f}" for e in s["extents"]) + " m",
             "  repairs  " + ("; ".join(s["repairs"]) if s["repairs"] else "none needed"),
             "",
             f"  {'mesh':<6} {'vertices':>8} {'surface':>8} {'tets':>7} {'edge mm':>8} {'min q':>6} {'mean q':>6} "
             f"{'envelope':>8}"]
    for res, m in new.meshes.items():
        lines.append(f"  {res:<6} {m['vertices']:>8} {m['surface_vertices']:>8} {m['tets']:>7} "
                     f"{1e3 * m['mean_edge']:>8.2f} {m['min_quality']:>6.3f} {m['mean_quality']:>6.3f} "
                     f"{m['epsilon']:>8.0e}")
    t, f, w = c["tool"], c["family"], c["workspace"]
    params = ", ".join(f"{k} {1e3 * v:.1f} mm" for k, v in t.items()
                       if k not in ("shape", "rest_orientation", "rest_clearance", "segments"))
    if "segments" in t:
        unit = "subdivisions" if t["shape"] == "sphere" else "segments"
        solver_tool = new.scene.tool  # the TOML's segments: the same mesh at both resolutions
        params += (f"; the solver's mesh {t['segments']} {unit}, its faces within "
                   f"{facet_depth(solver_tool) / c['dhat']:.2f} dhat of the {t['shape']} and turned up to "
                   f"{np.degrees(facet_tilt(solver_tool)):.1f} degrees from its normal")
    m = c["material"]
    support = ("ground plane at z = 0" if "ground" in c
               else f"bottom {1e3 * c['object']['pin_height']:.1f} mm glued in place")
    lines += ["",
              f"  tool      {t['shape']}: {params}; clearance at rest {1e3 * t['rest_clearance']:.1f} mm",
              f"  material  {m['preset']}: E {m['youngs_modulus']:.3g} Pa, nu {m['poisson_ratio']:g}, "
              f"rho {m['density']:g} kg/m^3",
              f"  support   {support}; dhat {1e3 * c['dhat']:.3f} mm; r_W ci "
              f"{1e3 * c['model']['ci']['world_radius']:.2f} mm, full "
              f"{1e3 * c['model']['full']['world_radius']:.2f} mm",
              "  workspace [" + ", ".join(f"{v:.3f}" for v in w["min"]) + "] .. ["
              + ", ".join(f"{v:.3f}" for v in w["max"]) + "] m",
              f"  family    presses, drags, plunges over the surface; depth {1e3 * f['depth'][0]:.1f}-"
              f"{1e3 * f['depth'][1]:.1f} mm, speed {1e3 * f['speed'][0]:.1f}-{1e3 * f['speed'][1]:.1f} mm/step, "
              f"tilt up to {f['tilt_deg'][1]:g} deg, first at ({f['target_xy'][0]:.3f}, {f['target_xy'][1]:.3f})"]
    lines += [f"  checked   {line}" for line in new.checks]
    return "\n".join(lines)
