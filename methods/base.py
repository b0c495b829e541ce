"""The fine-tuning method contract: plain SFT, plus the hooks every other method overrides.

The trainer calls, for each task of the stream (and once for the foundation stage):

    before_task(ctx)                  may look at the task's data (ctx.data)
    for each step:
        batch = sample_batch(ctx, batch_size, generator)
        per_sample = policy(batch)    [B] flow-matching losses
        loss, stats = loss(per_sample, batch, policy)
        loss.backward()
        after_backward(policy)        the gradient is in the parameters' .grad: project or mask it
        optimizer.step()
        after_step(policy)
    after_task(ctx)                   what a method keeps (a replay buffer, a Fisher) it takes here

A method sees a task's data only during that task's stage; what it keeps must live in its own
`state_dict`, which the checkpoint of every stage stores. At every stage's evaluation, each task
is rolled out inside `evaluation_view(policy, task, stream)`: a method that keeps per-task
weights (PackNet) shows the policy as it was for that task.
"""

from __future__ import annotations

import contextlib
import dataclasses
from dataclasses import dataclass
from typing import Any, ClassVar

import torch

from harness.data.datasets import TrainingData


@dataclass
class TaskContext:
    """What a method may see of the current stage."""

    stage: int  # 0 is the foundation stage, 1..k the stream tasks
    task: str  # the stream task, or "foundation"
    data: TrainingData  # this stage's training samples, and nothing earlier
    policy: torch.nn.Module
    foundation_loss: float  # the foundation's final training loss, kept in its checkpoint
    steps: int  # optimizer steps planned for this stage


def snapshot(module: torch.nn.Module) -> dict[str, torch.Tensor]:
    """A detached copy of the learned weights (not buffers such as normalization statistics):
    what L2 and EWC anchor to, and what the harness measures updates against."""
    return {n: p.detach().clone() for n, p in module.named_parameters()}


PAST_DATA, REFERENCE_COPY, TASK_IDENTITY = "past data", "reference copy", "task identity at evaluation"
REFERENCE_SHARE = 0.5  # a module holding this share of the policy's parameters is a copy of it


def observed_needs(method: Method, policy: torch.nn.Module, tasks: list[str]) -> list[str]:
    """What `method` keeps after a stage that trained `tasks`, found by looking, not by asking
    its class attributes (a user's method may not set them): "past data" when it holds
    TrainingData with samples of other tasks, "reference copy" when it holds a network with at
    least REFERENCE_SHARE of the policy's parameters that are not the policy's own (a frozen
    copy; an adapter around the policy's layers shares them). Weights kept as a dict of
    tensors (L2's anchor) are neither: they are not a network run in training."""
    own = {p.data_ptr() for p in policy.parameters()}
    size = sum(p.numel() for p in policy.parameters())
    found: list[str] = []
    for value in _held(vars(method), depth=3):
        if isinstance(value, TrainingData) and PAST_DATA not in found:
            held = {value.task_names[i] for i in value.task_index.unique().tolist()}
            if held - set(tasks):
                found.append(PAST_DATA)
        elif isinstance(value, torch.nn.Module) and value is not policy \
                and REFERENCE_COPY not in found:
            extra = sum(p.numel() for p in value.parameters() if p.data_ptr() not in own)
            if size and extra >= REFERENCE_SHARE * size:
                found.append(REFERENCE_COPY)
    return [need for need in (PAST_DATA, REFERENCE_COPY) if need in found]


def _held(value, depth: int):
    """The objects in a method's attributes, through dicts, lists and tuples."""
    if isinstance(value, dict):
        items = value.values()
    elif isinstance(value, (list, tuple)):
        items = value
    else:
        yield value
        return
    if depth > 0:
        for item in items:
            yield from _held(item, depth - 1)


@dataclass
class MethodConfig:
    """Hyperparameters of a method; subclasses extend it with their own fields."""


