"""The stream loop for one (method, seed): fine-tune on each new task, evaluate everything,
checkpoint the stage atomically, and resume from the last finished stage when restarted."""

from __future__ import annotations

import dataclasses
import hashlib
import json
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from harness.common.errors import RetainError
from harness.common.seeding import derive_seed, generator
from harness.config.benchmark import BenchConfig, run_key_settings, set_field, stage_name
from harness.config.validation import check
from harness.data.prepare import BenchmarkData
from harness.evaluate.recording import VideoSettings
from harness.evaluate.rollouts import Evaluator
from harness.evaluate.stages import (
    StageRecord,
    evaluate_stage,
    load_checkpoint,
    save_checkpoint,
)
from harness.evaluate.videos import VideoWriter
from harness.measure.metrics import (
    by_stage,
    core_metrics,
    heldout_loss_ratio,
    libero_metrics,
    paper_metrics,
    spatial_metrics,
)
from harness.measure.updates import paper_sparsity, update_stats
from harness.protocol.foundation import Foundation, build_policy
from harness.train.trainer import TrainSettings, train_stage
from methods import Method, TaskContext
from methods.base import observed_needs, snapshot
from suites import Suite


@dataclass
class RunResult:
    method: str
    seed: int
    run_dir: Path
    stages: list[StageRecord]
    metrics: dict[str, float]
    tasks: list[str]
    layer_rows: list[dict]
    # what the method was seen keeping (methods.base.observed_needs): "past data", "reference
    # copy", whatever its class attributes declare
    observed_needs: list[str] = dataclasses.field(default_factory=list)

    def success_matrix(self) -> np.ndarray:
        return np.array([[s.success[t] for t in self.tasks] for s in self.stages])

    def spatial_success_matrix(self) -> np.ndarray | None:
        """S[stage, task]: success from the spatial probe's states; None when it was off."""
        if not all(s.spatial_success for s in self.stages):
            return None
        return np.array([[s.spatial_success[t] for t in self.tasks] for s in self.stages])

    def heldout_matrix(self) -> np.ndarray:
        return np.array([[s.heldout_loss[t] for t in self.tasks] for s in self.stages])


def make_method(cls: type[Method], params: dict) -> Method:
    """Instantiate with hyperparameters from the config; a typo, or a value outside the field's
    declared range (harness/config/validation.py), is an error naming the field, before the method is
    built."""
    config = cls.Config()
    valid = sorted(f.name for f in dataclasses.fields(config))
    bench = sorted(f.name for f in dataclasses.fields(BenchConfig) if f.name != "method_params")
    for key, value in params.items():
        if key not in valid:
            raise RetainError(
                f"unknown setting {key!r} for method {cls.name!r}; its hyperparameters: "
                f"{', '.join(valid) or '(none)'}; benchmark settings: {', '.join(bench)}"
            )
        set_field(config, key, value)
    check(config, owner=cls.name)
    try:
        return cls(config)
    except ValueError as exc:
        raise RetainError(str(exc).splitlines()[0]) from None


def run_dir(cfg: BenchConfig, label: str, seed: int) -> Path:
    """results/<benchmark>/<label>/seed<k>: runs that differ in a result-changing setting have
    different labels ("sft", "sft[lr=0.0001]"), so they never share a directory."""
    return Path(cfg.results_dir) / cfg.name / label.replace(" ", "_").replace("/", "_") / f"seed{seed}"


