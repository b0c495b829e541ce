"""Privileged read-outs from a live LIBERO env: poses, object boxes, sites, joints, grasp.

Everything the expert knows comes from here, read from the simulator each step, so a plan
follows objects that move (settling, being pushed, slipping in the hand).
"""

from __future__ import annotations

import numpy as np

# The eef site's frame with the hand pointing down and the fingers closing along world y
GRIPPER_DOWN = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def hand_down(yaw: float) -> np.ndarray:
    """The hand pointing down, turned `yaw` rad about the vertical from its home pose."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ GRIPPER_DOWN


def _descendants(model, root: int) -> set[int]:
    bodies = {root}
    for b in range(root + 1, model.nbody):
        if model.body_parentid[b] in bodies:
            bodies.add(b)
    return bodies


class Scene:
    """Read-only view of a LIBERO problem env (`OffScreenRenderEnv.env`)."""

    def __init__(self, env):
        self.env = env.env if hasattr(env, "env") and hasattr(env.env, "sim") else env
        self.sim = self.env.sim
        self.model = self.sim.model._model
        self.data = self.sim.data._data
        self._geoms: dict[str, list[int]] = {}

    # -- the robot -------------------------------------------------------------------------
    def eef_pos(self) -> np.ndarray:
        return np.array(self.data.site_xpos[self.env.robots[0].eef_site_id["right"]])

    def eef_mat(self) -> np.ndarray:
        return np.array(self.data.site_xmat[self.env.robots[0].eef_site_id["right"]]).reshape(3, 3)

    def wrist_offset(self) -> np.ndarray:
        """The centre of the box around the arm's last link, in the hand's (eef site's) frame:
        the link turns with the hand and sticks out further on one side of it."""
        m = self.model
        body = m.jnt_bodyid[m.joint(self.env.robots[0].robot_joints[-1]).id]
        local = (self._geom_corners(self._own_geoms(body)) - self.eef_pos()) @ self.eef_mat()
        return (local.min(0) + local.max(0)) / 2

    def is_grasped(self, name: str) -> bool:
        robot = self.env.robots[0]
        return bool(self.env._check_grasp(robot.gripper["right"], self.thing(name)))

    def fingers_still(self) -> bool:
        """The gripper fingers have stopped moving (closed on something, or fully)."""
        robot = self.env.robots[0]
        qvel = self.sim.data.qvel[robot._ref_gripper_joint_vel_indexes["right"]]
        return bool(np.abs(qvel).max() < 0.005)

    # -- objects, fixtures and sites -------------------------------------------------------
    def thing(self, name: str):
        return self.env.get_object(name)

    def is_site(self, name: str) -> bool:
        return name in self.env.object_sites_dict

    def site_parent(self, name: str) -> str:
        return self.env.object_states_dict[name].parent_name

    def body_id(self, name: str) -> int:
        return self.env.obj_body_id[name]

    def pos(self, name: str) -> np.ndarray:
        """An object's body position, or a site's position."""
        if self.is_site(name):
            return np.array(self.sim.data.get_site_xpos(name))
        return np.array(self.data.xpos[self.body_id(name)])

    def mat(self, name: str) -> np.ndarray:
        if self.is_site(name):
            return np.array(self.sim.data.get_site_xmat(name))
        return np.array(self.data.xmat[self.body_id(name)]).reshape(3, 3)

    def site_size(self, name: str) -> np.ndarray:
        return np.array(self.env.object_sites_dict[name].size, dtype=float)

    def _collision_geoms(self, name: str) -> list[int]:
        if name not in self._geoms:
            m = self.model
            bodies = _descendants(m, self.body_id(name))
            self._geoms[name] = [g for g in range(m.ngeom) if m.geom_bodyid[g] in bodies
                                 and (m.geom_contype[g] or m.geom_conaffinity[g])]
        return self._geoms[name]

    def _corners(self, name: str) -> np.ndarray:
        """World corners of the boxes around the object's collision geoms."""
        return self._geom_corners(self._collision_geoms(name))

    def _own_geoms(self, body: int) -> list[int]:
        """One body's own collision geoms (not its children's)."""
        m = self.model
        return [g for g in range(m.ngeom) if m.geom_bodyid[g] == body
                and (m.geom_contype[g] or m.geom_conaffinity[g])]

    def _geom_corners(self, geoms) -> np.ndarray:
        signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], float)
        out = []
        for g in geoms:
            c, h = self.model.geom_aabb[g][:3], self.model.geom_aabb[g][3:]
            rot = self.data.geom_xmat[g].reshape(3, 3)
            out.append(self.data.geom_xpos[g] + (c + signs * h) @ rot.T)
        return np.concatenate(out)

    def box(self, name: str) -> tuple[np.ndarray, np.ndarray]:
        """World axis-aligned bounds (low, high) of an object's collision geometry."""
        pts = self._corners(name)
        return pts.min(0), pts.max(0)

    def part_boxes(self, skip: str) -> list[tuple[np.ndarray, np.ndarray]]:
        """World boxes of every body (its own collision geoms) of the objects and fixtures
        but `skip`: a cabinet's drawer and its top, not one box around the whole cabinet."""
        m = self.model
        out = []
        for name in [*self.env.objects_dict, *self.env.fixtures_dict]:
            if name == skip or name not in self.env.obj_body_id:
                continue
            for body in sorted(_descendants(m, self.body_id(name))):
                geoms = self._own_geoms(body)
                if geoms:
                    pts = self._geom_corners(geoms)
                    out.append((pts.min(0), pts.max(0)))
        return out

    def support_top(self, name: str) -> float:
        """The highest collision point of the bodies the object touches, the robot's excepted:
        what a lift must clear (a drawer's walls around a bowl in it, not just its floor)."""
        m, d = self.model, self.data
        own = _descendants(m, self.body_id(name))
        robot = _descendants(m, m.body(self.env.robots[0].robot_model.root_body).id)
        touching = set()
        for c in d.contact[:d.ncon]:
            b1, b2 = int(m.geom_bodyid[c.geom1]), int(m.geom_bodyid[c.geom2])
            for mine, other in ((b1, b2), (b2, b1)):
                if mine in own and other not in own and other not in robot:
                    touching.add(other)
        bottom = float(self.box(name)[0][2])
        return max([bottom, *(self.body_top(b) for b in touching)])

    def body_top(self, body: int) -> float:
        """The highest point of one body's own collision geoms (not its children's)."""
        geoms = self._own_geoms(body)
        return float(self._geom_corners(geoms)[:, 2].max()) if geoms else -np.inf

    def footprint(self, name: str) -> tuple[float, float, float]:
        """(narrow width, long width, yaw of the narrow direction) of the object seen from above.

        Found by sweeping directions in the plane, so it holds however the model's body frame
        is oriented (some LIBERO objects are modelled lying down and stood up by their pose).
        """
        pts = self._corners(name)[:, :2]
        yaws = np.linspace(0.0, np.pi, 36, endpoint=False)
        dirs = np.stack([np.cos(yaws), np.sin(yaws)], 1)
        proj = pts @ dirs.T
        widths = proj.max(0) - proj.min(0)
        k = int(widths.argmin())
        return float(widths[k]), float(widths.max()), float(yaws[k])

    def joint_qpos(self, name: str) -> float:
        """The first joint of an articulated object (or of a site's joints)."""
        joints = (self.env.object_sites_dict[name].joints if self.is_site(name)
                  else self.thing(name).joints)
        return float(self.sim.data.qpos[self.sim.model.get_joint_qpos_addr(joints[0])])

    def check(self, predicate: list[str]) -> bool:
        """One BDDL goal predicate, evaluated the way LIBERO's success check does."""
        return bool(self.env._eval_predicate(predicate))

    # -- articulated parts -----------------------------------------------------------------
    def joint_name(self, name: str) -> str:
        joints = (self.env.object_sites_dict[name].joints if self.is_site(name)
                  else self.thing(name).joints)
        return joints[0]

    def joint(self, joint: str) -> tuple[np.ndarray, np.ndarray, float]:
        """(world axis, world anchor, position) of a joint."""
        j = self.model.joint(joint).id
        return (np.array(self.data.xaxis[j]), np.array(self.data.xanchor[j]),
                float(self.data.qpos[self.model.jnt_qposadr[j]]))

    def lever(self, joint: str) -> np.ndarray:
        """A point to push a knob by: its highest parts' geom furthest from the hinge axis."""
        body = self.model.jnt_bodyid[self.model.joint(joint).id]
        pos = np.array(self.data.geom_xpos[self._own_geoms(body)])
        top = pos[pos[:, 2] > pos[:, 2].max() - 0.015]
        _, anchor, _ = self.joint(joint)
        return top[int(np.argmax(np.linalg.norm(top[:, :2] - anchor[:2], axis=1)))]

    def handle(self, joint: str, outward: np.ndarray) -> np.ndarray:
        """The collision geom of a joint's moving part that sticks out furthest `outward`."""
        body = self.model.jnt_bodyid[self.model.joint(joint).id]
        pos = np.array(self.data.geom_xpos[self._own_geoms(body)])
        return pos[int(np.argmax(pos @ outward))]
