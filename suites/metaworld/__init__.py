"""Meta-World v3 (Sawyer arm, MuJoCo): every task that has a scripted expert in `metaworld.policies`.

Observations are Meta-World's 39-d goal-observable state (hand, gripper, two objects, the previous
frame of those, goal). Initial states are seeded per episode through Meta-World's own
`seeded_rand_vec` path, so `reset(seed)` is reproducible across processes.

Spatial probe (keys >= SPATIAL_KEYS): the task's own reset draws its object and goal positions
(the "rand vec") from a widened box instead of `_random_reset_space`: every x and y range at
least MIN_WIDENED wide is scaled by WIDEN around its centre and clipped to the hand's reach
(`hand_low`/`hand_high`); z ranges and near-fixed coordinates stay as they are. Draws that land
inside the original box are rejected, so every probe state has at least one object or goal
coordinate beyond the demos' range; so are states where two bodies press into each other more
than PENETRATION deeper than in the task's own states (an object inside a bin wall, the gripper
inside a handle). The draw comes from Meta-World's seeded `np_random`, and the
task's own `reset_model` runs unchanged (including its own redraws, e.g. reach's minimum distance
between object and goal).

Cameras (on request only): `agentview_rgb` is Meta-World's "corner" camera, a fixed view of the
table and the arm from the front left, and `eye_in_hand_rgb` its "gripperPOV" camera, mounted on
the hand between the fingers. "corner" is defined with its up axis pointing down, so its image is
rotated by 180 degrees to come out upright (a rotation, not a flip: left stays left).
"""

from __future__ import annotations

from collections import defaultdict

import numpy as np

from suites import register_suite
from suites.base import (
    AGENTVIEW,
    EYE_IN_HAND,
    SPATIAL_KEYS,
    Observation,
    StepResult,
    Suite,
    TaskEnv,
    is_spatial,
)
from suites.metaworld.instructions import INSTRUCTIONS
from suites.render import MODES, apply_to_model, apply_to_scene, check_render

_STATE_DIM = 39
_ACTION_DIM = 4
# observation key -> (Meta-World camera, whether its image must be turned by 180 degrees)
_CAMERAS = {AGENTVIEW: ("corner", True), EYE_IN_HAND: ("gripperPOV", False)}
_SHADOW_MAP_SIZE = 1024
_TURNED = {"corner", "corner2", "corner3"}  # cameras Meta-World mounts upside down
# render modes (suites/render.py): faithful draws everything (reflections off moved 0.03/255)
WIDEN = 2.0  # the spatial probe's x and y ranges: this many times the task's own, same centre
MIN_WIDENED = 0.01  # m; narrower ranges (Meta-World's +-1 mm jitter) are not widened
PENETRATION = 0.005  # m: how much deeper than in the task's own states a probe state may press
MAX_DRAWS = 100  # widened draws per probe state before the last one is kept


def _env_classes():
    from metaworld.env_dict import ALL_V3_ENVIRONMENTS_GOAL_OBSERVABLE

    return ALL_V3_ENVIRONMENTS_GOAL_OBSERVABLE


def _expert_classes():
    from metaworld.policies import ENV_POLICY_MAP

    return ENV_POLICY_MAP


