"""Run every expert on its evaluation episodes and rewrite the table in this folder's README.md.

    python -m suites.bimanual.expert_table [--episodes N] [--tasks a,b]

An episode lasts at most `max_episode_steps` and stops at the first success, as in the harness.
"""

from __future__ import annotations

import argparse
import time
from dataclasses import dataclass
from pathlib import Path

from suites import get_suite
from suites.base import episode_seeds

README = Path(__file__).with_name("README.md")
BEGIN, END = "<!-- expert-table:begin -->", "<!-- expert-table:end -->"


@dataclass(frozen=True)
class Row:
    task: str
    episodes: int
    successes: int
    mean_length: float
    steps_per_s: float


def run_expert(suite, task: str, episodes: int) -> Row:
    env = suite.make_env(task)
    successes, lengths, start = 0, [], time.perf_counter()
    for seed in episode_seeds(suite.name, task, "eval", episodes):
        env.reset(seed)
        for t in range(1, suite.max_episode_steps + 1):  # noqa: B007 - t is the length
            if env.step(env.expert_action()).success:
                successes += 1
                break
        lengths.append(t)
    env.close()
    return Row(task, episodes, successes, sum(lengths) / len(lengths), sum(lengths) / (time.perf_counter() - start))


def table(rows: list[Row]) -> str:
    lines = ["| task | expert success | mean episode length (steps) | env steps/s |", "|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r.task} | {r.successes}/{r.episodes} ({100 * r.successes / r.episodes:.0f}%) "
                     f"| {r.mean_length:.0f} | {r.steps_per_s:.0f} |")
    return "\n".join(lines)


def rewrite_readme(text: str) -> None:
    readme = README.read_text()
    head, rest = readme.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    README.write_text(f"{head}{BEGIN}\n{text}\n{END}{tail}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--tasks", default="", help="comma-separated subset (default: all)")
    args = parser.parse_args()
    suite = get_suite("bimanual")
    tasks = args.tasks.split(",") if args.tasks else suite.task_names()
    rows = []
    for task in tasks:
        rows.append(run_expert(suite, suite.check_task(task), args.episodes))
        r = rows[-1]
        print(f"{task}: {r.successes}/{r.episodes}, mean length {r.mean_length:.0f}, {r.steps_per_s:.0f} steps/s",
              flush=True)
    text = table(rows) + f"\n\n{args.episodes} evaluation episodes per task (`episode_seeds(\"bimanual\", task, " \
        f"\"eval\", {args.episodes})`), at most {suite.max_episode_steps} steps, stopping at the first success."
    rewrite_readme(text)
    print(text)


if __name__ == "__main__":
    main()
