"""The report's figures, one function per figure, all drawn from `RowSummary` values.

PNGs are written without the matplotlib version in their metadata and from plain `Figure`
objects (no pyplot state), so the same summaries always give the same bytes.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from harness.report.aggregate import RowSummary, SeriesSummary
from harness.track import figures
from harness.track.figures import save


def success_heatmap(path: Path, s: RowSummary, benchmark: str) -> None:
    """A row's success matrix, mean over its seeds; each stage's trained tasks outlined."""
    figures.success_matrix(path, s.success_mean, s.foundation_tasks + s.stream_tasks,
                           s.stage_names, len(s.foundation_tasks),
                           f"{benchmark}: {s.label}, success rate (mean of {len(s.row.runs)} seeds)",
                           trained=[len(g) for g in s.stages])


def colors(summaries: list[RowSummary]) -> dict[str, tuple]:
    """One fixed color per row, the same in every figure."""
    from matplotlib import colormaps

    cmap = colormaps["tab10" if len(summaries) <= 10 else "tab20"]
    return {s.label: cmap(i % cmap.N) for i, s in enumerate(summaries)}


LINESTYLES = ("-", "--", "-.", ":")
MARKERS = ("o", "s", "^", "D", "v", "P", "X", "*", "<", ">")


def line_styles(summaries: list[RowSummary]) -> dict[str, dict]:
    """One line style and one hollow marker per row, fixed like its color: two rows with the
    same numbers (SFT and ConSFT at one retention) draw one line over the other, and the one
    below stays visible through the other's dashes and around its differently shaped marker.
    Rows drawn earlier get larger markers, so a marker on top never hides one beneath."""
    n = len(summaries)
    return {s.label: {"linestyle": LINESTYLES[i % len(LINESTYLES)],
                      "marker": MARKERS[i % len(MARKERS)], "markerfacecolor": "none",
                      "markersize": 5 + 4 * (n - 1 - i) / max(n - 1, 1),
                      "markeredgewidth": 1.3}
            for i, s in enumerate(summaries)}


def foundation_curves(path: Path, summaries: list[RowSummary], benchmark: str) -> None:
    """Foundation success after each stage: one line per row, its 95% CI band over seeds."""
    longest = max(summaries, key=lambda s: len(s.stages))  # rows of other stages: the most
    ticks = [f"{i}\n{figures.task_label(t, width=16)}"
             for i, t in enumerate(longest.stage_names)]
    tick_w, tick_h = figures.text_size(ticks)
    fig = Figure(figsize=(max(8.0, 3.5 + (tick_w + 0.2) * len(ticks)), 4.0 + tick_h))
    ax = fig.add_subplot()
    color, style = colors(summaries), line_styles(summaries)
    for s in summaries:  # stages that did not roll the foundation out (NaN) are left out
        evaluated = [(i, c) for i, c in enumerate(s.foundation_by_stage) if c.n]
        x = [i for i, _ in evaluated]
        ax.plot(x, [c.mean for _, c in evaluated], color=color[s.label], label=s.label,
                **style[s.label])
        if all(c.has_interval for _, c in evaluated):
            ax.fill_between(x, [c.low for _, c in evaluated], [c.high for _, c in evaluated],
                            color=color[s.label], alpha=0.2)
    ax.set_xticks(range(len(ticks)), ticks, fontsize=figures.FONT_PT)
    ax.set_ylim(-0.02, 1.02)
    ax.set_xlabel("stage (what it trained on)")
    ax.set_ylabel("foundation success (mean over foundation tasks)")
    ax.set_title(f"{benchmark}: retention of the foundation tasks (band: 95% CI over seeds)",
                 fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend(loc="center left", bbox_to_anchor=(1.01, 0.5), fontsize=8)
    fig.tight_layout()
    save(fig, path)


def plasticity_retention(path: Path, summaries: list[RowSummary], benchmark: str) -> None:
    """One point per row (error bars: 95% CI); SFT's learning-rate sweep as the frontier line, and
    each method's sweep over one numeric setting (merge's alpha) as a curve in its color."""
    fig = Figure(figsize=(10, 6))
    ax = fig.add_subplot()
    color = colors(summaries)
    labelled: list[tuple[float, float, str]] = []
    for s in summaries:
        x, y = s.cells["plasticity"], s.cells["retention"]
        if not (x.n and y.n):
            continue
        ax.errorbar(x.mean, y.mean, xerr=_err(x), yerr=_err(y), fmt="o", color=color[s.label],
                    capsize=3, label=s.label)
        labelled.append((x.mean, y.mean, s.label))
    frontier = sft_frontier(summaries)
    if frontier:
        ax.plot([p[0] for p in frontier], [p[1] for p in frontier], "--", color="black",
                linewidth=1.2, label="SFT learning-rate sweep: the frontier to beat", zorder=0)
    for (label, first), points in sweep_curves(summaries).items():
        ax.plot([p[0] for p in points], [p[1] for p in points], "-", color=color[first],
                linewidth=1, alpha=0.6, label=label, zorder=0)
    points = [(s.cells["plasticity"], s.cells["retention"]) for s in summaries]
    xs = [v for x, _ in points if x.n for v in (x.mean, x.low, x.high) if v is not None]
    ys = [v for _, y in points if y.n for v in (y.mean, y.low, y.high) if v is not None]
    ax.set_xlim(*_zoom(xs))
    ax.set_ylim(*_zoom(ys))
    ax.set_xlabel("plasticity (mean success on each stream task right after its stage)")
    ax.set_ylabel("retention (foundation success after the last stage)")
    ax.set_title(f"{benchmark}: plasticity vs retention (up and right is better)", fontsize=10)
    _legend_right(fig, ax)
    label_points(ax, labelled)
    save(fig, path)


def label_points(ax, points: list[tuple[float, float, str]]) -> None:
    """Name each point beside it: the first spot around it, moving outwards, where the name
    stays inside the axes, clear of other points and of the names already placed, and less than
    half as far from its own point as from any other (so it never reads as a neighbour's name);
    failing that, the free spot relatively nearest its own point. A thin line leads back to a
    point whose name had to move away. Call it after `tight_layout`: it measures final pixels."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    renderer = FigureCanvasAgg(ax.figure).get_renderer()
    frame = ax.get_window_extent(renderer)
    pixels = ax.transData.transform([(x, y) for x, y, _ in points]) if points else []
    placed = []
    for i, (x, y, name) in enumerate(points):
        others = [p for p in pixels if np.hypot(*(p - pixels[i])) > 8]  # markers overlapping
        # its own (8 px, a marker's width) are one place: either name may sit beside it
        best = None  # (own distance / nearest other's, offset) of the best free spot
        for dx, dy in _label_offsets():
            text = _annotate(ax, name, (x, y), (dx, dy))
            box = text.get_window_extent(renderer)
            text.remove()
            inside = frame.contains(box.x0, box.y0) and frame.contains(box.x1, box.y1)
            nearest = min([_distance(box, p) for p in others] or [np.inf])
            if not inside or nearest == 0 or any(box.overlaps(b) for b in placed):
                continue  # outside, over another point, or over a name
            ratio = _distance(box, pixels[i]) / nearest
            if best is None or ratio < best[0]:
                best = ratio, (dx, dy)
            if ratio < 0.5:
                break
        text = _annotate(ax, name, (x, y), best[1] if best else (_BESIDE, _BESIDE))
        placed.append(text.get_window_extent(renderer))


def _annotate(ax, name: str, point: tuple[float, float], offset: tuple[float, float]):
    """`name` at `offset` points from `point`, its nearest corner there; a leader line when far."""
    dx, dy = offset
    return ax.annotate(name, point, xytext=offset, textcoords="offset points", fontsize=8,
                       ha="left" if dx > 0 else "right", va="bottom" if dy > 0 else "top",
                       arrowprops={"arrowstyle": "-", "color": "grey", "linewidth": 0.5,
                                   "shrinkA": 0, "shrinkB": 2} if abs(dy) > _BESIDE else None)


def _distance(box, point) -> float:
    """Pixels from a point to the nearest edge of a box (0 inside it)."""
    dx = max(box.x0 - point[0], 0.0, point[0] - box.x1)
    dy = max(box.y0 - point[1], 0.0, point[1] - box.y1)
    return float(np.hypot(dx, dy))


_BESIDE = 5  # offset points from a point to its name's nearest corner


def _label_offsets():
    """Spots for a point's name, in offset points: the four corners beside it, then further up
    and down, one text line at a time."""
    for step in range(4):
        for dx in (_BESIDE, -_BESIDE):
            for sign in (1, -1):
                yield dx, sign * (_BESIDE + 11 * step)


def _zoom(values: list[float]) -> tuple[float, float]:
    """Axis limits around the points (0.1 margin) inside [0, 1]: clusters stay readable."""
    if not values:
        return -0.02, 1.02
    return max(-0.02, min(values) - 0.1), min(1.02, max(values) + 0.1)


def sft_frontier(summaries: list[RowSummary]) -> list[tuple[float, float]]:
    """(plasticity, retention) of SFT rows with distinct learning rates, by plasticity; [] when
    SFT ran at fewer than two learning rates."""
    points = {s.row.lr: (s.cells["plasticity"].mean, s.cells["retention"].mean)
              for s in summaries if s.row.method == "sft" and s.row.lr is not None
              and s.cells["plasticity"].n and s.cells["retention"].n}
    return sorted(points.values()) if len(points) >= 2 else []


def sweep_curves(summaries: list[RowSummary]) -> dict[tuple[str, str], list[tuple[float, float]]]:
    """A method's sweep over one numeric setting as a retention/plasticity curve (merge's alpha,
    say): {(legend label, first row's label): (plasticity, retention) points by the setting's
    value}, for sweeps with at least two points. Rows that differ in other settings as well
    (`merge[alpha=0.5 lr=0.001]`) make curves of their own."""
    groups: dict[tuple[str, str, str], list[tuple[float, RowSummary]]] = {}
    for s in summaries:
        key, sep, value = s.row.sweep_point.partition("=")
        if not sep or " " in s.row.sweep_point or not _is_number(value):
            continue
        if not (s.cells["plasticity"].n and s.cells["retention"].n):
            continue
        rest = s.label.replace(s.row.sweep_point, "", 1)  # the other settings of the row
        groups.setdefault((s.row.method, key, rest), []).append((float(value), s))
    curves = {}
    for (method, key, _), rows in groups.items():
        if len({v for v, _ in rows}) < 2:
            continue
        rows.sort(key=lambda r: r[0])
        label = f"{method}: {key} from {rows[0][0]:g} to {rows[-1][0]:g}"
        curves[(label, rows[0][1].label)] = [(s.cells["plasticity"].mean, s.cells["retention"].mean)
                                             for _, s in rows]
    return curves


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _err(cell) -> np.ndarray | None:
    if not cell.has_interval:
        return None
    return np.array([[cell.mean - cell.low], [cell.high - cell.mean]])


def update_distribution(path: Path, summaries: list[RowSummary], benchmark: str) -> None:
    """Grouped bars: fraction of all trainable scalars per bin of |delta theta| / RMS(theta_0)."""
    rows = [s for s in summaries if s.updates is not None]
    rows = [s for s in rows if s.updates.bins == rows[0].updates.bins]  # runs of older versions
    fig = Figure(figsize=(8, 4.5))
    ax = fig.add_subplot()
    color = colors(summaries)
    if rows:
        bins = rows[0].updates.bins
        width = 0.8 / len(rows)
        for i, s in enumerate(rows):
            x = np.arange(len(bins)) + (i - (len(rows) - 1) / 2) * width
            bars = ax.bar(x, s.updates.fractions, width, color=color[s.label], label=s.label)
            if len(rows) <= 4:  # beyond that the labels run into each other
                ax.bar_label(bars, [f"{v:.0%}" for v in s.updates.fractions], fontsize=7)
        ax.set_xticks(range(len(bins)), [b.replace(" - ", "-\n") for b in bins], fontsize=8)
        ax.legend(fontsize=8, loc="center left", bbox_to_anchor=(1.01, 0.5))
    ax.set_ylim(0, 1.08)
    ax.set_xlabel("|delta theta| / RMS(theta_0) of its tensor, theta_k vs theta_0")
    ax.set_ylabel("fraction of trainable scalars (mean over seeds)")
    ax.set_title(f"{benchmark}: how much of the network moved (left bin: unchanged)", fontsize=10)
    ax.grid(axis="y", alpha=0.3)
    fig.tight_layout()
    save(fig, path)


def layer_relative_l2(path: Path, summaries: list[RowSummary], benchmark: str) -> None:
    """Horizontal grouped bars: per layer, ||theta_k - theta_0|| / ||theta_0||, one bar per row.

    The axis turns logarithmic when layers differ by more than 20x, so small layers stay visible.
    """
    rows = [s for s in summaries if s.layer_relative_l2]
    layers = list(dict.fromkeys(name for s in rows for name in s.layer_relative_l2))
    height = 0.8 / max(len(rows), 1)
    fig = Figure(figsize=(9, 1.5 + len(layers) * max(0.25, 0.1 * len(rows))))
    ax = fig.add_subplot()
    color = colors(summaries)
    for i, s in enumerate(rows):
        y = np.arange(len(layers)) + (i - (len(rows) - 1) / 2) * height
        ax.barh(y, [s.layer_relative_l2.get(name, 0.0) for name in layers], height,
                color=color[s.label], label=s.label)
    values = [v for s in rows for v in s.layer_relative_l2.values() if v > 0]
    if values and max(values) > 20 * min(values):
        ax.set_xscale("log")
    ax.set_yticks(range(len(layers)), layers, fontsize=8)
    ax.set_ylim(len(layers) - 0.5, -0.5)  # first layer on top
    ax.set_xlabel("||theta_k - theta_0|| / ||theta_0|| of the layer (mean over seeds)")
    ax.set_title(f"{benchmark}: update size per layer (relative L2)", fontsize=10)
    ax.grid(axis="x", alpha=0.3)
    if rows:
        ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    save(fig, path)


def spatial_retention(path: Path, summaries: list[RowSummary], benchmark: str) -> None:
    """Spatial retention against retention, one point per row (error bars: 95% CI), each with a
    faint arrow from its stage-0 values: below the diagonal, what generalised beyond the demos'
    range is kept worse than what lies inside it (the paper's "spatial overfitting")."""
    fig = Figure(figsize=(10, 6))
    ax = fig.add_subplot()
    color = colors(summaries)
    xs, ys = [], []
    labelled: list[tuple[float, float, str]] = []
    for s in summaries:
        x, y = s.cells["retention"], s.cells["spatial_retention"]
        start = s.foundation_by_stage[0], s.cells["spatial_foundation_success_stage0"]
        if not (x.n and y.n):
            continue
        ax.errorbar(x.mean, y.mean, xerr=_err(x), yerr=_err(y), fmt="o", color=color[s.label],
                    capsize=3, label=s.label)
        labelled.append((x.mean, y.mean, s.label))
        if start[0].n and start[1].n:
            ax.annotate("", (x.mean, y.mean), xytext=(start[0].mean, start[1].mean),
                        arrowprops={"arrowstyle": "->", "color": color[s.label], "alpha": 0.4})
            ax.plot(start[0].mean, start[1].mean, "x", color="black",
                    label="stage 0 (the foundation)" if not xs else None)
            xs.append(start[0].mean)
            ys.append(start[1].mean)
        xs += [v for v in (x.mean, x.low, x.high) if v is not None]
        ys += [v for v in (y.mean, y.low, y.high) if v is not None]
    lo, hi = _zoom(xs + ys)
    ax.plot([lo, hi], [lo, hi], ":", color="grey", linewidth=1, zorder=0,
            label="spatial = in-range success")
    ax.set_xlim(lo, hi)
    ax.set_ylim(lo, hi)
    ax.set_xlabel("retention (foundation success after the last stage, demo-range states)")
    ax.set_ylabel("spatial retention (the same, from widened initial states)")
    ax.set_title(f"{benchmark}: spatial probe (arrows start at stage 0; below the diagonal: "
                 "worse beyond the demos' range)", fontsize=10)
    _legend_right(fig, ax)
    label_points(ax, labelled)
    save(fig, path)


def _legend_right(fig, ax) -> None:
    """The grid, and the legend outside the axes on the right, as every scatter and curve here."""
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="center left", bbox_to_anchor=(1.01, 0.5))
    fig.tight_layout()


