"""Scripted bimanual experts: one waypoint state machine that drives both arms in lock-step.

An expert is a list of phases; a phase gives each arm one `Move` (where the grip site should go,
how the fingers should be turned, open or closed). The phase ends when BOTH arms have arrived (and
waited), which is what coordinates them: an arm that is done early holds still until the other
catches up. Single-arm skills (`pick`, `place`) return lists of moves; `together` zips the two
arms' lists into phases, padding the shorter one with "stay here" moves, and `in_turn` runs one
arm's skill while the other holds.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from suites.bimanual.scene import ARM_ACTION_DIM, ARMS
from suites.bimanual.world import World
from suites.robosuite_common import CLOSED, OPEN, POS_SCALE, ROT_SCALE

Point = Callable[[World], np.ndarray]
Angle = Callable[[World], float]

_POS_GAIN = 0.8  # fraction of the remaining error commanded per step
_MAX_POS_ACTION = 0.7  # caps the speed (0.7 * 0.05 m at 20 Hz = 0.7 m/s commanded)
_YAW_TOL = 0.08  # rad


@dataclass(frozen=True)
class Move:
    """One arm's goal for one phase.

    to:     live target for the grip site (re-read every step, so it follows moving objects);
            None means "where this arm was when the phase began".
    offset: added to the target (e.g. hover 10 cm above it).
    grip:   OPEN / CLOSED; None keeps the arm's last grip command.
    yaw:    heading of the finger-closing axis; None keeps the heading the phase began with.
    """

    to: Point | None = None
    offset: tuple[float, float, float] = (0.0, 0.0, 0.0)
    grip: float | None = None
    yaw: Angle | None = None
    tol: float = 0.015
    wait: int = 0  # extra steps after arriving (lets the fingers close or open)


STAY = Move()

Phase = tuple[Move, Move]  # (left, right)


def together(left: list[Move], right: list[Move]) -> list[Phase]:
    """Run two single-arm move lists side by side, phase i pairing their i-th moves."""
    n = max(len(left), len(right))
    return [(left[i] if i < len(left) else STAY, right[i] if i < len(right) else STAY) for i in range(n)]


def in_turn(arm: str, moves: list[Move]) -> list[Phase]:
    """Run one arm's moves while the other arm holds where it is."""
    return together(moves, []) if arm == "left" else together([], moves)


def pick(at: Point, yaw: Angle | None = None, hover: float = 0.10, lift: float = 0.12, dz: float = 0.0) -> list[Move]:
    """Open above `at`, descend, close, lift straight up."""
    return [
        Move(to=at, offset=(0, 0, hover), grip=OPEN, yaw=yaw, tol=0.02),
        Move(to=at, offset=(0, 0, dz), grip=OPEN, yaw=yaw, tol=0.01),
        Move(grip=CLOSED, wait=8),
        Move(offset=(0, 0, lift), grip=CLOSED, tol=0.02),
    ]


def place(at: Point, height: float, hover: float = 0.10, yaw: Angle | None = None, retreat: float = 0.10) -> list[Move]:
    """Carry to above `at`, lower until the grip site is `height` above it, open, back off upwards."""
    return [
        Move(to=at, offset=(0, 0, hover), grip=CLOSED, yaw=yaw, tol=0.02),
        Move(to=at, offset=(0, 0, height), grip=CLOSED, yaw=yaw, tol=0.01),
        Move(grip=OPEN, wait=6),
        Move(offset=(0, 0, retreat), grip=OPEN, tol=0.02),
    ]


def target_orientation(yaw: float) -> np.ndarray:
    """Grip-site rotation pointing straight down with the fingers closing along heading `yaw`."""
    finger = np.array([np.cos(yaw), np.sin(yaw), 0.0])
    down = np.array([0.0, 0.0, -1.0])
    return np.stack([finger, np.cross(down, finger), down], axis=1)


def nearest_equivalent_yaw(yaw: float, current: float) -> float:
    """Fingers are symmetric: yaw and yaw + pi grasp alike, so turn the shorter way."""
    return current + (yaw - current + np.pi / 2) % np.pi - np.pi / 2


def rotation_error(target: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Axis-angle vector (world frame) rotating `current` onto `target`."""
    r = target @ current.T
    angle = np.arccos(np.clip((np.trace(r) - 1) / 2, -1.0, 1.0))
    if angle < 1e-6:
        return np.zeros(3)
    axis = np.array([r[2, 1] - r[1, 2], r[0, 2] - r[2, 0], r[1, 0] - r[0, 1]])
    norm = np.linalg.norm(axis)
    if norm < 1e-6:  # angle ~ pi: any axis perpendicular to the symmetric part works; rarely hit
        return np.array([np.pi, 0.0, 0.0])
    return axis / norm * angle


class Script:
    """Steps through phases, emitting 14-d actions [left 7, right 7] from the current World."""

    def __init__(self, phases: list[Phase], timeout: int = 80):
        self.phases = phases
        self.timeout = timeout  # a phase that cannot be finished (blocked arm) gives way after this many steps
        self.index = 0
        self._steps = 0
        self._arrived = 0
        self._start: dict[str, tuple[np.ndarray, float]] = {}
        self._grip = {arm: OPEN for arm in ARMS}

    @property
    def done(self) -> bool:
        return self.index >= len(self.phases)

    def act(self, world: World) -> np.ndarray:
        if self.done:
            moves = (STAY, STAY)
        else:
            moves = self.phases[self.index]
        if not self._start:
            self._start = {arm: (world.eef_pos[arm].copy(), world.finger_yaw(arm)) for arm in ARMS}
        action, arrived = [], True
        for arm, move in zip(ARMS, moves):
            a, ok = self._arm_action(arm, move, world)
            action.append(a)
            arrived &= ok
        self._advance(arrived, max(m.wait for m in moves))
        return np.concatenate(action).astype(np.float32)

    def _advance(self, arrived: bool, wait: int) -> None:
        if self.done:
            return
        self._steps += 1
        self._arrived += arrived or self._arrived > 0  # once arrived, the wait counts down regardless
        if self._arrived > wait or self._steps >= self.timeout:
            self.index += 1
            self._steps = self._arrived = 0
            self._start = {}

    def _arm_action(self, arm: str, move: Move, world: World) -> tuple[np.ndarray, bool]:
        start_pos, start_yaw = self._start[arm]
        goal = (move.to(world) if move.to is not None else start_pos) + np.asarray(move.offset)
        current_yaw = world.finger_yaw(arm)
        yaw = nearest_equivalent_yaw(move.yaw(world) if move.yaw is not None else start_yaw, current_yaw)
        if move.grip is not None:
            self._grip[arm] = move.grip

        pos_err = goal - world.eef_pos[arm]
        pos_action = pos_err * _POS_GAIN / POS_SCALE
        speed = np.linalg.norm(pos_action)
        if speed > _MAX_POS_ACTION:
            pos_action *= _MAX_POS_ACTION / speed
        rot_action = np.clip(rotation_error(target_orientation(yaw), world.eef_mat[arm]) / ROT_SCALE, -1, 1)
        action = np.concatenate([pos_action, rot_action, [self._grip[arm]]])
        assert action.shape == (ARM_ACTION_DIM,)
        arrived = np.linalg.norm(pos_err) < move.tol and abs(yaw - current_yaw) < _YAW_TOL
        return np.clip(action, -1.0, 1.0), bool(arrived)
