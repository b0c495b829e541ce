"""Skills as phase lists: waypoints for the hand, recomputed every step from privileged state.

A `Phase` is one end-effector target (position and yaw, hand pointing down) plus a gripper
command. It ends when the target is reached, after a fixed number of steps (gripper phases), on
its own test, or when it runs out of steps (a blocked move gives up and the plan goes on).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from suites.libero.experts.scene import Scene, hand_down

OPEN, CLOSED = -1.0, 1.0
MAX_PHASE_STEPS = 60
FINGER_REACH = 0.027  # the palm sits about 3 cm above the grip point: grip no deeper
HELD_DRIFT = 0.03  # how far an object may sit from its grip point and still count as held
GRIPPER_SPAN = 0.075  # widest thing the open hand takes in across its fingers
PUSH_DEPTH = -0.01  # the eef target below a pushed object's bottom: pressing on its floor
PUSH_BACKSET = 0.02  # fingers go in this far behind the object's centre, against the push
PUSH_CONTACT = 0.03  # the hand from the centre where it meets the rim ahead, from inside
PUSH_LEAD = 0.04  # how far past that contact the hand is aimed
PUSH_TOL = 0.015  # a push leg ends with the object's centre this close to its end point


@dataclass
class Phase:
    name: str
    target: Callable[[], np.ndarray]  # end-effector position to move to
    grip: float
    yaw: Callable[[], float]
    steps: int = 0  # >0: a timed phase (open/close the gripper) instead of a move
    tol: float = 0.01
    held: Callable[[], bool] | None = None  # must stay true (object in hand), or start over
    done: Callable[[], bool] | None = None
    speed: float = 1.0  # action-norm cap for the translation
    limit: int = MAX_PHASE_STEPS
    orient: Callable[[], np.ndarray] | None = None  # a full hand orientation instead of yaw
    stall: bool = False  # a move that stops making progress (blocked by contact) counts as done


class _Here:
    """A target that stays where the hand was when the phase began (gripper phases hold still;
    a zero command would let the arm drift while the fingers push on something)."""

    def __init__(self, scene: Scene):
        self.scene, self.pos = scene, None

    def __call__(self) -> np.ndarray:
        if self.pos is None:
            self.pos = self.scene.eef_pos()
        return self.pos


def _wrap_half_turn(yaw: float) -> float:
    """The hand is symmetric under a half turn: take the equivalent yaw in (-pi/2, pi/2]."""
    return np.pi / 2 - (np.pi / 2 - yaw) % np.pi


@dataclass
class Grasp:
    """How to hold one object: where the grip point sits relative to the object's body."""

    offset: np.ndarray  # grip point minus the object's body position, world frame, at plan time
    yaw: float
    below: float  # from the grip point down to the object's bottom

    def holds(self, scene: Scene, obj: str) -> Callable[[], bool]:
        """In hand: both finger pads touch it, or it still sits where the grip put it (a bowl
        pinched by its rim often touches one pad only)."""
        def test() -> bool:
            near = np.linalg.norm(scene.pos(obj) + self.offset - scene.eef_pos()) < HELD_DRIFT
            return near or scene.is_grasped(obj)
        return test

    @classmethod
    def plan(cls, scene: Scene, obj: str, wrist_from: np.ndarray | None = None) -> Grasp:
        """`wrist_from`: a point the wrist should keep away from (what hangs over the object),
        where the grasp has a choice (a rim pinch: either of two half-turn twins)."""
        lo, hi = scene.box(obj)
        narrow, wide, narrow_yaw = scene.footprint(obj)
        centre = (lo + hi) / 2
        body = scene.pos(obj)
        height = hi[2] - lo[2]
        grip_z = max(lo[2] + min(0.012, height / 2), hi[2] - FINGER_REACH)
        # Fingers close along the hand's y axis; at yaw 0 that is world y.
        if narrow <= GRIPPER_SPAN and wide > 0.06 and wide > 1.15 * narrow:
            yaw = _wrap_half_turn(narrow_yaw - np.pi / 2)
        else:
            yaw = 0.0
        offset = np.array([centre[0] - body[0], centre[1] - body[1], grip_z - body[2]])
        if narrow > GRIPPER_SPAN:  # a bowl or other wide thing: pinch its rim nearest the robot
            rim_z = hi[2] - 0.015
            offset = np.array([centre[0] - body[0] - (hi[0] - lo[0]) / 2 + 0.012,
                               centre[1] - body[1], rim_z - body[2]])
            yaw = np.pi / 2
            if wrist_from is not None:
                yaw = _wrist_away(scene, wrist_from[:2] - centre[:2])
        return cls(offset, float(yaw), float(body[2] + offset[2] - lo[2]))


def _wrist_away(scene: Scene, toward: np.ndarray) -> float:
    """Of the rim pinch's yaws (+-pi/2, fingers across the rim nearest the robot), the one
    that turns the wrist's bulk (its last link sticks out further on one side of the hand)
    away from `toward`: under an open drawer, the other hits it."""
    bulk = scene.wrist_offset()

    def away(yaw: float) -> float:
        return -float((hand_down(yaw) @ bulk)[:2] @ toward)
    return max((np.pi / 2, -np.pi / 2), key=away)


