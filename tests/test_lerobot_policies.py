"""LeRobot's PI0, PI0.5 and SmolVLA as Retain policies (policies/lerobot): the loss every method
sees is LeRobot's own, a checkpoint folder round-trips and never loads as a random model, and a
checkpoint that does not fit the suite is refused at plan time in one line."""

import json
from pathlib import Path

import pytest
import torch
from safetensors.torch import load_file, save_file

from harness.common.errors import RetainError
from harness.perf import gpu_check
from harness.run.plan import plan
from policies import get_policy
from policies.base import noise_shape
from policies.lerobot.checkpoint import CheckpointError, checkpoint_folder
from suites.base import CAMERA_KEYS

KINDS = ["lerobot_pi0", "lerobot_pi05", "lerobot_smolvla"]
TEXTS = ("put the bowl on the plate", "open the top drawer")
B, S, A, H, PX = 5, 9, 7, 4, 32


def build(kind, **fields):
    cls = get_policy(kind)
    settings = {"state_dim": S, "action_dim": A, "size": "tiny", "chunk_size": H,
                "n_action_steps": H, "image_keys": CAMERA_KEYS, "image_size": PX,
                "instructions": TEXTS, **fields}
    torch.manual_seed(0)
    return cls(cls.Config(**settings))


def batch_for(policy, seed=0):
    g = torch.Generator().manual_seed(seed)
    c = policy.config
    batch = {"state": torch.randn(B, c.state_dim, generator=g),
             "actions": torch.randn(B, c.chunk_size, c.action_dim, generator=g),
             "action_mask": torch.ones(B, c.chunk_size, dtype=torch.bool),
             "instruction_id": torch.tensor([0, 1, 0, 1, 1])}
    batch["action_mask"][0, -2:] = False  # a chunk past its episode's end
    for key in c.image_keys:
        batch[key] = torch.randint(0, 256, (B, c.image_size, c.image_size, 3), dtype=torch.uint8,
                                   generator=g)
    return batch


@pytest.fixture(scope="module")
def policies():
    out = {}
    for kind in KINDS:
        policy = build(kind)
        batch = batch_for(policy)
        policy.state_norm.fit(batch["state"])
        policy.action_norm.fit(batch["actions"].flatten(0, 1))
        out[kind] = policy
    return out


@pytest.mark.parametrize("kind", KINDS)
def test_the_loss_is_lerobots_own_at_the_same_batch_and_noise(policies, kind):
    policy = policies[kind]
    batch = batch_for(policy, seed=1)
    lerobot_batch = policy._lerobot_batch(batch, actions=True)
    torch.manual_seed(7)  # LeRobot draws its noise, then its times, from torch's global RNG
    expected, _ = policy.model.forward(lerobot_batch, reduction="none")
    torch.manual_seed(7)
    noise = torch.normal(0.0, 1.0, size=noise_shape(policy, B))
    time = torch.distributions.Beta(torch.tensor(1.5), torch.tensor(1.0)).sample((B,)) * 0.999 + 0.001
    ours = policy({**batch, "noise": noise, "time": time})
    assert ours.shape == (B,)
    assert torch.equal(ours, expected)
    other = policy({**batch, "noise": noise, "time": time.flip(0)})
    assert not torch.allclose(other, expected)  # the times reached LeRobot's model


@pytest.mark.parametrize("kind", ["lerobot_pi0", "lerobot_pi05"])
def test_predicted_velocity_is_the_velocity_the_loss_is_taken_of(policies, kind):
    policy = policies[kind]  # PI0's loss ignores the padding mask: a plain mean over H x A
    batch = batch_for(policy, seed=2)
    g = torch.Generator().manual_seed(3)
    batch["noise"], batch["time"] = torch.randn(noise_shape(policy, B), generator=g), policy.sample_time(B, g)
    velocity = policy.predicted_velocity(batch)
    lerobot_batch = policy._lerobot_batch(batch, actions=True)
    target = batch["noise"][..., :A] - lerobot_batch["action"]
    assert velocity.shape == (B, H, A)
    assert torch.allclose(((velocity - target) ** 2).mean(dim=(1, 2)), policy(batch), atol=1e-6)


def test_noise_of_the_suites_width_only_is_refused(policies):
    policy = policies["lerobot_pi0"]
    batch = batch_for(policy)
    with pytest.raises(ValueError, match=r"expected \(5, 4, 32\)"):
        policy({**batch, "noise": torch.randn(B, H, A), "time": torch.rand(B)})


