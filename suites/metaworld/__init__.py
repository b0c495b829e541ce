"""Meta-World v3 (Sawyer arm, MuJoCo): every task that has a scripted expert in `metaworld.policies`.

Observations are Meta-World's 39-d goal-observable state (hand, gripper, two objects, the previous
frame of those, goal). Initial states are seeded per episode through Meta-World's own
`seeded_rand_vec` path, so `reset(seed)` is reproducible across processes.

Cameras (on request only): `agentview_rgb` is Meta-World's "corner" camera, a fixed view of the
table and the arm from the front left, and `eye_in_hand_rgb` its "gripperPOV" camera, mounted on
the hand between the fingers. "corner" is defined with its up axis pointing down, so its image is
rotated by 180 degrees to come out upright (a rotation, not a flip: left stays left).
"""

from __future__ import annotations

import numpy as np

from suites import register_suite
from suites.base import AGENTVIEW, EYE_IN_HAND, Observation, StepResult, Suite, TaskEnv
from suites.metaworld.instructions import INSTRUCTIONS

_STATE_DIM = 39
_ACTION_DIM = 4
# observation key -> (Meta-World camera, whether its image must be turned by 180 degrees)
_CAMERAS = {AGENTVIEW: ("corner", True), EYE_IN_HAND: ("gripperPOV", False)}
_SHADOW_MAP_SIZE = 1024


def _env_classes():
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS_GOAL_OBSERVABLE

    return ALL_V3_ENVIRONMENTS_GOAL_OBSERVABLE


def _expert_classes():
    from metaworld.policies import ENV_POLICY_MAP

    return ENV_POLICY_MAP


class MetaWorldEnv(TaskEnv):
    def __init__(self, task: str, cameras: bool, image_size: int):
        import warnings

        warnings.filterwarnings("ignore", message="Constant\\(s\\) may be too high")
        self.task = task
        self._env = _env_classes()[f"{task}-goal-observable"](seed=0)
        self._expert = _expert_classes()[task]()
        self._obs: np.ndarray | None = None
        self._renderer = None
        if cameras:
            import mujoco

            model = self._env.model
            # Meta-World's 4096^2 shadow map costs more than the image itself at these sizes
            # (twice the render time on a CPU); 1024^2 gives the same shadows at a few hundred pixels
            model.vis.quality.shadowsize = min(model.vis.quality.shadowsize, _SHADOW_MAP_SIZE)
            self._renderer = mujoco.Renderer(model, image_size, image_size)

    def _observation(self, raw: np.ndarray) -> Observation:
        self._obs = raw
        obs = {"state": raw.astype(np.float32)}
        if self._renderer is not None:
            for key, (camera, turn) in _CAMERAS.items():
                self._renderer.update_scene(self._env.data, camera=camera)
                image = self._renderer.render()  # a new array per call
                obs[key] = np.ascontiguousarray(image[::-1, ::-1]) if turn else image
        return obs

    def reset(self, seed: int) -> Observation:
        env = self._env
        env._freeze_rand_vec = False
        env.seeded_rand_vec = True
        env.seed(int(seed))
        raw, _ = env.reset()
        return self._observation(raw)

    def step(self, action: np.ndarray) -> StepResult:
        action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        raw, _reward, _term, _trunc, info = self._env.step(action)
        return StepResult(self._observation(raw), bool(info["success"]))

    def expert_action(self) -> np.ndarray:
        assert self._obs is not None, "reset() first"
        return np.clip(self._expert.get_action(self._obs), -1.0, 1.0).astype(np.float32)

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
        self._env.close()


@register_suite("metaworld")
class MetaWorldSuite(Suite):
    state_dim = _STATE_DIM
    action_dim = _ACTION_DIM
    max_episode_steps = 500  # Meta-World's own limit; benchmarks usually set less

    def task_names(self) -> list[str]:
        envs = {name.removesuffix("-goal-observable") for name in _env_classes()}
        return sorted(envs & set(_expert_classes()) & set(INSTRUCTIONS))

    def instruction(self, task: str) -> str:
        return INSTRUCTIONS[self.check_task(task)]

    def make_env(self, task: str, cameras: bool = False, image_size: int = 84) -> TaskEnv:
        return MetaWorldEnv(self.check_task(task), cameras, image_size)
