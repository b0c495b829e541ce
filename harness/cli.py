"""`python -m harness bench METHOD=sft PROFILE=quick SEED=1 steps_per_task=2000`.

Everything a user can get wrong is checked before the first demo is generated: the benchmark,
profile, method, every override, every task name, and the tracking store.
"""

from __future__ import annotations

import copy
import itertools
import sys
import time
from dataclasses import dataclass

import torch

from harness.config import (
    BENCH_KEYS,
    SHARED_BY_SWEEP_POINTS,
    BenchConfig,
    resolve,
    run_label,
    set_field,
)
from harness.errors import RetainError
from methods import Method, get_method, method_names
from suites import UnknownName, get_suite


@dataclass
class Variant:
    """One method at one point of a sweep: what a child run is."""

    cfg: BenchConfig  # this run's resolved config (a sweep may change lr, say)
    method: Method
    point: str = ""  # "kappa=0.1 w_min=0.05", or "" outside a sweep

    @property
    def label(self) -> str:
        """The run's name in tables and its directory under results/<benchmark>/."""
        return run_label(self.method.name, self.point)


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
    from harness.runner import make_method

    cfg = resolve(args)
    try:
        suite = get_suite(cfg.suite)
        for task in cfg.foundation_tasks + cfg.stream_tasks:
            suite.check_task(task)
    except UnknownName as exc:
        raise RetainError(str(exc)) from None
    both = sorted(set(cfg.foundation_tasks) & set(cfg.stream_tasks))
    if both:
        raise RetainError(f"task {both[0]!r} is both a foundation and a stream task in {cfg.name}")
    if not cfg.stream_tasks or not cfg.foundation_tasks:
        raise RetainError(f"benchmark {cfg.name} needs at least one foundation and one stream task")
    from harness.device import resolve_device
    from harness.foundation import policy_config

    resolve_device(cfg.device)
    try:
        policy_config(cfg, suite)  # an unknown policy or size fails here, naming the valid ones
    except ValueError as exc:
        raise RetainError(str(exc).splitlines()[0]) from None
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
        for key in params:  # a setting must belong to at least one of the methods
            if not any(key in c.Config.__dataclass_fields__ for c in classes):
                make_method(classes[0], {key: params[key]})
        label = " ".join(f"{k}={v}" for k, v in point.items())
        for cls in classes:
            own = {k: v for k, v in params.items() if k in cls.Config.__dataclass_fields__}
            variants.append(Variant(run_cfg, make_method(cls, own), label))
    return Plan(cfg, variants)


def bench(args: list[str]) -> int:
    from harness.data import prepare_data
    from harness.evaluation import Evaluator
    from harness.foundation import load_or_train_foundation
    from harness.run_outputs import summary_table
    from harness.stages import eval_settings
    from harness.tracking import BatchedMetrics, Tracker, git_commit, package_versions

    p = plan(args)
    cfg = p.cfg
    torch.set_num_threads(cfg.torch_threads)
    tracker = Tracker(cfg.results_dir, experiment=cfg.name)
    provenance = {"git_commit": git_commit(), "versions": package_versions(),
                  "command": " ".join(args), "seeds": cfg.seed_list()}
    parent = tracker.start_run(f"{cfg.name}:{cfg.method}", tags={"benchmark": cfg.name})
    tracker.log_params(parent, _provenance_params(cfg, provenance))
    start = time.time()
    status = "FAILED"
    try:
        suite = get_suite(cfg.suite)
        print(f"[retain] {cfg.name}: {len(cfg.foundation_tasks)} foundation + "
              f"{len(cfg.stream_tasks)} stream tasks, runs {[v.label for v in p.variants]}, "
              f"seeds {cfg.seed_list()}", flush=True)
        data = prepare_data(cfg, suite)
        print(f"[retain] demos ready ({time.time() - start:.0f}s)", flush=True)
        results = []
        with Evaluator(suite, eval_settings(cfg), cfg.workers(), cfg.torch_threads) as evaluator:
            for seed in cfg.seed_list():
                curve = BatchedMetrics(tracker, parent, prefix=f"foundation_seed{seed}/")
                foundation = load_or_train_foundation(cfg, suite, data, seed, evaluator, log=curve)
                curve.flush()
                print(f"[retain] seed {seed}: foundation ready, stage-0 foundation success "
                      f"{_foundation_success(cfg, foundation.stage0):.3f} "
                      f"({time.time() - start:.0f}s)", flush=True)
                for variant in p.variants:
                    r = _run_one(variant, suite, data, foundation, seed, evaluator, tracker,
                                 parent, provenance)
                    results.append(r)
                    print(f"[retain] {variant.label} seed {seed}: foundation success "
                          f"{r.metrics['foundation_success_stage0']:.3f} -> "
                          f"{r.metrics['retention']:.3f}, plasticity {r.metrics['plasticity']:.3f} "
                          f"({time.time() - start:.0f}s)", flush=True)
        print("\n" + summary_table(results))
        for r in results:
            print(f"  {r.method} seed {r.seed}: {r.run_dir}/")
        print(f"  MLflow: {tracker.uri} (experiment {cfg.name!r}); `make ui` to browse")
        status = "FINISHED"
        return 0
    finally:
        tracker.end_run(parent, status)


