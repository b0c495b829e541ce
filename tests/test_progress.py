"""Progress of long work: a bar in place on a terminal, a line every few minutes in a log, and
the trainer's steps counted through it."""

import io

import torch

from harness.common.progress import Progress
from harness.perf.throughput import _policy, synthetic_data
from harness.train.trainer import TrainSettings, train_stage
from methods import Method, TaskContext


class Terminal(io.StringIO):
    def isatty(self):
        return True


def test_in_a_log_a_line_every_interval_and_at_the_end(monkeypatch, capsys):
    monkeypatch.delenv("RETAIN_PROGRESS", raising=False)
    monkeypatch.setenv("RETAIN_PROGRESS_EVERY", "0")
    with Progress(4, "foundation seed 0") as shown:
        for _ in range(4):
            shown.update()
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("[retain] foundation seed 0:  25%| 1/4 steps [")
    assert lines[-1].startswith("[retain] foundation seed 0: 100%| 4/4 steps [")
    monkeypatch.setenv("RETAIN_PROGRESS_EVERY", "180")  # short work: nothing in a log
    with Progress(4, "stage 1") as shown:
        shown.update(4)
    assert capsys.readouterr().out == ""


def test_on_a_terminal_a_bar_in_place_on_stderr(monkeypatch, capsys):
    terminal = Terminal()
    monkeypatch.setattr("sys.stderr", terminal)
    monkeypatch.delenv("RETAIN_PROGRESS", raising=False)
    with Progress(3, "evaluation (eval) of 2 tasks", unit="episodes") as shown:
        shown.update(2)
    text = terminal.getvalue()
    assert "\r" in text and "0/3 [" in text and "evaluation (eval) of 2 tasks" in text
    assert capsys.readouterr().out == ""
    monkeypatch.setenv("RETAIN_PROGRESS", "lines")  # jobs sharing the terminal: no bar
    assert Progress(3, "x").bar is None


def test_the_trainer_counts_its_steps(monkeypatch, capsys):
    monkeypatch.setenv("RETAIN_PROGRESS", "lines")
    monkeypatch.setenv("RETAIN_PROGRESS_EVERY", "0")
    policy = _policy("tiny")
    ctx = TaskContext(0, "foundation", synthetic_data(64, 0), policy, 0.0, 3)
    train_stage(ctx, Method(), TrainSettings(3, 16, 1e-3), torch.Generator().manual_seed(0),
                progress="foundation seed 0")
    out = capsys.readouterr().out
    assert "foundation seed 0: 100%| 3/3 steps" in out
    train_stage(ctx, Method(), TrainSettings(3, 16, 1e-3), torch.Generator().manual_seed(0))
    assert capsys.readouterr().out == ""  # no description: no progress
