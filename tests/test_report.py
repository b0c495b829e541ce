"""The comparison report, end to end from a small MLflow store this test writes itself, and
LIBERO's learning-curve metrics on a worked example."""

import csv
import io

import numpy as np
import pytest

from harness.measure.metrics import core_metrics, libero_metrics, offline_retention

FOUNDATION = ["reach-v3", "push-v3"]
STREAM = ["drawer-close-v3", "window-close-v3"]
EXPERIMENT = "mw-test"


# --- LIBERO FWT / NBT / AUC -------------------------------------------------------------------

def test_libero_metrics_worked_example():
    # K = 3 stream tasks in columns 1..3 (column 0: a foundation task); rows: stages 0..3
    R = np.array([
        [0.9, 0.0, 0.0, 0.0],
        [0.8, 0.6, 0.1, 0.0],
        [0.7, 0.4, 0.8, 0.2],
        [0.6, 0.2, 0.5, 1.0],
    ])
    curves = [np.array([0.0, 0.4, 0.8, 0.6]),  # task 1: best 0.8 mid-stage, ends at R[1,1] = 0.6
              np.array([0.1, 0.8]),
              np.array([0.2, 0.6, 1.0])]
    m = libero_metrics(curves, R, [1, 2, 3])
    # FWT_k = mean of the curve: 0.45, 0.45, 0.6
    assert m.fwt == pytest.approx((0.45 + 0.45 + 0.6) / 3)
    # NBT_1 = ((0.8 - 0.4) + (0.8 - 0.2)) / 2 = 0.5; NBT_2 = 0.8 - 0.5 = 0.3; NBT_3 = 0 (empty)
    assert m.nbt == pytest.approx((0.5 + 0.3 + 0.0) / 3)
    # AUC_1 = (0.45 + 0.4 + 0.2) / 3 = 0.35; AUC_2 = (0.45 + 0.5) / 2 = 0.475; AUC_3 = 0.6
    assert m.auc == pytest.approx((0.35 + 0.475 + 0.6) / 3)
    assert set(m.as_dict()) == {"fwt", "nbt", "auc"}


def test_libero_metrics_needs_one_curve_per_task():
    with pytest.raises(ValueError, match="one learning curve per stream task"):
        libero_metrics([np.array([0.5])], np.zeros((3, 2)), [0, 1])


# --- a small MLflow store: sft with seeds 0, 1, 2; consft with seeds 0, 1 (seed 2 missing) -----

def success_matrix(method: str, seed: int) -> np.ndarray:
    """Stages 0..2 by [F1, F2, S1, S2]; retention and plasticity chosen to be easy to average."""
    if method == "sft":
        final = 0.2 + 0.1 * seed  # retention 0.2, 0.3, 0.4 -> mean 0.3
        return np.array([[0.8, 0.8, 0.0, 0.0], [0.5, 0.5, 0.9, 0.0], [final, final, 0.3, 0.9]])
    final = 0.6 + 0.2 * seed  # retention 0.6, 0.8 -> mean 0.7
    return np.array([[0.8, 0.8, 0.0, 0.0], [0.8, 0.8, 0.6, 0.0], [final, final, 0.5, 0.7]])


