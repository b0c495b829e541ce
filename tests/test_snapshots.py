"""A foundation killed mid-training resumes from its snapshot to the uninterrupted weights."""

import itertools
import tempfile
import time
import types
from pathlib import Path

import pytest
import torch

from harness.evaluate.stages import load_checkpoint, save_checkpoint
from harness.perf.throughput import _policy, synthetic_data
from harness.train.trainer import Snapshots, TrainSettings, train_stage
from methods import Method, TaskContext

SETTINGS = TrainSettings(steps=12, batch_size=32, lr=1e-3, weight_decay=0.01)


class Killed(Exception):
    pass


def _train(snapshots=None, kill_at=None):
    torch.manual_seed(0)
    policy = _policy("tiny")
    ctx = TaskContext(0, "foundation", synthetic_data(512, 0), policy, float("nan"), SETTINGS.steps)

    def after_step(done):
        if done == kill_at:
            raise Killed

    result = train_stage(ctx, Method(), SETTINGS, torch.Generator().manual_seed(3),
                         after_step=after_step, snapshots=snapshots)
    return policy, result


class Store:
    """Snapshots kept in a file as the foundation keeps them: written by save_checkpoint, read
    back by load_checkpoint's weights-only unpickler (the optimizer's moments and the generator
    state are plain data it allows)."""

    def __init__(self, every_seconds=0.0):
        self.folder = tempfile.TemporaryDirectory()
        self.path, self.saved, self.steps = Path(self.folder.name) / "snapshot.pt", False, []
        self.snapshots = Snapshots(self.load, self.save, every_seconds)

    def load(self):
        return load_checkpoint(self.path) if self.saved else None

    def save(self, state):
        save_checkpoint(self.path, state)
        self.saved = True
        self.steps.append(state["step"])


@pytest.mark.parametrize("cores", [1, 4])  # 4: the next batch is prefetched on a second thread
def test_a_stage_killed_after_a_snapshot_resumes_to_the_uninterrupted_weights(monkeypatch, cores):
    monkeypatch.setattr("harness.train.trainer.os.cpu_count", lambda: cores)
    reference, ref_result = _train()
    store = Store()
    with pytest.raises(Killed):
        _train(store.snapshots, kill_at=7)
    assert store.steps == [1, 2, 3, 4, 5, 6]  # every step but the killed one and the last
    resumed, result = _train(store.snapshots)
    assert store.steps[6:] == [7, 8, 9, 10, 11]  # it went on from step 6
    assert result == ref_result  # the final loss averages steps before and after the kill
    for (name, a), b in zip(reference.state_dict().items(), resumed.state_dict().values()):
        assert torch.equal(a, b), name


def test_snapshots_wait_for_their_interval():
    store = Store(every_seconds=3600)
    _train(store.snapshots)
    assert store.steps == []


def test_prefetching_resumes_after_a_snapshot_step(monkeypatch):
    """A snapshot step samples its next batch itself; the steps after it prefetch again."""
    monkeypatch.setattr("harness.train.trainer.os.cpu_count", lambda: 4)  # prefetch on
    reference, ref_result = _train()
    clock = itertools.count()  # one second a reading: a snapshot every third step
    monkeypatch.setattr("harness.train.trainer.time", types.SimpleNamespace(
        monotonic=lambda: float(next(clock)), perf_counter=time.perf_counter))
    store = Store(every_seconds=3)
    with pytest.raises(Killed):
        _train(store.snapshots, kill_at=8)
    assert store.steps == [3, 6]
    resumed, result = _train(store.snapshots)
    assert result == ref_result
    for (name, a), b in zip(reference.state_dict().items(), resumed.state_dict().values()):
        assert torch.equal(a, b), name
