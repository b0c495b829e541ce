import os

os.environ.setdefault("MUJOCO_GL", "egl")
os.environ.setdefault("HF_HUB_OFFLINE", "1")
os.environ.setdefault("TRANSFORMERS_OFFLINE", "1")

import pytest  # noqa: E402
import torch  # noqa: E402

torch.set_num_threads(1)


@pytest.fixture
def tiny_policy():
    from policies import FlowMatchingConfig, FlowMatchingPolicy

    torch.manual_seed(0)
    return FlowMatchingPolicy(FlowMatchingConfig(state_dim=5, action_dim=3, size="tiny", chunk_size=4,
                                                 n_action_steps=2))


def make_batch(policy, b=8, seed=0):
    g = torch.Generator().manual_seed(seed)
    c = policy.config
    return {
        "state": torch.randn(b, c.state_dim, generator=g),
        "instruction": torch.randn(b, c.instruction_dim, generator=g),
        "actions": torch.randn(b, c.chunk_size, c.action_dim, generator=g),
    }


@pytest.fixture
def forbid_retraining(monkeypatch):
    """Call it to make generating demos or training any stage fail from then on: for checks
    that a rerun only reuses what the first run made."""

    def fail(*args, **kwargs):
        raise AssertionError("work was redone instead of reused")

    def forbid() -> None:
        import harness.data.prepare

        for target in ("harness.data.demos.generate_demos", "harness.protocol.foundation.train_stage",
                       "harness.protocol.stream.train_stage"):
            monkeypatch.setattr(target, fail)
        find_missing = harness.data.prepare.missing_demo_jobs

        def none_missing(*args):  # demo files made in worker processes would escape the patches
            missing = find_missing(*args)
            if missing:
                fail()
            return missing

        monkeypatch.setattr(harness.data.prepare, "missing_demo_jobs", none_missing)

    return forbid