class MetaWorldEnv(TaskEnv):
    def __init__(self, task: str, cameras: bool, image_size: int, render: str = "faithful"):
        import warnings

        warnings.filterwarnings("ignore", message="Constant\\(s\\) may be too high")
        self.task = task
        self._env = _env_classes()[f"{task}-goal-observable"](seed=0)
        self._expert = _expert_classes()[task]()
        self._obs: np.ndarray | None = None
        self._allowance: dict | None = None  # the spatial probe's, made at its first reset
        self._renderer = None
        self._view = None  # draws recorded states for videos (render_state)
        self.render = MODES[check_render(render)]
        if cameras:
            import mujoco

            model = self._env.model
            # Meta-World's 4096^2 shadow map costs more than the image itself at these sizes
            # (twice the render time on a CPU); 1024^2 gives the same shadows at a few hundred pixels
            model.vis.quality.shadowsize = min(model.vis.quality.shadowsize, _SHADOW_MAP_SIZE)
            apply_to_model(model, self.render)
            self._renderer = mujoco.Renderer(model, image_size, image_size)
            apply_to_scene(self._renderer.scene, self.render)

    def _observation(self, raw: np.ndarray) -> Observation:
        self._obs = raw
        obs = {"state": raw.astype(np.float32)}
        if self._renderer is not None:
            for key, (camera, turn) in _CAMERAS.items():
                self._renderer.update_scene(self._env.data, camera=camera)
                image = self._renderer.render()  # a new array per call
                obs[key] = np.ascontiguousarray(image[::-1, ::-1]) if turn else image
        return obs

    def reset(self, seed: int) -> Observation:
        env = self._env
        env._freeze_rand_vec = False
        env.seeded_rand_vec = True
        if is_spatial(seed):
            return self._observation(self._spatial_reset(int(seed) - SPATIAL_KEYS))
        env.seed(int(seed))
        raw, _ = env.reset()
        return self._observation(raw)

    def _spatial_reset(self, seed: int) -> np.ndarray:
        """The task's own reset with the widened draw, redrawn (up to MAX_DRAWS times) while
        the state presses anything into anything else deeper than the task's own states do."""
        env = self._env
        allowed = self._contact_allowance()
        env.seed(seed)
        env._get_state_rand_vec = self._widened_rand_vec  # the task's reset draws from it
        try:
            for _ in range(MAX_DRAWS):
                raw, _ = env.reset()
                depths = self._contact_depths()
                if all(depth <= allowed[pair] for pair, depth in depths.items()):
                    break
        finally:
            del env._get_state_rand_vec  # back to Meta-World's own draw
        return raw

    def _widened_rand_vec(self) -> np.ndarray:
        """One draw from the widened box outside the original (the module docstring)."""
        env = self._env
        box = env._random_reset_space
        low, high, widened = widened_box(box.low, box.high, env.hand_low, env.hand_high)
        while True:
            vec = env.np_random.uniform(low, high, size=low.size)
            outside = (vec < box.low) | (vec > box.high)
            if outside[widened].any():
                env._last_rand_vec = vec
                return vec

    def _contact_depths(self) -> dict[tuple[int, int], float]:
        """(body, body) -> the deepest penetration between them now, in m."""
        data, model = self._env.data, self._env.model
        out: dict[tuple[int, int], float] = {}
        for contact in data.contact[:data.ncon]:
            a, b = sorted((model.geom_bodyid[contact.geom1], model.geom_bodyid[contact.geom2]))
            out[(a, b)] = max(out.get((a, b), 0.0), -float(contact.dist))
        return out

    def _contact_allowance(self) -> dict[tuple[int, int], float]:
        """How deep each pair of bodies may press into each other in a probe state: as deep as
        in the task's own initial states (seeds 0..9; the hammer rests 28 mm into the table)
        plus PENETRATION; a pair that never touches there, PENETRATION."""
        if self._allowance is None:
            env, deepest = self._env, {}
            for seed in range(10):
                env.seed(seed)
                env.reset()
                for pair, depth in self._contact_depths().items():
                    deepest[pair] = max(deepest.get(pair, 0.0), depth)
            self._allowance = defaultdict(lambda: PENETRATION,
                                          {p: d + PENETRATION for p, d in deepest.items()})
        return self._allowance

    def step(self, action: np.ndarray) -> StepResult:
        action = np.clip(np.asarray(action, dtype=np.float64), -1.0, 1.0)
        raw, _reward, _term, _trunc, info = self._env.step(action)
        return StepResult(self._observation(raw), bool(info["success"]))

    def expert_action(self) -> np.ndarray:
        assert self._obs is not None, "reset() first"
        return np.clip(self._expert.get_action(self._obs), -1.0, 1.0).astype(np.float32)

    def view_state(self) -> np.ndarray:
        from suites.views import mujoco_state

        return mujoco_state(self._env.model, self._env.data)

    def render_state(self, state: np.ndarray, camera: str, size: int) -> np.ndarray:
        from suites.views import MujocoView, check_camera

        camera = check_camera(self._env.model, camera or _CAMERAS[AGENTVIEW][0], "metaworld")
        if self._view is None:
            model = self._env.model
            model.vis.quality.shadowsize = min(model.vis.quality.shadowsize, _SHADOW_MAP_SIZE)
            apply_to_model(model, self.render)
            self._view = MujocoView(model, self._env.data, self.render)
        image = self._view.draw(state, camera, size)
        return np.ascontiguousarray(image[::-1, ::-1]) if camera in _TURNED else image

    def close(self) -> None:
        if self._renderer is not None:
            self._renderer.close()
        if self._view is not None:
            self._view.close()
        self._env.close()


def widened_box(low: np.ndarray, high: np.ndarray, hand_low: np.ndarray, hand_high: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The spatial probe's box for a rand vec of (x, y, z) positions: (low, high, which
    coordinates were widened). Why x and y only: z is a height (on the table, or a goal in the
    air), and a lower one would be inside the table."""
    low, high = np.asarray(low, dtype=np.float64), np.asarray(high, dtype=np.float64)
    horizontal = np.arange(low.size) % 3 < 2
    widened = horizontal & (high - low >= MIN_WIDENED)
    centre, half = (low + high) / 2, WIDEN * (high - low) / 2
    reach_low, reach_high = np.resize(hand_low, low.size), np.resize(hand_high, low.size)
    new_low = np.where(widened, np.maximum(centre - half, np.minimum(reach_low, low)), low)
    new_high = np.where(widened, np.minimum(centre + half, np.maximum(reach_high, high)), high)
    widened &= (new_low < low) | (new_high > high)  # clipping may leave no room outside
    if not widened.any():
        raise ValueError("no position range of this task can be widened within the hand's reach")
    return new_low, new_high, widened


@register_suite("metaworld")
class MetaWorldSuite(Suite):
    video_camera = _CAMERAS[AGENTVIEW][0]
    state_dim = _STATE_DIM
    action_dim = _ACTION_DIM
    max_episode_steps = 500  # Meta-World's own limit; benchmarks usually set less
    simulator_mb = (25.0, 100.0)  # make bench-envs BENCH=mw-paper: 23 MB, 97 with cameras
    spatial_probe_version = f"widen{WIDEN:g}x-1"

    def task_names(self) -> list[str]:
        envs = {name.removesuffix("-goal-observable") for name in _env_classes()}
        return sorted(envs & set(_expert_classes()) & set(INSTRUCTIONS))

    def instruction(self, task: str) -> str:
        return INSTRUCTIONS[self.check_task(task)]

    def make_env(self, task: str, cameras: bool = False, image_size: int = 84,
                 render: str = "faithful") -> TaskEnv:
        return MetaWorldEnv(self.check_task(task), cameras, image_size, render)
