"""merge, distill and mas: their defining behaviours, their checkpoints, the policy's
predicted_velocity they share, and the report's marking of what each method needs."""

import copy

import pytest
import torch

from harness.data.datasets import TrainingData
from harness.evaluate.stages import load_checkpoint, save_checkpoint
from harness.train.trainer import TrainSettings, train_stage
from methods import TaskContext, get_method, method_names
from methods.distill import Distill, DistillConfig
from methods.mas import MAS, MASConfig, output_sensitivity
from methods.merge import MergeConfig, WeightMerge
from tests.conftest import make_batch


def _data(policy, n, task, seed):
    b = make_batch(policy, b=n, seed=seed)
    mask = torch.ones(n, 4, dtype=torch.bool)
    mask[: n // 4, 3] = False  # some chunks padded at the end, as at an episode's end
    return TrainingData({"state": b["state"]}, b["actions"], mask,
                        torch.zeros(n, dtype=torch.long), b["instruction"][:1], [task])


def _ctx(policy, data, stage):
    return TaskContext(stage=stage, task=data.task_names[0], data=data, policy=policy,
                       foundation_loss=0.1, steps=10)


def _weights(policy):
    return {n: p.detach().clone() for n, p in policy.named_parameters()}


def _train(policy, method, data, stage, steps=8, log=None):
    """A real stage of the trainer: before_task, steps, after_task."""
    settings = TrainSettings(steps=steps, batch_size=16, lr=1e-2)
    return train_stage(_ctx(policy, data, stage), method, settings,
                       torch.Generator().manual_seed(stage), log=log)


def test_registry_and_needs():
    assert {"merge", "distill", "mas"} <= set(method_names())
    assert get_method("distill").needs() == "reference copy"
    assert get_method("er").needs() == get_method("multitask").needs() == "past data"
    for name in ("sft", "merge", "mas", "l2", "ewc", "consft"):
        assert get_method(name).needs() == "none", name


# --- the policy's predicted velocity ----------------------------------------------------------

def test_forward_is_the_masked_squared_error_of_predicted_velocity(tiny_policy):
    data = _data(tiny_policy, 8, "t", seed=1)
    batch = data.batch(torch.arange(8))
    batch["noise"] = torch.randn(batch["actions"].shape, generator=torch.Generator().manual_seed(2))
    batch["time"] = torch.linspace(0.1, 0.9, 8)
    v = tiny_policy.predicted_velocity(batch)
    assert v.shape == batch["actions"].shape
    target = batch["noise"] - tiny_policy.action_norm.normalize(batch["actions"])
    m = batch["action_mask"][:, :, None].float()
    expected = (((v - target) ** 2) * m).sum(dim=(1, 2)) / (m.sum(dim=(1, 2)) * v.shape[-1])
    torch.testing.assert_close(tiny_policy(batch), expected, rtol=1e-6, atol=1e-7)
    assert not torch.equal(expected[:2], ((v - target) ** 2).mean(dim=(1, 2))[:2])  # mask matters


# --- merge ------------------------------------------------------------------------------------

@pytest.mark.parametrize("alpha", [0.0, 1.0, 0.25])
def test_merge_interpolates_with_the_foundation(tiny_policy, alpha):
    foundation, task = _data(tiny_policy, 32, "f", 1), _data(tiny_policy, 32, "t", 2)
    theta0 = _weights(tiny_policy)
    method = WeightMerge(MergeConfig(alpha=alpha))
    method.after_task(_ctx(tiny_policy, foundation, 0))
    tuned = copy.deepcopy(tiny_policy)
    _train(tuned, get_method("sft")(), task, 1)  # what the task's training alone reaches
    _train(tiny_policy, method, task, 1)  # the same training, then the merge
    theta_task, merged = _weights(tuned), _weights(tiny_policy)
    assert any(not torch.equal(theta0[n], theta_task[n]) for n in theta0)
    for n in theta0:
        if alpha == 0.0:
            assert torch.equal(merged[n], theta0[n]), n  # the foundation, exactly
        elif alpha == 1.0:
            assert torch.equal(merged[n], theta_task[n]), n  # plain SFT, exactly
        else:
            torch.testing.assert_close(merged[n], 0.75 * theta0[n] + 0.25 * theta_task[n])


def test_merge_rejects_alpha_outside_zero_one():
    from harness.common.errors import RetainError
    from harness.protocol.stream import make_method

    with pytest.raises(RetainError, match=r"bad value 1.5 for alpha \(method merge\): expected "
                                          r"a number in \[0, 1\]"):
        make_method(WeightMerge, {"alpha": "1.5"})


# --- distill ----------------------------------------------------------------------------------

def _penalties(policy, method, data, stage, steps=8):
    seen = []
    _train(policy, method, data, stage, steps, log=lambda step, stats: seen.append(
        stats["distill/penalty"]))
    return seen


def test_distill_penalty_is_zero_at_the_first_step_of_every_task(tiny_policy):
    foundation = _data(tiny_policy, 32, "f", 1)
    first, second = _data(tiny_policy, 32, "a", 2), _data(tiny_policy, 32, "b", 3)
    method = Distill()
    method.after_task(_ctx(tiny_policy, foundation, 0))
    for stage, data in ((1, first), (2, second)):
        penalties = _penalties(tiny_policy, method, data, stage)
        assert penalties[0] == 0.0, stage  # the reference is the model before this task
        assert min(penalties[1:]) > 0.0 and penalties[-1] > 1e-6, stage


def test_distill_foundation_reference_penalises_from_the_second_task_on(tiny_policy):
    foundation = _data(tiny_policy, 32, "f", 1)
    first, second = _data(tiny_policy, 32, "a", 2), _data(tiny_policy, 32, "b", 3)
    method = Distill(DistillConfig(reference="foundation"))
    method.after_task(_ctx(tiny_policy, foundation, 0))
    assert _penalties(tiny_policy, method, first, 1)[0] == 0.0
    assert _penalties(tiny_policy, method, second, 2)[0] > 1e-6  # the stream moved the policy


def test_distill_pulls_the_velocity_field_towards_the_reference(tiny_policy):
    foundation, task = _data(tiny_policy, 32, "f", 1), _data(tiny_policy, 32, "t", 2)
    free, distilled = copy.deepcopy(tiny_policy), copy.deepcopy(tiny_policy)
    probe = Distill()
    probe.after_task(_ctx(tiny_policy, foundation, 0))
    probe.before_task(_ctx(tiny_policy, foundation, 1))  # the reference: the starting weights
    _train(free, get_method("sft")(), task, 1, steps=30)
    _train(distilled, Distill(DistillConfig(strength=20.0)), task, 1, steps=30)
    batch = Distill().sample_batch(_ctx(tiny_policy, task, 1), 32, torch.Generator().manual_seed(9))
    with torch.no_grad():
        assert probe.penalty(batch, distilled) < 0.5 * probe.penalty(batch, free)


def test_distill_at_strength_zero_is_sft_bit_for_bit(tiny_policy):
    """The draws it puts in the batch are those the policy's forward would make, in order."""
    foundation, task = _data(tiny_policy, 32, "f", 1), _data(tiny_policy, 32, "t", 2)
    sft, distilled = copy.deepcopy(tiny_policy), copy.deepcopy(tiny_policy)
    method = Distill(DistillConfig(strength=0.0))
    method.after_task(_ctx(distilled, foundation, 0))
    a = _train(sft, get_method("sft")(), task, 1)
    b = _train(distilled, method, task, 1)
    assert a.final_loss == b.final_loss
    assert all(torch.equal(p, q) for p, q in zip(sft.parameters(), distilled.parameters()))


def test_distill_rejects_an_unknown_reference():
    from harness.common.errors import RetainError
    from harness.protocol.stream import make_method

    with pytest.raises(RetainError, match="bad value 'teacher' for reference .*: expected one of "
                                          "previous, foundation"):
        make_method(Distill, {"reference": "teacher"})


# --- mas --------------------------------------------------------------------------------------

def _mas_batch(policy, n=6):
    batch = make_batch(policy, b=n, seed=4)
    g = torch.Generator().manual_seed(5)
    batch["noise"] = torch.randn(batch["actions"].shape, generator=g)
    batch["time"] = torch.rand(n, generator=g)
    return batch


def test_mas_importance_is_the_mean_absolute_per_sample_gradient(tiny_policy):
    batch = _mas_batch(tiny_policy)
    omega = output_sensitivity(tiny_policy, batch, chunk=4)  # two chunks: 4 + 2
    expected = {n: torch.zeros_like(p) for n, p in tiny_policy.named_parameters()}
    for i in range(6):
        one = {k: v[i:i + 1] for k, v in batch.items()}
        tiny_policy.zero_grad()
        (tiny_policy.predicted_velocity(one) ** 2).sum().backward()
        for n, p in tiny_policy.named_parameters():
            expected[n] += p.grad.abs() / 6
    assert omega.keys() == expected.keys()
    for n in omega:
        assert (omega[n] >= 0).all(), n
        torch.testing.assert_close(omega[n], expected[n], rtol=1e-4, atol=1e-7)
    # the absolute value of the batch gradient would let samples cancel: it is smaller
    tiny_policy.zero_grad()
    (tiny_policy.predicted_velocity(batch) ** 2).sum().div(6).backward()
    w = "action_in.weight"
    assert dict(tiny_policy.named_parameters())[w].grad.abs().sum() < omega[w].sum()


def test_mas_importance_is_zero_for_weights_that_do_not_reach_the_output(tiny_policy):
    with torch.no_grad():
        tiny_policy.action_out[1].weight.zero_()  # the output is now the bias alone
    omega = output_sensitivity(tiny_policy, _mas_batch(tiny_policy))
    upstream = [n for n in omega if not n.startswith("action_out")]
    assert upstream and all(torch.equal(omega[n], torch.zeros_like(omega[n])) for n in upstream)
    bias = tiny_policy.action_out[1].bias.detach()
    torch.testing.assert_close(omega["action_out.1.bias"], 2 * bias.abs())  # d||b||^2/db = 2b
    assert omega["action_out.1.weight"].abs().sum() > 0


def test_mas_accumulates_online_and_anchors_after_each_task(tiny_policy):
    data = _data(tiny_policy, 32, "f", 1)
    method = MAS(MASConfig(decay=0.5, importance_samples=16))
    method.after_task(_ctx(tiny_policy, data, 0))
    first = {k: v.clone() for k, v in method.importance.items()}
    method.after_task(_ctx(tiny_policy, data, 0))  # same draws: Omega = 0.5 Omega + Omega
    torch.testing.assert_close(method.importance["action_in.weight"],
                               1.5 * first["action_in.weight"])
    assert all(torch.equal(method.anchor[n], p) for n, p in tiny_policy.named_parameters())


# --- checkpoints: a fresh instance resumes with the same next step ----------------------------

@pytest.mark.parametrize("make", [
    lambda: WeightMerge(MergeConfig(alpha=0.3)),
    lambda: Distill(),
    lambda: Distill(DistillConfig(reference="foundation")),
    lambda: MAS(MASConfig(strength=100.0, importance_samples=16)),
], ids=["merge", "distill", "distill-foundation", "mas"])
def test_state_round_trips_through_a_checkpoint(tiny_policy, tmp_path, make):
    foundation, task = _data(tiny_policy, 32, "f", 1), _data(tiny_policy, 32, "t", 2)
    method = make()
    method.after_task(_ctx(tiny_policy, foundation, 0))
    _train(tiny_policy, method, task, 1)
    ctx = _ctx(tiny_policy, task, 2)
    method.before_task(ctx)  # mid-task from here on: a killed run resumes at this point
    _train_steps(tiny_policy, method, ctx, 3)
    save_checkpoint(tmp_path / "stage.pt", {"method": method.state_dict()})
    resumed = make()
    resumed.load_state_dict(load_checkpoint(tmp_path / "stage.pt")["method"])
    batch = method.sample_batch(ctx, 16, torch.Generator().manual_seed(7))
    batch.setdefault("noise", torch.randn(batch["actions"].shape))
    batch.setdefault("time", torch.rand(16))
    losses = [m.loss(tiny_policy(batch), batch, tiny_policy) for m in (method, resumed)]
    assert torch.equal(losses[0][0], losses[1][0]) and losses[0][1] == losses[1][1]
    # and a whole stage after the resume (hooks included: merge acts in after_task) is the same
    twin, before = copy.deepcopy(tiny_policy), _weights(tiny_policy)
    _train(tiny_policy, method, task, 3)
    _train(twin, resumed, task, 3)
    assert all(torch.equal(p, q) for p, q in zip(tiny_policy.parameters(), twin.parameters()))
    assert any(not torch.equal(p, before[n]) for n, p in tiny_policy.named_parameters())


def _train_steps(policy, method, ctx, steps):
    optimizer = torch.optim.SGD(policy.parameters(), lr=1e-2)
    g = torch.Generator().manual_seed(3)
    for _ in range(steps):
        batch = method.sample_batch(ctx, 16, g)
        loss, _ = method.loss(policy(batch, generator=g), batch, policy)
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()


# --- the report: needs per method, and a sweep drawn as a curve -------------------------------

def _fake_run(method, needs, sweep_point="", retention=0.5, plasticity=0.5):
    from harness.report.runs import RunRecord
    from tests.test_report import FOUNDATION, STREAM, success_matrix

    return RunRecord(run_id=f"{method}{sweep_point}", method=method, seed=0,
                     sweep_point=sweep_point, start_time=0,
                     params={"config.lr": "0.0003", "config.name": "mw-test"},
                     metrics={"retention": retention, "plasticity": plasticity},
                     foundation_tasks=FOUNDATION, stream_tasks=STREAM,
                     success=success_matrix("sft", 0), layers=[], needs=needs)


def test_alpha_sweep_is_drawn_as_a_retention_plasticity_curve(monkeypatch, tmp_path):
    from harness.report import plots
    from harness.report.aggregate import summarize
    from harness.report.groups import build_rows

    runs = [_fake_run("merge", "none", f"alpha={a}", retention=1 - a, plasticity=a)
            for a in (1.0, 0.25, 0.5)] + [_fake_run("sft", "none"), _fake_run("merge", "none")]
    summaries = [summarize(r) for r in build_rows(runs)[0]]
    curves = plots.sweep_curves(summaries)
    assert list(curves) == [("merge: alpha from 0.25 to 1", "merge[alpha=0.25]")]
    assert curves[("merge: alpha from 0.25 to 1", "merge[alpha=0.25]")] == [
        (0.25, 0.75), (0.5, 0.5), (1.0, 0.0)]
    figures = []
    monkeypatch.setattr(plots, "save", lambda fig, path: figures.append(fig))
    plots.plasticity_retention(tmp_path / "p.png", summaries, "mw-test")
    lines = {line.get_label(): line for line in figures[0].axes[0].lines}
    assert list(lines["merge: alpha from 0.25 to 1"].get_xdata()) == [0.25, 0.5, 1.0]


@pytest.fixture(scope="module")
def tiny_comparison(tmp_path_factory):
    """PROFILE=tiny end to end for the three methods (merge at alpha=0), then the report."""
    from harness.report import ReportSettings, build_report
    from harness.run.cli import main

    root = tmp_path_factory.mktemp("mdm")
    with pytest.MonkeyPatch.context() as mp:
        mp.delenv("MLFLOW_TRACKING_URI", raising=False)
        assert main(["bench", "PROFILE=tiny", "METHOD=merge,distill,mas", "alpha=0.0",
                     f"results_dir={root}/results", f"cache_dir={root}/cache", "progress=false",
                     "eval_workers=1"]) == 0
        build_report(ReportSettings("mw-quick-tiny", f"{root}/results", log_run=False))
    return root / "results" / "mw-quick-tiny"


def test_tiny_end_to_end_for_merge_distill_mas(tiny_comparison):
    import json

    for name in ("merge[alpha=0.0]", "distill", "mas"):  # alpha away from its default: labelled
        metrics = json.loads((tiny_comparison / name / "seed0" / "metrics.json").read_text())
        assert metrics["metrics"]["plasticity"] >= 0, name
    merge = json.loads((tiny_comparison / "merge[alpha=0.0]" / "seed0" / "metrics.json").read_text())
    # at alpha = 0 every stage ends on the foundation's weights: nothing moved, nothing lost
    assert merge["metrics"]["update_relative_l2"] == 0.0
    assert merge["metrics"]["heldout_loss_ratio"] == 1.0
    distill = json.loads((tiny_comparison / "distill" / "seed0" / "metrics.json").read_text())
    assert distill["metrics"]["update_relative_l2"] > 0


def test_report_marks_what_each_method_needs(tiny_comparison):
    import csv
    import io

    report = tiny_comparison / "report"
    md = (report / "summary.md").read_text()
    assert "| method | seeds | needs |" in md
    assert "| distill | 1 | reference copy |" in md
    assert "| merge | 1 | none |" in md and "| mas | 1 | none |" in md
    assert "- needs: what a method uses beyond the current task's data" in md
    rows = {r["label"]: r for r in csv.DictReader(io.StringIO((report / "summary.csv").read_text()))}
    assert rows["distill"]["needs"] == "reference copy" and rows["mas"]["needs"] == "none"
    assert "reference copy" in (report / "summary.tex").read_text()


def test_needs_of_runs_without_the_tag_read_not_logged():
    from harness.report.groups import build_rows

    rows, _ = build_rows([_fake_run("er", ""), _fake_run("er", "past data", "replay_ratio=0.2")])
    assert {r.label: r.needs for r in rows} == {"er": "not logged",
                                                "er[replay_ratio=0.2]": "past data"}
