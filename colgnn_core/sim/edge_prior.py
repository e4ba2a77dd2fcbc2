"""A physics prior for a blade: linear elasticity at the settled rest, the edge carrying the surface above it.

Why: a knife's edge presses on face interiors along a line, between the mesh nodes. On ``knife_torus`` the contact
prior holds faces or vertices outside the blade, and neither works (docs/FIDELITY.md, session 46): on the ``ci``
mesh each face's deepest point lies nearer a flat than the edge, so the faces are held apart sideways and the
points move 17-31 mm where the truth moves 15; on the full mesh an edge that enters between vertices is not seen at
all (the prior barely moves). The truth has no fracture: the surface wraps around the edge, and the material that
lay above the edge is carried down with it, as the cone's tip carries one point (``sim.tip_prior``).

The model (units: m):

* **Contact.** The edge (the tool frame's x axis, |x| <= length/2) is sampled about once per rest surface edge
  length. Each sample, taken the solver's gap ahead of the edge (along the tool's -z), that lies inside the settled
  rest shape carries the rest-surface point straight above it: where the ray from the sample along the tool's +z
  (towards the spine) leaves the rest shape (the sample is inside when the first face that ray meets faces along
  it; the surface's faces are wound outward). No state: a frictionless edge that slides along itself leaves the
  material where it was, and the material above the edge at each pose is the one it holds.
* **Response.** The displacement u [N_mesh,3] minimises 1/2 u^T K u (K the stable Neo-Hookean Hessian at the
  settled rest, glued vertices fixed) subject to every carried point reaching its sample in the blade's plane:
  two equality rows a point, along the tool's y (across the blade) and z (up); along the edge (x) it is free to
  slide. The solve is the contact prior's (``ContactPrior.solve`` with equality rows only).
* **Not the flats.** Holding every face that then reaches into the blade's flats or bevel outside them, with the
  contact prior's active set, was measured and left out (docs/FIDELITY.md, session 48): alone it scored the same
  on three training sequences (0.367 / 0.482 / 0.348 against 0.350 / 0.480 / 0.351) at 2-3 times the cost, and
  behind the correction on the 4.3 cm press and drag it scored 2.69 against 0.65 (why was not examined).

Measured on ``knife_torus`` full (session 48), all vertices: alone 0.350 / 0.480 / 0.351 on three training
sequences (``rest + correction`` 0.858 / 0.913 / 0.820; session 24's network 0.398 / 0.409 / 0.270), the same behind
the correction, and 0.650 there on the held-out press and drag (1.170; the network 0.714).

Cost: the rays are cast, all in one compiled call, only at the faces that straddle the blade's plane (a strip a
face wide; 0.4 ms a step on the full torus), and the solve has two rows a carried point (exact K^-1 at ``ci``,
``sim.compliance.ModalCompliance`` on a fine mesh). On the full torus the exact response is one back-substitution
with the whole Cholesky factor, 16 ms a call in contact: twice the network, so a model with it stepped in 23.6 ms
even with the prior beside the network (session 48). ``compliance="modal_response"`` reads the response from the
modes and the near field at the graph's nodes instead: about 2 ms, and as accurate alone (docs/FIDELITY.md,
session 49).
"""

from __future__ import annotations

import numpy as np

from colgnn_core.errors import InputError
from colgnn_core.geometry.rays import first_hits
from colgnn_core.geometry.transforms import quat_to_matrix
from colgnn_core.sim.compliance import ExactCompliance, ModalCompliance
from colgnn_core.sim.contact_prior import ContactPrior, EqualityRows
from colgnn_core.sim.rest_stiffness import RestStiffness

__all__ = ["EdgePrior", "check_edge_tool"]


def check_edge_tool(tool) -> None:
    """InputError unless ``tool`` is a blade (its edge, the tool frame's x axis, leads every contact)."""
    if tool.shape != "blade":
        raise InputError(f"the edge prior needs a blade, not a {tool.shape} {dict(tool.params)}")


