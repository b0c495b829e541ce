"""`python -m suites.libero.expert_table [SUITE ...] [--episodes N] [--tasks a,b] [--no-write]`:
the scripted experts' success over LIBERO's fixed init states (50 by default, LIBERO's
protocol), one table per LIBERO suite in this folder's README.md (see `suites/expert_table.py`),
with a row per task that has an expert (`experts/coverage.py`); a suite with none is skipped.
SUITE is libero_spatial, libero_object, libero_goal, libero_10 or libero_90 (default: all five).
"""

from __future__ import annotations

import sys
from pathlib import Path

from suites.expert_table import main as table_main
from suites.libero.experts.coverage import EXPERT_TASKS
from suites.libero.tasks import NUM_INIT_STATES, SUITES, suite_tasks

README = Path(__file__).with_name("README.md")


def main(argv=None) -> None:
    argv = list(sys.argv[1:] if argv is None else argv)
    chosen, rest = [], []
    for i, arg in enumerate(argv):  # positional words not taken by an option are suite names
        if arg.startswith("-") or (i > 0 and argv[i - 1] in ("--episodes", "--tasks")):
            rest.append(arg)
        elif arg in SUITES:
            chosen.append(arg)
        else:
            raise SystemExit(f"unknown LIBERO suite {arg!r}; valid: {', '.join(SUITES)}")
    for suite in chosen or SUITES:
        covered = [task for task in suite_tasks(suite) if task in EXPERT_TASKS]
        print(f"== {suite}: {len(covered)} of {len(suite_tasks(suite))} tasks have an expert",
              flush=True)
        if covered or "--tasks" in rest:
            table_main("libero", README, argv=rest, tasks=covered, block=suite,
                       episodes=NUM_INIT_STATES)


if __name__ == "__main__":
    main()