def _at(xy: Callable[[], np.ndarray], z) -> Callable[[], np.ndarray]:
    return lambda: np.array([*xy()[:2], z() if callable(z) else z])


def pick(scene: Scene, obj: str, grasp: Grasp, travel_z: float,
         withdraw: tuple[float, np.ndarray] | None = None) -> list[Phase]:
    """Above the object at travel height, down to the grip point, close, lift to travel height.
    `withdraw` (rise, horizontal shift): out from under something first, lifted only `rise`."""
    def grip_point():
        return scene.pos(obj) + grasp.offset

    yaw = lambda: grasp.yaw  # noqa: E731
    above = min(travel_z, grip_point()[2] + 0.12)
    held = grasp.holds(scene, obj)
    phases = [
        Phase("above", _at(grip_point, max(above, grip_point()[2] + 0.06)), OPEN, yaw, tol=0.015),
        Phase("descend", grip_point, OPEN, yaw, tol=0.006, speed=0.6, stall=True),
        Phase("close", _Here(scene), CLOSED, yaw, steps=20, done=scene.fingers_still),
    ]
    if withdraw is not None:
        rise, shift = withdraw
        start = _Here(scene)
        phases.append(Phase("withdraw", lambda: start() + np.array([*shift[:2], rise]), CLOSED,
                            yaw, held=held, tol=0.015, speed=0.6))
    phases.append(Phase("lift", _at(scene.eef_pos, travel_z), CLOSED, yaw, held=held, tol=0.02,
                        speed=0.7))
    return phases


def place(scene: Scene, obj: str, grasp: Grasp, target_xy: Callable[[], np.ndarray],
          rest_z: Callable[[], float], travel_z: float) -> list[Phase]:
    """Carry so the object sits over `target_xy`, lower its bottom to `rest_z`, let go, rise."""
    def hand_xy_obj():  # where the hand goes so the object's grip point ends over the target
        obj_xy = scene.pos(obj)[:2]
        return target_xy()[:2] + scene.eef_pos()[:2] - obj_xy

    yaw = lambda: grasp.yaw  # noqa: E731
    release_z = lambda: rest_z() + grasp.below  # noqa: E731
    return [
        Phase("carry", _at(hand_xy_obj, travel_z), CLOSED, yaw, held=grasp.holds(scene, obj), tol=0.012,
              speed=0.8, limit=80),
        Phase("lower", _at(hand_xy_obj, release_z), CLOSED, yaw, held=grasp.holds(scene, obj), tol=0.01,
              speed=0.5),
        Phase("release", _Here(scene), OPEN, yaw, steps=25,
              done=lambda: scene.fingers_still() and not scene.is_grasped(obj)),
        Phase("retreat", lambda: np.array([*scene.eef_pos()[:2], travel_z]), OPEN, yaw,
              tol=0.02),
    ]


def turn(scene: Scene, joint: str, sign: float, done: Callable[[], bool]) -> list[Phase]:
    """Push a knob's lever around its hinge with closed fingers (sign +1: the positive way)."""
    yaw = lambda: 0.0  # noqa: E731

    def tangent():
        axis, anchor, _ = scene.joint(joint)
        t = sign * np.cross(axis, scene.lever(joint) - anchor)
        t[2] = 0.0
        return t / max(np.linalg.norm(t), 1e-6)

    start = lambda: scene.lever(joint) - tangent() * 0.035  # noqa: E731
    height = scene.lever(joint)[2] + 0.018  # fingertips sit ~1 cm below the grip point
    return [
        Phase("above-lever", _at(start, height + 0.08), CLOSED, yaw, tol=0.015),
        Phase("beside-lever", _at(start, height), CLOSED, yaw, tol=0.008, stall=True),
        Phase("sweep", _at(lambda: scene.lever(joint) + tangent() * 0.04, height), CLOSED, yaw,
              speed=0.5, limit=80, done=done),
        Phase("rise", lambda: np.array([*scene.eef_pos()[:2], height + 0.08]), CLOSED, yaw,
              tol=0.02),
    ]


def facing(approach: np.ndarray, tilt: float) -> np.ndarray:
    """The hand tipped `tilt` rad from pointing down toward the horizontal `approach`.

    The fingers close in the vertical plane of the approach: along it when pointing down,
    vertically when pointing straight ahead.
    """
    a = np.array([approach[0], approach[1], 0.0])
    a /= np.linalg.norm(a)
    up = np.array([0.0, 0.0, 1.0])
    z = -np.cos(tilt) * up + np.sin(tilt) * a
    x = np.sin(tilt) * up + np.cos(tilt) * a
    return np.stack([x, np.cross(z, x), z], axis=1)


