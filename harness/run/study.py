"""`python -m harness study STUDY=regimes [PART=mw-broad-6,...] [SEED=0 SEEDS=1] [DRY=1] [executor=local jobs=2]`.

A study is a named list of parts (harness/studies/<name>.yaml). A part is one benchmark with the
runs to compare on it ("sft", "sft lr=1e-4", "consft variant=dft"), each for the same seeds.
Why parts and not one long command: a study takes days on two cores, so it has to run in pieces
and continue after a restart. A part's runs are planned by `harness bench`'s own planning
(harness.run.plan.plan), merged into one comparison on one executor, and only the jobs whose MLflow
run is not FINISHED are run; an unfinished one resumes after its last finished stage. After each
part its report is rebuilt (harness.report). SEED= and SEEDS= pick a piece of each part's seeds
(`SEED=1 SEEDS=1`: seed 1 only), for a machine that has time for one seed's jobs but not three.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from harness.common.errors import USER_ERRORS, RetainError
from harness.config.benchmark import NOT_IN_RUN_KEY, SHARED_BY_SWEEP_POINTS, coerce, parse_overrides
from harness.run.execute import execute
from harness.run.plan import Plan, Variant, plan, variant_job_key, variant_run_key

STUDY_DIR = Path(__file__).parents[1] / "studies"

# command-line settings a study passes to every part: where and how its jobs run, never what
# they measure (so the pieces of one study stay one study)
PASS_THROUGH = frozenset(NOT_IN_RUN_KEY) - {"seed", "seeds", "method", "grid", "profile"}
STUDY_KEYS = ("STUDY", "PART", "DRY", "SEED", "SEEDS")
PART_KEYS = ("bench", "runs", "seeds", "profile", "settings")
# settings runs of one part may not differ in: one part builds one foundation per seed
SHARED_BY_PART = SHARED_BY_SWEEP_POINTS - {"method"}


@dataclass(frozen=True)
class StudyPart:
    """One benchmark and the runs compared on it, each for `seeds` seeds from seed 0."""

    name: str
    bench: str
    runs: tuple[str, ...]  # "sft", "sft lr=1e-4": a method, then its key=value settings
    seeds: int
    profile: str = ""
    settings: tuple[tuple[str, str], ...] = ()  # for every run: policy=pi0, name=<experiment>

    def run_args(self, run: str, extra: list[str], seeds: range) -> list[str]:
        """The `harness bench` arguments of one run of this part, for its seeds or a piece."""
        method, *rest = run.split()
        profile = [f"PROFILE={self.profile}"] if self.profile else []
        return [f"BENCH={self.bench}", *profile, f"METHOD={method}", f"SEED={seeds.start}",
                f"SEEDS={len(seeds)}", *(f"{k}={v}" for k, v in self.settings), *rest, *extra]

    def seed_piece(self, first: int, count: int | None) -> range:
        """Seeds first .. first + count - 1 (to the last when count is None), within 0 .. seeds - 1."""
        last = self.seeds if count is None else first + count
        if first < 0 or (count is not None and count < 1) or last > self.seeds:
            shown = f"SEED={first}" + ("" if count is None else f" SEEDS={count}")
            raise RetainError(f"bad seed piece {shown} for part {self.name!r}: its seeds are "
                              f"0-{self.seeds - 1}")
        return range(first, last)


@dataclass(frozen=True)
class Study:
    name: str
    path: Path
    parts: dict[str, StudyPart]


def study_names() -> list[str]:
    return sorted(p.stem for p in STUDY_DIR.glob("*.yaml"))


def load_study(name: str) -> Study:
    """A study by name (harness/studies/<name>.yaml) or by the path of a YAML file."""
    path = Path(name) if name.endswith((".yaml", ".yml")) else STUDY_DIR / f"{name}.yaml"
    if not path.exists():
        raise RetainError(f"unknown study {name!r}; valid: {', '.join(study_names())} "
                          "(or the path of a study .yaml file)")
    try:
        raw = yaml.safe_load(path.read_text())
    except yaml.YAMLError as exc:
        raise RetainError(f"study file {path} is not valid YAML: {str(exc).splitlines()[0]}") from None
    if not isinstance(raw, dict) or not isinstance(raw.get("parts"), dict) or not raw["parts"]:
        raise RetainError(f"study file {path} needs a mapping 'parts' of part name -> settings")
    bad = sorted(set(raw) - {"name", "seeds", "profile", "runs", "parts"})
    if bad:
        raise RetainError(f"study file {path}: unknown key {bad[0]!r}; valid: name, seeds, "
                          "profile, runs, parts")
    parts = {str(n): _part(path, str(n), spec, raw) for n, spec in raw["parts"].items()}
    return Study(str(raw.get("name", path.stem)), path, parts)


def _part(path: Path, name: str, spec: Any, top: dict) -> StudyPart:
    if not isinstance(spec, dict) or "bench" not in spec:
        raise RetainError(f"study file {path}: part {name!r} needs a mapping with 'bench'")
    bad = sorted(set(spec) - set(PART_KEYS))
    if bad:
        raise RetainError(f"study file {path}: part {name!r} has unknown key {bad[0]!r}; "
                          f"valid: {', '.join(PART_KEYS)}")
    runs = spec.get("runs", top.get("runs"))
    if not isinstance(runs, list) or not runs or not all(isinstance(r, str) and r.split()
                                                         for r in runs):
        raise RetainError(f"study file {path}: part {name!r} needs 'runs', a list such as "
                          "[sft, 'sft lr=1e-4']")
    settings = spec.get("settings", {}) or {}
    if not isinstance(settings, dict):
        raise RetainError(f"study file {path}: part {name!r}: 'settings' must be a mapping")
    seeds = coerce("seeds", spec.get("seeds", top.get("seeds", 1)), int)
    if seeds < 1:
        raise RetainError(f"study file {path}: part {name!r}: bad seeds {seeds}: expected >= 1")
    return StudyPart(name, str(spec["bench"]), tuple(runs), seeds,
                     str(spec.get("profile", top.get("profile", "")) or ""),
                     tuple((str(k), str(v)) for k, v in settings.items()))


@dataclass
class PartPlan:
    """A part's runs planned by `harness bench`'s planning, merged into one comparison."""

    part: StudyPart
    plan: Plan  # every run's variants; the first run's config, which they all share
    jobs: list[tuple[int, Variant, str]]  # (seed, variant, job key), seeds outer
    seeds: range  # the part's seeds, or the piece of them asked for

    @property
    def experiment(self) -> str:
        return self.plan.cfg.name


def plan_part(part: StudyPart, extra: list[str], seeds: range | None = None) -> PartPlan:
    """Plan every run of the part, for its seeds or a piece of them (nothing is trained or
    written), and check that they can share one foundation per seed and never share a run
    directory."""
    from suites import get_suite

    seeds = range(part.seeds) if seeds is None else seeds
    plans = []
    for run in part.runs:
        try:
            plans.append(plan(part.run_args(run, extra, seeds)))
        except USER_ERRORS as exc:
            raise RetainError(f"study part {part.name!r}, run {run!r}: {exc}") from None
    first = plans[0].cfg
    for run, p in zip(part.runs, plans):
        differ = sorted(k for k in SHARED_BY_PART if getattr(p.cfg, k) != getattr(first, k))
        if differ:
            raise RetainError(f"study part {part.name!r}: run {run!r} sets {differ[0]!r} apart "
                              f"from run {part.runs[0]!r}; a part's runs share their foundation: "
                              "put it in a part of its own")
    variants = [v for p in plans for v in p.variants]
    labels = [v.label for v in variants]
    twice = sorted({x for x in labels if labels.count(x) > 1})
    if twice:
        raise RetainError(f"study part {part.name!r}: two runs are both {twice[0]!r}")
    cfg = copy.deepcopy(first)
    cfg.method = ",".join(dict.fromkeys(v.method.name for v in variants))
    suite = get_suite(cfg.suite)
    jobs = [(seed, v, variant_job_key(v, suite, seed)) for seed in cfg.seed_list()
            for v in variants]
    return PartPlan(part, Plan(cfg, variants), jobs, seeds)


def finished_keys(pp: PartPlan) -> set[str]:
    """The keys of the part's jobs whose MLflow run is FINISHED (none before the store exists)."""
    from harness.track.tracking import finished_keys as finished
    from harness.track.tracking import quiet_mlflow, tracking_uri

    cfg = pp.plan.cfg
    uri = tracking_uri(cfg.results_dir)
    if uri.startswith("sqlite:") and not (Path(cfg.results_dir) / "mlflow.db").exists():
        return set()
    quiet_mlflow()
    from mlflow.tracking import MlflowClient

    client = MlflowClient(tracking_uri=uri)
    experiment = client.get_experiment_by_name(cfg.name)
    if experiment is None:
        return set()
    return finished(client, experiment.experiment_id, [key for *_, key in pp.jobs])


