"""A synthetic file in exactly LIBERO's HDF5 layout, for the reader and data tests."""

from __future__ import annotations

import json

import h5py
import numpy as np


def write_libero_file(path, lengths=(5, 7), images=True, drop: str | None = None,
                      instruction="put the bowl on the plate", image_size: int = 8):
    """Write demos of `lengths` steps; `drop` omits one dataset of demo_0 ("obs/ee_states")."""
    rng = np.random.default_rng(0)
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        data.attrs["problem_info"] = json.dumps({"language_instruction": instruction})
        for i, steps in enumerate(lengths):
            demo = data.create_group(f"demo_{i}")
            fields = {
                "actions": rng.uniform(-1, 1, (steps, 7)),
                "obs/ee_states": rng.normal(size=(steps, 6)),
                "obs/gripper_states": rng.normal(size=(steps, 2)),
                "obs/joint_states": rng.normal(size=(steps, 7)),
            }
            if images:
                for key in ("agentview_rgb", "eye_in_hand_rgb"):
                    fields[f"obs/{key}"] = rng.integers(
                        0, 255, (steps, image_size, image_size, 3), dtype=np.uint8)
            for key, value in fields.items():
                if not (i == 0 and key == drop):
                    demo.create_dataset(key, data=value)
    return path
