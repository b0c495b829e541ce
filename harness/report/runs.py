"""Read the finished child runs of one experiment from MLflow into typed records.

Why MLflow and not the run directories: a team's runs live on a shared tracking server, and the
store is the one record that every machine wrote to. Everything a report needs is read here, so
the rest of the report code never talks to MLflow.
"""

from __future__ import annotations

import ast
import csv
import io
import itertools
import math
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from harness.common.errors import RetainError
from harness.config.benchmark import stage_name
from harness.measure.metrics import LEGACY_METRIC_KEYS
from harness.track.tracking import metric_key, quiet_mlflow, run_commits

PARENT_TAG = "mlflow.parentRunId"
# per-step metrics the figures draw (the paper's Eq. 8 sparsity, ConSFT's weighting), read only
# from runs that logged them
SERIES_KEYS = ("sparsity/eq8", "consft/tau", "consft/weight_mean", "consft/frac_at_floor",
               "consft/loss_q10", "consft/loss_q50", "consft/loss_q90")


@dataclass(frozen=True)
class LayerUpdate:
    """One row of `updates_per_layer.csv`: how much one tensor moved, theta_k vs theta_0."""

    layer: str
    numel: int
    relative_l2: float
    frac_changed: dict[float, float]  # rho -> fraction of scalars with |delta| > rho * RMS(theta_0)


@dataclass(frozen=True)
class StepSeries:
    """A per-step metric of the stream stages. `step` counts the steps from the stream's start
    as MLflow's step axis does: stage i's steps start at (i - 1) * steps_per_task, whether or
    not an earlier stage stopped early (`until_success`)."""

    step: np.ndarray  # int: steps done since the stream's start, in that planned schedule
    stage: np.ndarray  # int: the stream stage (1..k) the step belongs to
    value: np.ndarray


@dataclass(frozen=True)
class RunRecord:
    """One finished (method, seed) child run, as the report needs it."""

    run_id: str
    method: str
    seed: int
    sweep_point: str  # the `sweep_point` tag ("kappa=0.1"), "" when the run is not a sweep point
    start_time: int
    params: dict[str, str]
    metrics: dict[str, float]  # final values (MLflow's latest step of each key)
    foundation_tasks: list[str]
    stream_tasks: list[str]
    success: np.ndarray  # R[stage, task], stages 0..k, tasks = foundation then stream
    layers: list[LayerUpdate]
    needs: str = ""  # the `needs` tag ("past data, reference copy", "none"); "" if not logged
    commits: tuple[str, ...] = ()  # the commits that ran it (more than one if resumed at another)
    stage_sizes: tuple[int, ...] = ()  # stream tasks per stage; (): one task a stage
    # per stream stage 1..k, NaN where not logged: the optimizer steps it took, and the success
    # at its last until_success check
    stage_steps: tuple[float, ...] = ()
    stage_check_success: tuple[float, ...] = ()
    series: dict[str, StepSeries] = field(default_factory=dict)  # SERIES_KEYS it logged

    @property
    def tasks(self) -> list[str]:
        return self.foundation_tasks + self.stream_tasks

    @property
    def stages(self) -> list[list[str]]:
        """The stream tasks of each stage, in order: one a stage unless grouped."""
        sizes = self.stage_sizes or (1,) * len(self.stream_tasks)
        ends = list(itertools.accumulate(sizes))
        return [self.stream_tasks[end - n:end] for n, end in zip(sizes, ends)]

    @property
    def stage_names(self) -> list[str]:
        """"foundation", then what each stage trained on (harness.config.benchmark.stage_name)."""

        return ["foundation", *(stage_name(i, g) for i, g in enumerate(self.stages, start=1))]


def open_client(uri: str):
    """An MlflowClient with quiet warnings and no retry storms against a dead server."""
    quiet_mlflow()
    from mlflow.tracking import MlflowClient

    return MlflowClient(tracking_uri=uri)


