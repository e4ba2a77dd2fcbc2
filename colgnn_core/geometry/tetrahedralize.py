"""Tetrahedralization of closed surfaces with fTetWild (PyPI ``pytetwild``).

``colgnn scene new`` tetrahedralizes a user's surface at both resolutions with :func:`tetrahedralize_for`. It also
built the committed ``.npz`` assets (the bunnies) offline. Regenerate those with::

    .venv/bin/pip install pytetwild==0.4.2
    # ci bunny (300 surface vertices)
    .venv/bin/python -m colgnn_core.geometry.tetrahedralize \
        colgnn_core/assets/meshes/small-bunny.obj colgnn_core/assets/meshes/small-bunny-tets.npz \
        --edge-length-fac 0.2 --epsilon 5e-3
    # full bunny (3,012 surface vertices): IPC's bunny surface re-tetrahedralized
    .venv/bin/python -m colgnn_core.geometry.tetrahedralize \
        colgnn_core/assets/meshes/bunny.msh colgnn_core/assets/meshes/bunny-tets.npz \
        --edge-length-fac 0.0275 --epsilon 1e-3 --coarsen

``import pytetwild`` pulls in pyvista (not installed), so the compiled wrapper
``pytetwild.PyfTetWildWrapper`` is loaded directly from the package folder.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.machinery
import importlib.util
import os
import sys
import tempfile
import threading
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from colgnn_core.geometry.tetmesh import TetMesh, load_msh


def _wrapper():
    spec = importlib.util.find_spec("pytetwild")
    if spec is None or not spec.submodule_search_locations:
        raise RuntimeError("pytetwild is not installed: pip install pytetwild==0.4.2")
    folder = Path(list(spec.submodule_search_locations)[0])
    so = next(folder.glob("PyfTetWildWrapper*.so"))
    loader = importlib.machinery.ExtensionFileLoader("PyfTetWildWrapper", str(so))
    mod_spec = importlib.util.spec_from_loader("PyfTetWildWrapper", loader)
    module = importlib.util.module_from_spec(mod_spec)
    loader.exec_module(module)
    return module


_CWD_LOCK = threading.Lock()  # the working folder is the process's: one tetrahedralization at a time changes it


@contextlib.contextmanager
def _scratch_folder() -> Iterator[None]:
    """Run the block in a fresh temporary working folder, then return to the caller's and delete it.

    fTetWild writes its scratch file ``__tracked_surface.stl`` (about 1 MB) into the working folder on every call;
    without this, ``colgnn scene new`` would leave it in the user's folder (or overwrite a file of that name).
    """
    with _CWD_LOCK, tempfile.TemporaryDirectory(prefix="colgnn-ftetwild-") as scratch:
        home = os.getcwd()
        os.chdir(scratch)
        try:
            yield
        finally:
            os.chdir(home)


def tetrahedralize_surface(
    vertices: np.ndarray,
    faces: np.ndarray,
    edge_length_fac: float = 0.1,
    epsilon: float = 1e-3,
    num_threads: int = 1,
    coarsen: bool = False,
) -> TetMesh:
    """Tet mesh of the solid bounded by a closed surface (fTetWild; surface is remeshed within ``epsilon``*bbox)."""
    w = _wrapper()
    empty_v, empty_t, empty_val = np.zeros((0, 3)), np.zeros((0, 4), np.int32), np.zeros(0)
    with _scratch_folder():
        v, t = w.tetrahedralize_mesh(
            # writable copies: the binding refuses read-only arrays
            np.array(vertices, dtype=np.float64, order="C", copy=True),
            np.array(faces, dtype=np.uint32, order="C", copy=True),
            True,  # optimize
            False,  # skip_simplify
            float(edge_length_fac),
            0.0,  # edge_length_abs (0 = use the factor)
            float(epsilon),
            10.0,  # stop_energy
            bool(coarsen),  # coarsen the interior while keeping quality
            int(num_threads),
            80,  # num_opt_iter
            6,  # loglevel
            True,  # quiet
            False,  # vtk_ordering
            False,  # disable_filtering
            empty_v,
            empty_t,
            empty_val,
        )
    t = np.asarray(t, dtype=np.int64)
    used, t = np.unique(t, return_inverse=True)
    mesh = TetMesh.from_tets(np.asarray(v, dtype=np.float64)[used], t.reshape(-1, 4), orient=True)
    mesh.validate()
    return mesh


# Per resolution: the surface vertex count aimed at (as the built-in scenes: ~300 for ci, ~3000 for full) and the
# envelopes (fractions of the bbox diagonal) tried in turn. fTetWild sometimes returns a surface that is not a
# 2-manifold where a thin part (a leg, an ear) is only a few target edge lengths thick; the next envelope is tried.
# The interior is coarsened (fewer tets, quality kept), as for the full bunny: the solver's cost follows the tets.
RESOLUTION_TARGETS = {
    "ci": (300, (8e-3, 5e-3, 4e-3, 3e-3, 2e-3)),
    "full": (3000, (1e-3, 7e-4, 1.5e-3, 5e-4)),
}
COARSEN = True
MIN_TET_QUALITY = 0.05  # worst normalised radius ratio accepted (the shipped meshes: >= 0.17)


def target_edge_length(area: float, surface_vertices: int) -> float:
    """Edge length (m) of an equilateral triangulation of ``area`` m^2 with about ``surface_vertices`` vertices."""
    return float(np.sqrt(2.0 * area / (np.sqrt(3.0) * max(int(surface_vertices), 4))))


def tetrahedralize_for(vertices: np.ndarray, faces: np.ndarray, area: float, resolution: str,
                       num_threads: int = 1) -> tuple[TetMesh, dict]:
    """Tet mesh of a closed surface for a scene resolution ('ci' | 'full'), and how it was made.

    The target edge length follows from the surface area and the resolution's surface vertex count; the fTetWild
    envelopes of ``RESOLUTION_TARGETS`` are tried in turn until the mesh is valid (closed 2-manifold boundary,
    positive tets) and its worst tet quality is at least ``MIN_TET_QUALITY``. ValueError listing every attempt
    when none is.
    """
    target, epsilons = RESOLUTION_TARGETS[resolution]
    v = np.asarray(vertices, dtype=np.float64)
    diag = float(np.linalg.norm(v.max(0) - v.min(0)))
    fac = target_edge_length(area, target) / diag
    tries = []
    for eps in epsilons:
        try:
            mesh = tetrahedralize_surface(v, faces, fac, eps, num_threads=num_threads, coarsen=COARSEN)
        except (ValueError, RuntimeError) as exc:
            tries.append(f"envelope {eps:g}: {exc}")
            continue
        q = mesh.quality()
        if q["min_quality"] < MIN_TET_QUALITY:
            tries.append(f"envelope {eps:g}: worst tet quality {q['min_quality']:.3f} < {MIN_TET_QUALITY}")
            continue
        return mesh, {"edge_length_fac": fac, "epsilon": eps, "coarsen": COARSEN, "attempts": len(tries) + 1, **q}
    raise ValueError(f"fTetWild gave no valid {resolution} tet mesh: " + "; ".join(tries))


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("surface",
                    help="closed triangle surface (.obj/.stl/.ply, read with trimesh) or a .msh tet mesh (its "
                         "boundary)")
    ap.add_argument("out", help="output .npz (vertices, tets)")
    ap.add_argument("--edge-length-fac", type=float, default=0.1, help="target edge length / bbox diagonal")
    ap.add_argument("--epsilon", type=float, default=1e-3, help="surface envelope / bbox diagonal")
    ap.add_argument("--coarsen", action="store_true", help="coarsen the interior (fewer tets)")
    args = ap.parse_args(argv)
    if args.surface.endswith(".msh"):
        src = load_msh(args.surface)
        vertices, faces = src.vertices, src.faces
    else:
        import trimesh  # lazy: trimesh is slow to import and only mesh files need it

        surf = trimesh.load(args.surface, process=False, force="mesh")
        vertices, faces = np.asarray(surf.vertices), np.asarray(surf.faces)
    mesh = tetrahedralize_surface(vertices, faces, args.edge_length_fac, args.epsilon, coarsen=args.coarsen)
    mesh.save_npz(args.out)
    print(f"{args.out}: {mesh.num_vertices} vertices, {len(mesh.surface_vertices)} surface vertices, "
          f"{len(mesh.faces)} faces, {len(mesh.tets)} tets")
    return 0


if __name__ == "__main__":
    sys.exit(main())
