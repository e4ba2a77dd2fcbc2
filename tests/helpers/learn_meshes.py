"""Small real meshes and a sphere tool for the learn/ tests (plain arrays, no scene files)."""

from __future__ import annotations

import numpy as np

from colgnn_core.learn.graph import make_template


def box_tet_mesh(nx: int = 3, ny: int = 3, nz: int = 2, size: float = 0.1) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A grid of cubes, each split into 6 positive tets. Returns (vertices [N,3], tets [K,4], faces [F,3])."""
    g = np.stack(np.meshgrid(np.arange(nx + 1), np.arange(ny + 1), np.arange(nz + 1), indexing="ij"), -1)
    verts = g.reshape(-1, 3).astype(np.float64) * size / max(nx, ny, nz)
    vid = np.arange(verts.shape[0]).reshape(nx + 1, ny + 1, nz + 1)
    c = np.stack([vid[:-1, :-1, :-1], vid[1:, :-1, :-1], vid[1:, 1:, :-1], vid[:-1, 1:, :-1],
                  vid[:-1, :-1, 1:], vid[1:, :-1, 1:], vid[1:, 1:, 1:], vid[:-1, 1:, 1:]], -1).reshape(-1, 8)
    kuhn = np.array([[0, 1, 2, 6], [0, 2, 3, 6], [0, 3, 7, 6], [0, 7, 4, 6], [0, 4, 5, 6], [0, 5, 1, 6]])
    tets = c[:, kuhn].reshape(-1, 4)
    x = verts[tets]
    vol = np.einsum("ij,ij->i", np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), x[:, 3] - x[:, 0])
    tets[vol < 0] = tets[vol < 0][:, [0, 2, 1, 3]]
    tri = tets[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3)
    key = np.sort(tri, axis=1)
    _, inv, counts = np.unique(key, axis=0, return_inverse=True, return_counts=True)
    faces = tri[counts[inv.ravel()] == 1]
    return verts, tets, faces


def sphere_points(n: int = 60, radius: float = 0.03, seed: int = 0) -> np.ndarray:
    """``n`` points exactly on a sphere of ``radius`` around the origin (tool frame)."""
    p = np.random.default_rng(seed).normal(size=(n, 3))
    return radius * p / np.linalg.norm(p, axis=1, keepdims=True)


def sphere_sdf(radius: float):
    """World SDF of a sphere tool whose pose is [px,py,pz,qx,qy,qz,qw] (rotation irrelevant)."""
    def sdf(points: np.ndarray, pose: np.ndarray) -> np.ndarray:
        return np.linalg.norm(points - np.asarray(pose)[:3], axis=1) - radius
    return sdf


def box_and_sphere(surface_only: bool = False, world_radius: float = 0.03, pinned=None, tool_n: int = 60):
    """Template for a 0.1 m box and a 3 cm sphere tool; returns (template, rest [N_mesh,3], tool_local [M,3])."""
    verts, tets, faces = box_tet_mesh()
    tool = sphere_points(tool_n)
    tpl = make_template(verts, tets, faces, num_tool_nodes=tool.shape[0], world_radius=world_radius,
                        surface_only=surface_only, pinned=pinned, tool_sdf=sphere_sdf(0.03), sdf_margin=0.0)
    return tpl, verts, tool
