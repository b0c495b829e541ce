"""The ConSFT paper's protocol: matched-target stopping on check episodes of their own, stages of
several tasks, the fine-tuning optimizer's settings, Adam's eps share, and its Eq. 8 sparsity."""

import json
import os
import sys

import numpy as np
import pytest
import torch

from harness.config.benchmark import BenchConfig
from harness.data.prepare import BenchmarkData
from harness.evaluate.rollouts import EvalSettings, TaskEvaluation
from harness.evaluate.stages import StageRecord, load_checkpoint
from harness.measure.updates import paper_sparsity, update_stats
from harness.perf.throughput import _policy, synthetic_data
from harness.protocol.stream import StageWatch
from harness.run.cli import main
from harness.train.optim import ClippedAdamW
from harness.train.trainer import TrainSettings, train_stage
from methods import Method, TaskContext
from methods.base import snapshot
from suites.metaworld import MetaWorldSuite


class ScriptedChecks:
    """An evaluator whose "check" split returns a fixed sequence of success rates: the stopping
    rule's own test (the rollouts themselves are tested in test_evaluation.py)."""

    def __init__(self, rates, episodes=10):
        self.rates, self.splits, self.n = list(rates), [], episodes

    def evaluate(self, policy, tasks, instructions, noise_seed, split="eval"):
        """A rate per check, or a list of per-task successes (out of `episodes`) per check."""
        self.splits.append(split)
        rate = self.rates.pop(0)
        wins = rate if isinstance(rate, list) else [round(rate * self.n)] * len(tasks)
        return {t: TaskEvaluation(t, tuple(i < k for i in range(self.n)), 0)
                for t, k in zip(tasks, wins)}


def _watch_run(rates, until=0.9, check_every=4, budget=20, tasks=("s",), episodes=10):
    cfg = BenchConfig("b", "metaworld", ["f"], list(tasks), steps_per_task=budget,
                      until_success=until, check_every=check_every, stage_sizes=[len(tasks)])
    policy = _policy("tiny")
    theta0 = snapshot(policy)
    before = StageRecord(0, "foundation", dict.fromkeys(tasks, 0.0), {}, {})
    evaluator = ScriptedChecks(rates, episodes)
    logged = []
    data = BenchmarkData({}, {}, {"s": {}})
    watch = StageWatch(cfg, policy, Method(), evaluator, data, 0, list(tasks), theta0, before,
                       lambda step, m: logged.append((step, m)))
    ctx = TaskContext(1, "s", synthetic_data(256, 0), policy, 0.05, budget)
    result = train_stage(ctx, Method(), TrainSettings(budget, 16, 1e-3), torch.Generator(),
                         after_step=watch)
    record = StageRecord(1, "s", dict.fromkeys(tasks, 1.0), {}, {})
    watch.finish(record, result.steps)
    return result, record, evaluator, logged


def test_a_stage_stops_at_the_first_check_that_reaches_the_threshold():
    result, record, evaluator, logged = _watch_run([0.2, 0.8, 0.9, 1.0])
    assert result.steps == 12 and record.steps_used == 12
    assert record.check_steps == [4, 8, 12] and record.check_success == [0.2, 0.8, 0.9]
    assert evaluator.splits == ["check"] * 3  # never the evaluation episodes
    assert [m["check/success"] for _, m in logged if "check/success" in m] == [0.2, 0.8, 0.9]


def test_a_check_at_the_threshold_stops_whatever_the_rounding_of_its_mean():
    # libero-paper's check: ten tasks, three episodes each; 27 of 30 is a mean of 0.8999999999999998
    tasks = [f"t{i}" for i in range(10)]
    wins = [1, 3, 3, 3, 3, 3, 3, 3, 3, 2]
    assert float(np.mean([k / 3 for k in wins])) < 0.9
    result, record, _, _ = _watch_run([[2] * 10, wins, [3] * 10], tasks=tasks, episodes=3)
    assert result.steps == 8 and record.check_steps == [4, 8]
    # one episode short of the threshold still trains on
    result, record, _, _ = _watch_run([[2] * 10, [3] * 6 + [2] * 4, [3] * 10], tasks=tasks,
                                      episodes=3)
    assert result.steps == 12 and record.check_steps == [4, 8, 12]


def test_a_stage_that_never_reaches_the_threshold_uses_its_budget():
    result, record, _, _ = _watch_run([0.1, 0.5, 0.6, 0.7], budget=18)
    assert result.steps == 18 and record.check_steps == [4, 8, 12, 16]
    # the paper's sparsity is tracked at every check and at the stage's end
    assert record.sparsity_steps == [4, 8, 12, 16, 18]
    assert all(0.0 <= v <= 1.0 for v in record.sparsity)
    assert record.sparsity_layers and all(len(v) == 5 for v in record.sparsity_layers.values())


def test_check_episodes_are_apart_from_the_evaluation_episodes():
    suite = MetaWorldSuite()
    check = suite.episode_keys("reach-v3", "check", 20)
    assert not set(check) & set(suite.episode_keys("reach-v3", "eval", 20))
    assert EvalSettings(5, 10, 2, check_episodes=3).episodes_of("check") == 3
    with pytest.raises(ValueError, match="valid: eval, spatial, check"):
        EvalSettings(5, 10, 2).episodes_of("test")


