"""Offline tetrahedralization of closed surfaces with fTetWild (PyPI ``pytetwild``).

Used once to build the committed ``.npz`` assets (the bunnies); neither the
tests nor the scenes import it, so CI does not need pytetwild. Regenerate::

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
import importlib.machinery
import importlib.util
import sys
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