def _segments(series: SeriesSummary):
    """(step, mean, low, high) per stream stage: a line per stage, none drawn across stages
    (ConSFT's schedule restarts; a stage stopped early leaves a gap before the next)."""
    for stage in np.unique(series.stage):
        at = series.stage == stage
        yield series.step[at], series.mean[at], series.low[at], series.high[at]


def _stage_starts(ax, rows: list[RowSummary]) -> None:
    """Dotted lines where stages 2..k start on the planned step axis (stage i at
    (i - 1) * steps_per_task), from the first row's settings."""
    run = rows[0].row.runs[0]
    per_stage = int(run.params.get("config.steps_per_task", 0))
    for i in range(1, len(run.stages)):
        ax.axvline(i * per_stage, color="grey", linestyle=":", linewidth=1, zorder=0)


def sparsity_progress(path: Path, summaries: list[RowSummary], benchmark: str) -> None:
    """The ConSFT paper's Eq. 8 sparsity against the training step within the stream (its
    figure 2): one line per row, the mean over seeds, shaded from the lowest seed to the
    highest. Draw it only when some row has `sparsity/eq8` (`has_series`)."""
    rows = [s for s in summaries if "sparsity/eq8" in s.series]
    fig = Figure(figsize=(10, 5))
    ax = fig.add_subplot()
    color, style = colors(summaries), line_styles(summaries)
    for s in rows:
        series = s.series["sparsity/eq8"]
        marked = len(series.step) <= 80
        for j, (x, mean, low, high) in enumerate(_segments(series)):
            ax.plot(x, mean, linestyle=style[s.label]["linestyle"],
                    marker=style[s.label]["marker"] if marked else None, markersize=4,
                    markerfacecolor="none", color=color[s.label],
                    label=f"{s.label} ({series.n} seed{'s' * (series.n > 1)})" if j == 0 else None)
            if series.n > 1:
                ax.fill_between(x, low, high, color=color[s.label], alpha=0.15, linewidth=0)
    if rows:
        _stage_starts(ax, rows)
    ax.set_xlabel("training step within the stream (stage i starts at (i - 1) x steps_per_task; "
                  "dotted: stage starts)")
    ax.set_ylabel("Eq. 8 sparsity: share of scalars\nwith |theta - theta_0| / |theta_0| < 1e-3")
    ax.set_title(f"{benchmark}: how much of the network stays at the foundation's weights "
                 "(mean over seeds; band: min to max)", fontsize=10)
    _legend_right(fig, ax)
    save(fig, path)