def test_eq8_sparsity_against_a_hand_computation():
    ref = {"a": torch.tensor([1.0, -2.0, 0.5, 0.0]), "b": torch.tensor([10.0, 10.0])}
    cur = {"a": torch.tensor([1.0005, -2.01, 0.5, 0.0]), "b": torch.tensor([10.02, 10.001])}
    # |delta| / |theta_0|: a: 5e-4 (kept), 5e-3, 0 (kept), 0/0 (kept); b: 2e-3, 1e-4 (kept)
    total, layers = paper_sparsity(ref, cur)
    assert layers == {"a": 0.75, "b": 0.5}
    assert total == pytest.approx(4 / 6)
    summary, rows = update_stats(ref, cur)
    assert summary["eq8_sparsity"] == pytest.approx(4 / 6)
    assert [r["eq8_sparsity"] for r in rows] == [0.75, 0.5]


def test_adam_eps_share_counts_scalars_whose_second_moment_is_below_eps():
    flat = torch.nn.Parameter(torch.zeros(4))
    flat.grad = torch.tensor([0.0, 1e-9, 1e-7, 1.0])
    optimizer = ClippedAdamW(flat, lr=1e-3, weight_decay=0.0, grad_clip=0.0, betas=(0.9, 0.95),
                          eps=1e-8)
    optimizer.step()  # v_hat = g^2 after one step: sqrt(v_hat) = |g|
    assert optimizer.frac_eps_dominated() == 0.5
    flat.grad.copy_(torch.tensor([0.0, 1e-9, 1e-7, 1.0]))
    optimizer.adamw.param_groups[0]["eps"] = 1e-6
    assert optimizer.frac_eps_dominated() == 0.75


def test_stage_sizes_group_the_stream():
    cfg = BenchConfig("b", "metaworld", ["f"], ["a", "b", "c", "d"], stage_sizes=[3, 1])
    assert cfg.stream_stages() == [["a", "b", "c"], ["d"]] and cfg.num_stages == 2
    assert BenchConfig("b", "metaworld", ["f"], ["a", "b"]).stream_stages() == [["a"], ["b"]]


@pytest.fixture(scope="module")
def grouped_run(tmp_path_factory):
    """mw-quick's tiny profile with its two stream tasks as one stage, until success 0.5."""
    root = tmp_path_factory.mktemp("grouped")
    record = root / "record.jsonl"
    os.environ["RETAIN_TEST_RECORD"] = str(record)
    args = ["bench", "PROFILE=tiny", "METHOD=tests/recording_method.py:RecordingSFT",
            "stage_sizes=2", "until_success=0.5", "check_every=4", "steps_per_task=16",
            f"results_dir={root}/results", f"cache_dir={root}/cache", "progress=false",
            "eval_workers=1", "executor=serial"]
    try:
        assert main(args) == 0
    finally:
        del os.environ["RETAIN_TEST_RECORD"]
    runs = list((root / "results" / "mw-quick-tiny").glob("*/seed0"))
    assert len(runs) == 1
    lines = [json.loads(line) for line in record.read_text().splitlines()]
    return runs[0], lines


def test_a_grouped_stage_trains_on_all_of_its_tasks_data(grouped_run):
    run, lines = grouped_run
    stage1 = [line for line in lines if line["stage"] == 1]
    assert stage1[0]["data_tasks"] == ["drawer-close-v3", "window-close-v3"]
    assert stage1[1]["batch_tasks"] == ["drawer-close-v3", "window-close-v3"]
    rows = (run / "success_matrix.csv").read_text().splitlines()
    assert len(rows) == 3 and rows[2].split(",")[1] == "stage1-2-tasks"  # header, stages 0, 1


def test_the_grouped_run_records_the_stopping_rule(grouped_run):
    run, _ = grouped_run
    stage = load_checkpoint(run / "stages" / "stage_1.pt")["records"][0]
    metrics = json.loads((run / "metrics.json").read_text())["metrics"]
    checks = list(zip(stage["check_steps"], stage["check_success"]))
    reached = [n for n, v in checks if v >= 0.5]
    assert stage["steps_used"] == (reached[0] if reached else 16)
    assert all(v < 0.5 for n, v in checks if n < stage["steps_used"])
    assert metrics["stream_steps"] == stage["steps_used"]
    assert metrics["target"] == pytest.approx(metrics["plasticity"])  # one stage: the same


@pytest.mark.slow
def test_matched_target_stopping_resumes_to_the_same_point_after_a_kill(tmp_path):
    from tests.test_reliability import _kill_when, _run

    def cmd(tmp):
        return [sys.executable, "-m", "harness", "bench", "PROFILE=tiny", "METHOD=consft",
                "until_success=0.5", "check_every=3", "steps_per_task=12",
                f"results_dir={tmp}/results", f"cache_dir={tmp_path}/cache", "progress=false",
                "eval_workers=1"]

    def stages(tmp):
        run = next((tmp / "results" / "mw-quick-tiny").glob("consft*/seed0"))
        records = load_checkpoint(run / "stages" / "stage_2.pt")["records"]
        return [(r["steps_used"], r["check_steps"], r["check_success"], r["success"])
                for r in records], (run / "metrics.json").read_text()

    reference = tmp_path / "reference"
    assert _run(cmd(reference)).returncode == 0
    killed = tmp_path / "killed"
    _kill_when(cmd(killed), "stage 1 (", 0.3)  # mid stage 2, after stage 1's checkpoint
    assert _run(cmd(killed)).returncode == 0
    assert stages(killed) == stages(reference)
