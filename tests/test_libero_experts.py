"""The scripted experts on real LIBERO: coverage errors, and real rollouts to success through the
suite's own env (LIBERO's protocol: the fixed init state, the settle steps, the step limit)."""

from __future__ import annotations

import numpy as np
import pytest

from suites import get_suite
from suites.libero.experts import EXPERT_TASKS, make_expert
from suites.libero.experts.coverage import LIBERO_GOAL, LIBERO_OBJECT
from suites.libero.experts.planner import HAND_ROOM, _box_gap, _overhangs, _push_legs, _withdrawal
from suites.libero.experts.scene import Scene, hand_down
from suites.libero.experts.skills import Grasp, facing, nearer_half_turn, turn_angle
from suites.libero.tasks import suite_tasks


def test_uncovered_task_raises_one_line_key_error():
    with pytest.raises(KeyError) as err:
        make_expert("no_such_task_in_libero", env=None)
    message = str(err.value)
    assert "no_such_task_in_libero" in message and "\n" not in message


def test_libero_object_and_goal_suites_are_covered():
    assert set(LIBERO_OBJECT) | set(LIBERO_GOAL) <= EXPERT_TASKS
    assert suite_tasks("libero_object") == list(LIBERO_OBJECT)
    assert suite_tasks("libero_goal") == list(LIBERO_GOAL)


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


def test_expert_puts_a_bowl_into_the_drawer_that_opens_over_it():
    # the open top drawer hangs over the bowl in front of the cabinet
    assert _solves("open_the_top_drawer_and_put_the_bowl_inside", init_state=1)


def test_front_grasp_takes_the_half_turn_the_wrist_reaches():
    # A handle facing -y: the plain front grasp is half a turn from the hand's home pose (where
    # the controller's orientation error vanishes, and past the wrist's limit); its twin is not.
    home = hand_down(0.0)
    front = facing(np.array([0.0, -1.0, 0.0]), np.pi / 2)
    chosen = nearer_half_turn(front, home)
    assert turn_angle(front, home) == pytest.approx(np.pi)
    assert turn_angle(chosen, home) == pytest.approx(np.pi / 2)
    np.testing.assert_allclose(chosen[:, 2], front[:, 2])  # same pointing direction


@pytest.fixture(scope="module")
def plate_env():
    env = get_suite("libero").make_env("push_the_plate_to_the_front_of_the_stove")
    yield env
    env.close()


def test_evaluation_reset_places_fixtures_the_same_whatever_ran_before(plate_env):
    env = plate_env
    model = env.env.sim.model
    cabinet = model.body_name2id("wooden_cabinet_1_main")
    saved = np.random.get_state()
    env.reset(3)
    first = model.body_pos[cabinet].copy(), model.body_quat[cabinet].copy()
    env.reset(7)
    np.random.seed(123)  # the caller's RNG must not matter either
    env.reset(3)
    np.testing.assert_array_equal(model.body_pos[cabinet], first[0])
    np.testing.assert_array_equal(model.body_quat[cabinet], first[1])
    np.random.set_state(saved)


def _distance_to_box(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> float:
    return float(np.linalg.norm(np.maximum(np.maximum(lo - points, points - hi), 0.0), axis=1).min())


def _polyline(start: np.ndarray, legs: list[np.ndarray]) -> np.ndarray:
    stops = [start, *legs]
    return np.concatenate([a + np.linspace(0, 1, 50)[:, None] * (b - a)
                           for a, b in zip(stops, stops[1:])])


def test_plate_push_ends_inside_its_region_going_around_the_cream_cheese(plate_env):
    plate_env.reset(0)
    scene = Scene(plate_env.env)
    region = "main_table_stove_front_region"
    legs = _push_legs(scene, "plate_1", region)
    half = np.abs(scene.mat(region) @ scene.site_size(region))[:2]
    assert np.all(np.abs(legs[-1] - scene.pos(region)[:2]) <= half)  # LIBERO's region test
    start = scene.pos("plate_1")[:2]
    lo, hi = (b[:2] for b in scene.box("cream_cheese_1"))
    straight = _distance_to_box(_polyline(start, [legs[-1]]), lo, hi)
    chosen = _distance_to_box(_polyline(start, legs), lo, hi)
    assert len(legs) == 2 and chosen > straight + 0.03  # one turn, well clear of the cheese


def test_bowl_under_an_open_drawer_is_pinched_wrist_away_and_withdrawn_before_the_lift(plate_env):
    plate_env.reset(0)  # the bowl stands in front of the cabinet's top drawer
    scene = Scene(plate_env.env)
    bowl = "akita_black_bowl_1"
    assert _overhangs(scene, bowl) == []  # closed, the drawer is beside the bowl
    sim = plate_env.env.sim
    sim.data.qpos[sim.model.get_joint_qpos_addr("wooden_cabinet_1_top_level")] = -0.15  # open
    sim.forward()
    over = _overhangs(scene, bowl)
    assert len(over) == 1
    drawer_lo, drawer_hi = over[0]
    toward = ((drawer_lo + drawer_hi) / 2 - scene.pos(bowl))[:2]
    grasp = Grasp.plan(scene, bowl, wrist_from=(drawer_lo + drawer_hi) / 2)
    plain = Grasp.plan(scene, bowl)
    assert grasp.yaw == pytest.approx(-plain.yaw)  # the half-turn twin of the plain rim pinch
    assert (hand_down(grasp.yaw) @ scene.wrist_offset())[:2] @ toward < 0  # wrist turned away
    np.testing.assert_allclose(grasp.offset, plain.offset)  # the same grip point
    rise, shift = _withdrawal(scene, bowl, grasp, over)
    lo, hi = scene.box(bowl)
    assert 0 < rise and hi[2] + rise < drawer_lo[2]  # lifted off the table, still under it
    assert shift @ toward < 0  # out toward the grip side, away from the drawer
    assert _box_gap(lo[:2] + shift, hi[:2] + shift, drawer_lo[:2], drawer_hi[:2]) >= HAND_ROOM
