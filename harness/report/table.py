"""The comparison table (rows: method settings, columns: metrics) as Markdown, CSV and LaTeX,
and the ConSFT paper's table 2 columns (harness/report/paper.py) as Markdown and CSV.

Each cell is the mean over seeds with its 95% bootstrap interval; the best row of each column is
marked (bold), by the column's direction. Means are compared as printed (3 decimals), so rows
that print the same value are marked together. Columns that are facts rather than scores (steps
used) have no direction and no best.
"""

from __future__ import annotations

import csv
import io
import math

from harness.measure.bootstrap import Interval
from harness.report.aggregate import Metric, RowSummary, shown_metrics
from harness.report.paper import BASE_LABEL, PAIRED, REFERENCE, PaperTable

DIGITS = 3


def best_labels(summaries: list[RowSummary], metric: Metric) -> set[str]:
    """Labels of the rows with the best printed mean in this column; none when every row prints
    the same value (nothing to single out) or no row has data."""
    values = {s.label: round(s.cells[metric.key].mean, metric.digits) for s in summaries
              if s.cells[metric.key].n}
    if not metric.ranked or len(set(values.values())) < 2:
        return set()
    best = max(values.values()) if metric.higher_is_better else min(values.values())
    return {label for label, v in values.items() if v == best}


def arrow(metric: Metric) -> str:
    """↑ or ↓ by the column's direction; "" for a column without one."""
    if not metric.ranked:
        return ""
    return "↑" if metric.higher_is_better else "↓"


def heading(metric: Metric) -> str:
    return f"{metric.title} {arrow(metric)}".strip()


def cell_text(cell: Interval, digits: int = DIGITS) -> tuple[str, str]:
    """(mean, interval) as printed; the interval is "" with one seed, the mean "n/a" with none."""
    if cell.n == 0 or math.isnan(cell.mean):
        return "n/a", ""
    if not cell.has_interval:
        return f"{cell.mean:.{digits}f}", ""
    return f"{cell.mean:.{digits}f}", f"[{cell.low:.{digits}f}, {cell.high:.{digits}f}]"


def _cells(summary: RowSummary, metrics, best: dict, bold) -> list[tuple[str, str]]:
    """(mean, interval) text per metric, the mean passed through `bold` where it is the best."""
    out = []
    for m in metrics:
        mean, interval = cell_text(summary.cells[m.key], m.digits)
        out.append((bold(mean) if summary.label in best[m.key] else mean, interval))
    return out


