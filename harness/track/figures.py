"""What a run's own figure and the report's figures share: task labels that fit, the success
matrix drawn one way, and PNGs that are the same bytes for the same numbers.

LIBERO's task names run to 60 characters ("pick_up_the_chocolate_pudding_and_place_it_in_the_basket");
labels are broken into lines at the name's own separators and figures are sized from the
longest line, so a 22-task LIBERO matrix reads as well as a Meta-World one.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from harness.common.atomic import atomic_path

DPI = 120
FONT_PT = 8
CHAR_IN = 0.62 * FONT_PT / 72  # width of one character of the tick font, inches (DejaVu Sans)
LINE_IN = 1.25 * FONT_PT / 72  # height of one line of it
LABEL_WIDTH = 26  # characters per label line: every Meta-World name fits on one


def task_label(task: str, width: int = LABEL_WIDTH) -> str:
    """A task's name for a figure: the version suffix dropped ("drawer-close-v3" ->
    "drawer-close"), a long name broken into lines after its '_' or '-' separators."""
    name = re.sub(r"-v\d+$", "", task)
    lines, line = [], ""
    for word in re.findall(r"[^_-]+[_-]*|[_-]+", name):
        if line and len(line) + len(word) > width:
            lines.append(line)
            line = ""
        line += word
    return "\n".join([*lines, line])


def text_size(labels: list[str]) -> tuple[float, float]:
    """(width, height) in inches of the largest of some tick labels, unrotated."""
    lines = [label.split("\n") for label in labels] or [[""]]
    return (max(len(line) for ls in lines for line in ls) * CHAR_IN,
            max(len(ls) for ls in lines) * LINE_IN)


def save(fig: Figure, path: Path) -> None:
    """Without the matplotlib version in the metadata: same figure, same bytes."""
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=DPI, metadata={"Software": None})


def success_matrix(path: Path, R: np.ndarray, tasks: list[str], stage_names: list[str],
                   n_foundation: int, title: str, trained: list[int] | None = None) -> None:
    """Stages (rows) by tasks (columns), foundation tasks left of the red line; NaN cells (never
    evaluated) grey. With `trained` (stream tasks per stage, in stream order), stage i's own
    stream tasks are outlined together (their mean is its plasticity term)."""
    from matplotlib import colormaps
    from matplotlib.patches import Rectangle

    xlabels = [task_label(t) for t in tasks]
    ylabels = [f"{i}: {task_label(t)}" for i, t in enumerate(stage_names)]
    (xw, xh), (yw, yh) = text_size(xlabels), text_size(ylabels)
    cell_w, cell_h = max(0.62, xh + 0.15), max(0.5, yh + 0.12)  # room for a label's lines
    fig = Figure(figsize=(yw + cell_w * len(tasks) + 2.2, xw + cell_h * len(R) + 1.3))
    ax = fig.add_subplot()
    cmap = colormaps["viridis"].with_extremes(bad="lightgrey")
    im = ax.imshow(np.ma.masked_invalid(R), vmin=0, vmax=1, cmap=cmap, aspect="auto")
    for (i, j), v in np.ndenumerate(R):
        ax.text(j, i, "n/a" if np.isnan(v) else f"{v:.2f}", ha="center", va="center",
                fontsize=FONT_PT, color="white" if np.isnan(v) or v < 0.6 else "black")
    if trained:
        first = n_foundation
        for i, size in enumerate(trained, start=1):
            ax.add_patch(Rectangle((first - 0.5, i - 0.5), size, 1, fill=False,
                                   edgecolor="white", linewidth=1.5))
            first += size
    ax.axvline(n_foundation - 0.5, color="red", linewidth=2)
    ax.set_xticks(range(len(tasks)), xlabels, rotation=90, fontsize=FONT_PT)
    ax.set_yticks(range(len(R)), ylabels, fontsize=FONT_PT)
    ax.set_xlabel("evaluated task (left of red line: foundation; right: stream)")
    ax.set_ylabel("stage: trained on")
    ax.set_title(title, fontsize=10)
    fig.colorbar(im, ax=ax, label="success rate")
    fig.tight_layout()
    save(fig, path)
