"""Bad input stops with one line naming the bad value and the valid choices, before long work."""

import subprocess
import sys

import pytest


def _bench(tmp_path, *args):
    cmd = [sys.executable, "-m", "harness", "bench", f"results_dir={tmp_path}/results",
           f"cache_dir={tmp_path}/cache", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("args, expected", [
    (["METHOD=nope"], ["'nope'", "sft"]),
    (["BENCH=mw-nope"], ["'mw-nope'", "mw-quick", "mw-standard"]),
    (["PROFILE=huge"], ["'huge'", "quick", "tiny"]),
    (["stream_tasks=drawer-close-v3,fly-v3"], ["'fly-v3'", "reach-v3"]),
    (["steps_per_task"], ["'steps_per_task'", "key=value"]),
    (["steps_per_task=many"], ["'many'", "steps_per_task", "int"]),
    (["kapa=0.1"], ["'kapa'", "steps_per_task"]),
    (["stream_tasks=reach-v3"], ["'reach-v3'", "both"]),
    (["GRID=kappa"], ["'kappa'", "key=v1,v2"]),
    (["GRID=eval_episodes=5,10"], ["'eval_episodes'", "separate benchmarks"]),
    (["METHOD=consft", "variant=clipp"], ["'clipp'", "paper, kappa_temp, dft, ratio"]),
])
def test_bad_input_is_one_line_and_nonzero(tmp_path, args, expected):
    proc = _bench(tmp_path, *args)
    assert proc.returncode != 0
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1, proc.stderr
    assert lines[0].startswith("error: ")
    for text in expected:
        assert text in lines[0]
    assert not (tmp_path / "cache").exists()  # nothing was generated
    assert not (tmp_path / "results").exists()  # nothing was tracked
