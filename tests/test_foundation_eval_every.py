"""`foundation_eval_every`: the foundation tasks rolled out only at stage 0, every N-th stage and
the last; the stream tasks and every held-out loss at every stage. The skipped cells are NaN
(not evaluated) on disk and absent in MLflow, the metrics come from the stages that were rolled
out, and a rerun resumes without logging a stage twice."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from harness.common.errors import RetainError
from harness.config.benchmark import BenchConfig, resolve, run_key_settings
from harness.evaluate.stages import load_checkpoint
from harness.run.cli import main

RUN = "sft[spatial_episodes=2 foundation_eval_every=2]"


def read_matrix(path) -> np.ndarray:
    with open(path) as f:
        rows = list(csv.reader(f))[1:]
    return np.array([[float(x) for x in row[2:]] for row in rows])


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The tiny profile (2 + 2 tasks, stages 0-2) on one cache: with the foundation rolled out at
    stages 0 and 2 only (and the spatial probe on), and at every stage."""
    root = tmp_path_factory.mktemp("foundation-every")
    common = ["bench", "PROFILE=tiny", "METHOD=sft", f"results_dir={root}/results",
              f"cache_dir={root}/cache", "progress=false", "eval_workers=1", "spatial_episodes=2"]
    sparse = common + ["foundation_eval_every=2"]
    assert main(sparse) == 0
    assert main(common) == 0
    return root, sparse


def test_skipped_stage_has_no_foundation_rollouts(runs):
    root, _ = runs
    base = root / "results" / "mw-quick-tiny"
    sparse_dir, full_dir = base / RUN.replace(" ", "_") / "seed0", base / "sft[spatial_episodes=2]" / "seed0"
    for name in ("success_matrix.csv", "spatial_success_matrix.csv"):
        R, full = read_matrix(sparse_dir / name), read_matrix(full_dir / name)
        assert R.shape == full.shape == (3, 4)
        assert np.isnan(R[1, :2]).all()  # stage 1: the foundation tasks were not rolled out
        assert not np.isnan(R[[0, 2]]).any() and not np.isnan(R[:, 2:]).any()
        assert not np.isnan(full).any()
        np.testing.assert_array_equal(R[0], full[0])  # the shared stage 0
    heldout = read_matrix(sparse_dir / "heldout_loss.csv")
    assert not np.isnan(heldout).any()  # held-out losses at every stage
    stage1, full1 = (load_checkpoint(d / "stages" / "stage_2.pt")["records"][0]
                     for d in (sparse_dir, full_dir))
    assert stage1["episodes"]["reach-v3"] == [] and len(stage1["episodes"]["drawer-close-v3"]) == 2
    assert stage1["env_steps"] < full1["env_steps"]


def test_metrics_use_the_stages_that_were_rolled_out(runs):
    root, _ = runs
    run = root / "results" / "mw-quick-tiny" / RUN.replace(" ", "_") / "seed0"
    R = read_matrix(run / "success_matrix.csv")
    S = read_matrix(run / "spatial_success_matrix.csv")
    m = json.loads((run / "metrics.json").read_text())["metrics"]
    assert m["foundation_success_stage0"] == pytest.approx(R[0, :2].mean())
    assert m["retention"] == pytest.approx(R[2, :2].mean())
    assert m["plasticity"] == pytest.approx((R[1, 2] + R[2, 3]) / 2)
    assert m["forgetting"] == pytest.approx(R[1, 2] - R[2, 2])
    assert m["spatial_retention"] == pytest.approx(S[2, :2].mean())
    assert all(v == v for k, v in m.items() if k != "retention_ratio"), m  # no NaN metric


def _child(root, label):
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=f"sqlite:///{root}/results/mlflow.db")
    experiment = client.get_experiment_by_name("mw-quick-tiny").experiment_id
    child = next(r for r in client.search_runs([experiment]) if r.data.tags.get("label") == label)
    return client, child.info.run_id


def test_rerun_resumes_and_logs_each_stage_once(runs, forbid_retraining):
    root, sparse = runs
    forbid_retraining()
    assert main(sparse) == 0
    client, run_id = _child(root, RUN)

    def steps(key: str) -> list[int]:
        return sorted(m.step for m in client.get_metric_history(run_id, key))

    assert steps("foundation_success") == [0, 2]
    assert steps("success/reach-v3") == [0, 2] and steps("spatial_success/reach-v3") == [0, 2]
    assert steps("success/drawer-close-v3") == [0, 1, 2]
    assert steps("heldout_loss/reach-v3") == [0, 1, 2]


def test_report_reads_the_skipped_cells_as_not_evaluated(runs):
    from harness.report import ReportSettings, build_report
    from harness.report.aggregate import summarize
    from harness.report.groups import build_rows
    from harness.report.runs import experiment_id, load_runs, open_client

    root, _ = runs
    uri = f"sqlite:///{root}/results/mlflow.db"
    client = open_client(uri)
    rows, _ = build_rows(load_runs(client, experiment_id(client, "mw-quick-tiny", uri)))
    by_every = {s.row.runs[0].params["config.foundation_eval_every"]: s
                for s in map(summarize, rows)}
    assert [c.n for c in by_every["2"].foundation_by_stage] == [1, 0, 1]  # stage 1: no value
    assert [c.n for c in by_every["1"].foundation_by_stage] == [1, 1, 1]
    assert np.isnan(by_every["2"].success_mean[1, :2]).all()
    files = build_report(ReportSettings("mw-quick-tiny", str(root / "results"), log_run=False))
    assert "foundation_success.png" in {f.name for f in files}
    assert "foundation_eval_every=2" in (root / "results/mw-quick-tiny/report/summary.md").read_text()


def test_which_stages_roll_the_foundation_out_and_bad_values():
    cfg = BenchConfig("b", "metaworld", ["reach-v3"], [f"t{i}" for i in range(10)])
    assert [i for i in range(11) if cfg.evaluates_foundation(i)] == list(range(11))
    cfg.foundation_eval_every = 4
    assert [i for i in range(11) if cfg.evaluates_foundation(i)] == [0, 4, 8, 10]
    assert run_key_settings(cfg)["foundation_eval_every"] == 4
    cfg.foundation_eval_every = 1  # the default leaves run keys as they were before the setting
    assert "foundation_eval_every" not in run_key_settings(cfg)
    with pytest.raises(RetainError, match="bad value 0 for foundation_eval_every"):
        resolve(["foundation_eval_every=0"])
