"""The `tiny` profile end to end: demos, foundation, stream, evaluation, outputs, MLflow."""

import json

import numpy as np
import pytest
import yaml

from harness.run.cli import main
from harness.track.tracking import machine


@pytest.fixture(scope="module")
def tiny_run(tmp_path_factory):
    root = tmp_path_factory.mktemp("tiny")
    args = ["bench", "PROFILE=tiny", "METHOD=sft", f"results_dir={root}/results",
            f"cache_dir={root}/cache", "progress=false", "learning_curve_every=5", "eval_workers=1"]
    assert main(args) == 0
    return root, args


def test_outputs_on_disk(tiny_run):
    root, _ = tiny_run
    # learning_curve_every is not the benchmark's: the run's label and directory say so
    run = root / "results" / "mw-quick-tiny" / "sft[learning_curve_every=5]" / "seed0"
    for name in ("success_matrix.csv", "metrics.json", "config.yaml", "success_matrix.png",
                 "heldout_loss.csv", "updates_per_layer.csv"):
        assert (run / name).stat().st_size > 0, name
    lines = (run / "success_matrix.csv").read_text().splitlines()
    assert lines[0].split(",")[:3] == ["stage", "trained_on", "reach-v3"]
    assert len(lines) == 1 + 3  # stage 0 and two stream stages (tiny keeps two)
    R = np.array([[float(x) for x in line.split(",")[2:]] for line in lines[1:]])
    assert R.shape == (3, 4) and ((R >= 0) & (R <= 1)).all()
    metrics = json.loads((run / "metrics.json").read_text())["metrics"]
    assert metrics["foundation_success_stage0"] == pytest.approx(R[0, :2].mean())
    assert metrics["retention"] == pytest.approx(R[2, :2].mean())
    assert metrics["plasticity"] == pytest.approx((R[1, 2] + R[2, 3]) / 2)
    assert 0 < metrics["update_relative_l2"]
    stages = json.loads((run / "metrics.json").read_text())["stages"]
    curves = [s["curve"] for s in stages[1:]]
    assert [s["curve_steps"] for s in stages[1:]] == [[0, 5, 10], [0, 5, 10]]
    assert curves[0][0] == R[0, 2] and curves[0][-1] == R[1, 2] and curves[1][-1] == R[2, 3]
    assert metrics["fwt"] == pytest.approx((np.mean(curves[0]) + np.mean(curves[1])) / 2)
    assert metrics["nbt"] == pytest.approx((max(curves[0]) - R[2, 2]) / 2)
    config = (run / "config.yaml").read_text()
    assert "git_commit" in config and "torch" in config and "steps_per_task: 10" in config
    provenance = yaml.safe_load(config)
    assert provenance["git_commits"] == [provenance["git_commit"]]  # one attempt, one commit
    assert provenance["machine"] == machine()  # the CPU that ran it: floats differ across CPUs


def test_mlflow_has_parent_and_child_runs(tiny_run):
    from mlflow.tracking import MlflowClient

    root, _ = tiny_run
    client = MlflowClient(tracking_uri=f"sqlite:///{root}/results/mlflow.db")
    experiment = client.get_experiment_by_name("mw-quick-tiny")
    runs = client.search_runs([experiment.experiment_id])
    children = [r for r in runs if "mlflow.parentRunId" in r.data.tags]
    parents = [r for r in runs if "mlflow.parentRunId" not in r.data.tags]
    assert len(parents) == 1 and len(children) == 1
    child = children[0]
    assert child.data.tags["mlflow.parentRunId"] == parents[0].info.run_id
    assert child.data.params["method"] == "sft" and child.data.params["config.seed"] == "0"
    for run in (child, parents[0]):  # the commit that ran it, as a tag a resumed run extends
        assert run.data.tags["retain.git_commits"] == run.data.params["git_commit"] != ""
    assert child.data.tags["retain.machine.cpu"] == machine()["cpu"] != ""
    assert "retention" in child.data.metrics and "foundation_success" in child.data.metrics
    history = client.get_metric_history(child.info.run_id, "foundation_success")
    assert sorted(m.step for m in history) == [0, 1, 2]
    artifacts = {a.path for a in client.list_artifacts(child.info.run_id)}
    assert {"success_matrix.csv", "metrics.json", "success_matrix.png"} <= artifacts


def test_second_run_reuses_demos_foundation_and_stages(tiny_run, forbid_retraining):
    root, args = tiny_run
    matrix = root / "results/mw-quick-tiny/sft[learning_curve_every=5]/seed0/success_matrix.csv"
    before = matrix.read_text()

    forbid_retraining()
    assert main(args) == 0
    assert matrix.read_text() == before
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=f"sqlite:///{root}/results/mlflow.db")
    runs = client.search_runs([client.get_experiment_by_name("mw-quick-tiny").experiment_id],
                              order_by=["attribute.start_time DESC"])
    assert len(runs) == 2 and all(r.info.status == "FINISHED" for r in runs)  # continued
    resumed = next(r for r in runs if "mlflow.parentRunId" in r.data.tags)
    history = client.get_metric_history(resumed.info.run_id, "foundation_success")
    assert sorted(m.step for m in history) == [0, 1, 2]  # stages from checkpoints are logged too
