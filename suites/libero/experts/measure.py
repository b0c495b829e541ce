"""Per-task success of the scripted experts on real LIBERO, from the fixed init states.

    python -m suites.libero.experts.measure libero_object [n_states] [--tasks 0,3]

One process, one env at a time; episode i starts from init state i, LIBERO's step limits.
It runs the goal-driven expert on any task, covered or not: this is how coverage is decided.
"""

from __future__ import annotations

import argparse
import time

from suites.libero.experts.expert import GoalExpert
from suites.libero.experts.libero_env import (
    STEP_LIMITS,
    SUITES,
    make_env,
    start_episode,
    suite_tasks,
)


def run_episode(env, task, state: int, limit: int) -> tuple[bool, int]:
    obs = start_episode(env, task, state)
    expert = GoalExpert(env, [list(g) for g in env.env.parsed_problem["goal_state"]])
    for step in range(1, limit + 1):
        obs, _, _, _ = env.step(expert.act(obs))
        if env.check_success():
            return True, step
    return False, limit


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("suite", choices=SUITES)
    parser.add_argument("n_states", type=int, nargs="?", default=50)
    parser.add_argument("--tasks", default="", help="comma-separated task indices (default all)")
    parser.add_argument("--first-state", type=int, default=0)
    args = parser.parse_args(argv)
    tasks = suite_tasks(args.suite)
    if args.tasks:
        tasks = [tasks[int(i)] for i in args.tasks.split(",")]
    limit = STEP_LIMITS[args.suite]
    print("| task | success | mean steps |\n|---|---|---|", flush=True)
    start, total = time.time(), [0, 0]
    for task in tasks:
        env = make_env(task)
        try:
            runs = [run_episode(env, task, s, limit)
                    for s in range(args.first_state, args.first_state + args.n_states)]
        finally:
            env.close()
        wins = sum(ok for ok, _ in runs)
        total[0] += wins
        total[1] += len(runs)
        print(f"| `{task.name}` | {wins}/{len(runs)} | "
              f"{sum(n for _, n in runs) / len(runs):.0f} |", flush=True)
    print(f"\n{args.suite}: {total[0]}/{total[1]} episodes solved; "
          f"{time.time() - start:.0f} s", flush=True)


if __name__ == "__main__":
    main()
