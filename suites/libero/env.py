"""`LiberoTaskEnv`: one real LIBERO task as a harness `TaskEnv`.

Episodes (`reset(key)`):
  key < FRESH_PLACEMENT  LIBERO's fixed init state `key mod 50` from the task's init file, set
                         after a reset as LIBERO's evaluation does (evaluation episode i uses i);
                         the reset's fixture placement is seeded by the key, as below.
  key >= FRESH_PLACEMENT a fresh scene from LIBERO's own placement sampler, as a freshly
                         loaded model places it, its arm joints moved by robosuite's default
                         initialization noise, both seeded by the key (demo and held-out
                         episodes: the distribution LIBERO drew its init states from, but never
                         one of the 50 evaluation states).
  key >= SPATIAL_KEYS    the spatial probe: fixed init state `key & 63` with every object that
                         rests on the table or floor moved by a seeded 3-6 cm offset in a
                         random direction, to beyond its demo range (`spatial_state`).
Either way SETTLE_STEPS no-op steps follow (gripper open) while objects settle; they are not
part of the episode, as in LIBERO's evaluations.

Steps go through `fast_step.FastStepper` (robosuite's control step to the bit, about three
times as fast) unless `fast_step=False` or the environment variable RETAIN_LIBERO_FAST_STEP=0
asks for robosuite's own `env.step`.

State layout (STATE_DIM = 65, one layout per task, zeros in unused object slots):
  [0:3]  end-effector position (world, m)   [3:7] end-effector quaternion (xyzw)
  [7:9]  gripper finger joint positions
  [9:65] MAX_OBJECTS = 8 slots x (position 3, quaternion xyzw 4): the task's movable objects in
         its BDDL file's order (`env.objects`), the same order every episode.
With cameras, also `agentview_rgb` and `eye_in_hand_rgb` (uint8 HxWx3), exactly as LIBERO's
dataset files store them: robosuite's renders unflipped (OpenGL convention, bottom row first).
"""

from __future__ import annotations

import dataclasses
import logging
import os
from xml.etree import ElementTree

import numpy as np

import suites.robosuite_quiet  # noqa: F401  (before any robosuite import)
from suites.base import AGENTVIEW, Observation, StepResult, SuiteError, TaskEnv, is_spatial
from suites.libero.fast_step import FastStepper, Unsupported
from suites.libero.install import ensure_installed
from suites.libero.tasks import (
    MAX_OBJECTS,
    NUM_INIT_STATES,
    OBJECT_DIM,
    PROPRIO_DIM,
    SETTLE_STEPS,
    STATE_DIM,
    LiberoTask,
    init_states,
)
from suites.render import FAST, RenderSettings, apply_to_robosuite, check_render
from suites.views import robosuite_draw, robosuite_state

FRESH_PLACEMENT = 1 << 30
SPATIAL_OFFSET = (0.03, 0.06)  # m: how far the spatial probe moves an object (x, y), at least/most
DEMO_RANGE_MARGIN = 0.005  # m: an object's demo range is its init states' x-y box grown by this
PENETRATION = 0.003  # m: a moved object may not sink deeper than this into anything new
MAX_DRAWS = 200  # offsets tried per object before it is left where it is
INIT_INDEX_BITS = 6  # a spatial key's low bits hold its init state's index (< 64)
NOOP = np.array([0, 0, 0, 0, 0, 0, -1], dtype=np.float64)  # LIBERO's dummy action: hold, open
CAMERAS = {"agentview_rgb": "agentview", "eye_in_hand_rgb": "robot0_eye_in_hand"}
# The arm's start in a fresh scene: LIBERO's init states were drawn with robosuite's "default"
# initialization noise (N(0, 0.02 rad) on each of the 7 arm joints; the 50 states' joint spread
# is 0.017-0.022). ControlEnv's own default is none, and demos that all start at one pose leave
# the policy lost from any other: issue 15's libero-broad foundation succeeded from 2-9 of 10
# demo starts and 0-2 of 10 init states on the same tasks. An init-state episode draws none, as
# LIBERO's evaluation env does: robosuite builds the OSC controller at the reset with the arm's
# pose then as its nullspace target, which set_init_state does not move (`start`).
ROBOT_INIT_NOISE = "default"
# Set to 0 (or false/no/off) to step every LIBERO env through robosuite's own `env.step`.
FAST_STEP_ENV = "RETAIN_LIBERO_FAST_STEP"
# LIBERO's render modes (suites/render.py). Faithful draws as robosuite does: its reflection pass
# is not free of pixels (libero_spatial's first task: 227 of agentview's 16384 pixels, mean
# 1.1/255, up to 134; tests/test_render.py), and its lights cast no shadows. Fast keeps the
# reflections too (over simplified meshes they cost little: 10.4 ms a view without, 13.9 with,
# and 2.99/255 from faithful against 2.69), turns multisampling off and simplifies every visual
# mesh above MESH_FACES faces (suites/libero/simplify.py).
MESH_FACES = 2000
RENDER = {"faithful": RenderSettings(),
          "fast": dataclasses.replace(FAST, reflections=True, mesh_faces=MESH_FACES)}
