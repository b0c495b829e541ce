"""The training loop: one stage of optimizer steps driven by a method's hooks."""

from __future__ import annotations

import dataclasses
import math
import os
import time
from collections import deque
from collections.abc import Callable
from concurrent.futures import Future, ThreadPoolExecutor
from dataclasses import dataclass

import torch

from harness.common.device import autocast
from harness.common.errors import NonFiniteLoss
from harness.common.progress import Progress
from harness.data.datasets import batch_to
from harness.train.optim import ClippedAdamW, contiguous_parameters
from methods import Method, TaskContext


@dataclass(frozen=True)
class TrainSettings:
    steps: int
    batch_size: int
    lr: float
    weight_decay: float = 0.0
    grad_clip: float = 1.0
    betas: tuple[float, float] = (0.9, 0.999)
    eps: float = 1e-8


@dataclass(frozen=True)
class TrainResult:
    final_loss: float  # mean per-sample loss over the last 10% of steps
    steps: int  # the steps taken: fewer than planned when `after_step` stopped the stage


StepLogger = Callable[[int, dict[str, float]], None]


@dataclass(frozen=True)
class Snapshots:
    """Where a long stage keeps its progress, so that a killed process resumes mid-stage rather
    than from the stage's start (a 52,000-step LIBERO base; a pi0 base longer than a GPU lease).

    A snapshot holds the weights, the optimizer's moments, the generator's state, the step and
    the recent losses, so the resumed stage is the uninterrupted one, step for step: the step
    that takes one samples its next batch after it, not ahead of it on the prefetch thread. A
    method's own state is not in it; only stages of a stateless method (the foundation's) use
    it, and stream stages resume from their stage's start."""
    load: Callable[[], dict | None]  # the last snapshot, or None
    save: Callable[[dict], None]  # written whole or not at all
    every_seconds: float  # wall time between snapshots


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
    after_step: Callable[[int], bool | None] | None = None,
    snapshots: Snapshots | None = None, progress: str = "",
) -> TrainResult:
    """Fine-tune `ctx.policy` on `ctx.data` for `settings.steps` steps with `method`.

    The optimizer is fresh each stage (the usual continual-learning protocol): nothing of an
    earlier task's optimizer state leaks into the next. The next batch is sampled on a second
    thread while this step's backward and optimizer step run; `generator` is drawn from in the
    same order as without it (the batch, then the forward's noise and times), so results do not
    depend on the overlap.

    The stage trains where the policy's parameters are: off the CPU, the stage's data moves
    there once, batches that a method draws elsewhere (a CPU buffer) follow, and the forward
    and the method's loss run under bf16 autocast. `generator` stays a CPU generator.

    A method that loads its stages' weights instead of training (`method.trains` false) gets
    its hooks and no step.

    `after_step(steps_done)` runs after every step (learning curves, matched-target checks); a
    true return ends the stage there. With `log`, every step also logs the share of parameters
    whose Adam denominator is set by eps rather than by the gradient (`optim/frac_eps_dominated`,
    sqrt(v_hat) < eps): where a small loss scale makes Adam's step shrink (issue 36).

    With `progress` (a description, "foundation seed 0"), the steps show as progress
    (harness.common.progress).

    With `snapshots`, the stage starts from the last snapshot, if any, and takes one whenever
    `snapshots.every_seconds` have passed since the last (see `Snapshots`).
    """
    policy = ctx.policy
    device = next(policy.parameters()).device
    if device.type != "cpu":
        ctx = dataclasses.replace(ctx, data=ctx.data.to(device))
    policy.train()
    method.before_task(ctx)  # first: a method may freeze parameters here
    params = [p for p in policy.parameters() if p.requires_grad]
    tail = max(1, settings.steps // 10)
    recent: deque[float] = deque(maxlen=tail)  # the last steps' mean losses (it may stop early)
    done = 0
    resumed = snapshots.load() if snapshots is not None else None
    if resumed is not None:
        policy.load_state_dict(resumed["policy"])
        generator.set_state(resumed["generator"])
        recent.extend(resumed["recent"])
        done = resumed["step"]
    last_snapshot = time.monotonic()
    timer = timer if timer is not None else _NoTimer()
    # Only with a core to spare: beside as many intra-op threads as cores, a third thread makes
    # them wait on each other (a default step took 2x as long with two threads on two cores).
    prefetch = method.prefetch_batches and torch.get_num_threads() < (os.cpu_count() or 1)
    steps = settings.steps if method.trains else 0
    with contiguous_parameters(params) as flat, ThreadPoolExecutor(1) as data_thread, \
            Progress(steps, progress, enabled=bool(progress), initial=done) as shown:
        optimizer = ClippedAdamW(flat, settings.lr, settings.weight_decay, settings.grad_clip,
                              settings.betas, settings.eps)
        if resumed is not None:
            optimizer.load_state_dict(resumed["optimizer"])
        next_batch: Future | None = None
        for step in range(done, steps):
            timer.mark("other")
            if next_batch is None:
                batch = method.sample_batch(ctx, settings.batch_size, generator)
            else:
                batch, next_batch = next_batch.result(), None
            if device.type != "cpu":
                batch = batch_to(batch, device, non_blocking=True)
            timer.mark("data")
            with autocast(device):
                per_sample = policy(batch, generator=generator)
                loss, stats = method.loss(per_sample, batch, policy)
            timer.mark("forward")
            snapshot_due = (snapshots is not None and step + 1 < settings.steps
                            and time.monotonic() - last_snapshot >= snapshots.every_seconds)
            if prefetch and step + 1 < settings.steps and not snapshot_due:
                next_batch = data_thread.submit(method.sample_batch, ctx, settings.batch_size,
                                                generator)
            if not torch.isfinite(loss):
                raise NonFiniteLoss(
                    f"non-finite loss ({loss.item()}) in method {method.name!r} at stage "
                    f"{ctx.stage} ({ctx.task}), step {step}; the last finished stage is kept"
                )
            loss.backward()
            method.after_backward(policy)  # SFT's does nothing: a projection or a mask goes here
            timer.mark("backward")
            optimizer.step()  # clips, updates, zeroes the gradient
            method.after_step(policy)
            timer.mark("optimizer")
            mean_loss = per_sample.detach().mean().item()
            recent.append(mean_loss)
            if log is not None:
                log(step, {"train/flow_loss": mean_loss, "train/objective": loss.item(),
                           "optim/frac_eps_dominated": optimizer.frac_eps_dominated(), **stats})
            done = step + 1
            shown.update()
            if after_step is not None and after_step(done):
                break
            if snapshot_due:
                snapshots.save({"step": done, "policy": policy.state_dict(),
                                "optimizer": optimizer.state_dict(),
                                "generator": generator.get_state(), "recent": list(recent)})
                last_snapshot = time.monotonic()
    method.after_task(ctx)
    policy.eval()
    final = sum(recent) / len(recent) if recent else math.nan
    return TrainResult(final_loss=final, steps=done)
