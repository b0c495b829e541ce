"""Per-row statistics over seeds: the numbers every table and plot of the report draws from.

Why one place: the table's retention and the scatter plot's retention must be the same number,
computed once.
"""

from __future__ import annotations

import itertools
from dataclasses import dataclass

import numpy as np

from harness.bootstrap import Interval, bootstrap_ci
from harness.errors import RetainError
from harness.report.groups import Row
from harness.report.runs import RunRecord


@dataclass(frozen=True)
class Metric:
    """A table column: an MLflow final-metric key, its heading, and which direction is better."""

    key: str
    title: str
    higher_is_better: bool
    note: str  # one line for the report's legend
    optional: bool = False  # shown only when some run logged it (FWT/NBT/AUC need learning curves)


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
    Metric("offline_retention", "offline retention (loss ratio)", False,
           "held-out flow-matching loss on the foundation tasks, stage k over 0"),
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
]
OPTIONAL_NOTES = {
    "fwt": "FWT, NBT and AUC (LIBERO) appear when runs log learning-curve evaluations.",
    "spatial_retention": "The spatial columns appear when runs evaluate the spatial probe "
                         "(`spatial_episodes` > 0).",
}


@dataclass(frozen=True)
class UpdateHistogram:
    """Fraction of all trainable scalars per bin of |delta theta| / RMS(theta_0 of its tensor)."""

    bins: list[str]  # bin labels, smallest change first
    fractions: np.ndarray  # mean over seeds; sums to 1


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

    @property
    def label(self) -> str:
        return self.row.label


def shown_metrics(summaries: list[RowSummary]) -> list[Metric]:
    return [m for m in METRICS if not m.optional or any(s.cells[m.key].n for s in summaries)]


def summarize(row: Row) -> RowSummary:
    runs = row.runs
    first = runs[0]
    for run in runs[1:]:
        if run.tasks != first.tasks:
            raise RetainError(f"runs of {row.label} evaluate different tasks ({first.run_id}: "
                              f"{first.tasks}; {run.run_id}: {run.tasks}); report them apart")
    stack = np.stack([r.success for r in runs])
    n_f = len(first.foundation_tasks)
    per_stage = stack[:, :, :n_f].mean(axis=2)  # [seed, stage]
    return RowSummary(
        row=row,
        cells={m.key: bootstrap_ci([r.metrics.get(m.key, float("nan")) for r in runs])
               for m in METRICS},
        foundation_tasks=first.foundation_tasks,
        stream_tasks=first.stream_tasks,
        success_mean=_nanmean(stack),
        foundation_by_stage=[bootstrap_ci(per_stage[:, i]) for i in range(per_stage.shape[1])],
        updates=_update_histogram(runs),
        layer_relative_l2=_layer_relative_l2(runs),
    )


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
