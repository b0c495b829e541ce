"""Weight merging with the foundation after every task (WiSE-FT, Wortsman et al., 2022):

    theta <- (1 - alpha) * theta_0 + alpha * theta_task        after each stream task

theta_0 is the foundation's weights (taken after stage 0, as L2 takes its reference) and
theta_task the weights plain SFT reached on the task, starting from the previous merged model.
alpha = 1 is SFT; alpha = 0 returns the foundation exactly and learns nothing. A sweep over alpha
traces a retention/plasticity curve (`make sweep METHOD=merge GRID="alpha=0.25,0.5,0.75,1.0"`).
Buffers (the normalization statistics) are the foundation's throughout and are not merged.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import torch
from annotated_types import Interval

from methods import register_method
from methods.base import Method, MethodConfig, TaskContext, snapshot


@dataclass
class MergeConfig(MethodConfig):
    # weight of the fine-tuned model (WiSE-FT's; mw-quick sweep, docs/methods.md)
    alpha: Annotated[float, Interval(ge=0, le=1)] = 0.75


@register_method
class WeightMerge(Method):
    name = "merge"
    Config = MergeConfig

    def __init__(self, config: MergeConfig | None = None):
        super().__init__(config)
        self.theta0: dict[str, torch.Tensor] | None = None

    @torch.no_grad()
    def after_task(self, ctx: TaskContext) -> None:
        if ctx.stage == 0:  # the foundation's weights: the end every merge interpolates from
            self.theta0 = snapshot(ctx.policy)
            return
        for n, p in ctx.policy.named_parameters():
            # lerp is exact at both ends: theta_0 at alpha = 0, theta_task at alpha = 1
            p.copy_(torch.lerp(self.theta0[n].to(p.device), p, self.config.alpha))

    def state_dict(self):
        return {"theta0": self.theta0}

    def load_state_dict(self, state):
        self.theta0 = state["theta0"]
