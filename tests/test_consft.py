"""ConSFT as the paper defines it (arXiv 2605.08879: Eq. 5, 11-12, App. C.1, table 5): its
schedule against a hand computation, its weights, and its stop-gradient."""

import math

import pytest
import torch

from harness.common.errors import RetainError
from harness.protocol.stream import make_method
from methods.consft import ConSFT, ConSFTConfig, annealing, temperature
from tests.conftest import make_batch
from tests.test_methods import _ctx, _data

PAPER = ConSFTConfig()  # table 5's values


def _hand_tau(t, T=2000, lam=0.8, c=3.5, tau_start=0.003, tau_end=5.0, eps=1e-8):
    rho = (math.exp(-lam * min(t / T, 1) ** c) - math.exp(-lam)) / (1 - math.exp(-lam))
    return min(tau_start / max(rho, eps), tau_end)


def test_defaults_are_table_5():
    assert (PAPER.tau_start, PAPER.tau_end, PAPER.kappa, PAPER.lam, PAPER.c, PAPER.w_min,
            PAPER.anneal_steps, PAPER.variant) == (0.003, 5.0, 25.0, 0.8, 3.5, 1e-3, 2000, "paper")


@pytest.mark.parametrize("t", [0, 1000, 1800, 2000, 4000])
def test_schedule_matches_a_hand_computation(t):
    assert temperature(t, PAPER) == pytest.approx(_hand_tau(t), rel=1e-12)


def test_schedule_starts_at_tau_start_ends_at_tau_end_and_never_falls():
    assert annealing(0, PAPER) == pytest.approx(1.0) and annealing(2000, PAPER) == pytest.approx(0)
    assert temperature(0, PAPER) == pytest.approx(0.003)
    # by hand: rho(T/2) = (exp(-0.8 * 0.5**3.5) - exp(-0.8)) / (1 - exp(-0.8)) = 0.8725...
    rho_half = (math.exp(-0.8 * 0.5 ** 3.5) - math.exp(-0.8)) / (1 - math.exp(-0.8))
    assert temperature(1000, PAPER) == pytest.approx(0.003 / rho_half)
    assert 0.0034 < temperature(1000, PAPER) < 0.0035
    assert all(temperature(t, PAPER) == 5.0 for t in (2000, 2001, 4000, 10**6))
    taus = [temperature(t, PAPER) for t in range(0, 2600, 7)]
    assert all(b >= a for a, b in zip(taus, taus[1:]))
    assert temperature(1999, PAPER) < 5.0  # reached at T, not before the last steps


def test_weights_sit_at_the_floor_for_usual_losses_and_reach_one_at_zero_loss():
    method = ConSFT()
    w = method.weights(torch.tensor([0.0, 1e-6, 0.04, 3.0]))
    assert w[0].item() == 1.0
    assert w[1].item() == pytest.approx(math.exp(-25 * 1e-6 / 0.003), rel=1e-5)
    # exp(-25 * L / 0.003) < 1e-3 once L > 0.003 * ln(1000) / 25 = 8.3e-4: the floor
    assert w[2].item() == pytest.approx(1e-3) and w[3].item() == pytest.approx(1e-3)


def test_weights_follow_the_step_within_the_stage(tiny_policy):
    method = ConSFT()
    method.before_task(_ctx(tiny_policy, _data(tiny_policy, 4, "t", seed=0)))
    for _ in range(2000):
        method.after_step(tiny_policy)
    w = method.weights(torch.tensor([0.04]))  # tau = 5 now: exp(-25 * 0.04 / 5)
    assert w.item() == pytest.approx(math.exp(-0.2), rel=1e-6)
    method.before_task(_ctx(tiny_policy, _data(tiny_policy, 4, "t", seed=0), stage=2))
    assert method.t == 0 and method.weights(torch.tensor([0.04])).item() == pytest.approx(1e-3)


def test_kappa_in_the_temperature_reading():
    method = ConSFT(ConSFTConfig(variant="kappa_temp"))
    w = method.weights(torch.tensor([0.04, 10.0]))
    assert w[0].item() == pytest.approx(math.exp(-0.04 / (25 * 0.003)), rel=1e-5)  # 0.587
    assert w[1].item() == pytest.approx(1e-3)


