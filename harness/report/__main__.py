"""`python -m harness.report [EXPERIMENT=mw-quick] [results_dir=results] [log_run=1] [open=1]`.

BENCH= and PROFILE= name the experiment the way `make bench` does, so the Makefile can pass the
same variables to both.
"""

from __future__ import annotations

import sys
import webbrowser

from harness.common.errors import RetainError
from harness.config.benchmark import coerce, experiment_name, parse_overrides, pop_bench_and_profile
from harness.report.build import ReportSettings, build_report
from harness.report.page import PAGE

KEYS = ("EXPERIMENT", "BENCH", "PROFILE", "results_dir", "log_run", "open")


def settings_from(args: list[str]) -> ReportSettings:
    given = parse_overrides(args)
    unknown = sorted(set(given) - set(KEYS))
    if unknown:
        raise RetainError(f"unknown report setting {unknown[0]!r}; valid: {', '.join(KEYS)}")
    bench, profile = pop_bench_and_profile(dict(given))
    experiment = given.get("EXPERIMENT") or experiment_name(bench, profile)  # as `make bench` names it
    return ReportSettings(experiment=experiment,
                          results_dir=given.get("results_dir") or "results",
                          log_run=coerce("log_run", given.get("log_run", "1"), bool))


def main(argv: list[str] | None = None) -> int:
    try:
        args = list(sys.argv[1:] if argv is None else argv)
        settings = settings_from(args)
        show = coerce("open", parse_overrides(args).get("open", "0"), bool)
        files = build_report(settings)
    except RetainError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"[retain] report for {settings.experiment}: {len(files)} files in {settings.out_dir}/")
    print(f"  table: {settings.out_dir / 'summary.md'}")
    page = (settings.out_dir / PAGE).resolve()
    print(f"  page: {page}")
    if show:
        webbrowser.open(page.as_uri())
    return 0


if __name__ == "__main__":
    sys.exit(main())
