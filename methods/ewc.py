"""Online EWC (Schwarz et al., 2018) with a per-sample empirical Fisher.

    F <- gamma * F + mean_i (grad_theta l_i)^2        after stage 0 (foundation data) and each task
    loss = mean(l) + lambda/2 * sum_j F_j (theta_j - theta*_j)^2,   theta* = weights after the task

The Fisher diagonal is the mean of squared per-sample gradients (torch.func vmap), not the square
of a batch gradient, which would underestimate it by the batch size's averaging.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch.func import functional_call, grad, vmap

from methods import register_method
from methods.anchored import AnchoredMethod
from methods.base import MethodConfig, TaskContext, snapshot


@dataclass
class EWCConfig(MethodConfig):
    strength: float = 1e4  # lambda (sweep: docs/methods.md)
    decay: float = 0.9  # gamma: how much of the earlier Fisher survives each task
    fisher_samples: int = 1024
    fisher_batch: int = 128


def per_sample_fisher(policy: torch.nn.Module, batch: dict, chunk: int = 128) -> dict[str, torch.Tensor]:
    """Mean over the batch of squared per-sample gradients, parameter by parameter.

    `batch` must fix "noise" and "time" so each sample's loss is a function of the weights only.
    """
    params = {n: p.detach() for n, p in policy.named_parameters() if p.requires_grad}
    buffers = {n: b for n, b in policy.named_buffers()}

    def sample_loss(p, sample):
        one = {k: v.unsqueeze(0) for k, v in sample.items()}
        return functional_call(policy, (p, buffers), (one,)).squeeze(0)

    per_sample_grads = vmap(grad(sample_loss), in_dims=(None, 0))
    n = next(iter(batch.values())).shape[0]
    total = {k: torch.zeros_like(v) for k, v in params.items()}
    for start in range(0, n, chunk):
        part = {k: v[start:start + chunk] for k, v in batch.items()}
        for k, g in per_sample_grads(params, part).items():
            total[k] += (g ** 2).sum(0)
    return {k: v / n for k, v in total.items()}


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
        g = torch.Generator().manual_seed(2000 + ctx.stage)
        idx = torch.randperm(len(ctx.data), generator=g)[: c.fisher_samples]
        batch = {k: v for k, v in ctx.data.batch(idx).items()
                 if k not in ("index", "task_index")}
        batch["noise"] = torch.randn(batch["actions"].shape, generator=g)
        batch["time"] = ctx.policy.sample_time(len(idx), g)
        new = per_sample_fisher(ctx.policy, batch, c.fisher_batch)
        if self.importance is None:
            self.importance = new
        else:
            self.importance = {k: c.decay * self.importance[k] + new[k] for k in new}
        self.anchor = snapshot(ctx.policy)