def log_child(client, exp_id: str, parent: str, method: str, seed: int, tmp) -> None:
    """A child run shaped like the ones `python -m harness bench` logs (harness/run/execute.py)."""
    from mlflow.entities import Metric, Param

    tags = {"mlflow.parentRunId": parent, "method": method, "seed": str(seed), "benchmark": EXPERIMENT}
    if (method, seed) == ("sft", 1):  # resumed at a second commit; the others only have the param
        tags["retain.git_commits"] = "abc123,def456"
    run_id = client.create_run(exp_id, run_name=f"{method}/seed{seed}", tags=tags).info.run_id
    params = {"config.name": EXPERIMENT, "config.foundation_tasks": repr(FOUNDATION),
              "config.stream_tasks": repr(STREAM), "config.lr": "0.0003", "config.seed": str(seed),
              "config.method": method, "method": method, "seed": str(seed), "git_commit": "abc123"}
    if method == "consft":  # the paper's ConSFT logs its schedule (methods/consft.py)
        params.update({"method.variant": "paper", "method.kappa": "25.0",
                       "method.tau_start": "0.003"})
    client.log_batch(run_id, params=[Param(k, v) for k, v in sorted(params.items())])
    R = success_matrix(method, seed)
    tasks = FOUNDATION + STREAM
    metrics = [Metric(f"success/{t}", float(R[i, j]), 0, i) for i in range(3) for j, t in enumerate(tasks)]
    final = core_metrics(R, [0, 1], [2, 3]).as_dict()
    final["offline_retention"] = float(offline_retention(np.array([[1.0, 1.0], [2.0, 2.0]]), [0, 1])[-1])
    sparse = method == "consft"
    final.update({"update_frac_changed_rho0.001": 0.5 if sparse else 0.9,
                  "update_frac_changed_rho0.01": 0.1 if sparse else 0.6,
                  "update_hoyer_sparsity": 0.4 if sparse else 0.2,
                  "update_relative_l2": 0.01 * (seed + 1) * (1 if sparse else 3)})
    metrics += [Metric(k, v, 0, 2) for k, v in final.items()]
    client.log_batch(run_id, metrics=metrics)
    layers = tmp / f"{method}{seed}" / "updates_per_layer.csv"
    layers.parent.mkdir()
    layers.write_text("layer,numel,relative_l2,frac_changed_rho0.001,frac_changed_rho0.01\n"
                      f"encoder.weight,300,{0.02 if sparse else 0.05},0.5,0.1\n"
                      f"head.weight,100,{0.01 if sparse else 0.08},0.9,0.3\n")
    client.log_artifact(run_id, str(layers))
    client.set_terminated(run_id, "FINISHED")


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """results/ with an sqlite MLflow store holding one parent run and five child runs."""
    from mlflow.tracking import MlflowClient

    root = tmp_path_factory.mktemp("report")
    results = root / "results"
    results.mkdir()
    with pytest.MonkeyPatch.context() as mp:
        mp.delenv("MLFLOW_TRACKING_URI", raising=False)
        client = MlflowClient(tracking_uri=f"sqlite:///{results / 'mlflow.db'}")
        exp_id = client.create_experiment(EXPERIMENT, artifact_location=(results / "mlartifacts").as_uri())
        parent = client.create_run(exp_id, run_name="bench", tags={"benchmark": EXPERIMENT}).info.run_id
        for method, seeds in (("sft", [0, 1, 2]), ("consft", [0, 1])):
            for seed in seeds:
                log_child(client, exp_id, parent, method, seed, root)
        client.set_terminated(parent, "FINISHED")
        yield results, client, exp_id


@pytest.fixture(scope="module")
def report(store):
    from harness.report import ReportSettings, build_report

    results, client, exp_id = store
    with pytest.MonkeyPatch.context() as mp:
        mp.delenv("MLFLOW_TRACKING_URI", raising=False)
        settings = ReportSettings(EXPERIMENT, str(results))
        first = {p.name: p.read_bytes() for p in build_report(settings)}
        second = {p.name: p.read_bytes() for p in build_report(settings)}
    return settings.out_dir, first, second, client, exp_id


def rows_of(out) -> dict[str, dict[str, str]]:
    return {r["label"]: r for r in csv.DictReader(io.StringIO((out / "summary.csv").read_text()))}


def test_report_files(report):
    first = report[1]
    assert {"summary.md", "summary.csv", "summary.tex", "foundation_success.png",
            "plasticity_vs_retention.png", "update_sparsity.png", "relative_l2_per_layer.png",
            "success_matrix_sft.png", "success_matrix_consft.png", "report.html"} == set(first)
    assert all(first[name][:8] == b"\x89PNG\r\n\x1a\n" for name in first if name.endswith(".png"))


def test_table_means_match_hand_computed(report):
    rows = rows_of(report[0])
    assert list(rows) == ["sft", "consft"]  # SFT, the baseline, first
    sft, consft = rows["sft"], rows["consft"]
    assert float(sft["retention_mean"]) == pytest.approx(0.3)
    assert float(consft["retention_mean"]) == pytest.approx(0.7)
    assert float(sft["plasticity_mean"]) == pytest.approx(0.9)  # (0.9 + 0.9) / 2 every seed
    assert float(consft["plasticity_mean"]) == pytest.approx(0.65)
    assert float(sft["update_relative_l2_mean"]) == pytest.approx(0.06)  # 0.03, 0.06, 0.09
    # the bootstrap interval lies within the seeds' values and contains the mean
    low, high = float(sft["retention_ci_low"]), float(sft["retention_ci_high"])
    assert 0.2 - 1e-9 <= low < 0.3 < high <= 0.4 + 1e-9
    assert sft["retention_n"] == "3" and consft["retention_n"] == "2"
    assert "fwt_mean" not in sft  # FWT/NBT/AUC only when logged
    # these runs logged the held-out loss ratio under its old key, offline_retention: the
    # report reads it under its name now
    assert float(sft["heldout_loss_ratio_mean"]) == pytest.approx(2.0)
    assert "offline_retention_mean" not in sft
    assert "held-out loss ratio" in (report[0] / "summary.md").read_text()


def test_missing_seed_is_marked(report):
    out = report[0]
    rows = rows_of(out)
    assert rows["consft"]["missing_seeds"] == "2" and rows["sft"]["missing_seeds"] == ""
    md = (out / "summary.md").read_text()
    assert "| consft | 2/3: missing seed 2 |" in md
    assert "| sft | 3 |" in md
    assert "2/3: missing seed 2" in (out / "summary.tex").read_text()


