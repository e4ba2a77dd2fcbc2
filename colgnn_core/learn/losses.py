"""Training losses: the data term L_q, the latent KL term, L_ccd, ξ_Random and L_valid.

L_GNN = L_q + L_ccd + L_compact (paper eq. 2), L_ccd = ξ_VF + ξ_EE (eq. 4),
L_compact = ξ_Random + L_KL (eq. 9). The collision depths come from the
collision module (filter + narrow phase, evaluated differentiably in torch);
ξ_Random uses the tool's analytic SDF. L_valid (ours, not the paper's) penalises surface triangles whose predicted
normal turns too far from their rest normal (:func:`flip_hinge`), the flips that
:mod:`colgnn_core.collision.surface_validity` counts. Weights and ramps are training settings
(:class:`colgnn_core.learn.train.TrainConfig`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from colgnn_core.collision.surface_validity import best_rotation


def loss_q(pred_norm: torch.Tensor, target_norm: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """L_q: squared error of the normalised acceleration, summed over xyz, averaged over (masked) nodes.

    This is MGN's loss (``reduce_sum`` over the 3 components, mean over free
    nodes), i.e. 3 x the elementwise MSE. Shapes [N,3], mask [N] bool.
    """
    err = ((pred_norm - target_norm) ** 2).sum(dim=-1)
    if mask is not None:
        err = err[mask]
    if err.numel() == 0:
        return pred_norm.sum() * 0.0
    return err.mean()


def kl_latent(latents: torch.Tensor, mask: torch.Tensor | None = None, eps: float = 1e-6) -> torch.Tensor:
    """L_KL: KL(N(mu_d, sigma_d^2) || N(0,1)) averaged over the latent dimensions d.

    The processor is deterministic, so there is no per-node posterior as in a
    VAE. What L_compact needs is that the *distribution* of the latents the
    decoder sees matches the N(0, I) it samples from; we fit a diagonal Gaussian
    to the node latents of the frame (per-dimension batch mean ``mu_d`` and
    biased variance ``sigma_d^2`` over the nodes) and use its closed-form KL:
    ``0.5 * (mu^2 + sigma^2 - 1 - log sigma^2)``. Zero iff every dimension has
    mean 0 and variance 1; differentiable; the mean over dimensions keeps its
    scale independent of the latent width.

    Args:
        latents: [N,D] node latents (object nodes).
        mask: optional [N] bool rows to use.
        eps: floor on the variance inside the log.
    """
    if mask is not None:
        latents = latents[mask]
    if latents.shape[0] == 0:
        return latents.sum() * 0.0
    mu = latents.mean(dim=0)
    var = latents.var(dim=0, unbiased=False)
    kl = 0.5 * (mu ** 2 + var - 1.0 - torch.log(var + eps))
    return kl.mean()


# -- collision-aware terms ---------------------------------------------------------------------------------------
# L_ccd and ξ_Random reduce a set of non-negative penetration depths (metres) to a scalar. The paper's form is
# the max over the set; the smoother forms spread the gradient over every offending primitive instead of only
# the deepest one. Depths are divided by a length ``scale`` (the training loop passes the target acceleration's
# std, i.e. the unit L_q's errors are measured in) so the weights are dimensionless.
REDUCTIONS = ("max", "mean", "sum_squares")


def reduce_depths(depths: torch.Tensor, form: str = "max", scale: float = 1.0, num_nodes: int = 1) -> torch.Tensor:
    """Reduce depths [K] (m, >= 0) to a scalar.

    * ``max``: ``max_k d_k / scale`` (the paper's ξ = max(D));
    * ``mean``: ``mean_k d_k / scale`` over the K offending primitives;
    * ``sum_squares``: ``sum_k (d_k / scale)^2 / num_nodes`` (a penetration costs what a prediction error of the
      same size costs in L_q, which is a per-node mean of squared normalised errors).

    An empty set gives 0 (with a zero gradient when ``depths`` is part of a graph).
    """
    if form not in REDUCTIONS:
        raise ValueError(f"unknown reduction {form!r}; valid: {', '.join(REDUCTIONS)}")
    if depths.numel() == 0:
        return depths.sum() * 0.0
    d = depths / scale
    if form == "max":
        return d.max()
    if form == "mean":
        return d.mean()
    return (d * d).sum() / max(int(num_nodes), 1)


def loss_ccd(depths: dict[str, torch.Tensor], form: str = "max", scale: float = 1.0,
             num_nodes: int = 1) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """L_ccd = ξ_VF + ξ_EE (paper eq. 4-8) from the crossing depths of one step.

    Args:
        depths: ``{'vertex_face': [Kvf], 'edge_edge': [Kee]}`` wrong-side depths at t+1 (m) of the object/tool
            primitive pairs that cross during t -> t+1, as given by
            :meth:`colgnn_core.collision.CollisionDetector.crossing_depths_torch` (differentiable w.r.t. the
            predicted positions).
        form, scale, num_nodes: see :func:`reduce_depths`.

    Returns:
        ``(L_ccd, ξ_VF, ξ_EE)``.
    """
    vf = reduce_depths(depths["vertex_face"], form, scale, num_nodes)
    ee = reduce_depths(depths["edge_edge"], form, scale, num_nodes)
    return vf + ee, vf, ee


def sdf_violation(tool, points: torch.Tensor, pose, threshold: float) -> torch.Tensor:
    """``max(Δ - SDF_tool(x), 0)`` [N] (m) for world points [N,3] against the tool at ``pose`` [7]."""
    pose_t = pose if isinstance(pose, torch.Tensor) else torch.as_tensor(pose, dtype=points.dtype)
    return torch.relu(threshold - tool.sdf_torch(points, pose_t))


def xi_random(tool, x_random: torch.Tensor, pose_next, threshold: float, form: str = "max", scale: float = 1.0,
              mask: torch.Tensor | None = None) -> torch.Tensor:
    """ξ_Random (paper eq. 10): SDF violation of the positions decoded from random latents z ~ N(0, I).

    Args:
        tool: the scene's :class:`~colgnn_core.geometry.tools.Tool` (its analytic SDF is differentiable).
        x_random: [N,3] positions at t+1 decoded from random latents (m).
        pose_next: [7] tool pose at t+1.
        threshold: Δ (m), the collision-free margin.
        form, scale: see :func:`reduce_depths`; ``mean`` averages over the violating nodes only, ``sum_squares``
            divides by the number of (masked) nodes.
        mask: optional [N] bool nodes to use (free nodes: pinned ones cannot move).
    """
    if mask is not None:
        x_random = x_random[mask]
    v = sdf_violation(tool, x_random, pose_next, threshold)
    if form == "mean":
        v = v[v > 0]  # empty when nothing violates: reduce_depths gives 0 with a zero gradient
    return reduce_depths(v, form, scale, num_nodes=x_random.shape[0])


def unit_normals(X: torch.Tensor, faces: torch.Tensor) -> torch.Tensor:
    """Unit normals [F,3] of the triangles ``faces`` [F,3] (int64) of positions X [N,3] (m)."""
    a, b, c = X[faces[:, 0]], X[faces[:, 1]], X[faces[:, 2]]
    n = torch.linalg.cross(b - a, c - a)
    return n / n.norm(dim=1).clamp_min(torch.finfo(X.dtype).tiny)[:, None]


def flip_hinge(x_pred: torch.Tensor, faces: torch.Tensor, rest_normals: torch.Tensor, rotation: torch.Tensor,
               min_cos: float) -> torch.Tensor:
    """L_valid: sum over triangles of ``max(min_cos - cos, 0)``, cos between a triangle's predicted normal, turned
    into the rest frame by ``rotation``, and its rest normal. A flipped triangle (cos <= 0, the validity test)
    costs at least ``min_cos``; one within arccos(min_cos) of its rest orientation costs nothing.

    Args:
        x_pred: [N,3] predicted positions at t+1 (m), differentiable.
        faces: [F,3] int64 surface triangles indexing x_pred (outward).
        rest_normals: [F,3] their unit rest normals.
        rotation: [3,3] the best rotation of the *target* surface onto the rest
            (:func:`~colgnn_core.collision.surface_validity.best_rotation`, no gradient): the frame the object
            rests in, whatever it rolls to, as the validity test aligns it.
        min_cos: cosine below which a triangle costs (the IPC truth stays above 0.19; 0.1 leaves it free).

    A sum, not a mean: a few flipped triangles among thousands must count against L_q's per-node mean.
    """
    n = unit_normals(x_pred, faces)
    cos = (n @ rotation.T * rest_normals).sum(dim=1)
    return torch.relu(min_cos - cos).sum()


@dataclass(frozen=True)
class SurfaceRest:
    """The rest surface that L_valid measures against: faces [F,3] (graph ids, int64 tensor), their unit rest
    normals [F,3], and the surface's graph ids [S] with their rest positions [S,3] (numpy, m) for the alignment.
    The rest is the settled one (the truth's frame 0), as in the validity test."""

    faces: torch.Tensor
    normals: torch.Tensor
    ids: np.ndarray
    rest: np.ndarray

    @classmethod
    def of(cls, surface_faces: np.ndarray, rest: np.ndarray) -> "SurfaceRest":
        """From the graph's surface faces [F,3] and its settled rest [N,3] (m)."""
        faces = torch.as_tensor(np.asarray(surface_faces, dtype=np.int64))
        rest = torch.as_tensor(np.asarray(rest, dtype=np.float64))
        ids = np.unique(np.asarray(surface_faces))
        return cls(faces, unit_normals(rest, faces), ids, rest.numpy()[ids])

    def loss(self, x_pred: torch.Tensor, x_target: torch.Tensor, min_cos: float) -> torch.Tensor:
        """L_valid of the prediction ``x_pred`` [N,3], in the frame that aligns the target [N,3] with the rest."""
        target = x_target.detach().numpy()[self.ids]
        q = torch.as_tensor(best_rotation(target, self.rest), dtype=x_pred.dtype)
        return flip_hinge(x_pred, self.faces, self.normals.to(x_pred.dtype), q, min_cos)
