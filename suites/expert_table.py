"""Run every task's scripted expert on its evaluation episodes and rewrite a suite's README table.

    python -m suites.bimanual.expert_table [--episodes N] [--tasks a,b] [--no-write]
    python -m suites.libero.expert_table [libero_object ...] [--episodes N] ...

The harness's protocol: the task's evaluation episodes (`Suite.episode_keys`: seeds, or LIBERO's
fixed init states), at most the task's step limit, stopping at the first success. The table sits
between two marker comments (one block per LIBERO suite), so the prose around it is kept.
"""

from __future__ import annotations

import argparse
import re
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from suites import get_suite
from suites.base import run_expert_episode

BEGIN, END = "<!-- expert-table:begin -->", "<!-- expert-table:end -->"


@dataclass
class ExpertResult:
    task: str
    group: str  # the task's family, or "" where a suite has none
    successes: int
    episodes: int
    mean_length: float  # steps to first success (max_episode_steps for a failure)


def markers(block: str = "") -> tuple[str, str]:
    """The comments around a table: BEGIN/END, or per named block (a LIBERO suite)."""
    if not block:
        return BEGIN, END
    return f"<!-- expert-table:{block}:begin -->", f"<!-- expert-table:{block}:end -->"


def run_expert(suite, task: str, episodes: int, group: str = "") -> ExpertResult:
    env = suite.make_env(task)
    limit = suite.step_limit(task, suite.max_episode_steps)
    try:
        runs = [run_expert_episode(env, key, limit)
                for key in suite.episode_keys(task, "eval", episodes)]
    finally:
        env.close()
    return ExpertResult(task, group, sum(r.success for r in runs), episodes,
                        sum(r.steps for r in runs) / len(runs))


def render_table(results: list[ExpertResult], steps_per_s: float) -> str:
    grouped = any(r.group for r in results)
    lines = ["| task |" + (" family |" if grouped else "") + " expert success | mean episode length |",
             "|---|" + ("---|" if grouped else "") + "---|---|"]
    for r in results:
        lines.append(f"| `{r.task}` |" + (f" {r.group} |" if grouped else "")
                     + f" {r.successes}/{r.episodes} ({100 * r.successes / r.episodes:.0f}%) "
                     f"| {r.mean_length:.1f} |")
    total = sum(r.successes for r in results), sum(r.episodes for r in results)
    lines.append(f"\nOverall {total[0]}/{total[1]}; simulation ran at {steps_per_s:.0f} env "
                 "steps/s (expert, resets and env construction included; state observations; "
                 "one process).")
    return "\n".join(lines)


def write_table(table: str, readme: Path, block: str = "") -> None:
    begin, end = markers(block)
    text = readme.read_text()
    pattern = re.compile(re.escape(begin) + ".*?" + re.escape(end), re.DOTALL)
    if not pattern.search(text):
        raise ValueError(f"{readme}: no {begin} ... {end} block to replace")
    readme.write_text(pattern.sub(lambda _m: f"{begin}\n{table}\n{end}", text))


def main(suite_name: str, readme: Path, group_of: Callable[[str], str] = lambda task: "",
         argv=None, tasks: list[str] | None = None, block: str = "", episodes: int = 20) -> None:
    """`tasks` (default: all of the suite's) and `block` (the README block) come from a suite's
    own command (LIBERO: one of its five suites)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=episodes)
    parser.add_argument("--tasks", default="", help="comma-separated subset (default: all)")
    parser.add_argument("--no-write", action="store_true", help="print only")
    args = parser.parse_args(argv)
    suite = get_suite(suite_name)
    tasks = ([suite.check_task(t) for t in args.tasks.split(",") if t] or tasks
             or suite.task_names())
    results, start = [], time.perf_counter()
    for task in tasks:
        results.append(run_expert(suite, task, args.episodes, group_of(task)))
        r = results[-1]
        print(f"{task}: {r.successes}/{r.episodes}, mean length {r.mean_length:.1f}", flush=True)
    steps = sum(r.mean_length * r.episodes for r in results)
    table = render_table(results, steps / (time.perf_counter() - start))
    print(table)
    if not args.no_write:
        write_table(table, readme, block)
        print(f"wrote {readme}")
