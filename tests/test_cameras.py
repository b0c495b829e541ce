"""Camera observations: rendered only when asked for, upright, under LIBERO's key names, and
carried from the simulator into the demo file, the training batch and the policy."""

import h5py
import numpy as np
import pytest
import torch

from harness.config.benchmark import BenchConfig
from harness.data.demos import read_demo_file
from harness.data.prepare import prepare_data
from harness.protocol.foundation import build_policy
from suites import get_suite
from suites.base import CAMERA_KEYS

SIZE = 32


def _wood_row(image: np.ndarray) -> float:
    """Mean row of the table's wood-brown pixels."""
    r, g, b = (image[..., i].astype(int) for i in range(3))
    rows, _ = np.nonzero((r > g + 15) & (g > b + 10) & (g > 50))
    return float(rows.mean())


def test_metaworld_renders_both_cameras_upright():
    env = get_suite("metaworld").make_env("reach-v3", cameras=True, image_size=SIZE)
    try:
        obs = env.reset(0)
        assert set(obs) == {"state", *CAMERA_KEYS}
        for key in CAMERA_KEYS:
            assert obs[key].dtype == np.uint8 and obs[key].shape == (SIZE, SIZE, 3)
        assert env.step(np.zeros(4)).obs["eye_in_hand_rgb"].shape == (SIZE, SIZE, 3)
        # the table lies in the lower part of the front view (Meta-World's "corner" camera is
        # upside down as defined)
        assert _wood_row(obs["agentview_rgb"]) > 0.6 * SIZE
    finally:
        env.close()


def test_without_cameras_nothing_is_rendered():
    env = get_suite("metaworld").make_env("reach-v3")
    try:
        assert set(env.reset(0)) == {"state"} and env._renderer is None
    finally:
        env.close()


def test_images_flow_from_the_simulator_to_the_demo_file_the_batch_and_the_policy(tmp_path):
    cfg = BenchConfig(name="cameras", suite="metaworld", foundation_tasks=["reach-v3"],
                      stream_tasks=[], demos_per_task=1, heldout_demos_per_task=1,
                      max_episode_steps=100, cameras=True, image_size=SIZE, policy_size="tiny",
                      cache_dir=str(tmp_path), progress=False)
    suite = get_suite("metaworld")
    data = prepare_data(cfg, suite)
    [path] = (tmp_path / "demos" / "metaworld").glob("reach-v3.demo.*.hdf5")
    with h5py.File(path) as f:
        demo = f["data/demo_0"]
        steps = len(demo["actions"])
        for key in CAMERA_KEYS:  # LIBERO's layout: data/demo_<i>/obs/agentview_rgb
            assert demo[f"obs/{key}"].dtype == np.uint8
            assert demo[f"obs/{key}"].shape == (steps, SIZE, SIZE, 3)
            assert demo[f"obs/{key}"].compression == "gzip"
    [episode] = read_demo_file(path)[1]  # lossless: the file holds what training used
    for key in CAMERA_KEYS:
        assert np.array_equal(episode.obs[key], data.train["reach-v3"].obs[key][:steps].numpy())
    batch = data.train["reach-v3"].batch(torch.arange(5))
    for key in CAMERA_KEYS:
        assert batch[key].dtype == torch.uint8 and batch[key].shape == (5, SIZE, SIZE, 3)
    policy = build_policy(cfg, suite)
    assert tuple(policy.image_encoders) == CAMERA_KEYS
    loss = policy(batch)
    assert loss.shape == (5,) and torch.isfinite(loss).all()
    loss.mean().backward()  # the image encoders learn from the images
    assert all(p.grad is not None and p.grad.abs().sum() > 0
               for p in policy.image_encoders.parameters())


def test_bimanual_renders_the_front_view_and_both_wrists():
    pytest.importorskip("robosuite")
    env = get_suite("bimanual").make_env("dual_lift", cameras=True, image_size=SIZE)
    try:
        obs = env.reset(0)
        assert set(obs) == {"state", *CAMERA_KEYS}
        for key in CAMERA_KEYS:
            assert obs[key].dtype == np.uint8 and obs[key].shape == (SIZE, SIZE, 3)
        # [left wrist | right wrist]: two different cameras, not one image twice
        wrists = obs["eye_in_hand_rgb"]
        assert not np.array_equal(wrists[:, : SIZE // 2], wrists[:, SIZE // 2:])
    finally:
        env.close()
