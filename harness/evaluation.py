"""Closed-loop evaluation: roll the policy out on every task's fixed, seeded evaluation episodes.

Episodes run in lockstep, so the policy predicts one batch of action chunks for all episodes
that need a new chunk (across tasks: the instruction is per row). Each episode's sampling noise
comes from its own generator, seeded by the episode, so results do not depend on how episodes
are batched or split across worker processes.
"""

from __future__ import annotations

import os
from collections import deque
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass
from multiprocessing import get_context

import numpy as np
import torch

from harness.datasets import TrainingData
from harness.seeding import generator
from suites import Suite, get_suite


@dataclass(frozen=True)
class EvalSettings:
    episodes: int
    max_episode_steps: int
    n_action_steps: int
    cameras: bool = False
    image_size: int = 84
    envs_per_task: int = 2  # simulators per task and worker; their episodes run one after another


@dataclass(frozen=True)
class EvalEpisode:
    task: str
    seed: int  # the suite's reset key: a seed, or for LIBERO the fixed init state's index
    max_steps: int  # the task's step limit (the suite's own where it has one, e.g. LIBERO's)


@dataclass(frozen=True)
class TaskEvaluation:
    task: str
    successes: tuple[bool, ...]
    steps: int  # environment steps taken, for throughput figures

    @property
    def success_rate(self) -> float:
        return float(np.mean(self.successes)) if self.successes else float("nan")


class EnvCache:
    """Simulators kept across stages, at most `envs_per_task` per task: building one can take
    longer than an episode, and one per episode would hold gigabytes (robosuite's ~85 MB each)."""

    def __init__(self, suite: Suite, settings: EvalSettings):
        self.suite, self.settings = suite, settings
        self.envs: dict[str, list] = {}

    def for_task(self, task: str, n: int) -> list:
        pool = self.envs.setdefault(task, [])
        while len(pool) < n:
            pool.append(self.suite.make_env(task, self.settings.cameras, self.settings.image_size))
        return pool[:n]

    def close(self) -> None:
        for pool in self.envs.values():
            for env in pool:
                env.close()
        self.envs.clear()


@dataclass
class _Slot:
    """One simulator running its task's episodes one after another."""

    env: object
    task: str
    episode: int | None = None  # index into the episode list; None when the slot is done
    t: int = 0
    obs: dict | None = None
    plan: np.ndarray | None = None
    noise: torch.Generator | None = None


@torch.no_grad()
def rollout(policy, episodes: list[EvalEpisode], instructions: dict[str, np.ndarray],
            settings: EvalSettings, noise_seed: int, envs: EnvCache) -> list[tuple[bool, int]]:
    """(success, steps) per episode. Slots step in lockstep; every slot that needs a new action
    chunk gets it from one batched policy call; a finished episode's slot starts the next
    episode of its task at once."""
    policy.eval()
    chunk_shape = (policy.config.chunk_size, policy.config.action_dim)
    queues: dict[str, deque[int]] = {}
    for i, ep in enumerate(episodes):
        queues.setdefault(ep.task, deque()).append(i)
    slots = [_Slot(env, task) for task, queue in queues.items()
             for env in envs.for_task(task, min(len(queue), settings.envs_per_task))]
    outcomes: list[tuple[bool, int] | None] = [None] * len(episodes)

    def start_next(slot: _Slot) -> None:
        queue = queues[slot.task]
        slot.episode = queue.popleft() if queue else None
        if slot.episode is not None:
            ep = episodes[slot.episode]
            slot.t, slot.obs = 0, slot.env.reset(ep.seed)
            slot.noise = generator("eval-noise", noise_seed, ep.task, ep.seed)

    for slot in slots:
        start_next(slot)
    while True:
        live = [s for s in slots if s.episode is not None]
        if not live:
            break
        need = [s for s in live if s.t % settings.n_action_steps == 0]
        if need:
            batch = {k: torch.as_tensor(np.stack([s.obs[k] for s in need])) for k in need[0].obs}
            batch["instruction"] = torch.as_tensor(np.stack([instructions[s.task] for s in need]))
            noise = torch.stack([torch.randn(chunk_shape, generator=s.noise) for s in need])
            for s, chunk in zip(need, policy.sample_actions(batch, noise=noise).numpy()):
                s.plan = chunk
        for s in live:
            result = s.env.step(s.plan[s.t % settings.n_action_steps])
            s.t += 1
            s.obs = result.obs
            if result.success or s.t >= episodes[s.episode].max_steps:
                outcomes[s.episode] = (result.success, s.t)
                start_next(s)
    return outcomes


