"""Suite -> training data: every task's demos (cached), chunked, with its instruction embedded
(the pooled sentence embedding, and the MiniLM token ids for policies that read tokens)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from harness.config import BenchConfig
from harness.datasets import TrainingData, chunk_episodes
from harness.demos import DemoSpec, Episode, load_or_generate
from policies.text_encoder import embed_instructions, tokenize_instructions
from suites import Suite


@dataclass
class BenchmarkData:
    train: dict[str, TrainingData]  # task -> training samples
    heldout: dict[str, TrainingData]  # task -> held-out samples (offline retention)
    # task -> {"instruction": [384] embedding, "instruction_tokens": [L] token ids}
    instructions: dict[str, dict[str, np.ndarray]]

    def foundation(self, tasks: list[str]) -> TrainingData:
        return TrainingData.concat([self.train[t] for t in tasks])


def demo_spec(cfg: BenchConfig, suite: Suite, task: str, split: str) -> DemoSpec:
    n = cfg.demos_per_task if split == "demo" else cfg.heldout_demos_per_task
    return DemoSpec(suite=suite.name, suite_version=suite.version(), task=task, split=split,
                    num_demos=n, max_episode_steps=cfg.max_episode_steps, cameras=cfg.cameras,
                    image_size=cfg.image_size)


def prepare_data(cfg: BenchConfig, suite: Suite) -> BenchmarkData:
    tasks = cfg.foundation_tasks + cfg.stream_tasks
    cache = Path(cfg.cache_dir)
    texts = [suite.instruction(t) for t in tasks]
    embeddings = embed_instructions(texts, cache / "instructions")
    token_ids = tokenize_instructions(texts, cache / "instructions")
    token_ids = token_ids[:, :max(1, int((token_ids != 0).sum(1).max()))]  # no all-padding column
    data = BenchmarkData({}, {}, {})
    for task, embedding, tokens in zip(tasks, embeddings, token_ids):
        data.instructions[task] = {"instruction": embedding, "instruction_tokens": tokens}
        for split, target in (("demo", data.train), ("heldout", data.heldout)):
            episodes = load_or_generate(suite, demo_spec(cfg, suite, task, split), cache, cfg.progress)
            target[task] = chunk_episodes(episodes, task, embedding, cfg.chunk_size, tokens)
    return data


def libero_training_data(path: str | Path, chunk_size: int, cache_dir: Path | None = None) -> TrainingData:
    """One task's training samples from a real LIBERO HDF5 file.

    The state is LIBERO's own proprioception (ee_states + gripper_states), so these samples train
    policies meant for real LIBERO; evaluating them there needs the optional `libero` extra.
    """
    from suites.robosuite_libero.libero_files import read_libero_file

    task = read_libero_file(path)
    episodes = [Episode(e["actions"], e["obs"], seed=-1) for e in task.episodes]
    embedding = embed_instructions([task.instruction], cache_dir)[0]
    tokens = tokenize_instructions([task.instruction], cache_dir)[0]
    return chunk_episodes(episodes, Path(path).stem, embedding, chunk_size, tokens)