RAW_KEYS = ("robot0_joint_pos", "robot0_eef_pos", "robot0_eef_quat", "robot0_gripper_qpos")

log = logging.getLogger(__name__)


def fast_step_default() -> bool:
    """The fast path unless RETAIN_LIBERO_FAST_STEP turns it off: an environment variable rather
    than a benchmark setting, since both paths give the same episodes to the bit (a setting would
    split run labels and caches over a speed choice), and it reaches every worker process."""
    return os.environ.get(FAST_STEP_ENV, "1").strip().lower() not in ("0", "false", "no", "off")


def patch_floor_mount() -> None:
    """rpent-libero 0.2.0 gives its floor robot no base, and robosuite 1.5's robot_base_factory
    fails on None (libero_object's scenes): give it robosuite's NullMount, as LIBERO 1.4 had."""
    from libero.libero.envs.robots.on_the_ground_panda import OnTheGroundPanda

    prop = OnTheGroundPanda.__dict__.get("default_base")
    if isinstance(prop, property) and prop.fget(None) is None:  # left alone once fixed upstream
        OnTheGroundPanda.default_base = property(lambda self: "NullMount")


def make_raw_env(task: LiberoTask, cameras: bool, image_size: int,
                 render: RenderSettings = RENDER["faithful"]):
    """LIBERO's own env class (`ControlEnv`, the base of `OffScreenRenderEnv`, which only forces
    rendering on): OSC_POSE at 20 Hz as LIBERO sets it, rendering only when cameras are on, as
    `render` says (its simplified meshes swapped in by an XML processor, kept at reloads)."""
    ensure_installed()
    patch_floor_mount()
    from libero.libero.envs.env_wrapper import ControlEnv

    env = ControlEnv(bddl_file_name=task.bddl_file, has_renderer=False,
                     has_offscreen_renderer=cameras, use_camera_obs=cameras,
                     camera_names=list(CAMERAS.values()), camera_heights=image_size,
                     camera_widths=image_size, horizon=10**9, ignore_done=True,
                     initialization_noise=ROBOT_INIT_NOISE,
                     hard_reset=False)  # start() reloads the model for a fresh scene only
    if not cameras:
        drop_textures(env.env)
    elif render.mesh_faces:
        from suites.libero.simplify import simplified_meshes

        reload_with(env.env, simplified_meshes(render.mesh_faces))
    if cameras:
        apply_to_robosuite(env.env.sim, render)
    return env


def drop_textures(env) -> None:
    """Rebuild a robosuite env's sim without its textures, and every later reload too.

    Without cameras nothing reads them, and they are most of a LIBERO scene's memory (143 of
    the 220 MB of a kitchen scene's compiled model): an evaluation holds one scene per task at
    once, 42 of them in libero-paper. Physics reads no texture, so episodes are unchanged
    (tests/test_suite_libero.py steps both and compares the states bit for bit)."""
    reload_with(env, _without_textures)


