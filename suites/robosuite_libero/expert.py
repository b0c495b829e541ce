"""The scripted expert: one waypoint state machine, parametrised by task kind, for every task.

A plan is a list of `Phase`s, each an end-effector target recomputed every step from privileged
object state (so it tracks objects that move) plus a gripper command. A phase ends when the
target is reached, after a fixed number of steps (gripper phases), or on its own test (push).
If the object slips out of the hand mid-carry, the plan restarts from the approach.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from robosuite.utils.control_utils import orientation_error

from suites.robosuite_common import CLOSED, OPEN, POS_SCALE, ROT_SCALE, TABLE_TOP
from suites.robosuite_libero.scene import TabletopEnv

GRIPPER_DOWN = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])  # Panda's home
SAFE_Z = TABLE_TOP + 0.25  # travel height for the hand with nothing in it
CLEARANCE = 0.12  # carried object's bottom above the table while travelling (bin walls: 6 cm)
MAX_PHASE_STEPS = 60  # a move that cannot finish (blocked) gives up and moves on


@dataclass
class Phase:
    name: str
    target: Callable[[], np.ndarray]  # end-effector position to move to
    grip: float
    steps: int = 0  # >0: a timed phase (open/close the gripper) instead of a move
    tol: float = 0.008
    carrying: bool = False  # the object must stay in hand; otherwise restart the plan
    done: Callable[[], bool] | None = None
    speed: float = 1.0  # action-norm cap for the translation
    limit: int = MAX_PHASE_STEPS


class WaypointExpert:
    """Runs a plan built by `plan_for`; `act()` returns a 7-d action in [-1, 1]."""

    def __init__(self, env: TabletopEnv, obj: int, plan: list[Phase]):
        self.env, self.obj, self.plan = env, obj, plan
        self.i = self.t = 0

    def act(self) -> np.ndarray:
        env = self.env
        phase = self._advance()
        eef = env.eef_pos()
        delta = (phase.target() - eef) / POS_SCALE
        norm = np.linalg.norm(delta)
        if norm > phase.speed:
            delta *= phase.speed / norm
        rot_action = orientation_error(GRIPPER_DOWN, env.eef_mat()) / ROT_SCALE
        return np.clip(np.concatenate([delta, rot_action, [phase.grip]]), -1, 1).astype(np.float32)

    def _advance(self) -> Phase:
        env = self.env
        while True:
            phase = self.plan[self.i]
            if phase.carrying and self.t > 2 and not env.is_grasped(self.obj):
                self.i = self.t = 0  # dropped it: start over
                continue
            if phase.steps:
                finished = self.t >= phase.steps
            elif phase.done:
                finished = phase.done() or self.t >= phase.limit
            else:
                reached = np.linalg.norm(phase.target() - env.eef_pos()) < phase.tol
                finished = reached or self.t >= phase.limit
            if finished and self.i < len(self.plan) - 1:
                self.i, self.t = self.i + 1, 0
                continue
            self.t += 1
            return phase


def plan_for(env: TabletopEnv, kind: str, obj: int, target: Callable[[], np.ndarray] | None,
             target_top: Callable[[], float] | None = None) -> list[Phase]:
    """The phase list for one task kind ("place", "lift", "push").

    `target()` is the goal point on the table (or the top centre of the object to stack on);
    `target_top()` the height the carried object's bottom must end at, if not the table.
    """
    bottom, top = env.extents[obj]
    grasp_dz = max(0.0, top - 0.03)  # grip tall things near the top, so the hand clears them
    below_grip = grasp_dz - bottom  # from the grip point down to the object's bottom

    def obj_xy():
        return env.object_pos(obj)[:2]

    def at(xy, z):
        return lambda: np.array([*xy(), z() if callable(z) else z])

    grasp_z = lambda: env.object_pos(obj)[2] + grasp_dz
    pick = [
        Phase("above", at(obj_xy, SAFE_Z), OPEN, tol=0.02),
        Phase("descend", at(obj_xy, grasp_z), OPEN),
        Phase("close", at(obj_xy, grasp_z), CLOSED, steps=10),
    ]
    carry_z = TABLE_TOP + CLEARANCE + below_grip
    if kind == "lift":
        return pick + [Phase("lift", at(obj_xy, carry_z), CLOSED, carrying=True, speed=0.5)]
    if kind == "place":
        def hand_xy():  # where the hand goes so the *object* ends over the target
            return target()[:2] + env.eef_pos()[:2] - obj_xy()

        rest = target_top or (lambda: TABLE_TOP)
        place_z = lambda: rest() + 0.015 + below_grip
        return pick + [
            Phase("lift", at(obj_xy, carry_z), CLOSED, carrying=True, tol=0.02, speed=0.6),
            Phase("carry", at(hand_xy, carry_z), CLOSED, carrying=True, tol=0.01, speed=0.6),
            Phase("lower", at(hand_xy, place_z), CLOSED, carrying=True, tol=0.01, speed=0.4),
            Phase("release", lambda: env.eef_pos(), OPEN, steps=8),
            Phase("retreat", lambda: np.array([*env.eef_pos()[:2], SAFE_Z]), OPEN),
        ]
    if kind == "push":  # with closed fingers, from behind, along the line object -> target
        half = (top - bottom) / 2

        def direction():
            d = target()[:2] - obj_xy()
            return d / max(np.linalg.norm(d), 1e-6)

        behind = lambda: obj_xy() - direction() * (half + 0.04)
        through = lambda: obj_xy() + direction() * 0.03
        low = TABLE_TOP + 0.02
        return [
            Phase("above", at(behind, SAFE_Z - 0.1), CLOSED, tol=0.02),
            Phase("descend", at(behind, low), CLOSED),
            Phase("push", at(through, low), CLOSED, speed=0.6, limit=150,
                  done=lambda: np.linalg.norm(target()[:2] - obj_xy()) < 0.015),
            Phase("retreat", lambda: np.array([*env.eef_pos()[:2], SAFE_Z - 0.1]), CLOSED),
        ]
    raise ValueError(f"unknown task kind {kind!r}")
