"""Online EWC (Schwarz et al., 2018) with a per-sample empirical Fisher.

    F <- gamma * F + mean_i (grad_theta l_i)^2        after stage 0 (foundation data) and each task
    loss = mean(l) + lambda/2 * sum_j F_j (theta_j - theta*_j)^2,   theta* = weights after the task

The Fisher diagonal is the mean of squared per-sample gradients (torch.func vmap), not the square
of a batch gradient, which would underestimate it by the batch size's averaging.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import torch
from annotated_types import Ge, Interval

from methods import register_method
from methods.anchored import AnchoredMethod, importance_batch, per_sample_gradient_mean
from methods.base import MethodConfig, TaskContext, snapshot


@dataclass
class EWCConfig(MethodConfig):
    strength: Annotated[float, Ge(0)] = 1e4  # lambda (sweep: docs/methods.md)
    # gamma: how much of the earlier Fisher survives each task
    decay: Annotated[float, Interval(ge=0, le=1)] = 0.9
    fisher_samples: Annotated[int, Ge(1)] = 1024
    fisher_batch: Annotated[int, Ge(1)] = 128


def per_sample_fisher(policy: torch.nn.Module, batch: dict, chunk: int = 128) -> dict[str, torch.Tensor]:
    """Mean over the batch of squared per-sample gradients of the loss, parameter by parameter.

    `batch` must fix "noise" and "time" so each sample's loss is a function of the weights only.
    """
    return per_sample_gradient_mean(policy, batch, lambda p, one: p(one).squeeze(0),
                                    torch.square, chunk)


@register_method
class OnlineEWC(AnchoredMethod):
    name = "ewc"
    Config = EWCConfig

    @property
    def fisher(self) -> dict[str, torch.Tensor] | None:
        """The online Fisher: the importance of each weight in the pull to the anchor."""
        return self.importance

    def after_task(self, ctx: TaskContext) -> None:
        c = self.config
        batch = importance_batch(ctx.data, ctx.policy, c.fisher_samples, seed=2000 + ctx.stage)
        new = per_sample_fisher(ctx.policy, batch, c.fisher_batch)
        if self.importance is None:
            self.importance = new
        else:
            self.importance = {k: c.decay * self.importance[k] + new[k] for k in new}
        self.anchor = snapshot(ctx.policy)