def reload_with(env, processor) -> None:
    """Reload a robosuite env's sim through an XML processor, which it applies at every reload
    after; numpy's global RNG is left as it was."""
    env.set_xml_processor(processor)
    saved = np.random.get_state()  # LIBERO's reset may draw placements from numpy's global RNG
    try:
        env.reset_from_xml_string(env.model.get_xml())
    finally:
        np.random.set_state(saved)


def _without_textures(xml: str) -> str:
    root = ElementTree.fromstring(xml)
    asset = root.find("asset")
    for texture in asset.findall("texture") if asset is not None else []:
        asset.remove(texture)
    for material in root.iter("material"):
        material.attrib.pop("texture", None)
    return ElementTree.tostring(root, encoding="unicode")


def _quat2axisangle(quat: np.ndarray) -> np.ndarray:
    from robosuite.utils.transform_utils import quat2axisangle

    return quat2axisangle(np.asarray(quat, dtype=np.float64))


class NoExpert(SuiteError):
    """The task has no scripted expert (yet): demos for it need demos_dir."""


class LiberoTaskEnv(TaskEnv):
    def __init__(self, task: LiberoTask, cameras: bool = False, image_size: int = 128,
                 fast_step: bool | None = None, reload_fresh_scenes: bool = False,
                 render: str = "faithful"):
        self.task, self.cameras = task, cameras
        self.render = RENDER[check_render(render)]
        self.fast_step = fast_step_default() if fast_step is None else fast_step
        # a fresh scene by robosuite's reload (1.5-3 s) instead of a reset in place (10-30
        # ms): the reference tests/test_suite_libero.py holds the reset in place to
        self.reload_fresh_scenes = reload_fresh_scenes
        self._loaded_poses: tuple[np.ndarray, np.ndarray] | None = None
        self._stepper: FastStepper | None = None
        self.env = make_raw_env(task, cameras, image_size, self.render)  # the raw env experts get
        self.objects = [obj.name for obj in self.env.env.objects]  # BDDL order: fixed per task
        self.fresh_noise = dict(self.env.env.robots[0].initialization_noise)  # robosuite's default
        if len(self.objects) > MAX_OBJECTS:
            raise ValueError(f"LIBERO task {task.name!r} has {len(self.objects)} objects; the "
                             f"state holds {MAX_OBJECTS}")
        self.raw_obs: dict | None = None
        self.expert = None
        self.expert_error = ""  # why the task has no expert, once asked

    # --- TaskEnv -------------------------------------------------------------------------------
    def reset(self, key: int) -> Observation:
        self.start(int(key))
        for _ in range(SETTLE_STEPS):
            self.raw_obs, _ = self._raw_step(NOOP)
        self.expert, self.expert_error = None, ""  # made at the episode's first expert_action
        return self._observation(self.raw_obs)

    def start(self, key: int) -> None:
        """The episode's initial sim state, before the settle steps."""
        # LIBERO's samplers draw from numpy's global RNG: seed it for this reset only. Fixtures
        # (cabinets, stoves) are placed by writing the model's body poses, which the flattened
        # init state does not hold: unseeded, an init state's cabinet would sit wherever the
        # previous reset's draw left it (up to 1 cm and 2 degrees apart, enough to move a bowl
        # that starts in its drawer). A spatial episode's fixtures are its init state's.
        seed = key & ((1 << INIT_INDEX_BITS) - 1) if is_spatial(key) else key
        fresh = key >= FRESH_PLACEMENT and not is_spatial(key)
        if fresh:
            self._as_loaded()
        self.env.env.rng = np.random.default_rng(seed)  # robosuite draws the arm's noise from it
        self._arm_noise(fresh)
        saved = np.random.get_state()
        np.random.seed(seed % (1 << 32))
        try:
            self.env.reset()
        finally:
            np.random.set_state(saved)
            self.env.env.hard_reset = False
        if self.cameras:  # a reload made a new renderer
            apply_to_robosuite(self.env.sim, self.render)
        if is_spatial(key):
            state = self.spatial_state(key)
        elif key < FRESH_PLACEMENT:
            state = init_states(self.task.name)[key % NUM_INIT_STATES]
        else:
            state = self.sim_state()
        # what the flattened state leaves out (the solver's warm start, the last controls)
        # would carry the previous episode into this one: clear it, so a key gives one episode
        data = self.env.sim.data
        data.qacc_warmstart[:] = 0
        data.ctrl[:] = 0
        self.raw_obs = self.env.set_init_state(state)

    def _arm_noise(self, fresh: bool) -> None:
        """robosuite's initialization noise for the next reset: its default in a fresh scene, none
        before an init state. The reset builds the arm's controller with the pose it draws as
        the nullspace target, and set_init_state moves the arm but not that target: with noise,
        an init state's episode had another target from LIBERO's evaluation (no noise) on every
        task until this (turn_on_the_stove's expert: 103.5 steps an episode against 86.1)."""
        robot = self.env.env.robots[0]  # a reload makes a new one: set it at every start
        robot.initialization_noise = ({**self.fresh_noise} if fresh
                                      else {**self.fresh_noise, "magnitude": 0.0})

    def _as_loaded(self) -> None:
        """Make the next reset place a fresh scene as a freshly loaded model would.

        LIBERO's reset moves a fixture (a cabinet, a stove) by writing its body's pose into the
        model, and places an object that starts on a fixture (a bowl in a drawer) from the
        fixture's site as the model has it: after a reset in place the site has moved and the
        object lands 0.3-0.9 m off, in mid-air. So the bodies get back the poses the model was
        loaded with (compiled once from the env's XML), which makes the reset in place give a
        reload's scene to the bit. The reload itself (`reload_fresh_scenes`) also clears
        LIBERO's property samplers (a drawer's open/close, a stove's on/off), which its model
        loader appends to at every reload without clearing: each reload added a draw from
        numpy's global RNG, so a key's scene depended on how many reloads the env had made."""
        raw = self.env.env
        if self.reload_fresh_scenes:
            raw.object_property_initializers.clear()
            raw.hard_reset = True
            return
        if self._loaded_poses is None:
            import mujoco

            xml = raw.model.get_xml()
            for process in raw._xml_processors:  # as robosuite's _initialize_sim applies them
                xml = process(xml)
            loaded = mujoco.MjModel.from_xml_string(xml)
            self._loaded_poses = (loaded.body_pos.copy(), loaded.body_quat.copy())
        model = raw.sim.model._model
        model.body_pos[:], model.body_quat[:] = self._loaded_poses

    def step(self, action: np.ndarray) -> StepResult:
        action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        self.raw_obs, success = self._raw_step(action)
        return StepResult(self._observation(self.raw_obs),
                          self.success() if success is None else success)

    def success(self) -> bool:
        """LIBERO's BDDL goal."""
        return bool(self.env.check_success())

    def expert_action(self) -> np.ndarray:
        if self.expert is None and not self.expert_error:
            self._make_expert()
        if self.expert is None:
            raise NoExpert(f"no scripted expert for LIBERO task {self.task.name!r} "
                           f"({self.expert_error}); train it on LIBERO's files with demos_dir=")
        return np.asarray(self.expert.act(self.raw_obs), dtype=np.float32)

    def demo_extras(self) -> dict[str, np.ndarray]:
        """LIBERO's per-step dataset keys (as its create_dataset.py writes them)."""
        raw = self.raw_obs
        eef_pos, eef_quat, grip = raw["robot0_eef_pos"], raw["robot0_eef_quat"], raw["robot0_gripper_qpos"]
        ori = _quat2axisangle(eef_quat)
        return {
            "obs/ee_states": np.concatenate([eef_pos, ori]),
            "obs/ee_pos": np.asarray(eef_pos),
            "obs/ee_ori": ori,
            "obs/gripper_states": np.asarray(grip),
            "obs/joint_states": np.asarray(raw["robot0_joint_pos"]),
            "states": self.sim_state(),
            "robot_states": np.concatenate([grip, eef_pos, eef_quat]),
        }

    def close(self) -> None:
        self.env.close()

    # --- helpers -------------------------------------------------------------------------------
    def raw_keys(self) -> list[str]:
        """The raw observations this env reads (state(), demo_extras(), the proprio suite's
        state, the cameras): the fast path samples these and no other."""
        keys = list(RAW_KEYS) + [f"{name}_{part}" for name in self.objects
                                 for part in ("pos", "quat")]
        return keys + ([f"{camera}_image" for camera in CAMERAS.values()] if self.cameras else [])

    def _raw_step(self, action: np.ndarray) -> tuple[dict, bool | None]:
        """One control step: (raw observations, BDDL success, or None where not yet known)."""
        stepper = self._fast_stepper()
        if stepper is None:
            raw, *_ = self.env.step(action)
            return raw, None
        return stepper.step(action)

    def _fast_stepper(self) -> FastStepper | None:
        """The fast path bound to the env's current sim and controllers (a reset may replace
        them), or None for robosuite's own step."""
        if not self.fast_step:
            return None
        raw_env = self.env.env
        if self._stepper is None or not self._stepper.bound_to(raw_env):
            try:
                self._stepper = FastStepper(raw_env, self.raw_keys())
            except Unsupported as err:
                log.warning("LIBERO task %s: robosuite's own step (%s)", self.task.name, err)
                self.fast_step, self._stepper = False, None
        return self._stepper

    def sim_state(self) -> np.ndarray:
        """The flattened MuJoCo state, LIBERO's `states` (and init-state) format."""
        return np.asarray(self.env.get_sim_state())

    def view_state(self) -> np.ndarray:
        """`sim_state` and every body's pose in the model: LIBERO places its fixtures by writing
        their poses into the model at each reset, and the qpos alone would draw another scene's."""
        return robosuite_state(self.env.sim, bodies=True)

    def render_state(self, state: np.ndarray, camera: str, size: int) -> np.ndarray:
        """A recorded state drawn by robosuite's renderer (this env needs cameras on: without,
        its textures were dropped)."""
        if not self.cameras:
            raise SuiteError("a LIBERO env draws video frames only when built with cameras")
        return robosuite_draw(self.env.sim, state, camera or CAMERAS[AGENTVIEW], size, "libero")

    def observation_from_sim_state(self, state: np.ndarray) -> Observation:
        """The observation at a recorded sim state (reading a LIBERO dataset file's `states`)."""
        self.raw_obs = self.env.regenerate_obs_from_state(np.asarray(state, dtype=np.float64))
        return self._observation(self.raw_obs)

    # --- the spatial probe -----------------------------------------------------------------------
    def spatial_state(self, key: int) -> np.ndarray:
        """Fixed init state `key & 63` with its table- or floor-standing objects moved.

        In BDDL order, each object whose init predicate puts it on a region of the workspace
        (LIBERO's table or floor) is moved, together with any object its init puts on top of it
        (a bowl on a cookie box), by an offset of SPATIAL_OFFSET length in a random direction,
        drawn from a generator seeded by the key until the object lands outside its demo range
        (the x-y box of its 50 init states, which LIBERO's placement sampler matches to within
        4 mm, grown by DEMO_RANGE_MARGIN) and sinks into nothing it did not already touch.
        Objects in or on a fixture (a drawer, a cabinet top) stay. An object with no such
        offset in MAX_DRAWS draws stays too (none of the tasks measured needed it).
        """
        index = key & ((1 << INIT_INDEX_BITS) - 1)
        state = np.array(init_states(self.task.name)[index % NUM_INIT_STATES], dtype=np.float64)
        rng = np.random.default_rng(key)
        for base, stack in self.spatial_stacks().items():
            addresses = [self.qpos_address(name) for name in stack]
            low, high = self.demo_ranges()[base]
            touching = self._touching(state, stack)
            for _ in range(MAX_DRAWS):
                angle, length = rng.uniform(0, 2 * np.pi), rng.uniform(*SPATIAL_OFFSET)
                offset = length * np.array([np.cos(angle), np.sin(angle)])
                xy = state[addresses[0]:addresses[0] + 2] + offset
                if np.all((xy >= low) & (xy <= high)):
                    continue
                trial = state.copy()
                for a in addresses:
                    trial[a:a + 2] += offset
                if not self._sinks(trial, stack, touching):
                    state = trial
                    break
        return state

    def spatial_stacks(self) -> dict[str, list[str]]:
        """Object on the workspace -> it and the objects its init puts on top of it."""
        problem = self.env.env
        on = [(fact[1], fact[2]) for fact in problem.parsed_problem["initial_state"]
              if len(fact) == 3 and fact[0].lower() == "on" and fact[1] in problem.objects_dict]
        stacks = {obj: [obj] for obj, where in on
                  if where.startswith(problem.workspace_name + "_")}
        for obj, where in on:
            if where in stacks:
                stacks[where].append(obj)
        return stacks

    def demo_ranges(self) -> dict[str, tuple[np.ndarray, np.ndarray]]:
        """Object -> the (low, high) x-y corners of its demo range (`spatial_state`)."""
        if not hasattr(self, "_demo_ranges"):
            states = init_states(self.task.name)
            self._demo_ranges = {}
            for name in self.objects:
                a = self.qpos_address(name)
                xy = states[:, a:a + 2]
                self._demo_ranges[name] = (xy.min(axis=0) - DEMO_RANGE_MARGIN,
                                           xy.max(axis=0) + DEMO_RANGE_MARGIN)
        return self._demo_ranges

    def qpos_address(self, name: str) -> int:
        """Where the object's free-joint x sits in a flattened state ([time, qpos, qvel])."""
        joint = self.env.env.objects_dict[name].joints[-1]
        return 1 + self.env.sim.model.get_joint_qpos_addr(joint)[0]

    def _contacts(self, state: np.ndarray, stack: list[str]) -> list[tuple[int, float]]:
        """(root body, depth) of every contact between the stack and anything else at `state`."""
        sim = self.env.sim
        sim.set_state_from_flattened(state)
        sim.forward()
        model, data = sim.model._model, sim.data._data
        objects = self.env.env.objects_dict
        ours = {model.body_rootid[model.body(objects[n].root_body).id] for n in stack}
        out = []
        for contact in data.contact[:data.ncon]:
            roots = [model.body_rootid[model.geom_bodyid[geom]]
                     for geom in (contact.geom1, contact.geom2)]
            if (roots[0] in ours) != (roots[1] in ours):
                out.append((roots[1] if roots[0] in ours else roots[0], -contact.dist))
        return out

    def _touching(self, state: np.ndarray, stack: list[str]) -> set[int]:
        return {root for root, _ in self._contacts(state, stack)}

    def _sinks(self, state: np.ndarray, stack: list[str], touching: set[int]) -> bool:
        return any(depth > PENETRATION and root not in touching
                   for root, depth in self._contacts(state, stack))

    def _make_expert(self) -> None:
        """The task's expert (suites.libero.experts), built once per episode from the settled
        scene: lazily, so evaluating a policy never depends on an expert."""
        try:
            from suites.libero.experts import make_expert
        except ModuleNotFoundError as err:
            if err.name != "suites.libero.experts":
                raise
            self.expert_error = "suites.libero.experts is not installed"
            return
        try:
            self.expert = make_expert(self.task.name, self.env)
        except (NotImplementedError, KeyError) as err:
            self.expert_error = str(err).strip("'\"") or type(err).__name__

    def state(self, raw: dict) -> np.ndarray:
        state = np.zeros(STATE_DIM, dtype=np.float32)
        state[0:3] = raw["robot0_eef_pos"]
        state[3:7] = raw["robot0_eef_quat"]
        state[7:9] = raw["robot0_gripper_qpos"]
        for i, name in enumerate(self.objects):
            start = PROPRIO_DIM + OBJECT_DIM * i
            state[start:start + 3] = raw[f"{name}_pos"]
            state[start + 3:start + 7] = raw[f"{name}_quat"]
        return state

    def _observation(self, raw: dict) -> Observation:
        obs = {"state": self.state(raw)}
        if self.cameras:
            for key, camera in CAMERAS.items():
                obs[key] = np.asarray(raw[f"{camera}_image"], dtype=np.uint8)
        return obs
