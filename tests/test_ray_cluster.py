"""A real Ray cluster of two nodes, each its own raylet and object store, on 127.0.0.1 (Ray's
own multi-node harness, `ray.cluster_utils.Cluster`), with one `mlflow server` over HTTP and
shared results and cache folders: the tiny comparison (2 methods x 2 seeds) with executor=ray,
the worker node killed while a job runs on it. The job is retried on the head, resumes after
its last finished stage, every result equals the serial run's, and the server holds one
FINISHED run per job. The test ends only what it started: the cluster's nodes and the server."""

import ipaddress
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
import urllib.request
import uuid
from contextlib import contextmanager
from pathlib import Path

import psutil
import pytest
import test_executors as executors_tests

ROOT = executors_tests.ROOT
RUNS = executors_tests.RUNS
serial = executors_tests.serial  # the reference: the same comparison run serially
BENCHMARK = "mw-quick-tiny"


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _wait_for(check, what: str, timeout: float, every: float = 0.01, command=None, log=()):
    """`check()` once it is true, failing at once if `command` (a process) ends first; the
    timeout is a hang guard, no measure of speed."""
    end = time.time() + timeout
    while time.time() < end:
        found = check()
        if found:
            return found
        if command is not None and command.poll() is not None:
            raise AssertionError(f"the command ended (exit {command.returncode}) before "
                                 f"{what}:\n" + "".join(list(log)[-40:]))
        time.sleep(every)
    raise AssertionError(f"timed out after {timeout:.0f}s waiting for {what}:\n"
                         + "".join(list(log)[-40:]))


@contextmanager
def mlflow_server(folder: Path):
    """`make mlflow-server`'s command on a free loopback port, ended by its pid (its group)."""
    port = _free_port()
    folder.mkdir()
    with open(folder / "server.log", "w") as log:
        proc = subprocess.Popen(
            [str(Path(sys.executable).parent / "mlflow"), "server",
             "--backend-store-uri", f"sqlite:///{folder}/mlflow.db",
             "--artifacts-destination", str(folder / "artifacts"), "--serve-artifacts",
             "--host", "127.0.0.1", "--port", str(port), "--workers", "1"],
            stdout=log, stderr=subprocess.STDOUT, start_new_session=True,
            # without MLflow's job runner (a dozen idle consumer processes): Retain runs none
            env={**os.environ, "MLFLOW_SERVER_ENABLE_JOB_EXECUTION": "false"})
    uri = f"http://127.0.0.1:{port}"

    def up() -> bool:
        assert proc.poll() is None, (folder / "server.log").read_text()[-2000:]
        try:
            return urllib.request.urlopen(f"{uri}/health", timeout=1).status == 200
        except OSError:
            return False

    try:
        _wait_for(up, "the MLflow server", timeout=90, every=0.5)
        yield uri
    finally:
        os.killpg(proc.pid, signal.SIGTERM)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()


@contextmanager
def ray_cluster(monkeypatch, node_home: Path):
    """A head and a worker node of one CPU each, so two jobs at once run one on each node.
    Everything on loopback (RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0), under a temp folder of its own
    (short: Ray's socket paths are limited to 107 characters), with a token of its own. The
    nodes start in `node_home`, as a `ray start` run in some other folder than the driver's."""
    temp = tempfile.mkdtemp(prefix="retain-rc-")
    for key, value in {"RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER": "0", "RAY_TMPDIR": temp,
                       "RAY_AUTH_MODE": "token", "RAY_AUTH_TOKEN": uuid.uuid4().hex}.items():
        monkeypatch.setenv(key, value)
    from ray._private import ray_constants
    from ray.cluster_utils import Cluster

    # read when Ray is imported: the same, should this process have imported Ray before
    monkeypatch.setattr(ray_constants, "ENABLE_RAY_CLUSTER", False)
    node_home.mkdir()
    monkeypatch.chdir(node_home)
    cluster = Cluster()
    try:
        cluster.add_node(num_cpus=1, include_dashboard=False)  # the head
        worker = cluster.add_node(num_cpus=1)
        cluster.wait_for_nodes()
        monkeypatch.chdir(ROOT)
        yield cluster, worker
    finally:
        cluster.shutdown()
        shutil.rmtree(temp, ignore_errors=True)


def _raylet_pid(node) -> int:
    return node.all_processes["raylet"][0].process.pid


def _children(pid: int) -> list[int]:
    """Every live process below `pid`."""
    try:
        return [p.pid for p in psutil.Process(pid).children(recursive=True)]
    except psutil.NoSuchProcess:
        return []


def _title(pid: int) -> str:
    try:
        return Path(f"/proc/{pid}/cmdline").read_text().replace("\0", " ").strip()
    except OSError:
        return ""


def _running_job(node) -> tuple[int, str, int] | None:
    """(pid, label, seed) of a comparison job running on `node`: Ray titles a task's worker
    process `ray::<task name>`, and the executor names a job's task `<label> seed <k>`."""
    for pid in _children(_raylet_pid(node)):
        found = re.match(r"ray::(\S+) seed (\d+)", _title(pid))
        if found and found[1] != "foundation":
            return pid, found[1], int(found[2])
    return None