def experiment_id(client, name: str, uri: str) -> str:
    """The experiment's id, or a one-line error naming the experiments that do exist."""
    try:
        found = client.get_experiment_by_name(name)
        if found is not None:
            return found.experiment_id
        names = sorted(e.name for e in client.search_experiments())
    except Exception as exc:  # noqa: BLE001 - MLflow raises many types for one cause
        first = (str(exc).splitlines() or [type(exc).__name__])[0]
        raise RetainError(f"tracking store {uri} is unreachable: {first[:200]}") from None
    raise RetainError(f"no MLflow experiment {name!r} at {uri}; experiments there: "
                      f"{', '.join(names) or '(none)'}")


def load_runs(client, exp_id: str) -> list[RunRecord]:
    """Every finished (method, seed) child run of the experiment, in a fixed order."""
    runs = [r for r in _search_finished(client, exp_id)
            if PARENT_TAG in r.data.tags and "method" in r.data.tags
            and r.data.tags.get("report") != "true"]
    records = [_record(client, r) for r in runs]
    records.sort(key=lambda r: (r.method, r.sweep_point, r.seed, r.start_time, r.run_id))
    return records


def _search_finished(client, exp_id: str) -> list:
    out, token = [], None
    while True:
        page = client.search_runs([exp_id], filter_string="attributes.status = 'FINISHED'",
                                  max_results=1000, page_token=token)
        out.extend(page)
        token = page.token
        if not token:
            return out


def _record(client, run) -> RunRecord:
    params, tags, run_id = run.data.params, run.data.tags, run.info.run_id
    foundation = _task_list(params, "config.foundation_tasks", run_id)
    stream = _task_list(params, "config.stream_tasks", run_id)
    sizes = _stage_sizes(params, len(stream), run_id)
    k = len(sizes)
    per_stage = {key: _per_stage(client, run_id, key, k) if key in run.data.metrics
                 else (math.nan,) * k for key in ("stage_steps", "stage_check_success")}
    return RunRecord(
        run_id=run_id, method=tags["method"], seed=int(tags.get("seed", params.get("seed", 0))),
        sweep_point=tags.get("sweep_point", ""), start_time=run.info.start_time,
        params=dict(params), metrics=_current_keys(run.data.metrics),
        foundation_tasks=foundation, stream_tasks=stream,
        success=_success_matrix(client, run_id, foundation + stream, k),
        layers=_layer_updates(client, run_id), needs=tags.get("needs", ""),
        commits=tuple(run_commits(params, tags)), stage_sizes=tuple(sizes),
        stage_steps=per_stage["stage_steps"], stage_check_success=per_stage["stage_check_success"],
        series={key: _series(client, run_id, key, params, per_stage["stage_steps"])
                for key in SERIES_KEYS if key in run.data.metrics},
    )


def _current_keys(metrics: dict[str, float]) -> dict[str, float]:
    """A run's final metrics under today's keys: an old run's `offline_retention` is read as
    `heldout_loss_ratio` (the same number, renamed), unless it logged both."""
    out = dict(metrics)
    for old, new in LEGACY_METRIC_KEYS.items():
        if old in out:
            out.setdefault(new, out.pop(old))
    return out


def _task_list(params: dict[str, str], key: str, run_id: str) -> list[str]:
    try:
        value = ast.literal_eval(params[key])
    except (KeyError, ValueError, SyntaxError):
        raise RetainError(f"run {run_id} has no readable param {key!r}; was it logged by "
                          "`python -m harness bench`?") from None
    return [str(t) for t in value]


def _stage_sizes(params: dict[str, str], n_stream: int, run_id: str) -> list[int]:
    """Stream tasks per stage: `config.stage_sizes`, or one task a stage where it is absent (a
    run from before stages were grouped) or empty."""
    text = params.get("config.stage_sizes", "[]")
    try:
        sizes = [int(n) for n in ast.literal_eval(text)]
    except (ValueError, SyntaxError, TypeError):
        raise RetainError(f"run {run_id} has an unreadable param 'config.stage_sizes': "
                          f"{text!r}; expected a list of stage sizes") from None
    if sizes and (min(sizes) < 1 or sum(sizes) != n_stream):
        raise RetainError(f"run {run_id}: config.stage_sizes {sizes} does not split its "
                          f"{n_stream} stream tasks into stages")
    return sizes or [1] * n_stream


