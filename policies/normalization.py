"""Mean/std normalization with a floor on each std and clipping.

Statistics come from the foundation data and travel with the checkpoint. The floor and the clip
keep a stream task whose states lie outside the foundation range (a dimension that was constant
there, say) from inflating the loss by orders of magnitude.
"""

from __future__ import annotations

import torch
from torch import nn


class Normalizer(nn.Module):
    def __init__(self, dim: int, std_floor: float, clip: float):
        super().__init__()
        self.register_buffer("mean", torch.zeros(dim))
        self.register_buffer("std", torch.ones(dim))
        self.std_floor = std_floor
        self.clip = clip

    @torch.no_grad()
    def fit(self, x: torch.Tensor) -> None:
        """Set statistics from rows of `x` ([N, dim])."""
        self.mean.copy_(x.mean(0))
        self.std.copy_(x.std(0, unbiased=False).clamp_min(self.std_floor))

    def normalize(self, x: torch.Tensor) -> torch.Tensor:
        return ((x - self.mean) / self.std).clamp(-self.clip, self.clip)

    def unnormalize(self, x: torch.Tensor) -> torch.Tensor:
        return x * self.std + self.mean
