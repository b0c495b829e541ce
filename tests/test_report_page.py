"""`make bench ... videos=true` at PROFILE=tiny writes the report page, and the page plays in a
real headless Chromium (Debian's package, installed by the fixture where missing): every video
loads (`readyState`), has a duration and advances when played. Set RETAIN_SCREENSHOT=path to
keep the page's screenshot (docs/report-page.png is one)."""

import os
import shutil

import pytest
from mlflow.tracking import MlflowClient

from harness.evaluate.recording import read_indexes
from harness.run.cli import main
from tests.browser import PLAY_VIDEOS, Browser, ensure_chromium

pytestmark = pytest.mark.slow  # a whole tiny benchmark, then a browser


@pytest.fixture(scope="module")
def bench_with_videos(tmp_path_factory):
    root = tmp_path_factory.mktemp("videos")
    args = ["bench", "PROFILE=tiny", "METHOD=sft", f"results_dir={root}/results",
            f"cache_dir={root}/cache", "progress=false", "eval_workers=1", "videos=true",
            "video_tasks=reach-v3,drawer-close-v3", "video_size=64"]
    return root, args


def test_a_tiny_bench_with_videos_writes_them_and_the_page(bench_with_videos, capsys):
    root, args = bench_with_videos
    assert main(args) == 0
    page = root / "results" / "mw-quick-tiny" / "report" / "report.html"
    assert f"report page with the videos: {page}" in capsys.readouterr().out
    run = root / "results" / "mw-quick-tiny" / "sft" / "seed0"
    shown = {(e.task, e.stage) for e in read_indexes(run / "videos")}
    assert shown == {("reach-v3", 0), ("reach-v3", 2), ("drawer-close-v3", 0),
                     ("drawer-close-v3", 1), ("drawer-close-v3", 2)}
    client = MlflowClient(tracking_uri=f"sqlite:///{root}/results/mlflow.db")
    child = next(r for r in client.search_runs(
        [client.get_experiment_by_name("mw-quick-tiny").experiment_id])
        if "mlflow.parentRunId" in r.data.tags)
    logged = {f.path for f in client.list_artifacts(child.info.run_id, "videos")}
    assert "videos/stage1_drawer-close-v3_ep0.mp4" in logged and "videos/stage0.json" in logged
    assert page.read_text().count("data:video/mp4;base64,") == 5


def test_the_page_plays_its_videos_in_headless_chromium(bench_with_videos, tmp_path):
    root, _ = bench_with_videos
    page = root / "results" / "mw-quick-tiny" / "report" / "report.html"
    if not page.exists():
        pytest.skip("the bench test before this one did not write the page")
    binary, why = ensure_chromium()
    if binary is None:
        pytest.skip(why)
    shot = tmp_path / "report.png"
    with Browser(binary) as browser:
        session = browser.page(page.as_uri())
        videos = browser.evaluate(session, PLAY_VIDEOS)
        browser.screenshot(session, shot)
    assert len(videos) == 5
    for v in videos:
        assert v["error"] == 0 and v["play"] is True, v
        assert v["readyState"] >= 2 and v["duration"] > 0 and v["advanced"] > 0, v
        assert v["width"] == 64, v
    assert shot.stat().st_size > 10_000 and shot.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    if os.environ.get("RETAIN_SCREENSHOT"):
        shutil.copy(shot, os.environ["RETAIN_SCREENSHOT"])
