"""MLflow tracking: one parent run per benchmark invocation, one child per job (method, seed).

The default store is SQLite under `results/` (artifacts beside it); `MLFLOW_TRACKING_URI` points
at a shared `mlflow server` instead. The experiment is created before any run starts, so several
processes logging to one SQLite file do not race to create it.

Runs are found again by a key tag (`retain.key`): a job that is retried or rerun after a kill
continues its own run instead of leaving a RUNNING one behind and starting another.

Many writers (docs/reliability.md, `make bench-tracking`): an HTTP error (a server restarting, a
503 while its store is busy) is retried by MLflow's own retry settings, about a minute; a SQLite
lock held past MLflow's busy timeout is retried here, a line each. What still fails is one line.
"""

from __future__ import annotations

import fcntl
import logging
import os
import platform
import random
import re
import subprocess
import sys
import time
import warnings
from importlib import metadata
from pathlib import Path
from typing import Any

from harness.common.errors import RetainError

PACKAGES = ("torch", "numpy", "mujoco", "metaworld", "robosuite", "mlflow", "h5py",
            "sentence-transformers", "lerobot", "transformers")
_MAX_BATCH = 1000  # MLflow's limit on metrics per log_batch call
KEY_TAG = "retain.key"  # a job's (or an invocation's) identity: a rerun continues its run
COMMITS_TAG = "retain.git_commits"  # every commit that ran part of a run, in order
# MLflow's HTTP retries (urllib3's, on connection errors, timeouts, 408/429/5xx): backoff 0, 2, 4,
# 8, 16, 32 s (+ up to 1 s jitter each), enough for a server restart; a user's own settings win
HTTP_RETRY = {"MLFLOW_HTTP_REQUEST_MAX_RETRIES": "6", "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR": "1",
              "MLFLOW_HTTP_REQUEST_BACKOFF_JITTER": "1", "MLFLOW_HTTP_REQUEST_TIMEOUT": "60"}
LOCK_WAIT_S = 300.0  # how long a SQLite store may stay locked before a call gives up
log = logging.getLogger(__name__)


def tracking_uri(results_dir: str) -> str:
    uri = os.environ.get("MLFLOW_TRACKING_URI")
    if uri:
        return uri
    return f"sqlite:///{Path(results_dir).resolve() / 'mlflow.db'}"


def run_commits(params: dict[str, str], tags: dict[str, str]) -> list[str]:
    """The commits that ran a run: its commits tag, or (logged before the tag) its param."""
    listed = tags.get(COMMITS_TAG) or params.get("git_commit", "")
    return [c for c in listed.split(",") if c]