def markdown_table(summaries: list[RowSummary], metrics: list[Metric] | None = None,
                   first: list[str] | None = None) -> str:
    """The rows under the metrics (the main table's by default); `first`, an already formatted
    row (the paper table's base) above them."""
    metrics = shown_metrics(summaries) if metrics is None else metrics
    best = {m.key: best_labels(summaries, m) for m in metrics}
    lines = ["| method | seeds | needs | " + " | ".join(heading(m) for m in metrics) + " |",
             "|---|---|---|" + "---|" * len(metrics)]
    if first is not None:
        lines.append("| " + " | ".join(first) + " |")
    for s in summaries:
        cells = [f"{mean} {interval}".strip()
                 for mean, interval in _cells(s, metrics, best, lambda v: f"**{v}**")]
        lines.append(f"| {s.label} | {s.row.seeds_text()} | {s.row.needs} | "
                     + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def paper_markdown(table: PaperTable, summaries: list[RowSummary]) -> str:
    """The paper's table 2 shape: the base row (stage 0; no steps, no check), then each row."""
    base = [BASE_LABEL, str(len(table.base_seeds)), "-"]
    for m in table.columns:
        cell = table.base.get(m.key)
        base.append(" ".join(cell_text(cell, m.digits)).strip() if cell is not None else "-")
    return markdown_table(summaries, table.columns, first=base)


def paper_csv(table: PaperTable, summaries: list[RowSummary]) -> str:
    """As csv_table, with the base row first (label "base", no method)."""
    base = ["base", "", "", "", len(table.base_seeds), ";".join(map(str, table.base_seeds)),
            "", ""]
    for m in table.columns:
        cell = table.base.get(m.key)
        base += ([_full(cell.mean if cell.n else None), _full(cell.low), _full(cell.high),
                  cell.n, 0] if cell is not None else ["", "", "", 0, 0])
    return csv_table(summaries, table.columns, first=base)


PAIRED_TITLES = {"target": "target", "heldout_avg": "held-out avg"}


def paired_markdown(table: PaperTable) -> str:
    """Each row minus sft, seed by seed: the mean difference, its interval, and the per-seed
    differences, so a reader sees whether the seeds agree in sign."""
    head = " | ".join(f"Δ {PAIRED_TITLES[k]}" for k in PAIRED)
    lines = [f"| method | seeds | {head} | per seed ({PAIRED_TITLES[PAIRED[-1]]}) |",
             "|---|---|" + "---|" * len(PAIRED) + "---|"]
    for row in table.paired:
        cells = [_signed(row.cells[k]) for k in PAIRED]
        per_seed = ", ".join(f"{s}: {v:+.3f}" for s, v in zip(row.seeds, row.per_seed[PAIRED[-1]]))
        lines.append(f"| {row.label} | {len(row.seeds)} | " + " | ".join(cells)
                     + f" | {per_seed} |")
    return "\n".join(lines) + "\n"


def _signed(cell: Interval) -> str:
    if not cell.has_interval:
        return f"{cell.mean:+.{DIGITS}f}"
    return f"{cell.mean:+.{DIGITS}f} [{cell.low:+.{DIGITS}f}, {cell.high:+.{DIGITS}f}]"


def paired_csv(table: PaperTable) -> str:
    """Machine-readable: per row and column, the mean difference from sft, its interval, and
    the difference at each seed."""
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    header = ["label", "reference", "n_seeds", "seeds"]
    for k in PAIRED:
        header += [f"{k}_diff_mean", f"{k}_diff_ci_low", f"{k}_diff_ci_high", f"{k}_diff_per_seed"]
    writer.writerow(header)
    for row in table.paired:
        line = [row.label, REFERENCE, len(row.seeds), ";".join(map(str, row.seeds))]
        for k in PAIRED:
            c = row.cells[k]
            line += [_full(c.mean), _full(c.low), _full(c.high),
                     ";".join(_full(v) for v in row.per_seed[k])]
        writer.writerow(line)
    return buf.getvalue()


def csv_table(summaries: list[RowSummary], metrics: list[Metric] | None = None,
              first: list | None = None) -> str:
    """Machine-readable: full-precision mean, CI bounds and sample count per metric."""
    metrics = shown_metrics(summaries) if metrics is None else metrics
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    header = ["label", "method", "sweep_point", "lr", "n_seeds", "seeds", "missing_seeds", "needs"]
    for m in metrics:
        header += [f"{m.key}_mean", f"{m.key}_ci_low", f"{m.key}_ci_high", f"{m.key}_n",
                   f"{m.key}_best"]
    writer.writerow(header)
    if first is not None:
        writer.writerow(first)
    best = {m.key: best_labels(summaries, m) for m in metrics}
    for s in summaries:
        row = s.row
        line = [row.label, row.method, row.sweep_point, _full(row.lr), len(row.runs),
                ";".join(map(str, row.seeds)), ";".join(map(str, row.missing_seeds)), row.needs]
        for m in metrics:
            c = s.cells[m.key]
            line += [_full(c.mean if c.n else None), _full(c.low), _full(c.high), c.n,
                     int(s.label in best[m.key])]
        writer.writerow(line)
    return buf.getvalue()


def _full(v: float | None) -> str:
    return "" if v is None or math.isnan(v) else format(float(v), ".10g")


def latex_table(summaries: list[RowSummary]) -> str:
    """A booktabs tabular (needs \\usepackage{booktabs}); the interval in small type."""
    metrics = shown_metrics(summaries)
    best = {m.key: best_labels(summaries, m) for m in metrics}
    arrows = {"↑": r" $\uparrow$", "↓": r" $\downarrow$", "": ""}
    lines = [r"\begin{tabular}{lll" + "r" * len(metrics) + "}", r"\toprule",
             "method & seeds & needs & " + " & ".join(f"{_tex(m.title)}{arrows[arrow(m)]}" for m in metrics)
             + r" \\", r"\midrule"]
    for s in summaries:
        cells = [mean + (rf" {{\scriptsize {interval}}}" if interval else "")
                 for mean, interval in _cells(s, metrics, best, lambda v: rf"\textbf{{{v}}}")]
        lines.append(f"{_tex(s.label)} & {_tex(s.row.seeds_text())} & {_tex(s.row.needs)} & "
                     + " & ".join(cells) + r" \\")
    lines += [r"\bottomrule", r"\end{tabular}"]
    return "\n".join(lines) + "\n"


_TEX = {"\\": r"\textbackslash{}", "_": r"\_", "%": r"\%", "&": r"\&", "#": r"\#", "$": r"\$",
        "{": r"\{", "}": r"\}", "~": r"\textasciitilde{}", "^": r"\textasciicircum{}"}


def _tex(text: str) -> str:
    return "".join(_TEX.get(char, char) for char in text)
