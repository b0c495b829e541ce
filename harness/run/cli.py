"""`python -m harness bench METHOD=sft PROFILE=quick SEED=1 steps_per_task=2000`, `... study
STUDY=paper` and `... lerobot-export`: the commands, and their errors as one line and exit 2."""

from __future__ import annotations

import sys

from harness.common.errors import USER_ERRORS
from harness.run.execute import execute
from harness.run.plan import plan


def bench(args: list[str]) -> int:
    """Demos, then each seed's foundation, then one job per (seed, variant) on the executor."""
    p = plan(args)
    return execute(p, [(seed, v) for seed in p.cfg.seed_list() for v in p.variants],
                   " ".join(args))


def _study(args: list[str]) -> int:
    from harness.run.study import study

    return study(args)


def _lerobot_export(args: list[str]) -> int:
    from harness.run.lerobot_export import main as export_main

    return export_main(args)


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    commands = {"bench": bench, "study": _study, "lerobot-export": _lerobot_export}
    if not argv or argv[0] not in commands:
        print(f"usage: python -m harness {{{','.join(commands)}}} [KEY=VALUE ...]", file=sys.stderr)
        return 2
    try:
        return commands[argv[0]](argv[1:])
    except USER_ERRORS as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted; finished stages are kept and the same command resumes", file=sys.stderr)
        return 130
