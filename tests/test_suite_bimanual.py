"""The bimanual suite: shapes, and that [left | right] actions reach the right arms (seeding and
experts: tests/test_suites.py)."""

from __future__ import annotations

import numpy as np
import pytest

pytest.importorskip("robosuite")

from suites import get_suite  # noqa: E402

SUITE = get_suite("bimanual")
TASKS = SUITE.task_names()
_ENVS: dict = {}


def env_for(task: str):
    """One env per task for the whole file: building a robosuite env costs seconds, resetting does not."""
    if task not in _ENVS:
        _ENVS[task] = SUITE.make_env(task)
    return _ENVS[task]


def teardown_module(module):
    for env in _ENVS.values():
        env.close()


def test_suite_shape():
    assert SUITE.action_dim == 14
    assert len(TASKS) >= 8
    assert all(SUITE.instruction(t) for t in TASKS)


@pytest.mark.parametrize("moving,still", [("left", "right"), ("right", "left")])
def test_action_halves_drive_the_named_arm(moving, still):
    """+z on one 7-d half lifts that arm's end effector; the other arm, sent zeros, stays put."""
    env = env_for("dual_lift")
    env.reset(0)
    before = {arm: env.world.eef_pos[arm].copy() for arm in ("left", "right")}
    action = np.zeros(14, dtype=np.float32)
    action[(0 if moving == "left" else 7) + 2] = 1.0  # each arm: [dx, dy, dz, rx, ry, rz, grip]
    for _ in range(8):
        env.step(action)
    moved = {arm: env.world.eef_pos[arm] - before[arm] for arm in ("left", "right")}
    assert moved[moving][2] > 0.05
    assert np.linalg.norm(moved[still]) < 0.005
    # and the robot on the +y side of the table is the left one (seen from behind the robots)
    assert env.world.eef_pos["left"][1] > 0 > env.world.eef_pos["right"][1]
