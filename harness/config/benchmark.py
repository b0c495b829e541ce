"""Benchmark configuration: named YAML files, profiles, and `key=value` overrides.

Resolution: BENCH (or the benchmark PROFILE stands for) -> the YAML file -> the profile's
scaling (tiny, paper) -> command-line overrides. Lower-case keys name a field of `BenchConfig`
or a hyperparameter of the method; a key that is neither is an error naming the valid keys.
"""

from __future__ import annotations

import dataclasses
import hashlib
import os
import types
import typing
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from annotated_types import Ge, Gt, Interval, MinLen, doc

from harness.common.errors import RetainError
from harness.config.validation import AtMost, check

BENCHMARK_DIR = Path(__file__).parents[1] / "benchmarks"
PROFILE_BENCHMARKS = {"quick": "mw-quick", "standard": "mw-standard", "tiny": "mw-quick",
                      "paper": "mw-standard"}


@dataclass
class BenchConfig:
    name: Annotated[str, MinLen(1)]
    suite: Annotated[str, MinLen(1)]  # a registered suite (plan checks the name)
    foundation_tasks: Annotated[list[str], MinLen(1)]
    stream_tasks: Annotated[list[str], MinLen(1)]
    demos_per_task: Annotated[int, Ge(1)] = 50
    heldout_demos_per_task: Annotated[int, Ge(1)] = 5
    eval_episodes: Annotated[int, Ge(1)] = 20
    # per task and stage, from widened initial states
    spatial_episodes: Annotated[int, Ge(0), doc("0: no spatial probe")] = 0
    # foundation tasks are rolled out at stage 0, every N-th stage and the last (stream tasks and
    # every held-out loss at every stage): a long stream's failed foundation episodes, each run to
    # the episode limit, are most of its evaluation time, and retention needs stages 0 and k only
    foundation_eval_every: Annotated[
        int, Ge(1), doc("1: every stage; N: stage 0, every N-th and the last")] = 1
    max_episode_steps: Annotated[int, Ge(1)] = 200
    # evaluation and check episodes stop after this many steps, below any task's own limit (a
    # smoke test of a slow suite, such as LIBERO with cameras on a CPU); demos keep their limits
    eval_step_cap: Annotated[int, Ge(0), doc("0: no cap")] = 0
    foundation_steps: Annotated[int, Ge(1)] = 4000
    steps_per_task: Annotated[int, Ge(1)] = 1500
    batch_size: Annotated[int, Ge(1)] = 256
    lr: Annotated[float, Gt(0)] = 3e-4
    weight_decay: Annotated[float, Ge(0)] = 0.0
    grad_clip: Annotated[float, Ge(0), doc("0: no clipping")] = 1.0
    # a registered policy (mlp, pi0) or module.path:Class / file.py:Class (plan checks it)
    policy: Annotated[str, MinLen(1)] = "mlp"
    policy_size: Annotated[str, MinLen(1)] = "default"
    # a LeRobot policy's checkpoint: a folder, or a hub id where the hub is reachable. It is the
    # foundation (evaluated at stage 0, never retrained); its config sets the chunk, the
    # cameras and their size (docs/lerobot.md). "": a random init at policy_size
    policy_path: str = ""
    chunk_size: Annotated[int, Ge(1)] = 4
    n_action_steps: Annotated[int, Ge(1), AtMost("chunk_size")] = 4
    cameras: bool = False
    image_size: Annotated[int, Ge(1)] = 84
    # how camera views are drawn (suites/render.py): the suites' own images, or fast ones a few
    # times cheaper on a CPU and slightly apart; nothing without cameras
    render: Literal["faithful", "fast"] = "faithful"
    profile: Literal["", "quick", "standard", "tiny", "paper"] = ""
    seed: Annotated[int, Ge(0)] = 0  # first seed
    seeds: Annotated[int, Ge(1)] = 1  # number of seeds: seed, seed + 1, ...
    method: Annotated[str, MinLen(1)] = "sft"
    method_params: dict[str, Any] = field(default_factory=dict)
    grid: str = ""  # a sweep: "kappa=0.1,0.25 w_min=0.05,0.2", one run per point and seed
    # kept apart from lr, so a sweep of lr shares one foundation
    foundation_lr: Annotated[float, Gt(0)] = 3e-4
    results_dir: Annotated[str, MinLen(1)] = "results"
    cache_dir: Annotated[str, MinLen(1)] = "cache"
    demos_dir: str = ""  # real LIBERO dataset files (<task>_demo.hdf5) to train on instead of experts
    progress: bool = True
    # at plan time, the policy computes its loss and one action chunk on one sample of the
    # suite's shapes (on the CPU: a published 3B checkpoint takes a minute and 16 GB there)
    dry_run: bool = True
    # intra-op threads per process; small CPU batches are slower with more
    torch_threads: Annotated[int, Ge(1)] = 1
    eval_workers: Annotated[int, Ge(0), doc("0: one per core")] = 0  # evaluation processes
    # simulators per task and worker (memory against batching)
    eval_envs_per_task: Annotated[int, Ge(1)] = 2
    # a stage's evaluation episodes are split into this many interleaved shares, each rolled out
    # in its own lockstep batch; fixed per run, so results never depend on how many workers (or
    # which executor) ran them. At most this many evaluation workers per job have work.
    eval_shards: Annotated[int, Ge(1)] = 2
    # evaluate the stage's task every N steps (LIBERO's FWT/NBT/AUC)
    learning_curve_every: Annotated[int, Ge(0), doc("0: off")] = 0
    # where a comparison's jobs run: serial, local (processes) or ray
    executor: Literal["serial", "local", "ray"] = "local"
    jobs: Annotated[int, Ge(0), doc("0: as many as the cores and memory allow")] = 0  # jobs at once
    # cpu, cuda, cuda:N or auto (CUDA when present; plan checks it); CUDA trains in bf16 autocast
    device: Annotated[str, MinLen(1)] = "cpu"
    compile: bool = False  # torch.compile the policy (worth it on a GPU)
    # the foundation's training saves a snapshot this often (wall time), so a killed base
    # resumes where it was rather than from step 0; results do not depend on it
    snapshot_minutes: Annotated[float, Gt(0)] = 10.0
    # -- the ConSFT paper's protocol (issue 36; docs/methods.md) ------------------------------
    # stream stages of several tasks trained together (the paper's target is a whole suite): how
    # many consecutive stream tasks each stage trains, [] for one task a stage. A benchmark file
    # writes it as nested lists, `stream_tasks: [[a, b, c], d]`, which sets this.
    stage_sizes: list[Annotated[int, Ge(1)]] = field(default_factory=list)
    # matched target success: a stage trains until its tasks reach this success on check
    # episodes of their own (rolled out every check_every steps), or for steps_per_task; 0: off
    until_success: Annotated[float, Interval(ge=0, le=1), doc("0: off")] = 0.0
    check_every: Annotated[int, Ge(1)] = 250
    # per task, from the suite's "check" split, apart from evaluation's
    check_episodes: Annotated[int, Ge(1)] = 10
    # the fine-tuning optimizer, the same for every method (the foundation keeps torch's AdamW
    # defaults); the paper's: betas (0.9, 0.95), eps 1e-8, lr 2.5e-5, weight decay 1e-10
    adam_beta1: Annotated[float, Interval(ge=0, lt=1)] = 0.9
    adam_beta2: Annotated[float, Interval(ge=0, lt=1)] = 0.999
    adam_eps: Annotated[float, Gt(0)] = 1e-8
    # the paper's held-out suites: name -> foundation tasks, each reported on its own and
    # averaged (its table 2: base, target, each held-out suite, the held-out average)
    heldout_groups: dict[str, list[str]] = field(default_factory=dict)
    # -- rollout videos (docs/reports.md): states recorded during the evaluation, frames drawn
    # after it; every chosen task's first video_episodes episodes at stage 0, after its own
    # stage and after the last. Off: nothing is recorded and nothing drawn
    videos: bool = False
    video_tasks: list[str] = field(default_factory=list)  # []: every task
    video_episodes: Annotated[int, Ge(1), AtMost("eval_episodes")] = 1
    video_size: Annotated[int, Interval(ge=32, le=1024), doc("pixels, square")] = 224
    # a camera of the suite's scenes (checked where the first frame is drawn: the scene names
    # them); "": the suite's view of the workspace (Meta-World corner, LIBERO agentview)
    video_camera: Annotated[str, doc('"": the suite\'s view of the workspace')] = ""
    video_fps: Annotated[int, Interval(ge=1, le=60)] = 20

    def stream_stages(self) -> list[list[str]]:
        """The stream tasks of each stage, in order (`stage_sizes`; one task a stage by default)."""
        sizes = self.stage_sizes or [1] * len(self.stream_tasks)
        starts = [sum(sizes[:i]) for i in range(len(sizes))]
        return [self.stream_tasks[a:a + n] for a, n in zip(starts, sizes)]

    @property
    def num_stages(self) -> int:
        """k: the number of stream stages."""
        return len(self.stage_sizes) if self.stage_sizes else len(self.stream_tasks)

    def all_tasks(self) -> list[str]:
        return self.foundation_tasks + self.stream_tasks
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
        return stage % self.foundation_eval_every == 0 or stage == self.num_stages

    def seed_list(self) -> list[int]:
        return list(range(self.seed, self.seed + self.seeds))

    def as_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


