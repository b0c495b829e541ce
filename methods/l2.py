"""L2 towards the foundation weights: loss + lambda/2 * ||theta - theta_0||^2."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from methods import register_method
from methods.base import Method, MethodConfig, TaskContext


@dataclass
class L2Config(MethodConfig):
    strength: float = 1.0  # lambda


@register_method
class L2ToReference(Method):
    name = "l2"
    Config = L2Config

    def __init__(self, config: L2Config | None = None):
        super().__init__(config)
        self.reference: dict[str, torch.Tensor] | None = None

    def after_task(self, ctx: TaskContext) -> None:
        if ctx.stage == 0:  # the foundation weights are the reference for the whole stream
            self.reference = {n: p.detach().clone() for n, p in ctx.policy.named_parameters()}

    def penalty(self, policy: torch.nn.Module) -> torch.Tensor:
        return sum(((p - self.reference[n]) ** 2).sum() for n, p in policy.named_parameters())

    def loss(self, per_sample, batch, policy):
        penalty = self.penalty(policy)
        return per_sample.mean() + 0.5 * self.config.strength * penalty, {"l2/penalty": penalty.item()}

    def state_dict(self):
        return {"reference": self.reference}

    def load_state_dict(self, state):
        self.reference = state["reference"]
