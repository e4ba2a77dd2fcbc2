"""Online feature normalizer (as in MeshGraphNets' ``normalization.py``).

Statistics (count, sum, sum of squares per feature) are accumulated during
training, in float64, for up to ``max_accumulations`` calls; afterwards they
are frozen. They live in module buffers, so they are part of the owning
model's ``state_dict`` and hence of the checkpoint.

Differences from MGN, both for robustness: an empty normalizer (count 0) is the
identity (MGN divides by ``std_epsilon``, which turns the first unseen edge set,
e.g. world edges when the tool never came close, into huge values), and the
variance is clamped at 0 before the square root (round-off).
"""

from __future__ import annotations

import torch
from torch import nn


class Normalizer(nn.Module):
    """Elementwise ``(x - mean) / max(std, std_epsilon)`` over the last dimension of size ``size``."""

    def __init__(self, size: int, max_accumulations: int = 10**6, std_epsilon: float = 1e-8):
        super().__init__()
        self.size = size
        self.max_accumulations = max_accumulations
        self.std_epsilon = std_epsilon
        self.register_buffer("acc_count", torch.zeros((), dtype=torch.float64))
        self.register_buffer("num_accumulations", torch.zeros((), dtype=torch.float64))
        self.register_buffer("acc_sum", torch.zeros(size, dtype=torch.float64))
        self.register_buffer("acc_sum_squared", torch.zeros(size, dtype=torch.float64))

    @torch.no_grad()
    def accumulate(self, x: torch.Tensor) -> None:
        """Add the rows of ``x`` [B,size] to the statistics (no-op once frozen or when B = 0)."""
        x = x.detach().reshape(-1, self.size).to(torch.float64)
        if x.shape[0] == 0 or self.num_accumulations.item() >= self.max_accumulations:
            return
        self.acc_sum += x.sum(0)
        self.acc_sum_squared += (x * x).sum(0)
        self.acc_count += x.shape[0]
        self.num_accumulations += 1

    def mean(self) -> torch.Tensor:
        """[size] float64."""
        return self.acc_sum / self.acc_count.clamp(min=1.0)

    def std(self) -> torch.Tensor:
        """[size] float64, at least ``std_epsilon``; all ones while nothing has been accumulated."""
        if self.acc_count.item() == 0:
            return torch.ones_like(self.acc_sum)
        var = self.acc_sum_squared / self.acc_count - self.mean() ** 2
        return var.clamp(min=0.0).sqrt().clamp(min=self.std_epsilon)

    def forward(self, x: torch.Tensor, accumulate: bool = False) -> torch.Tensor:
        """Normalise ``x`` [...,size] (accumulating first if asked); keeps ``x``'s dtype."""
        if accumulate:
            self.accumulate(x)
        return (x - self.mean().to(x.dtype)) / self.std().to(x.dtype)

    def inverse(self, y: torch.Tensor) -> torch.Tensor:
        """Undo :meth:`forward`: ``y * std + mean``; keeps ``y``'s dtype."""
        return y * self.std().to(y.dtype) + self.mean().to(y.dtype)

    def extra_repr(self) -> str:
        return f"size={self.size}, max_accumulations={self.max_accumulations}, std_epsilon={self.std_epsilon}"
