"""Per-row statistics over seeds: the numbers every table and plot of the report draws from.

Why one place: the table's retention and the scatter plot's retention must be the same number,
computed once.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from harness.common.errors import RetainError
from harness.measure.bootstrap import Interval, bootstrap_ci
from harness.report.groups import Row
from harness.report.runs import SERIES_KEYS, RunRecord


@dataclass(frozen=True)
class Metric:
    """A table column: an MLflow final-metric key, its heading, and which direction is better."""

    key: str
    title: str
    higher_is_better: bool
    note: str  # one line for the report's legend
    optional: bool = False  # shown only when some run logged it (FWT/NBT/AUC need learning curves)
    ranked: bool = True  # False: a fact about the run, not a score (steps used): no best, no arrow
    digits: int = 3  # decimals printed


METRICS = [
    Metric("retention", "retention", True,
           "foundation success after the last stage (the headline)"),
    Metric("retention_drop", "retention drop", False,
           "foundation success at stage 0 minus at stage k"),
    Metric("retention_ratio", "retention ratio", True,
           "foundation success at stage k over stage 0"),
    Metric("plasticity", "plasticity", True,
           "mean success on each stream task right after its own stage"),
    Metric("stream_final_success", "stream final success", True,
           "mean success on the stream tasks after the last stage"),
    Metric("forgetting", "forgetting", False,
           "mean drop of each stream task from its best earlier stage to the end"),
    Metric("bwt", "BWT", True,
           "mean of R[k, s_i] - R[i, s_i] over i < k; negative when later tasks erase earlier"),
    Metric("heldout_loss_ratio", "held-out loss ratio", False,
           "held-out flow-matching loss on the foundation tasks, stage k over stage 0 (1: "
           "unchanged; lower is better; logged as offline_retention before issue 48)"),
    Metric("update_frac_changed_rho0.01", "frac. changed (rho=0.01)", False,
           "fraction of scalars with |delta| > 0.01 RMS of their tensor"),
    Metric("update_hoyer_sparsity", "Hoyer sparsity", True,
           "Hoyer sparsity of theta_k - theta_0 (1 = one scalar moved)"),
    Metric("update_relative_l2", "relative L2", False, "||theta_k - theta_0|| / ||theta_0||"),
    Metric("fwt", "FWT", True,
           "LIBERO forward transfer: mean success along each task's own learning curve",
           optional=True),
    Metric("nbt", "NBT", False,
           "LIBERO negative backward transfer: best success on a task minus later success",
           optional=True),
    Metric("auc", "AUC", True,
           "LIBERO area under the success curve: FWT and later success together", optional=True),
    Metric("spatial_foundation_success_stage0", "spatial stage-0", True,
           "spatial probe: foundation success from widened initial states (beyond the demos' "
           "range) after the foundation stage", optional=True),
    Metric("spatial_retention", "spatial retention", True,
           "spatial probe: foundation success from widened initial states after the last stage",
           optional=True),
    Metric("spatial_plasticity", "spatial plasticity", True,
           "spatial probe: mean success from widened initial states on each stream task right "
           "after its own stage", optional=True),
    Metric("stream_steps", "steps used", False,
           "optimizer steps over all stream stages; fewer than planned where `until_success` "
           "stopped a stage at its check", optional=True, ranked=False, digits=1),
    Metric("update_eq8_sparsity", "Eq. 8 sparsity", True,
           "the ConSFT paper's Eq. 8: share of scalars with |theta_k - theta_0| / |theta_0| "
           "< 1e-3", optional=True),
]
CHECK_SUCCESS = "check_success"  # derived per run: mean over stages of `stage_check_success`
OPTIONAL_NOTES = {
    "fwt": "FWT, NBT and AUC (LIBERO) appear when runs log learning-curve evaluations.",
    "spatial_retention": "The spatial columns appear when runs evaluate the spatial probe "
                         "(`spatial_episodes` > 0).",
    "stream_steps": "Steps used and Eq. 8 sparsity appear for runs that log them (issue 36 on).",
}


def run_value(run: RunRecord, key: str) -> float:
    """A run's value of a column: its final metric, or for `check_success` the mean over its
    stages of the success at each stage's last `until_success` check (NaN where it was off)."""
    if key == CHECK_SUCCESS:
        checked = [v for v in run.stage_check_success if not math.isnan(v)]
        return float(np.mean(checked)) if checked else math.nan
    return run.metrics.get(key, math.nan)


@dataclass(frozen=True)
class UpdateHistogram:
    """Fraction of all trainable scalars per bin of |delta theta| / RMS(theta_0 of its tensor)."""

    bins: list[str]  # bin labels, smallest change first
    fractions: np.ndarray  # mean over seeds; sums to 1


@dataclass(frozen=True)
class SeriesSummary:
    """A per-step metric of a row over its seeds (runs.StepSeries): at each step the mean and
    the range (min, max) of the seeds that logged it there (a seed whose stage stopped early
    has no later steps in that stage)."""

    step: np.ndarray
    stage: np.ndarray
    mean: np.ndarray
    low: np.ndarray
    high: np.ndarray
    n: int  # seeds that logged it


