"""A file in exactly LIBERO's dataset layout (as its create_dataset.py writes it), for the reader
tests. Its `states` are real sim states of the task (rows of its init-state file), so the reader
can rebuild the suite's state from them; the other arrays are arbitrary but well-shaped."""

from __future__ import annotations

import json

import h5py
import numpy as np


def write_libero_file(path, task: str, states: np.ndarray, lengths=(5, 7), images=True,
                      drop: str | None = None, instruction="a task", bddl_file: str = "",
                      image_size: int = 8):
    """Demos of `lengths` steps whose states are consecutive rows of `states`; `drop` omits one
    dataset of demo_0 (e.g. "obs/ee_states")."""
    rng = np.random.default_rng(0)
    with h5py.File(path, "w") as f:
        data = f.create_group("data")
        data.attrs["problem_info"] = json.dumps({"language_instruction": instruction,
                                                 "problem_name": "libero_floor_manipulation"})
        data.attrs["bddl_file_name"] = bddl_file or f"libero/bddl_files/x/{task}.bddl"
        data.attrs["env_args"] = json.dumps({"type": 1, "env_name": "Libero_Floor_Manipulation"})
        start = 0
        for i, steps in enumerate(lengths):
            demo = data.create_group(f"demo_{i}")
            fields = {
                "actions": rng.uniform(-1, 1, (steps, 7)),
                "states": states[start:start + steps],
                "obs/ee_states": rng.normal(size=(steps, 6)),
                "obs/gripper_states": rng.normal(size=(steps, 2)),
                "obs/joint_states": rng.normal(size=(steps, 7)),
                "rewards": np.zeros(steps), "dones": np.zeros(steps, np.uint8),
            }
            start += steps
            if images:
                for key in ("agentview_rgb", "eye_in_hand_rgb"):
                    fields[f"obs/{key}"] = rng.integers(
                        0, 255, (steps, image_size, image_size, 3), dtype=np.uint8)
            for key, value in fields.items():
                if not (i == 0 and key == drop):
                    demo.create_dataset(key, data=value)
    return path
