"""Real LIBERO (suite "libero"): its 130 tasks, LIBERO's init-state evaluation protocol, the
fixed state layout, the asset check, and demo files in LIBERO's layout both ways.
Building a LIBERO env takes seconds: this file builds seven (one per suite, one with cameras, one
with textures, one for demos_dir)."""

from __future__ import annotations

import json
import sys
import types

import h5py
import numpy as np
import pytest

from harness.common.errors import RetainError
from harness.config.benchmark import BenchConfig
from harness.data.demos import DemoSpec, Episode, read_demo_file, write_demo_file
from harness.evaluate.rollouts import evaluation_episodes
from suites import get_suite
from suites.libero import install
from suites.libero.env import FRESH_PLACEMENT, NoExpert
from suites.libero.files import read_libero_file, task_file
from suites.libero.tasks import (
    MAX_OBJECTS,
    MAX_STEPS,
    NUM_INIT_STATES,
    STATE_DIM,
    SUITES,
    all_tasks,
    init_states,
    suite_tasks,
)
from tests.libero_file import write_libero_file

SUITE = get_suite("libero")
OBJECT_TASK = "pick_up_the_alphabet_soup_and_place_it_in_the_basket"
SPATIAL_TASK = "pick_up_the_black_bowl_between_the_plate_and_the_ramekin_and_place_it_on_the_plate"


@pytest.fixture(scope="module")
def object_env():
    env = SUITE.make_env(OBJECT_TASK)
    yield env
    env.close()


def test_five_suites_130_tasks_with_libero_names_and_instructions():
    sizes = {s: len(suite_tasks(s)) for s in SUITES}
    assert sizes == {"libero_spatial": 10, "libero_object": 10, "libero_goal": 10,
                     "libero_10": 10, "libero_90": 90}
    names = SUITE.task_names()
    assert len(names) == len(set(names)) == 130  # distinct without qualification
    assert suite_tasks("libero_object")[0] == OBJECT_TASK  # LIBERO's standard order
    assert SUITE.instruction(OBJECT_TASK) == "pick up the alphabet soup and place it in the basket"
    assert all(SUITE.instruction(t) for t in names)
    assert {SUITE.max_steps(t) for t in suite_tasks("libero_goal")} == {300}
    assert SUITE.max_steps("KITCHEN_SCENE1_put_the_black_bowl_on_the_plate") == MAX_STEPS["libero_90"]
    with pytest.raises(ValueError, match="unknown libero task 'no_such_task'; valid: ") as err:
        SUITE.make_env("no_such_task")
    assert "\n" not in str(err.value)


def test_max_objects_is_the_most_any_task_has():
    from libero.libero.envs.bddl_utils import robosuite_parse_problem

    counts = [sum(len(v) for v in robosuite_parse_problem(t.bddl_file)["objects"].values())
              for t in all_tasks().values()]
    assert max(counts) == MAX_OBJECTS and STATE_DIM == SUITE.state_dim == 9 + 7 * MAX_OBJECTS


def test_evaluation_episode_i_starts_from_init_state_i_mod_50(object_env):
    keys = SUITE.episode_keys(OBJECT_TASK, "eval", 53)
    assert keys == list(range(53))
    for key in (0, 3, 52):
        object_env.start(key)  # before the settle steps
        np.testing.assert_array_equal(object_env.sim_state(), init_states(OBJECT_TASK)[key % 50])
    first = object_env.reset(3)["state"]
    np.testing.assert_array_equal(object_env.reset(3)["state"], first)
    assert not np.array_equal(object_env.reset(4)["state"], first)
    # evaluation runs each task for its LIBERO suite's limit, whatever the benchmark's default
    episodes = evaluation_episodes(SUITE, [OBJECT_TASK, SPATIAL_TASK], 2, 100)
    assert [(e.seed, e.max_steps) for e in episodes] == [(0, 280), (1, 280), (0, 220), (1, 220)]


