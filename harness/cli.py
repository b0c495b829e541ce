"""`python -m harness bench METHOD=sft PROFILE=quick SEED=1 steps_per_task=2000`.

Everything a user can get wrong is checked before the first demo is generated: the benchmark,
profile, method, every override, every task name, and the tracking store.
"""

from __future__ import annotations

import copy
import dataclasses
import itertools
import os
import sys
import time
from dataclasses import dataclass, field

import torch

from harness.config import (
    BENCH_KEYS,
    SHARED_BY_SWEEP_POINTS,
    BenchConfig,
    base_config,
    changed_settings,
    resolve,
    run_label,
    set_field,
    setting_text,
)
from harness.errors import USER_ERRORS, RetainError
from harness.executors import available_cores
from harness.jobs import Job
from harness.validation import check
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
        return run_label(self.method.name, " ".join(p for p in (self.point, self.changed) if p))


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
    return Plan(cfg, variants)


def _portable(spec: str) -> str:
    """`file.py:Class` with an absolute path, so a job in another process finds the file."""
    module, sep, cls = spec.rpartition(":")
    if sep and module.endswith(".py"):
        return f"{os.path.abspath(module)}:{cls}"
    return spec


def _changed(run_cfg: BenchConfig, base: BenchConfig, method: Method, own: dict,
             point: dict) -> str:
    """Settings given outside GRID that change this run's results: benchmark settings away
    from the benchmark's YAML (after its profile), method hyperparameters away from defaults."""
    changed = changed_settings(run_cfg, base)
    defaults = dataclasses.asdict(type(method.config)())
    hyper = method.hyperparameters()
    changed.update({k: setting_text(hyper[k]) for k in own if hyper[k] != defaults.get(k)})
    return " ".join(f"{k}={v}" for k, v in changed.items() if k not in point)


def bench(args: list[str]) -> int:
    """Demos, then each seed's foundation, then one job per (seed, variant) on the executor."""
    p = plan(args)
    return execute(p, [(seed, v) for seed in p.cfg.seed_list() for v in p.variants],
                   " ".join(args))