def evaluation_episodes(suite: Suite, tasks: list[str], n: int, max_episode_steps: int
                        ) -> list[EvalEpisode]:
    return [EvalEpisode(t, key, suite.step_limit(t, max_episode_steps))
            for t in tasks for key in suite.episode_keys(t, "eval", n)]


def group_by_task(episodes: list[EvalEpisode], outcomes: list[tuple[bool, int]]
                  ) -> dict[str, TaskEvaluation]:
    by_task: dict[str, list[tuple[bool, int]]] = {}
    for ep, out in zip(episodes, outcomes):
        by_task.setdefault(ep.task, []).append(out)
    return {t: TaskEvaluation(t, tuple(s for s, _ in v), sum(n for _, n in v)) for t, v in by_task.items()}


class Evaluator:
    """Evaluates a policy on a benchmark's tasks, in this process or in `workers` processes.

    Workers are started once and keep their simulators between stages; each receives the
    policy's weights and an interleaved share of the episodes.
    """

    def __init__(self, suite: Suite, settings: EvalSettings, workers: int = 1, torch_threads: int = 1):
        self.suite, self.settings, self.workers = suite, settings, max(1, workers)
        self._local = EnvCache(suite, settings) if self.workers == 1 else None
        self._pool = None
        if self.workers > 1:
            self._pool = ProcessPoolExecutor(self.workers, mp_context=get_context("spawn"),
                                             initializer=_init_worker,
                                             initargs=(suite.name, settings, torch_threads))

    def evaluate(self, policy, tasks: list[str], instructions: dict[str, np.ndarray],
                 noise_seed: int) -> dict[str, TaskEvaluation]:
        episodes = evaluation_episodes(self.suite, tasks, self.settings.episodes,
                                       self.settings.max_episode_steps)
        if self._pool is None:
            outcomes = rollout(policy, episodes, instructions, self.settings, noise_seed, self._local)
            return group_by_task(episodes, outcomes)
        shares = [s for s in (episodes[i::self.workers] for i in range(self.workers)) if s]
        # a copy: sending tensors to workers moves their storage to shared memory, and during a
        # learning-curve evaluation the parameters are views into the trainer's flat buffer
        weights = {k: v.detach().clone() for k, v in policy.state_dict().items()}
        futures = [self._pool.submit(_worker_rollout, policy.config, weights, share, instructions,
                                     noise_seed) for share in shares]
        outcomes: dict[EvalEpisode, tuple[bool, int]] = {}
        for share, future in zip(shares, futures):
            outcomes.update(zip(share, future.result()))
        return group_by_task(episodes, [outcomes[ep] for ep in episodes])

    def close(self) -> None:
        if self._pool is not None:
            self._pool.shutdown(cancel_futures=True)
        if self._local is not None:
            self._local.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


_WORKER: dict = {}


def _init_worker(suite_name: str, settings: EvalSettings, torch_threads: int) -> None:
    os.environ.setdefault("MUJOCO_GL", "egl")
    torch.set_num_threads(torch_threads)
    _WORKER["envs"] = EnvCache(get_suite(suite_name), settings)
    _WORKER["settings"] = settings


def _worker_rollout(config, weights, episodes, instructions, noise_seed):
    from policies import FlowMatchingPolicy

    if _WORKER.get("config") != config:
        _WORKER["policy"], _WORKER["config"] = FlowMatchingPolicy(config), config
    policy = _WORKER["policy"]
    policy.load_state_dict(weights)
    return rollout(policy, episodes, instructions, _WORKER["settings"], noise_seed, _WORKER["envs"])


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
