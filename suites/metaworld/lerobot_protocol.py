"""Meta-World under lerobot-eval's protocol (registered as "metaworld-lerobot"): what LeRobot
0.6.1's `MetaworldEnv` hands a policy (tests/test_lerobot_eval_parity.py holds it to LeRobot's
own env class).

- The env is built as LeRobot builds it: `metaworld.MT1(task, seed=42)`'s class with its first
  train task, camera "corner2" moved where LeRobot moves it, objects placed by
  `seeded_rand_vec` from `reset(seed)`; evaluation episode i is lerobot-eval's seed 1000 + i
  (its `--seed` default, the same for every task).
- State: LeRobot's `agent_pos`, the first 4 values of Meta-World's observation (hand position
  and gripper), as `observation.state`.
- Images: "corner2" from Meta-World's own renderer, flipped on both axes as LeRobot flips it,
  at Meta-World's 480 px (LeRobot passes no size), as LeRobot's `observation.image`; the wrist
  camera ("gripperPOV", unflipped) is rendered as well, for policies that read two.
- Actions reach Meta-World as lerobot-eval hands them over: float32, unclipped.
- 500 steps (MT1's max_path_length, which lerobot-eval reads as `_max_episode_steps`), ending at
  Meta-World's `success`.
- Instructions: LeRobot's TASK_DESCRIPTIONS (its envs/metaworld_config.json), not Retain's.

The scripted experts still read the goal: the MT1 env's goal is hidden from its observation,
so it is shown again (`_partially_observable = False`), which changes no physics and none of
the four values LeRobot's state keeps.
"""

from __future__ import annotations

import functools
import importlib.util
import json
from pathlib import Path

import numpy as np

from suites import register_suite
from suites.base import AGENTVIEW, EYE_IN_HAND, Observation, StepResult, TaskEnv, is_spatial
from suites.lerobot_protocol import LeRobotProtocol, LeRobotProtocolSuite
from suites.metaworld import MetaWorldEnv, MetaWorldSuite, _expert_classes
from suites.render import MODES

LEROBOT_MT1_SEED = 42  # LeRobot's metaworld.MT1(task, seed=42)
LEROBOT_EVAL_SEED = 1000  # lerobot-eval's --seed default: episode i resets with seed 1000 + i
LEROBOT_MAX_STEPS = 500
LEROBOT_IMAGE_SIZE = 480  # Meta-World's own render size, which LeRobot's env keeps
LEROBOT_CAMERA = "corner2"
LEROBOT_CAMERA_POS = (0.75, 0.075, 0.7)  # where LeRobot's MetaworldEnv puts corner2
LEROBOT_STATE_DIM = 4


@functools.cache
def task_descriptions() -> dict[str, str]:
    """LeRobot's TASK_DESCRIPTIONS, read from its installed metaworld_config.json (importing
    lerobot.envs.metaworld would import gymnasium and all of Meta-World's policies)."""
    spec = importlib.util.find_spec("lerobot")
    if spec is None or not spec.submodule_search_locations:
        raise ModuleNotFoundError("suite metaworld-lerobot reads LeRobot's task descriptions: "
                                  "install lerobot (make venv)")
    path = Path(spec.submodule_search_locations[0]) / "envs" / "metaworld_config.json"
    return dict(json.loads(path.read_text())["TASK_DESCRIPTIONS"])


class MetaWorldLeRobotEnv(MetaWorldEnv):
    """Retain's Meta-World env (experts, spatial probe) on the env LeRobot builds."""

    def __init__(self, task: str, cameras: bool, image_size: int):
        import warnings

        import metaworld

        warnings.filterwarnings("ignore", message="Constant\\(s\\) may be too high")
        self.task = task
        mt1 = metaworld.MT1(task, seed=LEROBOT_MT1_SEED)
        render = {"render_mode": "rgb_array", "camera_name": LEROBOT_CAMERA,
                  "width": image_size, "height": image_size} if cameras else {}
        env = mt1.train_classes[task](**render)
        env.set_task(mt1.train_tasks[0])
        camera = env.model.camera(LEROBOT_CAMERA).id
        env.model.cam_pos[camera] = LEROBOT_CAMERA_POS
        env.reset()
        env._partially_observable = False  # the experts read the goal (module docstring)
        self._env = env
        self._expert = _expert_classes()[task]()
        self._obs, self._allowance, self._renderer, self._view = None, None, None, None
        self.render = MODES["faithful"]  # lerobot-eval's images: Meta-World's own drawing
        self.cameras = cameras
        if cameras:
            import mujoco

            self._renderer = mujoco.Renderer(env.model, image_size, image_size)

    def reset(self, seed: int) -> Observation:
        if is_spatial(seed):
            return super().reset(seed)
        env = self._env
        env._freeze_rand_vec, env.seeded_rand_vec = False, True
        env.seed(int(seed))
        raw, _ = env.reset(seed=int(seed))  # as LeRobot's MetaworldEnv.reset
        return self._observation(raw)

    def step(self, action: np.ndarray) -> StepResult:
        """The action as lerobot-eval hands it over: the policy's float32, unclipped (Meta-World
        clips the hand's move in float32 itself, and MuJoCo's control range bounds the
        gripper; Retain's own suite clips in float64 first, which moves the hand by other bits)."""
        raw, _reward, _term, _trunc, info = self._env.step(np.asarray(action, dtype=np.float32))
        return StepResult(self._observation(raw), bool(info["success"]))

    def _observation(self, raw: np.ndarray) -> Observation:
        self._obs = raw
        obs = {"state": np.asarray(raw[:LEROBOT_STATE_DIM]).astype(np.float32)}
        if self.cameras:
            obs[AGENTVIEW] = np.ascontiguousarray(np.flip(self._env.render(), (0, 1)))
            self._renderer.update_scene(self._env.data, camera="gripperPOV")
            obs[EYE_IN_HAND] = self._renderer.render()
        return obs


@register_suite("metaworld-lerobot")
class MetaWorldLeRobotSuite(LeRobotProtocolSuite, MetaWorldSuite):
    state_dim = LEROBOT_STATE_DIM
    max_episode_steps = LEROBOT_MAX_STEPS
    evaluation_version = "lerobot-1"
    lerobot = LeRobotProtocol("metaworld", LEROBOT_IMAGE_SIZE,
                              (("state", "observation.state"), (AGENTVIEW, "observation.image")))

    def task_names(self) -> list[str]:
        return [t for t in super().task_names() if t in task_descriptions()]

    def instruction(self, task: str) -> str:
        return task_descriptions()[self.check_task(task)]

    def make_env(self, task: str, cameras: bool = False,
                 image_size: int = LEROBOT_IMAGE_SIZE) -> TaskEnv:
        return MetaWorldLeRobotEnv(self.check_task(task), cameras, image_size)

    def episode_keys(self, task: str, split: str, n: int) -> list[int]:
        """Evaluation episode i: lerobot-eval's seed 1000 + i; the other splits as "metaworld"."""
        if split == "eval":
            return [LEROBOT_EVAL_SEED + i for i in range(n)]
        return super().episode_keys(task, split, n)

    def max_steps(self, task: str) -> int:
        return LEROBOT_MAX_STEPS