def test_an_evaluation_episode_keeps_liberos_controller_and_a_demo_its_noisy_start(object_env):
    """robosuite builds the arm's OSC controller at the reset, with the arm's pose then as its
    nullspace target, and set_init_state leaves that target alone: an init state's episode must
    reset without the arm's noise, as LIBERO's evaluation env (no noise) does; a fresh scene
    draws it."""
    robot = object_env.env.env.robots[0]

    def target(key: int) -> np.ndarray:
        object_env.start(key)
        return np.array(robot.composite_controller.part_controllers["right"].initial_joint)

    demo = SUITE.episode_keys(OBJECT_TASK, "demo", 1)[0]
    for key in (3, demo, 3):  # an evaluation episode after a demo's is LIBERO's all the same
        if key == demo:
            assert np.abs(target(key) - robot.init_qpos).max() > 1e-3  # the demo's noisy start
        else:
            np.testing.assert_array_equal(target(key), robot.init_qpos)


def test_the_evaluation_version_is_part_of_the_stage0_and_job_keys(monkeypatch):
    """A change to how evaluation episodes start makes the cached stage-0 evaluation, the jobs
    (their MLflow runs) and their stage checkpoints (which hold the evaluations) new ones."""
    from harness.protocol.foundation import stage0_key
    from harness.run.plan import plan, variant_job_key

    variant = plan(["BENCH=libero-spatial", "METHOD=sft"]).variants[0]
    keys = stage0_key(variant.cfg, SUITE), variant_job_key(variant, SUITE, 0)
    monkeypatch.setattr(type(SUITE), "evaluation_version", "")
    assert stage0_key(variant.cfg, SUITE) != keys[0]
    assert variant_job_key(variant, SUITE, 0) != keys[1]


def test_demo_episodes_are_fresh_seeded_scenes_not_evaluation_states(object_env):
    keys = SUITE.episode_keys(OBJECT_TASK, "demo", 2)
    assert all(k >= FRESH_PLACEMENT for k in keys)
    object_env.start(keys[0])
    first = object_env.sim_state()
    object_env.start(keys[1])
    assert not np.allclose(object_env.sim_state(), first)
    object_env.start(keys[0])
    np.testing.assert_array_equal(object_env.sim_state(), first)
    assert not np.isclose(init_states(OBJECT_TASK), first).all(axis=1).any()


@pytest.mark.slow
def test_demo_starts_spread_the_arm_like_liberos_init_states(object_env):
    """LIBERO's 50 init states start the arm's 7 joints about 0.02 rad from its home pose: demos
    that all started at the home pose left the policy lost from every evaluation start."""
    def arm_spread(states: np.ndarray) -> float:  # a flattened state is [time, qpos, qvel]
        joints = states[:, 1:8]
        return float((joints - joints.mean(0)).std())

    starts = []
    for key in SUITE.episode_keys(OBJECT_TASK, "demo", 16):
        object_env.start(key)
        starts.append(object_env.sim_state())
    demo, libero = arm_spread(np.stack(starts)), arm_spread(np.asarray(init_states(OBJECT_TASK)))
    assert 0.015 < libero < 0.025
    assert 0.6 * libero < demo < 1.5 * libero, (demo, libero)


def test_demo_starts_put_objects_on_fixtures_where_liberos_init_states_have_them():
    """A bowl that starts on (or in) the cabinet: LIBERO places it from the fixture's site, which
    after a reset in place put it 0.3-0.9 m off, in mid-air over the table."""
    task = "pick_up_the_black_bowl_in_the_top_drawer_of_the_wooden_cabinet_and_place_it_on_the_plate"
    env = SUITE.make_env(task)
    try:
        states = np.asarray(init_states(task))
        env.start(0)  # an init state first: the fresh scenes that follow come after a reset
        for key in SUITE.episode_keys(task, "demo", 3):
            env.start(key)
            start = env.sim_state()
            for name in env.objects:
                a = env.qpos_address(name)
                low, high = states[:, a:a + 3].min(0) - 0.01, states[:, a:a + 3].max(0) + 0.01
                assert (low <= start[a:a + 3]).all() and (start[a:a + 3] <= high).all(), name
    finally:
        env.close()


def _fresh_scene_two_ways(env, key: int, steps: int):
    """(sim state after `steps` seeded actions, states seen) from fresh scene `key`, by a reset
    in place and then by robosuite's reload."""
    out = []
    for reload in (False, True):
        env.reload_fresh_scenes = reload
        seen = [env.reset(key)["state"]]
        rng = np.random.default_rng(key)
        seen += [env.step(rng.uniform(-1, 1, 7)).obs["state"] for _ in range(steps)]
        out.append((env.sim_state(), np.array(seen)))
    env.reload_fresh_scenes = False
    return out


