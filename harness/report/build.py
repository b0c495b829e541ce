"""Build `results/<benchmark>/report/` from the finished runs in MLflow, and log it as a run.

Why rebuilding gives the same bytes: rows and runs are sorted, the bootstrap RNG is fixed, no file
holds a timestamp or a path of this machine, and PNGs carry no software version. Files of an
earlier build that this build does not write (a method since removed) are deleted, so the
folder always describes one build.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

from harness.atomic import write_text
from harness.bootstrap import RESAMPLES
from harness.errors import RetainError
from harness.report import plots
from harness.report.aggregate import OPTIONAL_NOTES, RowSummary, shown_metrics, summarize
from harness.report.groups import build_rows
from harness.report.runs import experiment_id, load_runs, open_client
from harness.report.table import arrow, csv_table, latex_table, markdown_table
from harness.tracking import tracking_uri

OWNED = (".md", ".csv", ".tex", ".png")  # the kinds of file a build writes into the report folder

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
    summaries = [summarize(row) for row in rows]
    files = write_report(settings.out_dir, summaries, settings.experiment, superseded)
    if settings.log_run:
        log_report_run(settings, files, n_runs=sum(len(r.runs) for r in rows))
    return files


def write_report(out: Path, summaries: list[RowSummary], benchmark: str,
                 superseded: int = 0) -> list[Path]:
    out.mkdir(parents=True, exist_ok=True)
    figures = {
        "foundation_success.png": plots.foundation_curves,
        "plasticity_vs_retention.png": plots.plasticity_retention,
        "update_sparsity.png": plots.update_distribution,
        "relative_l2_per_layer.png": plots.layer_relative_l2,
    }
    if any(s.cells["spatial_retention"].n for s in summaries):
        figures["spatial_vs_retention.png"] = plots.spatial_retention
    written = []
    for name, draw in figures.items():
        draw(out / name, summaries, benchmark)
        written.append(out / name)
    heatmaps = {s.label: f"success_matrix_{slug(s.label)}.png" for s in summaries}
    for s in summaries:
        plots.success_heatmap(out / heatmaps[s.label], s, benchmark)
        written.append(out / heatmaps[s.label])
    texts = {
        "summary.md": summary_markdown(summaries, benchmark, superseded, list(figures), heatmaps),
        "summary.csv": csv_table(summaries),
        "summary.tex": latex_table(summaries),
    }
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


def summary_markdown(summaries: list[RowSummary], benchmark: str, superseded: int,
                     figures: list[str], heatmaps: dict[str, str]) -> str:
    runs = [r for s in summaries for r in s.row.runs]
    seeds = sorted({r.seed for r in runs})
    commits = sorted({c for r in runs for c in r.commits or ("unknown",)})
    lines = [
        f"# {benchmark}: comparison of fine-tuning methods",
        "",
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
        markdown_table(summaries),
    ]
    notes = [f"- **{s.label}** lacks seed{'s' if len(s.row.missing_seeds) > 1 else ''} "
             f"{', '.join(map(str, s.row.missing_seeds))} that other rows have: its cells average "
             f"its {len(s.row.runs)} seeds only, so compare it with care."
             for s in summaries if s.row.missing_seeds]
    if superseded:
        notes.append(f"- {superseded} older run(s) of a (method, seed) that was run again were "
                     "left out; the newest run counts.")
    if notes:
        lines += ["Notes:", "", *notes, ""]
    lines += ["## Columns", ""]
    lines.append("- needs: what a method uses beyond the current task's data, so that like is "
                 "compared with like: past data (samples of earlier tasks: a replay buffer, a "
                 "memory), reference copy (a frozen copy of the network run beside the policy "
                 "in training; stored weights, as L2, EWC, MAS and merge keep, are not one), task "
                 "identity at evaluation (the policy must be told which task it acts on); none: "
                 "the current task's data alone.")
    lines += [f"- {m.title} {arrow(m)}: {m.note}." for m in shown_metrics(summaries)]
    shown = {m.key for m in shown_metrics(summaries)}
    lines += [f"- {note}" for key, note in OPTIONAL_NOTES.items() if key not in shown]
    lines += ["", "## Figures", ""]
    lines += [f"![{name.removesuffix('.png')}]({name})" for name in figures]
    lines += ["", "Success matrix per method (mean over seeds):", ""]
    lines += [f"- {label}: ![{label}]({name})" for label, name in heatmaps.items()]
    lines += ["", "How to read each table and plot: `docs/reports.md`.", ""]
    return "\n".join(lines)


def log_report_run(settings: ReportSettings, files: list[Path], n_runs: int) -> str:
    """A run tagged report=true in the same experiment, holding the report files as artifacts."""
    from harness.tracking import Tracker

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
