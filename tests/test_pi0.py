"""The pi0 policy (block mask, prefix cache, per-sample loss), the policy registry, and the
device setting; the tiny pi0 end to end and under every method."""

import json
import pickle
import re
import subprocess
import sys
from multiprocessing import get_context
from pathlib import Path

import numpy as np
import pytest
import torch

from harness.common.device import resolve_device
from harness.common.errors import RetainError
from harness.config.benchmark import class_label, resolve
from harness.data.datasets import TrainingData, chunk_episodes, instruction_entries
from harness.data.demos import Episode
from harness.data.prepare import prepare_data
from harness.run.cli import main
from harness.train.trainer import TrainSettings, train_stage
from methods import TaskContext, get_method, method_names
from policies import Pi0Config, Pi0Policy, get_policy, make_config, policy_for_config
from policies.pi0.modeling import block_attention_mask
from policies.text_encoder import MAX_TOKENS, tokenize_instructions
from suites import get_suite

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "adding-a-policy.md"
CAMERAS = ("agentview_rgb", "eye_in_hand_rgb")


def _policy(cameras=CAMERAS, seed=0):
    torch.manual_seed(seed)
    return Pi0Policy(Pi0Config(5, 3, size="tiny", chunk_size=4, n_action_steps=2,
                               image_keys=cameras, image_size=24))


def _batch(b=4, seed=0, cameras=CAMERAS):
    g = torch.Generator().manual_seed(seed)
    texts = ["push the puck to the goal", "open the drawer"] * b
    batch = {"state": torch.randn(b, 5, generator=g), "actions": torch.randn(b, 4, 3, generator=g),
             "instruction": torch.randn(b, 384, generator=g),
             "instruction_tokens": torch.from_numpy(tokenize_instructions(texts[:b]))}
    for key in cameras:
        batch[key] = torch.randint(0, 256, (b, 24, 24, 3), dtype=torch.uint8, generator=g)
    return batch


def test_forward_returns_a_per_sample_loss_that_predicted_velocity_explains():
    policy, batch = _policy(), _batch()
    assert policy(batch, generator=torch.Generator().manual_seed(0)).shape == (4,)
    g = torch.Generator().manual_seed(1)
    batch["noise"], batch["time"] = torch.randn(4, 4, 3, generator=g), torch.rand(4, generator=g)
    actions = policy.action_norm.normalize(batch["actions"])
    target = batch["noise"] - actions
    expected = ((policy.predicted_velocity(batch) - target) ** 2).mean(dim=(1, 2))
    assert torch.allclose(policy(batch), expected)
    batch["action_mask"] = torch.tensor([[True, True, False, False]] * 4)
    masked = ((policy.predicted_velocity(batch) - target) ** 2)[:, :2].mean(dim=(1, 2))
    assert torch.allclose(policy(batch), masked)


def test_the_block_mask_lets_the_prefix_see_only_itself():
    valid = torch.tensor([[True, True, False, True]])  # a padding token at 2
    mask = block_attention_mask(valid, 3)[0]
    assert not mask[:4, 4:].any()  # the prefix never attends to actions
    assert mask[:, [0, 1, 3]].all()  # everyone sees the valid prefix
    assert not mask[:, 2].any()  # nobody sees padding
    assert mask[4:, 4:].all()  # actions see each other


def test_perturbing_an_action_token_never_changes_the_prefix():
    policy, batch = _policy(), _batch()
    x = torch.randn(4, 4, 3)
    t = torch.rand(4)
    states, velocity = policy.joint_velocity(batch, x, t)
    perturbed = x.clone()
    perturbed[:, 2] += 10.0
    states2, velocity2 = policy.joint_velocity(batch, perturbed, t)
    assert len(states) == policy.config.dims.depth - 1
    assert all(torch.equal(a, b) for a, b in zip(states, states2))
    assert not torch.allclose(velocity, velocity2)  # the actions themselves do see the change
    x.requires_grad_(True)  # and no gradient flows from the prefix back to the actions
    states, _ = policy.joint_velocity(batch, x, t)
    (grad,) = torch.autograd.grad(sum(s.sum() for s in states), x)
    assert torch.count_nonzero(grad) == 0


def test_sampling_with_the_cached_prefix_equals_sampling_without_it():
    policy, batch = _policy(), _batch()
    noise = torch.randn(4, 4, 3, generator=torch.Generator().manual_seed(3))
    cached = policy.sample_actions(batch, noise=noise)
    assert cached.shape == (4, 4, 3)
    assert torch.allclose(cached, policy.sample_actions_without_cache(batch, noise), atol=1e-5)
    t = torch.rand(4)
    context = policy.encode_observation(batch)
    assert torch.allclose(policy.velocity(noise, t, context),
                          policy.joint_velocity(batch, noise, t)[1], atol=1e-5)


