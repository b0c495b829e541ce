"""Group runs into table rows: one row per method setting, its seeds as the samples.

Why a row is more than a method name: averaging runs made with different settings (two SFT
learning rates, two ConSFT kappas) would hide exactly what a sweep measures. A run tagged
`sweep_point` ("kappa=0.1") gets the row "consft[kappa=0.1]"; untagged runs of one method whose
settings differ get the differing settings in their label ("sft[lr=0.001]"). ConSFT runs made
before Retain implemented the paper's objective (issue 36) are labelled as that reading
("consft (abstract-only reading)"), so they are never taken for the paper's method.
"""

from __future__ import annotations

import re
from dataclasses import dataclass

from harness.config.benchmark import NOT_IN_RUN_KEY, QUIET_DEFAULTS, run_label, short_value
from harness.report.runs import RunRecord

# config fields that do not change what a run measures (the run key's exclusions in
# harness.config.benchmark: where a run is written, how its rollouts are split), or that name the method
# and seed themselves
NOT_SETTINGS = set(NOT_IN_RUN_KEY) | {"method_params", "torch_threads"}
ABSTRACT_ONLY = " (abstract-only reading)"


def abstract_only(run: RunRecord) -> bool:
    """A consft run of Retain's reading of the paper's abstract alone (the `clip` variant with an
    l_ref `reference`, and its dft/ratio variants at a temperature kappa * l_ref), not the
    paper's objective. Every consft run logs all of its config as `method.*` params, and the
    paper's (every variant) has `tau_start`, which the earlier reading never had."""
    return run.method == "consft" and "method.tau_start" not in run.params


@dataclass(frozen=True)
class Row:
    """The runs of one method setting, one per seed (the newest when a seed was run twice)."""

    label: str
    method: str
    sweep_point: str
    runs: list[RunRecord]  # sorted by seed
    missing_seeds: list[int]  # seeds other rows have and this one lacks

    @property
    def abstract_only(self) -> bool:
        """ConSFT as Retain read it from the paper's abstract, not as the paper defines it."""
        return abstract_only(self.runs[0])

    @property
    def seeds(self) -> list[int]:
        return [r.seed for r in self.runs]

    @property
    def lr(self) -> float | None:
        value = self.runs[0].params.get("config.lr")
        return float(value) if value is not None else None

    @property
    def needs(self) -> str:
        """What the method needs beyond the current task's data (the newest run's `needs` tag):
        "past data", "reference copy", "task identity at evaluation", "none"; "not logged" for
        runs from before the tag existed."""
        return next((r.needs for r in reversed(self.runs) if r.needs), "not logged")

    def seeds_text(self) -> str:
        """"3" when complete, else e.g. "2/3: missing seed 2"."""
        n, total = len(self.runs), len(self.runs) + len(self.missing_seeds)
        if not self.missing_seeds:
            return str(n)
        word = "seed" if len(self.missing_seeds) == 1 else "seeds"
        return f"{n}/{total}: missing {word} {', '.join(map(str, self.missing_seeds))}"


def settings(run: RunRecord) -> dict[str, str]:
    """The params that define what a run measures: benchmark settings and method hyperparameters."""
    out = {}
    for key, value in run.params.items():
        if key.startswith("config.") and key.removeprefix("config.") not in NOT_SETTINGS:
            out[key.removeprefix("config.")] = value
        elif key.startswith("method."):
            out[key.removeprefix("method.")] = value
    for key, default in QUIET_DEFAULTS.items():  # logged at its default, or from before it existed
        if out.get(key, str(default)) == str(default):
            out.pop(key, None)
    return out


def label_of(run: RunRecord, varying: list[str]) -> str:
    """The method (or the run name it was given), the sweep point, then the settings that tell
    this run from others of its method and point; " (abstract-only reading)" after an earlier
    reading of ConSFT."""
    s = settings(run)
    extra = ",".join(f"{k}={short_value(s.get(k, QUIET_DEFAULTS.get(k, '-')))}" for k in varying)
    name = s.get("label") or run.method  # a method's own run name (METHOD=checkpoints label=)
    label = run_label(name, " ".join(part for part in (run.sweep_point, extra) if part))
    return label + (ABSTRACT_ONLY if abstract_only(run) else "")


def build_rows(runs: list[RunRecord]) -> tuple[list[Row], int]:
    """Rows (SFT first, then by label) and the number of older duplicate runs left out."""
    varying = _varying_settings(runs)
    by_label: dict[str, dict[int, RunRecord]] = {}
    superseded = 0
    for run in sorted(runs, key=lambda r: (r.start_time, r.run_id)):  # newest last: it wins
        label = label_of(run, varying.get(_group(run), []))
        seeds = by_label.setdefault(label, {})
        superseded += run.seed in seeds
        seeds[run.seed] = run
    all_seeds = sorted({seed for seeds in by_label.values() for seed in seeds})
    rows = []
    for label, seeds in by_label.items():
        first = next(iter(seeds.values()))
        rows.append(Row(label=label, method=first.method, sweep_point=first.sweep_point,
                        runs=[seeds[s] for s in sorted(seeds)],
                        missing_seeds=[s for s in all_seeds if s not in seeds]))
    rows.sort(key=lambda r: (r.method != "sft", r.method, _natural(r.label)))
    return rows, superseded


def _group(run: RunRecord) -> tuple[str, str, bool]:
    """Runs whose settings are compared for labels: one method, sweep point and reading (the
    two readings of ConSFT have different settings; the suffix already tells them apart)."""
    return run.method, run.sweep_point, abstract_only(run)


def _varying_settings(runs: list[RunRecord]) -> dict[tuple[str, str, bool], list[str]]:
    """Per method, sweep point and reading, the settings that differ between its runs (never
    the point's own, which its runs share): the same point swept at two base settings
    (GRID="variant=dft" with kappa=1, then with kappa=4) gives two rows, not one run
    superseding the other."""
    groups: dict[tuple[str, str, bool], list[dict[str, str]]] = {}
    for run in runs:
        groups.setdefault(_group(run), []).append(settings(run))
    out = {}
    for group, all_settings in groups.items():
        keys = sorted({k for s in all_settings for k in s})
        out[group] = [k for k in keys if len({s.get(k) for s in all_settings}) > 1]
    return out


def _natural(label: str) -> tuple:
    """Sort "lr=0.0003" before "lr=0.001": numbers compare as numbers."""
    parts = re.split(r"(\d+(?:\.\d+)?(?:e-?\d+)?)", label)
    return tuple((0, float(p), "") if i % 2 else (1, 0.0, p) for i, p in enumerate(parts))
