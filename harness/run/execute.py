"""A plan's jobs run: the demos, each seed's foundation, then one job per (seed, variant) on
the executor, each with its MLflow run; progress and CPU use printed as they go."""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

import torch

from harness.config.benchmark import BenchConfig
from harness.run.executors import available_cores
from harness.run.jobs import Job
from harness.run.plan import Plan, Variant, variant_job_key
from suites import get_suite


def execute(p: Plan, runs: list[tuple[int, Variant]], command: str) -> int:
    """Run the given (seed, variant) jobs of a plan: the data, each of their seeds' foundations,
    then the jobs on the executor. `harness bench` runs all of a plan's; a study (harness.run.study)
    only the ones not finished yet, of several plans on one benchmark merged into one."""
    from harness.data.prepare import prepare_data, short_demos_text
    from harness.evaluate.recording import VideoSettings
    from harness.evaluate.videos import check_camera
    from harness.run.executors import (
        available_memory_mb,
        evaluation_worker_mb,
        make_executor,
        plan_slots,
    )
    from harness.run.jobs import (
        FoundationJob,
        Tracking,
        build_foundation,
        invocation_key,
        provenance_params,
        run_job,
    )
    from harness.track.run_outputs import summary_table
    from harness.track.tracking import Tracker, finished_keys, git_commit, package_versions

    cfg = p.cfg
    torch.set_num_threads(cfg.torch_threads)
    tracker = Tracker(cfg.results_dir, experiment=cfg.name)
    suite = get_suite(cfg.suite)
    provenance = {"git_commit": git_commit(), "versions": package_versions(),
                  "command": command, "seeds": cfg.seed_list()}
    keyed = [(seed, variant, variant_job_key(variant, suite, seed)) for seed, variant in runs]
    seeds = sorted({seed for seed, _ in runs})
    slots = plan_slots(cfg, len(keyed), worker_mb=evaluation_worker_mb(cfg, suite),
                       memory_mb=available_memory_mb())
    usage = CpuUsage.now()
    start = usage.wall
    print(f"[retain] {cfg.name}: {len(cfg.foundation_tasks)} foundation + "
          f"{len(cfg.stream_tasks)} stream tasks, runs "
          f"{list(dict.fromkeys(v.label for _, v in runs))}, "
          f"seeds {seeds}; {len(keyed)} jobs, executor {cfg.executor} "
          f"({_slots_text(cfg, slots)})", flush=True)
    for note in (slots.workers_note, slots.memory_note):
        if note:
            print(f"[retain] {note}", flush=True)
    # the data before any run: an error in it (a truncated file, a missing task) is one line
    # and leaves no FAILED run behind in MLflow; so is a video camera the scenes lack
    videos = VideoSettings.of(cfg)
    if videos is not None:
        check_camera(suite, videos)
    make_missing_demos(cfg, suite)
    data = prepare_data(cfg, suite)
    print(f"[retain] demos ready ({time.time() - start:.0f}s)", flush=True)
    short = data.short_of_demos(cfg.demos_per_task)
    if short:
        print(f"[retain] {short_demos_text(cfg, short)}", flush=True)
        provenance["demos_used"] = dict(data.demos_used)
    parent = tracker.continue_or_start_run(invocation_key(cfg.name, [k for *_, k in keyed]),
                                           f"{cfg.name}:{cfg.method}", provenance["git_commit"],
                                           tags={"benchmark": cfg.name})
    tracker.log_params(parent, provenance_params(cfg, provenance))
    tracking = Tracking(tracker.uri, parent, provenance)
    status, children = "FAILED", []
    try:
        earlier = finished_keys(tracker.client, tracker.experiment_id, [k for *_, k in keyed])
        jobs = []
        for seed, variant, key in keyed:
            child = _child_run(tracker, variant, seed, key, parent, provenance)
            children.append(child)
            jobs.append(Job(variant.cfg, variant.spec, variant.params, variant.point,
                            variant.label, seed, key, child, tracking, slots.eval_workers))
        if slots.parallel > 1:  # jobs sharing one terminal: progress as lines, not bars
            os.environ["RETAIN_PROGRESS"] = "lines"
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
        if cfg.videos:  # the videos are for watching: the page that shows them, built now
            print(f"  report page with the videos: {report_page(cfg)}", flush=True)
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


def report_page(cfg: BenchConfig) -> Path:
    """The experiment's report (`make report`), built from MLflow; its HTML page's path."""
    from harness.report.build import ReportSettings, build_report
    from harness.report.page import PAGE

    settings = ReportSettings(experiment=cfg.name, results_dir=cfg.results_dir, log_run=False)
    build_report(settings)
    return (settings.out_dir / PAGE).resolve()


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
    from harness.data.prepare import make_demo_file, missing_demo_jobs
    from harness.run.executors import LocalExecutor

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


def _child_run(tracker, variant: Variant, seed: int, key: str, parent: str, provenance) -> str:
    """The job's MLflow run: the one an earlier (killed) attempt started, or a new one."""
    from harness.run.jobs import provenance_params

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
