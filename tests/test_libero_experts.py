"""The scripted experts on real LIBERO: coverage errors, and one real rollout to success."""

from __future__ import annotations

import pytest

from suites.libero.experts import EXPERT_TASKS, make_expert
from suites.libero.experts.coverage import LIBERO_OBJECT
from suites.libero.experts.libero_env import STEP_LIMITS, make_env, start_episode, suite_tasks


def test_uncovered_task_raises_one_line_key_error():
    with pytest.raises(KeyError) as err:
        make_expert("no_such_task_in_libero", env=None)
    message = str(err.value)
    assert "no_such_task_in_libero" in message and "\n" not in message


def test_libero_object_suite_is_covered():
    assert set(LIBERO_OBJECT) <= EXPERT_TASKS
    assert [t.name for t in suite_tasks("libero_object")] == list(LIBERO_OBJECT)


def test_expert_solves_a_libero_object_task_from_a_fixed_init_state():
    task = suite_tasks("libero_object")[1]  # cream cheese: a flat box, the yaw-aligned grasp
    env = make_env(task)
    try:
        obs = start_episode(env, task, state=3)
        assert not env.check_success()
        expert = make_expert(task.name, env)
        for _ in range(STEP_LIMITS["libero_object"]):
            action = expert.act(obs)
            assert action.shape == (7,) and abs(action).max() <= 1.0
            obs, _, _, _ = env.step(action)
            if env.check_success():
                break
        assert env.check_success()
    finally:
        env.close()


def test_expert_turns_a_knob_from_a_fixed_init_state():
    task = suite_tasks("libero_goal")[7]  # turn on the stove: the articulated family
    assert task.name == "turn_on_the_stove"
    env = make_env(task)
    try:
        obs = start_episode(env, task, state=2)
        assert not env.check_success()
        expert = make_expert(task.name, env)
        for _ in range(STEP_LIMITS["libero_goal"]):
            obs, _, _, _ = env.step(expert.act(obs))
            if env.check_success():
                break
        assert env.check_success()
    finally:
        env.close()
