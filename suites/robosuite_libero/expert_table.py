"""Run every task's scripted expert on its evaluation episodes and rewrite the README table.

    python -m suites.robosuite_libero.expert_table [--episodes N] [--tasks a,b] [--no-write]

The table sits between two marker comments in README.md, so the prose around it is kept.
"""

from __future__ import annotations

import argparse
import re
import time
from dataclasses import dataclass
from pathlib import Path

from suites import get_suite
from suites.base import episode_seeds

README = Path(__file__).with_name("README.md")
BEGIN, END = "<!-- expert-table:begin -->", "<!-- expert-table:end -->"


@dataclass
class ExpertResult:
    task: str
    family: str
    successes: int
    episodes: int
    mean_length: float  # steps to first success (max_episode_steps for a failure)


def run_expert(suite, task: str, episodes: int) -> ExpertResult:
    """The harness's protocol: eval seeds, at most max_episode_steps, stop at first success."""
    from suites.robosuite_libero.tasks import TASKS

    env = suite.make_env(task)
    successes, lengths = 0, []
    try:
        for seed in episode_seeds(suite.name, task, "eval", episodes):
            env.reset(seed)
            steps = suite.max_episode_steps
            for t in range(suite.max_episode_steps):
                if env.step(env.expert_action()).success:
                    successes, steps = successes + 1, t + 1
                    break
            lengths.append(steps)
    finally:
        env.close()
    return ExpertResult(task, TASKS[task].family, successes, episodes, sum(lengths) / len(lengths))


def render_table(results: list[ExpertResult], steps_per_s: float) -> str:
    lines = [
        "| task | family | expert success | mean episode length |",
        "|---|---|---|---|",
    ]
    for r in results:
        lines.append(f"| `{r.task}` | {r.family} | {r.successes}/{r.episodes} "
                     f"({100 * r.successes / r.episodes:.0f}%) | {r.mean_length:.1f} |")
    total = sum(r.successes for r in results), sum(r.episodes for r in results)
    lines.append(f"\nOverall {total[0]}/{total[1]}; simulation ran at {steps_per_s:.0f} env "
                 "steps/s (expert, resets and env construction included; state observations; one process).")
    return "\n".join(lines)


def write_table(table: str, readme: Path = README) -> None:
    text = readme.read_text()
    pattern = re.compile(re.escape(BEGIN) + ".*?" + re.escape(END), re.DOTALL)
    if not pattern.search(text):
        raise ValueError(f"{readme}: no {BEGIN} ... {END} block to replace")
    readme.write_text(pattern.sub(lambda _m: f"{BEGIN}\n{table}\n{END}", text))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--tasks", default="", help="comma-separated subset (default: all)")
    parser.add_argument("--no-write", action="store_true", help="print only")
    args = parser.parse_args(argv)
    suite = get_suite("libero_rs")
    tasks = [suite.check_task(t) for t in args.tasks.split(",") if t] or suite.task_names()
    results, start = [], time.perf_counter()
    for task in tasks:
        results.append(run_expert(suite, task, args.episodes))
        r = results[-1]
        print(f"{task}: {r.successes}/{r.episodes}, mean length {r.mean_length:.1f}", flush=True)
    steps = sum(r.mean_length * r.episodes for r in results)
    table = render_table(results, steps / (time.perf_counter() - start))
    print(table)
    if not args.no_write:
        write_table(table)
        print(f"wrote {README}")


if __name__ == "__main__":
    main()
