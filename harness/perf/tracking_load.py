"""Many writers, one tracking store (`make bench-tracking`): N processes log at once what a
benchmark invocation logs, through harness.track.tracking's own Tracker, then the store is read back.

Each writer is one `harness bench` process with its parent run and `runs` jobs, each job logged
the way harness.run.jobs.run_job logs it: params, per-step training metrics in BatchedMetrics
batches, a row of stage metrics after each stage, the final metrics, machine tags, its output
files as artifacts, FINISHED. Writers log as fast as the store takes it (a real job trains for
minutes between flushes), so the figures are the store's capacity. The check reads every run,
metric history and artifact back through MlflowClient, as the report does.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from urllib.parse import unquote, urlparse

from harness.common.errors import RetainError
from harness.track.tracking import KEY_TAG, BatchedMetrics, Tracker, machine, quiet_mlflow

EXPERIMENT = "tracking-load"
STEP_KEYS = ("train/flow_loss", "train/objective", "consft/weight_mean", "consft/ratio_mean")
HEADLINE = ("foundation_success_stage0", "retention", "retention_drop", "plasticity",
            "stream_final_success", "forgetting", "bwt", "offline_retention",
            "update_frac_changed_rho0.01", "update_relative_l2")
ARTIFACTS = ("success_matrix.csv", "heldout_loss.csv", "updates_per_layer.csv", "metrics.json",
             "config.yaml", "success_matrix.png")
STORES = ("server", "sqlite")
PARAMS = {f"config.key{i}": f"value{i}" for i in range(40)}  # a run's provenance and config
TRACKING_LOG = "harness.track.tracking"  # its lock retries; urllib3.util.retry has the HTTP ones


@dataclass(frozen=True)
class Volume:
    """What one writer logs. The defaults are one job per process in mw-quick's shape (a
    ConSFT job: 9 tasks, 3 stream stages, 4 per-step keys, 40 params, its 6 output files) at a
    fifth of its steps (300 a stage, not 1500), so that 32 writers take minutes, not a quarter
    of an hour, on two cores; the rate per second is what the figures are for."""

    runs: int = 1  # jobs per process, one after another (a serial executor)
    stages: int = 3
    steps: int = 300  # training steps per stage (mw-quick: 1500)
    step_keys: int = 4
    tasks: int = 9  # foundation + stream: success and held-out loss per task and stage
    artifact_kb: int = 16  # size of each output file (the heat map is the largest, ~30 KB)

    def stage_keys(self) -> list[str]:
        tasks = [f"task{i}" for i in range(self.tasks)]
        return ([f"success/{t}" for t in tasks] + [f"heldout_loss/{t}" for t in tasks]
                + ["update/relative_l2", "update/frac_changed_rho0.01", "foundation_success",
                   "stage_train_loss"])

    def expected_points(self, writer: int, run: int) -> dict[str, set[tuple[int, float]]]:
        """Every (step, value) each metric key of a job must hold: logged and checked alike."""
        out: dict[str, set[tuple[int, float]]] = {}
        for k, key in enumerate(STEP_KEYS[:self.step_keys]):
            out[key] = {(s, value(writer, run, k, s)) for s in range(self.stages * self.steps)}
        for k, key in enumerate(self.stage_keys(), start=len(STEP_KEYS)):
            out[key] = {(stage, value(writer, run, k, stage)) for stage in range(self.stages + 1)}
        for k, key in enumerate(HEADLINE, start=len(STEP_KEYS) + len(self.stage_keys())):
            out[key] = {(self.stages, value(writer, run, k, self.stages))}
        return out

    def points_per_run(self) -> int:
        return (self.stages * self.steps * self.step_keys
                + (self.stages + 1) * len(self.stage_keys()) + len(HEADLINE))

    def text(self) -> str:
        return (f"{self.runs} job(s) per process, each {self.stages} stages x {self.steps} steps x "
                f"{self.step_keys} per-step keys + {len(self.stage_keys())} stage keys x "
                f"{self.stages + 1} + {len(HEADLINE)} final = {self.points_per_run()} metric "
                f"points, {len(ARTIFACTS)} artifacts of {self.artifact_kb} KB")


def value(writer: int, run: int, key: int, step: int) -> float:
    """A metric value that names its point: a lost or misplaced point cannot match another."""
    return ((writer * 1_000_003 + run * 10_007 + key * 101 + step) % 1_000_000) / 1_000_000


def artifact_bytes(writer: int, run: int, name: str, kb: int) -> bytes:
    seed = hashlib.sha256(f"{writer}/{run}/{name}".encode()).digest()
    return (seed * (kb * 1024 // len(seed) + 1))[:kb * 1024]


def job_key(writer: int, run: int) -> str:
    return f"load-w{writer}-r{run}"


def parent_key(writer: int) -> str:
    return f"load-w{writer}"


# --- one writer process -------------------------------------------------------------------

class _RetryCounter(logging.Handler):
    """Counts retries: harness.track.tracking's (SQLite locks) and urllib3's (every HTTP retry MLflow's
    session makes is one `Incremented Retry` record, at DEBUG, which no one else prints)."""

    def __init__(self):
        super().__init__(logging.DEBUG)
        self.count = 0

    def emit(self, record: logging.LogRecord) -> None:
        text = record.getMessage()
        if text.startswith("Incremented Retry") or (record.name == TRACKING_LOG and "retry" in text):
            self.count += 1


def write(uri: str, results_dir: str, writer: int, volume: Volume) -> dict:
    """Log one benchmark invocation's runs; wait for `go` on stdin first, so all start at once."""
    counter = _RetryCounter()
    notices = logging.getLogger(TRACKING_LOG)
    notices.addHandler(counter)
    notices.addHandler(logging.StreamHandler())  # stderr, as a user sees them (lastResort's)
    http_log = logging.getLogger("urllib3.util.retry")
    http_log.setLevel(logging.DEBUG)
    http_log.addHandler(counter)
    http_log.propagate = False

    tracker = Tracker(results_dir, EXPERIMENT, uri)
    print("ready", flush=True)
    sys.stdin.readline()
    start = time.time()
    parent = tracker.continue_or_start_run(parent_key(writer), f"{EXPERIMENT}:w{writer}", "load",
                                           tags={"benchmark": EXPERIMENT})
    tracker.log_params(parent, PARAMS)
    with tempfile.TemporaryDirectory() as tmp:
        for run in range(volume.runs):
            _write_job(tracker, parent, writer, run, volume, Path(tmp))
    tracker.end_run(parent, "FINISHED")
    return {"start": start, "end": time.time(), "retries": counter.count}