class EdgePrior:
    """The prior's displacement of graph nodes for tool poses, for one scene and settled rest (module docstring).

    scene: its object (tet mesh, surface faces), material, glued vertices and tool (a blade);
    rest_mesh: [N_mesh,3] the settled rest (m); nodes: [N] mesh ids of the graph nodes the prior is given for;
    stiffness, compliance, points: as :class:`ContactPrior` (whose solve this prior uses).
    Set-up factorises the free stiffness (seconds at full resolution).
    """

    def __init__(self, scene, rest_mesh: np.ndarray, nodes: np.ndarray, stiffness: RestStiffness | None = None,
                 compliance: ExactCompliance | ModalCompliance | None = None, points: str = "faces"):
        check_edge_tool(scene.tool)
        self.contact = ContactPrior(scene, rest_mesh, nodes, stiffness=stiffness, compliance=compliance,
                                    points=points)
        self.stiffness, self.rest, self.nodes = self.contact.stiffness, self.contact.rest, self.contact.nodes
        self.gap = self.contact.gap
        self.faces = np.asarray(scene.object.faces, dtype=np.int64)   # the whole closed surface (inside tests)
        self.tri = np.ascontiguousarray(self.rest[self.faces])         # [F,3,3] (m) rest triangles, read every step
        edges = self.tri - np.roll(self.tri, 1, axis=1)
        spacing = float(np.linalg.norm(edges, axis=2).mean())
        half = 0.5 * float(scene.tool.params["length"])
        self.edge_x = np.linspace(-half, half, max(2, int(np.ceil(2 * half / spacing)) + 1))  # [S] (m), tool x

    # -- geometry ---------------------------------------------------------------------------------------------
    def carried(self, pose: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(faces [k] rows of the surface faces, barycentric weights [k,3], the samples [k,3] m) of the rest-surface
        points that the edge at ``pose`` [7] carries: one per edge sample inside the rest shape."""
        pose = np.asarray(pose, dtype=np.float64)
        rot = quat_to_matrix(pose[3:])
        up = rot[:, 2]
        samples = pose[:3] + np.outer(self.edge_x, rot[:, 0]) - self.gap * up          # [S,3]
        # The rays lie in the blade's plane: only faces that straddle it can be crossed. (Per-column minimum and
        # maximum: numpy's reductions over a 3-long axis cost the full torus 1.6 ms a step, these 0.05.)
        y = (self.tri.reshape(-1, 3) @ rot[:, 1]).reshape(-1, 3) - pose[:3] @ rot[:, 1]     # [F,3] across it
        low = np.minimum(np.minimum(y[:, 0], y[:, 1]), y[:, 2])
        high = np.maximum(np.maximum(y[:, 0], y[:, 1]), y[:, 2])
        strip = np.flatnonzero((low <= 0.0) & (high >= 0.0))
        tri = self.tri[strip]
        first, _, bary = first_hits(tri, samples, up)
        hit = np.flatnonzero(first >= 0)
        met = tri[first[hit]]                                                           # [H,3,3]
        outward = np.cross(met[:, 1] - met[:, 0], met[:, 2] - met[:, 0]) @ up
        # Inside when the first face the ray meets is one it leaves through (> 0 along the ray). Not a parity count:
        # a ray in the blade's plane often runs through a row of mesh edges, where both faces of an edge report the
        # hit.
        inside = hit[outward > 0.0]
        return strip[first[inside]], bary[inside], samples[inside]

    def edge_rows(self, pose: np.ndarray) -> EqualityRows | None:
        """The equality rows (module docstring) of the points the edge at ``pose`` [7] carries; None without any,
        or when every carried point lies on a glued face (nothing can move)."""
        faces, bary, samples = self.carried(pose)
        verts = self.faces[faces]
        movable = (np.where(self.stiffness.free_index[verts] >= 0, bary, 0.0) > 0).any(axis=1)
        if not movable.any():
            return None
        verts, bary, samples = verts[movable], bary[movable], samples[movable]
        rot = quat_to_matrix(np.asarray(pose, dtype=np.float64)[3:])
        moved = samples - np.einsum("kj,kjd->kd", bary, self.rest[verts])              # [k,3] to the sample
        normals = rot[:, 1:].T                                                          # [2,3]: y then z
        return (np.repeat(verts, 2, axis=0), np.repeat(bary, 2, axis=0), np.tile(normals, (len(verts), 1)),
                (moved @ normals.T).reshape(-1))

    # -- response ---------------------------------------------------------------------------------------------
    def step(self, previous: None, pose_prev: np.ndarray, pose: np.ndarray) -> tuple[None, np.ndarray]:
        """(no state, the displacement [N,3] at ``pose`` [7]): the interface of ``sim.tip_prior.TipPrior``."""
        return None, self.displacement(pose)

    def displacement(self, pose: np.ndarray) -> np.ndarray:
        """[N,3] (m): the graph nodes' displacement with the blade at ``pose`` [7]."""
        return self.stiffness.to_nodes(self.free_displacement(pose), self.nodes)

    def free_displacement(self, pose: np.ndarray) -> np.ndarray:
        """[3N_free] (m): the response to the edge's equality rows (0 while no edge sample is inside the rest
        shape: there the truth's surface has not yet wrapped around the edge)."""
        pose = np.asarray(pose, dtype=np.float64)
        rows = self.edge_rows(pose)
        if rows is None:
            return np.zeros(3 * self.stiffness.n_free)
        return self.contact.solve(self.rest, pose, {}, equality=rows)

    def rollout(self, poses: np.ndarray) -> np.ndarray:
        """[T,N,3] (m): the prior along a pose sequence [T,7]."""
        return np.stack([self.displacement(p) for p in np.asarray(poses, dtype=np.float64)])