def assert_reset_in_place_is_a_reload(env, keys, steps: int) -> None:
    samplers = len(env.env.env.object_property_initializers)
    env.start(0)  # a history: an init state, another fresh scene, a spatial probe
    env.start(FRESH_PLACEMENT + 99)
    env.start(SUITE.episode_keys(env.task.name, "spatial", 1)[0])
    for key in keys:
        (in_place, seen_in_place), (reloaded, seen_reloaded) = _fresh_scene_two_ways(env, key,
                                                                                    steps)
        np.testing.assert_array_equal(in_place, reloaded, err_msg=f"{env.task.name} key {key}")
        np.testing.assert_array_equal(seen_in_place, seen_reloaded)
    # LIBERO's loader appends its property samplers at every reload: the reload clears them
    assert len(env.env.env.object_property_initializers) == samplers


def test_a_fresh_scene_by_a_reset_in_place_is_a_reloaded_models_to_the_bit():
    """The drawer task: a bowl placed from a fixture's site and a drawer opened by a property
    sampler, the two things a reset in place got wrong before the model's poses were put back
    (and the reload before its samplers were cleared: a key's scene moved with each reload)."""
    task = "pick_up_the_black_bowl_in_the_top_drawer_of_the_wooden_cabinet_and_place_it_on_the_plate"
    env = SUITE.make_env(task)
    try:  # one sampler, as the BDDL's reading (LiberoSuite.version) has it
        assert len(env.env.env.object_property_initializers) == 1
        assert_reset_in_place_is_a_reload(env, SUITE.episode_keys(task, "demo", 2), steps=30)
    finally:
        env.close()


def test_only_the_tasks_whose_scenes_changed_get_new_demos():
    """Suite version 4 (a fresh scene independent of the env's reloads) changed the 28 tasks
    whose reset opens a drawer or turns on a stove; the others' cached demo files still hold."""
    drawer = "pick_up_the_black_bowl_in_the_top_drawer_of_the_wooden_cabinet_and_place_it_on_the_plate"
    versions = {task: SUITE.version(task) for task in all_tasks()}
    assert versions[drawer] == "4" and versions[OBJECT_TASK] == versions[SPATIAL_TASK] == "3"
    assert sum(v == "4" for v in versions.values()) == 28


@pytest.mark.slow
@pytest.mark.parametrize("task", sorted(all_tasks()))
def test_every_libero_tasks_fresh_scene_is_a_reloaded_models(task):
    env = SUITE.make_env(task)
    try:
        assert_reset_in_place_is_a_reload(env, SUITE.episode_keys(task, "demo", 1), steps=10)
    finally:
        env.close()


def test_state_layout_is_fixed_per_task(object_env):
    obs = object_env.reset(7)
    state, raw = obs["state"], object_env.raw_obs
    assert state.shape == (STATE_DIM,) and state.dtype == np.float32
    np.testing.assert_allclose(state[0:3], raw["robot0_eef_pos"], rtol=1e-6)
    np.testing.assert_allclose(state[7:9], raw["robot0_gripper_qpos"], rtol=1e-6)
    objects = object_env.objects
    assert objects[:2] == ["alphabet_soup_1", "basket_1"] and len(objects) == 7  # BDDL order
    for i, name in enumerate(objects):
        np.testing.assert_allclose(state[9 + 7 * i:12 + 7 * i], raw[f"{name}_pos"], rtol=1e-6)
        np.testing.assert_allclose(state[12 + 7 * i:16 + 7 * i], raw[f"{name}_quat"], rtol=1e-6)
    assert not state[9 + 7 * len(objects):].any()  # unused slots
    object_env.reset(8)
    assert object_env.objects == objects
    result = object_env.step(np.zeros(7))
    assert isinstance(result.success, bool) and np.isfinite(result.obs["state"]).all()


def _textures(env) -> int:
    return env.env.env.sim.model._model.ntex


