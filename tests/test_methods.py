"""The methods' defining behaviours, each a property that a wrong implementation would break."""

import math

import pytest
import torch

from harness.datasets import TrainingData
from methods import TaskContext, get_method, method_names
from methods.consft import ConSFT, ConSFTConfig
from methods.er import ERConfig, ExperienceReplay
from methods.ewc import OnlineEWC, per_sample_fisher
from methods.l2 import L2Config, L2ToReference
from tests.conftest import make_batch


def _data(policy, n, task, seed):
    b = make_batch(policy, b=n, seed=seed)
    return TrainingData({"state": b["state"]}, b["actions"], torch.ones(n, 4, dtype=torch.bool),
                        torch.zeros(n, dtype=torch.long), b["instruction"][:1], [task])


def _ctx(policy, data, stage=1, foundation_loss=0.1):
    return TaskContext(stage=stage, task=data.task_names[0], data=data, policy=policy,
                       foundation_loss=foundation_loss, steps=10)


def test_registry_has_every_method():
    assert {"sft", "consft", "er", "ewc", "l2", "multitask"} <= set(method_names())


def _param_grads(policy, loss):
    policy.zero_grad()
    loss.backward()
    return torch.cat([p.grad.flatten() for p in policy.parameters() if p.grad is not None])


def test_consft_scales_a_high_loss_samples_gradient_by_its_weight(tiny_policy):
    batch = make_batch(tiny_policy, b=1)
    batch["actions"] = batch["actions"] * 5  # far from what the policy predicts: a high loss
    batch["noise"], batch["time"] = torch.randn(1, 4, 3), torch.tensor([0.5])
    method = ConSFT(ConSFTConfig(kappa=0.5, w_min=0.01))
    method.l_ref = 0.8
    sft_grad = _param_grads(tiny_policy, tiny_policy(batch).mean())
    per_sample = tiny_policy(batch)
    loss, stats = method.loss(per_sample, batch, tiny_policy)
    consft_grad = _param_grads(tiny_policy, loss)
    value = per_sample.item()
    expected = min(1.0, max(0.01, math.exp(-(value - 0.8) / (0.5 * 0.8))))
    assert value > 0.8 and expected < 0.5
    assert torch.allclose(consft_grad, expected * sft_grad, rtol=1e-4, atol=1e-9)
    assert stats["consft/weight_mean"] == pytest.approx(expected)


def test_consft_weights_reach_one_below_the_reference_and_floor_above():
    method = ConSFT(ConSFTConfig(kappa=0.25, w_min=0.05))
    method.l_ref = 0.2
    w = method.weights(torch.tensor([0.01, 0.2, 0.25, 5.0]))
    assert w[0] == 1.0 and w[1] == 1.0
    assert w[2].item() == pytest.approx(math.exp(-0.05 / 0.05))
    assert w[3].item() == pytest.approx(0.05)


def test_consft_dft_weight_is_exp_of_minus_loss_over_tau():
    method = ConSFT(ConSFTConfig(variant="dft", kappa=2.0))
    method.l_ref = 0.5
    assert method.weights(torch.tensor([0.3])).item() == pytest.approx(math.exp(-0.3 / 1.0))


def test_consft_ratio_samples_past_the_clip_get_no_gradient():
    method = ConSFT(ConSFTConfig(variant="ratio", kappa=1.0, eps=0.2))
    method.l_ref = 0.5  # tau = 0.5
    method._old_loss = torch.tensor([1.0, 1.0, 1.0])
    # r = exp((1 - l) / 0.5): l = 0.5 -> r = e > 1.2 (clipped); l = 1.0 -> r = 1; l = 2 -> r < 0.8
    per_sample = torch.tensor([0.5, 1.0, 2.0], requires_grad=True)
    loss, stats = method.loss(per_sample, {"index": torch.arange(3)}, None)
    loss.backward()
    assert per_sample.grad[0].item() == 0.0
    assert per_sample.grad[1].item() != 0.0 and per_sample.grad[2].item() != 0.0
    assert stats["consft/frac_clipped"] == pytest.approx(1 / 3)


def test_consft_ratio_caches_losses_with_the_draws_it_reuses(tiny_policy):
    data = _data(tiny_policy, 16, "t", seed=1)
    method = ConSFT(ConSFTConfig(variant="ratio"))
    ctx = _ctx(tiny_policy, data)
    method.before_task(ctx)
    batch = method.sample_batch(ctx, 8, torch.Generator().manual_seed(0))
    with torch.no_grad():
        again = tiny_policy(batch)
    assert torch.allclose(again, method._old_loss[batch["index"]], atol=1e-6)  # r = 1 at start


