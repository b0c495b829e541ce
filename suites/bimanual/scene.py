"""Building robosuite two-arm environments for the suite: one table, two Pandas side by side.

Both Pandas stand on the -x edge of the table facing +x (robosuite's "parallel" configuration).
Seen from behind the robots, +y is to their left, so:

    LEFT arm  = robosuite robot 1 (base at y = +0.25)
    RIGHT arm = robosuite robot 0 (base at y = -0.25)

robosuite's flat action vector is [robot0 (7), robot1 (7)] = [right, left]; the suite's 14-d action is
[left (7), right (7)], and `to_robosuite_action` is the only place that swaps them.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from suites import robosuite_common
from suites.robosuite_common import TABLE_SIZE, TABLE_TOP

ARMS = ("left", "right")
ROBOT_INDEX = {"left": 1, "right": 0}  # suite arm name -> robosuite robot index
ARM_ACTION_DIM = 7  # OSC_POSE delta (3 pos + 3 axis-angle rot) + 1 gripper (+1 closes, -1 opens)


def to_robosuite_action(action: np.ndarray) -> np.ndarray:
    """Suite order [left, right] -> robosuite order [robot0 = right, robot1 = left]."""
    left, right = action[:ARM_ACTION_DIM], action[ARM_ACTION_DIM:]
    return np.concatenate([right, left])



# robosuite cameras: the fixed front view, and each arm's wrist camera (robot 1 = left, 0 = right)
AGENTVIEW_CAMERA = "agentview"
WRIST_CAMERAS = {arm: f"robot{ROBOT_INDEX[arm]}_eye_in_hand" for arm in ARMS}


def env_kwargs(cameras: bool, image_size: int) -> dict:
    """Keyword arguments shared by every robosuite env of the suite (20 Hz OSC_POSE deltas).

    With cameras: the agent view at image_size x image_size, and the two wrist cameras at half
    the width each (same height and vertical field of view), to be set side by side."""
    from robosuite import load_composite_controller_config

    names = [AGENTVIEW_CAMERA, WRIST_CAMERAS["left"], WRIST_CAMERAS["right"]]
    half = image_size // 2
    return dict(
        robosuite_common.env_kwargs(cameras, image_size, names),
        camera_widths=[image_size, half, image_size - half],
        robots=["Panda", "Panda"],
        env_configuration="parallel",
        controller_configs=load_composite_controller_config(robot="Panda"),  # OSC_POSE, delta, base frame
    )


@dataclass(frozen=True)
class Item:
    """A free object of a custom scene and the table region its initial pose is drawn from."""

    name: str
    make: Callable[[str], object]  # name -> robosuite MujocoObject
    x: tuple[float, float]
    y: tuple[float, float]
    yaw: tuple[float, float] = (0.0, 0.0)


@dataclass(frozen=True)
class Marker:
    """A flat, visual-only target pad on the table; its position is drawn at every reset."""

    name: str
    x: tuple[float, float]
    y: tuple[float, float]
    rgba: tuple[float, float, float, float] = (0.9, 0.9, 0.2, 0.6)
    radius: float = 0.035


def make_scene_env(items: tuple[Item, ...], markers: tuple[Marker, ...], **kwargs):
    """A robosuite env with the given objects and target pads on the table (class built lazily:
    importing robosuite takes seconds, and the suite registry must stay cheap to import)."""
    return _scene_class()(items=items, markers=markers, **kwargs)


_SCENE_CLASS = None


def _scene_class():
    global _SCENE_CLASS
    if _SCENE_CLASS is None:
        _SCENE_CLASS = _define_scene_class()
    return _SCENE_CLASS


def _define_scene_class():
    import robosuite.utils.transform_utils as T
    from robosuite.environments.manipulation.two_arm_env import TwoArmEnv
    from robosuite.models.arenas import TableArena
    from robosuite.models.objects import BoxObject
    from robosuite.models.tasks import ManipulationTask

    class BimanualScene(TwoArmEnv):
        """Two parallel Pandas at a table with free objects and fixed visual target pads.

        Success is judged by the suite's task specs, so `reward` and `_check_success` are stubs.
        """

        def __init__(self, items, markers, **kwargs):
            self.items = items
            self.markers = markers
            self.objects: dict[str, object] = {}
            super().__init__(**kwargs)

        def _load_model(self):
            super()._load_model()
            for robot, offset in zip(self.robots, (-0.25, 0.25)):
                xpos = np.array(robot.robot_model.base_xpos_offset["table"](TABLE_SIZE[0]))
                robot.robot_model.set_base_xpos(xpos + np.array((0.0, offset, 0.0)))
            arena = TableArena(table_full_size=TABLE_SIZE, table_offset=(0, 0, TABLE_TOP))
            arena.set_origin([0, 0, 0])
            self.objects = {item.name: item.make(item.name) for item in self.items}
            self.pads = {
                m.name: BoxObject(name=m.name, size=[m.radius, m.radius, 0.001], rgba=list(m.rgba),
                                  obj_type="visual", joints=None)
                for m in self.markers
            }
            self.model = ManipulationTask(
                mujoco_arena=arena,
                mujoco_robots=[robot.robot_model for robot in self.robots],
                mujoco_objects=list(self.objects.values()) + list(self.pads.values()),
            )

        def _setup_references(self):
            super()._setup_references()
            self.marker_body_ids = {n: self.sim.model.body_name2id(p.root_body) for n, p in self.pads.items()}

        def _reset_internal(self):
            super()._reset_internal()
            for item in self.items:
                obj = self.objects[item.name]
                xy = [self.rng.uniform(*item.x), self.rng.uniform(*item.y)]
                z = TABLE_TOP - obj.bottom_offset[2] + 0.002
                quat = T.convert_quat(T.axisangle2quat(np.array([0.0, 0.0, self.rng.uniform(*item.yaw)])), to="wxyz")
                self.sim.data.set_joint_qpos(obj.joints[0], np.concatenate([xy, [z], quat]))
            for m in self.markers:
                xy = [self.rng.uniform(*m.x), self.rng.uniform(*m.y)]
                self.sim.model.body_pos[self.marker_body_ids[m.name]] = [*xy, TABLE_TOP + 0.001]
            self.sim.forward()

        def reward(self, action=None):
            return 0.0

        def _check_success(self):
            return False

    return BimanualScene
