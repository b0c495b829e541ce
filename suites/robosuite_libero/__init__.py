"""LIBERO-style tasks on robosuite 1.5 (registered as "libero_rs"): a Franka Panda at a table,
OSC_POSE delta control at 20 Hz, 7-d actions, language instructions, 15 tasks in three families.

LIBERO itself needs its own install; this is its closest stand-in built only from robosuite's
arena and object models. See README.md for the task table, state layout and expert success.
"""

from __future__ import annotations

import suites.robosuite_quiet  # noqa: F401  (before any robosuite import)
from suites import register_suite
from suites.base import TaskEnv, TaskTableSuite
from suites.robosuite_libero.tasks import STATE_DIM, TASKS

ACTION_DIM = 7


@register_suite("libero_rs")
class LiberoRSSuite(TaskTableSuite):
    state_dim = STATE_DIM
    action_dim = ACTION_DIM
    max_episode_steps = 300

    def tasks(self) -> dict:
        return TASKS

    def make_env(self, task: str, cameras: bool = False, image_size: int = 84) -> TaskEnv:
        from suites.robosuite_libero.env import LiberoRSEnv

        return LiberoRSEnv(TASKS[self.check_task(task)], cameras, image_size)
