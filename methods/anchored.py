"""The shared shape of L2 and EWC: a quadratic pull towards anchor weights theta*,

    loss = mean(l) + lambda/2 * sum_j w_j (theta_j - theta*_j)^2

with w = 1 (L2) or a per-weight importance (EWC's Fisher). Subclasses decide when the anchor
and the importance are taken.
"""

from __future__ import annotations

import torch

from methods.base import Method


class AnchoredMethod(Method):
    def __init__(self, config=None):
        super().__init__(config)
        self.anchor: dict[str, torch.Tensor] | None = None
        self.importance: dict[str, torch.Tensor] | None = None  # None: every weight counts 1

    def penalty(self, policy: torch.nn.Module) -> torch.Tensor:
        total = torch.zeros(())
        for n, p in policy.named_parameters():
            if self.importance is not None and n not in self.importance:
                continue  # frozen when the importance was measured: it carries none
            sq = (p - self.anchor[n]) ** 2
            total = total + (sq if self.importance is None else self.importance[n] * sq).sum()
        return total

    def loss(self, per_sample, batch, policy):
        penalty = self.penalty(policy)
        return (per_sample.mean() + 0.5 * self.config.strength * penalty,
                {f"{self.name}/penalty": penalty.item()})

    def state_dict(self):
        return {"anchor": self.anchor, "importance": self.importance}

    def load_state_dict(self, state):
        self.anchor, self.importance = state["anchor"], state["importance"]