def test_header_names_every_commit_that_ran_a_run(report):
    assert "git commits `abc123`, `def456`." in (report[0] / "summary.md").read_text()


def test_best_per_column_is_marked_by_direction(report):
    out = report[0]
    rows = rows_of(out)
    assert rows["consft"]["retention_best"] == "1" and rows["sft"]["retention_best"] == "0"
    assert rows["sft"]["plasticity_best"] == "1"
    # lower is better for the fraction of changed scalars: consft changed fewer
    assert rows["consft"]["update_frac_changed_rho0.01_best"] == "1"
    md = (out / "summary.md").read_text()
    consft_line = next(line for line in md.splitlines() if line.startswith("| consft |"))
    sft_line = next(line for line in md.splitlines() if line.startswith("| sft |"))
    assert "**0.700**" in consft_line and "**0.900**" in sft_line and "**0.300**" not in sft_line
    assert "retention ↑" in md and "forgetting ↓" in md
    assert r"\textbf{0.700}" in (out / "summary.tex").read_text()


def test_two_builds_are_byte_identical(report):
    _, first, second, _, _ = report
    assert first.keys() == second.keys()
    for name in sorted(first):
        assert first[name] == second[name], name


def test_report_is_logged_as_a_run(report):
    _, first, _, client, exp_id = report
    runs = client.search_runs([exp_id], filter_string="tags.report = 'true'")
    assert len(runs) == 2  # one per build; report runs are never read back as method runs
    logged = {a.path for a in client.list_artifacts(runs[0].info.run_id, "report")}
    assert logged == {f"report/{name}" for name in first}


def test_unknown_experiment_is_one_line_error(store):
    from harness.common.errors import RetainError
    from harness.report import ReportSettings, build_report

    with pytest.MonkeyPatch.context() as mp:
        mp.delenv("MLFLOW_TRACKING_URI", raising=False)
        with pytest.raises(RetainError, match="no MLflow experiment 'mw-nope'.*mw-test"):
            build_report(ReportSettings("mw-nope", str(store[0]), log_run=False))


# --- rows: sweep points and SFT's learning-rate sweep -----------------------------------------

def fake_run(method, seed, lr="0.0003", sweep_point="", retention=0.5, plasticity=0.5, start=0):
    from harness.report.runs import RunRecord

    params = {"config.lr": lr, "config.name": EXPERIMENT}
    if method == "consft":  # the paper's reading: it logs the schedule's tau_start
        params["method.tau_start"] = "0.003"
    return RunRecord(run_id=f"{method}{lr}{sweep_point}{seed}{start}", method=method, seed=seed,
                     sweep_point=sweep_point, start_time=start, params=params,
                     metrics={"retention": retention, "plasticity": plasticity},
                     foundation_tasks=FOUNDATION, stream_tasks=STREAM,
                     success=success_matrix("sft", seed), layers=[])


def test_rows_split_sweeps_and_learning_rates():
    from harness.report.aggregate import summarize
    from harness.report.groups import build_rows
    from harness.report.plots import sft_frontier

    runs = [fake_run("sft", 0, lr="0.001", retention=0.1, plasticity=0.9),
            fake_run("sft", 0, lr="0.0003", retention=0.3, plasticity=0.8),
            fake_run("sft", 0, lr="0.0001", retention=0.6, plasticity=0.5),
            fake_run("consft", 0), fake_run("consft", 0, sweep_point="kappa=0.1"),
            fake_run("consft", 0, start=5, retention=0.9)]  # a re-run of consft seed 0: newer wins
    rows, superseded = build_rows(runs)
    assert [r.label for r in rows] == ["sft[lr=0.0001]", "sft[lr=0.0003]", "sft[lr=0.001]",
                                       "consft", "consft[kappa=0.1]"]
    assert superseded == 1
    summaries = [summarize(r) for r in rows]
    assert summaries[3].cells["retention"].mean == pytest.approx(0.9)
    assert sft_frontier(summaries) == [(0.5, 0.6), (0.8, 0.3), (0.9, 0.1)]


def test_update_histogram_uses_the_thresholds_every_run_logged():
    # Runs logged before and after a change of thresholds: bins on the shared threshold only.
    import dataclasses

    from harness.report.aggregate import summarize
    from harness.report.groups import Row
    from harness.report.runs import LayerUpdate

    old = dataclasses.replace(fake_run("sft", 0), layers=[
        LayerUpdate("w", 100, 0.1, {0.01: 0.4}), LayerUpdate("b", 300, 0.1, {0.01: 0.8})])
    new = dataclasses.replace(fake_run("sft", 1), layers=[
        LayerUpdate("w", 100, 0.1, {0.001: 0.9, 0.01: 0.2}),
        LayerUpdate("b", 300, 0.1, {0.001: 0.9, 0.01: 0.6})])
    histogram = summarize(Row("sft", "sft", "", [old, new], [])).updates
    assert histogram.bins == ["<= 0.01", "> 0.01"]
    above = ((100 * 0.4 + 300 * 0.8) / 400 + (100 * 0.2 + 300 * 0.6) / 400) / 2  # 0.6
    np.testing.assert_allclose(histogram.fractions, [1 - above, above])


