"""Training augmentation by a scene's symmetry: the same event, turned about the vertical axis.

Why: full-resolution ground truth costs minutes per sequence, and a cut seen at one place of a ring says
nothing to the network about the rest of the ring unless the network is told that the ring looks the same
everywhere. Gravity, the table and the glued band are unchanged by a turn about the vertical axis, so turning a
whole recorded transition (object, tool and its pose) about the axis of a rotationally symmetric object gives
another valid transition of the same object. Each training sample is turned by a random one of the mesh's own
symmetry rotations, which map the graph nodes onto each other: a node permutation, so the graph (topology, rest
shape, node types, coarse clusters) stays the scene's own. A physics prior (sim.prior) turns with the sample: it is
a function of the tool's pose on the same mesh, so the turned prior is the prior of the turned pose.

A scene declares its symmetry in its TOML::

    [symmetry]
    kind = "rotation_z"       # turns about the vertical axis through center_xy
    center_xy = [0.0, 0.0]    # m
    order = 124               # turns by multiples of 360/order degrees (default: the object's ``segments``)

:func:`node_symmetry` checks the declaration against the mesh: every turned graph node must land on a graph node
(within 1e-6 of the bbox diagonal), or the scene is refused with the largest mismatch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial import cKDTree

from colgnn_core.errors import InputError
from colgnn_core.geometry.transforms import axis_angle_quat, quat_multiply, quat_to_matrix
from colgnn_core.learn.model import Frame
from colgnn_core.scenes.scene import at_resolution

__all__ = ["NodeSymmetry", "node_symmetry", "SYMMETRY_TOLERANCE"]

SYMMETRY_TOLERANCE = 1e-6  # largest node mismatch after a turn, as a fraction of the object's bbox diagonal


@dataclass(frozen=True)
class NodeSymmetry:
    """Turns about the vertical axis through ``center`` that map the graph nodes onto themselves.

    center: [3] a point of the axis (m, z = 0); angles: [K] rad (the identity excluded);
    permutations: [K,N] int64, ``permutations[k, i]`` the graph node at the turned position of node ``i``.
    """

    center: np.ndarray
    angles: np.ndarray
    permutations: np.ndarray

    @property
    def order(self) -> int:
        return int(len(self.angles)) + 1

    def turn(self, frame: Frame, x_next: torch.Tensor, pose_t: np.ndarray, k: int
             ) -> tuple[Frame, torch.Tensor, np.ndarray]:
        """The sample ``(frame, x_next [N,3], pose_t [7])`` turned by ``angles[k]``, the frame's physics prior (a
        displacement [N,3]) with it; k = -1 returns it unchanged."""
        if k < 0:
            return frame, x_next, pose_t
        angle, perm = float(self.angles[k]), torch.from_numpy(self.permutations[k])
        R = torch.tensor(_rotation_z(angle))
        c = torch.from_numpy(self.center)

        def nodes(x: torch.Tensor) -> torch.Tensor:  # turned, then moved to the node that sits there at rest
            out = torch.empty_like(x)
            out[perm] = (x - c) @ R.T + c
            return out

        def points(y: torch.Tensor) -> torch.Tensor:
            return (y - c) @ R.T + c

        def displacements(u: torch.Tensor) -> torch.Tensor:  # a node vector field: turned, no centre
            out = torch.empty_like(u)
            out[perm] = u @ R.T.to(u.dtype)
            return out

        turned = Frame(nodes(frame.x_prev), nodes(frame.x_t), points(frame.tool_t), points(frame.tool_next),
                       None if frame.pose_next is None else self.turn_pose(frame.pose_next, angle),
                       None if frame.prior is None else displacements(frame.prior))
        return turned, nodes(x_next), self.turn_pose(pose_t, angle)

    def turn_points(self, points: np.ndarray, angle: float) -> np.ndarray:
        """Points [K,3] (m) turned by ``angle`` (rad) about the axis."""
        return (np.asarray(points, dtype=np.float64) - self.center) @ _rotation_z(angle).T + self.center

    def turn_pose(self, pose: np.ndarray, angle: float) -> np.ndarray:
        """A tool pose [7] (position m, quaternion xyzw) turned by ``angle`` (rad) about the axis."""
        pose = np.asarray(pose, dtype=np.float64)
        p = self.turn_points(pose[None, :3], angle)[0]
        q = quat_multiply(axis_angle_quat(np.array([0.0, 0.0, 1.0]), angle), pose[3:])
        return np.concatenate([p, q])


def _rotation_z(angle: float) -> np.ndarray:
    """[3,3] turn by ``angle`` (rad) about +z."""
    return quat_to_matrix(axis_angle_quat(np.array([0.0, 0.0, 1.0]), angle))


def node_symmetry(scene, rest: np.ndarray) -> NodeSymmetry | None:
    """The symmetry ``scene`` declares, on graph nodes with rest positions ``rest`` [N,3] (m); None if it declares
    none. InputError when the declaration is malformed or the nodes are not symmetric under it."""
    spec = scene.config.get("symmetry")
    if not spec:
        return None
    spec = at_resolution(spec, scene.resolution)
    if spec.get("kind") != "rotation_z":
        raise InputError(f"{scene.name}: symmetry.kind must be 'rotation_z', got {spec.get('kind')!r}")
    order = spec.get("order", at_resolution(scene.config.get("object", {}), scene.resolution).get("segments"))
    if not isinstance(order, int) or order < 2:
        raise InputError(f"{scene.name}: symmetry.order must be an integer >= 2 (turns by 360/order degrees), "
                         f"got {order!r}")
    cx, cy = (float(v) for v in spec.get("center_xy", [0.0, 0.0]))
    center = np.array([cx, cy, 0.0])
    rest = np.asarray(rest, dtype=np.float64)
    tree = cKDTree(rest)
    tol = SYMMETRY_TOLERANCE * scene.bbox_diagonal()
    angles = 2.0 * math.pi * np.arange(1, order) / order
    perms = np.empty((order - 1, len(rest)), dtype=np.int64)
    for k, angle in enumerate(angles):
        dist, idx = tree.query((rest - center) @ _rotation_z(angle).T + center)
        if dist.max() > tol or len(np.unique(idx)) != len(rest):
            raise InputError(f"{scene.name}/{scene.resolution}: the graph nodes are not symmetric under a turn by "
                             f"{math.degrees(angle):.3f} deg about ({cx}, {cy}): a node lands {dist.max():.3g} m "
                             f"from the nearest node (tolerance {tol:.3g} m)")
        perms[k] = idx
    return NodeSymmetry(center, angles, perms)
