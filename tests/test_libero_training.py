"""Training samples from a real LIBERO HDF5 file, in exactly LIBERO's layout."""

import pytest
import torch

from harness.data import libero_training_data
from tests.libero_file import write_libero_file


def test_libero_file_becomes_training_samples_a_policy_can_train_on(tmp_path):
    path = write_libero_file(tmp_path / "put_the_bowl_on_the_plate_demo.hdf5", lengths=(6, 9),
                             image_size=32)
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
    path = write_libero_file(tmp_path / "bad.hdf5", drop="obs/gripper_states")
    with pytest.raises(ValueError, match="gripper_states") as info:
        libero_training_data(path, chunk_size=4)
    assert "\n" not in str(info.value)