def execute(p: Plan, runs: list[tuple[int, Variant]], command: str) -> int:
    """Run the given (seed, variant) jobs of a plan: the data, each of their seeds' foundations,
    then the jobs on the executor. `harness bench` runs all of a plan's; a study (harness.study)
    only the ones not finished yet, of several plans on one benchmark merged into one."""
    from harness.data import prepare_data
    from harness.executors import make_executor, plan_slots
    from harness.jobs import (
        FoundationJob,
        Tracking,
        build_foundation,
        invocation_key,
        provenance_params,
        run_job,
    )
    from harness.run_outputs import summary_table
    from harness.tracking import Tracker, finished_keys, git_commit, package_versions

    cfg = p.cfg
    torch.set_num_threads(cfg.torch_threads)
    tracker = Tracker(cfg.results_dir, experiment=cfg.name)
    suite = get_suite(cfg.suite)
    provenance = {"git_commit": git_commit(), "versions": package_versions(),
                  "command": command, "seeds": cfg.seed_list()}
    keyed = [(seed, variant, variant_job_key(variant, suite, seed)) for seed, variant in runs]
    seeds = sorted({seed for seed, _ in runs})
    parent = tracker.continue_or_start_run(invocation_key(cfg.name, [k for *_, k in keyed]),
                                           f"{cfg.name}:{cfg.method}", provenance["git_commit"],
                                           tags={"benchmark": cfg.name})
    tracker.log_params(parent, provenance_params(cfg, provenance))
    tracking = Tracking(tracker.uri, parent, provenance)
    slots = plan_slots(cfg, len(keyed))
    usage = CpuUsage.now()
    start = usage.wall
    status, children = "FAILED", []
    try:
        print(f"[retain] {cfg.name}: {len(cfg.foundation_tasks)} foundation + "
              f"{len(cfg.stream_tasks)} stream tasks, runs "
              f"{list(dict.fromkeys(v.label for _, v in runs))}, "
              f"seeds {seeds}; {len(keyed)} jobs, executor {cfg.executor} "
              f"({_slots_text(cfg, slots)})", flush=True)
        make_missing_demos(cfg, suite)
        data = prepare_data(cfg, suite)
        print(f"[retain] demos ready ({time.time() - start:.0f}s)", flush=True)
        earlier = finished_keys(tracker.client, tracker.experiment_id, [k for *_, k in keyed])
        jobs = []
        for seed, variant, key in keyed:
            child = _child_run(tracker, variant, seed, key, parent, provenance)
            children.append(child)
            jobs.append(Job(variant.cfg, variant.spec, variant.params, variant.point,
                            variant.label, seed, key, child, tracking, slots.eval_workers))
        executor = make_executor(cfg, slots, suite, data)
        try:
            foundations = [FoundationJob(cfg, seed, tracking, slots.eval_workers)
                           for seed in seeds]
            for i, success in executor.run(build_foundation, foundations):
                print(f"[retain] seed {foundations[i].seed}: foundation ready, stage-0 "
                      f"foundation success {success:.3f} ({time.time() - start:.0f}s)", flush=True)
            results = [None] * len(jobs)
            progress = Progress(len(jobs), len(earlier))
            for i, r in executor.run(run_job, jobs):
                results[i] = r
                count, times = progress.done_one(jobs[i].key in earlier)
                print(f"[retain] {count} {jobs[i].label} seed {r.seed}: "
                      f"foundation success {r.metrics['foundation_success_stage0']:.3f} -> "
                      f"{r.metrics['retention']:.3f}, plasticity {r.metrics['plasticity']:.3f} "
                      f"({times})", flush=True)
        finally:
            executor.close()
        print("\n" + summary_table(results))
        for r in results:
            print(f"  {r.method} seed {r.seed}: {r.run_dir}/")
        print(f"  MLflow: {tracker.uri} (experiment {cfg.name!r}); `make ui` to browse")
        print(f"[retain] {len(jobs)} jobs in {_duration(time.time() - start)} wall time, "
              f"{usage.text()}", flush=True)
        status = "FINISHED"
        return 0
    except KeyboardInterrupt:
        status = "KILLED"
        raise
    finally:
        for child in children:  # a job that did not end its run (its worker was lost) failed
            if tracker.status(child) == "RUNNING":
                tracker.end_run(child, "FAILED" if status != "KILLED" else status)
        tracker.end_run(parent, status)


class Progress:
    """Jobs done of all, and the time left estimated from the rate of the jobs run now (a job
    finished by an earlier invocation returns at once and says nothing of the rate)."""

    def __init__(self, total: int, finished_earlier: int = 0):
        self.total, self.start = total, time.time()
        self.done, self.ran, self.to_run = 0, 0, total - finished_earlier

    def done_one(self, earlier: bool = False) -> tuple[str, str]:
        """("k/n", the times so far) for the job just done."""
        self.done += 1
        if earlier:
            return f"{self.done}/{self.total}", "finished earlier"
        self.ran += 1
        elapsed = time.time() - self.start
        left = elapsed / self.ran * (self.to_run - self.ran)
        return (f"{self.done}/{self.total}",
                f"{_duration(elapsed)} elapsed, about {_duration(left)} left")


def _duration(seconds: float) -> str:
    minutes, secs = divmod(int(round(seconds)), 60)
    return f"{minutes}m{secs:02d}s" if minutes else f"{secs}s"


@dataclass
class CpuUsage:
    """How busy the cores were over a run, a speed-up's other half: the CPU time of this process
    and of its finished children (local workers; Ray's workers are not its children), and the
    whole machine's busy share (Linux). Every counter is cumulative since its process (or the
    machine) started, so a run's share is the change from these readings, taken at its start:
    the totals also held the imports before the run and any earlier run in the same process
    (a one-second rerun once read "CPU time 11s (720% of 2 cores)")."""

    wall: float
    cpu: float
    machine: tuple[float, float] | None

    @classmethod
    def now(cls) -> CpuUsage:
        return cls(time.time(), _process_cpu(), _machine_cpu())

    def since(self) -> tuple[float, float]:
        """(wall seconds, CPU seconds) from these readings to now."""
        return time.time() - self.wall, _process_cpu() - self.cpu

    def text(self) -> str:
        wall, cpu = self.since()
        cores = available_cores()
        text = f"CPU time {_duration(cpu)} ({cpu / max(wall, 1e-9) / cores:.0%} of {cores} cores)"
        end = _machine_cpu()
        if self.machine and end and end[1] > self.machine[1]:
            busy = (end[0] - self.machine[0]) / (end[1] - self.machine[1])
            text += f", machine busy {busy:.0%}"
        return text


