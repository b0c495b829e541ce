"""A user method for tests: plain SFT that writes which tasks each stage's data and batches
held to the JSON-lines file named by RETAIN_TEST_RECORD."""

import json
import os

from methods import Method


class RecordingSFT(Method):
    name = "recording-sft"
    prefetch_batches = False

    def _write(self, entry: dict) -> None:
        with open(os.environ["RETAIN_TEST_RECORD"], "a") as f:
            f.write(json.dumps(entry) + "\n")

    def before_task(self, ctx):
        self.stage, self.seen = ctx.stage, set()
        self._write({"stage": ctx.stage, "data_tasks": sorted(ctx.data.task_names),
                     "samples": len(ctx.data)})

    def sample_batch(self, ctx, batch_size, generator):
        batch = super().sample_batch(ctx, batch_size, generator)
        self.seen |= {ctx.data.task_names[i] for i in ctx.data.task_index[batch["index"]].tolist()}
        return batch

    def after_task(self, ctx):
        if ctx.stage > 0:
            self._write({"stage": ctx.stage, "batch_tasks": sorted(self.seen)})
