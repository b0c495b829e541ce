"""Faults: SIGKILL at several points then resume, determinism, NaN losses, tracking stores."""

import os
import signal
import subprocess
import sys
import time
import zipfile
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
OUTPUTS = ("success_matrix.csv", "metrics.json", "heldout_loss.csv")


def _cmd(tmp, *args, cache=None):
    return [sys.executable, "-m", "harness", "bench", "PROFILE=tiny", "METHOD=er",
            f"results_dir={tmp}/results", f"cache_dir={cache or tmp / 'cache'}", "progress=false",
            "eval_workers=1", *args]


def _run(cmd, env=None, timeout=300):
    return subprocess.run(cmd, capture_output=True, text=True, timeout=timeout, cwd=ROOT,
                          env=env or dict(os.environ))


def _outputs(tmp, method="er", seed=0):
    run = Path(tmp) / "results" / "mw-quick-tiny" / method / f"seed{seed}"
    return {name: (run / name).read_text() for name in OUTPUTS}


def _kill_when(cmd, marker: str, delay: float) -> None:
    """Start `cmd`, SIGKILL it `delay` seconds after a line containing `marker` appears."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, cwd=ROOT)
    for line in proc.stdout:
        if marker in line:
            time.sleep(delay)
            break
    proc.send_signal(signal.SIGKILL)
    proc.wait()


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("reference")
    proc = _run(_cmd(tmp))
    assert proc.returncode == 0, proc.stderr[-2000:]
    return tmp, _outputs(tmp)


@pytest.mark.slow
def test_killed_runs_resume_to_the_same_results(tmp_path, reference):
    # killed while generating demos, while training the foundation, and mid-stream
    _kill_when(_cmd(tmp_path), "[retain] mw-quick-tiny", 1.5)
    _kill_when(_cmd(tmp_path), "demos ready", 0.5)
    _kill_when(_cmd(tmp_path), "stage 1 (", 0.3)
    assert (tmp_path / "results/mw-quick-tiny/er/seed0/stages/stage_1.pt").exists()
    proc = _run(_cmd(tmp_path))
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert _outputs(tmp_path) == reference[1]
    assert not list(tmp_path.rglob(".*.tmp"))  # no half-written file left behind


@pytest.mark.slow
def test_a_foundation_killed_mid_training_resumes_from_its_snapshot(tmp_path, reference):
    cmd = _cmd(tmp_path, "snapshot_minutes=0.00001")  # a snapshot after every step
    proc = subprocess.Popen(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, cwd=ROOT)
    deadline = time.monotonic() + 240
    while not list((tmp_path / "cache").glob("foundation/*/snapshot.pt")):
        assert proc.poll() is None and time.monotonic() < deadline, "no snapshot was written"
        time.sleep(0.001)
    proc.send_signal(signal.SIGKILL)  # mid-foundation: its weights are not written yet
    proc.wait()
    assert not list((tmp_path / "cache").glob("foundation/*/policy.pt"))
    proc = _run(cmd)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert "[retain] foundation seed 0: resuming at step" in proc.stdout + proc.stderr
    assert _outputs(tmp_path) == reference[1]  # the uninterrupted run's, to the last digit
    assert not list((tmp_path / "cache").glob("foundation/*/snapshot.pt"))  # removed once done


@pytest.mark.slow
def test_same_seed_same_results_and_other_seed_differs(tmp_path, reference):
    proc = _run(_cmd(tmp_path, "eval_workers=2"))  # also: worker count does not change results
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert _outputs(tmp_path) == reference[1]
    proc = _run(_cmd(tmp_path, "SEED=1"))
    assert proc.returncode == 0, proc.stderr[-2000:]
    other = _outputs(tmp_path, seed=1)
    assert other["heldout_loss.csv"] != reference[1]["heldout_loss.csv"]
    assert other["metrics.json"] != reference[1]["metrics.json"]


NAN_METHOD = '''
from methods import Method

class NaNAtStage2(Method):
    name = "nan_at_stage2"
    stage = 0

    def before_task(self, ctx):
        self.stage = ctx.stage

    def loss(self, per_sample, batch, policy):
        loss = per_sample.mean()
        return (loss * float("nan") if self.stage == 2 else loss), {}
'''


def test_nan_loss_stops_naming_method_stage_and_step_and_keeps_the_last_stage(tmp_path, reference):
    plugin = tmp_path / "nan_method.py"
    plugin.write_text(NAN_METHOD)
    cmd = _cmd(tmp_path, f"METHOD={plugin}:NaNAtStage2", cache=reference[0] / "cache")
    proc = _run(cmd)
    assert proc.returncode != 0
    assert proc.stderr.strip().count("\n") == 0
    assert "'nan_at_stage2'" in proc.stderr and "stage 2" in proc.stderr and "step 0" in proc.stderr
    run = tmp_path / "results/mw-quick-tiny/nan_at_stage2/seed0"
    assert (run / "stages/stage_1.pt").exists() and not (run / "stages/stage_2.pt").exists()


def test_unreachable_tracking_server_is_reported_before_training(tmp_path):
    env = {**os.environ, "MLFLOW_TRACKING_URI": "http://127.0.0.1:9"}
    start = time.time()
    proc = _run(_cmd(tmp_path), env=env, timeout=120)
    assert proc.returncode != 0
    assert proc.stderr.strip().count("\n") == 0 and "127.0.0.1:9" in proc.stderr
    assert "unreachable" in proc.stderr
    # the whole reason, not the first 200 characters of requests' wrapped text ("... [Err")
    assert proc.stderr.strip().endswith("[Errno 111] Connection refused"), proc.stderr
    assert "0x" not in proc.stderr and "HTTPConnectionPool" not in proc.stderr
    assert not (tmp_path / "cache").exists()  # no demo was generated
    assert time.time() - start < 60


@pytest.mark.slow
def test_three_processes_logging_to_one_store_lose_no_run(tmp_path, reference):
    from mlflow.tracking import MlflowClient

    procs = [subprocess.Popen(_cmd(tmp_path, f"SEED={seed}", "METHOD=sft", cache=reference[0] / "cache"),
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
             for seed in (0, 1, 2)]
    for p in procs:
        _, err = p.communicate(timeout=300)
        assert p.returncode == 0, err[-2000:]
    client = MlflowClient(tracking_uri=f"sqlite:///{tmp_path}/results/mlflow.db")
    runs = client.search_runs([client.get_experiment_by_name("mw-quick-tiny").experiment_id])
    children = [r for r in runs if "mlflow.parentRunId" in r.data.tags]
    assert sorted(r.data.tags["seed"] for r in children) == ["0", "1", "2"]
    assert all(r.info.status == "FINISHED" for r in runs) and len(runs) == 6


def test_a_checkpoint_saved_before_the_subpackages_still_loads(tmp_path):
    """A replay buffer pickles its TrainingData by module name; checkpoints written while the
    class lived in harness.datasets (before harness/ was grouped) must still resume."""
    from harness.data.datasets import TrainingData
    from harness.evaluate.stages import load_checkpoint, save_checkpoint

    buffer = TrainingData({"state": torch.ones(2, 3)}, torch.zeros(2, 4, 2),
                          torch.ones(2, 4, dtype=torch.bool), torch.zeros(2, dtype=torch.long),
                          torch.zeros(1, 8), ["task"])
    path = tmp_path / "stage_1.pt"
    save_checkpoint(path, {"method": {"buffer": buffer}})
    with zipfile.ZipFile(path) as z:  # the same file as the old layout wrote it
        entries = {info: z.read(info.filename) for info in z.infolist()}
    old = tmp_path / "old.pt"
    with zipfile.ZipFile(old, "w", zipfile.ZIP_STORED) as z:
        for info, data in entries.items():
            if info.filename.endswith("data.pkl"):
                assert b"harness.data.datasets\n" in data
                data = data.replace(b"harness.data.datasets\n", b"harness.datasets\n")
            z.writestr(info, data)
    with pytest.raises(ModuleNotFoundError):
        torch.load(old, weights_only=False)
    loaded = load_checkpoint(old)["method"]["buffer"]
    assert isinstance(loaded, TrainingData) and torch.equal(loaded.obs["state"], buffer.obs["state"])
