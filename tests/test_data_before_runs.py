"""A dataset's problems surface before any MLflow run exists, and fewer demos than asked are
said and recorded, not used silently (issue 48, items 1 and 2)."""

from __future__ import annotations

import yaml
from mlflow.tracking import MlflowClient

from harness.run.cli import main
from suites import get_suite
from tests.test_lerobot import make_episodes, write_v2

TASKS = ["reach-v3", "push-v3", "drawer-close-v3", "window-close-v3"]  # mw-quick-tiny's


def dataset(root, per_task: int = 2, tasks=TASKS):
    """A LeRobot v2.1 folder of Meta-World-shaped episodes (39-D state, 4-D actions), matched
    to the suite's tasks by instruction: `per_task` episodes of each."""
    suite = get_suite("metaworld")
    episodes = make_episodes([6] * (per_task * len(tasks)), action_dim=4, state_dim=39)
    return write_v2(root, [(suite.instruction(t), e) for i, t in enumerate(tasks)
                           for e in episodes[i * per_task:(i + 1) * per_task]], cameras=None)


def args(tmp_path, folder):
    return ["bench", "PROFILE=tiny", "METHOD=sft", f"demos_dir={folder}",
            f"results_dir={tmp_path}/results", f"cache_dir={tmp_path}/cache", "progress=false",
            "executor=serial", "eval_workers=1"]


def runs(tmp_path):
    client = MlflowClient(tracking_uri=f"sqlite:///{tmp_path}/results/mlflow.db")
    experiment = client.get_experiment_by_name("mw-quick-tiny")
    return [] if experiment is None else client.search_runs([experiment.experiment_id])


def test_fewer_demos_than_asked_are_said_and_recorded(tmp_path, capsys):
    """Two episodes a task under tiny (demos_per_task=3, one held out): one trains, and the
    run says so, in its output, its config.yaml and its MLflow params."""
    assert main(args(tmp_path, dataset(tmp_path / "ds"))) == 0
    out = capsys.readouterr().out
    assert ("demos_dir holds fewer demos than demos_per_task=3 plus heldout_demos_per_task=1 "
            "for 4 task(s)") in out and "they train on 1 demo(s) each" in out
    run = next((tmp_path / "results" / "mw-quick-tiny").glob("sft*/seed0"))
    config = yaml.safe_load((run / "config.yaml").read_text())
    assert config["demos_used"] == dict.fromkeys(TASKS, 1)
    assert config["config"]["demos_per_task"] == 3  # what was asked, beside what was used
    params = [r.data.params for r in runs(tmp_path)]
    assert params and all(p["demos_used"] == " ".join(f"{t}=1" for t in TASKS) for p in params)


def test_enough_demos_record_nothing_extra(tmp_path, capsys):
    assert main(args(tmp_path, dataset(tmp_path / "ds", per_task=4))) == 0
    assert "fewer demos" not in capsys.readouterr().out
    run = next((tmp_path / "results" / "mw-quick-tiny").glob("sft*/seed0"))
    assert "demos_used" not in yaml.safe_load((run / "config.yaml").read_text())


def test_a_missing_task_leaves_no_run_behind(tmp_path, capsys):
    folder = dataset(tmp_path / "ds", tasks=TASKS[:3])
    assert main(args(tmp_path, folder)) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "no episodes of task 'window-close-v3'" in err
    assert runs(tmp_path) == []  # not even a FAILED parent


def test_a_truncated_data_file_leaves_no_run_behind(tmp_path, capsys):
    folder = dataset(tmp_path / "ds")
    data = folder / "data/chunk-000/episode_000005.parquet"
    data.write_bytes(data.read_bytes()[:40])
    assert main(args(tmp_path, folder)) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "episode_000005.parquet" in err
    assert runs(tmp_path) == []
