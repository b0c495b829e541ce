"""`LiberoRSEnv`: one task of the suite as a harness `TaskEnv` (seeding, state vector, success).

State layout (STATE_DIM = 36, identical for every task, zeros where a slot is unused):
  [0:3]   end-effector position (world, m)     [3:7] end-effector quaternion (xyzw)
  [7:9]   gripper finger joint positions
  [9:30]  3 object slots x (position 3, quaternion xyzw 4), in the scene's object order
  [30:36] 2 fixture slots x position 3 (bin / marker / region centre on the table)
"""

from __future__ import annotations

import numpy as np

from suites import robosuite_common
from suites.base import Observation, StepResult, TaskEnv
from suites.robosuite_common import TABLE_TOP, seed_env, upright
from suites.robosuite_libero.expert import WaypointExpert, plan_for
from suites.robosuite_libero.scene import BIN_SIZE, MARKER_RADIUS, REGION_HALF, TabletopEnv
from suites.robosuite_libero.tasks import MAX_OBJECTS, PROPRIO_DIM, STATE_DIM, Task

CAMERAS = {"agentview_image": "agentview", "wrist_image": "robot0_eye_in_hand"}


def make_robosuite_env(task: Task, cameras: bool, image_size: int) -> TabletopEnv:
    from robosuite import load_composite_controller_config

    controller = load_composite_controller_config(controller="BASIC")
    controller["body_parts"] = {"right": {**controller["body_parts"]["right"], "type": "OSC_POSE"}}
    return TabletopEnv(task.scene, controller_configs=controller,
                       **robosuite_common.env_kwargs(cameras, image_size, list(CAMERAS.values())))


class LiberoRSEnv(TaskEnv):
    def __init__(self, task: Task, cameras: bool = False, image_size: int = 84):
        self.task = task
        self.cameras = cameras
        self.env = make_robosuite_env(task, cameras, image_size)
        self.obj = 0
        self.expert: WaypointExpert | None = None

    # --- TaskEnv -------------------------------------------------------------------------------
    def reset(self, seed: int) -> Observation:
        seed_env(self.env, int(seed))  # its Generator drives joint noise and object placement
        raw = self.env.reset()
        self.obj = self._resolve_object()
        self.expert = WaypointExpert(self.env, self.obj, self._plan())
        return self._observation(raw)

    def step(self, action: np.ndarray) -> StepResult:
        action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        raw, _reward, _done, _info = self.env.step(action)
        return StepResult(self._observation(raw), self.success())

    def expert_action(self) -> np.ndarray:
        assert self.expert is not None, "reset() first"
        return self.expert.act()

    def close(self) -> None:
        self.env.close()

    # --- task logic ----------------------------------------------------------------------------
    def _resolve_object(self) -> int:
        """A slot index; spatial words pick by y (the robot's left is +y)."""
        obj = self.task.obj
        if isinstance(obj, int):
            return obj
        order = np.argsort([self.env.object_pos(i)[1] for i in range(len(self.env.objects))])
        return int({"right": order[0], "middle": order[len(order) // 2], "left": order[-1]}[obj])

    def _target(self) -> np.ndarray:
        """The point the object must reach: a fixture centre, the top of another object, or
        for the region strip (pushing) the nearest point on its centre line."""
        target = self.task.target
        if target.startswith("slot:"):
            other = int(target.removeprefix("slot:"))
            return self.env.object_pos(other) + [0, 0, self.env.extents[other][1]]
        pos = self.env.fixture_pos(target)
        if target == "region":
            pos[1] = self.env.object_pos(self.obj)[1]
        return pos

    def _plan(self):
        """The expert's phases; `rest` is where the carried object's bottom is set down."""
        t = self.task
        if t.kind == "lift":
            return plan_for(self.env, "lift", self.obj, None)
        rest = None  # the table
        if t.target == "bin":
            rest = lambda: TABLE_TOP + 0.01
        elif t.target.startswith("slot:"):
            rest = lambda: self._target()[2]
        return plan_for(self.env, t.kind, self.obj, self._target, rest)

    def success(self) -> bool:
        env, t, i = self.env, self.task, self.obj
        pos = env.object_pos(i)
        bottom = pos[2] + env.extents[i][0]
        if t.kind == "lift":
            return bool(bottom > TABLE_TOP + 0.08)
        if t.kind == "push":
            off = np.abs(pos[:2] - env.fixture_pos(t.target)[:2])
            return bool(np.all(off < REGION_HALF) and bottom < TABLE_TOP + 0.01)
        goal = self._target()
        off = np.abs(pos[:2] - goal[:2])
        if env.is_grasped(i):
            return False  # placed means let go
        if t.target == "bin":
            inner = np.array(BIN_SIZE[:2]) / 2 - 0.01
            return bool(np.all(off < inner) and bottom < TABLE_TOP + BIN_SIZE[2])
        if t.target == "marker":
            return bool(np.linalg.norm(off) < MARKER_RADIUS and bottom < TABLE_TOP + 0.01)
        # stacked: centred on the other object and resting on its top
        return bool(np.linalg.norm(off) < 0.025 and abs(bottom - goal[2]) < 0.01)

    # --- observation ---------------------------------------------------------------------------
    def state(self, raw: dict) -> np.ndarray:
        env = self.env
        state = np.zeros(STATE_DIM, dtype=np.float32)
        state[0:3] = raw["robot0_eef_pos"]
        state[3:7] = raw["robot0_eef_quat"]
        state[7:9] = raw["robot0_gripper_qpos"]
        for i in range(len(env.objects)):
            start = PROPRIO_DIM + 7 * i
            state[start:start + 3] = env.object_pos(i)
            state[start + 3:start + 7] = env.object_quat(i)
        for j, (kind, _xy) in enumerate(env.scene.fixtures):
            start = PROPRIO_DIM + 7 * MAX_OBJECTS + 3 * j
            state[start:start + 3] = env.fixture_pos(kind)
        return state

    def _observation(self, raw: dict) -> Observation:
        obs = {"state": self.state(raw)}
        if self.cameras:
            for key, camera in CAMERAS.items():
                obs[key] = upright(raw[f"{camera}_image"])
        return obs