class Method:
    """Plain supervised fine-tuning: the mean of the per-sample flow-matching losses."""

    name: ClassVar[str] = "sft"
    Config: ClassVar[type[MethodConfig]] = MethodConfig
    # What a method needs beyond the current task's data and the policy; the report marks it, so a
    # reader compares like with like (`needs()` is the tag every run logs).
    uses_past_data: ClassVar[bool] = False  # earlier tasks' samples (a replay buffer, a memory)
    uses_reference_copy: ClassVar[bool] = False  # a frozen copy of the network run in training
    task_aware_eval: ClassVar[bool] = False  # the task's identity when evaluating (task masks)
    # The trainer samples the next batch on a second thread while a step's backward and optimizer
    # step run. A method whose sample_batch reads the policy (loss-based sampling, say) must say
    # False, or it would read weights that are being updated.
    prefetch_batches: ClassVar[bool] = True
    # False for a "method" whose stages load weights made elsewhere (`checkpoints`): the trainer
    # takes no step, and METHOD=all (`method_names`) leaves it out
    trains: ClassVar[bool] = True
    label_omits: ClassVar[tuple[str, ...]] = ()  # hyperparameters its run label never shows

    def __init__(self, config: MethodConfig | None = None):
        self.config = config if config is not None else self.Config()

    @classmethod
    def needs(cls, observed: tuple[str, ...] | list[str] = ()) -> str:
        """What the method needs, as the report prints it: "past data, reference copy", or
        "none" for a method that uses only the current task's data. `observed` adds what
        `observed_needs` found it keeping, whatever its class attributes say."""
        flags = [(cls.uses_past_data, PAST_DATA), (cls.uses_reference_copy, REFERENCE_COPY),
                 (cls.task_aware_eval, TASK_IDENTITY)]
        return ", ".join(name for on, name in flags if on or name in observed) or "none"

    @property
    def label(self) -> str:
        """The run's name before its settings ("consft" in "consft[kappa=0.1]")."""
        return self.name

    def check_setup(self, policy_config, stages: int) -> None:
        """At plan time, with the run's policy config and its number of stream stages: raise a
        ValueError (one line) for a setting that cannot work, before anything runs."""

    # -- hooks -------------------------------------------------------------------------------

    def before_task(self, ctx: TaskContext) -> None:
        """Called before training on a task (stage 0 is the foundation)."""

    def sample_batch(self, ctx: TaskContext, batch_size: int, generator: torch.Generator) -> dict:
        return ctx.data.sample(batch_size, generator)

    def loss(self, per_sample: torch.Tensor, batch: dict, policy: torch.nn.Module
             ) -> tuple[torch.Tensor, dict[str, float]]:
        """Reduce per-sample losses [B] to the scalar to minimise, plus stats to log."""
        return per_sample.mean(), {}

    def after_backward(self, policy: torch.nn.Module) -> None:
        """Called between backward and the optimizer step, with the gradient in each parameter's
        `.grad` (the trainer's `.grad` are views into one flat buffer: change them in place)."""

    def after_step(self, policy: torch.nn.Module) -> None:
        """Called after every optimizer step."""

    def after_task(self, ctx: TaskContext) -> None:
        """Called after training on a task, with the trained policy and the task's data."""

    def mid_task_policy(self, policy: torch.nn.Module) -> torch.nn.Module:
        """The policy a learning-curve evaluation rolls out while a task trains: by default the
        policy itself. A method that wraps the policy's layers during a task (LoRA) returns a
        plain copy, which evaluation workers (they build a plain policy) can load."""
        return policy

    def evaluation_view(self, policy: torch.nn.Module, task: str, stream: list[str]
                        ) -> contextlib.AbstractContextManager:
        """The policy as it should be evaluated on `task` (a foundation task or one of `stream`),
        entered around that task's rollouts and held-out loss; by default the policy as it is.
        A method that overrides it sets `task_aware_eval = True`. Foundation tasks share one view:
        stage 0 trained them together."""
        return contextlib.nullcontext()

    # -- checkpoints -------------------------------------------------------------------------

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        pass

    def hyperparameters(self) -> dict[str, Any]:
        return dataclasses.asdict(self.config)
