"""A physics prior for a sharp tool: linear elasticity at the settled rest, with the tip carrying a surface point.

Why: a sharp cone pushes on face interiors, between the mesh nodes, and the object answers with a dent *and* a
bending of its whole body (``cone_bunny``: 65-69% of the vertices move more than a tenth of the dent). A
state-free network trained on 20-26 family sequences dented too little at contact places it had not seen
(held-out relative displacement error 0.91). The dent's size and its spread through the body are mostly linear
elasticity, which is cheap once the stiffness is factorised; what a network then has to learn is the remainder.

The model (units: m):

* **Contact.** While the tip (the tool frame's origin) lies inside the settled rest shape, one material point of
  the rest surface is carried to the tip: the point where the tip entered (the segment from the previous tip to
  this one crosses the rest surface there; when the tip starts inside, the point where the tool's axis leaves the
  rest shape above the tip). A frictionless cone drags its pocket along (measured, docs/FIDELITY.md session 10),
  but not without bound: when the carried point's rest position lies farther than ``kappa`` times the tip's depth
  (along the axis) from the axis point (where the axis leaves the rest shape), it slides toward the axis point to
  that distance. Outside the rest shape there is no contact and no displacement.
* **Response.** The displacement u [N_mesh,3] minimises the linear-elastic energy 1/2 u^T K u (K the stable
  Neo-Hookean Hessian at the settled rest, glued vertices fixed) subject to the carried point reaching the tip:
  sum_k b_k u_k = tip - sum_k b_k X_k over the carried face's vertices k with barycentric weights b. Three
  equality constraints: u = K^-1 A^T (A K^-1 A^T)^-1 d. The columns K^-1 A^T are three back-substitutions per face
  vertex, solved together for a new face (about 27 ms at full ``cone_bunny``) and cached per vertex, so a stab
  that stays on one face costs them once.

Measured offline on ``cone_bunny`` full (docs/FIDELITY.md, session 12): over all frames and vertices, 0.70 on
the six held-out trajectories without the slide rule (stabs 0.23-0.37 per frame at depth) against 0.91 for the
shipped network; wrong where a slice or drag moves the tip far through the material.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import trimesh
from scipy.spatial import cKDTree

from colgnn_core.errors import InputError
from colgnn_core.geometry.rays import first_hits, ray_faces
from colgnn_core.geometry.transforms import quat_to_matrix
from colgnn_core.sim.contact_prior import ContactPrior, point_rows
from colgnn_core.sim.rest_stiffness import RestStiffness

__all__ = ["AHEAD_GAPS", "KAPPA", "SIDE_ROUNDS", "TipContact", "TipPrior", "TipSidePrior", "check_tip_tool"]

AHEAD_GAPS = 1.0  # TipSidePrior: the carried point is held this many solver gaps ahead of the tip
SIDE_ROUNDS = 12  # TipSidePrior: active-set rounds per pose (the hard drag on cone_bunny: 5.4 on average)
KAPPA = 2.0  # carried point at most KAPPA x tip depth from the axis point (chosen on 12 training sequences; on 74,
             # 0.75-1 fits better as a prior alone, but a network on kappa 1 scored worse held out: docs/FIDELITY.md
             # session 55; a model sets its own with ModelConfig.tip_kappa)


@dataclass(frozen=True)
class TipContact:
    """The carried material point: rest-surface triangle ``face`` (row of the object's faces) and barycentric
    weights ``bary`` [3]."""

    face: int
    bary: tuple[float, float, float]


def check_tip_tool(tool) -> None:
    """InputError unless ``tool`` is a sharp cone (its tip, the tool frame's origin, leads every contact)."""
    if tool.shape != "cone" or float(tool.params.get("tip_radius", 0.0)) > 0.0:
        raise InputError(f"the tip prior needs a sharp cone (tip_radius 0), not a {tool.shape} "
                         f"{dict(tool.params)}")


def _axis(pose: np.ndarray) -> np.ndarray:
    """[3] the cone's axis in the world at ``pose`` [7]: the tool frame's +z, along which the cone opens, out of
    the object."""
    return quat_to_matrix(np.asarray(pose, dtype=np.float64)[3:]) @ np.array([0.0, 0.0, 1.0])


class TipPrior:
    """The prior's displacement of graph nodes for tool poses, for one scene and settled rest (module docstring).

    scene: its object (tet mesh, surface faces), material, glued vertices and tool (a sharp cone);
    rest_mesh: [N_mesh,3] the settled rest (m); nodes: [N] mesh ids of the graph nodes the prior is given for.
    Set-up factorises the free stiffness (seconds at full resolution).
    """

    def __init__(self, scene, rest_mesh: np.ndarray, nodes: np.ndarray, kappa: float = KAPPA):
        check_tip_tool(scene.tool)
        self.stiffness = RestStiffness(scene, rest_mesh)
        self.rest = self.stiffness.rest
        self.nodes = np.asarray(nodes, dtype=np.int64)
        self.kappa = float(kappa)
        self.faces = np.asarray(scene.object.faces, dtype=np.int64)
        self.triangles = self.rest[self.faces]                 # [F,3,3]
        self.centroids = cKDTree(self.triangles.mean(axis=1))

    # -- geometry ---------------------------------------------------------------------------------------------
    def inside(self, point: np.ndarray) -> bool:
        """Whether ``point`` [3] lies inside the rest shape (odd crossings of a ray along +z)."""
        hit, _, _ = ray_faces(self.triangles, np.asarray(point, dtype=np.float64), np.array([0.0, 0.0, 1.0]))
        return int(hit.sum()) % 2 == 1

    def first_hit(self, origin: np.ndarray, direction: np.ndarray, limit: float = np.inf
                   ) -> tuple[TipContact, float] | None:
        """(the rest-surface point, its distance in units of ``direction``) where the ray from ``origin`` [3] along
        ``direction`` [3] first crosses the rest surface within ``limit``; None when it does not."""
        face, t, bary = first_hits(self.triangles, np.asarray(origin, dtype=np.float64)[None], direction)
        if face[0] < 0 or t[0] > limit:
            return None
        return TipContact(int(face[0]), tuple(float(b) for b in bary[0])), float(t[0])

    def point(self, contact: TipContact) -> np.ndarray:
        """The contact's material point in the rest shape [3] (m)."""
        return np.asarray(contact.bary) @ self.triangles[contact.face]

    def _nearest(self, q: np.ndarray) -> TipContact:
        """The rest-surface point nearest to ``q`` [3] (among the 16 triangles with the nearest centroids)."""
        _, cand = self.centroids.query(q, k=min(16, len(self.faces)))
        cand = np.atleast_1d(cand)
        tri = self.triangles[cand]
        close = trimesh.triangles.closest_point(tri, np.repeat(q[None], len(cand), axis=0))
        j = int(np.argmin(np.linalg.norm(close - q, axis=1)))
        b = trimesh.triangles.points_to_barycentric(tri[j][None], close[j][None])[0]
        b = np.clip(b, 0.0, None)
        return TipContact(int(cand[j]), tuple(float(v) for v in b / b.sum()))

    def contact(self, previous: TipContact | None, pose_prev: np.ndarray, pose: np.ndarray) -> TipContact | None:
        """The carried point at ``pose`` [7], given the one before (None: no contact) and the previous pose [7]."""
        pose = np.asarray(pose, dtype=np.float64)
        tip, tip_prev = pose[:3], np.asarray(pose_prev, dtype=np.float64)[:3]
        if not self.inside(tip):
            return None
        axis = _axis(pose)
        up = self.first_hit(tip, axis)
        if up is None:  # inside, yet the axis never leaves: only at a grazing ray; keep what there was
            return previous
        axis_point, depth = up
        carried = previous
        if carried is None:
            step = tip - tip_prev
            length = float(np.linalg.norm(step))
            entered = self.first_hit(tip_prev, step / length, length) if length > 0 else None
            carried = entered[0] if entered is not None else axis_point
        rc, ra = self.point(carried), self.point(axis_point)
        gap, reach = float(np.linalg.norm(rc - ra)), self.kappa * depth
        if gap > reach:
            carried = self._nearest(ra + (rc - ra) * (reach / gap))
        return carried

    # -- response ---------------------------------------------------------------------------------------------
    def displacement(self, contact: TipContact | None, pose: np.ndarray) -> np.ndarray:
        """[N,3] (m): the graph nodes' linear-elastic displacement that carries ``contact``'s point to the tip of
        the tool at ``pose`` [7]."""
        return self.stiffness.to_nodes(self.free_displacement(contact, pose), self.nodes)

    def free_displacement(self, contact: TipContact | None, pose: np.ndarray) -> np.ndarray:
        """[3N_free] (m): the free vertices' displacement that carries ``contact``'s point to :meth:`target`."""
        free_u = np.zeros(3 * self.stiffness.n_free)
        if contact is None:
            return free_u
        fi = self.stiffness.free_index
        verts = self.faces[contact.face]
        weights = [(int(v), b) for v, b in zip(verts, contact.bary) if fi[v] >= 0 and b > 0]
        if not weights:  # a glued triangle: nothing can move
            return free_u
        columns = self.stiffness.columns([v for v, _ in weights])
        cols = sum(b * c for (_, b), c in zip(weights, columns))                # K^-1 A^T, transposed [3, 3N_free]
        s = sum(b * cols[:, 3 * fi[v]:3 * fi[v] + 3] for v, b in weights)      # A K^-1 A^T
        lam = np.linalg.solve(s, self.target(contact, pose))
        return lam @ cols

    def target(self, contact: TipContact, pose: np.ndarray) -> np.ndarray:
        """[3] (m): the carried point's displacement, from its rest place to the tip of the tool at ``pose`` [7]."""
        return np.asarray(pose, dtype=np.float64)[:3] - self.point(contact)

    def step(self, previous: TipContact | None, pose_prev: np.ndarray, pose: np.ndarray
             ) -> tuple[TipContact | None, np.ndarray]:
        """(the carried point, the displacement [N,3]) at ``pose`` [7], from the carried point at ``pose_prev``."""
        contact = self.contact(previous, pose_prev, pose)
        return contact, self.displacement(contact, pose)

    def rollout(self, poses: np.ndarray) -> np.ndarray:
        """[T,N,3] (m): the prior along a pose sequence [T,7] that starts out of contact or in it (frame 0 too)."""
        poses = np.asarray(poses, dtype=np.float64)
        out = np.zeros((len(poses), self.nodes.size, 3))
        contact = None
        for t, pose in enumerate(poses):
            contact, out[t] = self.step(contact, poses[max(t - 1, 0)], pose)
        return out


class TipSidePrior(TipPrior):
    """The tip prior with frictionless contact on the cone's side: a pocket as wide as the cone.

    Why: the tip prior's pocket is a point-load spike, narrower than the cone, so the cone's side passes through
    the faces around it; on a drag the correction then has hundreds of crossings to undo and falls back
    (docs/FIDELITY.md, sessions 12 and 14). Here the carried point is held ``AHEAD_GAPS`` solver gaps ahead of
    the tip (a face through the sharp tip itself would be pierced by the cone's side whatever its tilt), and every
    surface face that reaches into the cone is held outside it at the solver's gap, as in ``sim.contact_prior``:
    the displacement minimises the same elastic energy under the tip's three equality constraints and the faces'
    inequality constraints. A stretched face that slides over the cone may get a second point, and the cone's
    axis, which pierces a wide face between its samples, gives each face one more sample.

    Measured on ``cone_bunny`` full (docs/FIDELITY.md, session 15): alone, as accurate as the tip prior on 12
    training sequences (0.539 against 0.534); behind the correction, 0.628 against 0.727 on six held-out
    trajectories, since the correction stops falling back on a family drag. A network on top added nothing (0.626,
    two seeds), and the hard drags still fall back: the carried point's slide, not the pocket's width, is next.
    """

    def __init__(self, scene, rest_mesh: np.ndarray, nodes: np.ndarray, kappa: float = KAPPA):
        super().__init__(scene, rest_mesh, nodes, kappa)
        self.side = ContactPrior(scene, rest_mesh, nodes, stiffness=self.stiffness)

    def target(self, contact: TipContact, pose: np.ndarray) -> np.ndarray:
        pose = np.asarray(pose, dtype=np.float64)
        return pose[:3] - AHEAD_GAPS * self.side.gap * _axis(pose) - self.point(contact)

    def free_displacement(self, contact: TipContact | None, pose: np.ndarray) -> np.ndarray:
        """[3N_free] (m): the tip's constraint and the side's, together, while the tip is inside the rest shape.

        The side alone, with the tip outside, is left out: on 12 training sequences it scored 0.585 against 0.539
        (it pushes the surface away at the solver's gap before the tip enters). So a cone whose side sweeps a part
        over with its tip outside (``cone_bunny``'s ears, up to 9 cm in one training sequence) gets no prior."""
        free_u = super().free_displacement(contact, pose)
        if contact is None or not free_u.any():  # no contact, or a glued triangle
            return free_u
        pose = np.asarray(pose, dtype=np.float64)
        tip = point_rows(self.faces[contact.face], np.asarray(contact.bary), self.target(contact, pose))
        ray = (pose[:3], _axis(pose))
        every = np.arange(self.rest.shape[0])
        active: dict = {}
        for _ in range(SIDE_ROUNDS):
            x = self.rest + self.stiffness.to_nodes(free_u, every)
            new = self.side.entering(x, pose, active, resample=True, ray=ray)
            if not new:
                break
            active.update(new)
            free_u = self.side.solve(x, pose, active, equality=tip)
        return free_u
