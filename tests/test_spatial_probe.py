"""The spatial probe: widened initial states (beyond the demos' range) that are seeded, the same
for every method and stage, and measured to lie outside the demo range; its metrics on a
hand-computed matrix; and a tiny run end to end with the probe on and off."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest

from harness.common.errors import RetainError
from harness.config.benchmark import BenchConfig, resolve, run_key_settings
from harness.measure.metrics import spatial_metrics
from suites import get_suite
from suites.base import SuiteError, is_spatial
from suites.metaworld import widened_box

MW = get_suite("metaworld")
MW_TASKS = ["reach-v3", "push-v3", "drawer-open-v3", "window-open-v3"]


def object_and_goal_xy(obs: dict) -> np.ndarray:
    """Meta-World's observed object x, y (obs 4:6) and goal x, y (obs 36:38)."""
    state = obs["state"]
    return np.concatenate([state[4:6], state[36:38]])


# --- Meta-World --------------------------------------------------------------------------------

def test_widened_box_doubles_x_and_y_within_the_hands_reach():
    low, high, widened = widened_box(np.array([-0.1, 0.4, 0.0, 0.0, 0.6, 0.05]),
                                     np.array([0.1, 0.5, 0.0, 0.0005, 0.7, 0.3]),
                                     np.array([-0.5, 0.4, 0.05]), np.array([0.5, 1.0, 0.5]))
    # x doubled; y doubled but clipped at the hand's reach (0.4); z (heights) and the 0.5 mm
    # jitter of the second x kept
    np.testing.assert_allclose(low, [-0.2, 0.4, 0.0, 0.0, 0.55, 0.05])
    np.testing.assert_allclose(high, [0.2, 0.55, 0.0, 0.0005, 0.75, 0.3])
    assert widened.tolist() == [True, True, False, False, True, False]


def test_metaworld_spatial_keys_are_seeded_the_same_in_every_env():
    keys = MW.episode_keys("push-v3", "spatial", 4)
    assert keys == MW.episode_keys("push-v3", "spatial", 4)
    assert all(is_spatial(k) for k in keys)
    assert not any(is_spatial(k) for split in ("demo", "heldout", "eval")
                   for k in MW.episode_keys("push-v3", split, 50))
    first, second = MW.make_env("push-v3"), MW.make_env("push-v3")
    states = [first.reset(k)["state"] for k in keys]
    second.reset(MW.episode_keys("push-v3", "eval", 1)[0])  # another episode before: no effect
    again = [second.reset(k)["state"] for k in reversed(keys)][::-1]
    for a, b in zip(states, again):
        np.testing.assert_array_equal(a, b)
    positions = [object_and_goal_xy({"state": s}) for s in states]
    assert len({p.tobytes() for p in positions}) == len(keys)  # different states
    first.close()
    second.close()


@pytest.mark.parametrize("task", MW_TASKS)
def test_metaworld_probe_states_lie_beyond_every_demo_and_eval_state(task):
    env = MW.make_env(task)
    box = env._env._random_reset_space  # the task's own range: demos and evaluation draw from it
    inside, heights = [], []
    for split in ("demo", "eval"):
        for key in MW.episode_keys(task, split, 25):
            obs = env.reset(key)
            vec = env._env._last_rand_vec
            assert np.all((vec >= box.low) & (vec <= box.high))
            inside.append(object_and_goal_xy(obs))
            heights.append(obs["state"][6])
    low, high = np.min(inside, axis=0), np.max(inside, axis=0)
    for key in MW.episode_keys(task, "spatial", 10):
        obs = env.reset(key)
        xy = object_and_goal_xy(obs)
        # measured in the observation: some object or goal coordinate beyond all 50 demo and
        # evaluation states, and the object at the height it has in them (on the table)
        assert ((xy < low - 1e-6) | (xy > high + 1e-6)).any(), (task, key, xy, low, high)
        assert min(heights) - 1e-3 <= obs["state"][6] <= max(heights) + 1e-3
        vec = env._env._last_rand_vec
        assert ((vec < box.low) | (vec > box.high)).any()
    env.close()


