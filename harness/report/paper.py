"""The ConSFT paper's table 2 in Retain's numbers: the base (stage 0), then per row the target,
each held-out suite and their average, beside the steps used and the success the stages
stopped at (`until_success`).

Why a table of its own: the paper compares methods held to one target success, on named
held-out suites (`heldout_groups`), not on retention and plasticity; its columns put Retain's
rows beside its own. Runs log these figures (harness/measure/metrics.py `paper_metrics`); a run from
before them has none, and without any the table is not written.
"""

from __future__ import annotations

import ast
import math
from dataclasses import dataclass

from harness.measure.bootstrap import Interval, bootstrap_ci
from harness.report.aggregate import CHECK_SUCCESS, METRICS, Metric
from harness.report.groups import Row
from harness.report.runs import RunRecord

BASE_LABEL = "base (stage 0)"
HELDOUT = "heldout/"  # the per-suite final metrics: heldout/<suite>, base_heldout/<suite>
SAME = 1e-9  # stage-0 values of one seed further apart than this come from different foundations
REFERENCE = "sft"  # the row every other row is paired against
PAIRED = ("target", "heldout_avg")  # matched plasticity, then the paper's retention


@dataclass(frozen=True)
class PairedRow:
    """One row minus the reference row (sft) on the seeds both have."""

    label: str
    seeds: list[int]
    per_seed: dict[str, list[float]]  # column key -> the difference at each of `seeds`
    cells: dict[str, Interval]  # column key -> mean difference and its interval over the seeds


@dataclass(frozen=True)
class PaperTable:
    columns: list[Metric]  # target, each held-out suite, held-out average, steps, check success
    base: dict[str, Interval]  # column key -> its stage-0 value over seeds (score columns only)
    base_seeds: list[int]  # seeds behind the base row
    differing_seeds: list[int]  # seeds whose runs logged different stage-0 values
    paired: list[PairedRow]  # each row against sft, seed by seed; [] without an sft row


def heldout_suites(runs: list[RunRecord]) -> list[str]:
    """The held-out suites the runs logged, in the order of their benchmark's `heldout_groups`
    (the paper's order: Object, then Goal); a benchmark without named suites logs one,
    `foundation`, every foundation task."""
    logged = {k.removeprefix(HELDOUT) for r in runs for k in r.metrics if k.startswith(HELDOUT)}
    order: list[str] = []
    for run in runs:
        try:
            order += [str(name) for name in ast.literal_eval(run.params["config.heldout_groups"])]
        except (KeyError, ValueError, SyntaxError, TypeError):
            continue
    ranked = [name for name in dict.fromkeys(order) if name in logged]
    return ranked + sorted(logged - set(ranked))


def paper_columns(runs: list[RunRecord]) -> list[Metric]:
    """The table's columns; [] when no run logged the paper's metrics (runs before issue 36)."""
    if not any("target" in r.metrics for r in runs):
        return []
    steps = next(m for m in METRICS if m.key == "stream_steps")
    return [
        Metric("target", "target", True, "success on the stream (target) tasks after the last "
               "stage, mean over the tasks"),
        *(Metric(f"{HELDOUT}{name}", f"held-out: {name}", True,
                 f"success on the held-out suite `{name}` (foundation tasks) after the last stage")
          for name in heldout_suites(runs)),
        Metric("heldout_avg", "held-out avg", True,
               "mean over the held-out suites: the paper's prior capability retention"),
        steps,
        Metric(CHECK_SUCCESS, "check success", True,
               "mean over the stages of the success on their own check episodes at the stage's "
               "last `until_success` check (the one it stopped at, or the last before the step "
               "budget); n/a where until_success was off", ranked=False),
    ]


def base_key(key: str) -> str | None:
    """The stage-0 metric of a score column ("target" -> "base_target"); None for the columns
    that have no stage 0 (steps used, check success)."""
    if key in ("target", "heldout_avg") or key.startswith(HELDOUT):
        return f"base_{key}"
    return None


def paper_table(rows: list[Row], columns: list[Metric]) -> PaperTable:
    """The columns and the base row. Every method of a seed starts from that seed's foundation,
    so its stage-0 values are the same in each of its runs: per seed, their mean (equal to any
    one of them; seeds where runs disagree are listed), then mean and CI over the seeds."""
    runs = [run for row in rows for run in row.runs]
    seeds = sorted({run.seed for run in runs})
    base: dict[str, Interval] = {}
    differing: set[int] = set()
    for column in columns:
        key = base_key(column.key)
        if key is None:
            continue
        per_seed = []
        for seed in seeds:
            values = [r.metrics[key] for r in runs if r.seed == seed and key in r.metrics
                      and not math.isnan(r.metrics[key])]
            if values:
                per_seed.append(sum(values) / len(values))
                if max(values) - min(values) > SAME:
                    differing.add(seed)
        base[column.key] = bootstrap_ci(per_seed)
    shown = [s for s in seeds if any(r.seed == s and "base_target" in r.metrics for r in runs)]
    return PaperTable(columns, base, shown, sorted(differing), paired_rows(rows))


def paired_rows(rows: list[Row]) -> list[PairedRow]:
    """Each row's target and held-out average minus sft's, seed by seed, then the mean difference
    and its bootstrap interval over the seeds both rows have.

    Why paired: every method of a seed starts from that seed's foundation and is evaluated on the
    same episodes, so the seed-to-seed spread of the foundation cancels in the difference; two
    rows' separate intervals overlap long after their difference is clear of zero."""
    reference = next((row for row in rows if row.label == REFERENCE), None)
    if reference is None:
        return []
    ref = {run.seed: run.metrics for run in reference.runs}
    out = []
    for row in rows:
        if row is reference:
            continue
        seeds = [run.seed for run in row.runs if run.seed in ref
                 and all(_has(run.metrics, k) and _has(ref[run.seed], k) for k in PAIRED)]
        if not seeds:
            continue
        mine = {run.seed: run.metrics for run in row.runs}
        per_seed = {k: [mine[s][k] - ref[s][k] for s in seeds] for k in PAIRED}
        out.append(PairedRow(row.label, seeds, per_seed,
                             {k: bootstrap_ci(v) for k, v in per_seed.items()}))
    return out


def _has(metrics: dict[str, float], key: str) -> bool:
    return key in metrics and not math.isnan(metrics[key])
