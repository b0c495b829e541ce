"""The suite contract, for every task of every suite: reset, step, success, seeding, expert."""

from __future__ import annotations

import numpy as np
import pytest

from suites import episode_seeds, get_suite, suite_names

# real LIBERO's 130 tasks take seconds each to build: tests/test_suite_libero.py samples them
# (and tests/test_lerobot_libero.py libero-proprio, the same LIBERO with another state); the
# -lerobot suites are the same simulators under lerobot-eval's conventions, held to LeRobot's
# env classes by tests/test_lerobot_eval_parity.py
SUITES = [s for s in suite_names() if not s.startswith("libero") and not s.endswith("-lerobot")]
CASES = [(s, t) for s in SUITES for t in get_suite(s).task_names()]
_ENVS: dict = {}


def env_for(suite_name: str, task: str):
    """One env per task for the whole file: building a robosuite env costs seconds, resetting not."""
    if (suite_name, task) not in _ENVS:
        _ENVS[suite_name, task] = get_suite(suite_name).make_env(task)
    return _ENVS[suite_name, task]


def teardown_module(module):
    for env in _ENVS.values():
        env.close()


@pytest.mark.parametrize("suite_name", SUITES)
def test_suite_names_tasks_with_distinct_instructions(suite_name):
    suite = get_suite(suite_name)
    instructions = [suite.instruction(t) for t in suite.task_names()]
    assert all(instructions) and len(set(instructions)) == len(instructions)
    with pytest.raises(ValueError, match=f"unknown {suite_name} task 'no_such_task'; valid: "):
        suite.make_env("no_such_task")


@pytest.mark.parametrize("suite_name, task", CASES)
def test_task_resets_steps_and_reproduces(suite_name, task):
    suite = get_suite(suite_name)
    env = env_for(suite_name, task)
    seed, other = episode_seeds(suite_name, task, "demo", 2)
    first = env.reset(seed)["state"]
    assert first.shape == (suite.state_dim,) and first.dtype == np.float32
    rng = np.random.default_rng(0)
    for _ in range(3):
        result = env.step(rng.uniform(-1, 1, suite.action_dim).astype(np.float32))
        assert isinstance(result.success, bool)
        assert result.obs["state"].shape == (suite.state_dim,) and np.isfinite(result.obs["state"]).all()
    np.testing.assert_array_equal(env.reset(seed)["state"], first)  # same seed, same start
    assert not np.array_equal(env.reset(other)["state"], first)


@pytest.mark.parametrize("suite_name, task", CASES)
def test_expert_solves_a_seeded_evaluation_episode(suite_name, task):
    """Experts succeed on about 95% of episodes: one of the first three must be solved."""
    suite = get_suite(suite_name)
    env = env_for(suite_name, task)
    for seed in episode_seeds(suite_name, task, "eval", 3):
        env.reset(seed)
        for _ in range(suite.max_episode_steps):
            action = env.expert_action()
            assert action.shape == (suite.action_dim,) and np.all(np.abs(action) <= 1.0)
            if env.step(action).success:
                return
    pytest.fail(f"expert solved none of 3 {suite_name}/{task} episodes in {suite.max_episode_steps} steps")
