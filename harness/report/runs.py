"""Read the finished child runs of one experiment from MLflow into typed records.

Why MLflow and not the run directories: a team's runs live on a shared tracking server, and the
store is the one record that every machine wrote to. Everything a report needs is read here, so
the rest of the report code never talks to MLflow.
"""

from __future__ import annotations

import ast
import csv
import io
import tempfile
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from harness.errors import RetainError
from harness.tracking import metric_key, quiet_mlflow, run_commits

PARENT_TAG = "mlflow.parentRunId"


@dataclass(frozen=True)
class LayerUpdate:
    """One row of `updates_per_layer.csv`: how much one tensor moved, theta_k vs theta_0."""

    layer: str
    numel: int
    relative_l2: float
    frac_changed: dict[float, float]  # rho -> fraction of scalars with |delta| > rho * RMS(theta_0)


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

    @property
    def tasks(self) -> list[str]:
        return self.foundation_tasks + self.stream_tasks


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
    params, tags = run.data.params, run.data.tags
    foundation = _task_list(params, "config.foundation_tasks", run.info.run_id)
    stream = _task_list(params, "config.stream_tasks", run.info.run_id)
    return RunRecord(
        run_id=run.info.run_id, method=tags["method"], seed=int(tags.get("seed", params.get("seed", 0))),
        sweep_point=tags.get("sweep_point", ""), start_time=run.info.start_time,
        params=dict(params), metrics=dict(run.data.metrics),
        foundation_tasks=foundation, stream_tasks=stream,
        success=_success_matrix(client, run.info.run_id, foundation + stream, len(stream)),
        layers=_layer_updates(client, run.info.run_id), needs=tags.get("needs", ""),
        commits=tuple(run_commits(params, tags)),
    )


def _task_list(params: dict[str, str], key: str, run_id: str) -> list[str]:
    try:
        value = ast.literal_eval(params[key])
    except (KeyError, ValueError, SyntaxError):
        raise RetainError(f"run {run_id} has no readable param {key!r}; was it logged by "
                          "`python -m harness bench`?") from None
    return [str(t) for t in value]


def _success_matrix(client, run_id: str, tasks: list[str], k: int) -> np.ndarray:
    """R[stage, task] from the `success/<task>` metric histories (step = stage); NaN if absent."""
    R = np.full((k + 1, len(tasks)), np.nan)
    for j, task in enumerate(tasks):
        history = sorted(client.get_metric_history(run_id, metric_key(f"success/{task}")),
                         key=lambda m: (m.step, m.timestamp))
        for m in history:  # a resumed run may log a stage twice: the later value wins
            if 0 <= m.step <= k:
                R[m.step, j] = m.value
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
