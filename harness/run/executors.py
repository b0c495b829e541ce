"""Where a comparison's jobs run: `serial` (one after another in this process), `local`
(parallel worker processes on this machine, the default) or `ray` (Ray tasks on the cluster at
RAY_ADDRESS, or on a Ray started in this process).

Every executor runs the same job functions (harness.run.jobs) and yields each result as its job
finishes, so results are identical whichever runs them. Retries are Ray's own: a task whose
worker is lost runs again, and the job continues from its last finished stage.
"""

from __future__ import annotations

import ctypes
import dataclasses
import os
import shutil
import signal
import tempfile
from collections.abc import Callable, Iterator
from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path

from harness.common.errors import USER_ERRORS
from harness.config.benchmark import BenchConfig
from harness.run.jobs import with_absolute_paths

RAY_RETRIES = 3  # attempts after a lost worker (a Python exception is not retried)
PROCESS_MB = 500.0  # an evaluation worker before its simulators: Python, torch, the suite's imports
MEMORY_SHARE = 0.8  # of the memory available at the start, what the evaluation workers may hold


def available_cores() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1


def available_memory_mb() -> float | None:
    """The kernel's MemAvailable, in MB; None where it cannot be read (not Linux)."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) / 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def evaluation_worker_mb(cfg: BenchConfig, suite) -> float:
    """One evaluation worker's memory at its peak: a final evaluation builds a simulator for
    every task (`eval_envs_per_task` each) and keeps them (libero-paper: 42 x 180 MB)."""
    per_simulator = suite.simulator_mb[1 if cfg.cameras else 0]
    return PROCESS_MB + len(cfg.all_tasks()) * cfg.eval_envs_per_task * per_simulator


@dataclass(frozen=True)
class Slots:
    """How a comparison's jobs share the machine: jobs at once, evaluation workers per job."""

    parallel: int
    eval_workers: int
    memory_note: str = ""  # why memory set fewer than the cores would, if it did
    workers_note: str = ""  # why fewer evaluation workers run than `eval_workers` asked for


def plan_slots(cfg: BenchConfig, n_jobs: int, cores: int | None = None, worker_mb: float = 0.0,
               memory_mb: float | None = None) -> Slots:
    """`jobs` at once (0: as many as the cores allow, each job keeping max(torch_threads,
    its evaluation workers) cores busy), never more than there are jobs; a job's evaluation
    workers are `eval_workers`, or (when 0) its share of the cores (one on Ray, whose
    machines the cores of this one say nothing about).

    Given `memory_mb` (what is available) and `worker_mb` (`evaluation_worker_mb`), the settings
    left at 0 also keep the evaluation workers that hold simulators at once (a job's first
    `eval_shards`; the others get no work) within MEMORY_SHARE of it: on many cores a LIBERO
    benchmark would otherwise build more simulators than the memory holds. A setting given is
    kept as given, up to the workers that can have work (`useful_workers`): `eval_workers=1000`
    runs eval_shards workers on the CPU, never 1000 processes (`workers_note` says so)."""
    cores = cores or available_cores()
    most = useful_workers(cfg, cores)
    given = cfg.eval_workers
    if given > most:  # the jobs at once follow the workers that will run, not the number asked
        cfg = dataclasses.replace(cfg, eval_workers=most)
    slots = _slots_by_memory(cfg, n_jobs, cores, worker_mb, memory_mb)
    if slots.eval_workers > most:  # a share of the cores beyond what has work
        slots = dataclasses.replace(slots, eval_workers=most)
    if given <= most:
        return slots
    why = (f"a policy on the CPU is evaluated in eval_shards={cfg.eval_shards} shards, one per "
           "worker, so more get no work" if _cpu_policy(cfg) and most == cfg.eval_shards
           else f"this machine has {cores} cores")
    return dataclasses.replace(slots, workers_note=(
        f"{slots.eval_workers} evaluation worker(s) per job, not eval_workers={given}: {why}"))


def useful_workers(cfg: BenchConfig, cores: int) -> int:
    """The most evaluation workers a job can use: a CPU policy's evaluation runs `eval_shards`
    shards, one per worker (more would get no work); one on an accelerator steps simulators in
    every worker, as many as this machine's cores (Ray's machines are not this one)."""
    shards = cfg.eval_shards if _cpu_policy(cfg) else None
    if cfg.executor == "ray":
        return shards or max(1, cfg.eval_workers)
    return max(1, min(cores, shards or cores))


def _cpu_policy(cfg: BenchConfig) -> bool:
    from harness.common.device import resolve_device

    try:
        return resolve_device(cfg.device).type == "cpu"
    except USER_ERRORS:
        return True


