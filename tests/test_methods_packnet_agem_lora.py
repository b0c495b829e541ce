"""PackNet, A-GEM and LoRA: each one's defining property, checkpoint round trips, and one tiny
end-to-end run of all three through `python -m harness bench`."""

import io
import json

import pytest
import torch

from harness.evaluate.stages import load_checkpoint
from harness.perf.throughput import ACTION_DIM, STATE_DIM, synthetic_data
from harness.run.cli import main
from harness.train.trainer import TrainSettings, train_stage
from methods import TaskContext, get_method
from methods.agem import AGEM, AGEMConfig
from methods.base import snapshot
from methods.lora import LoRA, LoRAConfig
from methods.packnet import FREE, PackNet, PackNetConfig, prunable_weights
from policies import FlowMatchingConfig, FlowMatchingPolicy

# weight decay on purpose: it would move weights that get no gradient
SETTINGS = TrainSettings(steps=6, batch_size=16, lr=1e-2, weight_decay=0.1)
FOUNDATION = synthetic_data(64, 0, "foundation-task")


def _policy() -> FlowMatchingPolicy:
    torch.manual_seed(0)
    return FlowMatchingPolicy(FlowMatchingConfig(STATE_DIM, ACTION_DIM, size="tiny"))


def _ctx(policy, stage: int) -> TaskContext:
    if stage == 0:
        return TaskContext(0, "foundation", FOUNDATION, policy, 0.05, SETTINGS.steps)
    data = synthetic_data(64, stage, f"task{stage}")
    return TaskContext(stage, f"task{stage}", data, policy, 0.05, SETTINGS.steps)


def _train(method, policy, stage: int, after_step=None) -> None:
    torch.manual_seed(stage)
    train_stage(_ctx(policy, stage), method, SETTINGS, torch.Generator().manual_seed(stage),
                after_step=after_step)


def _stages(method, policy, last: int) -> None:
    """The runner's order: after_task on the foundation, then stages 1..last."""
    method.after_task(_ctx(policy, 0))
    for stage in range(1, last + 1):
        _train(method, policy, stage)


# -- PackNet -----------------------------------------------------------------------------------


def test_packnet_keeps_each_tasks_weights_and_frees_the_rest():
    policy, method = _policy(), PackNet(PackNetConfig(post_prune_fraction=0.5))
    method.after_task(_ctx(policy, 0))
    weights = prunable_weights(policy)
    for n, p in weights.items():
        kept = method.owner[n] == 0
        assert kept.sum().item() == p.numel() - round(0.75 * p.numel())
        assert (p[~kept] == 0).all()  # freed weights are zeroed
        assert p[kept].abs().min() > 0
    after_foundation = snapshot(policy)
    _train(method, policy, 1)
    for n, p in policy.named_parameters():
        if n in weights:
            kept = method.owner[n] == 0
            assert torch.equal(p[kept], after_foundation[n][kept]), n
            mine = method.owner[n] == 1
            assert mine.any() and (p[mine] != 0).all(), n  # task 1 trained its share
        else:  # biases and norms keep the foundation's values
            assert torch.equal(p, after_foundation[n]), n
    assert all(p.requires_grad for p in policy.parameters())  # the policy as found


def test_packnet_frozen_weights_stay_bit_equal_over_later_tasks():
    policy, method = _policy(), PackNet(PackNetConfig(post_prune_fraction=0.5))
    _stages(method, policy, 1)
    after_task1 = snapshot(policy)
    owner = {n: o.clone() for n, o in method.owner.items()}
    _train(method, policy, 2)
    for n, o in owner.items():
        kept = (o == 0) | (o == 1)
        assert torch.equal(policy.get_parameter(n)[kept], after_task1[n][kept]), n
        assert torch.equal(method.owner[n][kept], o[kept])


def test_packnet_evaluation_view_zeroes_later_tasks_weights_and_restores_them():
    policy, method = _policy(), PackNet(PackNetConfig(post_prune_fraction=0.5))
    _stages(method, policy, 2)
    before = snapshot(policy)
    stream = ["task1", "task2", "task3"]
    for task, level in (("foundation-task", 0), ("task1", 1), ("task2", 2), ("task3", 3)):
        with method.evaluation_view(policy, task, stream):
            for n, p in prunable_weights(policy).items():
                o = method.owner[n]
                visible = (o != FREE) & (o <= level)
                assert torch.equal(p[visible], before[n][visible])
                assert (p[~visible] == 0).all()
                if level >= 2:  # the last trained task, and any later one, sees everything
                    assert torch.equal(p, before[n])
        assert all(torch.equal(p, before[n]) for n, p in policy.named_parameters())


