"""Experience replay: a buffer of foundation demos and of finished stream tasks, mixed into
every batch. The one method here whose nature is to keep data."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

import torch
from annotated_types import Ge, Interval

from harness.data.datasets import TrainingData, merge_batches
from methods import register_method
from methods.base import Method, MethodConfig, TaskContext


@dataclass
class ERConfig(MethodConfig):
    # samples kept per task (LIBERO's ER keeps 1000 per task)
    buffer_per_task: Annotated[int, Ge(1)] = 1000
    # fraction of every batch drawn from the buffer
    replay_ratio: Annotated[float, Interval(ge=0, lt=1)] = 0.5


@register_method
class ExperienceReplay(Method):
    name = "er"
    Config = ERConfig
    uses_past_data = True

    def __init__(self, config: ERConfig | None = None):
        super().__init__(config)
        self.buffer: TrainingData | None = None

    def sample_batch(self, ctx: TaskContext, batch_size: int, generator: torch.Generator) -> dict:
        n_replay = round(self.config.replay_ratio * batch_size) if self.buffer is not None else 0
        current = ctx.data.sample(batch_size - n_replay, generator)
        if n_replay == 0:
            return current
        return merge_batches(current, self.buffer.sample(n_replay, generator))

    def after_task(self, ctx: TaskContext) -> None:
        """Keep up to `buffer_per_task` samples of every task in this stage's data."""
        g = torch.Generator().manual_seed(1000 + ctx.stage)
        kept = ctx.data.per_task_subset(self.config.buffer_per_task, g).to("cpu")
        self.buffer = kept if self.buffer is None else TrainingData.concat([self.buffer, kept])

    def state_dict(self):
        return {"buffer": self.buffer}

    def load_state_dict(self, state):
        self.buffer = state["buffer"]
