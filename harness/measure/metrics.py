"""Continual-learning metrics from the success matrix R[stage, task] (definitions: DESIGN.md),
and the spatial probe's from its own matrix S[stage, task], defined the same way.

R has k+1 rows (stage 0 = after the foundation, stage i = after stream task s_i) and one column
per task; `foundation` and `stream` name the column indices of the foundation tasks F and the
stream tasks s_1..s_k (stream[i-1] is the task trained at stage i).
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np


@dataclass(frozen=True)
class CoreMetrics:
    foundation_success_stage0: float
    retention: float  # foundation success at stage k (absolute)
    retention_drop: float  # stage 0 minus stage k
    retention_ratio: float  # stage k over stage 0
    plasticity: float
    stream_final_success: float
    forgetting: float
    bwt: float

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def foundation_success(R: np.ndarray, foundation: list[int]) -> np.ndarray:
    """Mean over foundation tasks, per stage: [k+1]."""
    return R[:, foundation].mean(axis=1)


def plasticity(R: np.ndarray, stream: list[int]) -> float:
    """Mean over i of R[i, s_i]: how well each task is learned right after its stage."""
    return float(np.mean([R[i + 1, s] for i, s in enumerate(stream)]))


def stream_final_success(R: np.ndarray, stream: list[int]) -> float:
    """Mean over i of R[k, s_i]."""
    return float(np.mean(R[-1, stream]))


def forgetting(R: np.ndarray, stream: list[int]) -> float:
    """Mean over i<k of max_{l in [i, k-1]} R[l, s_i] - R[k, s_i]; 0 for a single-task stream."""
    k = len(stream)
    if k < 2:
        return 0.0
    drops = [R[i + 1:k, s].max() - R[k, s] for i, s in enumerate(stream[:-1])]
    return float(np.mean(drops))


def backward_transfer(R: np.ndarray, stream: list[int]) -> float:
    """Mean over i<k of R[k, s_i] - R[i, s_i] (negative when later tasks erase earlier ones)."""
    k = len(stream)
    if k < 2:
        return 0.0
    return float(np.mean([R[k, s] - R[i + 1, s] for i, s in enumerate(stream[:-1])]))


def core_metrics(R: np.ndarray, foundation: list[int], stream: list[int]) -> CoreMetrics:
    fs = foundation_success(R, foundation)
    ratio = float(fs[-1] / fs[0]) if fs[0] > 0 else float("nan")
    return CoreMetrics(
        foundation_success_stage0=float(fs[0]),
        retention=float(fs[-1]),
        retention_drop=float(fs[0] - fs[-1]),
        retention_ratio=ratio,
        plasticity=plasticity(R, stream),
        stream_final_success=stream_final_success(R, stream),
        forgetting=forgetting(R, stream),
        bwt=backward_transfer(R, stream),
    )


@dataclass(frozen=True)
class SpatialMetrics:
    """The spatial probe's counterparts of CoreMetrics, from the spatial success matrix S
    (success from widened initial states, beyond the demos' range) with the same definitions:
    does fine-tuning keep what generalised beyond the demos (the paper's "spatial overfitting")?"""

    spatial_foundation_success_stage0: float
    spatial_retention: float  # foundation success on S at stage k
    spatial_plasticity: float

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def spatial_metrics(S: np.ndarray, foundation: list[int], stream: list[int]) -> SpatialMetrics:
    fs = foundation_success(S, foundation)
    return SpatialMetrics(spatial_foundation_success_stage0=float(fs[0]),
                          spatial_retention=float(fs[-1]),
                          spatial_plasticity=plasticity(S, stream))


def by_stage(R: np.ndarray, foundation: list[int], groups: list[list[int]]
             ) -> tuple[np.ndarray, list[int], list[int]]:
    """(R', F', S') with one column per stream stage: a stage that trained several tasks together
    (the paper's target suite) is one column, their mean success, so every definition above
    reads "task" as "stage". With one task a stage, R' is R with its columns reordered."""
    cols = [R[:, foundation]] + [R[:, g].mean(axis=1, keepdims=True) for g in groups]
    n = len(foundation)
    return np.concatenate(cols, axis=1), list(range(n)), list(range(n, n + len(groups)))


def paper_metrics(R: np.ndarray, tasks: list[str], foundation: list[str], stream: list[str],
                  heldout_groups: dict[str, list[str]]) -> dict[str, float]:
    """The ConSFT paper's table 2 columns: the target (every stream task) and each held-out
    suite (a named group of foundation tasks), at the base (stage 0) and after the stream
    (stage k), and the held-out average (the mean over the suites; without named suites, one
    suite of every foundation task, so it equals retention)."""
    groups = heldout_groups or {"foundation": foundation}

    def mean(stage: int, names: list[str]) -> float:
        return float(np.mean([R[stage, tasks.index(t)] for t in names]))

    out = {"base_target": mean(0, stream), "target": mean(-1, stream)}
    for name, names in groups.items():
        out[f"base_heldout/{name}"], out[f"heldout/{name}"] = mean(0, names), mean(-1, names)
    out["base_heldout_avg"] = float(np.mean([mean(0, g) for g in groups.values()]))
    out["heldout_avg"] = float(np.mean([mean(-1, g) for g in groups.values()]))
    return out


def heldout_loss_ratio(heldout: np.ndarray, foundation: list[int]) -> np.ndarray:
    """Held-out flow-matching loss on foundation tasks, stage i over stage 0: [k+1]. Lower is
    better (1: the loss is unchanged). Runs before issue 48 logged it as `offline_retention`,
    a name that read like a retention; the report reads either (`LEGACY_METRIC_KEYS`)."""
    losses = heldout[:, foundation].mean(axis=1)
    return losses / losses[0]


offline_retention = heldout_loss_ratio  # the old name, for code written against it

LEGACY_METRIC_KEYS = {"offline_retention": "heldout_loss_ratio"}
"""A metric key runs once logged -> its name now: a report reads an old run's under the new."""


# --- LIBERO's learning-curve metrics (Liu et al., 2023, "LIBERO: Benchmarking Knowledge Transfer
# for Lifelong Robot Learning", section 5.1) -------------------------------------------------------


@dataclass(frozen=True)
class LiberoMetrics:
    """FWT (higher is better), NBT (lower is better) and AUC (higher is better) over the stream."""

    fwt: float
    nbt: float
    auc: float

    def as_dict(self) -> dict[str, float]:
        return asdict(self)


def libero_metrics(curves: list[np.ndarray], R: np.ndarray, stream: list[int]) -> LiberoMetrics:
    """LIBERO's FWT, NBT and AUC for a stream of K tasks, from evaluations taken inside each stage.

    Why: the success matrix only sees each task at the end of its stage; LIBERO's metrics also
    reward learning a task quickly, which needs evaluations every N steps inside the stage.

    Inputs, with k = 1..K indexing the stream task s_k trained at stage k:
    - `curves[k-1]` = c_{k,k,e}: success on s_k at the evaluation checkpoints e of stage k, the
      first at e = 0 (before any step on s_k) and the last at the end of the stage. LIBERO uses
      11 checkpoints (epochs 0, 5, ..., 50); any number m+1 >= 1 works here.
    - `R` (the success matrix) and `stream` (its column of s_k): c_{tau,k} = R[tau, s_k], success
      on s_k after stage tau > k.

    With c_{k,k} = max_e c_{k,k,e} (the best success while learning s_k):
        FWT_k = mean_e c_{k,k,e}                                   FWT = sum_k FWT_k / K
        NBT_k = 1/(K-k) * sum_{tau=k+1..K} (c_{k,k} - c_{tau,k})   NBT = sum_k NBT_k / K
        AUC_k = 1/(K-k+1) * (FWT_k + sum_{tau=k+1..K} c_{tau,k})   AUC = sum_k AUC_k / K
    NBT_K is an empty sum, taken as 0, so NBT divides by K as the paper writes.

    One difference from LIBERO, by design: LIBERO continues from the earliest best checkpoint
    of each task (so c_{tau,k} is measured there); Retain continues from the stage's final
    weights, so c_{tau,k} is the success matrix entry at the end of stage tau.
    """
    K = len(stream)
    if K == 0 or len(curves) != K:
        raise ValueError(f"need one learning curve per stream task: {len(curves)} curves, {K} tasks")
    if any(len(c) == 0 for c in curves):
        raise ValueError("every learning curve needs at least one evaluation")
    fwt_k, nbt_k, auc_k = [], [], []
    for k, (curve, s) in enumerate(zip(curves, stream), start=1):
        fwt = float(np.mean(curve))
        later = R[k + 1:K + 1, s]  # c_{tau,k} for tau = k+1..K
        nbt_k.append(float(np.mean(np.max(curve) - later)) if later.size else 0.0)
        auc_k.append((fwt + float(later.sum())) / (K - k + 1))
        fwt_k.append(fwt)
    return LiberoMetrics(fwt=float(np.mean(fwt_k)), nbt=float(np.mean(nbt_k)),
                         auc=float(np.mean(auc_k)))
