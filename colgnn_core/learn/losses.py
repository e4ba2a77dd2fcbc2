"""Training losses that need no collision code: the data term L_q and the latent KL term.

L_ccd and ξ_Random (the collision and SDF penalties) are built on the collision
module's torch filter / narrow phase and the tool SDF; they live beside these
once that code exists.
"""

from __future__ import annotations

import torch


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