def _slots_by_memory(cfg: BenchConfig, n_jobs: int, cores: int, worker_mb: float,
                     memory_mb: float | None) -> Slots:
    by_cores = _slots_by_cores(cfg, n_jobs, cores)
    if cfg.executor == "ray" or memory_mb is None or worker_mb <= 0:
        return by_cores
    fit = max(1, int(MEMORY_SHARE * memory_mb // worker_mb))  # workers holding simulators
    parallel, workers = by_cores.parallel, by_cores.eval_workers
    if cfg.executor == "local" and not cfg.jobs:
        parallel = max(1, min(parallel, fit // min(cfg.eval_workers or 1, cfg.eval_shards)))
        workers = cfg.eval_workers or max(1, cores // parallel)
    if not cfg.eval_workers and parallel * min(workers, cfg.eval_shards) > fit:
        workers = max(1, fit // parallel)
    if (parallel, workers) == (by_cores.parallel, by_cores.eval_workers):
        return by_cores
    return Slots(parallel, workers, (
        f"memory: {parallel} at once with {workers} evaluation worker(s) each, not "
        f"{by_cores.parallel} with {by_cores.eval_workers}: a worker holds about "
        f"{worker_mb / 1024:.1f} GB of simulators and {memory_mb / 1024:.1f} GB is available"))


def _slots_by_cores(cfg: BenchConfig, n_jobs: int, cores: int) -> Slots:
    if cfg.executor == "serial":
        return Slots(1, cfg.eval_workers or cores)
    if cfg.executor == "ray":  # Ray places the tasks; each asks for what it uses
        return Slots(min(cfg.jobs or n_jobs, n_jobs), cfg.eval_workers or 1)
    per_job = max(cfg.torch_threads, cfg.eval_workers or 1)
    parallel = cfg.jobs or max(1, cores // per_job)
    parallel = max(1, min(parallel, n_jobs))
    workers = cfg.eval_workers or max(1, cores // parallel)
    return Slots(parallel, workers)


class SerialExecutor:
    """One job after another in this process, sharing one evaluator and the loaded data."""

    def __init__(self, cfg: BenchConfig, suite, data, workers: int):
        from harness.evaluate.stages import make_evaluator

        self.data = data
        self.evaluator = make_evaluator(cfg, suite, workers)

    def run(self, fn: Callable, jobs: list) -> Iterator[tuple[int, object]]:
        for i, job in enumerate(jobs):
            yield i, fn(job, self.evaluator, self.data)

    def close(self) -> None:
        self.evaluator.close()


class LocalExecutor:
    """Jobs in parallel worker processes (spawned: no state inherited from this one)."""

    def __init__(self, parallel: int):
        self.pool = ProcessPoolExecutor(parallel, mp_context=get_context("spawn"),
                                        initializer=_die_with_parent)

    def run(self, fn: Callable, jobs: list) -> Iterator[tuple[int, object]]:
        futures = {self.pool.submit(fn, job): i for i, job in enumerate(jobs)}
        pending = set(futures)
        try:
            while pending:
                done, pending = wait(pending, return_when=FIRST_COMPLETED)
                for future in done:
                    yield futures[future], future.result()
        finally:
            for future in pending:
                future.cancel()

    def close(self) -> None:
        self.pool.shutdown(wait=True, cancel_futures=True)


class RayExecutor:
    """Each job a Ray task asking for the cores it uses, retried (and so continued) when its
    worker is lost. The cluster at RAY_ADDRESS, or a Ray started here with a temp folder of
    its own (a stale shared one can hang `ray.init`) and all traffic on 127.0.0.1."""

    def __init__(self, cores: int, max_in_flight: int = 0):
        import ray

        self.ray, self.max_in_flight, self.temp_dir = ray, max_in_flight, None
        env = {"runtime_env": {"env_vars": {"PYTHONPATH": _source_root()}}}
        if os.environ.get("RAY_ADDRESS"):
            ray.init(address=os.environ["RAY_ADDRESS"], logging_level="WARNING", **env)
        else:
            self.temp_dir = tempfile.mkdtemp(prefix="retain-ray-")
            ray.init(address="local", num_cpus=cores, _temp_dir=self.temp_dir,
                     _node_ip_address="127.0.0.1", include_dashboard=False,
                     logging_level="WARNING", **env)

    def run(self, fn: Callable, jobs: list) -> Iterator[tuple[int, object]]:
        from ray.exceptions import RayTaskError

        ray = self.ray
        remote = ray.remote(fn)
        queue = list(enumerate(jobs))
        running: dict = {}
        limit = self.max_in_flight or len(jobs)
        try:
            while queue or running:
                while queue and len(running) < limit:
                    i, job = queue.pop(0)
                    task = remote.options(num_cpus=job.cpus, num_gpus=0, max_retries=RAY_RETRIES,
                                          name=f"{job.label} seed {job.seed}")
                    running[task.remote(with_absolute_paths(job))] = i
                done, _ = ray.wait(list(running), num_returns=1)
                i = running.pop(done[0])
                try:
                    yield i, ray.get(done[0])
                except RayTaskError as exc:
                    cause = exc.cause
                    raise (cause if isinstance(cause, USER_ERRORS) else exc) from None
        finally:
            for ref in running:
                ray.cancel(ref, force=True)

    def close(self) -> None:
        self.ray.shutdown()
        if self.temp_dir:
            shutil.rmtree(self.temp_dir, ignore_errors=True)


def make_executor(cfg: BenchConfig, slots: Slots, suite, data):
    """The executor `cfg.executor` names; one parallel slot runs the jobs here, as serial."""
    if cfg.executor == "ray":
        return RayExecutor(available_cores(), cfg.jobs)
    if cfg.executor == "local" and slots.parallel > 1:
        return LocalExecutor(slots.parallel)
    return SerialExecutor(cfg, suite, data, slots.eval_workers)


def _source_root() -> str:
    """The folder that holds harness/, methods/, ...: a Ray worker imports this code."""
    return str(Path(__file__).resolve().parents[2])


def _die_with_parent() -> None:
    """A local worker is SIGKILLed when the process that started it dies (Linux), so a killed
    comparison leaves no job running on beside its rerun."""
    try:
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)  # PR_SET_PDEATHSIG
    except OSError:
        pass
