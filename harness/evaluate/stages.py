"""What every stage produces, and how it is saved: a record and an atomic checkpoint file."""

from __future__ import annotations

import collections
import contextlib
import pickle
import re
from dataclasses import asdict, dataclass, field
from pathlib import Path

import torch

from harness.common.atomic import atomic_path
from harness.common.errors import RetainError
from harness.common.seeding import derive_seed
from harness.config.benchmark import BenchConfig, stage_name
from harness.data.datasets import TrainingData
from harness.data.prepare import BenchmarkData
from harness.evaluate.rollouts import EvalSettings, Evaluator, heldout_loss
from harness.evaluate.videos import VideoWriter
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
                        image_size=cfg.image_size, render=cfg.render,
                        envs_per_task=cfg.eval_envs_per_task,
                        shards=cfg.eval_shards, spatial_episodes=cfg.spatial_episodes,
                        check_episodes=cfg.check_episodes if cfg.until_success > 0 else 0,
                        step_cap=cfg.eval_step_cap)


def make_evaluator(cfg: BenchConfig, suite, workers: int) -> Evaluator:
    """The run's evaluator: its settings, `workers` processes, its threads and progress."""
    return Evaluator(suite, eval_settings(cfg), workers, cfg.torch_threads, progress=cfg.progress)


def evaluate_stage(policy, evaluator: Evaluator, cfg: BenchConfig, data: BenchmarkData, seed: int,
                   stage: int, task: str, method: Method | None = None,
                   videos: VideoWriter | None = None) -> StageRecord:
    """Roll out every task (foundation and stream), also from the spatial probe's states when
    it is on, and measure every held-out loss.

    The foundation tasks are rolled out only at the stages `cfg.evaluates_foundation` names; at
    the others their success is NaN (not evaluated) and their held-out loss is still measured.
    A task-aware method (PackNet) is evaluated group by group inside its `evaluation_view`: the
    foundation tasks together, then each stream task; any other method in one call, as before.
    With `videos`, the episodes it chooses keep their states and become videos after the stage.
    """
    tasks = cfg.all_tasks()
    rolled = set(tasks if cfg.evaluates_foundation(stage) else cfg.stream_tasks)
    noise_seed = derive_seed(seed, "eval")
    aware = method is not None and method.task_aware_eval
    stream = cfg.stream_stages()
    names = [stage_name(i, group) for i, group in enumerate(stream, start=1)]
    groups = [cfg.foundation_tasks] + stream if aware else [tasks]
    results, spatial, heldout = {}, {}, {}
    record = videos.episodes_at(stage) if videos is not None else frozenset()
    for group in (g for g in groups if g):
        # a task-aware view is per stage: the foundation's, or stream stage i's (by its name)
        view = (method.evaluation_view(policy, names[stream.index(group)] if group in stream
                                       else group[0], names) if aware
                else contextlib.nullcontext())
        rollouts = [t for t in group if t in rolled]
        with view:
            if rollouts:
                results.update(evaluator.evaluate(policy, rollouts, data.instructions, noise_seed,
                                                  record=record))
                if cfg.spatial_episodes > 0:
                    spatial.update(evaluator.evaluate(policy, rollouts, data.instructions,
                                                      noise_seed, split="spatial"))
            heldout.update({t: heldout_loss(policy, data.heldout[t], derive_seed("heldout", t))
                            for t in group})
    if videos is not None:
        videos.write(stage, task, results)
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


class CheckpointError(RetainError):
    """A checkpoint that holds something other than plain data, or cannot be read."""


# What a checkpoint may hold besides tensors, numbers, strings, lists, tuples and dicts (which
# torch's weights-only unpickler allows by itself): a method's TrainingData (a replay buffer),
# also under the module name it had before harness/ was grouped into subpackages, so a run saved
# then still resumes. Nothing else is ever built while loading: a results folder or a cache is
# shared, and opening a file of it must not run what a pickle names.
ALLOWED_GLOBALS = [TrainingData, (TrainingData, "harness.datasets.TrainingData")]
# exact types: a subclass (NumPy's float64 is a float, a namedtuple a tuple) pickles its own class
_SCALARS = (str, bytes, int, float, bool, complex, type(None), torch.dtype, torch.device,
            torch.Size)


def save_checkpoint(path: Path, payload: dict) -> None:
    """`payload` written atomically, after checking it holds only what `load_checkpoint` reads
    back: a method whose state holds another object fails here, naming it, not at its resume."""
    _check_plain(payload, "checkpoint")
    with atomic_path(path) as tmp:
        torch.save(payload, tmp)


def _check_plain(value, where: str) -> None:
    if type(value) in _SCALARS or isinstance(value, torch.Tensor):
        return
    if type(value) in (dict, collections.OrderedDict):
        for key, item in value.items():
            if type(key) not in (str, int, float, bool, type(None)):
                raise CheckpointError(f"{where} has a key of type {type(key).__name__}; a "
                                      "checkpoint's keys are strings or numbers")
            _check_plain(item, f"{where}[{key!r}]")
    elif type(value) in (list, tuple):
        for i, item in enumerate(value):
            _check_plain(item, f"{where}[{i}]")
    elif type(value) is TrainingData:
        for name, item in vars(value).items():
            _check_plain(item, f"{where}.{name}")
    else:
        raise CheckpointError(
            f"{where} holds a {type(value).__module__}.{type(value).__qualname__}; a checkpoint "
            "(a method's state_dict too) holds only tensors, numbers, strings, lists, tuples, "
            "dicts and TrainingData (docs/adding-a-method.md)")


def load_checkpoint(path: Path, map_location="cpu") -> dict:
    """A checkpoint written by `save_checkpoint`, loaded with torch's weights-only unpickler and
    ALLOWED_GLOBALS: a file that names any other class or function (a crafted pickle, or a
    checkpoint of an older Retain that pickled more) is refused in one line, and nothing it
    names is imported or called."""
    try:
        with torch.serialization.safe_globals(ALLOWED_GLOBALS):
            return torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as err:
        raise CheckpointError(f"{path} was not loaded: it holds {_refused(err)}, which a "
                              f"checkpoint may not (an older Retain pickled more); {REBUILD}"
                              ) from None
    except RuntimeError as err:
        if "PytorchStreamReader" not in str(err) and "zip archive" not in str(err):
            raise
        raise CheckpointError(f"{path} is not a readable checkpoint (truncated or not written "
                              f"by torch.save); {REBUILD}") from None


REBUILD = "delete it and it is rebuilt (`make clean-cache` deletes the whole cache)"


def _refused(err: Exception) -> str:
    """What the weights-only unpickler refused, from its many-line message, in a few words."""
    text = str(err)
    found = re.search(r"[Uu]nsupported (?:global: )?GLOBAL ([\w.]+)", text)
    if found:
        return f"a reference to {found.group(1)}"
    lines = [line.strip() for line in text.splitlines() if line.strip()
             and not line.startswith(("Weights only load failed", "Check the documentation"))]
    return f"an object outside plain data ({lines[0][:160] if lines else type(err).__name__})"