def package_versions() -> dict[str, str]:
    out = {"python": sys.version.split()[0]}
    for name in PACKAGES:
        try:
            out[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            out[name] = "absent"
    return out


def machine() -> dict[str, str]:
    """Where this process runs. The same job key and code gave other floats on another CPU
    (docs/study.md: libero-broad's seed-1 foundation), so each run says which machine made it."""
    return {"cpu": _cpu_model(), "cores": str(os.cpu_count() or 0), "platform": platform.platform()}


def _cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def git_commit() -> str:
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True,
                             check=True, cwd=Path(__file__).parent).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               capture_output=True, text=True, cwd=Path(__file__).parent).stdout
        return sha + ("-dirty" if dirty.strip() else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def quiet_mlflow() -> None:
    """Before the first MLflow client: no warnings or INFO lines (table creation) that say nothing
    about the run, and bounded HTTP retries (HTTP_RETRY). MLflow logs a traceback for every SQLite
    error it raises; the lock errors among them are retried here in one line, the rest raised."""
    warnings.filterwarnings("ignore", module="mlflow")
    for name, value in HTTP_RETRY.items():
        os.environ.setdefault(name, value)
    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")
    import mlflow  # noqa: F401 -- it sets its loggers' levels when imported: lower them after

    for name in ("mlflow", "alembic"):
        logging.getLogger(name).setLevel(logging.WARNING)
    logging.getLogger("mlflow.store.db.utils").setLevel(logging.CRITICAL)


def check_reachable(uri: str) -> None:
    """A server that does not answer at the start is a wrong address: say so at once, not after
    the minute of retries meant for one that restarts mid-run."""
    if not uri.startswith(("http://", "https://")):
        return
    import requests

    try:  # any answer, even a late one, says a server is there
        requests.get(f"{uri.rstrip('/')}/health", timeout=(5, 60))
    except requests.ReadTimeout:
        pass
    except requests.RequestException as exc:
        raise RetainError(f"tracking server {uri} is unreachable: "
                          f"{_first_line(_innermost(exc))}") from None


def finished_keys(client, experiment_id: str, keys) -> set[str]:
    """Those of `keys` whose run is FINISHED: the jobs a rerun skips."""
    runs = client.search_runs([experiment_id], filter_string="attributes.status = 'FINISHED'",
                              max_results=5000)
    return {run.data.tags.get(KEY_TAG, "") for run in runs} & set(keys)


class Tracker:
    """A thin layer over `MlflowClient` that knows Retain's run structure."""

    def __init__(self, results_dir: str, experiment: str, uri: str | None = None):
        quiet_mlflow()
        from mlflow.tracking import MlflowClient

        results = Path(results_dir)
        results.mkdir(parents=True, exist_ok=True)
        self.uri = uri or tracking_uri(results_dir)
        # Creating the client creates the SQLite schema: processes starting together take turns.
        check_reachable(self.uri)
        if self.uri.startswith("sqlite"):  # seconds of imports: not while others wait on the lock
            import mlflow.store.tracking.sqlalchemy_store  # noqa: F401
        with open(results / ".mlflow.lock", "w") as lock:
            fcntl.flock(lock, fcntl.LOCK_EX)
            self.client = _Retrying(MlflowClient(tracking_uri=self.uri), self.uri)
            self.experiment_id = self._experiment(experiment, results.resolve() / "mlartifacts")

    def _experiment(self, name: str, artifact_root: Path) -> str:
        """Get or create the experiment; fail in one line if the store cannot be reached."""
        for attempt in range(5):
            try:
                found = self.client.get_experiment_by_name(name)
                if found is not None:
                    return found.experiment_id
                location = None if self.uri.startswith("http") else artifact_root.as_uri()
                return self.client.create_experiment(name, artifact_location=location)
            except RetainError:
                raise
            except Exception as exc:  # noqa: BLE001 - MLflow raises many types for one cause
                text = str(exc)
                if "already exists" in text or "UNIQUE constraint" in text:
                    time.sleep(0.2 * (attempt + 1))  # another process created it (locks: _Retrying)
                    continue
                raise RetainError(f"tracking server {self.uri} is unreachable: "
                                  f"{_first_line(exc)}") from None
        raise RetainError(f"could not create MLflow experiment {name!r} at {self.uri}")

    def start_run(self, name: str, parent_id: str | None = None, tags: dict[str, str] | None = None) -> str:
        tags = dict(tags or {})
        if parent_id is not None:
            tags["mlflow.parentRunId"] = parent_id
        return self.client.create_run(self.experiment_id, run_name=name, tags=tags).info.run_id

    def continue_or_start_run(self, key: str, name: str, commit: str, parent_id: str | None = None,
                              tags: dict[str, str] | None = None) -> str:
        """The run tagged with `key` (set RUNNING again, whatever a kill left it as), or a new one;
        either way its commits tag gains `commit`.

        Why: a job retried after a lost worker, or a command rerun after a kill, is the same
        job; one run per job keeps the store free of RUNNING orphans and duplicates. Why a tag
        for the commits: MLflow params cannot change, so a job resumed at another commit keeps
        its first attempt's `git_commit` param."""
        found = self.client.search_runs([self.experiment_id],
                                        filter_string=f"tags.`{KEY_TAG}` = '{key}'",
                                        order_by=["attribute.start_time DESC"], max_results=1)
        tags = {**(tags or {}), KEY_TAG: key}
        if not found:
            run_id = self.start_run(name, parent_id, {**tags, COMMITS_TAG: commit})
            self._drop_twins(key, run_id)
            return run_id
        run = found[0]
        seen = run_commits(run.data.params, run.data.tags)
        tags[COMMITS_TAG] = ",".join(seen if commit in seen else [*seen, commit])
        self.client.update_run(run.info.run_id, status="RUNNING")
        if parent_id is not None:
            tags["mlflow.parentRunId"] = parent_id
        self.set_tags(run.info.run_id, tags)
        return run.info.run_id

    def _drop_twins(self, key: str, run_id: str) -> None:
        """Delete other runs with `key` made by this creation: a create_run retried after its
        answer was lost (the server went down after storing it) makes two, and the first would
        stay RUNNING with nothing logged."""
        for run in self.client.search_runs([self.experiment_id],
                                           filter_string=f"tags.`{KEY_TAG}` = '{key}'"):
            if run.info.run_id != run_id:
                self.client.delete_run(run.info.run_id)

    def commits(self, run_id: str) -> list[str]:
        """Every commit that ran part of the run, first to last."""
        data = self.client.get_run(run_id).data
        return run_commits(data.params, data.tags)

    def status(self, run_id: str) -> str:
        return self.client.get_run(run_id).info.status

    def logged_steps(self, run_id: str, key: str) -> set[int]:
        """The steps at which `key` was logged: what a continued run need not log again."""
        return {m.step for m in self.client.get_metric_history(run_id, metric_key(key))}

    def log_params(self, run_id: str, params: dict[str, Any]) -> None:
        """Log params the run does not have yet (MLflow params cannot change; a continued run
        keeps the ones it started with)."""
        from mlflow.entities import Param

        have = self.client.get_run(run_id).data.params
        items = [Param(k, str(v)[:6000]) for k, v in sorted(params.items()) if k not in have]
        for i in range(0, len(items), 100):
            self.client.log_batch(run_id, params=items[i:i + 100])

    def log_metrics(self, run_id: str, metrics: dict[str, float], step: int = 0) -> None:
        self.log_metric_rows(run_id, [(step, metrics)])

    def log_metric_rows(self, run_id: str, rows: list[tuple[int, dict[str, float]]]) -> None:
        """Log many (step, metrics) rows in as few calls as MLflow allows."""
        from mlflow.entities import Metric

        now = int(time.time() * 1000)
        items = [Metric(metric_key(k), float(v), now, step) for step, m in rows for k, v in m.items()
                 if v == v]  # NaN is skipped: MLflow stores it, but plots break on it
        for i in range(0, len(items), _MAX_BATCH):
            self.client.log_batch(run_id, metrics=items[i:i + _MAX_BATCH])

    def log_artifact(self, run_id: str, path: str | Path, artifact_path: str | None = None) -> None:
        self.client.log_artifact(run_id, str(path), artifact_path)

    def log_artifacts(self, run_id: str, directory: str | Path, artifact_path: str | None = None
                      ) -> None:
        """Every file of `directory` (a run's videos/), under `artifact_path`."""
        self.client.log_artifacts(run_id, str(directory), artifact_path)

    def set_tags(self, run_id: str, tags: dict[str, str]) -> None:
        for k, v in tags.items():
            self.client.set_tag(run_id, k, v)

    def end_run(self, run_id: str, status: str = "FINISHED") -> None:
        self.client.set_terminated(run_id, status)


class BatchedMetrics:
    """Collects per-step metrics and sends them to MLflow a few hundred rows at a time."""

    def __init__(self, tracker: Tracker, run_id: str, prefix: str = "", every: int = 200):
        self.tracker, self.run_id, self.prefix, self.every = tracker, run_id, prefix, every
        self.rows: list[tuple[int, dict[str, float]]] = []

    def __call__(self, step: int, metrics: dict[str, float]) -> None:
        self.rows.append((step, {self.prefix + k: v for k, v in metrics.items()}))
        if len(self.rows) >= self.every:
            self.flush()

    def flush(self) -> None:
        if self.rows:
            self.tracker.log_metric_rows(self.run_id, self.rows)
            self.rows = []


class _Retrying:
    """Calls through to MlflowClient. A SQLite lock held past MLflow's busy timeout (20 s) is
    retried with jittered backoff, a line each, for up to `lock_wait` seconds; HTTP errors were
    retried inside MLflow already, except an answer cut off mid-body by a server that died,
    which is retried here for every call that is safe to send twice. A call that still fails raises a one-line RetainError naming
    the store and the call; any other error is raised as it is."""

    def __init__(self, client, uri: str, lock_wait: float = LOCK_WAIT_S):
        self._client, self._uri, self._lock_wait = client, uri, lock_wait

    def __getattr__(self, name):
        method = getattr(self._client, name)
        if not callable(method):
            return method

        def call(*args, **kwargs):
            start, tries = time.monotonic(), 0
            while True:
                tries += 1
                try:
                    return method(*args, **kwargs)
                except Exception as exc:  # noqa: BLE001 - SQLAlchemy's OperationalError, wrapped
                    text = str(exc)
                    if ("Connection broken" in text and name not in NOT_IDEMPOTENT
                            and tries <= _http_retries()):
                        # the server died after answering, mid-body: urllib3 retries only up to
                        # the headers, so this call is retried here (the store keeps one copy)
                        delay = min(32.0, 2.0 ** (tries - 1))
                        log.warning("[retain] tracking: connection broken during %s; retry %d "
                                    "in %.0fs", name, tries, delay)
                        time.sleep(delay)
                        continue
                    if "API request to" in text and "failed with" in text:
                        raise RetainError(
                            f"tracking server {self._uri}: {name} failed after "
                            f"{_http_retries()} retries: "
                            f"{_first_line(exc)}") from None
                    if "is locked" not in text:
                        raise
                    waited = time.monotonic() - start
                    delay = min(5.0, 0.1 * 2 ** tries) * random.uniform(0.5, 1.5)
                    if waited + delay > self._lock_wait:
                        raise RetainError(
                            f"tracking store {self._uri} stayed locked for {waited:.0f}s ({name}, "
                            f"{tries} tries): another process holds its write lock; for many "
                            f"writers use `make mlflow-server`") from None
                    log.warning("[retain] tracking: database is locked during %s; retry %d in "
                                "%.1fs", name, tries, delay)
                    time.sleep(delay)

        return call


# Calls that must not be sent twice: a retry after a lost answer could make a second run
NOT_IDEMPOTENT = frozenset({"create_run", "create_experiment"})


def _http_retries() -> int:
    return int(os.environ.get("MLFLOW_HTTP_REQUEST_MAX_RETRIES") or HTTP_RETRY[
        "MLFLOW_HTTP_REQUEST_MAX_RETRIES"])


def _first_line(exc: BaseException) -> str:
    """An error's first line, whole words only ("..." where a very long one is cut), without
    the object addresses a wrapped error's text carries ("<urllib3... object at 0x7f..>: ")."""
    text = re.sub(r"<[^<>]* at 0x[0-9a-f]+>:\s*", "", str(exc)).strip()
    text = " ".join(text.splitlines()[0].split()) if text else type(exc).__name__
    if len(text) > MAX_REASON:
        text = text[:MAX_REASON].rsplit(" ", 1)[0] + " ..."
    return text


MAX_REASON = 300


def _innermost(exc: BaseException) -> BaseException:
    """Follow `reason` (urllib3), an exception as the first argument (requests) and
    `__cause__` down to the error that started it."""
    seen = {id(exc)}
    while True:
        nested = getattr(exc, "reason", None)
        if not isinstance(nested, BaseException):
            first = exc.args[0] if exc.args else None
            nested = first if isinstance(first, BaseException) else exc.__cause__
        if not isinstance(nested, BaseException) or id(nested) in seen:
            return exc
        seen.add(id(nested))
        exc = nested


def metric_key(key: str) -> str:
    """MLflow keys allow letters, digits, and _ - . / and space."""
    return "".join(c if c.isalnum() or c in "_-./ " else "_" for c in key)
