"""Small inputs for the simulator tests: a tet box and a sphere-tool scene, built without the scene registry."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np

from colgnn_core.geometry.tetmesh import TetMesh
from colgnn_core.geometry.tools import make_tool


def box_tet_mesh(lo, hi, cells) -> TetMesh:
    """Axis-aligned box [lo, hi] (m) on a cells=(nx,ny,nz) grid, 6 tets per cell (Kuhn subdivision)."""
    lo, hi = np.asarray(lo, float), np.asarray(hi, float)
    nx, ny, nz = cells
    axes = [np.linspace(lo[d], hi[d], c + 1) for d, c in enumerate(cells)]
    verts = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3)
    idx = np.arange(len(verts)).reshape(nx + 1, ny + 1, nz + 1)
    corners = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0], [0, 0, 1], [1, 0, 1], [0, 1, 1], [1, 1, 1]])
    paths = np.array([(0, 1, 3, 7), (0, 1, 5, 7), (0, 2, 3, 7), (0, 2, 6, 7), (0, 4, 5, 7), (0, 4, 6, 7)])
    i, j, k = (a.reshape(-1) for a in np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij"))
    cube = np.stack([idx[i + a, j + b, k + c] for a, b, c in corners], axis=1)  # [cells, 8]
    tets = cube[:, paths].reshape(-1, 4)
    return TetMesh.from_tets(verts, tets, orient=True)


def box_scene(cells=(6, 6, 2), ground: bool = True, gravity: bool = True, tool_z: float = 0.05, friction: float = 0.0):
    """A 10 x 10 x 2 cm rubber slab (0.5 mm above the ground z = 0) under a 2 cm sphere at (0, 0, tool_z)."""
    mesh = box_tet_mesh([-0.05, -0.05, 0.0005], [0.05, 0.05, 0.0205], cells)
    tool = make_tool("sphere", {"radius": 0.02}, "ci")
    diag = float(np.linalg.norm(mesh.vertices.max(0) - mesh.vertices.min(0)))

    def check_poses(poses):
        return np.asarray(poses, dtype=np.float64)

    return SimpleNamespace(
        name="box",
        resolution="ci",
        dt=0.04,
        material=SimpleNamespace(youngs_modulus=1e5, poisson_ratio=0.4, density=1000.0),
        object=mesh,
        tool=tool,
        tool_rest_pose=np.array([0.0, 0.0, tool_z, 0.0, 0.0, 0.0, 1.0]),
        ground_height=0.0 if ground else None,
        gravity=np.array([0.0, 0.0, -9.81 if gravity else 0.0]),
        dhat=1e-3 * diag,
        friction=friction,
        pinned=np.zeros(0, dtype=np.int64),
        check_poses=check_poses,
    )


def assert_sequence_crossing_free(seq, ground_height=None) -> None:
    """Independent check of a sequence with ipctk's exact CCD (Tight-Inclusion), built from the file's data only.

    Every frame: no intersection between or within the object surface and the tool; every motion from one frame
    to the next collision-free, straight or through the intermediate states the file records for it
    (``Sequence.motion``); object above the ground plane if there is one.
    """
    import ipctk

    from colgnn_core.geometry.tetmesh import surface_edges

    n = seq.object_positions.shape[1]
    faces = np.vstack([seq.object_faces, seq.tool_faces + n])
    edges = np.vstack([surface_edges(seq.object_faces), surface_edges(seq.tool_faces) + n])
    full0 = np.vstack([seq.object_positions[0], seq.tool_positions[0]])
    cm = ipctk.CollisionMesh.build_from_full_mesh(full0, edges.astype(np.int32), faces.astype(np.int32))
    m = seq.tool_positions.shape[1]
    cm.can_collide = ipctk.make_static_obstacle_filter(cm.num_vertices - m)
    ccd = ipctk.TightInclusionCCD(tolerance=1e-6, max_iterations=10_000_000)
    for t in range(seq.frames):
        v = cm.vertices(np.vstack([seq.object_positions[t], seq.tool_positions[t]]))
        assert not ipctk.has_intersections(cm, v), f"frame {t} intersects"
        if t > 0:
            legs = [cm.vertices(np.vstack(state)) for state in seq.motion(t)]
            for a, b in zip(legs[:-1], legs[1:]):
                assert ipctk.is_step_collision_free(cm, a, b, narrow_phase_ccd=ccd), (
                    f"crossing between frames {t - 1} and {t} ({len(legs) - 2} intermediate states)")
        if ground_height is not None:
            assert seq.object_positions[t][:, 2].min() > ground_height, f"frame {t} below the ground"
