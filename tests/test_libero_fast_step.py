"""The fast LIBERO step (suites/libero/fast_step.py) gives robosuite's trajectories to the bit.

Each check runs one seeded action sequence twice in one env from one of LIBERO's init states,
through robosuite's own `env.step` and through the fast path, and compares every step's
observation and success and the final sim state (joint positions and velocities of the robot
and of every object) for exact equality. The normal suite checks one task of each LIBERO suite
at init state 0 (libero_spatial and libero_90 in the normal suite, the other three under
`-m slow`, about 15 s each on one core), and `-m slow` checks all 130 tasks."""

from __future__ import annotations

import numpy as np
import pytest

from harness.perf.throughput import sweep_actions as actions
from suites.libero import fast_step
from suites.libero.env import FAST_STEP_ENV, FRESH_PLACEMENT, LiberoTaskEnv, fast_step_default
from suites.libero.tasks import SUITES, all_tasks, suite_tasks

STEPS = 300


def rollout(env: LiberoTaskEnv, fast: bool, key: int, acts: np.ndarray):
    """(states [n + 1, 65], successes [n], final flattened sim state) of one path."""
    env.fast_step = fast
    states, successes = [env.reset(key)["state"]], []
    for action in acts:
        result = env.step(action)
        states.append(result.obs["state"])
        successes.append(result.success)
    if fast:  # the fast path really ran (an unsupported env falls back to robosuite's step)
        assert env.fast_step and env._stepper is not None and env._stepper.bound_to(env.env.env)
    return np.array(states), successes, env.sim_state()


def assert_same(env: LiberoTaskEnv, key: int = 0, steps: int = STEPS) -> None:
    acts = actions(steps, seed=key)
    slow_states, slow_success, slow_sim = rollout(env, False, key, acts)
    fast_states, fast_success, fast_sim = rollout(env, True, key, acts)
    n_q = env.env.sim.model.nq
    qpos, qvel = slice(1, 1 + n_q), slice(1 + n_q, None)  # a flattened state: time, qpos, qvel
    gap = np.abs(fast_sim - slow_sim).max()
    np.testing.assert_array_equal(fast_sim[qpos], slow_sim[qpos],
                                  err_msg=f"joint positions {env.task.name} (max gap {gap:.1e})")
    np.testing.assert_array_equal(fast_sim[qvel], slow_sim[qvel],
                                  err_msg=f"joint velocities {env.task.name}")
    np.testing.assert_array_equal(fast_states, slow_states, err_msg=f"observations {env.task.name}")
    assert fast_success == slow_success, env.task.name


def make_env(task: str, cameras: bool = False) -> LiberoTaskEnv:
    return LiberoTaskEnv(all_tasks()[task], cameras=cameras, image_size=32)


@pytest.fixture(scope="module")
def spatial_env():
    env = make_env(suite_tasks("libero_spatial")[0])
    yield env
    env.close()


# the default set: one task of each suite; libero_spatial's also from a second init state and
# from a demo episode's fresh scene (a reloaded model: new sim, controllers and observables)
@pytest.mark.parametrize("suite", [s if s in ("libero_spatial", "libero_90") else
                                   pytest.param(s, marks=pytest.mark.slow) for s in SUITES])
def test_fast_step_is_robosuites_step_to_the_bit(suite, spatial_env):
    if suite == "libero_spatial":
        assert_same(spatial_env, key=0)
        assert_same(spatial_env, key=17, steps=60)
        assert_same(spatial_env, key=FRESH_PLACEMENT | 5, steps=40)  # a reloaded model
        return
    env = make_env(suite_tasks(suite)[0])
    try:
        assert_same(env, key=0)
    finally:
        env.close()


def test_a_wrong_gain_is_caught(spatial_env, monkeypatch):
    """The comparison can fail: the fast path with a 1% stiffer position gain differs."""
    torques = fast_step.FastStepper._torques

    def stiffer(self, arm, keep=False):
        kp = arm.osc.kp
        arm.osc.kp = kp * np.array([1.01, 1, 1, 1, 1, 1])
        try:
            torques(self, arm, keep)
        finally:
            arm.osc.kp = kp

    monkeypatch.setattr(fast_step.FastStepper, "_torques", stiffer)
    with pytest.raises(AssertionError, match="joint positions"):
        assert_same(spatial_env, steps=20)