def test_a_suite_without_a_probe_says_so_before_any_work(capsys):
    from harness.run.cli import main

    assert main(["bench", "BENCH=bimanual-quick", "spatial_episodes=2"]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "suite 'bimanual' has no spatial probe" in err
    bimanual = get_suite("bimanual")
    with pytest.raises(SuiteError, match="no spatial probe"):
        bimanual.episode_keys(bimanual.task_names()[0], "spatial", 2)


# --- LIBERO (one env: building one takes seconds) ---------------------------------------------

def test_libero_probe_moves_floor_objects_beyond_their_demo_range():
    from suites.libero.env import DEMO_RANGE_MARGIN, SPATIAL_OFFSET
    from suites.libero.tasks import init_states, suite_tasks

    suite = get_suite("libero")
    task = suite_tasks("libero_object")[0]
    keys = suite.episode_keys(task, "spatial", 3)
    assert keys == suite.episode_keys(task, "spatial", 3) and all(is_spatial(k) for k in keys)
    assert [k & 63 for k in keys] == [0, 1, 2]  # spatial episode i starts from init state i
    env = suite.make_env(task)
    states = init_states(task)
    for key in keys:
        env.start(key)
        moved = env.sim_state()
        env.start(keys[0] if key != keys[0] else keys[1])
        env.start(key)
        np.testing.assert_array_equal(env.sim_state(), moved)  # the same key, the same state
        fixed = states[key & 63]
        for name in env.objects:  # libero_object: every object stands on the floor
            a = env.qpos_address(name)
            length = np.linalg.norm(moved[a:a + 2] - fixed[a:a + 2])
            assert SPATIAL_OFFSET[0] - 1e-9 <= length <= SPATIAL_OFFSET[1] + 1e-9, name
            np.testing.assert_array_equal(moved[a + 2:a + 7], fixed[a + 2:a + 7])  # z, rotation
            xy, all_xy = moved[a:a + 2], states[:, a:a + 2]
            beyond = (xy < all_xy.min(axis=0) - DEMO_RANGE_MARGIN) | \
                     (xy > all_xy.max(axis=0) + DEMO_RANGE_MARGIN)
            assert beyond.any(), name  # outside the object's range over all 50 init states
        settled = env.reset(key)["state"]
        for i, name in enumerate(env.objects):  # after settling, still where it was put
            a = env.qpos_address(name)
            drift = np.linalg.norm(settled[9 + 7 * i:11 + 7 * i] - moved[a:a + 2])
            assert drift < 0.005, (name, drift)
    env.close()


# --- metrics -----------------------------------------------------------------------------------

def test_spatial_metrics_by_hand():
    # columns: F1, F2 (foundation), S1, S2 (stream); rows: stages 0..2
    S = np.array([[0.6, 0.4, 0.1, 0.0],
                  [0.5, 0.3, 0.7, 0.2],
                  [0.2, 0.0, 0.4, 0.9]])
    m = spatial_metrics(S, [0, 1], [2, 3])
    assert m.spatial_foundation_success_stage0 == pytest.approx(0.5)  # (0.6 + 0.4) / 2
    assert m.spatial_retention == pytest.approx(0.1)  # (0.2 + 0.0) / 2
    assert m.spatial_plasticity == pytest.approx(0.8)  # (S[1, S1] + S[2, S2]) / 2 = (0.7 + 0.9) / 2
    assert set(m.as_dict()) == {"spatial_foundation_success_stage0", "spatial_retention",
                                "spatial_plasticity"}


# --- settings ----------------------------------------------------------------------------------

def test_probe_off_leaves_run_keys_alone_and_bad_counts_fail():
    cfg = BenchConfig("b", "metaworld", ["reach-v3"], ["push-v3"])
    assert cfg.spatial_episodes == 0 and "spatial_episodes" not in run_key_settings(cfg)
    cfg.spatial_episodes = 3
    assert run_key_settings(cfg)["spatial_episodes"] == 3
    with pytest.raises(RetainError, match="spatial_episodes"):
        resolve(["spatial_episodes=-1"])


# --- end to end --------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def two_tiny_runs(tmp_path_factory):
    """The tiny profile twice on one cache: with the probe (2 episodes) and without."""
    from harness.run.cli import main

    root = tmp_path_factory.mktemp("spatial")
    common = ["bench", "PROFILE=tiny", "METHOD=sft", f"results_dir={root}/results",
              f"cache_dir={root}/cache", "progress=false", "eval_workers=1"]
    assert main(common + ["spatial_episodes=2"]) == 0
    assert main(common) == 0
    return root / "results"


def test_probe_on_writes_the_spatial_matrix_and_metrics(two_tiny_runs):
    run = two_tiny_runs / "mw-quick-tiny" / "sft[spatial_episodes=2]" / "seed0"
    with open(run / "spatial_success_matrix.csv") as f:
        rows = list(csv.reader(f))
    assert rows[0][:3] == ["stage", "trained_on", "reach-v3"]
    S = np.array([[float(x) for x in row[2:]] for row in rows[1:]])
    assert S.shape == (3, 4) and np.isin(S, [0.0, 0.5, 1.0]).all()  # two episodes per cell
    metrics = json.loads((run / "metrics.json").read_text())["metrics"]
    assert metrics["spatial_foundation_success_stage0"] == pytest.approx(S[0, :2].mean())
    assert metrics["spatial_retention"] == pytest.approx(S[2, :2].mean())
    assert metrics["spatial_plasticity"] == pytest.approx((S[1, 2] + S[2, 3]) / 2)
    # every stage's spatial success is an MLflow metric of the run, step = stage
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=f"sqlite:///{two_tiny_runs}/mlflow.db")
    experiment = client.get_experiment_by_name("mw-quick-tiny").experiment_id
    child = [r for r in client.search_runs([experiment])
             if r.data.tags.get("label") == "sft[spatial_episodes=2]"]
    history = client.get_metric_history(child[0].info.run_id, "spatial_success/reach-v3")
    assert [(m.step, m.value) for m in history] == [(i, S[i, 0]) for i in range(3)]
    # the probe adds to the normal evaluation and leaves it as it is
    plain = two_tiny_runs / "mw-quick-tiny" / "sft" / "seed0"
    assert (run / "success_matrix.csv").read_text() == (plain / "success_matrix.csv").read_text()