def test_language_tokens_reach_the_prefix():
    policy, batch = _policy(cameras=()), _batch(cameras=())
    tokens, valid = policy.prefix_tokens(batch)
    n_words = (batch["instruction_tokens"][0] != 0).sum().item()
    assert tokens.shape[1] == MAX_TOKENS + 1 and valid[0].sum().item() == n_words + 1
    noise = torch.randn(4, 4, 3)
    other = dict(batch, instruction_tokens=batch["instruction_tokens"].flip(0))
    assert not torch.allclose(policy.sample_actions(batch, noise=noise),
                              policy.sample_actions(other, noise=noise))


def test_token_ids_are_cached_and_travel_with_the_samples(tmp_path):
    ids = tokenize_instructions(["close the window"], tmp_path)
    assert ids.shape == (1, MAX_TOKENS) and ids[0, 0] == 101 and (ids[0] == 0).any()
    assert len(list(tmp_path.glob("*.npy"))) == 1
    assert np.array_equal(tokenize_instructions(["close the window"], tmp_path), ids)
    episode = Episode(np.zeros((3, 2), np.float32), {"state": np.zeros((3, 5), np.float32)}, 0)
    a = chunk_episodes([episode], "a", np.zeros(384, np.float32), 4, ids[0])
    b = chunk_episodes([episode], "b", np.ones(384, np.float32), 4, ids[0][:5])
    both = TrainingData.concat([a, b])  # tables of two widths: padded to the longer
    batch = both.batch(torch.tensor([0, 4]))
    assert torch.equal(batch["instruction_tokens"][0], torch.from_numpy(ids[0]))
    assert batch["instruction_tokens"][1].tolist() == ids[0][:5].tolist() + [0] * (MAX_TOKENS - 5)
    entries = instruction_entries({"a": {"instruction": np.zeros(384), "instruction_tokens": ids[0]}},
                                  ["a", "a"])
    assert entries["instruction_tokens"].shape == (2, MAX_TOKENS)


def _synthetic(n, task, seed):
    g = torch.Generator().manual_seed(seed)
    ids = torch.from_numpy(tokenize_instructions([f"do task {task}"]))
    return TrainingData({"state": torch.randn(n, 5, generator=g)},
                        torch.randn(n, 4, 3, generator=g), torch.ones(n, 4, dtype=torch.bool),
                        torch.zeros(n, dtype=torch.long), torch.randn(1, 384, generator=g), [task],
                        ids)


@pytest.mark.parametrize("name", method_names())
def test_every_method_trains_the_tiny_pi0(name):
    policy = _policy(cameras=())
    foundation, task = _synthetic(64, "foundation", 1), _synthetic(64, "task", 2)
    policy.state_norm.fit(foundation.obs["state"])
    policy.action_norm.fit(foundation.actions.flatten(0, 1))
    method = get_method(name)()
    method.after_task(TaskContext(0, "foundation", foundation, policy, 0.5, 0))
    before = {n: p.detach().clone() for n, p in policy.named_parameters()}
    result = train_stage(TaskContext(1, "task", task, policy, 0.5, 3), method,
                         TrainSettings(3, 16, 1e-3), torch.Generator().manual_seed(0))
    assert np.isfinite(result.final_loss)
    assert any(not torch.equal(p, before[n]) for n, p in policy.named_parameters())


def test_the_tiny_pi0_trains_end_to_end(tmp_path):
    args = ["bench", "PROFILE=tiny", "METHOD=sft", "policy=pi0", f"results_dir={tmp_path}/results",
            f"cache_dir={tmp_path}/cache", "progress=false", "eval_workers=1"]
    assert main(args) == 0
    out = tmp_path / "results/mw-quick-tiny/sft[policy=pi0]/seed0"  # a non-default policy: own dir
    run = json.loads((out / "metrics.json").read_text())
    assert 0.0 <= run["metrics"]["retention"] <= 1.0
    losses = [s["train_loss"] for s in run["stages"]]
    assert all(np.isfinite(losses)) and len(losses) == 3
    layers = (out / "updates_per_layer.csv").read_text()
    assert "expert_layers.0.qkv.weight" in layers and "language_proj.weight" in layers
    cfg = resolve(args[1:])  # the cached demos again: their batches carry the token ids
    data = prepare_data(cfg, get_suite(cfg.suite))
    task = cfg.stream_tasks[0]
    ids = tokenize_instructions([get_suite(cfg.suite).instruction(task)])[0]
    row = data.train[task].batch(torch.tensor([0]))["instruction_tokens"][0].numpy()
    assert np.array_equal(row, ids[:len(row)]) and (row != 0).sum() == (ids != 0).sum()
    assert np.array_equal(data.instructions[task]["instruction_tokens"], row)