def run_stream(cfg: BenchConfig, suite: Suite, data: BenchmarkData, foundation: Foundation,
               method: Method, seed: int, evaluator: Evaluator, label: str, log_step=None,
               on_stage=None) -> RunResult:
    """Stages 1..k for one method and seed, resuming from checkpoints in the run directory.

    `log_step(global_step, metrics)` receives training metrics; `on_stage(record)` each new
    stage's record (both for tracking).
    """
    out = run_dir(cfg, label, seed)
    checkpoints = out / "stages"
    policy = build_policy(cfg, suite)
    policy.load_state_dict(foundation.policy_state)
    theta0 = snapshot(policy)  # the foundation's weights, just loaded
    stages = [foundation.stage0]

    def context(stage: int, task: str, train) -> TaskContext:
        return TaskContext(stage=stage, task=task, data=train, policy=policy,
                           foundation_loss=foundation.final_loss, steps=cfg.steps_per_task)

    run_key = run_settings_key(cfg, method, foundation.key, suite.evaluation_version)
    k = cfg.num_stages
    resumed = _last_finished(checkpoints, k, run_key)
    observed: list[str] = []
    if resumed is None:  # what a method keeps from stage 0 (a buffer, a Fisher) it takes now
        method.after_task(context(0, "foundation", data.combined(cfg.foundation_tasks)))
    else:
        saved = load_checkpoint(checkpoints / f"stage_{resumed}.pt")
        policy.load_state_dict(saved["policy"])
        method.load_state_dict(saved["method"])
        stages += [StageRecord(**r) for r in saved["records"]]
        observed = list(saved.get("observed_needs", []))
        if resumed < k:
            print(f"[retain] {label} seed {seed}: resuming after stage {resumed} of {k}", flush=True)
    layer_rows: list[dict] = []
    videos = run_videos(cfg, suite, foundation, out)
    settings = TrainSettings(cfg.steps_per_task, cfg.batch_size, cfg.lr, cfg.weight_decay,
                             cfg.grad_clip, (cfg.adam_beta1, cfg.adam_beta2), cfg.adam_eps)
    for stage, tasks in enumerate(cfg.stream_stages(), start=1):
        if stage <= len(stages) - 1:
            continue
        name = stage_name(stage, tasks)
        previous = snapshot(policy)
        torch.manual_seed(derive_seed(seed, "stage", stage))
        offset = cfg.foundation_steps + (stage - 1) * cfg.steps_per_task

        def log(step, metrics, offset=offset):
            if log_step is not None:
                log_step(offset + step, metrics)

        watch = StageWatch(cfg, policy, method, evaluator, data, seed, tasks, theta0,
                           stages[-1], log)
        shown = f"{label} seed {seed}: stage {stage}/{k} ({name})" if cfg.progress else ""
        result = train_stage(context(stage, name, data.combined(tasks)), method, settings,
                             generator(seed, "stage", stage), log, after_step=watch,
                             progress=shown)
        observed = list(dict.fromkeys(observed + observed_needs(method, policy, tasks)))
        record = evaluate_stage(policy, evaluator, cfg, data, seed, stage, name, method, videos)
        record.train_loss = result.final_loss
        watch.finish(record, result.steps)
        current = snapshot(policy)
        record.updates, layer_rows = update_stats(theta0, current)
        record.updates_stage, _ = update_stats(previous, current)
        stages.append(record)
        save_checkpoint(checkpoints / f"stage_{stage}.pt", {
            "run_key": run_key, "policy": policy.state_dict(), "method": method.state_dict(),
            "records": [s.as_dict() for s in stages[1:]], "observed_needs": observed,
        })
        if on_stage is not None:
            on_stage(record)
    if not layer_rows:
        _, layer_rows = update_stats(theta0, snapshot(policy))
    tasks = cfg.all_tasks()
    result = RunResult(label, seed, out, stages, {}, tasks, layer_rows, observed)
    result.metrics = summary_metrics(cfg, result)
    return result


def run_videos(cfg: BenchConfig, suite: Suite, foundation: Foundation, out: Path
               ) -> VideoWriter | None:
    """The run's video writer (None with videos off), its videos/ folder given stage 0's
    videos from the foundation's cache (the same for every method of the seed)."""
    settings = VideoSettings.of(cfg)
    if settings is None or foundation.videos is None:
        return None
    directory = out / "videos"
    directory.mkdir(parents=True, exist_ok=True)
    for path in foundation.videos.iterdir():
        shutil.copy2(path, directory / path.name)
    return VideoWriter(suite, settings, directory, cfg.eval_episodes)


# a check's success is a mean of per-task fractions, and 27 of 30 episodes over ten tasks comes
# out as 0.8999999999999998: rounding must not decide whether a stage reached its threshold
CHECK_TOLERANCE = 1e-9


