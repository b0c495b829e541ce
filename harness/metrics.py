"""Continual-learning metrics from the success matrix R[stage, task] (definitions: DESIGN.md).

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


def offline_retention(heldout: np.ndarray, foundation: list[int]) -> np.ndarray:
    """Held-out flow-matching loss on foundation tasks, stage i over stage 0: [k+1]."""
    losses = heldout[:, foundation].mean(axis=1)
    return losses / losses[0]