@pytest.mark.parametrize("kind", KINDS)
def test_a_checkpoint_folder_round_trips(policies, kind, tmp_path):
    policy = policies[kind]
    folder = policy.save_folder(tmp_path / "ckpt")
    batch = batch_for(policy, seed=4)
    g = torch.Generator().manual_seed(5)
    batch["noise"], batch["time"] = torch.randn(noise_shape(policy, B), generator=g), policy.sample_time(B, g)
    loaded = build(kind, path=str(folder), features=tuple(policy.features.items()))
    assert policy.state_dict().keys() == loaded.state_dict().keys()
    assert all(torch.equal(a, b) for a, b in zip(policy.state_dict().values(),
                                                 loaded.state_dict().values()))
    assert torch.equal(policy(batch), loaded(batch))
    assert torch.equal(policy.sample_actions(batch, noise=batch["noise"]),
                       loaded.sample_actions(batch, noise=batch["noise"]))
    # one folder: what a reduced size needs is inside it, named relative to it
    names = {p.name for p in folder.iterdir()}
    assert {"config.json", "model.safetensors", "policy_preprocessor.json"} <= names
    if kind == "lerobot_smolvla":
        assert json.loads((folder / "config.json").read_text())["vlm_model_name"] == "vlm"
        assert (folder / "vlm" / "config.json").is_file()
    else:
        assert {"tokenizer", "retain_architecture.json"} <= names


@pytest.fixture(scope="module")
def saved_pi0(tmp_path_factory, policies):
    return policies["lerobot_pi0"].save_folder(tmp_path_factory.mktemp("pi0") / "ckpt")


def linked_without(saved: Path, folder: Path, left_out: str) -> Path:
    """`folder` holding links to every file of the checkpoint `saved` but `left_out`."""
    folder.mkdir()
    for p in saved.iterdir():
        if p.name != left_out:
            (folder / p.name).symlink_to(p)
    return folder


def _load(folder):
    features = (("state", "observation.state"),
                *((k, f"observation.images.{k}") for k in CAMERA_KEYS))
    return build("lerobot_pi0", path=str(folder), features=features)


def test_a_missing_weights_file_is_one_line_never_a_random_model(saved_pi0, tmp_path):
    folder = linked_without(saved_pi0, tmp_path / "no-weights", "model.safetensors")
    with pytest.raises(CheckpointError) as err:
        _load(folder)
    assert "has no model.safetensors" in str(err.value) and "\n" not in str(err.value)


def test_weights_that_do_not_fit_are_an_error_not_a_random_model(saved_pi0, tmp_path):
    folder = linked_without(saved_pi0, tmp_path / "bad-weights", "model.safetensors")
    weights = load_file(saved_pi0 / "model.safetensors")
    name = next(k for k in weights if k.endswith("state_proj.weight"))
    weights[name] = torch.zeros(weights[name].shape[0], weights[name].shape[1] + 1)  # wrong shape
    save_file(weights, folder / "model.safetensors")
    with pytest.raises(CheckpointError) as err:
        _load(folder)
    assert "did not load" in str(err.value) and "\n" not in str(err.value)
    del weights[name]  # a weight the file lacks stays random: refused too
    save_file(weights, folder / "model.safetensors")
    with pytest.raises(CheckpointError, match="not in model.safetensors"):
        _load(folder)


@pytest.mark.parametrize("path, named", [
    ("lerobot/pi0_base", "the hub is off"),
    ("/no/such/folder", "no such folder"),
])
def test_an_unreachable_hub_or_a_bad_path_is_one_line(path, named, monkeypatch):
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    checkpoint_folder.cache_clear()
    with pytest.raises(CheckpointError) as err:
        checkpoint_folder(path)
    assert named in str(err.value) and "\n" not in str(err.value)


@pytest.mark.parametrize("kind", KINDS)
def test_the_published_size_without_the_hub_is_one_line(kind, monkeypatch):
    """Before any weight is built: PI0's published size is 4B parameters (16 GB in float32)."""
    import lerobot.policies.factory as factory

    built = []
    monkeypatch.setenv("HF_HUB_OFFLINE", "1")
    if kind != "lerobot_smolvla":  # SmolVLA asks the hub inside its constructor, first thing
        monkeypatch.setattr(factory, "get_policy_class", lambda name: built.append)
    with pytest.raises(CheckpointError) as err:
        build(kind, size="default")
    assert built == []
    assert "needs files from the hub" in str(err.value) and "\n" not in str(err.value)


