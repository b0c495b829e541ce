"""Experience replay: a buffer of foundation demos and of finished stream tasks, mixed into
every batch. The one method here whose nature is to keep data."""

from __future__ import annotations

from dataclasses import dataclass

import torch

from harness.datasets import TrainingData, merge_batches
from methods import register_method
from methods.base import Method, MethodConfig, TaskContext


@dataclass
class ERConfig(MethodConfig):
    buffer_per_task: int = 1000  # samples kept per task (LIBERO's ER keeps 1000 per task)
    replay_ratio: float = 0.5  # fraction of every batch drawn from the buffer


@register_method
class ExperienceReplay(Method):
    name = "er"
    Config = ERConfig
    uses_past_data = True

    def __init__(self, config: ERConfig | None = None):
        super().__init__(config)
        if not 0.0 <= self.config.replay_ratio < 1.0:
            raise ValueError(f"replay_ratio={self.config.replay_ratio} must be in [0, 1)")
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
        kept = ctx.data.per_task_subset(self.config.buffer_per_task, g)
        self.buffer = kept if self.buffer is None else TrainingData.concat([self.buffer, kept])

    def state_dict(self):
        return {"buffer": self.buffer}

    def load_state_dict(self, state):
        self.buffer = state["buffer"]