def _history(client, run_id: str, key: str) -> dict[int, float]:
    """step -> value of a metric; a resumed run may log a step twice: the later value wins."""
    history = sorted(client.get_metric_history(run_id, metric_key(key)),
                     key=lambda m: (m.step, m.timestamp))
    return {m.step: m.value for m in history}


def _per_stage(client, run_id: str, key: str, k: int) -> tuple[float, ...]:
    """A per-stage metric (step = stage) for stages 1..k; NaN where not logged."""
    history = _history(client, run_id, key)
    return tuple(history.get(stage, math.nan) for stage in range(1, k + 1))


def _series(client, run_id: str, key: str, params: dict[str, str],
            stage_steps: tuple[float, ...]) -> StepSeries:
    """A per-step metric of the stream stages. The trainer logs steps on one axis from the
    foundation's start: foundation_steps + (stage - 1) * steps_per_task + steps done - 1.
    A stage killed and rerun logs into the same run; where the rerun stopped at an earlier
    check than the killed attempt reached, the attempt's later rows remain. So a stage's rows
    past its recorded `stage_steps` are dropped (all are kept where a run never logged it)."""
    history = _history(client, run_id, key)
    start = int(params.get("config.foundation_steps", 0))
    per_stage = max(1, int(params.get("config.steps_per_task", 1)))
    steps = np.array([s - start for s in history if s >= start], dtype=np.int64)
    values = np.array([v for s, v in history.items() if s >= start], dtype=np.float64)
    stage, done = steps // per_stage + 1, steps % per_stage + 1
    used = np.array([stage_steps[i - 1] if i <= len(stage_steps) else math.nan for i in stage],
                    dtype=np.float64)
    keep = np.isnan(used) | (done <= used)
    return StepSeries(step=steps[keep] + 1, stage=stage[keep], value=values[keep])


def _success_matrix(client, run_id: str, tasks: list[str], k: int) -> np.ndarray:
    """R[stage, task] from the `success/<task>` metric histories (step = stage); NaN if absent."""
    R = np.full((k + 1, len(tasks)), np.nan)
    for j, task in enumerate(tasks):
        for stage, value in _history(client, run_id, f"success/{task}").items():
            if 0 <= stage <= k:
                R[stage, j] = value
    return R


def _layer_updates(client, run_id: str) -> list[LayerUpdate]:
    """Rows of the run's `updates_per_layer.csv` artifact, in file order; [] if it is absent."""
    with tempfile.TemporaryDirectory() as tmp:
        try:
            path = client.download_artifacts(run_id, "updates_per_layer.csv", tmp)
        except Exception:  # noqa: BLE001 - absent artifact: MLflow raises store-specific types
            return []
        text = Path(path).read_text()
    rows = []
    for row in csv.DictReader(io.StringIO(text)):
        fracs = {float(k.removeprefix("frac_changed_rho")): float(v) for k, v in row.items()
                 if k.startswith("frac_changed_rho")}
        rows.append(LayerUpdate(row["layer"], int(row["numel"]), float(row["relative_l2"]),
                                dict(sorted(fracs.items()))))
    return rows


def download_videos(client, run_id: str, dst: Path) -> Path | None:
    """A run's `videos/` artifacts (the MP4s and an index per stage) copied under `dst`, from
    whatever store holds them; None when the run logged no videos."""
    if not any(f.path == "videos" for f in client.list_artifacts(run_id)):
        return None
    dst.mkdir(parents=True, exist_ok=True)
    return Path(client.download_artifacts(run_id, "videos", str(dst)))