def floor_edge(params: dict[str, str]) -> float | None:
    """The factor f such that a sample whose loss is below f * tau(t) gets a weight above
    ConSFT's floor w_min (w = max(w_min, exp(-kappa L / tau)) for `paper`, exp(-L / (kappa
    tau)) for `kappa_temp`); None for the other variants or settings that have no floor."""
    try:
        variant = params.get("method.variant", "paper")
        kappa, w_min = float(params["method.kappa"]), float(params["method.w_min"])
    except (KeyError, ValueError):
        return None
    if not 0 < w_min < 1 or kappa <= 0 or variant not in ("paper", "kappa_temp"):
        return None
    escape = np.log(1 / w_min)  # exp(-x) > w_min  <=>  x < ln(1 / w_min)
    return float(escape / kappa if variant == "paper" else escape * kappa)


def consft_weights(path: Path, summaries: list[RowSummary], benchmark: str) -> None:
    """ConSFT's weighting over the steps, per consft row (mean over seeds): above, on a log
    scale, the per-sample losses (median; band 10th to 90th percentile) against tau(t) and the
    loss below which a sample leaves the floor; below, the mean weight and the share of samples
    at the floor. Draw it only when some row logged `consft/*` (`has_series`)."""
    from matplotlib.lines import Line2D

    rows = [s for s in summaries if any(k.startswith("consft/") for k in s.series)]
    fig = Figure(figsize=(11, 8))
    top, bottom = fig.subplots(2, 1, sharex=True, height_ratios=[3, 2])
    color = colors(summaries)
    for s in rows:
        c, series = color[s.label], s.series
        edge = floor_edge(s.row.runs[0].params)
        if "consft/loss_q50" in series:
            for x, mean, _, _ in _segments(series["consft/loss_q50"]):
                top.plot(x, mean, "-", color=c, linewidth=1)
        if "consft/loss_q10" in series and "consft/loss_q90" in series:
            for (x, q10, _, _), (_, q90, _, _) in zip(_segments(series["consft/loss_q10"]),
                                                       _segments(series["consft/loss_q90"])):
                top.fill_between(x, q10, q90, color=c, alpha=0.15, linewidth=0)
        if "consft/tau" in series:
            for x, tau, _, _ in _segments(series["consft/tau"]):
                top.plot(x, tau, "--", color=c, linewidth=1.2)
                if edge is not None:
                    top.plot(x, edge * tau, ":", color=c, linewidth=1.5)
        for key, style in (("consft/weight_mean", "-"), ("consft/frac_at_floor", "--")):
            if key in series:
                for x, mean, _, _ in _segments(series[key]):
                    bottom.plot(x, mean, style, color=c, linewidth=1)
    for ax in (top, bottom):
        if rows:
            _stage_starts(ax, rows)
        ax.grid(alpha=0.3)
    top.set_yscale("log")
    top.set_ylabel("per-sample flow-matching loss, tau(t)")
    bottom.set_ylabel("mean weight, share at the floor")
    bottom.set_ylim(-0.02, 1.02)
    bottom.set_xlabel("training step within the stream (stage i starts at (i - 1) x "
                      "steps_per_task; dotted: stage starts)")
    top.set_title(f"{benchmark}: ConSFT's temperature against the losses (mean over seeds)",
                  fontsize=10)
    grey = "dimgrey"
    top.legend(handles=[
        *(Line2D([], [], color=color[s.label], linewidth=3, label=s.label) for s in rows),
        Line2D([], [], color=grey, label="loss median (band: 10th to 90th percentile)"),
        Line2D([], [], color=grey, linestyle="--", label="tau(t)"),
        Line2D([], [], color=grey, linestyle=":",
               label="floor edge: a loss below it\ngets a weight above w_min")],
        fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    bottom.legend(handles=[Line2D([], [], color=grey, label="mean weight"),
                           Line2D([], [], color=grey, linestyle="--",
                                  label="share of samples at the floor")],
                  fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    fig.tight_layout()
    save(fig, path)


def has_series(summaries: list[RowSummary], prefix: str) -> bool:
    """Whether some row logged a per-step metric starting with `prefix` (a figure's data)."""
    return any(k.startswith(prefix) for s in summaries for k in s.series)