def test_without_cameras_a_scene_drops_its_textures_and_keeps_its_physics(object_env, monkeypatch):
    """Textures are most of a scene's memory and nothing reads them without cameras; the
    episodes are bit for bit those of the textured scene, from an init state and from a fresh
    placement."""
    from suites.libero import env as libero_env

    monkeypatch.setattr(libero_env, "drop_textures", lambda env: None)
    textured = SUITE.make_env(OBJECT_TASK)
    try:
        assert _textures(textured) > 0 and _textures(object_env) == 0
        for key in (3, FRESH_PLACEMENT + 5):
            object_env.reset(key)
            textured.reset(key)
            np.testing.assert_array_equal(object_env.sim_state(), textured.sim_state())
            rng = np.random.default_rng(key)
            for _ in range(20):
                action = rng.uniform(-1, 1, 7)
                stripped, kept = object_env.step(action), textured.step(action)
                np.testing.assert_array_equal(stripped.obs["state"], kept.obs["state"])
            np.testing.assert_array_equal(object_env.sim_state(), textured.sim_state())
            assert _textures(object_env) == 0
    finally:
        textured.close()


def test_spatial_task_with_cameras_steps_and_renders():
    env = SUITE.make_env(SPATIAL_TASK, cameras=True, image_size=32)  # needs MUJOCO_GL=egl
    try:
        obs = env.reset(0)
        assert _textures(env) > 0  # cameras keep them
        assert obs["state"].shape == (STATE_DIM,)
        for key in ("agentview_rgb", "eye_in_hand_rgb"):
            assert obs[key].shape == (32, 32, 3) and obs[key].dtype == np.uint8 and obs[key].any()
        rng = np.random.default_rng(0)
        for _ in range(5):
            result = env.step(rng.uniform(-1, 1, 7))
        assert result.success is False and result.obs["agentview_rgb"].shape == (32, 32, 3)
    finally:
        env.close()


@pytest.mark.parametrize("suite_name, index", [("libero_goal", 0), ("libero_10", 9), ("libero_90", 0)])
def test_a_task_of_every_other_suite_builds_steps_and_reports_success(suite_name, index):
    from suites.libero.build_all import check_task

    _built, objects = check_task(SUITE, suite_tasks(suite_name)[index], steps=3)
    assert 1 <= objects <= MAX_OBJECTS


def test_task_without_expert_is_a_one_line_error_naming_it(object_env, monkeypatch):
    def make_expert(task, env):
        raise NotImplementedError(f"no expert for {task}")

    monkeypatch.setitem(sys.modules, "suites.libero.experts",
                        types.SimpleNamespace(make_expert=make_expert))
    object_env.reset(0)
    with pytest.raises(NoExpert, match=OBJECT_TASK) as err:
        object_env.expert_action()
    assert "\n" not in str(err.value)


def test_expert_gets_the_raw_env_after_the_settle_and_the_latest_raw_obs(object_env, monkeypatch):
    seen = []

    class Expert:
        def act(self, raw):
            seen.append(raw)
            return np.ones(7)

    def make_expert(task, env):
        seen.append((task, env, env.get_sim_state().copy()))
        return Expert()

    monkeypatch.setitem(sys.modules, "suites.libero.experts",
                        types.SimpleNamespace(make_expert=make_expert))
    object_env.reset(5)
    assert object_env.expert_action().tolist() == [1.0] * 7
    task, raw_env, state = seen[0]
    assert task == OBJECT_TASK and raw_env is object_env.env
    assert not np.array_equal(state, init_states(OBJECT_TASK)[5])  # settled first
    object_env.step(np.zeros(7))
    object_env.expert_action()
    assert len(seen) == 3 and seen[-1] is object_env.raw_obs  # one expert per episode, latest obs
    object_env.reset(6)
    object_env.expert_action()
    assert len(seen) == 5  # a new one after a reset


# --- assets ---------------------------------------------------------------------------------------


def test_missing_or_broken_assets_stop_with_one_line_saying_how_to_repair(tmp_path):
    with pytest.raises(install.LiberoAssetsError, match="make venv") as err:
        install.ensure_installed(source=tmp_path, target=tmp_path / "link")
    assert "\n" not in str(err.value) and "missing" in str(err.value)
    (tmp_path / "scenes").mkdir()
    with pytest.raises(install.LiberoAssetsError, match=r"broken: \d+ of \d+ files missing"):
        install.ensure_installed(source=tmp_path, target=tmp_path / "link")
    assert not (tmp_path / "link").exists()


