"""The scripted experts on real LIBERO: coverage errors, and real rollouts to success through the
suite's own env (LIBERO's protocol: the fixed init state, the settle steps, the step limit)."""

from __future__ import annotations

import pytest

from suites import get_suite
from suites.libero.experts import EXPERT_TASKS, make_expert
from suites.libero.experts.coverage import LIBERO_OBJECT
from suites.libero.tasks import suite_tasks


def test_uncovered_task_raises_one_line_key_error():
    with pytest.raises(KeyError) as err:
        make_expert("no_such_task_in_libero", env=None)
    message = str(err.value)
    assert "no_such_task_in_libero" in message and "\n" not in message


def test_libero_object_suite_is_covered():
    assert set(LIBERO_OBJECT) <= EXPERT_TASKS
    assert suite_tasks("libero_object") == list(LIBERO_OBJECT)


def _solves(task: str, init_state: int) -> bool:
    suite = get_suite("libero")
    env = suite.make_env(task)
    try:
        env.reset(init_state)  # evaluation key i: init state i, then the no-op settle
        assert not env.success()
        for _ in range(suite.max_steps(task)):
            action = env.expert_action()
            assert action.shape == (7,) and abs(action).max() <= 1.0
            if env.step(action).success:
                return True
        return False
    finally:
        env.close()


def test_expert_solves_a_libero_object_task_from_a_fixed_init_state():
    # cream cheese: a flat box, the yaw-aligned grasp
    assert _solves(suite_tasks("libero_object")[1], init_state=3)


def test_expert_turns_a_knob_from_a_fixed_init_state():
    task = suite_tasks("libero_goal")[7]  # turn on the stove: the articulated family
    assert task == "turn_on_the_stove"
    assert _solves(task, init_state=2)