def _write_job(tracker: Tracker, parent: str, writer: int, run: int, volume: Volume,
               tmp: Path) -> None:
    """One job, in the calls and order harness.run.execute and harness.run.jobs.run_job make."""
    child = tracker.continue_or_start_run(job_key(writer, run), f"w{writer}/run{run}", "load",
                                          parent_id=parent,
                                          tags={"method": "consft", "seed": str(run)})
    status = "FAILED"
    try:
        _log_job(tracker, child, writer, run, volume, tmp)
        status = "FINISHED"
    finally:
        tracker.end_run(child, status)


def _log_job(tracker: Tracker, child: str, writer: int, run: int, volume: Volume,
             tmp: Path) -> None:
    tracker.log_params(child, PARAMS)
    points = volume.expected_points(writer, run)
    step_keys, stage_keys = STEP_KEYS[:volume.step_keys], volume.stage_keys()
    at = {key: dict(pairs) for key, pairs in points.items()}
    logged = tracker.logged_steps(child, stage_keys[volume.tasks])  # a continued job's stages
    logger = BatchedMetrics(tracker, child)

    def log_stage(stage: int) -> None:
        if stage not in logged:
            tracker.log_metric_rows(child, [(stage, {k: at[k][stage] for k in stage_keys})])

    log_stage(0)
    for stage in range(1, volume.stages + 1):
        for step in range((stage - 1) * volume.steps, stage * volume.steps):
            logger(step, {k: at[k][step] for k in step_keys})
        logger.flush()
        log_stage(stage)
    if volume.stages not in tracker.logged_steps(child, "retention"):
        tracker.log_metrics(child, {k: at[k][volume.stages] for k in HEADLINE}, step=volume.stages)
    tracker.set_tags(child, {f"retain.machine.{k}": v for k, v in machine().items()})
    for name in ARTIFACTS:
        path = tmp / name
        path.write_bytes(artifact_bytes(writer, run, name, volume.artifact_kb))
        tracker.log_artifact(child, path)