@pytest.mark.parametrize("args, message", [
    (["policy=pi1"], "unknown policy 'pi1'; valid: lerobot_pi0, lerobot_pi05, lerobot_smolvla, mlp, pi0"),
    (["policy=pi0", "policy_size=huge"], "unknown policy size 'huge' for Pi0Config; valid: tiny, default, large"),
    (["policy_size=huge"], "valid: tiny, default, large, paper"),
    (["policy=json:NoSuchClass"], "has no class 'NoSuchClass'"),
    (["policy=collections:OrderedDict"], "is not a policy"),
    (["device=gpu"], "unknown device 'gpu'; valid: cpu, cuda, auto"),
])
def test_a_bad_policy_size_or_device_is_a_one_line_error(tmp_path, capsys, args, message):
    assert main(["bench", "PROFILE=tiny", f"results_dir={tmp_path}", f"cache_dir={tmp_path}",
                 *args]) == 2
    err = capsys.readouterr().err
    assert message in err and err.strip().count("\n") == 0
    assert not any(tmp_path.iterdir())  # refused before anything was written


def test_device_resolution():
    assert resolve_device("cpu", cuda_available=True).type == "cpu"
    assert resolve_device("auto", cuda_available=False).type == "cpu"
    assert resolve_device("auto", cuda_available=True).type == "cuda"
    assert resolve_device("cuda:1", cuda_available=True) == torch.device("cuda:1")
    with pytest.raises(RetainError, match="no CUDA GPU"):
        resolve_device("cuda", cuda_available=False)


def test_registry_builds_both_policies_from_the_harness_fields():
    fields = dict(state_dim=5, action_dim=3, size="tiny", chunk_size=4, n_action_steps=2,
                  image_keys=(), image_size=84)
    for name in ("mlp", "pi0"):
        config = make_config(name, **fields)
        policy = policy_for_config(pickle.loads(pickle.dumps(config)))
        assert type(policy) is get_policy(name) and policy.config == config


def _doc_example(tmp_path) -> Path:
    code = re.search(r"```python\n(.*?)```", DOC.read_text(), re.S).group(1)
    path = tmp_path / "plugin" / "my_policy.py"
    path.parent.mkdir()
    path.write_text(code)
    return path


def _rebuild_in_a_fresh_process(config_bytes):
    from policies import policy_for_config

    return type(policy_for_config(pickle.loads(config_bytes))).__name__


def test_a_users_policy_loads_by_file_path_here_and_in_spawned_workers(tmp_path):
    path = _doc_example(tmp_path)
    cls = get_policy(f"{path}:MyPolicy")
    config = cls.Config(state_dim=5, action_dim=3, size="tiny", chunk_size=4, n_action_steps=2)
    policy = cls(config)
    assert policy(_batch(cameras=())).shape == (4,)
    with get_context("spawn").Pool(1) as pool:  # as evaluation workers rebuild it
        assert pool.apply(_rebuild_in_a_fresh_process, (pickle.dumps(config),)) == "MyPolicy"
    with pytest.raises(ValueError, match="unknown policy size 'huge'.*valid: tiny, default"):
        cls.Config(state_dim=5, action_dim=3, size="huge")


def test_the_documented_policy_runs_a_tiny_benchmark_as_a_user_would(tmp_path):
    path = _doc_example(tmp_path)
    proc = subprocess.run(
        [sys.executable, "-m", "harness", "bench", "PROFILE=tiny", f"policy={path}:MyPolicy",
         f"results_dir={tmp_path}/results", f"cache_dir={tmp_path}/cache", "progress=false",
         "eval_workers=1"], capture_output=True, text=True, timeout=300, cwd=ROOT)
    assert proc.returncode == 0, proc.stderr[-2000:]
    # labelled by the policy's class and a hash of its path, not by the whole path
    (out,) = (tmp_path / "results/mw-quick-tiny").glob("sft*/seed0")
    assert re.fullmatch(r"sft\[policy=MyPolicy@[0-9a-f]{6}\]", out.parent.name), out.parent.name
    assert out.parent.name == f"sft[policy={class_label(f'{path}:MyPolicy')}]"
    layers = (out / "updates_per_layer.csv").read_text()
    assert "velocity_net.0.weight" in layers


def test_a_class_given_by_file_path_gets_a_short_label_that_never_collides(tmp_path):
    one, two = tmp_path / "a" / "my_policy.py", tmp_path / "b" / "my_policy.py"
    labels = {class_label(f"{one}:MyPolicy"), class_label(f"{two}:MyPolicy")}
    assert len(labels) == 2 and all(re.fullmatch(r"MyPolicy@[0-9a-f]{6}", x) for x in labels)
    assert class_label(f"{one}:MyPolicy") == class_label(f"{tmp_path}/b/../a/my_policy.py:MyPolicy")
    for spec in ("pi0", "my_pkg.my_policy:MyPolicy"):  # names and modules read well as they are
        assert class_label(spec) == spec
