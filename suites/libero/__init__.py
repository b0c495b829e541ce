"""Real LIBERO (registered as "libero"): its 130 tasks in five suites (libero_spatial,
libero_object, libero_goal, libero_10, libero_90), its fixed init states, BDDL success and
per-suite step limits, on rpent-libero (LIBERO ported to robosuite 1.5). See README.md.
"""

from __future__ import annotations

import json

from suites import register_suite
from suites.base import SPATIAL_KEYS, Suite, TaskEnv, episode_seeds
from suites.libero.install import ensure_installed
from suites.libero.tasks import STATE_DIM, LiberoTask, all_tasks, sets_joints_at_reset

ACTION_DIM = 7


@register_suite("libero")
class LiberoSuite(Suite):
    state_dim = STATE_DIM
    action_dim = ACTION_DIM
    max_episode_steps = 520  # the longest per-suite limit (libero_10); max_steps(task) is the rule
    spatial_probe_version = "offset3-6cm-1"
    # 2: an init state's episode resets without the arm's initialization noise, as LIBERO's
    # evaluation does (the OSC controller's nullspace target is LIBERO's home pose; env.py)
    evaluation_version = "2"
    simulator_mb = (180.0, 325.0)  # make bench-envs BENCH=libero-paper: 179 MB, 322 with cameras
    video_camera = "agentview"

    def __init__(self):
        super().__init__()
        ensure_installed()  # one line saying how to repair, before any long work

    def version(self, task: str) -> str:
        """2: resets place fixtures by the episode's key, and the experts take objects out from
        under an overhang. 3: fresh scenes are drawn as LIBERO drew its init states: the arm with
        its joint noise (env.py's ROBOT_INIT_NOISE) and objects on fixtures placed in a freshly
        loaded model. 4, the 28 tasks that open a drawer or turn on a stove at their reset: a
        key's fresh scene no longer depends on how many scenes the env loaded before it (LIBERO
        added a draw at every reload; env.py's `_as_loaded`); the other tasks' scenes did not
        change. Demo files made before a change are regenerated, not reused."""
        return "4" if sets_joints_at_reset(task) else "3"

    def task_names(self) -> list[str]:
        return list(all_tasks())

    def task(self, name: str) -> LiberoTask:
        return all_tasks()[self.check_task(name)]

    def instruction(self, task: str) -> str:
        return self.task(task).instruction

    def make_env(self, task: str, cameras: bool = False, image_size: int = 128,
                 render: str = "faithful") -> TaskEnv:
        from suites.libero.env import LiberoTaskEnv

        return LiberoTaskEnv(self.task(task), cameras, image_size, render=render)

    def episode_keys(self, task: str, split: str, n: int) -> list[int]:
        """Evaluation episode i: LIBERO's init state i mod 50. Spatial episode i: init state
        i mod 50 with its objects moved by a seeded offset (the key's low bits hold the index,
        the rest seeds the offsets). Demos and held-out demos: fresh scenes from LIBERO's
        placement sampler, seeded per episode (env.py)."""
        from suites.libero.env import FRESH_PLACEMENT, INIT_INDEX_BITS
        from suites.libero.tasks import NUM_INIT_STATES

        if split == "eval":
            return list(range(n))
        if split == "spatial":
            seeds = episode_seeds(self.name, task, split, n)
            index_bits = (1 << INIT_INDEX_BITS) - 1
            return [SPATIAL_KEYS | (seed & ~index_bits) | (i % NUM_INIT_STATES)
                    for i, seed in enumerate(seeds)]
        return [FRESH_PLACEMENT | seed for seed in episode_seeds(self.name, task, split, n)]

    def max_steps(self, task: str) -> int:
        return self.task(task).max_steps

    def demo_file_attrs(self, task: str) -> dict[str, str]:
        """What LIBERO's create_dataset.py puts on `data`, so our files read like LIBERO's."""
        from libero.libero.envs.bddl_utils import get_problem_info

        t = self.task(task)
        with open(t.bddl_file) as f:
            bddl = f.read()
        problem_info = get_problem_info(t.bddl_file)  # as LIBERO writes it (BDDL's wording)
        env_args = {"type": 1, "env_name": "ControlEnv",
                    "env_kwargs": {"bddl_file_name": t.bddl_file, "controller": "OSC_POSE",
                                   "control_freq": 20}}
        return {"problem_info": json.dumps(problem_info), "env_args": json.dumps(env_args),
                "bddl_file_name": t.bddl_file, "bddl_file_content": bddl,
                "macros_image_convention": "opengl", "env_name": "ControlEnv"}
