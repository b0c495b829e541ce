"""RoboTwin-style bimanual manipulation on MuJoCo through robosuite 1.5: two Panda arms, eight tasks.

Actions are 14-d, [left arm 7 | right arm 7], each arm = OSC_POSE deltas (dx, dy, dz in units of
5 cm, axis-angle rotation in units of 0.5 rad, world frame) + gripper (+1 close, -1 open), at 20 Hz.
"left"/"right" are as seen by the robots (who face +x): left = robosuite robot 1 at y = +0.25.
The state layout (`STATE_LAYOUT`) is shared by all tasks; slots a task does not use are zeros.
See README.md in this folder for the task list and the experts' success table.

Cameras (on request only): `agentview_rgb` is robosuite's "agentview", facing the robots across the
table; `eye_in_hand_rgb` holds both wrist cameras side by side, [left | right], each half as wide
as the image, so every suite has the same two camera keys.
"""

from __future__ import annotations

import functools

import numpy as np

from suites import register_suite
from suites.base import AGENTVIEW, EYE_IN_HAND, Observation, StepResult, TaskEnv, TaskTableSuite
from suites.bimanual.scene import AGENTVIEW_CAMERA, WRIST_CAMERAS, env_kwargs, to_robosuite_action
from suites.bimanual.script import Script, target_orientation
from suites.bimanual.tasks import TASKS
from suites.bimanual.world import read_world
from suites.render import MODES, apply_to_robosuite, check_render
from suites.robosuite_common import seed_env, upright
from suites.views import robosuite_draw, robosuite_state

MAX_OBJECTS = 3
MAX_POINTS = 2
ARM_STATE = ("eef_pos", 3), ("eef_quat", 4), ("gripper_qpos", 2)
STATE_LAYOUT: list[tuple[str, int]] = (
    [(f"{arm}_{key}", n) for arm in ("left", "right") for key, n in ARM_STATE]
    + [(f"object{i}_{key}", n) for i in range(MAX_OBJECTS) for key, n in (("pos", 3), ("quat", 4))]
    + [(f"point{i}_pos", 3) for i in range(MAX_POINTS)]
)
STATE_DIM = sum(n for _, n in STATE_LAYOUT)  # 45
ACTION_DIM = 14


def _quat(mat: np.ndarray) -> np.ndarray:
    """(w, x, y, z) of a rotation matrix."""
    import mujoco

    q = np.zeros(4)
    mujoco.mju_mat2Quat(q, np.ascontiguousarray(mat).reshape(-1))
    return q


def _hemisphere(q: np.ndarray, ref) -> np.ndarray:
    """q and -q are the same rotation; report the one nearer `ref` so the sign never jumps."""
    return q if np.dot(q, ref) >= 0 else -q


# The grip-site orientation of a gripper pointing straight down (fingers along y): the eef quaternions'
# reference, so a downward gripper's quaternion keeps one sign whatever its yaw within +-90 degrees.
@functools.cache
def _eef_ref() -> np.ndarray:
    return _quat(target_orientation(np.pi / 2))


class BimanualEnv(TaskEnv):
    def __init__(self, task: str, cameras: bool, image_size: int, render: str = "faithful"):
        self.spec = TASKS[task]
        self._env = self.spec.build(env_kwargs(cameras, image_size))
        self.render = MODES[check_render(render)]
        if cameras:  # robosuite made the renderer when it built the env (reset in place keeps it)
            apply_to_robosuite(self._env.sim, self.render)
        self._bodies, self._sites = self.spec.names(self._env)
        self._cameras = cameras
        self._script = None
        self._world = None
        self._raw_obs: dict = {}

    # -- TaskEnv
    def reset(self, seed: int) -> Observation:
        seed_env(self._env, int(seed))
        self._raw_obs = self._env.reset()
        self._refresh()
        self._script = Script(self.spec.expert(self._world))
        return self._observation()

    def step(self, action: np.ndarray) -> StepResult:
        action = np.clip(np.asarray(action, dtype=np.float64).reshape(ACTION_DIM), -1.0, 1.0)
        self._raw_obs, _, _, _ = self._env.step(to_robosuite_action(action))
        self._refresh()
        return StepResult(self._observation(), self.success())

    def expert_action(self) -> np.ndarray:
        """The expert's action for this step; call it once per step (its phase clock advances)."""
        assert self._script is not None, "reset() first"
        return self._script.act(self._world)

    def view_state(self) -> np.ndarray:
        return robosuite_state(self._env.sim)

    def render_state(self, state: np.ndarray, camera: str, size: int) -> np.ndarray:
        return robosuite_draw(self._env.sim, state, camera or AGENTVIEW_CAMERA, size, "bimanual")

    def close(self) -> None:
        self._env.close()

    # -- helpers
    def success(self) -> bool:
        return bool(self.spec.success(self._world, self._env))

    @property
    def world(self):
        """Privileged state snapshot (for tests and debugging)."""
        return self._world

    def _refresh(self) -> None:
        self._world = read_world(self._env, self._bodies, self._sites)

    def _observation(self) -> Observation:
        obs = {"state": state_vector(self._world, self.spec)}
        if self._cameras:
            raw = self._raw_obs
            obs[AGENTVIEW] = upright(raw[f"{AGENTVIEW_CAMERA}_image"])
            obs[EYE_IN_HAND] = upright(np.concatenate(
                [raw[f"{WRIST_CAMERAS[arm]}_image"] for arm in ("left", "right")], axis=1))
        return obs


def state_vector(world, spec) -> np.ndarray:
    """Pack a World into the shared STATE_LAYOUT."""
    parts = []
    for arm in ("left", "right"):
        parts += [world.eef_pos[arm], _hemisphere(_quat(world.eef_mat[arm]), _eef_ref()), world.gripper_qpos[arm]]
    for i in range(MAX_OBJECTS):
        if i < len(spec.objects):
            name = spec.objects[i]
            ref = spec.quat_ref.get(name, (1.0, 0.0, 0.0, 0.0))
            parts += [world.pos[name], _hemisphere(world.quat[name], ref)]
        else:
            parts += [np.zeros(7)]
    for i in range(MAX_POINTS):
        parts.append(world.pos[spec.points[i]] if i < len(spec.points) else np.zeros(3))
    state = np.concatenate(parts).astype(np.float32)
    assert state.shape == (STATE_DIM,)
    return state


@register_suite("bimanual")
class BimanualSuite(TaskTableSuite):
    video_camera = AGENTVIEW_CAMERA
    state_dim = STATE_DIM
    action_dim = ACTION_DIM
    max_episode_steps = 400  # 20 s at 20 Hz; the slowest expert needs about half
    simulator_mb = (230.0, 460.0)  # make bench-envs BENCH=bimanual-standard: 229 MB, 461

    def tasks(self) -> dict:
        return TASKS

    def make_env(self, task: str, cameras: bool = False, image_size: int = 84,
                 render: str = "faithful") -> TaskEnv:
        return BimanualEnv(self.check_task(task), cameras, image_size, render)
