"""The flow-matching conventions of the policy (DESIGN.md: pi0's, t = 1 is noise)."""

import torch

from tests.conftest import make_batch


def _exact_velocity_for(target_normalized):
    """The optimal velocity when every action chunk equals `target`: (x_t - target) / t."""

    def velocity(x_t, t, obs_embedding):
        return (x_t - target_normalized) / t[:, None, None]

    return velocity


def test_forward_returns_per_sample_loss(tiny_policy):
    loss = tiny_policy(make_batch(tiny_policy, b=8))
    assert loss.shape == (8,)
    assert torch.all(loss >= 0)


def test_t_equal_one_is_noise(tiny_policy):
    """With x_t = t*noise + (1-t)*a, the velocity (x_t - a)/t is exact at every t: zero loss.
    Under the opposite convention (t = 1 is data) the same velocity would be wrong."""
    batch = make_batch(tiny_policy, b=6)
    a = tiny_policy.action_norm.normalize(batch["actions"])
    tiny_policy.velocity = lambda x_t, t, e: (x_t - a) / t[:, None, None]
    batch["time"] = torch.tensor([1.0, 0.9, 0.5, 0.2, 0.05, 0.001])
    assert tiny_policy(batch).max().item() < 1e-8
    batch["noise"] = torch.randn_like(a)
    batch["time"] = torch.tensor([1.0, 0.9, 0.8, 0.2, 0.1, 0.05])  # t = 0.5 is symmetric
    tiny_policy.velocity = lambda x_t, t, e: (a - x_t) / (1 - t[:, None, None])  # t = 1 is data
    assert tiny_policy(batch)[1:].min().item() > 1e-3


def test_euler_sampling_recovers_point_mass_with_exact_velocity(tiny_policy):
    target = torch.tensor([[0.3, -1.2, 0.7]]).expand(4, 3)
    batch = make_batch(tiny_policy, b=5)
    tiny_policy.velocity = _exact_velocity_for(target)
    out = tiny_policy.sample_actions(batch, generator=torch.Generator().manual_seed(1))
    assert out.shape == (5, 4, 3)
    assert torch.allclose(out, target.expand(5, 4, 3), atol=1e-5)


def test_training_on_a_point_mass_makes_sampling_return_it(tiny_policy):
    torch.manual_seed(0)
    target = torch.tensor([0.5, -0.25, 1.0])
    batch = make_batch(tiny_policy, b=64)
    batch["actions"] = target.expand(64, 4, 3).clone()
    tiny_policy.action_norm.mean.zero_()
    optimizer = torch.optim.Adam(tiny_policy.parameters(), lr=3e-3)
    g = torch.Generator().manual_seed(0)
    for _ in range(400):
        loss = tiny_policy(batch, generator=g).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    out = tiny_policy.sample_actions(batch, generator=g)
    assert (out - target).abs().max().item() < 0.2


def test_time_is_beta_1_5_1_scaled(tiny_policy):
    t = tiny_policy.sample_time(200_000, torch.Generator().manual_seed(0))
    assert t.min() >= 0.001 and t.max() <= 1.0
    assert abs(t.mean().item() - (0.001 + 0.999 * 0.6)) < 0.005  # Beta(1.5, 1) has mean 0.6
    assert abs((t < 0.5).float().mean().item() - 0.5**1.5) < 0.005  # CDF x^1.5


def test_padded_actions_do_not_count(tiny_policy):
    """The loss averages over valid chunk steps only: with a zero velocity it is |noise - a|^2
    over the first two steps."""
    batch = make_batch(tiny_policy, b=4)
    batch["time"] = torch.full((4,), 0.5)
    batch["noise"] = torch.randn(4, 4, 3)
    batch["action_mask"] = torch.tensor([[True, True, False, False]] * 4)
    tiny_policy.velocity = lambda x_t, t, e: torch.zeros_like(x_t)
    a = tiny_policy.action_norm.normalize(batch["actions"])
    expected = ((batch["noise"] - a)[:, :2] ** 2).mean(dim=(1, 2))
    assert torch.allclose(tiny_policy(batch), expected)
    assert not torch.allclose(((batch["noise"] - a) ** 2).mean(dim=(1, 2)), expected)


def test_normalizer_floor_and_clip():
    from policies import Normalizer

    norm = Normalizer(2, std_floor=0.01, clip=5.0)
    norm.fit(torch.tensor([[0.0, 1.0], [0.0, 3.0]]))  # first dim constant in the foundation data
    assert abs(norm.std[0].item() - 0.01) < 1e-7
    out = norm.normalize(torch.tensor([[0.5, 2.0]]))  # would be 50 without the clip
    assert out[0, 0].item() == 5.0 and abs(out[0, 1].item()) < 1e-6


def test_normalization_statistics_travel_with_the_checkpoint(tiny_policy):
    from policies import FlowMatchingPolicy

    tiny_policy.state_norm.fit(torch.randn(100, 5) * 3 + 1)
    clone = FlowMatchingPolicy(tiny_policy.config)
    clone.load_state_dict(tiny_policy.state_dict())
    assert torch.equal(clone.state_norm.std, tiny_policy.state_norm.std)