def stages_done(seed: int, variant: Variant) -> int:
    """The stage a restart of the job resumes after: its last checkpoint, if made with the job's
    settings (one made with others, such as an earlier version of the benchmark, is not)."""
    from harness.protocol.stream import resumable_stage, run_dir
    from suites import get_suite

    cfg = variant.cfg
    checkpoints = run_dir(cfg, variant.label, seed) / "stages"
    if not checkpoints.is_dir():
        return 0
    run_key = variant_run_key(variant, get_suite(cfg.suite), seed)
    return resumable_stage(checkpoints, cfg.num_stages, run_key) or 0


def describe(study: Study, plans: list[PartPlan]) -> str:
    """Per part: its benchmark, runs, and how many of its jobs are finished, started, to do."""
    lines = [f"study {study.name} ({study.path}): {len(plans)} of {len(study.parts)} parts"]
    for pp in plans:
        done = finished_keys(pp)
        started = [(s, v) for s, v, k in pp.jobs if k not in done and stages_done(s, v)]
        todo = len(pp.jobs) - len(done) - len(started)
        piece = "" if len(pp.seeds) == pp.part.seeds else \
            f" (seeds {pp.seeds.start}-{pp.seeds.stop - 1} of 0-{pp.part.seeds - 1})"
        lines.append(f"  {pp.part.name}: {pp.experiment}, {len(pp.plan.variants)} runs x "
                     f"{len(pp.seeds)} seeds{piece} = {len(pp.jobs)} jobs: {len(done)} finished, "
                     f"{len(started)} started, {todo} to do")
        lines.append(f"    runs: {', '.join(v.label for v in pp.plan.variants)}")
        finished: dict[str, list[str]] = {}
        for s, v, k in pp.jobs:
            if k in done:
                finished.setdefault(v.label, []).append(str(s))
        if finished:
            lines.append("    finished: " + "; ".join(f"{label} seeds {','.join(seeds)}"
                                                  for label, seeds in finished.items()))
        for s, v in started:
            lines.append(f"    started: {v.label} seed {s}, {stages_done(s, v)} of "
                         f"{v.cfg.num_stages} stages")
    return "\n".join(lines)


