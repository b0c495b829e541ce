"""A comparison as a list of jobs: one per (seed, method, sweep point), after one foundation job
per seed. Each job is plain data and one function runs it in whatever process an executor gives
it (this one, a local worker process, a Ray worker on another machine).

Why jobs carry no live objects: a job must run the same anywhere, and be retried after its
process is lost. It rebuilds what it needs from the config and the shared cache (demos and the
seed's foundation are content-addressed there), continues its stream from the last stage
checkpoint in its run directory, and continues its own MLflow run (`run_id`).
"""

from __future__ import annotations

import hashlib
import json
import math
import os
from contextlib import nullcontext
from dataclasses import dataclass, replace
from typing import Any

import torch

from harness.common.errors import RetainError
from harness.config.benchmark import BenchConfig


@dataclass
class Tracking:
    """Where a job logs: the store, the experiment, the invocation's parent run."""

    uri: str
    parent_id: str
    provenance: dict  # git commit, package versions, command, seeds


@dataclass
class FoundationJob:
    """Pre-train (or find in the cache) one seed's foundation and its stage-0 evaluation."""

    cfg: BenchConfig
    seed: int
    tracking: Tracking
    eval_workers: int = 1

    label = "foundation"

    @property
    def cpus(self) -> int:
        return max(self.cfg.torch_threads, self.eval_workers)


@dataclass
class Job:
    """One (seed, method, sweep point): the stream of one method from the seed's foundation."""

    cfg: BenchConfig  # this run's config (a sweep point may change lr)
    method_spec: str  # a registered name or module.path:ClassName, imported where the job runs
    method_params: dict[str, Any]
    point: str  # "kappa=0.1", or "" outside a sweep
    label: str  # its name in tables and its directory: "sft", "consft[kappa=0.1]"
    seed: int
    key: str  # job_key(): the tag its MLflow run is found by
    run_id: str  # the MLflow child run it continues
    tracking: Tracking
    eval_workers: int = 1

    @property
    def cpus(self) -> int:
        """Cores it keeps busy: training threads, then its evaluation processes."""
        return max(self.cfg.torch_threads, self.eval_workers)


def with_absolute_paths(job: Job | FoundationJob) -> Job | FoundationJob:
    """The job with its folders made absolute here. Why: a Ray worker starts in the folder its
    node's `ray start` ran in, not the driver's, so a relative `results_dir=results` would write
    each node's share of the results somewhere else."""
    cfg = job.cfg
    folders = {k: os.path.abspath(v) for k in ("results_dir", "cache_dir", "demos_dir")
               if (v := getattr(cfg, k))}
    return replace(job, cfg=replace(cfg, **folders))


def job_key(run_key: str, seed: int, label: str) -> str:
    """A job's identity: its settings (runner.run_settings_key), seed and label."""
    return _hash([run_key, seed, label])


def invocation_key(name: str, job_keys: list[str]) -> str:
    """The parent run's identity: the same command (the same jobs) continues the same parent."""
    return _hash([name, sorted(job_keys)])


def _hash(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True).encode()).hexdigest()[:16]


def build_foundation(job: FoundationJob, evaluator=None, data=None) -> float:
    """The seed's foundation, trained into the cache or found there; its stage-0 foundation
    success. Its training curve goes to the parent run."""
    from harness.data.prepare import prepare_data
    from harness.evaluate.stages import make_evaluator
    from harness.protocol.foundation import load_or_train_foundation
    from harness.track.tracking import BatchedMetrics, Tracker
    from suites import get_suite

    cfg = job.cfg
    torch.set_num_threads(cfg.torch_threads)
    suite = get_suite(cfg.suite)
    data = data if data is not None else prepare_data(cfg, suite)
    tracker = Tracker(cfg.results_dir, cfg.name, job.tracking.uri)
    curve = BatchedMetrics(tracker, job.tracking.parent_id, prefix=f"foundation_seed{job.seed}/")
    own = evaluator is None
    with make_evaluator(cfg, suite, job.eval_workers) if own else nullcontext(evaluator) as ev:
        foundation = load_or_train_foundation(cfg, suite, data, job.seed, ev, log=curve)
    curve.flush()
    return foundation_success(cfg, foundation.stage0)