class StageWatch:
    """What runs between a stage's steps (the trainer's `after_step`): the learning curve
    (`learning_curve_every`), matched-target stopping (`until_success`: the stage's tasks rolled
    out on their check episodes every `check_every` steps, stopping at the first check at the
    threshold) and the paper's sparsity (Eq. 8) against the foundation at every check."""

    def __init__(self, cfg: BenchConfig, policy, method: Method, evaluator: Evaluator,
                 data: BenchmarkData, seed: int, tasks: list[str], theta0, before: StageRecord,
                 log):
        self.cfg, self.policy, self.method, self.evaluator = cfg, policy, method, evaluator
        self.data, self.seed, self.tasks, self.theta0, self.log = data, seed, tasks, theta0, log
        self.curve_steps = [0]
        self.curve = [_mean(before.success[t] for t in tasks)]
        self.checks: list[tuple[int, float]] = []  # (steps done, check success)
        self.sparsity: list[tuple[int, float, dict[str, float]]] = []  # (steps, global, layers)

    def _rollout(self, split: str) -> float:
        result = self.evaluator.evaluate(self.method.mid_task_policy(self.policy), self.tasks,
                                         self.data.instructions, derive_seed(self.seed, "eval"),
                                         split=split)
        self.policy.train()
        return _mean(result[t].success_rate for t in self.tasks)

    def _measure_sparsity(self, done: int) -> None:
        # a method that wraps layers (LoRA) shows its merged weights, as evaluation sees them
        value, layers = paper_sparsity(self.theta0, snapshot(self.method.mid_task_policy(self.policy)))
        self.sparsity.append((done, value, layers))
        self.log(done - 1, {"sparsity/eq8": value})

    def __call__(self, done: int) -> bool:
        cfg = self.cfg
        if cfg.learning_curve_every > 0 and done % cfg.learning_curve_every == 0 \
                and done < cfg.steps_per_task:
            self.curve_steps.append(done)
            self.curve.append(self._rollout("eval"))
        if done % cfg.check_every != 0 or done >= cfg.steps_per_task:
            return False
        self._measure_sparsity(done)
        if cfg.until_success <= 0:
            return False
        success = self._rollout("check")
        self.checks.append((done, success))
        self.log(done - 1, {"check/success": success})
        return success >= cfg.until_success - CHECK_TOLERANCE

    def finish(self, record: StageRecord, steps: int) -> None:
        """The stage's record gets its steps, its checks, its curve and its sparsity track."""
        record.steps_used = steps
        record.check_steps = [n for n, _ in self.checks]
        record.check_success = [v for _, v in self.checks]
        if not self.sparsity or self.sparsity[-1][0] != steps:
            self._measure_sparsity(steps)
        record.sparsity_steps = [n for n, _, _ in self.sparsity]
        record.sparsity = [v for _, v, _ in self.sparsity]
        record.sparsity_layers = {name: [layers[name] for _, _, layers in self.sparsity]
                                  for name in self.sparsity[-1][2]}
        if self.cfg.learning_curve_every > 0:
            record.curve_steps = self.curve_steps + [steps]
            record.curve = self.curve + [_mean(record.success[t] for t in self.tasks)]


def _mean(values) -> float:
    values = list(values)
    return float(np.mean(values)) if values else float("nan")


def run_settings_key(cfg: BenchConfig, method: Method, foundation_key: str,
                     evaluation_version: str) -> str:
    """Everything a stage checkpoint (and its evaluation records) depends on; a checkpoint with
    another key is not resumed, and a job with another key is another job. The suite's
    `evaluation_version` counts where it is set ("" keeps the keys made before it existed)."""
    settings = run_key_settings(cfg)
    parts = [settings, method.name, method.hyperparameters(), foundation_key]
    blob = json.dumps(parts + [evaluation_version] if evaluation_version else parts,
                      sort_keys=True, default=str)
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def resumable_stage(checkpoints: Path, k: int, run_key: str) -> int | None:
    """The highest stage whose checkpoint exists, if it was made with these exact settings;
    None when there is none or it was made with others (the run then starts over)."""
    for stage in range(k, 0, -1):
        path = checkpoints / f"stage_{stage}.pt"
        if path.exists():
            return stage if load_checkpoint(path).get("run_key") == run_key else None
    return None


def _last_finished(checkpoints: Path, k: int, run_key: str) -> int | None:
    """`resumable_stage`, after removing the checkpoints of other settings."""
    resumed = resumable_stage(checkpoints, k, run_key)
    if resumed is None and any(checkpoints.glob("stage_*.pt")):
        print(f"note: {checkpoints} was written with other settings; starting this run over")
        for old in checkpoints.glob("stage_*.pt"):
            old.unlink()
    return resumed


def summary_metrics(cfg: BenchConfig, result: RunResult) -> dict[str, float]:
    """The run's figures. A stage of several tasks counts as one column, their mean success
    (`metrics.by_stage`), so plasticity and the rest are per stage as DESIGN.md defines them."""
    tasks = result.tasks
    foundation = [tasks.index(t) for t in cfg.foundation_tasks]
    groups = [[tasks.index(t) for t in group] for group in cfg.stream_stages()]
    R, F, stream = by_stage(result.success_matrix(), foundation, groups)
    metrics = core_metrics(R, F, stream).as_dict()
    metrics["heldout_loss_ratio"] = float(heldout_loss_ratio(result.heldout_matrix(), foundation)[-1])
    S = result.spatial_success_matrix()
    if S is not None:
        metrics.update(spatial_metrics(*by_stage(S, foundation, groups)).as_dict())
    if all(s.curve for s in result.stages[1:]):
        curves = [np.array(s.curve) for s in result.stages[1:]]
        metrics.update(libero_metrics(curves, R, stream).as_dict())
    metrics.update(paper_metrics(result.success_matrix(), tasks, cfg.foundation_tasks,
                                 cfg.stream_tasks, cfg.heldout_groups))
    metrics["stream_steps"] = float(sum(s.steps_used for s in result.stages[1:]))
    for key, value in result.stages[-1].updates.items():
        metrics[f"update_{key}"] = value
    return metrics
