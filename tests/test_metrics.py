"""Metric formulas (DESIGN.md) against matrices computed by hand."""

import numpy as np
import pytest
import torch

from harness.measure.metrics import (
    backward_transfer,
    core_metrics,
    forgetting,
    foundation_success,
    offline_retention,
    plasticity,
    stream_final_success,
)
from harness.measure.updates import hoyer_sparsity, update_stats

# columns: F1, F2, s1, s2, s3; rows: stages 0..3
R = np.array([
    [0.9, 0.7, 0.0, 0.1, 0.0],
    [0.5, 0.5, 0.8, 0.2, 0.0],
    [0.3, 0.5, 0.6, 1.0, 0.1],
    [0.1, 0.3, 0.2, 0.4, 0.9],
])
F, S = [0, 1], [2, 3, 4]


def test_foundation_success_and_retention():
    assert foundation_success(R, F) == pytest.approx([0.8, 0.5, 0.4, 0.2])
    m = core_metrics(R, F, S)
    assert m.foundation_success_stage0 == pytest.approx(0.8)
    assert m.retention == pytest.approx(0.2)
    assert m.retention_drop == pytest.approx(0.6)
    assert m.retention_ratio == pytest.approx(0.25)


def test_plasticity_is_the_diagonal_of_the_stream_block():
    assert plasticity(R, S) == pytest.approx((0.8 + 1.0 + 0.9) / 3)


def test_stream_final_success():
    assert stream_final_success(R, S) == pytest.approx((0.2 + 0.4 + 0.9) / 3)


def test_forgetting_uses_the_best_earlier_stage():
    # s1: max(R[1..2, s1]) = 0.8, final 0.2 -> 0.6; s2: max(R[2, s2]) = 1.0, final 0.4 -> 0.6
    assert forgetting(R, S) == pytest.approx(0.6)
    # the best stage, not the first: s1 peaks after stage 1 here
    R2 = R.copy()
    R2[1, 2], R2[2, 2] = 0.5, 0.7
    assert forgetting(R2, S) == pytest.approx(((0.7 - 0.2) + 0.6) / 2)


def test_bwt():
    assert backward_transfer(R, S) == pytest.approx(((0.2 - 0.8) + (0.4 - 1.0)) / 2)


def test_single_task_stream_has_no_forgetting():
    assert forgetting(R[:2, :3], [2]) == 0.0 and backward_transfer(R[:2, :3], [2]) == 0.0


def test_offline_retention_is_relative_to_stage_zero():
    losses = np.array([[0.1, 0.3, 5.0], [0.2, 0.6, 1.0]])
    assert offline_retention(losses, [0, 1]) == pytest.approx([1.0, 2.0])


def test_hoyer_sparsity_extremes():
    assert hoyer_sparsity(torch.ones(100)) == pytest.approx(0.0)
    one_hot = torch.zeros(100)
    one_hot[3] = 2.0
    assert hoyer_sparsity(one_hot) == pytest.approx(1.0)


def test_update_stats_counts_changes_relative_to_tensor_rms():
    ref = {"a.weight": torch.ones(10, 10), "b.weight": torch.full((100,), 2.0)}
    cur = {k: v.clone() for k, v in ref.items()}
    cur["a.weight"][0, :5] += 0.005  # 5e-3 > 1e-3 * rms(1) but < 1e-2 * rms
    cur["b.weight"][:10] += 0.5  # > 1e-2 * rms(2) = 0.02
    summary, rows = update_stats(ref, cur)
    assert summary["frac_changed_rho0.001"] == pytest.approx(15 / 200)
    assert summary["frac_changed_rho0.01"] == pytest.approx(10 / 200)
    by_layer = {r["layer"]: r for r in rows}
    assert by_layer["a.weight"]["frac_changed_rho0.001"] == pytest.approx(0.05)
    assert by_layer["b.weight"]["relative_l2"] == pytest.approx((10 * 0.25) ** 0.5 / 20.0)
