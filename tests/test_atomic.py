"""A folder written with atomic_dir is found whole or not at all."""

import pytest

from harness.common.atomic import atomic_dir


def test_a_folder_replaces_the_old_one_only_when_written_whole(tmp_path):
    target = tmp_path / "site"
    with atomic_dir(target) as part:
        (part / "a.txt").write_text("first")
    assert (target / "a.txt").read_text() == "first"

    with pytest.raises(RuntimeError), atomic_dir(target) as part:
        (part / "a.txt").write_text("half")
        raise RuntimeError("killed mid-write")
    assert (target / "a.txt").read_text() == "first"  # the old folder stands

    with atomic_dir(target) as part:
        (part / "b.txt").write_text("second")
    assert sorted(p.name for p in target.iterdir()) == ["b.txt"]  # nothing of the old one
    assert [p.name for p in tmp_path.iterdir()] == ["site"]  # no temporary folder left
