"""Closed-loop evaluation: roll the policy out on each task's fixed, seeded evaluation episodes.

All episodes of a task run in lockstep, so the policy predicts one batch of action chunks for
every episode that needs a new chunk. The sampling noise of each episode comes from its own
generator (seeded by the episode), so a result does not depend on how episodes are batched or
split across workers.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from harness.datasets import TrainingData
from harness.seeding import generator
from suites import Suite, episode_seeds


@dataclass(frozen=True)
class EvalSettings:
    episodes: int
    max_episode_steps: int
    n_action_steps: int
    cameras: bool = False
    image_size: int = 84


@dataclass(frozen=True)
class TaskEvaluation:
    task: str
    successes: tuple[bool, ...]
    steps: int  # environment steps taken, for throughput figures

    @property
    def success_rate(self) -> float:
        return float(np.mean(self.successes)) if self.successes else float("nan")


def evaluate_task(
    policy, suite: Suite, task: str, instruction: np.ndarray, settings: EvalSettings,
    noise_seed: int, seeds: list[int] | None = None, envs: list | None = None,
) -> TaskEvaluation:
    """Success of `policy` on the task's evaluation episodes (or on `seeds` if given)."""
    seeds = seeds if seeds is not None else episode_seeds(suite.name, task, "eval", settings.episodes)
    own_envs = envs is None
    if own_envs:
        envs = [suite.make_env(task, settings.cameras, settings.image_size) for _ in seeds]
    policy.eval()
    chunk_size, action_dim = policy.config.chunk_size, policy.config.action_dim
    obs = [env.reset(seed) for env, seed in zip(envs, seeds)]
    generators = [generator("eval-noise", noise_seed, seed) for seed in seeds]
    instruction_t = torch.as_tensor(instruction, dtype=torch.float32)
    done = [False] * len(seeds)
    success = [False] * len(seeds)
    plans: list[np.ndarray | None] = [None] * len(seeds)
    env_steps = 0
    for t in range(settings.max_episode_steps):
        if t % settings.n_action_steps == 0:
            live = [i for i in range(len(seeds)) if not done[i]]
            if not live:
                break
            batch = {k: torch.as_tensor(np.stack([obs[i][k] for i in live])) for k in obs[live[0]]}
            batch["instruction"] = instruction_t.expand(len(live), -1)
            noise = torch.stack([torch.randn(chunk_size, action_dim, generator=generators[i])
                                 for i in live])
            chunks = policy.sample_actions(batch, noise=noise).numpy()
            for j, i in enumerate(live):
                plans[i] = chunks[j]
        for i, env in enumerate(envs):
            if done[i]:
                continue
            result = env.step(plans[i][t % settings.n_action_steps])
            env_steps += 1
            obs[i] = result.obs
            if result.success:
                success[i] = done[i] = True
    if own_envs:
        for env in envs:
            env.close()
    return TaskEvaluation(task, tuple(success), env_steps)


@torch.no_grad()
def heldout_loss(policy, data: TrainingData, seed: int) -> float:
    """Mean flow-matching loss on held-out demos with fixed noise and time draws.

    The draws depend only on `seed` and the data, so the figure is comparable across methods
    and stages: a cheap, deterministic retention signal.
    """
    policy.eval()
    g = torch.Generator().manual_seed(seed)
    noise = torch.randn(data.actions.shape, generator=g)
    time = policy.sample_time(len(data), g)
    batch = data.batch(torch.arange(len(data)))
    batch["noise"], batch["time"] = noise, time
    return policy(batch).mean().item()
