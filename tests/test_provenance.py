"""A job resumed at another commit: MLflow keeps its first `git_commit` param (params cannot
change), and the run's commits tag lists every commit that ran part of it."""

from harness.tracking import COMMITS_TAG, Tracker, run_commits


def test_a_resumed_run_lists_both_commits_and_a_rerun_at_the_same_one_adds_none(tmp_path, monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    tracker = Tracker(str(tmp_path / "results"), "provenance")
    first = tracker.continue_or_start_run("job-1", "sft/seed0")
    tracker.log_params(first, {"git_commit": "aaa"})
    tracker.record_commit(first, "aaa")
    assert tracker.client.get_run(first).data.tags[COMMITS_TAG] == "aaa"
    again = tracker.continue_or_start_run("job-1", "sft/seed0")  # the restart, at a new commit
    tracker.log_params(again, {"git_commit": "bbb"})
    tracker.record_commit(again, "bbb")
    tracker.record_commit(again, "bbb")
    data = tracker.client.get_run(again).data
    assert again == first and data.params["git_commit"] == "aaa"
    assert data.tags[COMMITS_TAG] == "aaa,bbb" and run_commits(data.params, data.tags) == ["aaa", "bbb"]


def test_a_run_logged_before_the_tag_reads_its_param():
    assert run_commits({"git_commit": "aaa"}, {}) == ["aaa"]
    assert run_commits({}, {}) == []
