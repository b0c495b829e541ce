"""Memory Aware Synapses (Aljundi et al., 2018): a weight matters as much as the policy's output
moves when it does.

    Omega_j = mean_i | d ||F(x_i)||^2 / d theta_j |        F: the predicted velocity [H, A]
    Omega  <- decay * Omega + Omega_new                      after stage 0 and each task
    loss   = mean(l) + lambda/2 * sum_j Omega_j (theta_j - theta*_j)^2,   theta* = weights then

F is evaluated at the flow-matching inputs x_t, with (t, noise) drawn as in training, on up to
`importance_samples` of the stage's samples; the gradients are per sample (the absolute value of a
batch gradient would let samples cancel). Needing no labels, the importance is of the output, not
of the loss: EWC's Fisher with the loss's gradient replaced by the output norm's. The importance
accumulates online over the foundation and every finished task; decay = 1 is the paper's sum.
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
class MASConfig(MethodConfig):
    strength: Annotated[float, Ge(0)] = 1.0  # lambda (Aljundi et al.'s 1)
    # how much of the earlier importance survives each task (1: the sum)
    decay: Annotated[float, Interval(ge=0, le=1)] = 1.0
    importance_samples: Annotated[int, Ge(1)] = 1024
    importance_batch: Annotated[int, Ge(1)] = 128


def output_sensitivity(policy: torch.nn.Module, batch: dict, chunk: int = 128
                       ) -> dict[str, torch.Tensor]:
    """mean_i |d ||v(x_i)||^2 / d theta| per weight; `batch` fixes "noise" and "time"."""
    return per_sample_gradient_mean(
        policy, batch, lambda p, one: p.predicted_velocity(one).square().sum(), torch.abs, chunk)


@register_method
class MAS(AnchoredMethod):
    name = "mas"
    Config = MASConfig

    def after_task(self, ctx: TaskContext) -> None:
        c = self.config
        batch = importance_batch(ctx.data, ctx.policy, c.importance_samples, seed=3000 + ctx.stage)
        new = output_sensitivity(ctx.policy, batch, c.importance_batch)
        if self.importance is None:
            self.importance = new
        else:
            self.importance = {k: c.decay * self.importance[k] + new[k] for k in new}
        self.anchor = snapshot(ctx.policy)