def _process_cpu() -> float:
    """CPU seconds of this process and of its children that have been waited for, so far."""
    usage = os.times()
    return usage.user + usage.system + usage.children_user + usage.children_system


def _machine_cpu() -> tuple[float, float] | None:
    """(busy, total) jiffies of all cores since boot, from /proc/stat; None elsewhere."""
    try:
        with open("/proc/stat") as f:
            values = [float(v) for v in f.readline().split()[1:]]
    except (OSError, ValueError):
        return None
    idle = values[3] + (values[4] if len(values) > 4 else 0.0)  # idle + iowait
    return sum(values) - idle, sum(values)


def _slots_text(cfg: BenchConfig, slots) -> str:
    if cfg.executor == "ray":
        return "Ray tasks" + (f", {cfg.jobs} at once" if cfg.jobs else "")
    each = "evaluation worker" + ("s" if slots.eval_workers != 1 else "")
    return f"{slots.parallel} at once, {slots.eval_workers} {each} each"


def make_missing_demos(cfg, suite) -> None:
    """The demo files not cached yet, one worker process per core (a benchmark's first run is
    mostly expert rollouts: LIBERO's nine libero-quick tasks took 9 min in one process). The
    serial executor leaves them to `prepare_data`, one after another in this process."""
    from harness.data import make_demo_file, missing_demo_jobs
    from harness.executors import LocalExecutor

    jobs = missing_demo_jobs(cfg, suite)
    workers = min(available_cores(), len(jobs))
    if cfg.executor == "serial" or workers < 2:
        return
    start, pool = time.time(), LocalExecutor(workers)
    try:
        for done, (i, n) in enumerate(pool.run(make_demo_file, jobs), 1):
            print(f"[retain] {jobs[i].label}: {n} episodes [{done}/{len(jobs)} files, "
                  f"{time.time() - start:.0f}s]", flush=True)
    finally:
        pool.close()


def variant_job_key(variant: Variant, suite, seed: int) -> str:
    """The job's identity (harness.jobs.job_key): its MLflow run carries it as a tag."""
    from harness.foundation import foundation_key
    from harness.jobs import job_key
    from harness.runner import run_settings_key

    run_key = run_settings_key(variant.cfg, variant.method, foundation_key(variant.cfg, suite, seed))
    return job_key(run_key, seed, variant.label)


def _child_run(tracker, variant: Variant, seed: int, key: str, parent: str, provenance) -> str:
    """The job's MLflow run: the one an earlier (killed) attempt started, or a new one."""
    from harness.jobs import provenance_params

    cfg, method = variant.cfg, variant.method
    tags = {"method": method.name, "seed": str(seed), "benchmark": cfg.name, "label": variant.label}
    tags["needs"] = method.needs()  # past data, reference copy, task identity: the report marks it
    if variant.point:
        tags["sweep_point"] = variant.point
    child = tracker.continue_or_start_run(key, f"{variant.label}/seed{seed}",
                                          provenance["git_commit"], parent_id=parent, tags=tags)
    tracker.log_params(child, {**provenance_params(cfg, provenance),
                               **{f"method.{k}": v for k, v in method.hyperparameters().items()},
                               "method": method.name, "seed": seed})
    return child


def _study(args: list[str]) -> int:
    from harness.study import study

    return study(args)


def _lerobot_export(args: list[str]) -> int:
    from harness.lerobot.export import main as export_main

    return export_main(args)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    commands = {"bench": bench, "study": _study, "lerobot-export": _lerobot_export}
    if not argv or argv[0] not in commands:
        print(f"usage: python -m harness {{{','.join(commands)}}} [KEY=VALUE ...]", file=sys.stderr)
        return 2
    try:
        return commands[argv[0]](argv[1:])
    except USER_ERRORS as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted; finished stages are kept and the same command resumes", file=sys.stderr)
        return 130
