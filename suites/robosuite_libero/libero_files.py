"""Read a real LIBERO HDF5 demonstration file into one task's dataset.

LIBERO layout (one file per task):
    data.attrs["problem_info"]            JSON string with "language_instruction"
    data/demo_<i>/actions                 float [T, 7]
    data/demo_<i>/obs/ee_states           float [T, 6]   (position + axis-angle)
    data/demo_<i>/obs/gripper_states      float [T, 2]
    data/demo_<i>/obs/joint_states        float [T, 7]   (not used)
    data/demo_<i>/obs/agentview_rgb       uint8 [T, H, W, 3]   (optional here)
    data/demo_<i>/obs/eye_in_hand_rgb     uint8 [T, H, W, 3]   (optional here)

The episode "state" is concat(ee_states, gripper_states): LIBERO's own proprioception, which is
NOT libero_rs's 36-d layout, so data read here trains policies for real LIBERO only. Images are
kept exactly as LIBERO stored them (its renders are upside down; no flip is applied here).
Anything malformed raises ValueError with one line naming the file and the key.
"""

from __future__ import annotations

import importlib.util
import json
import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

ACTION_DIM = 7
IMAGE_KEYS = {"agentview_rgb": "agentview_image", "eye_in_hand_rgb": "wrist_image"}
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
        info = json.loads(data.attrs["problem_info"])
        return str(info["language_instruction"]).strip()
    except (json.JSONDecodeError, TypeError, KeyError):
        raise _bad(path, "data.attrs['problem_info']['language_instruction']",
                   "missing or unreadable") from None


def _episode(path, demo) -> dict:
    actions = _array(path, demo, "actions", 2, ACTION_DIM).astype(np.float32)
    if "obs" not in demo:
        raise _bad(path, f"{demo.name.lstrip('/')}/obs", "missing key")
    obs_group, steps = demo["obs"], len(actions)
    ee = _array(path, obs_group, "ee_states", 2, length=steps)
    grip = _array(path, obs_group, "gripper_states", 2, length=steps)
    obs = {"state": np.concatenate([ee, grip], axis=1).astype(np.float32)}
    for key, out in IMAGE_KEYS.items():
        if key in obs_group:
            obs[out] = _array(path, obs_group, key, 4, 3, steps).astype(np.uint8)
    return {"actions": actions, "obs": obs}


def read_libero_file(path: str | Path) -> LiberoTaskData:
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
        return LiberoTaskData(_instruction(path, data), [_episode(path, data[k]) for _, k in demos])


# --- evaluating on real LIBERO (optional extra) ----------------------------------------------------
class LiberoUnavailable(RuntimeError):
    """Real-LIBERO evaluation was asked for but the optional `libero` package is absent."""


def libero_env_available() -> bool:
    return importlib.util.find_spec("libero") is not None


def require_libero() -> None:
    """Call before building real LIBERO envs: one clear line instead of a deep ImportError."""
    if not libero_env_available():
        raise LiberoUnavailable(
            "evaluating on real LIBERO needs the optional 'libero' package, which is not "
            "installed (pip install libero, or install LIBERO from its repository); "
            "use suite 'libero_rs' to run without it")
