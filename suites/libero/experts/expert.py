"""The goal-driven expert: one skill plan per BDDL goal predicate, run as a waypoint machine.

The plan for a goal is built when the goal comes up (from the scene as it is then) and rebuilt
when the carried object slips or the plan ends without the goal holding.
"""

from __future__ import annotations

import numpy as np

import suites.robosuite_quiet  # noqa: F401  (before any robosuite import)

# isort: split
from robosuite.utils.control_utils import orientation_error

from suites.libero.experts.planner import plan_goal
from suites.libero.experts.scene import Scene, hand_down
from suites.libero.experts.skills import OPEN, Phase

POS_SCALE, ROT_SCALE = 0.05, 0.5  # LIBERO's OSC_POSE: metres and radians per unit action
SLIP_STEPS = 3  # steps without a grasp before a carry counts as dropped
GAIN = 3.0  # the OSC lags its delta target; a proportional gain removes most of the lag
ROT_CAP = 0.4  # large turns at full rate throw the hand around: cap the rotation action
YAW_TOL = 0.08  # a move is not done until the hand's yaw is this close (rad)
MIN_TIMED = 8  # a timed gripper phase with its own `done` test runs at least this long


class GoalExpert:
    """`act(raw_obs)` returns LIBERO's 7-d action for the next step toward the BDDL goal."""

    def __init__(self, env, goals: list[list[str]]):
        self.scene = Scene(env)
        self.goals = goals
        self.goal = 0
        self.plan: list[Phase] = []
        self.i = self.t = self.slipping = 0
        self.trail: list[np.ndarray] = []
        self._next_goal()

    def _next_goal(self) -> None:
        while self.goal < len(self.goals) and self.scene.check(self.goals[self.goal]):
            self.goal += 1
        self._replan()

    def _replan(self) -> None:
        self.plan = plan_goal(self.scene, self.goals[self.goal]) if self.goal < len(
            self.goals) else []
        self.i = self.t = self.slipping = 0
        self.trail = []

    def act(self, raw_obs: dict | None = None) -> np.ndarray:
        phase = self._advance()
        if phase is None:
            return np.array([0, 0, 0, 0, 0, 0, OPEN], dtype=np.float32)
        scene = self.scene
        delta = GAIN * (phase.target() - scene.eef_pos()) / POS_SCALE
        norm = np.linalg.norm(delta)
        if norm > phase.speed:
            delta *= phase.speed / norm
        rot = orientation_error(self._orientation(phase), scene.eef_mat()) / ROT_SCALE
        rot_norm = np.linalg.norm(rot)
        if rot_norm > ROT_CAP:
            rot *= ROT_CAP / rot_norm
        return np.clip(np.concatenate([delta, rot, [phase.grip]]), -1, 1).astype(np.float32)

    @staticmethod
    def _orientation(phase: Phase) -> np.ndarray:
        return phase.orient() if phase.orient else hand_down(phase.yaw())

    def _reached(self, phase: Phase) -> bool:
        scene = self.scene
        pos = scene.eef_pos()
        self.trail.append(pos)
        yaw_err = np.linalg.norm(orientation_error(self._orientation(phase), scene.eef_mat()))
        if yaw_err > YAW_TOL:
            return False
        if np.linalg.norm(phase.target() - pos) < phase.tol:
            return True
        return (phase.stall and self.t > 10
                and np.linalg.norm(self.trail[-1] - self.trail[-5]) < 0.002)

    def _advance(self) -> Phase | None:
        scene = self.scene
        for _ in range(4 * max(len(self.plan), 1) + 8):
            if not self.plan:
                return None
            phase = self.plan[self.i]
            if phase.held and self.t > 2:
                self.slipping = 0 if phase.held() else self.slipping + 1
                if self.slipping >= SLIP_STEPS:
                    self._replan()
                    continue
            if phase.steps:
                finished = self.t >= phase.steps or (
                    phase.done is not None and self.t >= MIN_TIMED and phase.done())
            elif phase.done:
                finished = phase.done() or self.t >= phase.limit
            else:
                finished = self._reached(phase) or self.t >= phase.limit
            if not finished:
                self.t += 1
                return phase
            if self.i < len(self.plan) - 1:
                self.i, self.t, self.slipping = self.i + 1, 0, 0
                self.trail = []
                continue
            # The plan is over: on to the next goal, or try this one again.
            if scene.check(self.goals[self.goal]):
                self.goal += 1
                self._next_goal()
            else:
                self._replan()
        return self.plan[self.i] if self.plan else None