def test_assets_link_is_made_once_and_kept(tmp_path):
    source, target = install.asset_source(), tmp_path / "assets"
    install.ensure_installed(source=source, target=target)
    assert target.is_symlink() and target.resolve() == source.resolve()
    install.ensure_installed(source=source, target=target)  # idempotent
    assert (target / "scenes").is_dir()


# --- demo files in LIBERO's layout ----------------------------------------------------------------


def _recorded_episode(env, key: int, steps: int) -> Episode:
    obs, extras, actions = [env.reset(key)], [], []
    rng = np.random.default_rng(key)
    for _ in range(steps):
        extras.append(env.demo_extras())
        actions.append(rng.uniform(-1, 1, 7).astype(np.float32))
        obs.append(env.step(actions[-1]).obs)
    stack = {k: np.stack([o[k] for o in obs[:-1]]) for k in obs[0]}
    return Episode(np.stack(actions), stack, key, {k: np.stack([e[k] for e in extras]) for k in extras[0]})


def test_suite_demo_file_has_libero_keys_and_round_trips(object_env, tmp_path):
    episode = _recorded_episode(object_env, FRESH_PLACEMENT + 1, 6)
    spec = DemoSpec("libero", SUITE.version(OBJECT_TASK), OBJECT_TASK, "demo", 1, 280)
    path = tmp_path / f"{OBJECT_TASK}_demo.hdf5"
    write_demo_file(path, [episode], spec, SUITE.instruction(OBJECT_TASK),
                    SUITE.demo_file_attrs(OBJECT_TASK))
    with h5py.File(path) as f:
        data = f["data"]
        info = json.loads(data.attrs["problem_info"])
        assert info["problem_name"] == "libero_floor_manipulation"  # LIBERO's own problem_info
        assert info["language_instruction"] == "pick the alphabet soup and place it in the basket"
        assert data.attrs["instruction"] == SUITE.instruction(OBJECT_TASK)
        assert data.attrs["bddl_file_name"].endswith(f"{OBJECT_TASK}.bddl")
        assert json.loads(data.attrs["env_args"])["env_kwargs"]["controller"] == "OSC_POSE"
        demo = data["demo_0"]
        for key, width in (("actions", 7), ("states", len(object_env.sim_state())),
                           ("obs/ee_states", 6), ("obs/gripper_states", 2), ("obs/joint_states", 7),
                           ("robot_states", 9)):
            assert demo[key].shape == (6, width), key
        assert demo["rewards"].shape == demo["dones"].shape == (6,)
    _, [back] = read_demo_file(path, spec)
    assert set(back.obs) == {"state"}  # LIBERO's extra keys are not read back as observations
    np.testing.assert_array_equal(back.obs["state"], episode.obs["state"])
    # and LIBERO's own-file reader rebuilds the same states from the file's sim states
    # and LIBERO's own-file reader rebuilds the states from the file's sim states: the same up to
    # the motion of one physics substep (robosuite reads its live observation before integrating)
    [libero_back] = read_libero_file(path, object_env).episodes
    np.testing.assert_allclose(libero_back["obs"]["state"], episode.obs["state"], atol=3e-3)


def test_libero_layout_file_loads_with_state_rebuilt_from_sim_states(object_env, tmp_path):
    states = init_states(OBJECT_TASK)
    path = write_libero_file(tmp_path / f"{OBJECT_TASK}_demo.hdf5", OBJECT_TASK, states,
                             lengths=(4, 6), instruction="pick it up")
    task = read_libero_file(path, object_env, cameras=True)
    assert task.instruction == "pick it up" and [len(e["actions"]) for e in task.episodes] == [4, 6]
    object_env.start(5)  # demo_1's second step is init state 5
    np.testing.assert_allclose(task.episodes[1]["obs"]["state"][1],
                               object_env.state(object_env.raw_obs), atol=1e-6)
    with h5py.File(path) as f:
        assert np.array_equal(task.episodes[0]["obs"]["agentview_rgb"], f["data/demo_0/obs/agentview_rgb"][()])
    assert set(read_libero_file(path, object_env).episodes[0]["obs"]) == {"state"}
    with pytest.raises(ValueError, match="images of 8x8, not image_size=128, in 'data/demo_0/obs/agentview_rgb'"):
        read_libero_file(path, object_env, cameras=True, image_size=128)


