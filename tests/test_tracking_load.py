"""Several processes logging through harness.track.tracking at once, to a real loopback `mlflow server`
and to a SQLite file, while a real fault happens: the server is killed and restarted, or another
connection holds SQLite's write lock past MLflow's busy timeout. Every run, metric point and
artifact must be read back; what cannot be written must be a one-line error, never a silent gap.
(The figures for 8-32 writers: `make bench-tracking`, docs/reliability.md.)"""

import re
import sqlite3
import time
from pathlib import Path

import pytest

from harness.perf.tracking_load import Store, Volume, main, run_load

SMALL = Volume(runs=1, stages=2, steps=150, step_keys=4, tasks=3, artifact_kb=4)


def _database(store: Store) -> Path:
    return Path(store.backend.removeprefix("sqlite:///"))


def _wait_for_metrics(store: Store, timeout: float = 120.0) -> None:
    """Until the writers have stored their first metric points: the fault lands mid-run."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        try:
            with sqlite3.connect(f"file:{_database(store)}?mode=ro", uri=True, timeout=30) as db:
                if db.execute("SELECT COUNT(*) FROM metrics").fetchone()[0] > 0:
                    return
        except sqlite3.OperationalError:  # not created yet
            pass
        time.sleep(0.01)
    raise AssertionError("the writers stored no metric point")


def _assert_nothing_lost(result, writers: int = 4) -> None:
    assert result.problems == [] and not result.reported and not result.unreported
    assert result.lost_nothing
    assert result.runs_found == writers * 2  # each writer's parent and its job
    assert result.points_found == writers * SMALL.points_per_run()
    assert result.artifacts_found == writers * 6


def _writer(line: str) -> int:
    """The writer a problem ("load-w3-r0 ...") or a report ("writer 3: ...") is about."""
    return int(re.match(r"(?:load-w|writer )(\d+)", line).group(1))


def test_four_writers_to_sqlite_lose_nothing(tmp_path):
    _assert_nothing_lost(run_load("sqlite", 4, SMALL, tmp_path))


def test_server_gone_for_good_is_reported_in_one_line_and_nothing_else_is_lost(tmp_path,
                                                                              monkeypatch):
    monkeypatch.setenv("MLFLOW_SERVER_ENABLE_JOB_EXECUTION", "false")  # GenAI job runners

    def crash(store: Store) -> None:
        _wait_for_metrics(store)
        store.server.stop(kill=True)  # every process of it, mid-request, and no restart

    # few, fast retries (a user's MLflow settings win over Retain's): the give-up path in seconds
    env = {"MLFLOW_HTTP_REQUEST_MAX_RETRIES": "1", "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR": "0"}
    result = run_load("server", 4, SMALL, tmp_path, fault=crash, env=env, server_workers=1)
    assert result.unreported == [] and result.reported
    for line in result.reported:
        assert re.fullmatch(r"writer \d: error: tracking server http://127\.0\.0\.1:\d+: \w+ "
                            r"failed after 1 retries: .+", line), line
    assert result.points_found < result.points_expected  # the server died before the end
    # whatever the store lacks belongs to a writer that said so
    assert {_writer(p) for p in result.problems} <= {_writer(r) for r in result.reported}


@pytest.mark.parametrize("args, says", [
    (["--stores", "server,ftp"], "unknown tracking store 'ftp'; valid: server, sqlite"),
    (["--stores", ","], "unknown tracking store ''; valid: server, sqlite"),
    (["--writers", "8,0"], "bad writer counts '8,0': expected positive integers"),
    (["--writers", "many"], "bad writer counts 'many'"),
    (["--steps", "0"], "every count must be at least 1"),
])
def test_bad_bench_settings_are_refused_in_one_line_before_anything_starts(tmp_path, capsys,
                                                                          args, says):
    assert main([*args, "--root", str(tmp_path / "load")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: ") and says in err
    assert not (tmp_path / "load").exists()


@pytest.mark.slow
def test_server_killed_and_restarted_mid_run_loses_nothing(tmp_path, monkeypatch):
    monkeypatch.setenv("MLFLOW_SERVER_ENABLE_JOB_EXECUTION", "false")

    def crash_and_restart(store: Store) -> None:
        _wait_for_metrics(store)
        store.server.stop(kill=True)
        time.sleep(1.0)
        store.server.start()  # the same port and store; MLflow's retries (Retain's settings) wait

    result = run_load("server", 4, SMALL, tmp_path, fault=crash_and_restart, server_workers=1)
    _assert_nothing_lost(result)
    assert result.retried > 0  # the writers met the dead server and retried


@pytest.mark.slow
def test_sqlite_locked_past_the_busy_timeout_is_retried_and_loses_nothing(tmp_path):
    held = {}

    def take_write_lock(store: Store) -> None:
        # before the writers' first write, not at some point the writers may already have passed
        # (a loaded machine once let them finish before a lock taken mid-run, and CI's two cores
        # once let them finish in 1.8 s): every writer meets the lock
        held["db"] = sqlite3.connect(_database(store), timeout=60, isolation_level=None,
                                     check_same_thread=False)
        held["db"].execute("BEGIN EXCLUSIVE")  # what a long write by another process holds

    def release_write_lock(store: Store) -> None:
        time.sleep(23)  # past MLflow's busy_timeout of 20 s: the writers see "database is locked"
        held["db"].execute("COMMIT")
        held["db"].close()

    result = run_load("sqlite", 4, SMALL, tmp_path, before_go=take_write_lock,
                      fault=release_write_lock)
    _assert_nothing_lost(result)
    assert result.retried >= 4  # each writer met the lock at least once
    notices = [line for i in range(4) for line in (tmp_path / f"writer-{i}.err").read_text()
               .splitlines()]
    assert len(notices) == result.retried  # one line per retry, and nothing else
    assert all(re.fullmatch(r"\[retain\] tracking: database is locked during \w+; retry \d+ in "
                            r"[\d.]+s", line) for line in notices), notices


def test_an_answer_cut_off_mid_body_is_retried_only_where_a_second_send_is_safe(monkeypatch):
    """urllib3 retries up to the response headers; a server killed while sending the body
    leaves `Connection broken` to the caller, which Retain retries for idempotent calls."""
    from harness.common.errors import RetainError
    from harness.track import tracking

    broken = ("API request to http://127.0.0.1:5000/api/2.0/mlflow/runs/log-batch failed with "
              "exception ('Connection broken: IncompleteRead(0 bytes read, 2 more expected)')")

    class Client:
        calls = {"log_batch": 0, "create_run": 0}

        def log_batch(self):
            self.calls["log_batch"] += 1
            if self.calls["log_batch"] <= 2:
                raise RuntimeError(broken)
            return "stored"

        def create_run(self):
            self.calls["create_run"] += 1
            raise RuntimeError(broken)

    monkeypatch.setenv("MLFLOW_HTTP_REQUEST_MAX_RETRIES", "2")
    monkeypatch.setattr(tracking.time, "sleep", lambda s: None)
    client = tracking._Retrying(Client(), "http://127.0.0.1:5000")
    assert client.log_batch() == "stored" and Client.calls["log_batch"] == 3
    with pytest.raises(RetainError, match="create_run failed after 2 retries: .*Connection broken"):
        client.create_run()
    assert Client.calls["create_run"] == 1  # never sent twice: it could make a second run
    Client.calls["log_batch"] = -5  # broken more often than the retries allow: one-line error
    with pytest.raises(RetainError, match="log_batch failed after 2 retries"):
        client.log_batch()
