"""Benchmark configuration: named YAML files, profiles, and `key=value` overrides.

Resolution: BENCH (or the benchmark PROFILE stands for) -> the YAML file -> the profile's
scaling (tiny, paper) -> command-line overrides. Lower-case keys name a field of `BenchConfig`
or a hyperparameter of the method; a key that is neither is an error naming the valid keys.
"""

from __future__ import annotations

import dataclasses
import os
import types
import typing
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any

import yaml

from harness.errors import RetainError

BENCHMARK_DIR = Path(__file__).parent / "benchmarks"
PROFILE_BENCHMARKS = {"quick": "mw-quick", "standard": "mw-standard", "tiny": "mw-quick",
                      "paper": "mw-standard"}


@dataclass
class BenchConfig:
    name: str
    suite: str
    foundation_tasks: list[str]
    stream_tasks: list[str]
    demos_per_task: int = 50
    heldout_demos_per_task: int = 5
    eval_episodes: int = 20
    spatial_episodes: int = 0  # per task and stage, from widened initial states; 0: probe off
    # foundation tasks are rolled out at stage 0, every N-th stage and the last (stream tasks and
    # every held-out loss at every stage): a long stream's failed foundation episodes, each run to
    # the episode limit, are most of its evaluation time, and retention needs stages 0 and k only
    foundation_eval_every: int = 1
    max_episode_steps: int = 200
    foundation_steps: int = 4000
    steps_per_task: int = 1500
    batch_size: int = 256
    lr: float = 3e-4
    weight_decay: float = 0.0
    grad_clip: float = 1.0
    policy: str = "mlp"  # a registered policy (mlp, pi0) or module.path:Class / file.py:Class
    policy_size: str = "default"
    chunk_size: int = 4
    n_action_steps: int = 4
    cameras: bool = False
    image_size: int = 84
    profile: str = ""
    seed: int = 0  # first seed
    seeds: int = 1  # number of seeds: seed, seed + 1, ...
    method: str = "sft"
    method_params: dict[str, Any] = field(default_factory=dict)
    grid: str = ""  # a sweep: "kappa=0.1,0.25 w_min=0.05,0.2", one run per point and seed
    foundation_lr: float = 3e-4  # kept apart from lr, so a sweep of lr shares one foundation
    results_dir: str = "results"
    cache_dir: str = "cache"
    demos_dir: str = ""  # real LIBERO dataset files (<task>_demo.hdf5) to train on instead of experts
    progress: bool = True
    torch_threads: int = 1  # intra-op threads per process; small CPU batches are slower with more
    eval_workers: int = 0  # evaluation processes; 0 means one per core
    eval_envs_per_task: int = 2  # simulators per task and worker (memory against batching)
    # a stage's evaluation episodes are split into this many interleaved shares, each rolled out
    # in its own lockstep batch; fixed per run, so results never depend on how many workers (or
    # which executor) ran them. At most this many evaluation workers per job have work.
    eval_shards: int = 2
    learning_curve_every: int = 0  # evaluate the stage's task every N steps (LIBERO's FWT/NBT/AUC)
    executor: str = "local"  # where a comparison's jobs run: serial, local (processes) or ray
    jobs: int = 0  # jobs at once; 0: as many as the cores allow given each job's workers
    device: str = "cpu"  # cpu, cuda or auto (CUDA when present); CUDA trains in bf16 autocast
    compile: bool = False  # torch.compile the policy (worth it on a GPU)
    # a LeRobot dataset folder as demos_dir (docs/lerobot.md): the dataset's features for Retain's
    # keys, "state:observation.state,agentview_rgb:image" (else the common names); the suite's
    # tasks to the dataset's, "TASK:TASK_INDEX" or "TASK:text" (else by instruction); whether its
    # images are turned 180 degrees from the suite's renders (LIBERO's community sets are)
    lerobot_keys: str = ""
    lerobot_tasks: str = ""
    lerobot_rotate_images: bool = False

    def workers(self) -> int:
        return self.eval_workers if self.eval_workers > 0 else (os.cpu_count() or 1)

    def evaluates_foundation(self, stage: int) -> bool:
        """Whether the foundation tasks are rolled out after `stage` (see foundation_eval_every)."""
        return stage % self.foundation_eval_every == 0 or stage == len(self.stream_tasks)

    def seed_list(self) -> list[int]:
        return list(range(self.seed, self.seed + self.seeds))

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


# the settings an override or a GRID point sets on the config; any other key is a method's
BENCH_KEYS = frozenset(f.name for f in fields(BenchConfig)) - {"method_params", "grid"}

