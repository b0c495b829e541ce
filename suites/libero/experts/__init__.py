"""Scripted experts for real LIBERO tasks, driven by each task's BDDL goal and privileged state.

    from suites.libero.experts import make_expert
    expert = make_expert(task_name, env)  # after reset, set_init_state and the no-op settle
    action = expert.act(raw_obs)          # (7,) in [-1, 1]: OSC_POSE delta + gripper

`env` is LIBERO's `OffScreenRenderEnv` (or the problem env inside it). Covered tasks are the
ones in `coverage.EXPERT_TASKS`, each measured by `python -m suites.libero.expert_table` (see coverage.py).
"""

from __future__ import annotations

from suites.libero.experts.coverage import EXPERT_TASKS
from suites.libero.experts.expert import GoalExpert


def make_expert(task_name: str, env) -> GoalExpert:
    if task_name not in EXPERT_TASKS:
        raise KeyError(f"no scripted expert for LIBERO task {task_name!r}; covered: "
                       f"{len(EXPERT_TASKS)} tasks listed in suites.libero.experts.coverage")
    problem = env.env if hasattr(env, "env") and hasattr(env.env, "parsed_problem") else env
    return GoalExpert(env, [list(g) for g in problem.parsed_problem["goal_state"]])


__all__ = ["EXPERT_TASKS", "GoalExpert", "make_expert"]
