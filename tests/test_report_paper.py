"""The report under the ConSFT paper's protocol (issue 36): the table-2 columns with their base
row, grouped stages, the label of the earlier ConSFT reading, the per-step figures, and the
per-stage record a run writes. Runs are logged the way `python -m harness bench` logs them: the
config as params (jobs.provenance_params), per-stage metrics from jobs.stage_metrics, final
metrics from runner.summary_metrics."""

import csv
import dataclasses
import io
import json

import numpy as np
import pytest

from harness.config.benchmark import BenchConfig
from harness.evaluate.stages import StageRecord
from harness.protocol.stream import RunResult, summary_metrics
from harness.report.groups import Row
from harness.report.paper import paired_rows
from harness.report.runs import RunRecord
from harness.run.jobs import provenance_params, stage_metrics
from methods.consft import ConSFTConfig

EXPERIMENT = "mw-paper-test"
FOUNDATION = ["reach-v3", "push-v3", "pick-place-v3", "door-open-v3"]
HELDOUT = {"object": ["reach-v3", "push-v3"], "goal": ["pick-place-v3", "door-open-v3"]}
STREAM = ["drawer-close-v3", "window-close-v3", "button-press-v3"]
SIZES = [2, 1]  # stage 1 trains drawer-close and window-close together, stage 2 button-press
STEPS, FOUNDATION_STEPS, CHECK_EVERY = 10, 100, 5
# the issue-36 settings a run from before them never logged
NEW_SETTINGS = ("stage_sizes", "until_success", "check_every", "check_episodes", "adam_beta1",
                "adam_beta2", "adam_eps", "heldout_groups")
OLD_CONSFT = {"variant": "clip", "kappa": 4.0, "w_min": 0.1, "reference": "foundation",
              "quantile": 0.5, "eps": 0.2, "reference_samples": 2048}

# stage 0 is one seed's foundation, the same for every method: [F..., S...]
STAGE0 = {0: [0.8, 0.6, 0.4, 0.2, 0.0, 0.1, 0.2], 1: [0.6, 0.6, 0.4, 0.4, 0.2, 0.1, 0.0]}
FINAL = {("sft", 0): [0.2, 0.0, 0.1, 0.1, 1.0, 0.8, 0.9],
         ("sft", 1): [0.4, 0.2, 0.3, 0.1, 0.8, 0.8, 0.8],
         ("consft", 0): [0.6, 0.4, 0.3, 0.3, 0.9, 0.9, 0.9],
         ("consft", 1): [0.4, 0.4, 0.5, 0.3, 1.0, 0.8, 0.9]}
# per stage: (steps used, [(check step, check success)]); a check at the step budget is never
# made, so a stage that ran its 10 steps has one check, at 5
CHECKS = {("sft", 0): [(10, [(5, 0.4)]), (5, [(5, 0.6)])],
          ("sft", 1): [(10, [(5, 0.2)]), (10, [(5, 0.4)])],
          ("consft", 0): [(5, [(5, 0.5)]), (5, [(5, 0.7)])],
          ("consft", 1): [(10, [(5, 0.3)]), (5, [(5, 0.5)])]}


def config(grouped: bool = True) -> BenchConfig:
    cfg = BenchConfig(EXPERIMENT, "metaworld", list(FOUNDATION), list(STREAM))
    cfg.steps_per_task, cfg.foundation_steps, cfg.check_every = STEPS, FOUNDATION_STEPS, CHECK_EVERY
    if grouped:
        cfg.stage_sizes, cfg.heldout_groups, cfg.until_success = list(SIZES), dict(HELDOUT), 0.5
    return cfg