def _foundation_success(cfg: BenchConfig, record) -> float:
    return sum(record.success[t] for t in cfg.foundation_tasks) / len(cfg.foundation_tasks)


def _provenance_params(cfg: BenchConfig, provenance: dict) -> dict:
    """The resolved config, git commit and package versions, as MLflow params."""
    return {**{f"config.{k}": v for k, v in cfg.as_dict().items()},
            "git_commit": provenance["git_commit"],
            **{f"version.{k}": v for k, v in provenance["versions"].items()}}


def _run_one(variant: Variant, suite, data, foundation, seed, evaluator, tracker, parent,
             provenance):
    from harness.run_outputs import write_run_outputs
    from harness.runner import run_stream
    from harness.tracking import BatchedMetrics

    cfg, method = variant.cfg, variant.method
    tags = {"method": method.name, "seed": str(seed), "benchmark": cfg.name, "label": variant.label}
    if variant.point:
        tags["sweep_point"] = variant.point
    child = tracker.start_run(f"{variant.label}/seed{seed}", parent_id=parent, tags=tags)
    tracker.log_params(child, {**_provenance_params(cfg, provenance),
                               **{f"method.{k}": v for k, v in method.hyperparameters().items()},
                               "method": method.name, "seed": seed})
    logger = BatchedMetrics(tracker, child)
    status = "FAILED"
    try:
        logged: set[int] = set()

        def log_stage(record) -> None:
            logged.add(record.stage)
            tracker.log_metric_rows(child, [(record.stage, _stage_metrics(cfg, record))])
            if record.curve:
                tracker.log_metric_rows(child, [(n, {f"curve_success/{record.task}": v})
                                                for n, v in zip(record.curve_steps, record.curve)])

        def on_stage(record) -> None:
            print(f"[retain] {variant.label} seed {seed}: stage {record.stage} ({record.task}) done, "
                  f"foundation success {_foundation_success(cfg, record):.3f}", flush=True)
            logger.flush()
            log_stage(record)

        log_stage(foundation.stage0)
        result = run_stream(cfg, suite, data, foundation, method, seed, evaluator, variant.label,
                            logger, on_stage)
        for record in result.stages:  # stages resumed from checkpoints were not logged yet
            if record.stage not in logged:
                log_stage(record)
        logger.flush()
        tracker.log_metrics(child, result.metrics, step=len(cfg.stream_tasks))
        paths = write_run_outputs(cfg, result, provenance)
        for path in paths.values():
            tracker.log_artifact(child, path)
        status = "FINISHED"
        return result
    finally:
        tracker.end_run(child, status)


def _stage_metrics(cfg, record) -> dict[str, float]:
    m = {f"success/{t}": v for t, v in record.success.items()}
    m.update({f"heldout_loss/{t}": v for t, v in record.heldout_loss.items()})
    m.update({f"update/{k}": v for k, v in record.updates.items()})
    m["foundation_success"] = _foundation_success(cfg, record)
    m["stage_train_loss"] = record.train_loss
    return m


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    commands = {"bench": bench}
    if not argv or argv[0] not in commands:
        print(f"usage: python -m harness {{{','.join(commands)}}} [KEY=VALUE ...]", file=sys.stderr)
        return 2
    try:
        return commands[argv[0]](argv[1:])
    except RetainError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted; finished stages are kept and the same command resumes", file=sys.stderr)
        return 130