@pytest.mark.parametrize("drop", ["obs/gripper_states", "states", "actions"])
def test_libero_file_missing_a_key_is_one_line_naming_it(object_env, tmp_path, drop):
    path = write_libero_file(tmp_path / "broken.hdf5", OBJECT_TASK, init_states(OBJECT_TASK),
                             drop=drop)
    with pytest.raises(ValueError, match=f"missing key 'data/demo_0/{drop}'") as err:
        read_libero_file(path, object_env)
    assert "\n" not in str(err.value) and str(path) in str(err.value)


def test_demos_dir_matches_tasks_by_name_and_names_a_missing_one(tmp_path, monkeypatch):
    from harness.data.prepare import user_demos

    states = init_states(OBJECT_TASK)
    folder = tmp_path / "libero_object"
    folder.mkdir()
    write_libero_file(folder / "renamed.hdf5", OBJECT_TASK, states, lengths=(3, 4, 5, 6),
                      bddl_file=all_tasks()[OBJECT_TASK].bddl_file)
    assert task_file(folder, OBJECT_TASK) == folder / "renamed.hdf5"  # by its BDDL file name
    cfg = BenchConfig("t", "libero", [OBJECT_TASK], [SPATIAL_TASK], demos_per_task=2,
                      heldout_demos_per_task=1, demos_dir=str(folder), cache_dir=str(tmp_path / "c"))
    splits = user_demos(cfg, SUITE, OBJECT_TASK)
    assert [len(e) for e in splits["demo"]] == [3, 4] and [len(e) for e in splits["heldout"]] == [6]
    assert splits["demo"][0].obs["state"].shape == (3, STATE_DIM)
    monkeypatch.setattr(SUITE, "make_env", lambda *a, **k: pytest.fail("built an env"))
    cached = user_demos(cfg, SUITE, OBJECT_TASK)  # from the cache: no env is built
    np.testing.assert_array_equal(cached["heldout"][0].obs["state"], splits["heldout"][0].obs["state"])
    with pytest.raises(RetainError, match=f"no LIBERO demo file for task '{SPATIAL_TASK}'") as err:
        user_demos(cfg, SUITE, SPATIAL_TASK)
    assert "\n" not in str(err.value)


def test_expert_table_writes_one_block_per_libero_suite(tmp_path):
    from suites.expert_table import ExpertResult, markers, render_table, write_table

    readme = tmp_path / "README.md"
    begin, end = markers("libero_object")
    other = "\n".join(markers("libero_goal"))
    readme.write_text(f"intro\n{begin}\nold\n{end}\n{other}\noutro\n")
    write_table(render_table([ExpertResult(OBJECT_TASK, "", 47, NUM_INIT_STATES, 120.0)], 45.0),
                readme, "libero_object")
    text = readme.read_text()
    assert f"| `{OBJECT_TASK}` | 47/50 (94%) | 120.0 |" in text
    assert "old" not in text and text.endswith(f"{other}\noutro\n")


def test_every_libero_benchmark_but_libero_10_has_a_scripted_expert_for_every_task():
    """A task without an expert would stop a run after the demos of the tasks before it; only
    libero-10's stream (no expert yet) needs LIBERO's own files through `demos_dir`."""
    from harness.config.benchmark import benchmark_names, load_benchmark
    from suites.libero.experts import EXPERT_TASKS

    libero = [load_benchmark(n) for n in benchmark_names()]
    libero = [b for b in libero if b.suite == "libero"]
    assert len(libero) >= 5
    for bench in libero:
        missing = sorted(set(bench.foundation_tasks) - EXPERT_TASKS)
        assert not missing, f"{bench.name}: no expert for {missing}"
    needs_files = [b.name for b in libero if set(b.stream_tasks) - EXPERT_TASKS]
    assert needs_files == ["libero-10"]


def test_reading_a_tasks_bddl_prints_no_gym_notice():
    """LIBERO's env package imports gym 0.26, which prints a four-line deprecation notice: a
    study's dry run (which reads the BDDL files) greeted users with it until tasks.py silenced
    it as the env does."""
    import subprocess

    code = ("from suites.libero.tasks import sets_joints_at_reset, suite_tasks; "
            "print(sets_joints_at_reset(suite_tasks('libero_goal')[0]))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=120, check=True)
    assert done.stdout.strip() in ("True", "False")
    assert "Gym has been unmaintained" not in done.stderr, done.stderr
