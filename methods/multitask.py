"""Joint training on everything seen so far: the upper bound, not a continual method."""

from __future__ import annotations

import torch

from harness.data.datasets import TrainingData
from methods import register_method
from methods.base import Method, TaskContext


@register_method
class Multitask(Method):
    name = "multitask"
    uses_past_data = True

    def __init__(self, config=None):
        super().__init__(config)
        self.seen: TrainingData | None = None  # every finished stage's data, foundation included
        self._joined: TrainingData | None = None  # seen + the current task, built once per stage

    def before_task(self, ctx: TaskContext) -> None:
        self._joined = (ctx.data if self.seen is None  # where the stage's data is (a GPU's once)
                        else TrainingData.concat([self.seen.to(ctx.data.actions.device), ctx.data]))

    def sample_batch(self, ctx: TaskContext, batch_size: int, generator: torch.Generator) -> dict:
        return self._joined.sample(batch_size, generator)

    def after_task(self, ctx: TaskContext) -> None:
        data = ctx.data.to("cpu")  # kept on the CPU, as a checkpoint loads it
        self.seen = data if self.seen is None else TrainingData.concat([self.seen, data])
        self._joined = None

    def state_dict(self):
        return {"seen": self.seen}

    def load_state_dict(self, state):
        self.seen = state["seen"]
