"""Averaged gradient episodic memory, A-GEM (Chaudhry et al., 2019), as in LIBERO's lifelong AGEM.

A memory keeps `memory_per_task` samples of every finished stage (the foundation's tasks
included). At every step, with g the batch's gradient and g_ref the gradient of the loss on a
batch drawn from the memory:

    g <- g - (g . g_ref / g_ref . g_ref) g_ref     if g . g_ref < 0,  else g unchanged

so that no step increases the memory's loss to first order.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import torch
from annotated_types import Ge, doc

from harness.data.datasets import TrainingData, batch_to
from methods import register_method
from methods.base import Method, MethodConfig, TaskContext


@dataclass
class AGEMConfig(MethodConfig):
    memory_per_task: Annotated[int, Ge(1)] = 1000  # samples kept per task (LIBERO's n_memories)
    # memory samples per reference gradient
    memory_batch: Annotated[int, Ge(0), doc("0: the training batch size")] = 0


@torch.no_grad()
def project(grads: list[torch.Tensor], reference: list[torch.Tensor]) -> None:
    """A-GEM's projection, in place: remove from `grads` its component against `reference`.

    Without a branch on the sign (no device sync): the coefficient is min(g . g_ref, 0) / |g_ref|^2,
    so a gradient that does not conflict is left exactly as it was.
    """
    dot = sum((g * r).sum() for g, r in zip(grads, reference))
    norm_sq = sum((r * r).sum() for r in reference)
    coefficient = dot.clamp(max=0.0) / norm_sq.clamp_min(torch.finfo(norm_sq.dtype).tiny)
    for g, r in zip(grads, reference):
        g.sub_(coefficient * r)


@register_method
class AGEM(Method):
    name = "agem"
    Config = AGEMConfig
    uses_past_data = True

    def __init__(self, config: AGEMConfig | None = None):
        super().__init__(config)
        self.memory: TrainingData | None = None
        # Memory batches are drawn in after_backward, on the training thread, from a generator of
        # their own: the training batches (drawn ahead on a second thread) are SFT's.
        self._generator = torch.Generator().manual_seed(0)
        self._batch_size = 0

    def before_task(self, ctx: TaskContext) -> None:
        self._generator.manual_seed(5000 + ctx.stage)

    def sample_batch(self, ctx: TaskContext, batch_size: int, generator: torch.Generator) -> dict:
        self._batch_size = batch_size
        return super().sample_batch(ctx, batch_size, generator)

    def reference_gradient(self, policy: torch.nn.Module, params: list[torch.nn.Parameter]
                           ) -> list[torch.Tensor]:
        """g_ref: the gradient of the mean loss on a memory batch, without touching `.grad`."""
        n = self.config.memory_batch or self._batch_size
        device = params[0].device  # the memory is kept on the CPU
        batch = batch_to(self.memory.sample(n, self._generator), device)
        loss = policy(batch, generator=self._generator).mean()
        grads = torch.autograd.grad(loss, params, allow_unused=True)
        return [torch.zeros_like(p) if g is None else g for p, g in zip(params, grads)]

    def after_backward(self, policy: torch.nn.Module) -> None:
        if self.memory is None:
            return
        params = [p for p in policy.parameters() if p.requires_grad]
        project([p.grad for p in params], self.reference_gradient(policy, params))

    def after_task(self, ctx: TaskContext) -> None:
        """Keep up to `memory_per_task` samples of every task in this stage's data."""
        g = torch.Generator().manual_seed(4000 + ctx.stage)
        kept = ctx.data.per_task_subset(self.config.memory_per_task, g).to("cpu")
        self.memory = kept if self.memory is None else TrainingData.concat([self.memory, kept])

    def state_dict(self):
        return {"memory": self.memory}

    def load_state_dict(self, state):
        self.memory = state["memory"]
