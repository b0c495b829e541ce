"""Opening a results folder or a cache runs nothing a pickle holds (issue 48): stage checkpoints,
the foundation's weights and LIBERO's init-state files are read with torch's weights-only
unpickler and a short allow-list; anything else is refused in one line."""

from __future__ import annotations

import os
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from harness.common.errors import RetainError
from harness.data.datasets import TrainingData
from harness.evaluate.stages import CheckpointError, load_checkpoint, save_checkpoint


class Planted:
    """What a crafted checkpoint holds: unpickled the old way (weights_only=False), it would
    create `marker`."""

    def __init__(self, marker: Path):
        self.marker = marker

    def __reduce__(self):
        return (os.system, (f"touch {self.marker}",))


def plant(path: Path, marker: Path) -> None:
    """A file in a checkpoint's place whose unpickling would run a shell command."""
    path.parent.mkdir(parents=True, exist_ok=True)
    torch.save({"run_key": "x", "policy": {"w": torch.zeros(2)}, "method": Planted(marker)}, path)


def one_line(err) -> str:
    text = str(err.value)
    assert "\n" not in text
    return text


def test_a_crafted_checkpoint_is_refused_and_runs_nothing(tmp_path):
    marker = tmp_path / "ran"
    path = tmp_path / "stages" / "stage_1.pt"
    plant(path, marker)
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(path)
    text = one_line(err)
    assert str(path) in text and "posix.system" in text and "delete it" in text
    assert not marker.exists()
    assert isinstance(err.value, RetainError)  # the CLI prints it as one line, exit 2


def test_the_resume_check_refuses_a_crafted_stage_checkpoint(tmp_path):
    from harness.protocol.stream import resumable_stage

    marker = tmp_path / "ran"
    plant(tmp_path / "stages" / "stage_2.pt", marker)
    with pytest.raises(CheckpointError, match="stage_2.pt was not loaded"):
        resumable_stage(tmp_path / "stages", 2, "key")
    assert not marker.exists()


def test_a_truncated_checkpoint_says_to_rebuild_it(tmp_path):
    path = tmp_path / "policy.pt"
    save_checkpoint(path, {"policy": {"w": torch.ones(64)}})
    path.write_bytes(path.read_bytes()[:80])
    with pytest.raises(CheckpointError) as err:
        load_checkpoint(path)
    assert "not a readable checkpoint" in one_line(err) and "make clean-cache" in one_line(err)


def test_what_methods_keep_round_trips(tmp_path):
    """Tensors, numbers, strings, lists, tuples, dicts and TrainingData (a replay buffer) load."""
    buffer = TrainingData({"state": torch.randn(3, 4)}, torch.randn(3, 2, 2),
                          torch.ones(3, 2, dtype=torch.bool), torch.tensor([0, 1, 1]),
                          torch.zeros(2, 8), ["a", "b"], torch.ones(2, 5, dtype=torch.long),
                          torch.tensor([0, 1]))
    payload = {"run_key": "k", "policy": {"w": torch.randn(3)}, "records": [{"x": 0.5}],
               "method": {"buffer": buffer, "seen": None, "owner": {"w": torch.zeros(3, dtype=torch.int16)},
                          "pair": (1, "a"), "flag": True, "nan": float("nan")}}
    save_checkpoint(tmp_path / "c.pt", payload)
    loaded = load_checkpoint(tmp_path / "c.pt")
    kept = loaded["method"]["buffer"]
    assert isinstance(kept, TrainingData) and kept.task_names == ["a", "b"]
    assert torch.equal(kept.obs["state"], buffer.obs["state"])
    assert torch.equal(kept.instruction_ids, buffer.instruction_ids)
    assert loaded["method"]["pair"] == (1, "a") and np.isnan(loaded["method"]["nan"])


def test_a_state_that_would_not_load_fails_when_saved_naming_it(tmp_path):
    """A user's method whose state holds another object fails at the first checkpoint, not at
    the resume that would need it."""
    with pytest.raises(CheckpointError) as err:
        save_checkpoint(tmp_path / "c.pt", {"method": {"table": {"x": np.float64(1.0)}}})
    text = one_line(err)
    assert "checkpoint['method']['table']['x']" in text and "numpy.float64" in text
    assert not (tmp_path / "c.pt").exists()


def test_a_rerun_over_a_crafted_checkpoint_stops_in_one_line_and_runs_nothing(tmp_path, capsys):
    """The whole command: a finished tiny run, one of its checkpoints replaced, the rerun."""
    from harness.run.cli import main

    args = ["bench", "PROFILE=tiny", "METHOD=sft", f"results_dir={tmp_path}/results",
            f"cache_dir={tmp_path}/cache", "progress=false", "executor=serial", "eval_workers=1"]
    assert main(args) == 0
    stage = next((tmp_path / "results").rglob("stages/stage_2.pt"))
    marker = tmp_path / "ran"
    plant(stage, marker)
    capsys.readouterr()
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("error: ") and "stage_2.pt" in err
    assert not marker.exists()
    # the foundation's weights are read the same way
    weights = next((tmp_path / "cache" / "foundation").rglob("policy.pt"))
    plant(weights, marker)
    shutil.rmtree(stage.parent)
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "policy.pt" in err and not marker.exists()


def test_liberos_init_states_load_as_numpy_arrays_only(tmp_path, monkeypatch):
    pytest.importorskip("libero")
    import suites.libero.tasks as tasks
    from suites.base import SuiteError

    name = next(iter(tasks.all_tasks()))
    task = tasks.all_tasks()[name]
    states = tasks.init_states.__wrapped__(name)
    assert states.shape == (50, len(states[0])) and states.dtype == np.float64
    # the same numbers the old, unsafe load gave
    assert np.array_equal(states, np.asarray(torch.load(task.init_states_file, weights_only=False)))
    marker = tmp_path / "ran"
    crafted = tmp_path / "crafted.pruned_init"
    torch.save(Planted(marker), crafted)
    fake = {name: tasks.LiberoTask(name, task.suite, 0, task.instruction, task.bddl_file,
                                   str(crafted))}
    monkeypatch.setattr(tasks, "all_tasks", lambda: fake)
    with pytest.raises(SuiteError) as err:
        tasks.init_states.__wrapped__(name)
    assert "posix.system" in one_line(err) and str(crafted) in one_line(err)
    assert not marker.exists()
