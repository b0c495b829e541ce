"""`make bench-envs`: the memory and build time of a benchmark's simulators, one per task."""

from __future__ import annotations

import re

from harness.perf.throughput import bench_envs, main


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