def _listeners_off_loopback(nodes) -> list[str]:
    """The addresses any process of the nodes listens on that are not loopback."""
    pids = {info.process.pid for n in nodes for infos in n.all_processes.values()
            for info in infos}
    pids |= {p for n in nodes for p in _children(_raylet_pid(n))}
    off = []
    for pid in pids:
        try:
            conns = psutil.Process(pid).net_connections(kind="inet")
        except psutil.Error:
            continue
        for c in conns:
            ip = ipaddress.ip_address(c.laddr.ip)
            ip = getattr(ip, "ipv4_mapped", None) or ip
            if c.status == psutil.CONN_LISTEN and not ip.is_loopback:
                off.append(f"{_title(pid)[:60]} on {c.laddr.ip}:{c.laddr.port}")
    return off


@pytest.mark.slow
def test_worker_node_killed_mid_job_is_retried_on_the_head_and_resumes(tmp_path, serial,
                                                                        monkeypatch):
    shared = tmp_path / "shared"  # the cluster's shared filesystem: the driver's folder too
    for part in ("demos", "instructions"):  # the foundations are built on the cluster
        shutil.copytree(serial[0] / "cache" / part, shared / "cache" / part)
    with mlflow_server(tmp_path / "mlflow") as uri, \
            ray_cluster(monkeypatch, tmp_path / "node") as (cluster, worker):
        nodes = cluster.list_all_nodes()
        assert [n.node_ip_address for n in nodes] == ["127.0.0.1"] * 2
        assert _listeners_off_loopback(nodes) == []
        env = {**executors_tests._env(), "RAY_ADDRESS": cluster.address,
               "MLFLOW_TRACKING_URI": uri, "PYTHONPATH": str(ROOT)}
        # relative folders: the workers start in `node`, so they must get them made absolute
        proc = subprocess.Popen(executors_tests._cmd("results", "cache", "executor=ray",
                                                     "eval_workers=1"),
                                cwd=shared, env=env, stdout=subprocess.PIPE,
                                stderr=subprocess.STDOUT, text=True)
        lines: list[str] = []
        reader = threading.Thread(target=lambda: lines.extend(proc.stdout), daemon=True)
        reader.start()
        try:
            # a job runs on the worker; once its stage-1 checkpoint is written, pause it (so
            # the kill lands mid-job, whatever the timing), then kill the worker node
            pid, label, seed = _wait_for(lambda: _running_job(worker), "a job on the worker",
                                         timeout=400, every=0.2, command=proc, log=lines)
            stages = shared / "results" / BENCHMARK / label / f"seed{seed}" / "stages"
            _wait_for((stages / "stage_1.pt").exists, "its stage-1 checkpoint", timeout=300,
                      command=proc, log=lines)
            os.kill(pid, signal.SIGSTOP)
            assert not (stages / "stage_2.pt").exists(), "the job ended before it was paused"
            first = (stages / "stage_1.pt").stat()
            on_worker = _children(_raylet_pid(worker))
            cluster.remove_node(worker, allow_graceful=False)
            for left in on_worker:  # the node's processes go with it, the paused job too
                try:
                    os.kill(left, signal.SIGKILL)
                except ProcessLookupError:
                    pass
            assert proc.wait(timeout=400) == 0, "".join(lines[-40:])
        finally:
            if proc.poll() is None:
                proc.kill()
                proc.wait()
        reader.join(timeout=10)
        out = "".join(lines)

        # the lost job ran again on the remaining node and continued after stage 1
        resumed = re.findall(rf"pid=(\d+)\).*\[retain\] {label} seed {seed}: resuming after "
                             rf"stage 1 of 2", out)
        assert len(resumed) == 1 and int(resumed[0]) != pid, out[-3000:]
        assert out.count(f"[retain] {label} seed {seed}: stage 1 (") == 1, out[-3000:]
        again = (stages / "stage_1.pt").stat()
        assert (again.st_ino, again.st_mtime_ns) == (first.st_ino, first.st_mtime_ns)
        assert (stages / "stage_2.pt").exists()
        assert executors_tests._outputs(shared / "results") == serial[1]
        assert not (tmp_path / "node" / "results").exists()

        from mlflow.tracking import MlflowClient

        client = MlflowClient(tracking_uri=uri)
        experiment = client.get_experiment_by_name(BENCHMARK).experiment_id
        runs = client.search_runs([experiment])
        assert sorted(r.info.status for r in runs) == ["FINISHED"] * 5
        children = {(r.data.tags["label"], int(r.data.tags["seed"])): r for r in runs
                    if "mlflow.parentRunId" in r.data.tags}
        assert sorted(children) == sorted(RUNS)
        # the retried job's run was continued: each stage logged once
        history = client.get_metric_history(children[label, seed].info.run_id,
                                            "foundation_success")
        assert sorted(m.step for m in history) == [0, 1, 2]