@dataclass(frozen=True)
class RowSummary:
    row: Row
    cells: dict[str, Interval]  # metric key -> mean and 95% CI over seeds
    foundation_tasks: list[str]
    stream_tasks: list[str]
    success_mean: np.ndarray  # R[stage, task], mean over seeds
    foundation_by_stage: list[Interval]  # foundation success per stage, mean and CI over seeds
    updates: UpdateHistogram | None
    layer_relative_l2: dict[str, float]  # layer -> relative L2 of theta_k - theta_0, mean over seeds
    stages: list[list[str]] = field(default_factory=list)  # stream tasks of each stage
    series: dict[str, SeriesSummary] = field(default_factory=dict)  # runs.SERIES_KEYS logged

    @property
    def label(self) -> str:
        return self.row.label

    @property
    def stage_names(self) -> list[str]:
        return self.row.runs[0].stage_names


def shown_metrics(summaries: list[RowSummary]) -> list[Metric]:
    return [m for m in METRICS if not m.optional or any(s.cells[m.key].n for s in summaries)]


def summarize(row: Row, extra: list[str] = ()) -> RowSummary:
    """The row's statistics over its seeds: every main-table metric, and the `extra` column
    keys (the paper table's) as well."""
    runs = row.runs
    first = runs[0]
    for run in runs[1:]:
        if run.tasks != first.tasks or run.stages != first.stages:
            raise RetainError(f"runs of {row.label} evaluate different tasks or stages "
                              f"({first.run_id}: {first.stages}; {run.run_id}: {run.stages}); "
                              "report them apart")
    stack = np.stack([r.success for r in runs])
    n_f = len(first.foundation_tasks)
    per_stage = stack[:, :, :n_f].mean(axis=2)  # [seed, stage]
    return RowSummary(
        row=row,
        cells={key: bootstrap_ci([run_value(r, key) for r in runs])
               for key in dict.fromkeys([*(m.key for m in METRICS), *extra])},
        foundation_tasks=first.foundation_tasks,
        stream_tasks=first.stream_tasks,
        success_mean=_nanmean(stack),
        foundation_by_stage=[bootstrap_ci(per_stage[:, i]) for i in range(per_stage.shape[1])],
        updates=_update_histogram(runs),
        layer_relative_l2=_layer_relative_l2(runs),
        stages=first.stages,
        series={key: summary for key in SERIES_KEYS
                if (summary := _series_summary(runs, key)) is not None},
    )


def _series_summary(runs: list[RunRecord], key: str) -> SeriesSummary | None:
    logged = [r.series[key] for r in runs if key in r.series and len(r.series[key].step)]
    if not logged:
        return None
    steps = np.unique(np.concatenate([s.step for s in logged]))
    table = np.full((len(logged), len(steps)), np.nan)
    stage = np.zeros(len(steps), dtype=np.int64)
    for i, s in enumerate(logged):
        at = np.searchsorted(steps, s.step)
        table[i, at], stage[at] = s.value, s.stage
    # every step has a value from at least one seed, so nanmin/nanmax never see an empty column
    return SeriesSummary(steps, stage, _nanmean(table), np.nanmin(table, axis=0),
                         np.nanmax(table, axis=0), len(logged))


def _nanmean(stack: np.ndarray) -> np.ndarray:
    """Mean over seeds that keeps NaN (never evaluated) without numpy's empty-slice warning."""
    counts = np.sum(~np.isnan(stack), axis=0)
    sums = np.nansum(stack, axis=0)
    return np.where(counts > 0, sums / np.maximum(counts, 1), np.nan)


def _update_histogram(runs: list[RunRecord]) -> UpdateHistogram | None:
    """Exact coarse histogram from the logged per-layer fractions: with thresholds rho_1 < rho_2,
    the bins are [0, rho_1], (rho_1, rho_2] and above rho_2, weighted by each layer's size. Only
    the thresholds every run logged are used, so runs from before and after a change of
    thresholds still share bins."""
    logged = [run for run in runs if run.layers]
    if not logged:
        return None
    rhos = sorted(set.intersection(*(set(run.layers[0].frac_changed) for run in logged)))
    if not rhos:
        return None
    per_run = []
    for run in logged:
        total = sum(layer.numel for layer in run.layers)
        above = [sum(layer.numel * layer.frac_changed[rho] for layer in run.layers) / total
                 for rho in rhos]  # fraction of scalars above each threshold, decreasing
        edges = [1.0, *above, 0.0]
        per_run.append([edges[i] - edges[i + 1] for i in range(len(edges) - 1)])
    names = [f"<= {rhos[0]:g}"]
    names += [f"{lo:g} - {hi:g}" for lo, hi in itertools.pairwise(rhos)]
    names.append(f"> {rhos[-1]:g}")
    return UpdateHistogram(names, np.mean(per_run, axis=0))


def _layer_relative_l2(runs: list[RunRecord]) -> dict[str, float]:
    values: dict[str, list[float]] = {}
    for run in runs:
        for layer in run.layers:
            values.setdefault(layer.layer, []).append(layer.relative_l2)
    return {name: float(np.mean(v)) for name, v in values.items()}
