"""Real LIBERO dataset files (`<suite>/<task>_demo.hdf5`, as distributed) as one task's demos.

LIBERO layout (one file per task, as its create_dataset.py writes it):
    data.attrs["problem_info"]         JSON with "language_instruction"
    data.attrs["bddl_file_name"]       the task's BDDL path (its stem is the task name)
    data/demo_<i>/actions              float [T, 7]  (OSC_POSE deltas + gripper, in [-1, 1])
    data/demo_<i>/states               float [T, S]  flattened MuJoCo state per step
    data/demo_<i>/obs/ee_states        float [T, 6]  position + axis-angle
    data/demo_<i>/obs/gripper_states   float [T, 2]
    data/demo_<i>/obs/joint_states     float [T, 7]
    data/demo_<i>/obs/agentview_rgb    uint8 [T, H, W, 3]   (read when cameras are on)
    data/demo_<i>/obs/eye_in_hand_rgb  uint8 [T, H, W, 3]

The suite's state vector (proprioception plus every object's pose, env.py) is NOT in LIBERO's
`obs` (it has no object poses), so it is rebuilt: every step's `states` is set in the task's
env and the state read back, exactly as the env computes it during evaluation. Proprioception
therefore comes from the sim state too (its ee_states agree with it). Images are taken as LIBERO
stored them, which is also how the env renders them. Anything malformed raises ValueError with
one line naming the file and the key.
"""

from __future__ import annotations

import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ACTION_DIM = 7
IMAGE_KEYS = ("agentview_rgb", "eye_in_hand_rgb")
_DEMO = re.compile(r"demo_(\d+)$")


@dataclass
class LiberoTaskData:
    instruction: str
    episodes: list[dict] = field(default_factory=list)  # {"actions": [T,7], "obs": {...}}


def _bad(path, key: str, why: str) -> ValueError:
    return ValueError(f"{path}: {why} {key!r}")


def _array(path, group, key: str, ndim: int, width: int | None = None,
           length: int | None = None) -> np.ndarray:
    """Dataset `key` of `group`, checked for rank, last-axis width and length."""
    name = f"{group.name.lstrip('/')}/{key}"
    if key not in group:
        raise _bad(path, name, "missing key")
    data = np.asarray(group[key][()])
    if (data.ndim != ndim or (width is not None and data.shape[-1] != width)
            or (length is not None and data.shape[0] != length)):
        raise _bad(path, name, f"bad shape {data.shape} for")
    return data


def _instruction(path, data) -> str:
    if "problem_info" not in data.attrs:
        raise _bad(path, "data.attrs['problem_info']", "missing key")
    try:
        return str(json.loads(data.attrs["problem_info"])["language_instruction"]).strip()
    except (json.JSONDecodeError, TypeError, KeyError):
        raise _bad(path, "data.attrs['problem_info']['language_instruction']",
                   "missing or unreadable") from None


def task_file(demos_dir: str | Path, task: str) -> Path:
    """The file for `task` in `demos_dir` or a suite folder in it: `<task>_demo.hdf5` as LIBERO
    names them, else any .hdf5 file whose `bddl_file_name` attribute names the task's BDDL file."""
    import h5py

    folder = Path(demos_dir)
    if not folder.is_dir():
        raise ValueError(f"demos_dir {str(folder)!r} is not a folder")
    for direct in (folder / f"{task}_demo.hdf5", *sorted(folder.glob(f"*/{task}_demo.hdf5"))):
        if direct.is_file():  # also <demos_dir>/<suite>/<task>_demo.hdf5, LIBERO's datasets tree
            return direct
    for path in sorted(folder.glob("*.hdf5")):
        try:
            with h5py.File(path, "r") as f:
                bddl = str(f["data"].attrs.get("bddl_file_name", "")) if "data" in f else ""
        except OSError:
            continue
        if Path(bddl).stem == task:
            return path
    raise ValueError(f"no LIBERO demo file for task {task!r} in {folder} "
                     f"(expected {task}_demo.hdf5)")


def read_libero_file(path: str | Path, env, cameras: bool = False,
                     image_size: int | None = None) -> LiberoTaskData:
    """The file's demos with the state rebuilt in `env` (a LiberoTaskEnv of the file's task);
    with `cameras`, its images too, which must be `image_size` square (LIBERO's are 128)."""
    import h5py

    path = Path(path)
    try:
        handle = h5py.File(path, "r")
    except OSError as err:
        raise ValueError(f"{path}: not a readable HDF5 file ({err.__class__.__name__})") from None
    with handle:
        if "data" not in handle:
            raise _bad(path, "data", "missing key")
        data = handle["data"]
        demos = sorted((int(m.group(1)), k) for k in data if (m := _DEMO.match(k)))
        if not demos:
            raise _bad(path, "data/demo_<i>", "missing key")
        instruction = _instruction(path, data)
        return LiberoTaskData(instruction, [_episode(path, data[k], env, cameras, image_size)
                                            for _, k in demos])


def _episode(path, demo, env, cameras: bool, image_size: int | None) -> dict:
    actions = _array(path, demo, "actions", 2, ACTION_DIM).astype(np.float32)
    steps = len(actions)
    states = _array(path, demo, "states", 2, length=steps)
    expected = len(env.sim_state())
    if states.shape[1] != expected:
        raise _bad(path, f"{demo.name.lstrip('/')}/states",
                   f"sim states of width {states.shape[1]}, not this task's {expected}, in")
    if "obs" not in demo:
        raise _bad(path, f"{demo.name.lstrip('/')}/obs", "missing key")
    for key in ("ee_states", "gripper_states"):  # LIBERO's layout, checked though rebuilt
        _array(path, demo["obs"], key, 2, length=steps)
    obs = {"state": np.stack([env.observation_from_sim_state(s)["state"] for s in states])}
    if cameras:
        for key in IMAGE_KEYS:
            obs[key] = _array(path, demo["obs"], key, 4, 3, steps).astype(np.uint8)
            if image_size is not None and obs[key].shape[1:3] != (image_size, image_size):
                raise _bad(path, f"{demo.name.lstrip('/')}/obs/{key}",
                           f"images of {obs[key].shape[1]}x{obs[key].shape[2]}, not image_size="
                           f"{image_size}, in")
    return {"actions": actions, "obs": obs}