def stage_name(stage: int, tasks: list[str]) -> str:
    """What a stage trained on, in records and tables: its task, or for a group of tasks
    "stage<i>-<n>-tasks" (a valid MLflow key; the tasks themselves are in the config)."""
    return tasks[0] if len(tasks) == 1 else f"stage{stage}-{len(tasks)}-tasks"



# the settings an override or a GRID point sets on the config; any other key is a method's
BENCH_KEYS = frozenset(f.name for f in fields(BenchConfig)) - {"method_params", "grid"}

# settings of what every sweep point shares (the demos, the foundation, the evaluator), so a
# GRID cannot vary them: the points would record a value that was never used
SHARED_BY_SWEEP_POINTS = frozenset({
    "name", "suite", "foundation_tasks", "stream_tasks", "demos_per_task", "spatial_episodes",
    "heldout_demos_per_task", "eval_episodes", "foundation_eval_every", "max_episode_steps",
    "eval_step_cap",
    "foundation_steps", "foundation_lr", "policy_size", "chunk_size", "n_action_steps", "cameras",
    "image_size", "render", "profile", "seed", "seeds", "method", "results_dir", "cache_dir", "progress",
    "dry_run",
    "torch_threads", "eval_workers", "eval_envs_per_task", "eval_shards", "executor", "jobs",
    "policy", "policy_path", "device", "compile", "stage_sizes", "check_episodes", "heldout_groups",
    "snapshot_minutes", "videos", "video_tasks", "video_episodes", "video_size", "video_camera",
    "video_fps"})