def test_probe_off_writes_nothing_spatial(two_tiny_runs):
    run = two_tiny_runs / "mw-quick-tiny" / "sft" / "seed0"
    assert (run / "success_matrix.csv").exists()
    assert not (run / "spatial_success_matrix.csv").exists()
    metrics = json.loads((run / "metrics.json").read_text())["metrics"]
    assert not any(k.startswith("spatial") for k in metrics)


def test_report_shows_the_spatial_columns_and_figure(two_tiny_runs):
    from harness.report.build import ReportSettings, build_report

    files = build_report(ReportSettings("mw-quick-tiny", str(two_tiny_runs), log_run=False))
    names = {p.name for p in files}
    assert "spatial_vs_retention.png" in names
    summary = (two_tiny_runs / "mw-quick-tiny" / "report" / "summary.csv").read_text()
    with open(two_tiny_runs / "mw-quick-tiny" / "report" / "summary.csv") as f:
        rows = {row["label"]: row for row in csv.DictReader(f)}
    assert "spatial_retention_mean" in summary.splitlines()[0]
    on = json.loads((two_tiny_runs / "mw-quick-tiny" / "sft[spatial_episodes=2]" / "seed0" /
                     "metrics.json").read_text())["metrics"]
    assert float(rows["sft[spatial_episodes=2]"]["spatial_retention_mean"]) == \
        pytest.approx(on["spatial_retention"])
    # the run without the probe: its own row, n/a in the spatial columns
    assert rows["sft[spatial_episodes=0]"]["spatial_retention_mean"] == ""
    markdown = (two_tiny_runs / "mw-quick-tiny" / "report" / "summary.md").read_text()
    assert "spatial retention ↑" in markdown
