"""A job resumed at another commit: MLflow keeps its first `git_commit` param (params cannot
change), and the run's commits tag lists every commit that ran part of it."""

from harness.track.tracking import COMMITS_TAG, KEY_TAG, Tracker, run_commits


def test_a_resumed_run_lists_both_commits_and_a_rerun_at_the_same_one_adds_none(tmp_path, monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    tracker = Tracker(str(tmp_path / "results"), "provenance")
    first = tracker.continue_or_start_run("job-1", "sft/seed0", "aaa")
    tracker.log_params(first, {"git_commit": "aaa"})
    assert tracker.client.get_run(first).data.tags[COMMITS_TAG] == "aaa"
    again = tracker.continue_or_start_run("job-1", "sft/seed0", "bbb")  # the restart, at a new commit
    tracker.log_params(again, {"git_commit": "bbb"})
    assert tracker.continue_or_start_run("job-1", "sft/seed0", "bbb") == again  # a rerun at bbb
    data = tracker.client.get_run(again).data
    assert again == first and data.params["git_commit"] == "aaa"
    assert data.tags[COMMITS_TAG] == "aaa,bbb" and run_commits(data.params, data.tags) == ["aaa", "bbb"]
    assert tracker.commits(again) == ["aaa", "bbb"]  # what the run's config.yaml lists


def test_a_run_logged_before_the_tag_reads_its_param():
    assert run_commits({"git_commit": "aaa"}, {}) == ["aaa"]
    assert run_commits({}, {}) == []


def test_a_run_logged_before_the_tag_keeps_its_param_commit_first(tmp_path, monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    tracker = Tracker(str(tmp_path / "results"), "provenance")
    old = tracker.start_run("sft/seed0", tags={KEY_TAG: "job-1"})  # as the code before the tag did
    tracker.log_params(old, {"git_commit": "aaa"})
    assert tracker.continue_or_start_run("job-1", "sft/seed0", "bbb") == old
    assert tracker.client.get_run(old).data.tags[COMMITS_TAG] == "aaa,bbb"
