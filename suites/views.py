"""A recorded MuJoCo state drawn again from a named camera: the suites' side of rollout videos.

An evaluation records `TaskEnv.view_state()` every step (a copy of a few hundred floats) and the
frames are drawn after it, on an env of their own: the episode never waits for a renderer, and
a run without videos pays nothing. Two kinds of scene: our own MuJoCo models (Meta-World), drawn
with `mujoco.Renderer` as their observations are, and robosuite's (LIBERO, bimanual), drawn with
robosuite's own offscreen renderer, as theirs are.
"""

from __future__ import annotations

import mujoco
import numpy as np

from suites.base import SuiteError
from suites.render import RenderSettings, apply_to_scene

STATE = mujoco.mjtState.mjSTATE_INTEGRATION  # qpos, qvel, act, mocap, time, ctrl, warmstart


def camera_names(model) -> list[str]:
    return [mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_CAMERA, i) for i in range(model.ncam)]


def check_camera(model, camera: str, suite: str) -> str:
    """`camera` if the model has it; else a one-line error naming the valid cameras."""
    valid = camera_names(model)
    if camera not in valid:
        raise SuiteError(f"unknown video_camera {camera!r} for suite {suite}; valid: "
                         f"{', '.join(valid)}")
    return camera


def mujoco_state(model, data) -> np.ndarray:
    """The whole integration state (mj_getState), mocap bodies included."""
    out = np.empty(mujoco.mj_stateSize(model, STATE))
    mujoco.mj_getState(model, data, out, STATE)
    return out


class MujocoView:
    """Draws states of one MuJoCo model with `mujoco.Renderer`, one renderer per size."""

    def __init__(self, model, data, settings: RenderSettings | None = None):
        self.model, self.data, self.settings = model, data, settings
        self._renderers: dict[int, mujoco.Renderer] = {}

    def draw(self, state: np.ndarray, camera: str, size: int) -> np.ndarray:
        mujoco.mj_setState(self.model, self.data, np.asarray(state, dtype=np.float64), STATE)
        mujoco.mj_forward(self.model, self.data)
        if size not in self._renderers:
            self._renderers[size] = mujoco.Renderer(self.model, size, size)
            if self.settings is not None:  # the env's render mode (suites/render.py)
                apply_to_scene(self._renderers[size].scene, self.settings)
        renderer = self._renderers[size]
        renderer.update_scene(self.data, camera=camera)
        return renderer.render()

    def close(self) -> None:
        for renderer in self._renderers.values():
            renderer.close()
        self._renderers.clear()


def robosuite_state(sim, bodies: bool = False) -> np.ndarray:
    """robosuite's flattened state (time, qpos, qvel: LIBERO's `states` format); with `bodies`,
    every body's pose in the model after it (LIBERO writes its fixtures' there at each reset)."""
    state = np.asarray(sim.get_state().flatten())
    if not bodies:
        return state
    model = sim.model._model
    return np.concatenate([state, model.body_pos.ravel(), model.body_quat.ravel()])


def robosuite_draw(sim, state: np.ndarray, camera: str, size: int, suite: str) -> np.ndarray:
    """`state` from `camera` with robosuite's offscreen renderer (the env must have been built
    with cameras on), upright."""
    model = sim.model._model
    check_camera(model, camera, suite)
    state, n = np.asarray(state, dtype=np.float64), 1 + model.nq + model.nv
    if len(state) > n:  # the bodies' poses too (robosuite_state's `bodies`)
        model.body_pos[:] = state[n:n + 3 * model.nbody].reshape(-1, 3)
        model.body_quat[:] = state[n + 3 * model.nbody:].reshape(-1, 4)
    sim.set_state_from_flattened(state[:n])
    sim.forward()
    # robosuite renders into whichever GL context is current: another env's renderer in this
    # process (a Meta-World view, another task's env) may have made its own current
    sim._render_context_offscreen.gl_ctx.make_current()
    image = sim.render(width=size, height=size, camera_name=camera)
    return np.ascontiguousarray(image[::-1])
