"""Build `results/<benchmark>/report/` from the finished runs in MLflow, and log it as a run.

Why rebuilding gives the same bytes: rows and runs are sorted, the bootstrap RNG is fixed, no file
holds a timestamp or a path of this machine, and PNGs carry no software version. Files of an
earlier build that this build does not write (a method since removed) are deleted, so the
folder always describes one build.
"""

from __future__ import annotations

import math
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path

from harness.common.atomic import write_text
from harness.common.errors import RetainError
from harness.measure.bootstrap import RESAMPLES
from harness.report import plots
from harness.report.aggregate import (
    OPTIONAL_NOTES,
    Metric,
    RowSummary,
    run_value,
    shown_metrics,
    summarize,
)
from harness.report.groups import ABSTRACT_ONLY, build_rows
from harness.report.page import RowVideos, write_page
from harness.report.paper import REFERENCE, PaperTable, paper_columns, paper_table
from harness.report.runs import download_videos, experiment_id, load_runs, open_client
from harness.report.table import (
    csv_table,
    heading,
    latex_table,
    markdown_table,
    paired_csv,
    paired_markdown,
    paper_csv,
    paper_markdown,
)
from harness.track.tracking import tracking_uri

OWNED = (".md", ".csv", ".tex", ".png", ".html")  # the kinds of file a build writes into the report folder

@dataclass(frozen=True)
class ReportSettings:
    experiment: str = "mw-quick"  # the MLflow experiment = the benchmark name
    results_dir: str = "results"
    log_run: bool = True  # also log the files as artifacts of a run tagged report=true

    @property
    def out_dir(self) -> Path:
        return Path(self.results_dir) / self.experiment / "report"


def build_report(settings: ReportSettings) -> list[Path]:
    """Read, summarize, write; returns the files written, sorted."""
    uri = tracking_uri(settings.results_dir)
    client = open_client(uri)
    runs = load_runs(client, experiment_id(client, settings.experiment, uri))
    if not runs:
        raise RetainError(f"experiment {settings.experiment!r} at {uri} has no finished "
                          "(method, seed) runs yet; run `make bench` first")
    rows, superseded = build_rows(runs)
    columns = paper_columns([run for row in rows for run in row.runs])
    summaries = [summarize(row, [m.key for m in columns]) for row in rows]
    paper = paper_table(rows, columns) if columns else None
    files = write_report(settings.out_dir, summaries, settings.experiment, superseded, paper)
    markdown = [settings.out_dir / n for n in ("summary.md", "paper_table.md") if
                settings.out_dir / n in files]  # the summary first
    first = rows[0].runs[0]
    with tempfile.TemporaryDirectory() as tmp:
        page = write_page(settings.out_dir, settings.experiment, markdown, first.foundation_tasks,
                          first.stream_tasks, row_videos(client, rows, Path(tmp)))
    files = sorted(files + [page])
    if settings.log_run:
        log_report_run(settings, files, n_runs=sum(len(r.runs) for r in rows))
    return files


def row_videos(client, rows, folder: Path) -> list[RowVideos]:
    """Each row's videos from MLflow: those of its lowest seed that logged any."""
    found = []
    for row in rows:
        for run in row.runs:  # sorted by seed
            directory = download_videos(client, run.run_id, folder / slug(row.label) / str(run.seed))
            if directory is not None:
                found.append(RowVideos.read(row.label, run.seed, directory))
                break
    return found


