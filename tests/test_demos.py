"""Demonstrations: the HDF5 layout, its round trip, the cache, and bad files."""

import h5py
import numpy as np
import pytest

from harness.common.errors import DemoFileError
from harness.data.demos import DemoSpec, Episode, load_or_generate, read_demo_file, write_demo_file


def _episodes(n=2, t=7):
    rng = np.random.default_rng(0)
    return [Episode(rng.standard_normal((t + i, 4)).astype(np.float32),
                    {"state": rng.standard_normal((t + i, 39)).astype(np.float32)}, seed=10 + i)
            for i in range(n)]


SPEC = DemoSpec(suite="metaworld", suite_version="1", task="reach-v3", split="demo", num_demos=2,
                max_episode_steps=100)


def test_round_trip_in_robomimic_layout(tmp_path):
    path = tmp_path / "demos.hdf5"
    episodes = _episodes()
    write_demo_file(path, episodes, SPEC, "reach the goal position")
    with h5py.File(path) as f:
        assert f["data"].attrs["instruction"] == "reach the goal position"
        assert set(f["data/demo_1"]) == {"actions", "obs", "rewards", "dones"}
        assert f["data/demo_1/obs/state"].shape == (8, 39)
        assert f["data/demo_0/dones"][-1] == 1 and f["data/demo_0/dones"][:-1].sum() == 0
    instruction, loaded = read_demo_file(path, SPEC)
    assert instruction == "reach the goal position"
    for a, b in zip(episodes, loaded):
        np.testing.assert_array_equal(a.actions, b.actions)
        np.testing.assert_array_equal(a.obs["state"], b.obs["state"])
        assert a.seed == b.seed


def test_file_made_for_other_settings_is_refused(tmp_path):
    path = tmp_path / "demos.hdf5"
    write_demo_file(path, _episodes(), SPEC, "x")
    other = DemoSpec(**{**SPEC.__dict__, "num_demos": 50})
    with pytest.raises(DemoFileError, match="made for other settings") as info:
        read_demo_file(path, other)
    assert "\n" not in str(info.value)


def test_corrupt_file_is_refused_in_one_line(tmp_path):
    path = tmp_path / "demos.hdf5"
    write_demo_file(path, _episodes(), SPEC, "x")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 3])
    with pytest.raises(DemoFileError, match="corrupt") as info:
        read_demo_file(path, SPEC)
    assert "\n" not in str(info.value) and str(path) in str(info.value)


def test_missing_actions_is_refused(tmp_path):
    path = tmp_path / "demos.hdf5"
    write_demo_file(path, _episodes(), SPEC, "x")
    with h5py.File(path, "a") as f:
        del f["data/demo_0/actions"]
    with pytest.raises(DemoFileError, match="missing 'actions'"):
        read_demo_file(path, SPEC)


def test_generation_is_cached_and_reused(tmp_path, monkeypatch):
    from suites import get_suite

    suite = get_suite("metaworld")
    spec = DemoSpec(suite="metaworld", suite_version=suite.version("reach-v3"), task="reach-v3", split="demo",
                    num_demos=2, max_episode_steps=150)
    first = load_or_generate(suite, spec, tmp_path, progress=False)
    assert len(first) == 2 and all(len(e) > 5 for e in first)
    files = list((tmp_path / "demos" / "metaworld").glob("*.hdf5"))
    assert [f.name for f in files] == [spec.filename()]

    def fail(*args, **kwargs):
        raise AssertionError("the cache was not reused")

    monkeypatch.setattr("harness.data.demos.generate_demos", fail)
    second = load_or_generate(suite, spec, tmp_path, progress=False)
    np.testing.assert_array_equal(first[1].actions, second[1].actions)


def test_same_seed_same_demos(tmp_path):
    from harness.data.demos import generate_demos
    from suites import get_suite

    suite = get_suite("metaworld")
    spec = DemoSpec(suite="metaworld", suite_version=suite.version("push-v3"), task="push-v3", split="demo",
                    num_demos=1, max_episode_steps=150)
    a, b = generate_demos(suite, spec, progress=False), generate_demos(suite, spec, progress=False)
    np.testing.assert_array_equal(a[0].obs["state"], b[0].obs["state"])


def test_demo_files_made_in_worker_processes_equal_those_made_in_this_one(tmp_path, monkeypatch,
                                                                           capsys):
    import harness.run.execute
    from harness.data.prepare import missing_demo_jobs
    from harness.run.execute import make_missing_demos
    from harness.run.plan import plan
    from suites import get_suite

    monkeypatch.setattr(harness.run.execute, "available_cores", lambda: 2)  # CI may have one
    workers = plan(["PROFILE=tiny", "executor=local", f"cache_dir={tmp_path / 'workers'}"]).cfg
    here = plan(["PROFILE=tiny", "executor=serial", f"cache_dir={tmp_path / 'here'}"]).cfg
    suite = get_suite(workers.suite)
    jobs = missing_demo_jobs(workers, suite)
    assert len(jobs) == 2 * len(workers.foundation_tasks + workers.stream_tasks)

    make_missing_demos(here, suite)  # the serial executor leaves them to this process
    assert len(missing_demo_jobs(here, suite)) == len(jobs)
    make_missing_demos(workers, suite)
    assert missing_demo_jobs(workers, suite) == []
    assert capsys.readouterr().out.count("[retain] demos ") == len(jobs)
    for job in jobs:
        made_here = load_or_generate(suite, job.spec, tmp_path / "here", progress=False)
        _, made_there = read_demo_file(tmp_path / "workers" / "demos" / job.spec.suite
                                       / job.spec.filename(), job.spec)
        assert [e.seed for e in made_here] == [e.seed for e in made_there]
        for a, b in zip(made_here, made_there):
            np.testing.assert_array_equal(a.actions, b.actions)
            np.testing.assert_array_equal(a.obs["state"], b.obs["state"])
