"""The training loop's speed devices (one flat buffer for parameters and gradients updated by
direct kernel calls, the next batch sampled on a second thread) must not change what is
learned."""

import copy

import pytest
import torch

from harness.perf.throughput import _policy, synthetic_data
from harness.train.optim import ClippedAdamW
from harness.train.trainer import TrainSettings, train_stage
from methods import Method, TaskContext


class NoPrefetch(Method):
    prefetch_batches = False


def _train(policy, method, settings, seed=0):
    ctx = TaskContext(1, "task", synthetic_data(512, 0), policy, 0.05, settings.steps)
    return train_stage(ctx, method, settings, torch.Generator().manual_seed(seed))


def test_prefetching_the_next_batch_does_not_change_the_weights(monkeypatch):
    monkeypatch.setattr("harness.train.trainer.os.cpu_count", lambda: 4)  # a core to spare: prefetch
    a, b = _policy("tiny"), _policy("tiny")
    settings = TrainSettings(steps=12, batch_size=32, lr=1e-3)
    ra, rb = _train(a, Method(), settings), _train(b, NoPrefetch(), settings)
    assert ra.final_loss == rb.final_loss
    for (name, x), y in zip(a.state_dict().items(), b.state_dict().values()):
        assert torch.equal(x, y), name


def test_flat_buffers_give_per_parameter_adamw_with_global_norm_clipping():
    policy = _policy("tiny")
    reference = copy.deepcopy(policy)
    settings = TrainSettings(steps=6, batch_size=32, lr=1e-3, weight_decay=0.01, grad_clip=0.05)
    _train(policy, NoPrefetch(), settings)

    data, g = synthetic_data(512, 0), torch.Generator().manual_seed(0)
    reference.train()
    params = list(reference.parameters())
    optimizer = torch.optim.AdamW(params, lr=1e-3, weight_decay=0.01)
    clipped = False
    for _ in range(settings.steps):
        loss = reference(data.sample(32, g), generator=g).mean()
        optimizer.zero_grad()
        loss.backward()
        clipped |= torch.nn.utils.clip_grad_norm_(params, 0.05).item() > 0.05
        optimizer.step()
    assert clipped  # the test covers the clipping path
    for (name, x), y in zip(policy.named_parameters(), reference.parameters()):
        torch.testing.assert_close(x, y, rtol=1e-5, atol=1e-6, msg=name)


def test_parameters_get_their_own_storage_back_and_frozen_ones_stay_put():
    policy = _policy("tiny")
    policy.instruction_proj.weight.requires_grad_(False)
    frozen = policy.instruction_proj.weight.detach().clone()
    _train(policy, Method(), TrainSettings(steps=3, batch_size=16, lr=1e-2, weight_decay=0.1))
    assert torch.equal(policy.instruction_proj.weight, frozen)
    for name, p in policy.named_parameters():
        assert p.grad is None, name
        assert p.untyped_storage().nbytes() == p.numel() * p.element_size(), name


@pytest.mark.parametrize("betas, eps", [((0.9, 0.999), 1e-8), ((0.9, 0.95), 1e-6)])
def test_clipped_adamw_matches_clipping_then_the_for_loop_adamw(betas, eps):
    g = torch.Generator().manual_seed(0)
    ours = torch.nn.Parameter(torch.randn(1000, generator=g))
    theirs = torch.nn.Parameter(ours.detach().clone())
    ours.grad = torch.zeros_like(ours)
    optimizer = ClippedAdamW(ours, lr=1e-2, weight_decay=0.1, grad_clip=1.0, betas=betas, eps=eps)
    reference = torch.optim.AdamW([theirs], lr=1e-2, weight_decay=0.1, betas=betas, eps=eps,
                                  foreach=False)
    for scale in (10.0, 0.01, 5.0, 0.001):  # norms far above and below the clip
        grad = scale * torch.randn(1000, generator=g)
        ours.grad.copy_(grad)
        theirs.grad = grad.clone()
        torch.nn.utils.clip_grad_norm_([theirs], 1.0)
        optimizer.step()
        reference.step()
        torch.testing.assert_close(ours, theirs, rtol=1e-6, atol=1e-7)
        assert not ours.grad.any()  # zeroed for the next backward, which accumulates into it
