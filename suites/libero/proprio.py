"""LIBERO with the state of the community's LIBERO datasets (registered as "libero-proprio"):
8 values of proprioception, end-effector position (3), its orientation as axis-angle (3) and the
gripper's two finger joints (2), as openpi and LeRobot build `observation.state` from LIBERO's
`robot0_eef_pos`, `robot0_eef_quat` and `robot0_gripper_qpos`, and no object poses. Policies
trained on those datasets (physical-intelligence/libero, the LeRobot LIBERO sets) see the scene
through the cameras only, so this suite is run with `cameras=true`.

Tasks, instructions, episodes (the same seeds and init states as "libero"), step limits, experts
and success are LIBERO's, unchanged; only the state vector differs.
"""

from __future__ import annotations

import functools

import numpy as np

from suites import register_suite
from suites.base import TaskEnv
from suites.libero import LiberoSuite

PROPRIO_STATE_DIM = 8


def proprio_state(raw: dict) -> np.ndarray:
    """[eef position, eef axis-angle, gripper qpos] from a raw LIBERO observation."""
    from robosuite.utils.transform_utils import quat2axisangle

    return np.concatenate([raw["robot0_eef_pos"],
                           quat2axisangle(np.asarray(raw["robot0_eef_quat"], np.float64)),
                           raw["robot0_gripper_qpos"]]).astype(np.float32)


@functools.cache
def proprio_env_class() -> type[TaskEnv]:
    """LIBERO's env with the 8-D state (made on first use: env.py imports the simulator)."""
    from suites.libero.env import LiberoTaskEnv

    class LiberoProprioEnv(LiberoTaskEnv):
        def state(self, raw: dict) -> np.ndarray:
            return proprio_state(raw)

    return LiberoProprioEnv


@register_suite("libero-proprio")
class LiberoProprioSuite(LiberoSuite):
    state_dim = PROPRIO_STATE_DIM

    def __init__(self):
        super().__init__()
        self.libero = LiberoSuite()  # whose episode keys (demo scenes) this suite shares

    def make_env(self, task: str, cameras: bool = False, image_size: int = 128) -> TaskEnv:
        return proprio_env_class()(self.task(task), cameras, image_size)

    def episode_keys(self, task: str, split: str, n: int) -> list[int]:
        """The same episodes as suite "libero"'s: the same scenes, another state."""
        return self.libero.episode_keys(task, split, n)