def test_packnet_rejects_a_prune_ratio_outside_0_1():
    from harness.common.errors import RetainError
    from harness.protocol.stream import make_method

    with pytest.raises(RetainError, match=r"bad value 1.0 for prune_ratio .*: expected a number "
                                          r"in \(0, 1\)"):
        make_method(PackNet, {"prune_ratio": "1.0"})


# -- A-GEM -------------------------------------------------------------------------------------


def _agem_ready():
    policy, method = _policy(), AGEM(AGEMConfig(memory_batch=16))
    method.after_task(_ctx(policy, 0))
    method.before_task(_ctx(policy, 1))
    params = [p for p in policy.parameters() if p.requires_grad]
    state = method._generator.get_state()
    reference = method.reference_gradient(policy, params)
    method._generator.set_state(state)  # after_backward draws the same memory batch again
    return policy, method, params, reference


def _dot(a, b):
    return sum((x * y).sum() for x, y in zip(a, b)).item()


def test_agem_projects_a_conflicting_gradient_onto_the_memorys_half_space():
    policy, method, params, reference = _agem_ready()
    g = torch.Generator().manual_seed(1)
    for p, r in zip(params, reference):
        p.grad = -r + 0.3 * torch.randn(p.shape, generator=g) * r.abs().mean()
    raw = [p.grad.clone() for p in params]
    assert _dot(raw, reference) < 0
    method.after_backward(policy)
    projected = [p.grad for p in params]
    scale = _dot(reference, reference) ** 0.5 * _dot(raw, raw) ** 0.5
    assert _dot(projected, reference) >= -1e-5 * scale
    coefficient = _dot(raw, reference) / _dot(reference, reference)
    for g_raw, g_new, r in zip(raw, projected, reference):
        assert torch.allclose(g_new, g_raw - coefficient * r, rtol=1e-4, atol=1e-7)


def test_agem_leaves_a_gradient_that_agrees_with_the_memory_unchanged():
    policy, method, params, reference = _agem_ready()
    g = torch.Generator().manual_seed(2)
    for p, r in zip(params, reference):
        p.grad = r + 0.3 * torch.randn(p.shape, generator=g) * r.abs().mean()
    raw = [p.grad.clone() for p in params]
    assert _dot(raw, reference) > 0
    method.after_backward(policy)
    assert all(torch.equal(p.grad, r) for p, r in zip(params, raw))


def test_agem_memory_keeps_samples_of_every_finished_task():
    policy, method = _policy(), AGEM(AGEMConfig(memory_per_task=10))
    _stages(method, policy, 2)
    assert method.memory.task_names == ["foundation-task", "task1", "task2"]
    assert len(method.memory) == 30


# -- LoRA --------------------------------------------------------------------------------------


def test_lora_trains_adapters_only_and_merges_base_plus_scaled_b_a():
    policy, method = _policy(), LoRA(LoRAConfig(rank=2, alpha=6.0))
    targets = method.target_modules(policy)
    assert targets and all(n.startswith(("action_in", "blocks", "action_out")) for n in targets)
    before = snapshot(policy)
    seen = {}

    def capture(done):
        if done == SETTINGS.steps:  # the last step, before after_task merges
            seen["trainable"] = [n for n, p in policy.named_parameters() if p.requires_grad]
            for n in targets:
                layer = policy.get_submodule(n)
                seen[n] = (layer.base_layer.weight.detach().clone(),
                           layer.lora_A["default"].weight.detach().clone(),
                           layer.lora_B["default"].weight.detach().clone())

    _train(method, policy, 1, after_step=capture)
    assert seen["trainable"] and all(".lora_" in n for n in seen["trainable"])
    assert list(dict(policy.named_parameters())) == list(before)  # plain names again
    for n in targets:
        base, a, b = seen[n]
        assert torch.equal(base, before[f"{n}.weight"])  # training never touched the base
        assert b.abs().max() > 0
        merged = policy.get_submodule(n).weight
        assert torch.allclose(merged, base + b @ a * (6.0 / 2), atol=1e-6)
    for n, p in policy.named_parameters():
        if n.removesuffix(".weight") not in targets:
            assert torch.equal(p, before[n]), n  # untargeted layers and every bias untouched
    assert all(p.requires_grad for p in policy.parameters())


