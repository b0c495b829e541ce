"""The training loop: one stage of optimizer steps driven by a method's hooks."""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import torch

from harness.errors import NonFiniteLoss
from methods import Method, TaskContext


@dataclass(frozen=True)
class TrainSettings:
    steps: int
    batch_size: int
    lr: float
    weight_decay: float = 0.0
    grad_clip: float = 1.0


@dataclass(frozen=True)
class TrainResult:
    final_loss: float  # mean per-sample loss over the last 10% of steps
    steps: int


StepLogger = Callable[[int, dict[str, float]], None]


class PhaseTimer:
    """Wall time per phase of the training step, for `make bench-train`."""

    def __init__(self):
        self.seconds: dict[str, float] = {}
        self._last = time.perf_counter()

    def mark(self, phase: str) -> None:
        now = time.perf_counter()
        self.seconds[phase] = self.seconds.get(phase, 0.0) + now - self._last
        self._last = now


class _NoTimer:
    def mark(self, phase: str) -> None:
        pass


def train_stage(
    ctx: TaskContext, method: Method, settings: TrainSettings, generator: torch.Generator,
    log: StepLogger | None = None, timer: PhaseTimer | None = None,
    after_step: Callable[[int], None] | None = None,
) -> TrainResult:
    """Fine-tune `ctx.policy` on `ctx.data` for `settings.steps` steps with `method`.

    The optimizer is fresh each stage (the usual continual-learning protocol): nothing of an
    earlier task's optimizer state leaks into the next.
    """
    policy = ctx.policy
    policy.train()
    method.before_task(ctx)  # first: a method may freeze parameters here
    params = [p for p in policy.parameters() if p.requires_grad]
    # fused: one kernel for all parameters, a third of the for-loop version's time on a CPU
    optimizer = torch.optim.AdamW(params, lr=settings.lr, weight_decay=settings.weight_decay,
                                  fused=True)
    tail = max(1, settings.steps // 10)
    tail_losses: list[float] = []
    timer = timer if timer is not None else _NoTimer()
    for step in range(settings.steps):
        timer.mark("other")
        batch = method.sample_batch(ctx, settings.batch_size, generator)
        timer.mark("data")
        per_sample = policy(batch, generator=generator)
        loss, stats = method.loss(per_sample, batch, policy)
        timer.mark("forward")
        if not torch.isfinite(loss):
            raise NonFiniteLoss(
                f"non-finite loss ({loss.item()}) in method {method.name!r} at stage {ctx.stage} "
                f"({ctx.task}), step {step}; the last finished stage is kept"
            )
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        timer.mark("backward")
        if settings.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(params, settings.grad_clip, foreach=True)
        optimizer.step()
        method.after_step(policy)
        timer.mark("optimizer")
        mean_loss = per_sample.detach().mean().item()
        if step >= settings.steps - tail:
            tail_losses.append(mean_loss)
        if log is not None:
            log(step, {"train/flow_loss": mean_loss, "train/objective": loss.item(), **stats})
        if after_step is not None:
            after_step(step + 1)  # steps done so far, e.g. for learning-curve evaluations
    method.after_task(ctx)
    policy.eval()
    final = sum(tail_losses) / len(tail_losses) if tail_losses else math.nan
    return TrainResult(final_loss=final, steps=settings.steps)