# settings that cannot change a run's results (where it is written, how rollouts are split);
# torch_threads stays in: the summation order of a matrix product depends on it
NOT_IN_RUN_KEY = ("progress", "dry_run", "seed", "seeds", "method", "grid", "profile", "eval_workers",
                  "eval_envs_per_task", "results_dir", "cache_dir", "executor", "jobs",
                  "snapshot_minutes", "videos", "video_tasks", "video_episodes", "video_size",
                  "video_camera", "video_fps")

# settings added after results were recorded, at the value that changes nothing: there a run
# key leaves them out (earlier checkpoints still resume) and a report reads a run that never
# logged them as having it (its rows keep their labels)
QUIET_DEFAULTS: dict[str, Any] = {
    "spatial_episodes": 0, "eval_shards": 2, "foundation_eval_every": 1, "stage_sizes": [],
    "until_success": 0.0, "check_every": 250, "check_episodes": 10, "adam_beta1": 0.9,
    "adam_beta2": 0.999, "adam_eps": 1e-8, "heldout_groups": {}, "lerobot_keys": "",
    "lerobot_tasks": "", "lerobot_rotate_images": False, "policy_path": "", "eval_step_cap": 0,
    "render": "faithful"}


def run_key_settings(cfg: BenchConfig) -> dict[str, Any]:
    """The settings a run's results depend on (what its run key hashes)."""
    return {k: v for k, v in cfg.as_dict().items()
            if k not in NOT_IN_RUN_KEY and not (k in QUIET_DEFAULTS and v == QUIET_DEFAULTS[k])
            and not (k == "render" and not cfg.cameras)}  # no image, nothing rendered