# settings of what every sweep point shares (the demos, the foundation, the evaluator), so a
# GRID cannot vary them: the points would record a value that was never used
SHARED_BY_SWEEP_POINTS = frozenset({
    "name", "suite", "foundation_tasks", "stream_tasks", "demos_per_task", "spatial_episodes",
    "heldout_demos_per_task", "eval_episodes", "foundation_eval_every", "max_episode_steps",
    "foundation_steps", "foundation_lr", "policy_size", "chunk_size", "n_action_steps", "cameras",
    "image_size", "profile", "seed", "seeds", "method", "results_dir", "cache_dir", "progress",
    "torch_threads", "eval_workers", "eval_envs_per_task", "eval_shards", "executor", "jobs",
    "policy", "device", "compile"})

EXECUTORS = ("serial", "local", "ray")

# settings that cannot change a run's results (where it is written, how rollouts are split);
# torch_threads stays in: the summation order of a matrix product depends on it
NOT_IN_RUN_KEY = ("progress", "seed", "seeds", "method", "grid", "profile", "eval_workers",
                  "eval_envs_per_task", "results_dir", "cache_dir", "executor", "jobs")

# settings added after results were recorded, at the value that changes nothing: there a run
# key leaves them out (earlier checkpoints still resume) and a report reads a run that never
# logged them as having it (its rows keep their labels)
QUIET_DEFAULTS: dict[str, Any] = {"spatial_episodes": 0, "eval_shards": 2, "foundation_eval_every": 1}
QUIET_DEFAULTS.update(lerobot_keys="", lerobot_tasks="", lerobot_rotate_images=False)  # LeRobot's


def run_key_settings(cfg: BenchConfig) -> dict[str, Any]:
    """The settings a run's results depend on (what its run key hashes)."""
    return {k: v for k, v in cfg.as_dict().items()
            if k not in NOT_IN_RUN_KEY and not (k in QUIET_DEFAULTS and v == QUIET_DEFAULTS[k])}


def benchmark_names() -> list[str]:
    return sorted(p.stem for p in BENCHMARK_DIR.glob("*.yaml"))


def load_benchmark(name: str) -> BenchConfig:
    path = BENCHMARK_DIR / f"{name}.yaml"
    if not path.exists():
        raise RetainError(f"unknown benchmark {name!r}; valid: {', '.join(benchmark_names())}")
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise RetainError(f"benchmark file {path} is not valid YAML: {str(exc).splitlines()[0]}") from None
    if not isinstance(raw, dict):
        raise RetainError(f"benchmark file {path} must be a mapping of settings")
    valid = {f.name for f in fields(BenchConfig)}
    bad = sorted(set(raw) - valid)
    if bad:
        raise RetainError(f"benchmark file {path}: unknown key {bad[0]!r}; valid: {', '.join(sorted(valid))}")
    missing = [k for k in ("name", "suite", "foundation_tasks", "stream_tasks") if k not in raw]
    if missing:
        raise RetainError(f"benchmark file {path} is missing {missing[0]!r}")
    cfg = BenchConfig(**{k: raw[k] for k in ("name", "suite", "foundation_tasks", "stream_tasks")})
    for key, value in raw.items():
        set_field(cfg, key, value)
    return cfg


def apply_profile(cfg: BenchConfig, profile: str) -> None:
    """`tiny` shrinks any benchmark to seconds (tests); `paper` is the GPU scale."""
    if profile == "tiny":
        cfg.foundation_tasks = cfg.foundation_tasks[:2]
        cfg.stream_tasks = cfg.stream_tasks[:2]
        cfg.demos_per_task, cfg.heldout_demos_per_task, cfg.eval_episodes = 3, 1, 2
        cfg.spatial_episodes = min(cfg.spatial_episodes, 2)
        cfg.max_episode_steps = min(cfg.max_episode_steps, 100)
        cfg.foundation_steps, cfg.steps_per_task, cfg.batch_size = 30, 10, 32
        cfg.policy_size = "tiny"
    elif profile == "paper":
        cfg.policy_size = "large"
        cfg.demos_per_task *= 2
        cfg.foundation_steps *= 5
        cfg.steps_per_task *= 2
        cfg.eval_episodes = max(cfg.eval_episodes, 50)
        cfg.seeds = max(cfg.seeds, 3)
    cfg.profile = profile
    cfg.name = experiment_name(cfg.name, profile)


def run_label(method: str, setting: str = "") -> str:
    """A run's name in tables, plots and results/<benchmark>/: "consft[kappa=0.1]", or the
    method's name alone when it runs at its defaults."""
    return f"{method}[{setting}]" if setting else method


def setting_text(value: Any) -> str:
    """A setting's value as a label shows it: 0.0001, a,b for a list."""
    return ",".join(map(str, value)) if isinstance(value, (list, tuple)) else str(value)


def changed_settings(cfg: BenchConfig, base: BenchConfig) -> dict[str, str]:
    """The result-changing benchmark settings where `cfg` differs from `base` (the benchmark's
    YAML after its profile): what tells a run with `lr=1e-4` from one at the defaults."""
    ours, theirs = cfg.as_dict(), base.as_dict()
    return {k: setting_text(v) for k, v in ours.items()
            if k not in NOT_IN_RUN_KEY and k not in ("name", "method_params") and v != theirs[k]}