def run_part(pp: PartPlan) -> int:
    """The part's unfinished jobs through `harness bench`'s execution, then its report."""
    from harness.report.build import ReportSettings, build_report

    done = finished_keys(pp)
    todo = [(seed, v) for seed, v, key in pp.jobs if key not in done]
    cfg = pp.plan.cfg
    if todo:
        print(f"[study] part {pp.part.name}: {len(todo)} of {len(pp.jobs)} jobs to run "
              f"({len(done)} finished)", flush=True)
        status = execute(pp.plan, todo, f"study part {pp.part.name}")
        if status:
            return status
    else:
        print(f"[study] part {pp.part.name}: all {len(pp.jobs)} jobs finished; nothing to run",
              flush=True)
    settings = ReportSettings(experiment=cfg.name, results_dir=cfg.results_dir, log_run=True)
    files = build_report(settings)
    print(f"[study] part {pp.part.name}: report in {settings.out_dir}/ ({len(files)} files), "
          f"table {settings.out_dir / 'summary.md'}", flush=True)
    return 0


def select_parts(study: Study, names: str) -> list[StudyPart]:
    if not names:
        return list(study.parts.values())
    wanted = [n.strip() for n in names.split(",") if n.strip()]
    for n in wanted:
        if n not in study.parts:
            raise RetainError(f"unknown part {n!r} of study {study.name}; valid: "
                              f"{', '.join(study.parts)}")
    return [study.parts[n] for n in wanted]


def study(args: list[str]) -> int:
    given = parse_overrides(args)
    bad = sorted(k for k in given if k not in STUDY_KEYS and k not in PASS_THROUGH)
    if bad:
        raise RetainError(f"unknown study setting {bad[0]!r}; valid: "
                          f"{', '.join(STUDY_KEYS + tuple(sorted(PASS_THROUGH)))}")
    if not given.get("STUDY"):
        raise RetainError(f"STUDY= is required; valid: {', '.join(study_names())}")
    s = load_study(given["STUDY"])
    parts = select_parts(s, given.get("PART", ""))
    extra = [f"{k}={v}" for k, v in given.items() if k in PASS_THROUGH]
    first = coerce("SEED", given.get("SEED", "0") or "0", int)
    count = coerce("SEEDS", given["SEEDS"], int) if given.get("SEEDS") else None
    # every part checked before any runs
    plans = [plan_part(part, extra, part.seed_piece(first, count)) for part in parts]
    if coerce("DRY", given.get("DRY", "0") or "0", bool):
        print(describe(s, plans))
        return 0
    for pp in plans:
        status = run_part(pp)
        if status:
            return status
    return 0
