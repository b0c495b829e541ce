"""A command line resolved into a plan: the benchmark's config, then one `Variant` (method, sweep
point, changed settings) per run. Everything a user can get wrong is checked here, before the
first demo is generated: the benchmark, profile, method, every override, every task name."""

from __future__ import annotations

import copy
import dataclasses
import itertools
from dataclasses import dataclass, field

from harness.common.errors import RetainError
from harness.config.benchmark import (
    BENCH_KEYS,
    SHARED_BY_SWEEP_POINTS,
    BenchConfig,
    base_config,
    changed_settings,
    file_class_spec,
    parse_overrides,
    resolve,
    run_label,
    set_field,
    setting_text,
)
from harness.config.validation import check
from methods import Method, get_method, method_names
from suites import UnknownName, get_suite


@dataclass
class Variant:
    """One method at one point of a sweep: what a child run is."""

    cfg: BenchConfig  # this run's resolved config (a sweep may change lr, say)
    method: Method
    point: str = ""  # "kappa=0.1 w_min=0.05", or "" outside a sweep
    spec: str = ""  # the method as named on the command line (a job imports it from this)
    params: dict = field(default_factory=dict)  # its hyperparameters given on the command line
    changed: str = ""  # other result-changing settings away from the benchmark's: "lr=0.0001"

    @property
    def label(self) -> str:
        """The run's name in tables and its directory under results/<benchmark>/: the sweep
        point, then any other setting that differs from the benchmark's, so runs that differ
        in what they measure never share a directory."""
        return run_label(self.method.label, " ".join(p for p in (self.point, self.changed) if p))


@dataclass
class Plan:
    cfg: BenchConfig
    variants: list[Variant]


def parse_grid(grid: str) -> list[dict[str, str]]:
    """"kappa=0.1,0.25 w_min=0.05,0.2" -> the cartesian product, one dict per point."""
    axes = []
    for token in grid.replace(";", " ").split():
        key, sep, values = token.partition("=")
        items = [v for v in values.split(",") if v]
        if not sep or not key or not items:
            raise RetainError(f"malformed GRID entry {token!r}: expected key=v1,v2,...")
        axes.append([(key, v) for v in items])
    return [dict(point) for point in itertools.product(*axes)] if axes else [{}]


def plan(args: list[str]) -> Plan:
    """Resolve and validate everything; no simulator is stepped and nothing is written."""
    from harness.protocol.stream import make_method

    cfg = resolve(args)
    base = base_config(args)
    try:
        suite = get_suite(cfg.suite)
        for task in cfg.all_tasks():
            suite.check_task(task)
    except UnknownName as exc:
        raise RetainError(str(exc)) from None
    if cfg.spatial_episodes > 0:
        suite.check_spatial_probe()  # a suite without widened initial states says so now
    both = sorted(set(cfg.foundation_tasks) & set(cfg.stream_tasks))
    if both:
        raise RetainError(f"task {both[0]!r} is both a foundation and a stream task in {cfg.name}")
    if not cfg.stream_tasks or not cfg.foundation_tasks:
        raise RetainError(f"benchmark {cfg.name} needs at least one foundation and one stream task")
    given = parse_overrides(args)
    _cameras_for(cfg, base, given)
    from harness.protocol.foundation import check_takes_a_path

    try:
        check_takes_a_path(cfg)  # before the checkpoint is read: the error is about the policy
    except ValueError as exc:
        raise RetainError(str(exc)) from None
    if cfg.policy_path:  # the checkpoint fixes its chunk and cameras, for the labels' base too
        from harness.data.lerobot.checkpoint import adopt_checkpoint

        for key, value in adopt_checkpoint(cfg, suite, given).items():
            setattr(base, key, value)
    from harness.common.device import resolve_device
    from harness.protocol.foundation import policy_config

    resolve_device(cfg.device)
    try:  # an unknown policy or size fails here, naming the valid ones
        policy_settings = policy_config(cfg, suite)
    except ValueError as exc:
        raise RetainError(str(exc).splitlines()[0]) from None
    if cfg.dry_run:
        from harness.run.dry_run import dry_run_policy

        dry_run_policy(policy_settings, cfg, suite)
    if cfg.method == "all":
        names = ["sft"] + [n for n in method_names() if n != "sft"]
    else:
        names = [n.strip() for n in cfg.method.split(",") if n.strip()]
    try:
        classes = [get_method(n) for n in names]
    except ValueError as exc:
        raise RetainError(str(exc)) from None
    variants = []
    for point in parse_grid(cfg.grid):
        run_cfg = copy.deepcopy(cfg)
        params = dict(cfg.method_params)
        for key, value in point.items():
            if key in SHARED_BY_SWEEP_POINTS:
                raise RetainError(f"GRID cannot vary {key!r}: every sweep point shares the demos, "
                                  f"foundation and evaluation it sets; run it as separate benchmarks")
            if key in BENCH_KEYS:
                set_field(run_cfg, key, value)
            else:
                params[key] = value
        check(run_cfg)  # a GRID point's settings, as resolve() checked the command line's
        for key in params:  # a setting must belong to at least one of the methods
            if not any(key in c.Config.__dataclass_fields__ for c in classes):
                make_method(classes[0], {key: params[key]})
        label = " ".join(f"{k}={v}" for k, v in point.items())
        for name, cls in zip(names, classes):
            own = {k: v for k, v in params.items() if k in cls.Config.__dataclass_fields__}
            method = make_method(cls, own)
            changed = _changed(run_cfg, base, method, own, point)
            variants.append(Variant(run_cfg, method, label, _portable(name), own, changed))
    for variant in variants:
        try:
            variant.method.check_setup(policy_settings, variant.cfg.num_stages)
        except ValueError as exc:
            raise RetainError(str(exc).splitlines()[0]) from None
    return Plan(cfg, variants)