def test_consft_rejects_an_unknown_variant():
    with pytest.raises(ValueError, match="'clipp'.*clip, dft, ratio"):
        ConSFT(ConSFTConfig(variant="clipp"))


def test_ewc_fisher_matches_an_explicit_per_sample_loop(tiny_policy):
    batch = make_batch(tiny_policy, b=6, seed=3)
    batch["noise"], batch["time"] = torch.randn(6, 4, 3), torch.rand(6) * 0.9 + 0.05
    fisher = per_sample_fisher(tiny_policy, batch, chunk=4)
    expected = {n: torch.zeros_like(p) for n, p in tiny_policy.named_parameters()}
    for i in range(6):
        one = {k: v[i:i + 1] for k, v in batch.items()}
        tiny_policy.zero_grad()
        tiny_policy(one).sum().backward()
        for n, p in tiny_policy.named_parameters():
            expected[n] += p.grad ** 2 / 6
    for n in expected:
        assert torch.allclose(fisher[n], expected[n], rtol=1e-4, atol=1e-10), n
    batch_grad_sq = {}
    tiny_policy.zero_grad()
    tiny_policy(batch).mean().backward()
    for n, p in tiny_policy.named_parameters():
        batch_grad_sq[n] = p.grad ** 2
    name = "action_in.weight"
    assert not torch.allclose(batch_grad_sq[name], fisher[name])  # not the batch-gradient shortcut


def test_ewc_online_fisher_decays(tiny_policy):
    method = OnlineEWC(OnlineEWC.Config(fisher_samples=8, decay=0.5))
    data = _data(tiny_policy, 8, "t", seed=2)
    method.after_task(_ctx(tiny_policy, data, stage=0))
    first = {k: v.clone() for k, v in method.fisher.items()}
    method.after_task(_ctx(tiny_policy, data, stage=0))  # same draws: F = 0.5 F + F
    assert torch.allclose(method.fisher["action_in.weight"], 1.5 * first["action_in.weight"])


def _train(policy, method, data, steps=60, lr=1e-2):
    ctx = _ctx(policy, data)
    optimizer = torch.optim.SGD(policy.parameters(), lr=lr)
    g = torch.Generator().manual_seed(0)
    for _ in range(steps):
        batch = method.sample_batch(ctx, 16, g)
        loss, _ = method.loss(policy(batch, generator=g), batch, policy)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()


def _distance(policy, reference):
    return sum(((p - reference[n]) ** 2).sum().item() for n, p in policy.named_parameters())


def test_l2_pulls_towards_the_foundation_weights(tiny_policy):
    import copy

    data = _data(tiny_policy, 32, "new", seed=5)
    reference = {n: p.detach().clone() for n, p in tiny_policy.named_parameters()}
    free, anchored = copy.deepcopy(tiny_policy), copy.deepcopy(tiny_policy)
    _train(free, get_method("sft")(), data)
    l2 = L2ToReference(L2Config(strength=50.0))
    l2.after_task(_ctx(anchored, data, stage=0))
    _train(anchored, l2, data)
    assert _distance(anchored, reference) < 0.5 * _distance(free, reference)


def test_er_batches_hold_the_configured_mix(tiny_policy):
    old, new = _data(tiny_policy, 50, "old", seed=6), _data(tiny_policy, 50, "new", seed=7)
    method = ExperienceReplay(ERConfig(buffer_per_task=20, replay_ratio=0.25))
    method.after_task(_ctx(tiny_policy, old, stage=0))
    assert len(method.buffer) == 20
    batch = method.sample_batch(_ctx(tiny_policy, new), 64, torch.Generator().manual_seed(0))
    from_old = (batch["instruction"] == old.instruction_table[0]).all(dim=1).sum().item()
    assert from_old == 16 and len(batch["actions"]) == 64
    method.after_task(_ctx(tiny_policy, new, stage=1))
    assert len(method.buffer) == 40 and method.buffer.task_names == ["old", "new"]


def test_consft_ratio_stays_finite_when_the_loss_falls_far_below_its_start():
    method = ConSFT(ConSFTConfig(variant="ratio", kappa=1.0, eps=0.2))
    method.l_ref = 0.05  # (old - l) / tau = 74: exp would overflow float32
    method._old_loss = torch.tensor([3.8, 0.5])
    per_sample = torch.tensor([0.1, 0.6], requires_grad=True)  # r = exp(74) and exp(-2)
    loss, _ = method.loss(per_sample, {"index": torch.arange(2)}, None)
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(per_sample.grad).all()
    assert per_sample.grad[0].item() == 0.0 and per_sample.grad[1].item() != 0.0