def test_no_gradient_flows_through_the_weight(tiny_policy):
    batch = make_batch(tiny_policy, b=3, seed=2)
    batch["noise"], batch["time"] = torch.randn(3, 4, 3), torch.tensor([0.2, 0.5, 0.9])
    method = ConSFT(ConSFTConfig(variant="kappa_temp", kappa=2000.0))  # weights in (0, 1)
    per_sample = tiny_policy(batch)
    loss, stats = method.loss(per_sample, batch, tiny_policy)
    tiny_policy.zero_grad()
    loss.backward()
    got = torch.cat([p.grad.flatten() for p in tiny_policy.parameters() if p.grad is not None])
    # the gradient of mean(w_i * L_i) with w_i a constant: sum_i w_i / B * grad L_i
    w = method.weights(per_sample.detach())
    assert 0.001 < w.min() and w.max() < 0.999
    tiny_policy.zero_grad()
    (tiny_policy(batch) * w).mean().backward()
    expected = torch.cat([p.grad.flatten() for p in tiny_policy.parameters() if p.grad is not None])
    assert torch.allclose(got, expected, rtol=1e-5, atol=1e-9)
    assert stats["consft/weight_mean"] == pytest.approx(w.mean().item())
    assert stats["consft/tau"] == pytest.approx(0.003)


def test_it_logs_tau_the_floor_share_and_loss_quantiles():
    method = ConSFT()
    per_sample = torch.tensor([0.0, 0.01, 0.02, 5.0])
    _, stats = method.loss(per_sample, {}, None)
    assert stats["consft/frac_at_floor"] == pytest.approx(0.75)
    assert stats["consft/loss_q50"] == pytest.approx(0.015)
    assert set(stats) >= {"consft/tau", "consft/weight_mean", "consft/loss_q10", "consft/loss_q90"}


def test_dft_weight_is_exp_of_minus_loss_over_a_fixed_temperature():
    method = ConSFT(ConSFTConfig(variant="dft", tau_fixed=2.0))
    assert method.weights(torch.tensor([0.3])).item() == pytest.approx(math.exp(-0.3 / 2.0))


def test_ratio_samples_past_the_clip_get_no_gradient():
    method = ConSFT(ConSFTConfig(variant="ratio", tau_fixed=0.5, clip_eps=0.2))
    method._old_loss = torch.tensor([1.0, 1.0, 1.0])
    # r = exp((1 - l) / 0.5): l = 0.5 -> r = e > 1.2 (clipped); l = 1.0 -> r = 1; l = 2 -> r < 0.8
    per_sample = torch.tensor([0.5, 1.0, 2.0], requires_grad=True)
    loss, stats = method.loss(per_sample, {"index": torch.arange(3)}, None)
    loss.backward()
    assert per_sample.grad[0].item() == 0.0
    assert per_sample.grad[1].item() != 0.0 and per_sample.grad[2].item() != 0.0
    assert stats["consft/frac_clipped"] == pytest.approx(1 / 3)


def test_ratio_stays_finite_when_the_loss_falls_far_below_its_start():
    method = ConSFT(ConSFTConfig(variant="ratio", tau_fixed=0.05))
    method._old_loss = torch.tensor([3.8, 0.5])
    per_sample = torch.tensor([0.1, 0.6], requires_grad=True)  # r = exp(74) and exp(-2)
    loss, _ = method.loss(per_sample, {"index": torch.arange(2)}, None)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(per_sample.grad).all()
    assert per_sample.grad[0].item() == 0.0 and per_sample.grad[1].item() != 0.0


def test_ratio_caches_losses_with_the_draws_it_reuses(tiny_policy):
    data = _data(tiny_policy, 16, "t", seed=1)
    method = ConSFT(ConSFTConfig(variant="ratio"))
    ctx = _ctx(tiny_policy, data)
    method.before_task(ctx)
    batch = method.sample_batch(ctx, 8, torch.Generator().manual_seed(0))
    with torch.no_grad():
        again = tiny_policy(batch)
    assert torch.allclose(again, method._old_loss[batch["index"]], atol=1e-6)  # r = 1 at start


def test_the_abstract_only_clip_reading_is_gone():
    with pytest.raises(RetainError, match="'clip' for variant.*paper, kappa_temp, dft, ratio"):
        make_method(ConSFT, {"variant": "clip"})
