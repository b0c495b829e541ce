"""LIBERO as the community's LeRobot datasets carry it: suite "libero-proprio"'s 8-D state
(end-effector position, axis-angle, gripper), and a benchmark that trains on camera images plus
that state from a LeRobot folder and evaluates in LIBERO. Slow: LIBERO envs take seconds to
build, and the run rolls episodes out to LIBERO's 280-step limit."""

from __future__ import annotations

import json

import numpy as np
import pytest

from harness.data.demos import Episode
from harness.data.lerobot.writer import write_dataset
from suites import get_suite

pytestmark = pytest.mark.slow
FOUNDATION = "pick_up_the_alphabet_soup_and_place_it_in_the_basket"
STREAM = "pick_up_the_cream_cheese_and_place_it_in_the_basket"
SIZE = 32


def test_proprio_state_is_libero_state_in_the_community_layout():
    from robosuite.utils.transform_utils import quat2axisangle

    proprio, libero = get_suite("libero-proprio"), get_suite("libero")
    assert proprio.state_dim == 8
    assert proprio.episode_keys(FOUNDATION, "demo", 3) == libero.episode_keys(FOUNDATION, "demo", 3)
    from suites.libero.env import LiberoTaskEnv

    env = proprio.make_env(FOUNDATION)
    try:
        short = env.reset(4)["state"]
        full = LiberoTaskEnv.state(env, env.raw_obs)  # the same scene in suite libero's layout
    finally:
        env.close()
    assert short.shape == (8,) and short.dtype == np.float32
    np.testing.assert_allclose(short[:3], full[:3])
    np.testing.assert_allclose(short[3:6], quat2axisangle(full[3:7].astype(np.float64)), atol=1e-5)
    np.testing.assert_allclose(short[6:], full[7:9])


def test_cameras_and_proprioception_train_and_evaluate_from_a_lerobot_folder(tmp_path,
                                                                            monkeypatch):
    """Benchmark libero-lerobot-quick (pi0, tiny), on a v3.0 folder laid out as the community's
    LIBERO sets (8-D state, both cameras as video, turned 180 degrees), one task of each stage."""
    from harness.run.cli import main

    suite = get_suite("libero-proprio")
    rng = np.random.default_rng(0)

    def episode(n: int) -> Episode:
        images = rng.integers(0, 255, (n, SIZE, SIZE, 3), dtype=np.uint8)
        return Episode(rng.uniform(-1, 1, (n, 7)).astype(np.float32),
                       {"state": rng.normal(size=(n, 8)).astype(np.float32),
                        "agentview_rgb": images, "eye_in_hand_rgb": images[:, ::-1].copy()}, -1)

    write_dataset(tmp_path / "ds", [(suite.instruction(t), [episode(6) for _ in range(4)])
                                    for t in (FOUNDATION, STREAM)], fps=20, rotate_images=True)
    monkeypatch.chdir(tmp_path)  # relative folders keep the run's label (its directory) short
    code = main(["bench", "BENCH=libero-lerobot-quick", "PROFILE=tiny", "demos_dir=ds",
                 f"foundation_tasks={FOUNDATION}", f"stream_tasks={STREAM}", f"image_size={SIZE}",
                 "eval_episodes=1", "executor=serial", "eval_workers=1", "results_dir=results",
                 "cache_dir=cache"])
    assert code == 0
    metrics = json.loads(next((tmp_path / "results").rglob("metrics.json")).read_text())
    assert 0.0 <= metrics["metrics"]["foundation_success_stage0"] <= 1.0  # rolled out in LIBERO
    cached = sorted((tmp_path / "cache/demos/libero-proprio").glob("*.hdf5"))
    assert len(cached) == 4  # two tasks, two splits, read from the folder
    from harness.evaluate.stages import load_checkpoint

    policy = load_checkpoint(next((tmp_path / "cache/foundation").rglob("policy.pt")))["policy"]
    assert policy["state_norm.mean"].shape == (8,)  # the policy read the 8-D state
    assert any(k.startswith("vision.") for k in policy)  # and the cameras
