"""The worked example of docs/adding-a-method.md, run from outside the repository as a user would."""

import csv
import re
import subprocess
import sys
from pathlib import Path

import pytest

DOC = Path(__file__).resolve().parents[1] / "docs" / "adding-a-method.md"


def _example_module(tmp_path) -> Path:
    code = re.search(r"```python\n(.*?)```", DOC.read_text(), re.S).group(1)
    path = tmp_path / "plugin" / "my_methods.py"
    path.parent.mkdir()
    path.write_text(code)
    return path


def _bench(tmp_path, *args, env_path=None):
    import os

    env = dict(os.environ)
    if env_path:
        env["PYTHONPATH"] = f"{env_path}{os.pathsep}{env.get('PYTHONPATH', '')}"
    cmd = [sys.executable, "-m", "harness", "bench", "PROFILE=tiny", f"results_dir={tmp_path}/results",
           f"cache_dir={tmp_path}/cache", "progress=false", *args]
    return subprocess.run(cmd, capture_output=True, text=True, timeout=300, env=env,
                          cwd=Path(__file__).resolve().parents[1])


def test_documented_example_runs_by_module_name_and_freezes_the_encoders(tmp_path):
    module = _example_module(tmp_path)
    proc = _bench(tmp_path, "METHOD=my_methods:ExpertOnlySFT", "train_time_encoder=false",
                  env_path=module.parent)
    assert proc.returncode == 0, proc.stderr[-2000:]
    run = tmp_path / "results/mw-quick-tiny/expert_only[train_time_encoder=False]/seed0"
    rows = list(csv.DictReader(open(run / "updates_per_layer.csv")))
    change = {r["layer"]: float(r["relative_l2"]) for r in rows}
    assert change["instruction_proj.weight"] == 0.0 and change["time_encoder.0.weight"] == 0.0
    assert change["blocks.0.mlp.0.weight"] > 0.0


def test_documented_example_runs_by_file_path_and_rejects_a_typo(tmp_path):
    module = _example_module(tmp_path)
    proc = _bench(tmp_path, f"METHOD={module}:ExpertOnlySFT", "train_time_encodr=false")
    assert proc.returncode != 0
    assert proc.stderr.strip().count("\n") == 0
    assert "'train_time_encodr'" in proc.stderr and "train_time_encoder" in proc.stderr


@pytest.mark.parametrize("spec, message", [
    ("collections:OrderedDict", "is not a method"),
    ("json:NoSuchClass", "has no class 'NoSuchClass'"),
])
def test_a_class_that_is_not_a_method_is_refused(tmp_path, spec, message):
    proc = _bench(tmp_path, f"METHOD={spec}")
    assert proc.returncode != 0 and message in proc.stderr and proc.stderr.strip().count("\n") == 0


def test_a_users_method_without_a_name_of_its_own_is_refused(tmp_path):
    """It would inherit "sft" and be filed, labelled and reported as the built-in SFT."""
    plugin = tmp_path / "nameless.py"
    plugin.write_text("from methods.consft import ConSFT\n\n\nclass Tweaked(ConSFT):\n    pass\n")
    proc = _bench(tmp_path, f"METHOD={plugin}:Tweaked")
    assert proc.returncode == 2 and proc.stderr.strip().count("\n") == 0
    assert "needs a name of its own" in proc.stderr and "'consft' is a built-in" in proc.stderr