def _cameras_for(cfg: BenchConfig, base: BenchConfig, given: dict[str, str]) -> None:
    """A policy that reads camera images (`needs_cameras`: LeRobot's VLAs need at least one)
    turns them on, for the labels' base too; `cameras=false` given for it is refused."""
    from policies import get_policy

    try:
        needs = getattr(get_policy(cfg.policy), "needs_cameras", False)
    except ValueError:
        return  # an unknown policy is named below, with the valid ones
    if needs and not cfg.cameras:
        if "cameras" in given:
            raise RetainError(f"cameras={given['cameras']} for policy {cfg.policy!r}, which reads "
                              f"camera images: leave cameras on")
        cfg.cameras = base.cameras = True


def _portable(spec: str) -> str:
    """`file.py:Class` with an absolute path, so a job in another process finds the file."""
    parsed = file_class_spec(spec)
    return f"{parsed[0]}:{parsed[1]}" if parsed else spec


def _changed(run_cfg: BenchConfig, base: BenchConfig, method: Method, own: dict,
             point: dict) -> str:
    """Settings given outside GRID that change this run's results: benchmark settings away
    from the benchmark's YAML (after its profile), method hyperparameters away from defaults."""
    changed = changed_settings(run_cfg, base)
    if "policy_path" in changed:  # its folder's name and its weights' digest, not the path
        from policies.lerobot.checkpoint import checkpoint_identity, checkpoint_name

        path = run_cfg.policy_path
        changed["policy_path"] = f"{checkpoint_name(path)}@{checkpoint_identity(path)[:6]}"
    defaults = dataclasses.asdict(type(method.config)())
    hyper = method.hyperparameters()
    changed.update({k: setting_text(hyper[k]) for k in own
                    if hyper[k] != defaults.get(k) and k not in method.label_omits})
    return " ".join(f"{k}={v}" for k, v in changed.items() if k not in point)


def variant_run_key(variant: Variant, suite, seed: int) -> str:
    """What the job's stage checkpoints are made with (harness.protocol.stream.run_settings_key):
    its settings, its foundation and the suite's evaluation version."""
    from harness.protocol.foundation import foundation_key
    from harness.protocol.stream import run_settings_key

    return run_settings_key(variant.cfg, variant.method, foundation_key(variant.cfg, suite, seed),
                            suite.evaluation_version)


def variant_job_key(variant: Variant, suite, seed: int) -> str:
    """The job's identity (harness.run.jobs.job_key): its MLflow run carries it as a tag."""
    from harness.run.jobs import job_key

    return job_key(variant_run_key(variant, suite, seed), seed, variant.label)