def turn_angle(a: np.ndarray, b: np.ndarray) -> float:
    """The angle (rad) of the rotation from orientation `a` to `b`."""
    return float(np.arccos(np.clip((np.trace(a.T @ b) - 1.0) / 2.0, -1.0, 1.0)))


def nearer_half_turn(orient: np.ndarray, current: np.ndarray) -> np.ndarray:
    """`orient`, or the same grasp turned half a turn about the pointing axis (the hand is
    symmetric), whichever is the smaller turn from `current`: the other can lie past the
    wrist's joint limit, and a half turn away is where the controller's error vanishes."""
    flipped = orient @ np.diag([-1.0, -1.0, 1.0])
    return min((orient, flipped), key=lambda m: turn_angle(m, current))


def slide(scene: Scene, joint: str, target_q: float, opening: bool,
          done: Callable[[], bool]) -> list[Phase]:
    """Grip a drawer's handle from the front, fingers above and below it, and slide it."""
    axis, _, q0 = scene.joint(joint)
    direction = axis * (np.sign(target_q - q0) or 1.0)  # world direction the handle travels
    direction[2] = 0.0
    direction /= np.linalg.norm(direction)
    front = direction if opening else -direction  # the handle is on the side it opens toward
    # from the front: other handles may sit right above it
    hand = nearer_half_turn(facing(-front, np.pi / 2), scene.eef_mat())
    orient = lambda: hand  # noqa: E731
    yaw = lambda: 0.0  # noqa: E731
    back = -hand[:, 2]  # from the handle back along the hand's pointing direction

    def handle():
        return scene.handle(joint, front)

    def slide_target():
        remaining = abs(target_q - scene.joint(joint)[2]) + 0.03
        return handle() + direction * remaining

    return [
        Phase("before-handle", lambda: handle() + back * 0.10, OPEN, yaw, tol=0.015,
              orient=orient, limit=80),
        Phase("to-handle", lambda: handle() - back * 0.01, OPEN, yaw, tol=0.008, speed=0.5,
              orient=orient, stall=True),
        Phase("grip-handle", _Here(scene), CLOSED, yaw, steps=20,
              done=scene.fingers_still, orient=orient),
        Phase("slide", slide_target, CLOSED, yaw, done=done, speed=0.6, limit=100,
              orient=orient),
        Phase("let-go", _Here(scene), OPEN, yaw, steps=10, orient=orient),
        Phase("back-off", lambda: handle() + back * 0.10, OPEN, yaw, tol=0.02, orient=orient),
    ]


def push(scene: Scene, obj: str, legs: list[np.ndarray], done: Callable[[], bool]) -> list[Phase]:
    """Push a flat, wide object (a plate) over the table through `legs` (its centre's way
    points) with closed fingers set down inside its rim: the rim ahead takes the push, so the
    hand never reaches behind the object, where a cabinet may stand."""
    lo, hi = scene.box(obj)
    low, travel = lo[2] + PUSH_DEPTH, hi[2] + 0.08
    phases: list[Phase] = []
    start = scene.pos(obj)[:2]
    for k, end in enumerate(legs):
        last = k == len(legs) - 1
        phases += _push_leg(scene, obj, start, end, low, travel if k == 0 else None,
                            done if last else None)
        start = end
    phases.append(Phase("rise", lambda: np.array([*scene.eef_pos()[:2], travel]), CLOSED,
                        phases[-1].yaw, tol=0.02))
    return phases


def _push_leg(scene: Scene, obj: str, start: np.ndarray, end: np.ndarray, low: float,
              enter_from: float | None, done: Callable[[], bool] | None) -> list[Phase]:
    """One straight push; `enter_from`: first set the fingers down inside the rim from there."""
    u = (end - start) / max(float(np.linalg.norm(end - start)), 1e-6)
    angle = _wrap_half_turn(float(np.arctan2(u[1], u[0])))  # fingers side by side, across u
    yaw = lambda: angle  # noqa: E731
    phases = []
    if enter_from is not None:
        entry = lambda: scene.pos(obj)[:2] - u * PUSH_BACKSET  # noqa: E731
        phases += [Phase("above-object", _at(entry, enter_from), CLOSED, yaw, tol=0.015),
                   Phase("into-object", _at(entry, low), CLOSED, yaw, tol=0.008, speed=0.5,
                         stall=True)]

    def finished() -> bool:
        there = np.linalg.norm(scene.pos(obj)[:2] - end) < PUSH_TOL
        return bool(there or (done is not None and done()))

    def ahead() -> np.ndarray:  # past the rim on the line from the object's centre to `end`,
        centre = scene.pos(obj)[:2]  # so a push that drifts sideways is steered back
        way = end - centre
        dist = float(np.linalg.norm(way))
        return centre + (way / dist if dist > 1e-3 else u) * (PUSH_CONTACT + PUSH_LEAD)

    phases.append(Phase("push", _at(ahead, low), CLOSED, yaw, speed=0.4, limit=150,
                        done=finished))
    return phases
