"""What our own robosuite scenes (the bimanual suite) build on: robosuite's default table, the
units of its OSC_POSE delta actions, the env settings, per-episode seeding and image orientation.
Real LIBERO (suites/libero) brings its own scenes and env class."""

from __future__ import annotations

import numpy as np

import suites.robosuite_quiet  # noqa: F401  (before any robosuite import)

TABLE_TOP = 0.8  # m: robosuite's default table offset
TABLE_SIZE = (0.8, 0.8, 0.05)
OPEN, CLOSED = -1.0, 1.0  # gripper commands
POS_SCALE = 0.05  # metres per unit action (robosuite's OSC_POSE output_max)
ROT_SCALE = 0.5  # radians per unit action


def env_kwargs(cameras: bool, image_size: int, camera_names: str | list[str]) -> dict:
    """robosuite env keyword arguments: 20 Hz control, episodes ended by the
    harness (never by robosuite), reset in place, cameras only when images are asked for."""
    return dict(
        control_freq=20,
        horizon=10**9,
        ignore_done=True,
        hard_reset=False,  # reset in place: reloading the model costs ~2 s per episode
        has_renderer=False,
        has_offscreen_renderer=cameras,
        use_camera_obs=cameras,
        camera_names=camera_names,
        camera_heights=image_size,
        camera_widths=image_size,
    )


def seed_env(env, seed: int) -> None:
    """Point every RNG robosuite draws from at reset (robot joint noise, object samplers) to
    `seed`, so an episode is a function of the seed alone."""
    rng = np.random.default_rng(seed)
    env.rng = rng
    sampler = getattr(env, "placement_initializer", None)
    stack = [sampler] if sampler is not None else []
    while stack:
        s = stack.pop()
        s.rng = rng
        stack.extend(getattr(s, "samplers", {}).values())


def upright(image: np.ndarray) -> np.ndarray:
    """robosuite renders OpenGL-style, bottom row first: flip rows for an upright image."""
    return np.ascontiguousarray(image[::-1])