def experiment_name(bench: str, profile: str) -> str:
    """Tiny and paper runs get their own results directory and MLflow experiment."""
    return f"{bench}-{profile}" if profile in ("tiny", "paper") else bench


def pop_bench_and_profile(overrides: dict[str, str]) -> tuple[str, str]:
    """Take BENCH and PROFILE out of `overrides`: the benchmark (the profile's default when
    BENCH is not given) and the checked profile ("" for none)."""
    profile = overrides.pop("PROFILE", "") or ""
    if profile and profile not in PROFILE_BENCHMARKS:
        raise RetainError(f"unknown profile {profile!r}; valid: {', '.join(PROFILE_BENCHMARKS)}")
    return overrides.pop("BENCH", "") or PROFILE_BENCHMARKS.get(profile, "mw-quick"), profile


def coerce(key: str, value: Any, annotation: Any) -> Any:
    """Turn a YAML or command-line value into the field's type, or fail naming both.

    `annotation` is a resolved type (`typing.get_type_hints`), not its string form."""
    origin = typing.get_origin(annotation)
    try:
        if annotation is bool:
            if isinstance(value, bool):
                return value
            if str(value).lower() in ("1", "true", "yes", "on"):
                return True
            if str(value).lower() in ("0", "false", "no", "off"):
                return False
            raise ValueError
        if annotation is int:
            if isinstance(value, bool) or (isinstance(value, float) and not value.is_integer()):
                raise ValueError
            return int(value)
        if annotation is float:
            return float(value)
        if annotation is str:
            if not isinstance(value, (str, int, float)):
                raise ValueError
            return str(value)
        if origin is list:
            items = value.split(",") if isinstance(value, str) else value
            if not isinstance(items, list):
                raise ValueError
            return [str(v).strip() for v in items if str(v).strip()]
        if origin is dict or annotation is Any or isinstance(annotation, types.GenericAlias):
            return value
    except (TypeError, ValueError):
        pass
    else:
        return value
    kind = getattr(annotation, "__name__", str(annotation))
    raise RetainError(f"bad value {value!r} for {key}: expected {kind}")


def set_field(cfg: Any, key: str, value: Any) -> None:
    hints = typing.get_type_hints(type(cfg))
    setattr(cfg, key, coerce(key, value, hints[key]))


def parse_overrides(args: list[str]) -> dict[str, str]:
    out: dict[str, str] = {}
    for arg in args:
        key, sep, value = arg.partition("=")
        if not sep or not key or not key.replace("_", "").replace(".", "").isalnum():
            raise RetainError(f"malformed override {arg!r}: expected key=value, e.g. steps_per_task=2000")
        out[key] = value
    return out


def base_config(args: list[str]) -> BenchConfig:
    """The benchmark's YAML after its profile, before any other override: the defaults a run's
    label is relative to."""
    overrides = parse_overrides(args)
    bench, profile = pop_bench_and_profile(overrides)
    cfg = load_benchmark(bench)
    if profile in ("tiny", "paper"):
        apply_profile(cfg, profile)
    else:
        cfg.profile = profile
    return cfg


def resolve(args: list[str]) -> BenchConfig:
    """The full config from command-line arguments such as `METHOD=sft PROFILE=quick lr=1e-4`."""
    cfg = base_config(args)
    overrides = parse_overrides(args)
    pop_bench_and_profile(overrides)
    for upper, lower in (("METHOD", "method"), ("SEED", "seed"), ("SEEDS", "seeds"), ("GRID", "grid")):
        if overrides.get(upper, "") != "":
            set_field(cfg, lower, overrides.pop(upper))
        overrides.pop(upper, None)
    for key, value in overrides.items():
        if key in BENCH_KEYS:
            set_field(cfg, key, value)
        else:
            cfg.method_params[key.removeprefix("method.")] = value
    if cfg.seeds < 1:
        raise RetainError(f"bad value {cfg.seeds} for seeds: expected at least 1")
    if cfg.eval_shards < 1:
        raise RetainError(f"bad value {cfg.eval_shards} for eval_shards: expected at least 1")
    if cfg.executor not in EXECUTORS:
        raise RetainError(f"unknown executor {cfg.executor!r}; valid: {', '.join(EXECUTORS)}")
    if cfg.spatial_episodes < 0:
        raise RetainError(f"bad value {cfg.spatial_episodes} for spatial_episodes: expected 0 "
                          "(no spatial probe) or more")
    if cfg.foundation_eval_every < 1:
        raise RetainError(f"bad value {cfg.foundation_eval_every} for foundation_eval_every: "
                          "expected 1 (every stage) or more (stage 0, every N-th and the last)")
    if cfg.jobs < 0:
        raise RetainError(f"bad value {cfg.jobs} for jobs: expected 0 (as many as the cores "
                          "allow) or more")
    return cfg
