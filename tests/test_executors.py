"""Executors: the same tiny comparison (2 methods x 2 seeds) serially, in local processes and as
tasks of an in-process local Ray gives identical results; a Ray worker SIGKILLed mid-stage is
retried and continues; a killed and rerun comparison leaves one FINISHED MLflow run per job."""

import os
import re
import shutil
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from harness.config.benchmark import resolve
from harness.run.executors import plan_slots

ROOT = Path(__file__).resolve().parents[1]
OUTPUTS = ("success_matrix.csv", "metrics.json", "heldout_loss.csv")
RUNS = [(label, seed) for label in ("sft", "er") for seed in (0, 1)]


def _cmd(results, cache, *args):
    return [sys.executable, "-m", "harness", "bench", "PROFILE=tiny", "METHOD=sft,er", "SEEDS=2",
            f"results_dir={results}", f"cache_dir={cache}", "progress=false", *args]


def _env():
    env = {k: v for k, v in os.environ.items() if k not in ("RAY_ADDRESS", "MLFLOW_TRACKING_URI")}
    return {**env, "PYTHONUNBUFFERED": "1"}


def _run(cmd):
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300, cwd=ROOT, env=_env())
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    return proc.stdout


def _outputs(results, runs=RUNS):
    base = Path(results) / "mw-quick-tiny"
    return {(label, seed, name): (base / label / f"seed{seed}" / name).read_text()
            for label, seed in runs for name in OUTPUTS}


def _runs(results):
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=f"sqlite:///{results}/mlflow.db")
    return client.search_runs([client.get_experiment_by_name("mw-quick-tiny").experiment_id])


@pytest.fixture(scope="module")
def serial(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("serial")
    # two evaluation workers here, one per job elsewhere: the results must not depend on it
    _run(_cmd(tmp / "results", tmp / "cache", "executor=serial", "eval_workers=2"))
    return tmp, _outputs(tmp / "results")


@pytest.mark.slow
def test_local_processes_match_serial(tmp_path, serial):
    # the serial run's demos, not its foundations: the worker processes build those too
    for part in ("demos", "instructions"):
        shutil.copytree(serial[0] / "cache" / part, tmp_path / "cache" / part)
    out = _run(_cmd(tmp_path / "results", tmp_path / "cache", "executor=local", "jobs=2",
                    "eval_workers=1"))
    assert "2 at once, 1 evaluation worker each" in out
    assert _outputs(tmp_path / "results") == serial[1]
    done = re.findall(r"\[retain\] (\d)/4 (\w+) seed (\d): foundation success .* left\)", out)
    assert sorted((label, int(seed)) for _, label, seed in done) == sorted(RUNS)
    assert "foundation ready" in out and len(list((tmp_path / "cache/foundation").iterdir())) == 2
    runs = _runs(tmp_path / "results")
    assert len(runs) == 5 and all(r.info.status == "FINISHED" for r in runs)


@pytest.mark.slow
def test_ray_worker_killed_mid_stage_is_retried_and_continues(tmp_path, serial):
    """Kill the Ray worker running a job (its pid from Ray's own log prefix) once the job's
    stage 1 is done: Ray runs the task again, it resumes after stage 1, results are the same."""
    cmd = _cmd(tmp_path / "results", serial[0] / "cache", "executor=ray", "eval_workers=1")
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            cwd=ROOT, env=_env())
    killed, lines = None, []
    for line in proc.stdout:
        lines.append(line)
        found = re.search(r"pid=(\d+)\).*\[retain\] (\w+) seed (\d): stage 1 ", line)
        if found and killed is None:
            os.kill(int(found[1]), signal.SIGKILL)
            killed = (found[2], int(found[3]))
    assert proc.wait(timeout=60) == 0, "".join(lines[-40:])
    out = "".join(lines)
    assert killed is not None, out[-3000:]
    label, seed = killed
    assert f"[retain] {label} seed {seed}: resuming after stage 1 of 2" in out, out[-3000:]
    assert _outputs(tmp_path / "results") == serial[1]
    runs = _runs(tmp_path / "results")
    assert len(runs) == 5 and all(r.info.status == "FINISHED" for r in runs)


