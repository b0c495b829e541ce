"""`make bench-envs`: the memory and build time of a benchmark's simulators, one per task, and on
LIBERO the control step's speed on each path beside its physics."""

from __future__ import annotations

import re

from harness.perf.throughput import bench_envs, main, nudged_drift, sweep_actions


def test_bench_envs_builds_the_first_tasks_and_prints_their_memory(capsys):
    bench_envs("mw-quick", n_tasks=3)
    line = capsys.readouterr().out.strip()
    found = re.fullmatch(r"3 of mw-quick's metaworld simulators in one process, no cameras: "
                         r"([\d.]+) GB resident; (-?\d+) MB and ([\d.]+) s to build each after "
                         r"the first", line)
    assert found, line
    assert float(found[1]) > 0.1  # the process itself, at least


def test_bench_envs_command_line_names_an_unknown_benchmark(capsys):
    assert main(["envs", "--bench", "no-such-bench", "--tasks", "1"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: unknown benchmark 'no-such-bench'; valid: ") and "\n" not in err
    assert "libero-paper" in err


def test_bench_envs_on_libero_prints_the_control_step_beside_its_physics(capsys):
    """On LIBERO the memory line is followed by the first task's control step on each path,
    how far a last-bit change in its controls moves it, then a fresh scene's reset both ways."""
    assert main(["envs", "--bench", "libero-spatial", "--tasks", "1", "--steps", "2",
                 "--resets", "1", "--view-frames", "0"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 7 and lines[0].startswith("1 of libero-spatial's libero simulators")
    assert re.fullmatch(r"control step of \w+ \(2 seeded random steps from init state 0\), "
                        r"no cameras:", lines[1]), lines[1]
    rows = [re.fullmatch(r"  (.+?) +([\d.]+) steps/s +([\d.]+)x the physics' time", line)
            for line in lines[2:5]]
    assert all(rows), lines[2:5]
    assert [row[1] for row in rows] == ["physics alone (mj_step x 25)", "robosuite's env.step",
                                        "fast path (suites/libero/fast_step.py)"]
    assert float(rows[0][3]) == 1.0 and all(float(row[2]) > 0 for row in rows)
    assert re.fullmatch(r"  controls off by a relative 1e-15 at every substep, the joint positions "
                        r"2 steps later: \S+ apart \(these random steps\), \S+ \(a sweep into "
                        r"the table and objects\)", lines[5]), lines[5]
    resets = re.fullmatch(r"  a fresh scene's reset \(1 demo keys\): robosuite's reload (\d+) ms, "
                          r"in place (\d+) ms", lines[6])
    assert resets and int(resets[1]) > 0, lines[6]


def test_a_nudge_in_the_controls_moves_the_trajectory_and_none_leaves_it_alone():
    """nudged_drift compares two rollouts of one env: unscaled, they are the same to the bit."""
    from suites.libero.env import LiberoTaskEnv
    from suites.libero.tasks import all_tasks, suite_tasks

    env = LiberoTaskEnv(all_tasks()[suite_tasks("libero_object")[0]])
    try:
        acts = sweep_actions(10)
        assert nudged_drift(env, acts, nudge=0.0) == 0.0
        assert 0.0 < nudged_drift(env, acts, nudge=1e-6) < 1e-3
        assert "step2" not in vars(env.env.sim)  # the class's method again
    finally:
        env.close()


def test_bench_views_prints_both_render_modes_and_their_difference(capsys):
    """The camera-view table: a view's milliseconds both ways and fast's image difference."""
    from harness.perf.views import measure_views, print_views

    figures = measure_views("metaworld", ["reach-v3", "pick-place-v3"], frames=8, image_size=64)
    assert figures.frames == 8 and all(ms > 0 for ms in figures.ms.values())
    assert 0 < figures.mean_abs.mean() < 20 and 0 < figures.max_abs.max() <= 255
    assert 15 < figures.psnr < 60
    print_views([figures], 64)
    row = capsys.readouterr().out.strip().splitlines()[-1]
    assert re.fullmatch(r"\| metaworld \| 8 \| [\d.]+ \| [\d.]+ \| [\d.]+x \| [\d., ]+ \| "
                        r"[\d, ]+ \| [\d.]+ \|", row), row
