"""Training samples from a real LIBERO HDF5 file, in exactly LIBERO's layout."""

import json

import h5py
import numpy as np
import pytest
import torch

from harness.data import libero_training_data


def _write_libero(path, lengths=(6, 9)):
    rng = np.random.default_rng(0)
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        data.attrs["problem_info"] = json.dumps({"language_instruction": "put the bowl on the plate",
                                                 "problem_name": "libero_goal"})
        for i, t in enumerate(lengths):
            demo = data.create_group(f"demo_{i}")
            demo.create_dataset("actions", data=rng.uniform(-1, 1, (t, 7)))
            demo.create_dataset("obs/ee_states", data=rng.standard_normal((t, 6)))
            demo.create_dataset("obs/gripper_states", data=rng.standard_normal((t, 2)))
            demo.create_dataset("obs/joint_states", data=rng.standard_normal((t, 7)))
            demo.create_dataset("obs/agentview_rgb", data=rng.integers(0, 255, (t, 32, 32, 3), np.uint8))
            demo.create_dataset("obs/eye_in_hand_rgb", data=rng.integers(0, 255, (t, 32, 32, 3), np.uint8))


def test_libero_file_becomes_training_samples_a_policy_can_train_on(tmp_path):
    path = tmp_path / "put_the_bowl_on_the_plate_demo.hdf5"
    _write_libero(path)
    data = libero_training_data(path, chunk_size=4, cache_dir=tmp_path / "instructions")
    assert len(data) == 15
    assert data.obs["state"].shape == (15, 8) and data.obs["agentview_image"].shape == (15, 32, 32, 3)
    assert data.actions.shape == (15, 4, 7)
    assert data.action_mask[5].tolist() == [True, False, False, False]  # end of the first demo
    from policies import FlowMatchingConfig, FlowMatchingPolicy

    policy = FlowMatchingPolicy(FlowMatchingConfig(8, 7, size="tiny", image_keys=("agentview_image",),
                                                   image_size=32))
    loss = policy(data.sample(4, torch.Generator().manual_seed(0)))
    assert loss.shape == (4,) and torch.isfinite(loss).all()


def test_malformed_libero_file_names_the_missing_key(tmp_path):
    path = tmp_path / "bad.hdf5"
    _write_libero(path)
    with h5py.File(path, "a") as f:
        del f["data/demo_1/obs/gripper_states"]
    with pytest.raises(ValueError, match="gripper_states") as info:
        libero_training_data(path, chunk_size=4)
    assert "\n" not in str(info.value)