def check_protocol(cfg: BenchConfig) -> None:
    """The settings of the paper's protocol that only make sense together."""
    if cfg.render != "faithful" and cfg.policy_path:
        raise RetainError(f"render={cfg.render} with policy_path={cfg.policy_path}: a published "
                          "checkpoint is evaluated on the images it was trained on; leave "
                          "render=faithful")
    if cfg.stage_sizes and sum(cfg.stage_sizes) != len(cfg.stream_tasks):
        raise RetainError(f"bad value {cfg.stage_sizes} for stage_sizes: expected sizes that add "
                          f"up to the {len(cfg.stream_tasks)} stream tasks")
    for name, tasks in cfg.heldout_groups.items():
        outside = [t for t in tasks if t not in cfg.foundation_tasks]
        if outside:
            raise RetainError(f"heldout_groups[{name!r}] names {outside[0]!r}, which is not a "
                              f"foundation task of {cfg.name}")
    unknown = [t for t in cfg.video_tasks if t not in cfg.all_tasks()]
    if unknown:
        raise RetainError(f"bad value {unknown[0]!r} in video_tasks: expected tasks of "
                          f"{cfg.name}: {', '.join(cfg.all_tasks())}")


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
    if isinstance(raw["stream_tasks"], list) and "stage_sizes" not in raw:
        stages = [s if isinstance(s, list) else [s] for s in raw["stream_tasks"]]
        raw["stream_tasks"] = [t for stage in stages for t in stage]
        if any(len(s) != 1 for s in stages):
            raw["stage_sizes"] = [len(s) for s in stages]
    cfg = BenchConfig(**{k: raw[k] for k in ("name", "suite", "foundation_tasks", "stream_tasks")})
    for key, value in raw.items():
        set_field(cfg, key, value)
    return cfg


def apply_profile(cfg: BenchConfig, profile: str) -> None:
    """`tiny` shrinks any benchmark to seconds (tests); `paper` is the GPU scale."""
    if profile == "tiny":
        cfg.foundation_tasks = cfg.foundation_tasks[:2]
        stages = [stage[:2] for stage in cfg.stream_stages()[:2]]
        cfg.stream_tasks = [t for stage in stages for t in stage]
        cfg.stage_sizes = [len(s) for s in stages] if cfg.stage_sizes else []
        cfg.heldout_groups = {name: kept for name, tasks in cfg.heldout_groups.items()
                              if (kept := [t for t in tasks if t in cfg.foundation_tasks])}
        cfg.check_every, cfg.check_episodes = 5, 2
        cfg.demos_per_task, cfg.heldout_demos_per_task, cfg.eval_episodes = 3, 1, 2
        cfg.spatial_episodes = min(cfg.spatial_episodes, 2)
        cfg.max_episode_steps = min(cfg.max_episode_steps, 100)
        cfg.eval_step_cap = min(cfg.eval_step_cap or 100, 100)  # LIBERO's own limits too
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


