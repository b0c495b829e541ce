"""`python -m suites.robosuite_libero.expert_table [--episodes N] [--tasks a,b] [--no-write]`:
the experts' success table in this folder's README.md (see `suites/expert_table.py`)."""

from __future__ import annotations

from pathlib import Path

from suites.expert_table import BEGIN, END, ExpertResult, render_table, write_table  # noqa: F401
from suites.expert_table import main as _main

README = Path(__file__).with_name("README.md")


def _family(task: str) -> str:
    from suites.robosuite_libero.tasks import TASKS

    return TASKS[task].family


def main(argv=None) -> None:
    _main("libero_rs", README, _family, argv)


if __name__ == "__main__":
    main()
