"""The percentile bootstrap interval of a mean over seeds."""

import math

import numpy as np
import pytest

from harness.measure.bootstrap import bootstrap_ci


def test_interval_of_a_normal_sample_matches_theory():
    mu, sigma, n = 1.5, 2.0, 400
    x = np.random.default_rng(1).normal(mu, sigma, n)
    ci = bootstrap_ci(x)
    assert ci.n == n and ci.mean == pytest.approx(x.mean())
    assert ci.low < mu < ci.high
    expected = 2 * 1.96 * sigma / math.sqrt(n)  # 0.196
    assert ci.high - ci.low == pytest.approx(expected, rel=0.1)


def test_reproducible_and_order_free():
    values = [0.2, 0.35, 0.5, 0.1]
    assert bootstrap_ci(values) == bootstrap_ci(values)
    assert bootstrap_ci(values) == bootstrap_ci(sorted(values))  # rows sorted differently agree
    assert bootstrap_ci(values).low >= min(values) and bootstrap_ci(values).high <= max(values)


def test_one_seed_has_no_interval_and_nan_is_dropped():
    one = bootstrap_ci([0.7, float("nan")])
    assert (one.mean, one.low, one.high, one.n, one.has_interval) == (0.7, None, None, 1, False)
    none = bootstrap_ci([])
    assert none.n == 0 and math.isnan(none.mean)


def test_identical_values_give_a_zero_width_interval():
    ci = bootstrap_ci([0.4, 0.4, 0.4])
    assert ci.low == pytest.approx(0.4) and ci.high == pytest.approx(0.4)
