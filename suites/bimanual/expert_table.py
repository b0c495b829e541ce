"""`python -m suites.bimanual.expert_table [--episodes N] [--tasks a,b] [--no-write]`: the
experts' success table in this folder's README.md (see `suites/expert_table.py`)."""

from __future__ import annotations

from pathlib import Path

from suites.expert_table import main as _main

README = Path(__file__).with_name("README.md")


def main(argv=None) -> None:
    _main("bimanual", README, argv=argv)


if __name__ == "__main__":
    main()