# --- the driver ---------------------------------------------------------------------------

@dataclass
class Store:
    """Where the writers log: a loopback `mlflow server` (started here) or a SQLite file."""

    kind: str  # "server" or "sqlite"
    root: Path
    server: object = None  # harness.track.server.TrackingServer, for kind "server"

    @property
    def uri(self) -> str:
        if self.kind == "server":
            return self.server.uri
        return f"sqlite:///{(self.root / 'results' / 'mlflow.db').resolve()}"

    @property
    def results_dir(self) -> Path:
        return self.root / "results"

    @property
    def backend(self) -> str:
        """The database itself: read back directly, so a check needs no live server."""
        return self.server.backend if self.kind == "server" else self.uri

    def artifact_dir(self, artifact_uri: str) -> Path:
        """Where a run's artifacts lie on disk: under the server's --artifacts-destination, or
        the SQLite store's file location."""
        if artifact_uri.startswith("mlflow-artifacts:"):
            return self.server.root / "artifacts" / artifact_uri.split(":", 1)[1].lstrip("/")
        return Path(unquote(urlparse(artifact_uri).path))


@dataclass
class LoadResult:
    """One load: what was expected, what the store holds, the errors, the time."""

    store: str
    writers: int
    runs_expected: int
    runs_found: int  # one FINISHED run per writer (its parent) and per job, with its params
    points_expected: int
    points_found: int
    artifacts_expected: int
    artifacts_found: int  # present with the bytes that were logged
    retried: int  # retries that then succeeded or not (lock retries and HTTP retries)
    reported: list[str] = field(default_factory=list)  # writers' one-line errors
    unreported: list[str] = field(default_factory=list)  # writers that failed otherwise
    wall_s: float = 0.0  # from the first writer's start to the last one's end
    total_s: float = 0.0  # all of it: the store, the writers' start-up, the read-back
    load: float = 0.0  # the machine's 1-minute load average when the writers finished
    problems: list[str] = field(default_factory=list)  # what the check found missing or extra

    @property
    def lost_nothing(self) -> bool:
        return (not self.problems and self.runs_found == self.runs_expected
                and self.points_found == self.points_expected
                and self.artifacts_found == self.artifacts_expected)


def run_load(kind: str, writers: int, volume: Volume, root: Path,
             fault: Callable[[Store], None] | None = None, env: dict | None = None,
             server_workers: int | None = None,
             before_go: Callable[[Store], None] | None = None) -> LoadResult:
    """Start the store, run `writers` processes at once, read the store back. A test's injected
    failure: `before_go` runs once every writer has opened the store and before any writes (so
    that a fault it starts cannot miss them), `fault` in a thread once the writers have started."""
    from harness.track.server import TrackingServer

    _check_kinds([kind])
    root.mkdir(parents=True, exist_ok=True)
    began = time.time()
    store = Store(kind, root)
    if kind == "server":
        store.server = TrackingServer(root / "server", workers=server_workers).start()
    try:
        timing, reported, unreported = _run_writers(store, writers, volume, fault, env,
                                                    before_go)
        load = os.getloadavg()[0]
        result = check_store(store, writers, volume)
    finally:
        if store.server is not None:
            store.server.stop()
    result.retried = sum(t.get("retries", 0) for t in timing)
    result.reported, result.unreported = reported, unreported
    result.load, result.total_s = load, time.time() - began
    if timing:
        result.wall_s = max(t["end"] for t in timing) - min(t["start"] for t in timing)
    return result