def write_report(out: Path, summaries: list[RowSummary], benchmark: str,
                 superseded: int = 0, paper: PaperTable | None = None) -> list[Path]:
    """Every file of the report; the paper table and the per-step figures only where runs
    logged their data."""
    out.mkdir(parents=True, exist_ok=True)
    figures = {
        "foundation_success.png": plots.foundation_curves,
        "plasticity_vs_retention.png": plots.plasticity_retention,
        "update_sparsity.png": plots.update_distribution,
        "relative_l2_per_layer.png": plots.layer_relative_l2,
    }
    if any(s.cells["spatial_retention"].n for s in summaries):
        figures["spatial_vs_retention.png"] = plots.spatial_retention
    if plots.has_series(summaries, "sparsity/"):
        figures["sparsity_progress.png"] = plots.sparsity_progress
    if plots.has_series(summaries, "consft/"):
        figures["consft_weights.png"] = plots.consft_weights
    written = []
    for name, draw in figures.items():
        draw(out / name, summaries, benchmark)
        written.append(out / name)
    heatmaps = {s.label: f"success_matrix_{slug(s.label)}.png" for s in summaries}
    for s in summaries:
        plots.success_heatmap(out / heatmaps[s.label], s, benchmark)
        written.append(out / heatmaps[s.label])
    texts = {
        "summary.md": summary_markdown(summaries, benchmark, superseded, list(figures), heatmaps,
                                       paper is not None),
        "summary.csv": csv_table(summaries),
        "summary.tex": latex_table(summaries),
    }
    if paper is not None:
        texts["paper_table.md"] = paper_table_markdown(paper, summaries, benchmark)
        texts["paper_table.csv"] = paper_csv(paper, summaries)
        if paper.paired:
            texts["paper_paired.csv"] = paired_csv(paper)
    for name, text in texts.items():
        write_text(out / name, text)
        written.append(out / name)
    for stale in out.iterdir():
        if stale.is_file() and stale.suffix in OWNED and stale not in written:
            stale.unlink()
    return sorted(written)


def slug(label: str) -> str:
    """A file-name-safe form of a row label: "consft[kappa=0.1]" -> "consft_kappa_0.1"."""
    return re.sub(r"[^A-Za-z0-9.-]+", "_", label).strip("_")


def _header(summaries: list[RowSummary], benchmark: str) -> list[str]:
    """Which runs, seeds and commits; how to read a cell."""
    runs = [r for s in summaries for r in s.row.runs]
    seeds = sorted({r.seed for r in runs})
    commits = sorted({c for r in runs for c in r.commits or ("unknown",)})
    return [
        (f"{len(runs)} finished runs from the MLflow experiment `{benchmark}`; seeds "
         f"{', '.join(map(str, seeds))}; git commit{'s' if len(commits) > 1 else ''} "
         f"{', '.join(f'`{c}`' for c in commits)}."),
        "",
        (f"Each cell: mean over seeds, then its 95% percentile-bootstrap interval ({RESAMPLES:,} "
         "resamples, fixed RNG seed; no interval with one seed). **Bold**: the best row of the "
         "column (none where all rows print the same). ↑: higher is better; ↓: lower is better. "
         "`method[setting]` rows are sweep points or runs whose settings differ from the "
         "method's other runs."),
        "",
    ]


def _row_notes(summaries: list[RowSummary], superseded: int,
               metrics: list[Metric] | None = None) -> list[str]:
    """Rows to read with care: missing seeds, cells from fewer seeds than the row has (a metric
    that runs from before it was added never logged), superseded runs, an earlier reading of
    ConSFT."""
    notes = [f"- **{s.label}** lacks seed{'s' if len(s.row.missing_seeds) > 1 else ''} "
             f"{', '.join(map(str, s.row.missing_seeds))} that other rows have: its cells average "
             f"its {len(s.row.runs)} seeds only, so compare it with care."
             for s in summaries if s.row.missing_seeds]
    for m in shown_metrics(summaries) if metrics is None else metrics:
        for s in summaries:
            if 0 < s.cells[m.key].n < len(s.row.runs):
                unlogged = [r.seed for r in s.row.runs if math.isnan(run_value(r, m.key))]
                notes.append(f"- **{s.label}**: its {m.title} averages {s.cells[m.key].n} of its "
                             f"{len(s.row.runs)} seeds; seed{'s' * (len(unlogged) > 1)} "
                             f"{', '.join(map(str, unlogged))} did not log it (run before it "
                             "existed).")
    if superseded:
        notes.append(f"- {superseded} older run(s) of a (method, seed) that was run again were "
                     "left out; the newest run counts.")
    if any(s.row.abstract_only for s in summaries):
        notes.append(f"- Rows ending in \"{ABSTRACT_ONLY.strip()}\" are ConSFT as Retain read it "
                     "from the paper's abstract alone (the `clip` weighting relative to a "
                     "reference loss l_ref), run before Retain implemented the paper's objective "
                     "(Eq. 5, 11-12; docs/methods.md). They are not the paper's method.")
    return ["Notes:", "", *notes, ""] if notes else []


