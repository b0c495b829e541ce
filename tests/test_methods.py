"""The methods' defining behaviours, each a property that a wrong implementation would break."""

import torch

from harness.data.datasets import TrainingData
from methods import TaskContext, get_method, method_names
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