def run_job(job: Job, evaluator=None, data=None):
    """Run (or continue) one job's stream and write its outputs; returns its RunResult.

    `evaluator` and `data` are the serial executor's, shared by its jobs; elsewhere the job
    makes its own from the config and the cache."""
    from harness.data.prepare import prepare_data
    from harness.evaluate.stages import make_evaluator
    from harness.protocol.foundation import load_or_train_foundation
    from harness.protocol.stream import make_method, run_stream
    from harness.track.run_outputs import write_run_outputs
    from harness.track.tracking import BatchedMetrics, Tracker, machine
    from methods import get_method
    from suites import get_suite

    cfg, seed = job.cfg, job.seed
    torch.set_num_threads(cfg.torch_threads)
    try:
        method = make_method(get_method(job.method_spec), job.method_params)
    except ValueError as exc:
        raise RetainError(str(exc)) from None
    suite = get_suite(cfg.suite)
    data = data if data is not None else prepare_data(cfg, suite)
    tracker = Tracker(cfg.results_dir, cfg.name, job.tracking.uri)
    child = job.run_id
    logger = BatchedMetrics(tracker, child)
    status = "FAILED"
    try:
        # the stages an earlier attempt logged; held-out losses are logged at every stage, while
        # foundation success is NaN (not logged) where the foundation was not rolled out
        logged = tracker.logged_steps(child, f"heldout_loss/{cfg.foundation_tasks[0]}")

        def log_stage(record) -> None:
            if record.stage in logged:
                return
            logged.add(record.stage)
            tracker.log_metric_rows(child, [(record.stage, stage_metrics(cfg, record))])
            if record.curve:
                tracker.log_metric_rows(child, [(n, {f"curve_success/{record.task}": v})
                                                for n, v in zip(record.curve_steps, record.curve)])

        def on_stage(record) -> None:
            success = foundation_success(cfg, record)
            print(f"[retain] {job.label} seed {seed}: stage {record.stage} ({record.task}) done, "
                  + ("foundation not rolled out at this stage" if math.isnan(success)
                     else f"foundation success {success:.3f}"), flush=True)
            logger.flush()
            log_stage(record)

        own = evaluator is None
        with make_evaluator(cfg, suite, job.eval_workers) if own else nullcontext(evaluator) as ev:
            foundation = load_or_train_foundation(cfg, suite, data, seed, ev)
            log_stage(foundation.stage0)
            result = run_stream(cfg, suite, data, foundation, method, seed, ev, job.label,
                                logger, on_stage)
        for record in result.stages:  # stages resumed from checkpoints were not logged yet
            log_stage(record)
        logger.flush()
        if cfg.num_stages not in tracker.logged_steps(child, "retention"):
            tracker.log_metrics(child, result.metrics, step=cfg.num_stages)
        # a job resumed at another commit: its files name every commit, as its MLflow run does;
        # the machine is this process's (a Ray worker's, not the driver's), the one that finished
        provenance = {**job.tracking.provenance, "git_commits": tracker.commits(child),
                      "machine": machine()}
        tracker.set_tags(child, {f"retain.machine.{k}": v for k, v in provenance["machine"].items()})
        unsaid = [n for n in result.observed_needs if n not in method.needs()]
        if unsaid:  # the class attributes did not say it: the report marks what it kept
            print(f"[retain] note: {job.label} keeps {' and '.join(_KEPT[n] for n in unsaid)} "
                  f"but does not set {', '.join(_FLAG[n] for n in unsaid)} = True; its runs "
                  f"are marked needs: {method.needs(result.observed_needs)}", flush=True)
            tracker.set_tags(child, {"needs": method.needs(result.observed_needs)})
        paths = write_run_outputs(cfg, result, provenance)
        for path in paths.values():
            tracker.log_artifact(child, path)
        if cfg.videos and (result.run_dir / "videos").is_dir():
            tracker.log_artifacts(child, result.run_dir / "videos", "videos")
        status = "FINISHED"
        return result
    finally:
        tracker.end_run(child, status)


_KEPT = {"past data": "samples of earlier tasks", "reference copy": "a copy of the network"}
_FLAG = {"past data": "uses_past_data", "reference copy": "uses_reference_copy"}


def foundation_success(cfg: BenchConfig, record) -> float:
    """Mean success over the foundation tasks; NaN at a stage that did not roll them out."""
    return sum(record.success[t] for t in cfg.foundation_tasks) / len(cfg.foundation_tasks)


def stage_metrics(cfg: BenchConfig, record) -> dict[str, float]:
    m = {f"success/{t}": v for t, v in record.success.items()}
    m.update({f"heldout_loss/{t}": v for t, v in record.heldout_loss.items()})
    m.update({f"update/{k}": v for k, v in record.updates.items()})
    m.update({f"spatial_success/{t}": v for t, v in record.spatial_success.items()})
    m["foundation_success"] = foundation_success(cfg, record)
    m["stage_train_loss"] = record.train_loss
    if record.stage > 0 and record.steps_used > 0:  # not the foundation's, nor a stage record
        # from before steps were counted; fewer than steps_per_task: until_success stopped it
        m["stage_steps"] = record.steps_used
    if record.check_success:  # until_success's last check: the success the stage stopped at
        m["stage_check_success"] = record.check_success[-1]
    return m


def provenance_params(cfg: BenchConfig, provenance: dict) -> dict:
    """The resolved config, git commit and package versions, as MLflow params."""
    used = provenance.get("demos_used")  # only where demos_dir held fewer than demos_per_task
    return {**{f"config.{k}": v for k, v in cfg.as_dict().items()},
            "git_commit": provenance["git_commit"],
            **{f"version.{k}": v for k, v in provenance["versions"].items()},
            **({"demos_used": " ".join(f"{t}={n}" for t, n in used.items())} if used else {})}
