"""The shared shape of L2 and EWC: a quadratic pull towards anchor weights theta*,

    loss = mean(l) + lambda/2 * sum_j w_j (theta_j - theta*_j)^2

with w = 1 (L2) or a per-weight importance (EWC's Fisher, MAS's output sensitivity). Subclasses
decide when the anchor and the importance are taken.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch.func import functional_call, grad, vmap

from methods.base import Method, TaskContext
from policies.base import noise_shape, randn_from


class _Call(torch.nn.Module):
    """`fn(policy, batch)` as a module's forward, so torch.func can call any policy method."""

    def __init__(self, policy: torch.nn.Module, fn: Callable):
        super().__init__()
        self.policy, self.fn = policy, fn

    def forward(self, batch):
        return self.fn(self.policy, batch)


def per_sample_gradient_mean(
    policy: torch.nn.Module, batch: dict, value: Callable, transform: Callable, chunk: int = 128,
) -> dict[str, torch.Tensor]:
    """Mean over the batch of transform(d value(policy, sample) / d theta), per trainable weight.

    `value(policy, one_sample_batch)` is a scalar; per-sample gradients come from torch.func's
    vmap, so EWC's squared gradients and MAS's absolute ones are of each sample, not of the
    batch mean. `batch` must fix "noise" and "time" so each value depends on the weights only.
    A policy whose forward leaves tensors (`supports_vmap = False`: LeRobot's processors
    tokenize text) gets one backward pass a sample instead, with the same result.
    """
    if not getattr(policy, "supports_vmap", True):
        return _looped_gradient_mean(policy, batch, value, transform)
    call = _Call(policy, value)
    params = {n: p.detach() for n, p in call.named_parameters() if p.requires_grad}
    buffers = dict(call.named_buffers())

    def sample_value(p, sample):
        return functional_call(call, (p, buffers), ({k: v.unsqueeze(0) for k, v in sample.items()},))

    per_sample_grads = vmap(grad(sample_value), in_dims=(None, 0))
    n = next(iter(batch.values())).shape[0]
    total = {k: torch.zeros_like(v) for k, v in params.items()}
    for start in range(0, n, chunk):
        part = {k: v[start:start + chunk] for k, v in batch.items()}
        for k, g in per_sample_grads(params, part).items():
            total[k] += transform(g).sum(0)
    return {k.removeprefix("policy."): v / n for k, v in total.items()}


def _looped_gradient_mean(policy, batch: dict, value: Callable, transform: Callable
                          ) -> dict[str, torch.Tensor]:
    """per_sample_gradient_mean one sample at a time (a weight the sample does not reach gets a
    zero gradient, as vmap gives it)."""
    named = [(n, p) for n, p in policy.named_parameters() if p.requires_grad]
    total = {n: torch.zeros_like(p) for n, p in named}
    n = next(iter(batch.values())).shape[0]
    for i in range(n):
        one = {k: v[i:i + 1] for k, v in batch.items()}
        grads = torch.autograd.grad(value(policy, one), [p for _, p in named], allow_unused=True)
        for (name, _), g in zip(named, grads):
            if g is not None:
                total[name] += transform(g.detach())
    return {k: v / n for k, v in total.items()}


def importance_batch(ctx_data, policy: torch.nn.Module, samples: int, seed: int) -> dict:
    """Up to `samples` of a stage's samples with fixed (noise, time) draws, for an importance."""
    g = torch.Generator().manual_seed(seed)
    idx = torch.randperm(len(ctx_data), generator=g)[:samples]
    batch = {k: v for k, v in ctx_data.batch(idx).items() if k not in ("index", "task_index")}
    batch["noise"] = randn_from(noise_shape(policy, len(idx)), g, batch["actions"].device)
    batch["time"] = policy.sample_time(len(idx), g)
    return batch


class AnchoredMethod(Method):
    def __init__(self, config=None):
        super().__init__(config)
        self.anchor: dict[str, torch.Tensor] | None = None
        self.importance: dict[str, torch.Tensor] | None = None  # None: every weight counts 1

    def before_task(self, ctx: TaskContext) -> None:
        """The anchor and importance where the policy trains (a checkpoint loads them on the CPU)."""
        device = next(ctx.policy.parameters()).device
        for name in ("anchor", "importance"):
            kept = getattr(self, name)
            if kept is not None:
                setattr(self, name, {k: v.to(device) for k, v in kept.items()})

    def penalty(self, policy: torch.nn.Module) -> torch.Tensor:
        total = torch.zeros((), device=next(policy.parameters()).device)
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
