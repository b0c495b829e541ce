"""Figures stay readable with LIBERO's 60-character task names: every tick label inside the
figure and none on top of another (they overlapped and were cut off, a run's heatmap and the
report's alike)."""

import itertools
import warnings
from types import SimpleNamespace

import numpy as np
import pytest
from matplotlib.backends.backend_agg import FigureCanvasAgg

from harness.config.benchmark import load_benchmark
from harness.measure.bootstrap import Interval
from harness.report import plots
from harness.track import figures


@pytest.fixture
def drawn(monkeypatch):
    """The figures a function would save, drawn instead; tight_layout's warnings are errors."""
    out = []
    monkeypatch.setattr(figures, "save", lambda fig, path: out.append(fig))
    monkeypatch.setattr(plots, "save", lambda fig, path: out.append(fig))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        yield out


def tick_label_boxes(fig):
    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()
    boxes = []
    for axis in (fig.axes[0].xaxis, fig.axes[0].yaxis):  # the labels drawn: ticks in view
        lo, hi = sorted(axis.get_view_interval())
        boxes.append([label.get_window_extent(renderer)
                      for loc, label in zip(axis.get_ticklocs(), axis.get_ticklabels())
                      if lo <= loc <= hi and label.get_text()])
    return boxes, fig.bbox


def assert_readable(fig):
    axes_boxes, page = tick_label_boxes(fig)
    for boxes in axes_boxes:
        assert boxes
        for box in boxes:
            assert page.x0 <= box.x0 and box.x1 <= page.x1 and page.y0 <= box.y0 and box.y1 <= page.y1
        for a, b in itertools.combinations(boxes, 2):
            assert not a.overlaps(b)


def test_task_labels_keep_the_name_and_break_long_ones_at_its_separators():
    assert figures.task_label("button-press-topdown-wall-v3") == "button-press-topdown-wall"
    name = "LIVING_ROOM_SCENE4_pick_up_the_chocolate_pudding_and_put_it_in_the_tray"
    label = figures.task_label(name)
    assert label.replace("\n", "") == name
    assert all(0 < len(line) <= figures.LABEL_WIDTH for line in label.split("\n"))
    assert all(line.endswith("_") for line in label.split("\n")[:-1])


@pytest.mark.parametrize("bench", ["libero-broad", "libero-quick", "mw-broad"])
def test_a_success_matrix_shows_every_label_whole(drawn, bench):
    cfg = load_benchmark(bench)
    tasks = cfg.foundation_tasks + cfg.stream_tasks
    R = np.random.default_rng(0).random((len(cfg.stream_tasks) + 1, len(tasks)))
    R[0, len(cfg.foundation_tasks):] = np.nan
    figures.success_matrix(None, R, tasks, ["foundation", *cfg.stream_tasks],
                           len(cfg.foundation_tasks), f"{bench}: sft, seed 0",
                           trained=[1] * len(cfg.stream_tasks))
    assert_readable(drawn[0])


def test_the_foundation_curves_show_every_stage_name_whole(drawn):
    cfg = load_benchmark("libero-broad")
    stages = len(cfg.stream_tasks) + 1
    summary = SimpleNamespace(label="sft", stages=[[t] for t in cfg.stream_tasks],  # what the
                              stage_names=["foundation", *cfg.stream_tasks],  # figure reads
                              foundation_by_stage=[Interval(0.5, 0.4, 0.6, 3)] * stages)
    plots.foundation_curves(None, [summary], "libero-broad")
    assert_readable(drawn[0])