# -- the plan: a checkpoint against the suite --------------------------------------------------

@pytest.fixture(scope="module")
def mw_checkpoint(tmp_path_factory):
    """A tiny PI0 for Meta-World's shapes (39-D state, 4-D actions), chunk 5 of which 3 run."""
    policy = build("lerobot_pi0", state_dim=39, action_dim=4, chunk_size=5, n_action_steps=3)
    return policy.save_folder(tmp_path_factory.mktemp("mw") / "ckpt")


def _plan(*args):
    return plan(["PROFILE=tiny", "METHOD=sft", "policy=lerobot_pi0", *args])


def test_the_checkpoint_sets_the_chunk_and_the_cameras(mw_checkpoint):
    cfg = _plan(f"policy_path={mw_checkpoint}").cfg
    assert (cfg.chunk_size, cfg.n_action_steps, cfg.cameras, cfg.image_size) == (5, 3, True, PX)
    with pytest.raises(RetainError) as err:
        _plan(f"policy_path={mw_checkpoint}", "chunk_size=4")
    assert "chunk_size=4 conflicts" in str(err.value) and "whose chunk_size is 5" in str(err.value)


def test_a_checkpoint_that_does_not_fit_the_suite_is_one_line(mw_checkpoint, tmp_path):
    with pytest.raises(RetainError) as err:
        _plan("BENCH=libero-quick", f"policy_path={mw_checkpoint}")
    assert "acts in 4 dimensions; suite 'libero' takes 7" in str(err.value)
    config = json.loads((mw_checkpoint / "config.json").read_text())
    renamed = linked_without(mw_checkpoint, tmp_path / "renamed", "config.json")
    features = config["input_features"]
    features["observation.images.top_view"] = features.pop("observation.images.agentview_rgb")
    (renamed / "config.json").write_text(json.dumps(config))
    with pytest.raises(RetainError) as err:
        _plan(f"policy_path={renamed}")
    assert "'observation.images.top_view' is none of the suite's cameras" in str(err.value)
    assert "lerobot_keys=agentview_rgb:observation.images.top_view" in str(err.value)
    cfg = _plan(f"policy_path={renamed}", "lerobot_keys=agentview_rgb:observation.images.top_view").cfg
    assert cfg.cameras
    with pytest.raises(RetainError, match="takes no policy_path"):
        plan(["PROFILE=tiny", "METHOD=sft", f"policy_path={mw_checkpoint}"])


@pytest.mark.slow  # a minute: make test runs LeRobot end to end in tests/test_lerobot_checkpoint_cli.py
def test_every_method_trains_resumes_and_trains_on_with_lerobots_pi0(tmp_path):
    """All twelve methods (and ConSFT's variants): a stage, its checkpoint, the next stage."""
    result = gpu_check.check_methods(torch.device("cpu"), gpu_check.CPU_SMOKE, tmp_path,
                                     "lerobot_pi0")
    assert result.passed, result.line()
    assert result.figure.startswith("15 of 15 methods")


def test_lora_adapts_lerobots_own_peft_targets(policies):
    from methods.lora import LoRA

    names = LoRA().target_modules(policies["lerobot_pi0"])
    assert "model.model.state_proj" in names and "model.model.action_out_proj" in names
    assert any(n.endswith("gemma_expert.model.layers.0.self_attn.q_proj") for n in names)
    assert not any("vision_tower" in n or "language_model" in n for n in names)


def test_the_checkpoint_folder_identity_is_its_weights(saved_pi0, tmp_path):
    from policies.lerobot.checkpoint import checkpoint_identity

    copy = linked_without(saved_pi0, tmp_path / "copy", "model.safetensors")
    weights = load_file(saved_pi0 / "model.safetensors")
    save_file(weights, copy / "model.safetensors")
    assert checkpoint_identity(str(copy)) == checkpoint_identity(str(saved_pi0))
    name = next(iter(weights))
    weights[name] = weights[name] + 1
    save_file(weights, copy / "model.safetensors")
    assert checkpoint_identity(str(copy)) != checkpoint_identity(str(saved_pi0))