def _run_writers(store: Store, writers: int, volume: Volume, fault, env, before_go=None):
    env = {**os.environ, **(env or {})}
    env.pop("PYTEST_CURRENT_TEST", None)  # MLflow checks its own sessions under pytest
    cmd = [sys.executable, "-m", "harness.perf.tracking_load", "_writer", store.uri,
           str(store.results_dir), json.dumps(asdict(volume))]
    procs, errs = [], []
    for i in range(writers):
        err = open(store.root / f"writer-{i}.err", "w+")
        errs.append(err)
        procs.append(subprocess.Popen([*cmd, str(i)], stdin=subprocess.PIPE,
                                      stdout=subprocess.PIPE, stderr=err, text=True, env=env))
    try:
        ready = [_wait_ready(p) for p in procs]
        if before_go:
            before_go(store)
        for p in procs:  # all are ready (or failed): start them together
            if p.poll() is None:
                p.stdin.write("go\n")
                p.stdin.flush()
        injector = threading.Thread(target=fault, args=(store,)) if fault else None
        if injector:
            injector.start()
        outs = [p.communicate()[0] for p in procs]
        if injector:
            injector.join()
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.wait()
    timing, reported, unreported = [], [], []
    for i, (p, out, err, ok) in enumerate(zip(procs, outs, errs, ready)):
        err.seek(0)
        lines = [line for line in err.read().splitlines() if line.strip()]
        err.close()
        if p.returncode == 0 and ok:
            timing.append(json.loads(out.strip().splitlines()[-1]))
            continue
        last = lines[-1] if lines else f"exit status {p.returncode}, no output"
        one_line = p.returncode == 2 and last.startswith("error: ") and all(
            "retry" in line.lower() for line in lines[:-1])  # retry notices, then the error
        (reported if one_line else unreported).append(f"writer {i}: {last}")
    return timing, reported, unreported


def _wait_ready(proc: subprocess.Popen) -> bool:
    """Until the writer says `ready` (True) or ends without saying it (False)."""
    for line in proc.stdout:
        if line.strip() == "ready":
            return True
    return False


def check_store(store: Store, writers: int, volume: Volume) -> LoadResult:
    """Read every job's run and metric histories back (MlflowClient on the store's database) and
    its artifact files (from disk), and compare them with what was logged."""
    quiet_mlflow()
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=store.backend)
    result = LoadResult(store.kind, writers, writers * (volume.runs + 1), 0,
                        writers * volume.runs * volume.points_per_run(), 0,
                        writers * volume.runs * len(ARTIFACTS), 0, 0)
    experiment = client.get_experiment_by_name(EXPERIMENT)
    runs = _all_runs(client, experiment.experiment_id) if experiment else []
    by_key: dict[str, list] = {}
    for run in runs:
        by_key.setdefault(run.data.tags.get(KEY_TAG, ""), []).append(run)
    for writer in range(writers):
        result.runs_found += _check_run(by_key, parent_key(writer), result.problems) is not None
        for run_index in range(volume.runs):
            key = job_key(writer, run_index)
            whole = _check_run(by_key, key, result.problems)
            result.runs_found += whole is not None
            run = whole or next(iter(by_key.get(key, [])), None)
            if run is None:
                continue
            result.points_found += _check_points(client, run.info.run_id, key,
                                                 volume.expected_points(writer, run_index),
                                                 result.problems)
            files = store.artifact_dir(run.info.artifact_uri)
            result.artifacts_found += _check_artifacts(files, key, writer, run_index, volume,
                                                       result.problems)
    return result


def _check_run(by_key: dict[str, list], key: str, problems: list[str]):
    """The key's one run if it is whole (FINISHED, its params there), else None and a problem;
    a run to check the metrics and files of, whole or not."""
    found = by_key.get(key, [])
    run = found[0] if found else None
    problem = (f"{len(found)} runs" if len(found) != 1 else
               run.info.status if run.info.status != "FINISHED" else
               "params missing" if len(run.data.params) < len(PARAMS) else "")
    if problem:
        problems.append(f"{key}: {problem}")
    return None if problem else run


def _all_runs(client, experiment_id: str) -> list:
    out, token = [], None
    while True:
        page = client.search_runs([experiment_id], max_results=1000, page_token=token)
        out.extend(page)
        token = page.token
        if not token:
            return out


