"""What every stage produces, and how it is saved: a record and an atomic checkpoint file."""

from __future__ import annotations

import contextlib
import pickle
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from harness.common.atomic import atomic_path
from harness.common.seeding import derive_seed
from harness.config.benchmark import BenchConfig, stage_name
from harness.data.prepare import BenchmarkData
from harness.evaluate.rollouts import EvalSettings, Evaluator, heldout_loss
from methods import Method


@dataclass
class StageRecord:
    stage: int
    task: str  # "foundation" or the stream task trained at this stage
    success: dict[str, float]  # task -> success rate over its evaluation episodes
    episodes: dict[str, list[bool]]  # task -> per-episode success
    heldout_loss: dict[str, float]  # task -> held-out flow-matching loss
    train_loss: float = float("nan")
    updates: dict[str, float] = field(default_factory=dict)  # theta_i vs theta_0
    updates_stage: dict[str, float] = field(default_factory=dict)  # theta_i vs theta_{i-1}
    env_steps: int = 0
    curve_steps: list[int] = field(default_factory=list)  # learning curve of this stage's task:
    curve: list[float] = field(default_factory=list)  # success at those steps (0 and the end too)
    # the spatial probe (empty when off): success from widened initial states, as above
    spatial_success: dict[str, float] = field(default_factory=dict)
    spatial_episodes: dict[str, list[bool]] = field(default_factory=dict)
    steps_used: int = 0  # optimizer steps this stage took (fewer than planned: until_success)
    check_steps: list[int] = field(default_factory=list)  # until_success's checks: steps done,
    check_success: list[float] = field(default_factory=list)  # and the tasks' check success
    # the paper's sparsity (Eq. 8) against the foundation, during the stage: at these steps, the
    # share of scalars within delta of their pre-trained value, globally and per layer
    sparsity_steps: list[int] = field(default_factory=list)
    sparsity: list[float] = field(default_factory=list)
    sparsity_layers: dict[str, list[float]] = field(default_factory=dict)

    def as_dict(self) -> dict:
        return asdict(self)


def eval_settings(cfg: BenchConfig) -> EvalSettings:
    return EvalSettings(episodes=cfg.eval_episodes, max_episode_steps=cfg.max_episode_steps,
                        n_action_steps=cfg.n_action_steps, cameras=cfg.cameras,
                        image_size=cfg.image_size, envs_per_task=cfg.eval_envs_per_task,
                        shards=cfg.eval_shards, spatial_episodes=cfg.spatial_episodes,
                        check_episodes=cfg.check_episodes if cfg.until_success > 0 else 0)


def evaluate_stage(policy, evaluator: Evaluator, cfg: BenchConfig, data: BenchmarkData, seed: int,
                   stage: int, task: str, method: Method | None = None) -> StageRecord:
    """Roll out every task (foundation and stream), also from the spatial probe's states when
    it is on, and measure every held-out loss.

    The foundation tasks are rolled out only at the stages `cfg.evaluates_foundation` names; at
    the others their success is NaN (not evaluated) and their held-out loss is still measured.
    A task-aware method (PackNet) is evaluated group by group inside its `evaluation_view`: the
    foundation tasks together, then each stream task; any other method in one call, as before.
    """
    tasks = cfg.all_tasks()
    rolled = set(tasks if cfg.evaluates_foundation(stage) else cfg.stream_tasks)
    noise_seed = derive_seed(seed, "eval")
    aware = method is not None and method.task_aware_eval
    stream = cfg.stream_stages()
    names = [stage_name(i, group) for i, group in enumerate(stream, start=1)]
    groups = [cfg.foundation_tasks] + stream if aware else [tasks]
    results, spatial, heldout = {}, {}, {}
    for group in (g for g in groups if g):
        # a task-aware view is per stage: the foundation's, or stream stage i's (by its name)
        view = (method.evaluation_view(policy, names[stream.index(group)] if group in stream
                                       else group[0], names) if aware
                else contextlib.nullcontext())
        rollouts = [t for t in group if t in rolled]
        with view:
            if rollouts:
                results.update(evaluator.evaluate(policy, rollouts, data.instructions, noise_seed))
                if cfg.spatial_episodes > 0:
                    spatial.update(evaluator.evaluate(policy, rollouts, data.instructions,
                                                      noise_seed, split="spatial"))
            heldout.update({t: heldout_loss(policy, data.heldout[t], derive_seed("heldout", t))
                            for t in group})
    nan = float("nan")
    return StageRecord(
        stage, task,
        success={t: results[t].success_rate if t in results else nan for t in tasks},
        episodes={t: list(results[t].successes) if t in results else [] for t in tasks},
        heldout_loss={t: heldout[t] for t in tasks},
        env_steps=sum(r.steps for r in (*results.values(), *spatial.values())),
        spatial_success={t: spatial[t].success_rate if t in spatial else nan for t in tasks
                         } if spatial else {},
        spatial_episodes={t: list(spatial[t].successes) if t in spatial else [] for t in tasks
                          } if spatial else {},
    )


def save_checkpoint(path: Path, payload: dict) -> None:
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)


# Checkpoints pickle some harness classes (a replay buffer is a TrainingData) by module name.
# These modules moved when harness/ was grouped into subpackages; a run saved before still resumes.
MOVED_MODULES = {"harness.datasets": "harness.data.datasets", "harness.demos": "harness.data.demos"}


class _Unpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str):
        return super().find_class(MOVED_MODULES.get(module, module), name)


class _pickle_with_moved_modules:  # noqa: N801 - a pickle module, as torch.load takes one
    Unpickler = _Unpickler

    @staticmethod
    def load(file, **kwargs):
        return _Unpickler(file, **kwargs).load()


def load_checkpoint(path: Path) -> dict:
    return torch.load(path, map_location="cpu", weights_only=False,
                      pickle_module=_pickle_with_moved_modules)
