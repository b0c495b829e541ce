"""Issue 48's papercuts: what a method keeps marks its needs (5), short run labels (7), whole
error reasons (4)."""

from __future__ import annotations

import copy

import pytest
import torch

from harness.perf.throughput import _policy, synthetic_data
from harness.train.trainer import TrainSettings, train_stage
from methods import Method, TaskContext, get_method, method_names
from methods.base import observed_needs


def _after_one_stage(method: Method):
    """`method` after stage 0's after_task (foundation data of task "f") and a two-step stage
    on task "s1", as run_stream drives it; the policy."""
    policy = _policy("tiny")
    foundation, task = synthetic_data(64, 0, task="f"), synthetic_data(64, 1, task="s1")
    method.after_task(TaskContext(0, "foundation", foundation, policy, 0.05, 0))
    train_stage(TaskContext(1, "s1", task, policy, 0.05, 2), method,
                TrainSettings(steps=2, batch_size=8, lr=1e-3, weight_decay=0.0),
                torch.Generator().manual_seed(0))
    return policy


@pytest.mark.parametrize("name", [n for n in method_names()])
def test_what_each_builtin_keeps_is_what_it_declares(name):
    """Looking agrees with the class attributes for every method of Retain's own: replay
    methods hold samples of other tasks, distill a copy of the network; L2, EWC, MAS and merge
    keep weights as tensors, which is no network run in training."""
    cls = get_method(name)
    method = cls()
    policy = _after_one_stage(method)
    expected = [need for on, need in ((cls.uses_past_data, "past data"),
                                      (cls.uses_reference_copy, "reference copy")) if on]
    assert observed_needs(method, policy, ["s1"]) == expected


class FrozenCopy(Method):
    """A user's method that keeps a frozen copy of the network and says nothing of it."""

    name = "frozen_copy"

    def after_task(self, ctx):
        if ctx.stage == 0:
            self.teacher = {"net": copy.deepcopy(ctx.policy).requires_grad_(False)}


class KeepsOldData(Method):
    name = "keeps_old_data"

    def after_task(self, ctx):
        self.memory = [ctx.data] if ctx.stage == 0 else self.memory


class KeepsItsOwnData(Method):
    """Holding the stage's own data (for initial losses, say) is no past data."""

    name = "keeps_its_own_data"

    def before_task(self, ctx):
        self.data = ctx.data


def test_a_users_method_that_keeps_a_copy_or_old_data_is_marked_so():
    assert FrozenCopy.needs() == "none"  # what the attributes alone said
    policy = _after_one_stage(method := FrozenCopy())
    seen = observed_needs(method, policy, ["s1"])
    assert seen == ["reference copy"] and method.needs(seen) == "reference copy"
    policy = _after_one_stage(method := KeepsOldData())
    assert observed_needs(method, policy, ["s1"]) == ["past data"]
    policy = _after_one_stage(method := KeepsItsOwnData())
    assert observed_needs(method, policy, ["s1"]) == []


def test_a_users_method_is_tagged_with_what_it_keeps(tmp_path, capsys):
    """End to end: the run's `needs` tag (the report's needs column) and a note."""
    from mlflow.tracking import MlflowClient

    from harness.run.cli import main

    args = ["bench", "PROFILE=tiny", f"METHOD={__file__}:FrozenCopy",
            f"results_dir={tmp_path}/results", f"cache_dir={tmp_path}/cache", "progress=false",
            "executor=serial", "eval_workers=1"]
    assert main(args) == 0
    out = capsys.readouterr().out
    assert ("frozen_copy keeps a copy of the network but does not set uses_reference_copy = "
            "True") in out
    client = MlflowClient(tracking_uri=f"sqlite:///{tmp_path}/results/mlflow.db")
    runs = client.search_runs([client.get_experiment_by_name("mw-quick-tiny").experiment_id])
    child = next(r for r in runs if "mlflow.parentRunId" in r.data.tags)
    assert child.data.tags["needs"] == "reference copy"
    assert main(args) == 0  # a rerun (every stage resumed from its checkpoint) keeps the mark
    child = client.get_run(child.info.run_id)
    assert child.data.tags["needs"] == "reference copy"


class ViewWithoutFlag(Method):
    name = "view_without_flag"

    def evaluation_view(self, policy, task, stream):
        return super().evaluation_view(policy, task, stream)


def test_an_evaluation_view_without_task_aware_eval_is_refused():
    with pytest.raises(ValueError, match="overrides evaluation_view but does not set "
                                         "task_aware_eval = True"):
        get_method(f"{__file__}:ViewWithoutFlag")


def test_long_settings_give_a_short_label_and_the_full_settings_stay(tmp_path):
    """A run with demos_dir and task overrides once got a 200-character label and folder."""
    from harness.protocol.stream import run_dir
    from harness.run.plan import plan

    folder = tmp_path / "datasets" / "physical-intelligence" / "libero_lerobot_converted_v21"
    folder.mkdir(parents=True)
    tasks = "reach-v3:pick up the red cube and put it in the basket,push-v3:1"
    p = plan(["PROFILE=tiny", "METHOD=sft", f"demos_dir={folder}", f"lerobot_tasks={tasks}",
              "stream_tasks=drawer-close-v3,window-close-v3,button-press-v3", "lr=0.0001"])
    label = p.variants[0].label
    assert len(label) <= 100 and label.startswith("sft[") and "lr=0.0001" in label
    assert str(folder) not in label and "pick up" not in label
    assert len(run_dir(p.variants[0].cfg, label, 0).parent.name) <= 100
    assert p.variants[0].cfg.demos_dir == str(folder)  # params and config.yaml: the full value
    assert p.variants[0].cfg.lerobot_tasks == tasks
    # each long value is its start and a hash of the whole: two values never share a label
    other = plan(["PROFILE=tiny", "METHOD=sft", f"demos_dir={folder}",
                  f"lerobot_tasks={tasks.replace('red', 'blue')}",
                  "stream_tasks=drawer-close-v3,window-close-v3,button-press-v3", "lr=0.0001"])
    assert other.variants[0].label != label
    short = plan(["PROFILE=tiny", "METHOD=sft", f"demos_dir={folder}"]).variants[0].label
    assert short.startswith("sft[demos_dir=libero_lerob@") and len(short) < 40


def test_a_short_setting_is_shown_as_it_is():
    from harness.config.benchmark import run_label, setting_text

    assert setting_text(0.0001) == "0.0001" and setting_text(["a", "b"]) == "a,b"
    assert run_label("consft", "kappa=0.1") == "consft[kappa=0.1]"


def test_an_error_reason_is_whole_and_on_one_line():
    import requests

    from harness.common.errors import RetainError
    from harness.track.tracking import _first_line, check_reachable

    with pytest.raises(RetainError) as err:
        check_reachable("http://127.0.0.1:9")
    text = str(err.value)
    assert "\n" not in text and text.endswith(": [Errno 111] Connection refused")
    long = requests.ConnectionError("word " * 100)
    cut = _first_line(long)
    assert len(cut) <= 304 and cut.endswith("word ...")