def summary_markdown(summaries: list[RowSummary], benchmark: str, superseded: int,
                     figures: list[str], heatmaps: dict[str, str],
                     paper_table: bool = False) -> str:
    lines = [f"# {benchmark}: comparison of fine-tuning methods", "",
             *_header(summaries, benchmark), markdown_table(summaries)]
    lines += _row_notes(summaries, superseded)
    if paper_table:
        lines += ["The ConSFT paper's table-2 columns (base, target, each held-out suite, "
                  "held-out average, steps used, check success): [paper_table.md](paper_table.md).",
                  ""]
    lines += ["## Columns", ""]
    lines.append("- needs: what a method uses beyond the current task's data, so that like is "
                 "compared with like: past data (samples of earlier tasks: a replay buffer, a "
                 "memory), reference copy (a frozen copy of the network run beside the policy "
                 "in training; stored weights, as L2, EWC, MAS and merge keep, are not one), task "
                 "identity at evaluation (the policy must be told which task it acts on); none: "
                 "the current task's data alone.")
    lines += [f"- {heading(m)}: {m.note}." for m in shown_metrics(summaries)]
    shown = {m.key for m in shown_metrics(summaries)}
    lines += [f"- {note}" for key, note in OPTIONAL_NOTES.items() if key not in shown]
    lines += ["", "## Figures", ""]
    lines += [f"![{name.removesuffix('.png')}]({name})" for name in figures]
    lines += ["", "Success matrix per method (mean over seeds):", ""]
    lines += [f"- {label}: ![{label}]({name})" for label, name in heatmaps.items()]
    lines += ["", "How to read each table and plot: `docs/reports.md`.", ""]
    return "\n".join(lines)


def paper_table_markdown(paper: PaperTable, summaries: list[RowSummary], benchmark: str) -> str:
    """The ConSFT paper's table 2 shape (harness/report/paper.py), with its legend."""
    lines = [f"# {benchmark}: the ConSFT paper's table-2 columns", "",
             *_header(summaries, benchmark), paper_markdown(paper, summaries)]
    lines += _row_notes(summaries, 0, paper.columns)
    lines += ["## Columns", "",
              f"- {BASE_ROW_NOTE}"]
    if paper.differing_seeds:
        lines.append(f"- The runs of seed{'s' * (len(paper.differing_seeds) > 1)} "
                     f"{', '.join(map(str, paper.differing_seeds))} logged different stage-0 "
                     "values (different foundations); the base row takes their mean.")
    lines += [f"- {heading(m)}: {m.note}." for m in paper.columns]
    if paper.paired:
        lines += ["", f"## Against {REFERENCE}, seed by seed", "", PAIRED_NOTE, "",
                  paired_markdown(paper)]
    lines += ["", "How to read it: `docs/reports.md`.", ""]
    return "\n".join(lines)


PAIRED_NOTE = (f"Each row's value minus {REFERENCE}'s at the same seed (the same foundation, the "
               "same evaluation episodes), then the mean difference over the seeds both rows "
               "have and its 95% bootstrap interval (no interval with one seed). The "
               "foundation's own seed-to-seed spread cancels in the difference; an interval that "
               f"contains 0 means these seeds do not tell the row from {REFERENCE}. Also in "
               "paper_paired.csv.")


BASE_ROW_NOTE = ("base (stage 0): the foundation before any stream stage, the same checkpoint "
                 "for every method of a seed; its values are averaged over the seeds.")


def log_report_run(settings: ReportSettings, files: list[Path], n_runs: int) -> str:
    """A run tagged report=true in the same experiment, holding the report files as artifacts."""
    from harness.track.tracking import Tracker

    tracker = Tracker(settings.results_dir, experiment=settings.experiment)
    run_id = tracker.start_run("report", tags={"report": "true", "benchmark": settings.experiment})
    try:
        tracker.log_params(run_id, {"report.runs": n_runs})
        for path in files:
            tracker.log_artifact(run_id, path, "report")
    except Exception:
        tracker.end_run(run_id, "FAILED")
        raise
    tracker.end_run(run_id)
    return run_id