def test_compiled_torques_are_numpys_to_the_bit(spatial_env):
    """osc_torques compiled by numba gives what its own Python body gives with numpy: numba's
    arithmetic and BLAS calls round as numpy's do (the rollouts above compare the trajectories)."""
    from suites.libero.osc_torques import osc_torques

    if not hasattr(osc_torques, "py_func"):
        pytest.skip("robosuite's numba is turned off: osc_torques is Python already")
    spatial_env.fast_step = True
    spatial_env.reset(4)
    stepper = spatial_env._stepper
    (arm,) = stepper.arms
    for action in actions(12, seed=4):
        spatial_env.step(action)
        outputs = []
        for kernel in (osc_torques, osc_torques.py_func):  # each writes the same buffers anew
            kernel(*stepper.osc_arguments(arm))
            outputs.append([np.array(a) for a in (stepper.ctrl, arm.mass, arm.torques, arm.ref_vel)])
        assert np.abs(outputs[0][2]).max() > 0  # real torques, not an untouched buffer
        for compiled, python in zip(*outputs, strict=True):
            np.testing.assert_array_equal(compiled, python)


def test_paths_can_take_turns_within_an_episode(spatial_env):
    """The fast path leaves robosuite's controller and observable state as robosuite's step
    would, so the two may alternate (a test or tool stepping the raw env) with no trace."""
    acts = actions(40, seed=3)
    slow_states, _, slow_sim = rollout(spatial_env, False, 5, acts)
    spatial_env.fast_step = True
    states = [spatial_env.reset(5)["state"]]
    for i, action in enumerate(acts):
        spatial_env.fast_step = (i // 7) % 2 == 0
        states.append(spatial_env.step(action).obs["state"])
    np.testing.assert_array_equal(spatial_env.sim_state(), slow_sim)
    np.testing.assert_array_equal(np.array(states), slow_states)


@pytest.mark.slow  # software rendering here: a camera scene takes 5 s to build, 4 s to reset
def test_cameras_render_the_same_images_at_the_same_substep():
    env = make_env(suite_tasks("libero_goal")[1], cameras=True)
    try:
        acts = actions(3, seed=1)
        images = {}
        for fast in (False, True):
            env.fast_step = fast
            env.reset(2)
            images[fast] = [env.step(a).obs for a in acts]
        for slow, quick in zip(images[False], images[True], strict=True):
            assert set(quick) == set(slow)
            for key in slow:
                np.testing.assert_array_equal(quick[key], slow[key], err_msg=key)
    finally:
        env.close()


def test_fast_path_is_the_default_and_one_variable_turns_it_off(monkeypatch, spatial_env):
    monkeypatch.delenv(FAST_STEP_ENV, raising=False)
    assert fast_step_default()
    for off in ("0", "false", "OFF"):
        monkeypatch.setenv(FAST_STEP_ENV, off)
        assert not fast_step_default()
    monkeypatch.setenv(FAST_STEP_ENV, "1")
    assert fast_step_default()


def test_an_unsupported_controller_falls_back_to_robosuites_step(spatial_env, monkeypatch):
    def refuse(env):
        raise fast_step.Unsupported("OSC settings changed")

    monkeypatch.setattr(fast_step, "supported", refuse)
    spatial_env.fast_step, spatial_env._stepper = True, None
    spatial_env.reset(0)
    spatial_env.step(actions(1)[0])
    assert not spatial_env.fast_step and spatial_env._stepper is None
    spatial_env.fast_step = True


@pytest.mark.slow
@pytest.mark.parametrize("task", list(all_tasks()))
def test_every_libero_task_steps_the_same_on_both_paths(task):
    env = make_env(task)
    try:
        assert_same(env, key=0)
    finally:
        env.close()
