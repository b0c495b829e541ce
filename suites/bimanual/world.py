"""A snapshot of the privileged simulator state that experts, success checks and observations read."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from suites.bimanual.scene import ARMS, ROBOT_INDEX


@dataclass(frozen=True)
class World:
    """Grip-site poses of both arms, gripper finger joints, and named body/site positions.

    `eef_mat` columns are the grip site's axes in the world: column 0 is the direction the fingers
    close along, column 2 points out of the gripper (down when grasping from above).
    """

    eef_pos: dict[str, np.ndarray]
    eef_mat: dict[str, np.ndarray]
    gripper_qpos: dict[str, np.ndarray]
    pos: dict[str, np.ndarray]  # body or site name -> world position
    quat: dict[str, np.ndarray]  # body name -> world orientation, (w, x, y, z) as MuJoCo stores it

    def finger_yaw(self, arm: str) -> float:
        """Heading (rad, world xy-plane) of the axis the fingers close along."""
        axis = self.eef_mat[arm][:, 0]
        return float(np.arctan2(axis[1], axis[0]))

    def yaw(self, body: str) -> float:
        """Heading of a body's x axis in the world xy-plane."""
        w, x, y, z = self.quat[body]
        return float(np.arctan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z)))

    def tilt(self, body: str) -> float:
        """Angle (rad) between a body's z axis and the world's vertical."""
        w, x, y, z = self.quat[body]
        cos = 1 - 2 * (x * x + y * y)
        return float(np.arccos(np.clip(cos, -1.0, 1.0)))


def read_world(env, bodies: dict[str, str], sites: dict[str, str]) -> World:
    """Read `env` (a robosuite two-arm env); `bodies`/`sites` map suite names to MuJoCo names."""
    model, data = env.sim.model, env.sim.data
    eef_pos, eef_mat, grip = {}, {}, {}
    for arm in ARMS:
        robot = env.robots[ROBOT_INDEX[arm]]
        sid = robot.eef_site_id["right"]  # a Panda's only arm is called "right" inside robosuite
        eef_pos[arm] = np.array(data.site_xpos[sid])
        eef_mat[arm] = np.array(data.site_xmat[sid]).reshape(3, 3)
        grip[arm] = np.array(data.qpos[robot._ref_gripper_joint_pos_indexes["right"]])
    pos, quat = {}, {}
    for name, body in bodies.items():
        bid = model.body_name2id(body)
        pos[name] = np.array(data.body_xpos[bid])
        quat[name] = np.array(data.body_xquat[bid])
    for name, site in sites.items():
        pos[name] = np.array(data.site_xpos[model.site_name2id(site)])
    return World(eef_pos, eef_mat, grip, pos, quat)