@pytest.mark.slow
def test_killed_comparison_rerun_leaves_one_finished_run_per_job(tmp_path, serial):
    cmd = _cmd(tmp_path / "results", serial[0] / "cache", "executor=local", "jobs=2",
               "eval_workers=1")
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            cwd=ROOT, env=_env())
    for line in proc.stdout:
        if ": stage 1 (" in line:  # a job is in stage 2, the others wherever they are
            break
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    before = _runs(tmp_path / "results")
    assert any(r.info.status == "RUNNING" for r in before)  # what the kill left
    out = _run(cmd)
    # jobs the killed invocation finished are reported as such, and left out of the time estimate
    earlier = {(r.data.tags["label"], r.data.tags["seed"]) for r in before
               if r.info.status == "FINISHED" and "mlflow.parentRunId" in r.data.tags}
    for label, seed in RUNS:
        line = next(x for x in out.splitlines() if f" {label} seed {seed}: foundation" in x)
        assert line.endswith("(finished earlier)") == ((label, str(seed)) in earlier), line
    runs = _runs(tmp_path / "results")
    children = [r for r in runs if "mlflow.parentRunId" in r.data.tags]
    parents = [r for r in runs if "mlflow.parentRunId" not in r.data.tags]
    assert [r.info.status for r in runs] == ["FINISHED"] * 5
    assert len(parents) == 1
    assert sorted((r.data.tags["label"], int(r.data.tags["seed"])) for r in children) == sorted(RUNS)
    assert {r.data.tags["mlflow.parentRunId"] for r in children} == {parents[0].info.run_id}
    assert _outputs(tmp_path / "results") == serial[1]


def test_time_left_is_estimated_from_the_jobs_run_now():
    from harness.run.execute import Progress

    progress = Progress(total=4, finished_earlier=2)
    assert progress.done_one(earlier=True) == ("1/4", "finished earlier")
    progress.start -= 120  # the first job run now took two minutes; one more is to run
    count, times = progress.done_one()
    assert count == "2/4" and times.startswith("2m00s elapsed") and times.endswith("about 2m00s left")
    assert progress.done_one(earlier=True) == ("3/4", "finished earlier")
    assert progress.done_one()[1].endswith("about 0s left")


def test_a_setting_given_outside_grid_gets_its_own_run_directory():
    from harness.protocol.stream import run_dir
    from harness.run.plan import plan

    default = plan(["PROFILE=tiny", "METHOD=sft,consft"]).variants
    changed = plan(["PROFILE=tiny", "METHOD=sft,consft", "lr=1e-4", "kappa=0.5"]).variants
    assert [v.label for v in default] == ["sft", "consft"]
    assert [v.label for v in changed] == ["sft[lr=0.0001]", "consft[lr=0.0001 kappa=0.5]"]
    assert str(run_dir(changed[0].cfg, changed[0].label, 0)).endswith(
        "mw-quick-tiny/sft[lr=0.0001]/seed0")
    assert run_dir(default[0].cfg, "sft", 0) != run_dir(changed[0].cfg, changed[0].label, 0)
    # settings that cannot change results (where, how fast) leave the label alone
    same = plan(["PROFILE=tiny", "METHOD=sft", "executor=ray", "jobs=3", "eval_workers=2"])
    assert same.variants[0].label == "sft"


@pytest.mark.parametrize("args, cores, expected", [
    (["executor=local"], 2, (2, 1)),  # one evaluation worker per job, a job per core
    (["executor=local", "eval_workers=2"], 2, (1, 2)),  # each job keeps both cores busy
    (["executor=local", "jobs=3"], 8, (3, 2)),  # three jobs share the cores for evaluation
    (["executor=local"], 16, (4, 2)),  # never more jobs at once than there are jobs, and
    # never more evaluation workers than eval_shards=2 (a CPU policy's shards: more get no work)
    (["executor=serial"], 2, (1, 2)),
    (["executor=serial"], 16, (1, 2)),
    (["executor=ray"], 2, (4, 1)),  # Ray places the tasks, one evaluation worker each
    (["executor=ray", "jobs=2", "eval_workers=3"], 2, (2, 2)),  # 3 asked, eval_shards=2 run
    (["executor=ray", "jobs=2", "eval_workers=3", "eval_shards=4"], 2, (2, 3)),
])
def test_jobs_at_once_follow_the_cores(args, cores, expected):
    cfg = resolve(["PROFILE=tiny", *args])
    slots = plan_slots(cfg, n_jobs=4, cores=cores)
    assert (slots.parallel, slots.eval_workers) == expected


