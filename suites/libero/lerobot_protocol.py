"""LIBERO under lerobot-eval's protocol (registered as "libero-lerobot"): what LeRobot 0.6.1's
`LiberoEnv` and `LiberoProcessorStep` hand a policy, so a checkpoint fine-tuned and evaluated
with LeRobot sees here what it sees in lerobot-eval (tests/test_lerobot_eval_parity.py holds it
to LeRobot's own env class).

- Episode i: LIBERO's init state i, then 10 steps of [0,0,0,0,0,0,-1] (LeRobot's
  `num_steps_wait`; Retain's SETTLE_STEPS and NOOP are the same), in OSC_POSE delta control
  (LeRobot's control_mode="relative").
- Step limits: LeRobot's TASK_SUITE_MAX_STEPS (spatial 280, where suite "libero" keeps openpi's
  and OpenVLA's 220), ending at LIBERO's `check_success()`.
- State: LeRobot's 8-D `observation.state`, built by LeRobot's own `LiberoProcessorStep` (eef
  position, the quaternion's axis-angle computed in float32 as LeRobot does, gripper qpos).
- Images: both cameras flipped on both axes as `LiberoProcessorStep` flips them, rendered at
  lerobot-eval's 360 px (its EnvConfig; `LiberoEnv` alone defaults to 256); the agent view is
  LeRobot's `observation.images.image`, the wrist `observation.images.image2`.
- Instructions: LIBERO's BDDL language, as LeRobot's `task_description`.

One difference stays, by design: LIBERO's reset places fixtures (cabinets, stoves) from numpy's
global RNG, which lerobot-eval leaves unseeded (so its fixtures move from run to run by up to
1 cm); Retain seeds it with the episode's key, so its episodes repeat.
"""

from __future__ import annotations

import numpy as np

from suites import register_suite
from suites.base import CAMERA_KEYS, TaskEnv
from suites.lerobot_protocol import LeRobotProtocol, LeRobotProtocolSuite
from suites.libero import LiberoSuite

# lerobot 0.6.1's envs/libero.py TASK_SUITE_MAX_STEPS (a test compares them)
LEROBOT_MAX_STEPS = {"libero_spatial": 280, "libero_object": 280, "libero_goal": 300,
                     "libero_10": 520, "libero_90": 400}
LEROBOT_IMAGE_SIZE = 360  # lerobot-eval's LiberoEnv config: observation_height/width
LEROBOT_STATE_DIM = 8


def lerobot_state(raw: dict) -> np.ndarray:
    """LeRobot's `observation.state` from a raw LIBERO observation, by LeRobot's own
    `LiberoProcessorStep` (its float32 axis-angle differs from robosuite's float64 one in the
    last bits, which a policy sees)."""
    import torch
    from lerobot.processor.env_processor import LiberoProcessorStep

    def row(key: str) -> torch.Tensor:
        return torch.from_numpy(np.asarray(raw[key], dtype=np.float64))[None]

    robot_state = {"eef": {"pos": row("robot0_eef_pos"), "quat": row("robot0_eef_quat")},
                   "gripper": {"qpos": row("robot0_gripper_qpos")}}
    out = LiberoProcessorStep().observation({"observation.robot_state": robot_state})
    return out["observation.state"][0].numpy()


def flip_images(obs: dict) -> dict:
    """Both axes of every camera image flipped (LeRobot's LiberoProcessorStep)."""
    return {k: np.ascontiguousarray(v[::-1, ::-1]) if k in CAMERA_KEYS else v
            for k, v in obs.items()}


_ENV_CLASS: list[type] = []


def lerobot_env_class() -> type[TaskEnv]:
    """LIBERO's env with LeRobot's state and image orientation (made on first use: env.py
    imports the simulator)."""
    if not _ENV_CLASS:
        from suites.libero.env import LiberoTaskEnv

        class LiberoLeRobotEnv(LiberoTaskEnv):
            def state(self, raw: dict) -> np.ndarray:
                return lerobot_state(raw)

            def _observation(self, raw: dict) -> dict:
                return flip_images(super()._observation(raw))

        _ENV_CLASS.append(LiberoLeRobotEnv)
    return _ENV_CLASS[0]


@register_suite("libero-lerobot")
class LiberoLeRobotSuite(LeRobotProtocolSuite, LiberoSuite):
    state_dim = LEROBOT_STATE_DIM
    max_episode_steps = max(LEROBOT_MAX_STEPS.values())
    evaluation_version = "lerobot-1"
    lerobot = LeRobotProtocol("libero", LEROBOT_IMAGE_SIZE,
                              (("state", "observation.state"),
                               ("agentview_rgb", "observation.images.image"),
                               ("eye_in_hand_rgb", "observation.images.image2")))

    def __init__(self):
        super().__init__()
        self.libero = LiberoSuite()  # whose episode keys (init states, demo scenes) it shares

    def make_env(self, task: str, cameras: bool = False,
                 image_size: int = LEROBOT_IMAGE_SIZE) -> TaskEnv:
        return lerobot_env_class()(self.task(task), cameras, image_size)

    def episode_keys(self, task: str, split: str, n: int) -> list[int]:
        """Suite "libero"'s: evaluation episode i is init state i, as in lerobot-eval."""
        return self.libero.episode_keys(task, split, n)

    def max_steps(self, task: str) -> int:
        return LEROBOT_MAX_STEPS[self.task(task).suite]