def _check_points(client, run_id: str, key: str, expected: dict, problems: list[str]) -> int:
    found = 0
    for metric, pairs in expected.items():
        history = client.get_metric_history(run_id, metric)
        got = [(m.step, m.value) for m in history]
        found += len(pairs & set(got))
        if len(got) != len(pairs) or set(got) != pairs:
            problems.append(f"{key} {metric}: {len(pairs & set(got))} of {len(pairs)} points, "
                            f"{len(got)} stored")
    return found


def _check_artifacts(local: Path, key: str, writer: int, run: int, volume: Volume,
                     problems: list[str]) -> int:
    found = 0
    for name in ARTIFACTS:
        path = local / name
        if path.exists() and path.read_bytes() == artifact_bytes(writer, run, name,
                                                                 volume.artifact_kb):
            found += 1
        else:
            problems.append(f"{key} artifact {name}: "
                            + ("wrong bytes" if path.exists() else "missing"))
    return found


# --- the table ----------------------------------------------------------------------------

def table(results: list[LoadResult]) -> str:
    rows = ["| store | N | runs | metric points | artifacts | retried | reported | unreported "
            "| wall s | runs/s | points/s | load avg | all s |",
            "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in results:
        wall = max(r.wall_s, 1e-9)
        rows.append(
            f"| {r.store} | {r.writers} | {r.runs_found}/{r.runs_expected} "
            f"| {r.points_found}/{r.points_expected} | {r.artifacts_found}/{r.artifacts_expected} "
            f"| {r.retried} | {len(r.reported)} | {len(r.unreported)} | {r.wall_s:.1f} "
            f"| {r.runs_found / wall:.2f} | {r.points_found / wall:,.0f} | {r.load:.1f} "
            f"| {r.total_s:.0f} |")
    return "\n".join(rows)


def _check_kinds(kinds: list[str]) -> list[str]:
    bad = [k for k in kinds if k not in STORES] or ([] if kinds else [""])
    if bad:
        raise RetainError(f"unknown tracking store {bad[0]!r}; valid: {', '.join(STORES)}")
    return kinds


def _ints(text: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v]
    except ValueError:
        values = []
    if not values or min(values) < 1:
        raise RetainError(f"bad writer counts {text!r}: expected positive integers, e.g. 8,16,32")
    return values


def main(argv: list[str]) -> int:
    if argv and argv[0] == "_writer":
        uri, results_dir, volume, writer = argv[1:5]
        try:
            print(json.dumps(write(uri, results_dir, int(writer), Volume(**json.loads(volume)))))
        except RetainError as exc:
            print(f"error: {exc}", file=sys.stderr)
            return 2
        return 0
    parser = argparse.ArgumentParser(prog="python -m harness.perf.tracking_load",
                                     description="N writers at once to one tracking store")
    parser.add_argument("--writers", default="8,16,32", help="process counts, e.g. 8,16,32")
    parser.add_argument("--stores", default="server,sqlite", help="server, sqlite or both")
    parser.add_argument("--root", default="results/tracking-load",
                        help="where stores are made (emptied per load)")
    for name, default in asdict(Volume()).items():
        parser.add_argument(f"--{name.replace('_', '-')}", type=int, default=default)
    args = parser.parse_args(argv)
    try:
        counts = _ints(args.writers)
        stores = _check_kinds([s for s in args.stores.split(",") if s])
        volume = Volume(**{k: getattr(args, k) for k in asdict(Volume())})
        if min(asdict(volume).values()) < 1:
            raise RetainError(f"bad volume {asdict(volume)}: every count must be at least 1")
        print(f"tracking load: {volume.text()}; writers log as fast as the store takes them; "
              f"{os.cpu_count()} cores", flush=True)
        print("\n".join(table([]).splitlines()), flush=True)
        results = []
        for kind in stores:
            for n in counts:
                root = Path(args.root) / f"{kind}-{n}"
                if root.exists():
                    shutil.rmtree(root)
                result = run_load(kind, n, volume, root)
                results.append(result)
                print(table([result]).splitlines()[-1], flush=True)
                for line in result.reported + result.unreported + result.problems[:10]:
                    print(f"  {line}", flush=True)
        print("\n" + table(results))
        lost = [r for r in results if not r.lost_nothing or r.unreported]
        return 1 if lost else 0
    except RetainError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
