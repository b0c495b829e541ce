"""Camera views both ways (`make bench-envs` with cameras): each suite's milliseconds a view at
`render=faithful` and `render=fast`, and how far fast's images are from faithful's.

Both modes' envs start from the same episode keys and take the same seeded random actions:
rendering never touches physics (the fast meshes are visual-only), so the two see the same
scene at every frame (checked: their states are compared). Each frame is drawn by both envs'
own renderers (as their observations are), one after the other in the same process, so the
shared machine's noise falls on both. A view is one camera's image at `image_size`.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np

from suites import get_suite
from suites.render import RENDER_MODES

SUITES = ("libero", "metaworld", "bimanual")
RESET_EVERY = 5  # frames (of every camera) an episode before the next episode's scene


@dataclass
class ViewFigures:
    suite: str
    frames: int  # frames compared (each camera's image counts once)
    ms: dict[str, float]  # mode -> median milliseconds a view
    mean_abs: np.ndarray  # [3] mean absolute difference per channel (of 255)
    max_abs: np.ndarray  # [3] max absolute difference per channel
    psnr: float  # dB over every compared pixel


def views(env) -> list:
    """One callable per camera that draws the env's current state as its observations do."""
    robosuite_env = getattr(getattr(env, "env", None), "env", None) or getattr(env, "_env", None)
    renderer = getattr(env, "_renderer", None)
    if renderer is not None:  # Meta-World: mujoco.Renderer on its own model and data
        from suites.metaworld import _CAMERAS

        def draw(camera):
            def one():
                renderer.update_scene(env._env.data, camera=camera)
                return renderer.render()
            return one
        return [draw(camera) for camera, _ in _CAMERAS.values()]
    sim = robosuite_env.sim  # each env draws in its own GL context (suites/render.py)
    size = robosuite_env.camera_heights[0]
    return [lambda camera=camera: sim.render(width=size, height=size, camera_name=camera)
            for camera in robosuite_env.camera_names]


def measure_views(suite_name: str, tasks: list[str], frames: int = 100, image_size: int = 128,
                  steps_between: int = 3, seed: int = 0) -> ViewFigures:
    """`frames` frames spread over `tasks` (a few episodes each, `steps_between` random steps
    apart), every camera drawn by a faithful and a fast env of the same task."""
    suite = get_suite(suite_name)
    rng = np.random.default_rng(seed)
    times = {mode: [] for mode in RENDER_MODES}
    diffs, n = [], 0
    per_task = math.ceil(frames / len(tasks))
    for task in tasks:
        envs = {mode: suite.make_env(task, True, image_size, render=mode) for mode in RENDER_MODES}
        try:
            draws = {mode: views(env) for mode, env in envs.items()}
            cameras = len(draws["faithful"])
            keys = suite.episode_keys(task, "eval", math.ceil(per_task / cameras / RESET_EVERY))
            for i in range(math.ceil(per_task / cameras)):
                if i % RESET_EVERY == 0:  # another episode: another scene
                    for env in envs.values():
                        env.reset(keys[(i // RESET_EVERY) % len(keys)])
                action = rng.uniform(-1, 1, suite.action_dim)
                for _ in range(steps_between):
                    results = [env.step(action) for env in envs.values()]
                states = [r.obs["state"] for r in results]
                if not np.array_equal(*states):
                    raise AssertionError(f"{suite_name} {task}: the render modes' states differ")
                for c in range(cameras):
                    images = {}
                    for mode in RENDER_MODES:
                        start = time.perf_counter()
                        images[mode] = draws[mode][c]()
                        times[mode].append(time.perf_counter() - start)
                    diffs.append(images["fast"].astype(np.int16) - images["faithful"])
                    n += 1
        finally:
            for env in envs.values():
                env.close()
    d = np.abs(np.stack(diffs)).reshape(-1, 3)
    mse = float(np.mean(d.astype(np.float64) ** 2))
    return ViewFigures(suite_name, n, {m: 1000 * float(np.median(t)) for m, t in times.items()},
                       d.mean(axis=0), d.max(axis=0),
                       math.inf if mse == 0 else 10 * math.log10(255 ** 2 / mse))


def print_views(rows: list[ViewFigures], image_size: int) -> None:
    print(f"\ncamera views at {image_size} px, render=faithful against render=fast (median ms a "
          "view; fast's image difference from faithful's over the frames)")
    print("| suite | frames | faithful ms | fast ms | speed-up | mean abs diff (R, G, B) "
          "| max abs diff (R, G, B) | PSNR dB |")
    print("|---|---|---|---|---|---|---|---|")
    for f in rows:
        mean = ", ".join(f"{x:.2f}" for x in f.mean_abs)
        peak = ", ".join(str(int(x)) for x in f.max_abs)
        print(f"| {f.suite} | {f.frames} | {f.ms['faithful']:.1f} | {f.ms['fast']:.1f} | "
              f"{f.ms['faithful'] / f.ms['fast']:.1f}x | {mean} | {peak} | {f.psnr:.1f} |")


def bench_views(frames: int = 100, image_size: int = 128, n_tasks: int = 5) -> None:
    """Each suite's figures over `n_tasks` tasks spread over its task list."""
    rows = []
    for name in SUITES:
        tasks = get_suite(name).task_names()
        rows.append(measure_views(name, tasks[::max(1, len(tasks) // n_tasks)][:n_tasks], frames,
                                  image_size))
    print_views(rows, image_size)