def records(method: str, seed: int, grouped: bool = True) -> list[StageRecord]:
    """Stage 0 and the stream stages of one run, as the runner records them."""
    tasks = FOUNDATION + STREAM
    k = len(SIZES) if grouped else len(STREAM)
    final = FINAL.get((method, seed), [0.5] * len(tasks))
    rows = [STAGE0[seed]] + [[(a + b) / 2 for a, b in zip(STAGE0[seed], final)]] * (k - 1) + [final]
    names = ["foundation", "stage1-2-tasks", "button-press-v3"] if grouped else ["foundation", *STREAM]
    out = []
    for stage, row in enumerate(rows):
        record = StageRecord(stage, names[stage], dict(zip(tasks, row)), {},
                             {t: 1.0 + 0.1 * stage for t in tasks})
        if stage and grouped:
            record.steps_used, checks = CHECKS[(method, seed)][stage - 1]
            record.check_steps = [n for n, _ in checks]
            record.check_success = [v for _, v in checks]
        if stage == k:
            record.updates = {"eq8_sparsity": 0.6 if method == "consft" else 0.4,
                              "relative_l2": 0.01}
        out.append(record)
    return out


def sparsity(method: str, seed: int, stage: int) -> list[float]:
    """Eq. 8 at each check_every step and at the stage's end (steps 5 and 10; 5 alone when the
    stage stopped at its first check)."""
    used = CHECKS[(method, seed)][stage - 1][0]
    start = {("sft", 0): 0.9, ("sft", 1): 0.8, ("consft", 0): 0.95, ("consft", 1): 0.85}
    first = start[(method, seed)] - 0.2 * (stage - 1)
    return [first, first - 0.1][: used // CHECK_EVERY]


def global_step(stage: int, done: int) -> int:
    """The trainer's step axis: foundation_steps + (stage - 1) * steps_per_task + done - 1."""
    return FOUNDATION_STEPS + (stage - 1) * STEPS + done - 1


def log_child(tracker, exp_parent: str, method: str, seed: int, tmp, grouped: bool = True) -> None:
    cfg = config(grouped)
    tags = {"method": method, "seed": str(seed), "benchmark": EXPERIMENT, "needs": "none"}
    run_id = tracker.start_run(f"{method}/seed{seed}", parent_id=exp_parent, tags=tags)
    params = provenance_params(cfg, {"git_commit": "abc123", "versions": {}})
    if not grouped:  # a run from before issue 36 never logged its settings
        params = {k: v for k, v in params.items() if k.removeprefix("config.") not in NEW_SETTINGS}
    hyper = {}
    if method == "consft":
        hyper = dataclasses.asdict(ConSFTConfig()) if grouped else OLD_CONSFT
    tracker.log_params(run_id, {**params, **{f"method.{k}": v for k, v in hyper.items()},
                                "method": method, "seed": seed})
    stages = records(method, seed, grouped)
    tracker.log_metric_rows(run_id, [(r.stage, stage_metrics(cfg, r)) for r in stages])
    result = RunResult(method, seed, tmp, stages, {}, FOUNDATION + STREAM, [])
    final = summary_metrics(cfg, result)
    if not grouped:  # an earlier run's final metrics: none of the paper's
        final = {k: v for k, v in final.items() if k not in ("stream_steps", "update_eq8_sparsity")
                 and "target" not in k and not k.startswith(("heldout", "base_"))}
    tracker.log_metrics(run_id, final, step=len(STREAM))
    if grouped:
        steps = []
        for stage in (1, 2):
            steps += [(global_step(stage, CHECK_EVERY * (i + 1)), {"sparsity/eq8": v})
                      for i, v in enumerate(sparsity(method, seed, stage))]
            if method == "consft":
                used = CHECKS[(method, seed)][stage - 1][0]
                steps += [(global_step(stage, done), {
                    "consft/tau": 0.003 * done, "consft/weight_mean": 0.001 * done,
                    "consft/frac_at_floor": 1 - 0.05 * done, "consft/loss_q10": 0.01,
                    "consft/loss_q50": 0.1, "consft/loss_q90": 1.0}) for done in range(1, used + 1)]
        if (method, seed) == ("sft", 0):  # a killed attempt's row past where the rerun stopped
            steps.insert(0, (global_step(2, 10), {"sparsity/eq8": 0.123}))
        tracker.log_metric_rows(run_id, steps)
    tracker.end_run(run_id)


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """sft and consft (the paper's) at seeds 0 and 1 with grouped stages, and consft as read
    from the abstract alone (one task a stage, no paper metrics) at seeds 0 and 1."""
    from harness.track.tracking import Tracker

    root = tmp_path_factory.mktemp("paper")
    results = root / "results"
    with pytest.MonkeyPatch.context() as mp:
        mp.delenv("MLFLOW_TRACKING_URI", raising=False)
        tracker = Tracker(str(results), EXPERIMENT)
        parent = tracker.start_run("bench")
        for method in ("sft", "consft"):
            for seed in (0, 1):
                log_child(tracker, parent, method, seed, root)
        for seed in (0, 1):
            log_child(tracker, parent, "consft", seed, root, grouped=False)
        tracker.end_run(parent)
        yield results, tracker


@pytest.fixture(scope="module")
def report(store):
    from harness.report import ReportSettings, build_report

    with pytest.MonkeyPatch.context() as mp:
        mp.delenv("MLFLOW_TRACKING_URI", raising=False)
        settings = ReportSettings(EXPERIMENT, str(store[0]), log_run=False)
        files = build_report(settings)
    return settings.out_dir, {p.name for p in files}


def csv_rows(path) -> dict[str, dict[str, str]]:
    return {r["label"]: r for r in csv.DictReader(io.StringIO(path.read_text()))}


ABSTRACT = "consft (abstract-only reading)"


def test_paper_table_against_hand_computation(report):
    out, files = report
    assert {"paper_table.md", "paper_table.csv"} <= files
    rows = csv_rows(out / "paper_table.csv")
    assert list(rows) == ["base", "sft", "consft", ABSTRACT]
    sft, consft = rows["sft"], rows["consft"]
    # target: mean over the three stream tasks after the last stage, then over the two seeds
    assert float(sft["target_mean"]) == pytest.approx(((1.0 + 0.8 + 0.9) / 3 + 0.8) / 2)
    assert float(consft["target_mean"]) == pytest.approx(0.9)
    # held-out suites: object = reach, push; goal = pick-place, door-open
    assert float(sft["heldout/object_mean"]) == pytest.approx((0.1 + 0.3) / 2)
    assert float(sft["heldout/goal_mean"]) == pytest.approx((0.1 + 0.2) / 2)
    assert float(sft["heldout_avg_mean"]) == pytest.approx((0.1 + 0.25) / 2)
    assert float(consft["heldout/object_mean"]) == pytest.approx((0.5 + 0.4) / 2)
    assert float(consft["heldout_avg_mean"]) == pytest.approx(0.4)
    # steps used over the stream, and the success each stage stopped at, mean over stages
    assert float(sft["stream_steps_mean"]) == pytest.approx((15 + 20) / 2)
    assert float(consft["stream_steps_mean"]) == pytest.approx((10 + 15) / 2)
    assert float(sft["check_success_mean"]) == pytest.approx(((0.4 + 0.6) / 2 + (0.2 + 0.4) / 2) / 2)
    assert float(consft["check_success_mean"]) == pytest.approx(((0.5 + 0.7) / 2 + 0.4) / 2)
    # an interval from two seeds lies within them
    low, high = float(sft["heldout_avg_ci_low"]), float(sft["heldout_avg_ci_high"])
    assert 0.1 - 1e-9 <= low < 0.175 < high <= 0.25 + 1e-9
    # the columns follow the benchmark's heldout_groups order; best by direction, none for steps
    header = next(csv.reader(io.StringIO((out / "paper_table.csv").read_text())))
    assert [h.removesuffix("_mean") for h in header if h.endswith("_mean")] == [
        "target", "heldout/object", "heldout/goal", "heldout_avg", "stream_steps", "check_success"]
    assert consft["heldout_avg_best"] == "1" and sft["heldout_avg_best"] == "0"
    assert {r["stream_steps_best"] for r in rows.values()} == {"0"}
    # a run from before the paper's metrics: its row is there, its cells empty
    assert rows[ABSTRACT]["target_n"] == "0" and rows[ABSTRACT]["check_success_n"] == "0"
    md = (out / "paper_table.md").read_text()
    assert "| method | seeds | needs | target ↑ | held-out: object ↑ | held-out: goal ↑ | " \
           "held-out avg ↑ | steps used | check success |" in md
    assert "| consft | 2 | none | **0.900** [0.900, 0.900] |" in md


def test_base_row_is_stage_0_once_over_seeds(report):
    out, _ = report
    base = csv_rows(out / "paper_table.csv")["base"]
    assert base["seeds"] == "0;1" and base["method"] == ""
    # stage 0 per seed: target (0 + 0.1 + 0.2) / 3 and (0.2 + 0.1 + 0) / 3; object 0.7 and 0.6
    assert float(base["target_mean"]) == pytest.approx(0.1)
    assert float(base["heldout/object_mean"]) == pytest.approx(0.65)
    assert float(base["heldout/goal_mean"]) == pytest.approx(0.35)
    assert float(base["heldout_avg_mean"]) == pytest.approx(0.5)
    assert base["stream_steps_mean"] == "" and base["check_success_mean"] == ""
    md = (out / "paper_table.md").read_text().splitlines()
    base_lines = [line for line in md if line.startswith("| base (stage 0) |")]
    assert len(base_lines) == 1 and base_lines[0].startswith("| base (stage 0) | 2 | - | 0.100 ")
    assert "different foundations" not in "\n".join(md)  # every run of a seed agreed


def test_main_table_has_steps_and_eq8_sparsity(report):
    out, _ = report
    rows = csv_rows(out / "summary.csv")
    assert float(rows["sft"]["stream_steps_mean"]) == pytest.approx(17.5)
    assert float(rows["consft"]["update_eq8_sparsity_mean"]) == pytest.approx(0.6)
    assert rows["consft"]["update_eq8_sparsity_best"] == "1"
    assert rows[ABSTRACT]["stream_steps_n"] == "0"
    md = (out / "summary.md").read_text()
    assert "| steps used |" in md and "Eq. 8 sparsity ↑" in md
    assert "[paper_table.md](paper_table.md)" in md


def test_grouped_stages_are_read_from_the_config(store):
    from harness.report.runs import experiment_id, load_runs, open_client
    from harness.track.tracking import tracking_uri

    uri = tracking_uri(str(store[0]))
    client = open_client(uri)
    runs = {(r.method, r.seed, "method.tau_start" in r.params): r
            for r in load_runs(client, experiment_id(client, EXPERIMENT, uri))}
    grouped, old = runs[("sft", 0, False)], runs[("consft", 0, False)]
    assert grouped.stream_tasks == STREAM  # config.stream_tasks stays a flat list
    assert grouped.stages == [STREAM[:2], STREAM[2:]]
    assert grouped.stage_names == ["foundation", "stage1-2-tasks", "button-press-v3"]
    assert grouped.success.shape == (3, 7)  # stages 0..2
    np.testing.assert_allclose(grouped.success[2], FINAL[("sft", 0)])
    assert grouped.stage_steps == (10.0, 5.0) and grouped.stage_check_success == (0.4, 0.6)
    # no config.stage_sizes param (a run from before it): one task a stage
    assert old.stages == [[t] for t in STREAM] and old.success.shape == (4, 7)
    assert np.isnan(old.stage_steps).all() and not old.series
    # the per-step series on the stream's step axis: stage 2's steps start at steps_per_task
    eq8 = runs[("sft", 1, False)].series["sparsity/eq8"]
    assert eq8.step.tolist() == [5, 10, 15, 20] and eq8.stage.tolist() == [1, 1, 2, 2]
    np.testing.assert_allclose(eq8.value, [0.8, 0.7, 0.6, 0.5])
    # sft seed 0's stage 2 stopped at 5 steps: a killed attempt's row at its step 10 is dropped
    eq8 = runs[("sft", 0, False)].series["sparsity/eq8"]
    assert eq8.step.tolist() == [5, 10, 15] and eq8.stage.tolist() == [1, 1, 2]
    np.testing.assert_allclose(eq8.value, [0.9, 0.8, 0.7])


def test_grouped_stages_in_the_heatmap_and_curves(store, monkeypatch, tmp_path):
    from matplotlib.patches import Rectangle

    from harness.report import plots
    from harness.report.aggregate import summarize
    from harness.report.groups import build_rows
    from harness.report.runs import experiment_id, load_runs, open_client
    from harness.track.tracking import tracking_uri

    uri = tracking_uri(str(store[0]))
    client = open_client(uri)
    rows, _ = build_rows(load_runs(client, experiment_id(client, EXPERIMENT, uri)))
    summaries = {s.label: s for s in map(summarize, rows)}
    drawn = []
    monkeypatch.setattr(plots.figures, "save", lambda fig, path: drawn.append(fig))
    monkeypatch.setattr(plots, "save", lambda fig, path: drawn.append(fig))
    plots.success_heatmap(tmp_path / "h.png", summaries["sft"], EXPERIMENT)
    plots.foundation_curves(tmp_path / "f.png", [summaries["sft"]], EXPERIMENT)
    heatmap, curves = (fig.axes[0] for fig in drawn)
    assert [t.get_text() for t in heatmap.get_yticklabels()] == [
        "0: foundation", "1: stage1-2-tasks", "2: button-press"]
    outlined = [(p.get_x(), p.get_y(), p.get_width()) for p in heatmap.patches
                if isinstance(p, Rectangle) and not p.get_fill()]
    # stage 1 outlines both its tasks (columns 4 and 5), stage 2 its one (column 6)
    assert outlined == [(3.5, 0.5, 2), (5.5, 1.5, 1)]
    assert [t.get_text().split("\n")[1] for t in curves.get_xticklabels()] == [
        "foundation", "stage1-2-tasks", "button-press"]


def test_abstract_only_reading_is_labelled(report, store):
    out, files = report
    label = ABSTRACT
    for name in ("summary.csv", "paper_table.csv"):
        assert label in csv_rows(out / name)
    for name in ("summary.md", "paper_table.md", "summary.tex"):
        assert label in (out / name).read_text()
    assert "success_matrix_consft_abstract-only_reading.png" in files
    assert "are ConSFT as Retain read it from the paper's abstract alone" in \
        (out / "summary.md").read_text()
    # the paper's ConSFT (it logs tau_start) keeps the plain label
    assert "consft" in csv_rows(out / "summary.csv")


def test_abstract_only_test_reads_the_logged_params():
    from harness.report.groups import abstract_only, build_rows
    from harness.report.runs import RunRecord

    def run(method, params, seed=0):
        return RunRecord(f"{method}{seed}{len(params)}", method, seed, "", 0, params, {},
                         FOUNDATION, STREAM, np.zeros((4, 7)), [])

    paper = {f"method.{k}": str(v) for k, v in dataclasses.asdict(ConSFTConfig()).items()}
    dft = {**paper, "method.variant": "dft"}
    old = {f"method.{k}": str(v) for k, v in OLD_CONSFT.items()}
    assert not abstract_only(run("consft", paper)) and not abstract_only(run("consft", dft))
    assert abstract_only(run("consft", old))
    assert abstract_only(run("consft", {**old, "method.variant": "dft"}))  # the old dft too
    assert not abstract_only(run("sft", {}))
    # two readings in one experiment: two rows, told apart by the suffix alone, not by every
    # setting in which the readings differ
    rows, _ = build_rows([run("consft", paper), run("consft", old), run("consft", old, seed=1)])
    assert [r.label for r in rows] == ["consft", ABSTRACT]
    assert [len(r.runs) for r in rows] == [1, 2]


def test_per_step_figures_are_written_only_with_their_data(report, tmp_path):
    from test_report import fake_run

    from harness.report.aggregate import summarize
    from harness.report.build import write_report
    from harness.report.groups import build_rows

    out, files = report
    assert {"sparsity_progress.png", "consft_weights.png"} <= files
    assert all((out / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
               for name in ("sparsity_progress.png", "consft_weights.png"))
    md = (out / "summary.md").read_text()
    assert "![sparsity_progress](sparsity_progress.png)" in md
    # runs that logged neither: no figure, no link, and a stale one from an earlier build goes
    (tmp_path / "sparsity_progress.png").write_bytes(b"old")
    rows, _ = build_rows([fake_run("sft", 0), fake_run("consft", 0)])
    written = {p.name for p in write_report(tmp_path, [summarize(r) for r in rows], EXPERIMENT)}
    assert not {"sparsity_progress.png", "consft_weights.png", "paper_table.md"} & written
    assert not (tmp_path / "sparsity_progress.png").exists()
    assert "sparsity_progress" not in (tmp_path / "summary.md").read_text()


def test_sparsity_series_is_the_mean_and_range_over_seeds(store):
    from harness.report.aggregate import summarize
    from harness.report.groups import build_rows
    from harness.report.runs import experiment_id, load_runs, open_client
    from harness.track.tracking import tracking_uri

    uri = tracking_uri(str(store[0]))
    client = open_client(uri)
    rows, _ = build_rows(load_runs(client, experiment_id(client, EXPERIMENT, uri)))
    sft = summarize(next(r for r in rows if r.label == "sft")).series["sparsity/eq8"]
    # seed 0: 0.9, 0.8 in stage 1, then 0.7 (stopped at its first check); seed 1: 0.8, 0.7, 0.6, 0.5
    assert sft.step.tolist() == [5, 10, 15, 20] and sft.n == 2
    np.testing.assert_allclose(sft.mean, [0.85, 0.75, 0.65, 0.5])
    np.testing.assert_allclose(sft.low, [0.8, 0.7, 0.6, 0.5])
    np.testing.assert_allclose(sft.high, [0.9, 0.8, 0.7, 0.5])


def test_run_outputs_carry_the_stage_progress(tmp_path):
    from harness.track.run_outputs import write_run_outputs

    cfg = config()
    stages = records("consft", 0)
    stages[1].sparsity_steps, stages[1].sparsity = [5], [0.95]
    stages[1].sparsity_layers = {"encoder.weight": [0.9], "head.weight": [1.0]}
    stages[2].sparsity_steps, stages[2].sparsity = [5], [0.75]
    stages[2].sparsity_layers = {"encoder.weight": [0.7], "head.weight": [0.8]}
    result = RunResult("consft", 0, tmp_path, stages, {}, FOUNDATION + STREAM, [])
    result.metrics = summary_metrics(cfg, result)
    paths = write_run_outputs(cfg, result, {"git_commit": "abc123"})
    saved = json.loads(paths["metrics"].read_text())["stages"]
    assert [s["steps_used"] for s in saved] == [0, 5, 5]
    assert saved[1]["check_steps"] == [5] and saved[2]["check_success"] == [0.7]
    assert saved[2]["sparsity_steps"] == [5] and saved[2]["sparsity"] == [0.75]
    assert paths["sparsity_progress"].name == "sparsity_progress.csv"
    assert paths["sparsity_progress"].read_text() == (
        "stage,step,layer,eq8\n1,5,encoder.weight,0.9\n1,5,head.weight,1\n"
        "2,5,encoder.weight,0.7\n2,5,head.weight,0.8\n")


def test_stage_metrics_log_steps_and_the_last_check():
    cfg = config()
    stage0, stage1, _ = records("sft", 0)
    assert "stage_steps" not in stage_metrics(cfg, stage0)
    assert "stage_check_success" not in stage_metrics(cfg, stage0)
    m = stage_metrics(cfg, dataclasses.replace(stage1, check_steps=[3, 6], check_success=[0.2, 0.5]))
    assert m["stage_steps"] == 10 and m["stage_check_success"] == 0.5


def test_paired_against_sft_seed_by_seed(report):
    """consft minus sft at each seed (hand computation from FINAL), then the mean over seeds;
    the abstract-only consft logged no paper metrics, so it has no paired row."""
    out, files = report
    assert "paper_paired.csv" in files
    rows = {r["label"]: r for r in csv.DictReader(io.StringIO(
        (out / "paper_paired.csv").read_text()))}
    assert list(rows) == ["consft"]
    consft = rows["consft"]
    assert consft["reference"] == "sft" and consft["seeds"] == "0;1"
    # held-out avg: seed 0 consft 0.4 - sft 0.1; seed 1 consft 0.4 - sft 0.25
    assert [float(v) for v in consft["heldout_avg_diff_per_seed"].split(";")] == \
        pytest.approx([0.3, 0.15])
    assert float(consft["heldout_avg_diff_mean"]) == pytest.approx(0.225)
    assert 0.15 - 1e-9 <= float(consft["heldout_avg_diff_ci_low"]) \
        < 0.225 < float(consft["heldout_avg_diff_ci_high"]) <= 0.3 + 1e-9
    # target: seed 0 0.9 - 0.9, seed 1 0.9 - 0.8
    assert float(consft["target_diff_mean"]) == pytest.approx(0.05)
    md = (out / "paper_table.md").read_text()
    assert "## Against sft, seed by seed" in md
    assert "| method | seeds | Δ target | Δ held-out avg | per seed (held-out avg) |" in md
    assert "| consft | 2 | +0.050 [+0.000, +0.100] | +0.225 [+0.150, +0.300] | " \
           "0: +0.300, 1: +0.150 |" in md


def _run(method: str, seed: int, target: float, heldout: float) -> RunRecord:
    return RunRecord(f"{method}{seed}", method, seed, "", 0, {}, {"target": target,
                     "heldout_avg": heldout}, [], [], np.zeros((1, 1)), [])


def test_paired_rows_use_only_the_shared_seeds():
    sft = Row("sft", "sft", "", [_run("sft", s, 0.9, 0.5 + 0.1 * s) for s in (0, 1, 2)], [])
    er = Row("er", "er", "", [_run("er", s, 0.8, 0.9) for s in (1, 2, 3)], [0])
    nan = Row("ewc", "ewc", "", [_run("ewc", 0, 0.7, float("nan"))], [1, 2])
    (paired,) = paired_rows([er, sft, nan])
    assert paired.label == "er" and paired.seeds == [1, 2]
    assert paired.per_seed["heldout_avg"] == pytest.approx([0.3, 0.2])
    assert paired.per_seed["target"] == pytest.approx([-0.1, -0.1])
    assert paired.cells["heldout_avg"].mean == pytest.approx(0.25)
    # no sft row: nothing to pair against
    assert paired_rows([er, nan]) == []


def test_a_cell_from_fewer_seeds_than_its_row_is_noted():
    """seed 0's sft ran before check success was logged: the row has 3 seeds, the cell 2."""
    from harness.measure.bootstrap import bootstrap_ci
    from harness.report.aggregate import CHECK_SUCCESS, Metric, RowSummary
    from harness.report.build import _row_notes

    check = Metric(CHECK_SUCCESS, "check success", True, "", ranked=False)
    target = Metric("target", "target", True, "")

    def summary(label: str, checks: list[float]) -> RowSummary:
        runs = [dataclasses.replace(_run(label, s, 0.9, 0.5), stage_check_success=(c,))
                for s, c in enumerate(checks)]
        row = Row(label, label, "", runs, [])
        return RowSummary(row, {"target": bootstrap_ci([0.9] * 3), CHECK_SUCCESS:
                                bootstrap_ci(checks)}, [], [], np.zeros((1, 1)), [], None, {})

    notes = _row_notes([summary("sft", [float("nan"), 0.9, 0.95]),
                        summary("er", [0.9, 0.9, 0.95]),
                        summary("old", [float("nan")] * 3)], 0, [target, check])
    assert notes[2:-1] == ["- **sft**: its check success averages 2 of its 3 seeds; seed 0 "
                           "did not log it (run before it existed)."]