def test_lora_mid_task_policy_is_a_plain_merged_copy_that_evaluation_workers_load():
    """A learning-curve evaluation mid-task sends the policy's weights to workers that build a
    plain policy: LoRA's wrapped names (`base_layer`, `lora_A`) would not load there."""
    policy, method = _policy(), LoRA(LoRAConfig(rank=2, alpha=6.0))
    targets = method.target_modules(policy)
    seen = {}

    def capture(done):
        if done == 3:  # mid-task: the adapters are in place and trained a little
            plain = method.mid_task_policy(policy)
            seen["wrapped"] = list(policy.state_dict())
            worker_side = FlowMatchingPolicy(plain.config)
            worker_side.load_state_dict(plain.state_dict())  # strict, as a worker loads it
            seen["merged"] = {n: worker_side.get_submodule(n).weight.clone() for n in targets}
            seen["live"] = {n: policy.get_submodule(n).base_layer.weight
                            + policy.get_submodule(n).lora_B["default"].weight
                            @ policy.get_submodule(n).lora_A["default"].weight * 3.0 for n in targets}
            seen["trainable"] = [n for n, p in policy.named_parameters() if p.requires_grad]

    _train(method, policy, 1, after_step=capture)
    assert any(".lora_A." in n for n in seen["wrapped"])  # the copy left the training policy be
    assert seen["trainable"] and all(".lora_" in n for n in seen["trainable"])
    for n in targets:
        assert torch.allclose(seen["merged"][n], seen["live"][n].detach(), atol=1e-6), n
    assert method.mid_task_policy(policy) is policy  # after the task: nothing wrapped


def test_lora_target_selects_by_module_name_and_rejects_a_miss():
    policy = _policy()
    assert LoRA(LoRAConfig(target=".*")).target_modules(policy) == [
        n for n, m in policy.named_modules() if isinstance(m, torch.nn.Linear)]
    assert LoRA(LoRAConfig(target=r"blocks\.0\..*")).target_modules(policy) == [
        "blocks.0.mlp.0", "blocks.0.mlp.2"]
    with pytest.raises(ValueError, match="matches no Linear layer"):
        LoRA(LoRAConfig(target="decoder")).target_modules(policy)
    with pytest.raises(ValueError, match="not a regular expression"):
        LoRA(LoRAConfig(target="("))


# -- all three: a killed run resumes identically ------------------------------------------------


@pytest.mark.parametrize("name", ["packnet", "agem", "lora"])
def test_state_round_trips_through_a_checkpoint(name):
    cls = get_method(name)
    policy, method = _policy(), cls()
    _stages(method, policy, 1)
    buffer = io.BytesIO()
    torch.save({"policy": policy.state_dict(), "method": method.state_dict()}, buffer)
    buffer.seek(0)
    saved = torch.load(buffer, weights_only=False)
    resumed_policy, resumed = _policy(), cls()
    resumed_policy.load_state_dict(saved["policy"])
    resumed.load_state_dict(saved["method"])
    _train(method, policy, 2)
    _train(resumed, resumed_policy, 2)
    for (n, p), q in zip(policy.named_parameters(), resumed_policy.parameters()):
        assert torch.equal(p, q), n
    if name == "packnet":
        assert all(torch.equal(method.owner[n], resumed.owner[n]) for n in method.owner)


# -- end to end --------------------------------------------------------------------------------


def test_tiny_bench_runs_packnet_agem_and_lora(tmp_path):
    args = ["bench", "PROFILE=tiny", "METHOD=packnet,agem,lora", f"results_dir={tmp_path}/results",
            f"cache_dir={tmp_path}/cache", "progress=false", "eval_workers=1"]
    assert main(args) == 0
    runs = tmp_path / "results" / "mw-quick-tiny"
    for name in ("packnet", "agem", "lora"):
        report = json.loads((runs / name / "seed0" / "metrics.json").read_text())
        assert len(report["stages"]) == 3
        assert 0 <= report["metrics"]["retention"] <= 1
        assert report["metrics"]["update_relative_l2"] > 0
    # PackNet: from stage 1 on, the foundation tasks see only the weights stage 0 kept, and task 1
    # those up to stage 1, which never change again: their held-out losses and rollouts stop moving
    first, second = load_checkpoint(runs / "packnet/seed0/stages/stage_2.pt")["records"]
    for t in [t for t in first["heldout_loss"] if t != second["task"]]:
        assert first["heldout_loss"][t] == second["heldout_loss"][t], t
        assert first["episodes"][t] == second["episodes"][t], t
    assert first["heldout_loss"][second["task"]] != second["heldout_loss"][second["task"]]