def test_point_names_never_overlap_each_other_or_leave_the_axes(monkeypatch, tmp_path):
    # mw-broad-6's figures: SFT at 1e-4 and 3e-5 lie 0.02 apart in plasticity and 0.003 in
    # retention, and their names were drawn over each other; here two rows also share a point.
    import dataclasses
    from itertools import combinations

    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from harness.report import plots
    from harness.report.aggregate import summarize
    from harness.report.groups import build_rows

    figures = []
    monkeypatch.setattr(plots, "save", lambda fig, path: figures.append(fig))
    points = [("sft", "0.0003", 0.136, 0.973), ("sft", "0.0001", 0.294, 0.973),
              ("sft", "3e-05", 0.297, 0.993), ("consft", "0.0003", 0.206, 0.987),
              ("er", "0.0003", 0.922, 0.963), ("agem", "0.0003", 0.922, 0.963)]
    runs = []
    for method, lr, retention, plasticity in points:
        run = fake_run(method, 0, lr=lr, retention=retention, plasticity=plasticity)
        runs.append(dataclasses.replace(run, metrics={
            **run.metrics, "spatial_retention": 0.75 * retention,
            "spatial_foundation_success_stage0": 0.7}))
    summaries = [summarize(r) for r in build_rows(runs)[0]]
    plots.plasticity_retention(tmp_path / "p.png", summaries, "mw-test")
    plots.spatial_retention(tmp_path / "s.png", summaries, "mw-test")
    assert len(figures) == 2
    for fig in figures:
        ax = fig.axes[0]
        renderer = FigureCanvasAgg(fig).get_renderer()
        names = [t for t in ax.texts if t.get_text()]
        assert sorted(t.get_text() for t in names) == sorted(s.label for s in summaries)
        boxes = [t.get_window_extent(renderer) for t in names]
        assert not [(a, b) for a, b in combinations(boxes, 2) if a.overlaps(b)]
        frame = ax.get_window_extent(renderer)
        assert all(frame.x0 <= b.x0 and b.x1 <= frame.x1 and frame.y0 <= b.y0 <= b.y1 <= frame.y1
                   for b in boxes)


def test_one_sweep_point_at_two_base_settings_gives_two_rows():
    import dataclasses

    from harness.report.groups import build_rows

    def dft(kappa, start):
        run = fake_run("consft", 0, sweep_point="variant=dft", start=start)
        params = {**run.params, "method.kappa": kappa, "method.variant": "dft"}
        return dataclasses.replace(run, params=params, run_id=f"dft{kappa}")

    rows, superseded = build_rows([dft("4.0", 0), dft("1.0", 1), fake_run("consft", 0)])
    assert [r.label for r in rows] == ["consft", "consft[variant=dft kappa=1.0]",
                                       "consft[variant=dft kappa=4.0]"]
    assert superseded == 0


def test_two_rows_with_the_same_curve_are_both_visible(monkeypatch, tmp_path):
    """foundation_success.png once drew SFT's line wholly under ConSFT's when they coincided:
    each row has its own line style and hollow marker, so the lower one shows through."""
    from matplotlib import colormaps
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    from harness.report import plots
    from harness.report.aggregate import summarize
    from harness.report.groups import build_rows

    figures = []
    monkeypatch.setattr(plots, "save", lambda fig, path: figures.append(fig))
    summaries = [summarize(r) for r in build_rows([fake_run("sft", 0), fake_run("consft", 0)])[0]]
    plots.foundation_curves(tmp_path / "f.png", summaries, "mw-test")
    ax = figures[0].axes[0]
    lines = [line for line in ax.get_lines() if line.get_label() in ("sft", "consft")]
    assert len(lines) == 2 and (lines[0].get_ydata() == lines[1].get_ydata()).all()
    assert lines[0].get_linestyle() != lines[1].get_linestyle()
    assert lines[0].get_marker() != lines[1].get_marker()
    ax.get_legend().remove()  # its swatches would show the color anyway
    canvas = FigureCanvasAgg(figures[0])
    canvas.draw()
    pixels = np.asarray(canvas.buffer_rgba())[..., :3].astype(int)
    below = np.array(colormaps["tab10"](0)[:3]) * 255  # sft's, drawn first
    assert (np.abs(pixels - below).max(axis=-1) < 20).sum() > 100