LABEL_VALUE_CHARS = 24  # a longer setting value is shown as its start and a hash (short_value)
LABEL_SETTINGS_CHARS = 80  # settings beyond these characters are folded into one hash


def run_label(method: str, setting: str = "") -> str:
    """A run's name in tables, plots and results/<benchmark>/: "consft[kappa=0.1]", or the
    method's name alone when it runs at its defaults. Settings past LABEL_SETTINGS_CHARS are
    folded into their keys and one hash of them all ("+demos_dir,lerobot_tasks@3f2a9c"), so a
    label stays a readable folder name; the full settings are in the run's params and
    config.yaml."""
    if len(setting) > LABEL_SETTINGS_CHARS:
        kept, folded = [], []
        for part in setting.split(" "):  # in order, each that still fits; the rest folded
            fits = len(" ".join(kept + [part])) <= LABEL_SETTINGS_CHARS * 2 // 3
            (kept if fits else folded).append(part)
        keys = ",".join(part.split("=", 1)[0] for part in folded)
        keys = keys if len(keys) <= 40 else f"{len(folded)}more"
        setting = " ".join(kept + [f"+{keys}@{_digest(setting)}"])
    return f"{method}[{setting}]" if setting else method


def setting_text(value: Any) -> str:
    """A setting's value as a label shows it: 0.0001, a,b for a list, a user's class given by
    file path as its class name and a hash of the path (`class_label`), and anything longer than
    LABEL_VALUE_CHARS shortened (`short_value`)."""
    if isinstance(value, (list, tuple)):
        return short_value(",".join(map(str, value)))
    return short_value(class_label(value) if isinstance(value, str) else str(value))


def short_value(text: str) -> str:
    """`text` itself when short; else its start (a path's last part) and 6 hex digits of a hash
    of the whole: /data/lerobot/physical-intelligence/libero -> libero@3f2a9c, a list of LIBERO
    task names -> its first 12 characters and the hash. Two values never share one."""
    text = str(text)
    if len(text) <= LABEL_VALUE_CHARS:
        return text
    head = text.rstrip("/").rsplit("/", 1)[-1] if "/" in text else text
    head = "".join(c if c.isalnum() or c in "-_.,:" else "_" for c in head)[:12]
    return f"{head}@{_digest(text)}"


def _digest(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()[:6]


def class_label(spec: str) -> str:
    """`/home/me/exp/conv_policy.py:ConvPolicy` -> `ConvPolicy@` and six hex digits: short enough
    for a table and a folder name, and two different files never share one (the digits hash the
    file's absolute path). A registered name or `module:Class` is kept as it is."""
    parsed = file_class_spec(spec)
    if parsed is None:
        return spec
    path, name = parsed
    return f"{name}@{hashlib.sha256(str(path).encode()).hexdigest()[:6]}"


def file_class_spec(spec: str) -> tuple[Path, str] | None:
    """`path/to/file.py:Class` -> (the file's absolute path, "Class"); None for any other spec."""
    module, sep, name = spec.rpartition(":")
    return (Path(module).expanduser().resolve(), name) if sep and module.endswith(".py") else None


def changed_settings(cfg: BenchConfig, base: BenchConfig) -> dict[str, str]:
    """The result-changing benchmark settings where `cfg` differs from `base` (the benchmark's
    YAML after its profile): what tells a run with `lr=1e-4` from one at the defaults."""
    ours, theirs = cfg.as_dict(), base.as_dict()
    return {k: setting_text(v) for k, v in ours.items()
            if k not in NOT_IN_RUN_KEY and k not in ("name", "method_params") and v != theirs[k]
            and not (k == "render" and not cfg.cameras)}


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
            element = typing.get_args(annotation)[0]
            return [coerce(key, v, element) if element is not str else str(v).strip()
                    for v in items if str(v).strip()]
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
    check(cfg)  # every field against its declared values (harness/config/validation.py)
    check_protocol(cfg)  # the paper's protocol settings that only make sense together
    return cfg
