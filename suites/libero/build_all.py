"""`python -m suites.libero.build_all [SUITE ...] [--steps N]`: build every LIBERO task's env,
start it from init state 0 (with the settle), step it N times with random actions, and check
its BDDL goal; one line per task, then a summary. Exits non-zero if any task fails."""

from __future__ import annotations

import argparse
import sys
import time

import numpy as np

from suites import get_suite
from suites.libero.tasks import STATE_DIM, SUITES, suite_tasks


def check_task(suite, task: str, steps: int) -> tuple[float, int]:
    """(seconds to build, object count); raises on any failure."""
    start = time.perf_counter()
    env = suite.make_env(task)
    built = time.perf_counter() - start
    try:
        obs = env.reset(0)
        rng = np.random.default_rng(0)
        for _ in range(steps):
            result = env.step(rng.uniform(-1, 1, 7))
            if result.obs["state"].shape != (STATE_DIM,) or not np.isfinite(result.obs["state"]).all():
                raise RuntimeError("bad state")
        assert obs["state"].shape == (STATE_DIM,) and isinstance(result.success, bool)
        return built, len(env.objects)
    finally:
        env.close()


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("suites", nargs="*", help=f"any of {', '.join(SUITES)} (default: all)")
    parser.add_argument("--steps", type=int, default=20)
    args = parser.parse_args(argv)
    bad = [s for s in args.suites if s not in SUITES]
    if bad:
        parser.error(f"unknown LIBERO suite {bad[0]!r}; valid: {', '.join(SUITES)}")
    suite = get_suite("libero")
    failed, start = [], time.perf_counter()
    tasks = [t for s in (args.suites or SUITES) for t in suite_tasks(s)]
    for i, task in enumerate(tasks, 1):
        try:
            built, objects = check_task(suite, task, args.steps)
            print(f"[{i}/{len(tasks)}] ok   {task} (built in {built:.1f} s, {objects} objects)",
                  flush=True)
        except Exception as err:  # noqa: BLE001 - report every task, then fail
            failed.append(task)
            print(f"[{i}/{len(tasks)}] FAIL {task}: {type(err).__name__}: {err}", flush=True)
    print(f"{len(tasks) - len(failed)}/{len(tasks)} LIBERO tasks build, reset to an init state, "
          f"step and report success ({time.perf_counter() - start:.0f} s)")
    return 1 if failed else 0


if __name__ == "__main__":
    sys.exit(main())
