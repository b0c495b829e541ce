"""The libero_rs suite: shape, cameras, the expert table and the real-LIBERO file reader (seeding
and experts: tests/test_suites.py)."""

from __future__ import annotations

import numpy as np
import pytest

from suites import get_suite
from tests.libero_file import write_libero_file

h5py = pytest.importorskip("h5py")
pytest.importorskip("robosuite")

SUITE = get_suite("libero_rs")
TASKS = SUITE.task_names()


def test_suite_shape():
    assert len(TASKS) >= 12
    assert SUITE.state_dim == 36 and SUITE.action_dim == 7  # env.py's documented layout
    instructions = [SUITE.instruction(t) for t in TASKS]
    assert all(instructions) and len(set(instructions)) == len(TASKS)
    with pytest.raises(ValueError, match="unknown libero_rs task"):
        SUITE.make_env("no_such_task")


def test_cameras_give_uint8_images():
    env = SUITE.make_env("goal_lift_red", cameras=True, image_size=32)  # needs MUJOCO_GL=egl
    try:
        obs = env.reset(0)
        for key in ("agentview_image", "wrist_image"):
            assert obs[key].shape == (32, 32, 3) and obs[key].dtype == np.uint8
        assert env.step(np.zeros(7)).obs["agentview_image"].shape == (32, 32, 3)
    finally:
        env.close()


# --- real LIBERO files ---------------------------------------------------------------------------


def test_libero_reader_round_trips(tmp_path):
    from suites.robosuite_libero.libero_files import read_libero_file

    path = write_libero_file(tmp_path / "task_demo.hdf5")
    task = read_libero_file(path)
    assert task.instruction == "put the bowl on the plate"
    assert [len(e["actions"]) for e in task.episodes] == [5, 7]
    with h5py.File(path) as f:
        demo = f["data/demo_1"]
        episode = task.episodes[1]
        assert episode["actions"].dtype == np.float32
        np.testing.assert_allclose(episode["actions"], demo["actions"][()], rtol=1e-6)
        state = np.concatenate([demo["obs/ee_states"][()], demo["obs/gripper_states"][()]], 1)
        np.testing.assert_allclose(episode["obs"]["state"], state, rtol=1e-6)
        assert np.array_equal(episode["obs"]["agentview_image"], demo["obs/agentview_rgb"][()])
        assert np.array_equal(episode["obs"]["wrist_image"], demo["obs/eye_in_hand_rgb"][()])
    no_images = read_libero_file(write_libero_file(tmp_path / "plain.hdf5", images=False))
    assert set(no_images.episodes[0]["obs"]) == {"state"}


@pytest.mark.parametrize("drop, key", [("obs/ee_states", "data/demo_0/obs/ee_states"),
                                       ("actions", "data/demo_0/actions")])
def test_libero_reader_names_missing_key(tmp_path, drop, key):
    from suites.robosuite_libero.libero_files import read_libero_file

    path = write_libero_file(tmp_path / "broken.hdf5", drop=drop)
    with pytest.raises(ValueError) as err:
        read_libero_file(path)
    message = str(err.value)
    assert "\n" not in message and str(path) in message and key in message


def test_libero_reader_rejects_bad_shapes_and_non_hdf5(tmp_path):
    from suites.robosuite_libero.libero_files import read_libero_file

    path = write_libero_file(tmp_path / "shape.hdf5")
    with h5py.File(path, "a") as f:
        del f["data/demo_1/actions"]
        f["data/demo_1/actions"] = np.zeros((7, 6))
    with pytest.raises(ValueError, match="bad shape .*data/demo_1/actions"):
        read_libero_file(path)
    text = tmp_path / "notes.hdf5"
    text.write_text("not hdf5")
    with pytest.raises(ValueError, match="not a readable HDF5 file"):
        read_libero_file(text)


def test_real_libero_missing_is_one_clear_line(monkeypatch):
    from suites.robosuite_libero import libero_files

    monkeypatch.setattr(libero_files, "libero_env_available", lambda: False)
    with pytest.raises(libero_files.LiberoUnavailable) as err:
        libero_files.require_libero()
    assert "'libero' package" in str(err.value) and "\n" not in str(err.value)


def test_expert_table_rewrites_only_its_block(tmp_path):
    from suites.robosuite_libero.expert_table import (
        BEGIN,
        END,
        ExpertResult,
        render_table,
        write_table,
    )

    readme = tmp_path / "README.md"
    readme.write_text(f"intro\n{BEGIN}\nold\n{END}\noutro\n")
    write_table(render_table([ExpertResult("t", "goal", 19, 20, 88.0)], 150.0), readme)
    text = readme.read_text()
    assert "| `t` | goal | 19/20 (95%) | 88.0 |" in text
    assert text.startswith("intro\n") and text.endswith("outro\n") and "old" not in text
