"""One robosuite environment class, `TabletopEnv`, that builds any `Scene` from tasks.py.

A Franka Panda at a table (robosuite's TableArena), OSC_POSE delta control at 20 Hz. Objects
are free bodies re-placed on every reset from the env's own `rng` (re-seeded per episode by the
caller); fixtures (bin, marker, region) are fixed bodies built into the model, so one model
serves every episode and resets are cheap (`hard_reset=False`).
"""

from __future__ import annotations

import numpy as np
from robosuite.environments.manipulation.manipulation_env import ManipulationEnv
from robosuite.models.arenas import TableArena
from robosuite.models.objects import (
    Bin,
    BottleObject,
    BoxObject,
    BreadObject,
    CanObject,
    CerealObject,
    CylinderObject,
    LemonObject,
    MilkObject,
)
from robosuite.models.tasks import ManipulationTask
from robosuite.utils.transform_utils import convert_quat

from suites.robosuite_common import TABLE_SIZE, TABLE_TOP
from suites.robosuite_libero.tasks import Scene

BIN_SIZE = (0.16, 0.24, 0.06)  # full x, y, z of the basket (walls 1 cm)
MARKER_RADIUS = 0.04
REGION_HALF = (0.05, 0.2)  # a strip across the far side of the table


def _cube(rgba, half=0.021):
    return lambda name: BoxObject(name, size=[half] * 3, rgba=rgba, friction=[1.0, 5e-3, 1e-4])


OBJECT_MODELS = {
    "milk": lambda name: MilkObject(name),
    "bread": lambda name: BreadObject(name),
    "cereal": lambda name: CerealObject(name),
    "can": lambda name: CanObject(name),
    "lemon": lambda name: LemonObject(name),
    "bottle": lambda name: BottleObject(name),
    "red_cube": _cube([0.8, 0.1, 0.1, 1], 0.02),
    "green_cube": _cube([0.1, 0.7, 0.1, 1], 0.025),
    "blue_cube": _cube([0.1, 0.2, 0.8, 1], 0.021),
}


class _FixedBin(Bin):
    """robosuite's Bin without a free joint: a basket bolted to the table."""

    def _get_geom_attrs(self):
        return {**super()._get_geom_attrs(), "joints": None}


def _fixture_model(kind: str, name: str):
    if kind == "bin":
        return _FixedBin(name, bin_size=BIN_SIZE, transparent_walls=False)
    if kind == "marker":
        return CylinderObject(name, size=[MARKER_RADIUS, 0.001], rgba=[0.9, 0.8, 0.1, 1],
                              obj_type="visual", joints=None)
    if kind == "region":
        return BoxObject(name, size=[*REGION_HALF, 0.001], rgba=[0.2, 0.4, 0.9, 0.6],
                         obj_type="visual", joints=None)
    raise ValueError(f"unknown fixture kind {kind!r}")


class TabletopEnv(ManipulationEnv):
    """A robosuite env for one `Scene`; success is judged by the caller from `object_pos` etc."""

    def __init__(self, scene: Scene, **kwargs):
        self.scene = scene
        super().__init__(robots="Panda", **kwargs)

    # --- model -------------------------------------------------------------------------------
    def _load_model(self):
        super()._load_model()
        robot = self.robots[0].robot_model
        robot.set_base_xpos(robot.base_xpos_offset["table"](TABLE_SIZE[0]))
        arena = TableArena(table_full_size=TABLE_SIZE, table_offset=(0, 0, TABLE_TOP))
        arena.set_origin([0, 0, 0])
        self.objects = [OBJECT_MODELS[kind](f"obj{i}_{kind}")
                        for i, kind in enumerate(self.scene.objects)]
        self.fixtures = []
        for kind, (x, y) in self.scene.fixtures:
            model = _fixture_model(kind, f"fixture_{kind}")
            z = TABLE_TOP + (BIN_SIZE[2] / 2 if kind == "bin" else 0.001)
            model.get_obj().set("pos", f"{x} {y} {z}")
            self.fixtures.append(model)
        self.model = ManipulationTask(mujoco_arena=arena,
                                      mujoco_robots=[r.robot_model for r in self.robots],
                                      mujoco_objects=self.objects + self.fixtures)

    def _setup_references(self):
        super()._setup_references()
        self.object_body_ids = [self.sim.model.body_name2id(o.root_body) for o in self.objects]
        self.object_geom_ids = [[self.sim.model.geom_name2id(g) for g in o.contact_geoms]
                                for o in self.objects]

    def _reset_internal(self):
        super()._reset_internal()
        spots = np.asarray(self.scene.spots)
        order = self.rng.permutation(len(spots))[: len(self.objects)]
        xys = [spot + self.rng.uniform(-self.scene.jitter, self.scene.jitter, size=2)
               for spot in spots[order]]
        self._place(xys, np.full(len(xys), TABLE_TOP + 0.1))
        self.sim.forward()
        # robosuite's bottom/top offsets for mesh objects are off by centimetres: measure the
        # collision geometry instead, then drop every object onto the table surface exactly.
        self.extents = [self._z_extent(i) for i in range(len(self.objects))]
        self._place(xys, [TABLE_TOP + 0.001 - bottom for bottom, _ in self.extents])
        self.sim.forward()

    def _place(self, xys, zs):
        for obj, xy, z in zip(self.objects, xys, zs):
            self.sim.data.set_joint_qpos(obj.joints[0], np.array([xy[0], xy[1], z, 1, 0, 0, 0]))

    def _z_extent(self, i: int) -> tuple[float, float]:
        """(bottom, top) of object i's collision geoms, relative to its body origin (upright)."""
        m, d = self.sim.model._model, self.sim.data._data
        signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)])
        zs = []
        for g in self.object_geom_ids[i]:
            corners = m.geom_aabb[g, :3] + signs * m.geom_aabb[g, 3:]
            zs.append((corners @ d.geom_xmat[g].reshape(3, 3).T + d.geom_xpos[g])[:, 2])
        zs = np.concatenate(zs) - d.xpos[self.object_body_ids[i]][2]
        return float(zs.min()), float(zs.max())

    def reward(self, action=None):
        return 0.0  # the harness uses success only

    # --- privileged state ----------------------------------------------------------------------
    def object_pos(self, i: int) -> np.ndarray:
        return np.array(self.sim.data.body_xpos[self.object_body_ids[i]])

    def object_quat(self, i: int) -> np.ndarray:
        """xyzw, like robosuite's own object observations."""
        return convert_quat(np.array(self.sim.data.body_xquat[self.object_body_ids[i]]), to="xyzw")

    def fixture_pos(self, kind: str) -> np.ndarray:
        for k, (x, y) in self.scene.fixtures:
            if k == kind:
                return np.array([x, y, TABLE_TOP])
        raise KeyError(kind)

    def is_grasped(self, i: int) -> bool:
        return self._check_grasp(self.robots[0].gripper, self.objects[i])

    def eef_pos(self) -> np.ndarray:
        return np.array(self.sim.data.site_xpos[self.robots[0].eef_site_id["right"]])

    def eef_mat(self) -> np.ndarray:
        return np.array(self.sim.data.site_xmat[self.robots[0].eef_site_id["right"]]).reshape(3, 3)
