"""Comparison reports a paper could use: `python -m harness.report EXPERIMENT=mw-quick`.

Reads the finished (method, seed) runs of one MLflow experiment and writes, under
`results/<benchmark>/report/`, the summary table (Markdown, CSV, LaTeX) and the figures.
Modules, in data-flow order: runs (MLflow -> records), groups (records -> rows),
aggregate (rows -> statistics over seeds), table and plots (statistics -> files), build.
"""

from harness.report.build import ReportSettings, build_report

__all__ = ["ReportSettings", "build_report"]