# libero-paper's evaluation worker: 42 LIBERO simulators of 180 MB and the process, 7.9 GB
LIBERO_WORKER_MB = 500 + 42 * 180


@pytest.mark.parametrize("args, cores, memory_gb, expected", [
    (["executor=local"], 2, 24, (2, 1)),  # the two-core machine: both fit, as before
    (["executor=local"], 16, 24, (2, 1)),  # 16 cores, but two workers' simulators fit
    (["executor=local"], 16, 128, (4, 2)),  # 13 fit: 4 jobs of the 2 workers that have work
    (["executor=local"], 16, 8, (1, 1)),  # not even one fits: one, rather than none
    (["executor=local", "eval_workers=2"], 16, 24, (1, 2)),  # a setting given is kept
    (["executor=local", "jobs=4"], 16, 24, (4, 1)),  # ... and the rest fit around it
    (["executor=serial"], 16, 24, (1, 2)),  # 2 fit, and only eval_shards=2 have work
    (["executor=ray"], 16, 8, (4, 1)),  # Ray's machines are not this one
])
def test_jobs_at_once_follow_the_memory(args, cores, memory_gb, expected):
    cfg = resolve(["PROFILE=tiny", *args])
    slots = plan_slots(cfg, n_jobs=4, cores=cores, worker_mb=LIBERO_WORKER_MB,
                       memory_mb=memory_gb * 1024)
    assert (slots.parallel, slots.eval_workers) == expected
    by_cores = plan_slots(cfg, n_jobs=4, cores=cores)
    if (slots.parallel, slots.eval_workers) == (by_cores.parallel, by_cores.eval_workers):
        assert slots.memory_note == ""
    else:
        assert "7.9 GB of simulators" in slots.memory_note and f"{memory_gb:.1f} GB" in slots.memory_note


@pytest.mark.parametrize("args, cores, expected", [
    (["executor=local", "eval_workers=1000"], 16, (4, 2)),  # eval_shards=2 run, not 1000
    (["executor=serial", "eval_workers=1000", "eval_shards=8"], 16, (1, 8)),
    (["executor=serial", "eval_workers=1000", "eval_shards=64"], 16, (1, 16)),  # the cores
    (["executor=ray", "eval_workers=1000"], 16, (4, 2)),  # a Ray task asks for 2 cores
])
def test_evaluation_workers_are_the_ones_that_will_run(args, cores, expected):
    """`eval_workers=1000` once printed "1000 evaluation workers each" while 2 ran (a CPU
    policy is evaluated in eval_shards shards, one per worker): the plan says what runs, never
    starts more processes than there are shards (or cores), and says why in one line."""
    cfg = resolve(["PROFILE=tiny", *args])
    slots = plan_slots(cfg, n_jobs=4, cores=cores)
    assert (slots.parallel, slots.eval_workers) == expected
    assert slots.workers_note.startswith(f"{expected[1]} evaluation worker(s) per job, not "
                                         "eval_workers=1000: ")
    assert "\n" not in slots.workers_note
    assert plan_slots(resolve(["PROFILE=tiny", "eval_workers=2"]), 4, cores=cores).workers_note == ""


def test_the_banner_names_the_workers_that_run(tmp_path, capsys):
    from harness.run.cli import main

    assert main(["bench", "PROFILE=tiny", "METHOD=sft", "eval_workers=1000", "executor=serial",
                 f"results_dir={tmp_path}/results", f"cache_dir={tmp_path}/cache",
                 "progress=false"]) == 0
    out = capsys.readouterr().out
    assert "(1 at once, 2 evaluation workers each)" in out and "1000 evaluation" not in out
    assert "2 evaluation worker(s) per job, not eval_workers=1000" in out


def test_an_evaluation_worker_holds_a_simulator_per_task():
    from harness.run.executors import evaluation_worker_mb
    from suites.libero import LiberoSuite

    cfg = resolve(["BENCH=libero-paper"])
    assert len(cfg.all_tasks()) == 42 and cfg.eval_envs_per_task == 1
    assert evaluation_worker_mb(cfg, LiberoSuite) == 500 + 42 * 180
    cfg.cameras = True
    assert evaluation_worker_mb(cfg, LiberoSuite) == 500 + 42 * 325


def test_unknown_executor_is_a_one_line_error(capsys):
    from harness.run.cli import main

    assert main(["bench", "PROFILE=tiny", "executor=spark"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "'spark'" in err and "serial, local, ray" in err
