"""Studies (harness/run/study.py): the regimes study's parts expand to the jobs it promises without
running anything, bad names fail in one line, the breadth benchmarks are nested on one stream,
and a tiny study runs end to end and, run again, trains nothing."""

import subprocess
import sys
from pathlib import Path

import pytest
import torch

from harness.common.errors import RetainError
from harness.config.benchmark import load_benchmark
from harness.run.study import load_study, plan_part, stages_done, study

ROOT = Path(__file__).resolve().parents[1]
METHOD_LABELS = ["sft", "sft[lr=0.0001]", "sft[lr=3e-05]", "consft", "consft[variant=dft]",
                 "consft[variant=ratio]", "er"]


def test_regimes_parts_expand_to_their_jobs(tmp_path):
    s = load_study("regimes")
    assert list(s.parts) == ["mw-broad-6", "mw-broad-20", "mw-broad", "libero-broad",
                             "mw-broad-6-pi0"]
    extra = [f"results_dir={tmp_path}/results", f"cache_dir={tmp_path}/cache"]
    for name, bench in (("mw-broad-6", "mw-broad-6"), ("mw-broad", "mw-broad")):
        pp = plan_part(s.parts[name], extra)
        assert pp.experiment == bench
        assert [v.label for v in pp.plan.variants] == METHOD_LABELS
        assert len(pp.jobs) == 21 and len({key for *_, key in pp.jobs}) == 21
        assert sorted({seed for seed, *_ in pp.jobs}) == [0, 1, 2]
        by_label = {v.label: v for v in pp.plan.variants}
        assert [by_label[f"sft{x}"].cfg.lr for x in ("", "[lr=0.0001]", "[lr=3e-05]")] == \
            [3e-4, 1e-4, 3e-5]
        assert by_label["consft[variant=ratio]"].method.config.variant == "ratio"
        assert by_label["consft"].method.config.variant == "paper"
        assert by_label["er"].cfg.lr == 3e-4 and by_label["er"].method.name == "er"
    pi0 = plan_part(s.parts["mw-broad-6-pi0"], extra)
    assert pi0.experiment == "mw-broad-6-pi0"
    assert [v.label for v in pi0.plan.variants] == ["sft[policy=pi0]", "consft[policy=pi0]"]
    assert len(pi0.jobs) == 6 and all(v.cfg.policy == "pi0" for _, v, _ in pi0.jobs)
    assert not (tmp_path / "results").exists() and not (tmp_path / "cache").exists()


def test_a_seed_piece_plans_the_same_jobs_as_the_whole_part(tmp_path):
    """SEED=1 SEEDS=1 plans seed 1's jobs only, under the keys the whole part gives them (so a
    piece's finished jobs count as the part's), and a piece outside the part's seeds fails."""
    part = load_study("regimes").parts["mw-broad"]
    extra = [f"results_dir={tmp_path}/results", f"cache_dir={tmp_path}/cache"]
    whole = plan_part(part, extra)
    piece = plan_part(part, extra, part.seed_piece(1, 1))
    assert [seed for seed, *_ in piece.jobs] == [1] * 7
    assert [key for *_, key in piece.jobs] == [key for seed, _, key in whole.jobs if seed == 1]
    assert part.seed_piece(1, None) == range(1, 3)
    for first, count in ((3, 1), (2, 2), (0, 0), (-1, 1)):
        with pytest.raises(RetainError, match=f"SEED={first} SEEDS={count} .*'mw-broad'.* 0-2"):
            part.seed_piece(first, count)


def test_libero_part_plans_on_real_libero_tasks(tmp_path):
    pp = plan_part(load_study("regimes").parts["libero-broad"], [f"results_dir={tmp_path}"])
    assert len(pp.jobs) == 21 and pp.plan.cfg.suite == "libero"
    assert len(pp.plan.cfg.stream_tasks) == 10


def test_breadth_benchmarks_are_nested_and_share_the_stream():
    from suites import get_suite

    six, twenty, broad = (load_benchmark(n) for n in ("mw-broad-6", "mw-broad-20", "mw-broad"))
    assert six.stream_tasks == twenty.stream_tasks == broad.stream_tasks
    assert len(six.stream_tasks) == 5
    assert (len(six.foundation_tasks), len(twenty.foundation_tasks)) == (6, 20)
    assert twenty.foundation_tasks[:6] == six.foundation_tasks
    assert broad.foundation_tasks[:20] == twenty.foundation_tasks
    assert len(set(broad.foundation_tasks)) == len(broad.foundation_tasks)
    assert not set(broad.foundation_tasks) & set(broad.stream_tasks)
    # every Meta-World task with a scripted expert, less the stream and push-back (its expert
    # succeeds on 78% of episodes within 300 steps)
    everything = set(get_suite("metaworld").task_names())
    assert everything - set(broad.foundation_tasks) - set(broad.stream_tasks) == {"push-back-v3"}
    for cfg in (six, twenty):  # the same stream budget and evaluation: only breadth differs
        for key in ("eval_episodes", "max_episode_steps", "steps_per_task", "demos_per_task",
                    "lr", "batch_size", "policy_size"):
            assert getattr(cfg, key) == getattr(broad, key), key


@pytest.mark.parametrize("args, expected", [
    (["STUDY=nope"], ["'nope'", "regimes"]),
    (["STUDY=regimes", "PART=mw-broad-7"], ["'mw-broad-7'", "mw-broad-6", "libero-broad"]),
    (["STUDY=regimes", "lr=0.1"], ["'lr'", "executor"]),
    (["PART=mw-broad-6"], ["STUDY=", "regimes"]),
    (["STUDY=regimes", "PART=mw-broad-6", "SEED=2", "SEEDS=2"], ["SEED=2 SEEDS=2", "0-2"]),
])
def test_bad_study_input_is_one_line(tmp_path, args, expected):
    cmd = [sys.executable, "-m", "harness", "study", f"results_dir={tmp_path}/results", *args]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=120, cwd=ROOT)
    assert proc.returncode == 2
    lines = [line for line in proc.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    for text in expected:
        assert text in lines[0]
    assert not (tmp_path / "results").exists()


def test_part_runs_must_share_their_foundation(tmp_path):
    path = tmp_path / "mixed.yaml"
    path.write_text("seeds: 1\nparts:\n  a: {bench: mw-quick, runs: [sft, sft policy=pi0]}\n")
    with pytest.raises(RetainError, match="'policy'.*part of its own"):
        plan_part(load_study(str(path)).parts["a"], [])


TINY_STUDY = """\
name: tiny
seeds: 1
profile: tiny
runs: [sft, consft variant=dft]
parts:
  quick: {bench: mw-quick}
"""


def test_tiny_study_runs_then_resumes_without_training(tmp_path, capsys, forbid_retraining):
    path = tmp_path / "tiny.yaml"
    path.write_text(TINY_STUDY)
    args = [f"STUDY={path}", f"results_dir={tmp_path}/results", f"cache_dir={tmp_path}/cache",
            "progress=false", "eval_workers=1", "executor=serial"]
    assert study(args + ["DRY=1"]) == 0
    assert "quick: mw-quick-tiny, 2 runs x 1 seeds = 2 jobs: 0 finished, 0 started, 2 to do" \
        in capsys.readouterr().out
    # a checkpoint left by other settings (an earlier version of the benchmark) is no start:
    # the listing says "to do", and the run starts over
    base = tmp_path / "results" / "mw-quick-tiny"
    stale = base / "sft" / "seed0" / "stages" / "stage_1.pt"
    stale.parent.mkdir(parents=True)
    torch.save({"run_key": "other settings"}, stale)
    assert study(args + ["DRY=1"]) == 0
    assert "2 jobs: 0 finished, 0 started, 2 to do" in capsys.readouterr().out
    assert study(args) == 0
    out = capsys.readouterr().out
    assert "[study] part quick: 2 of 2 jobs to run (0 finished)" in out
    assert "was written with other settings; starting this run over" in out
    pp = plan_part(load_study(str(path)).parts["quick"], args[1:4])
    assert [stages_done(seed, v) for seed, v, _ in pp.jobs] == [2, 2]  # tiny's two stream stages
    assert all(len(v.cfg.stream_tasks) == 2 for _, v, _ in pp.jobs)
    matrices = {label: (base / label / "seed0" / "success_matrix.csv").read_text()
                for label in ("sft", "consft[variant=dft]")}
    assert (base / "report" / "summary.md").exists()

    forbid_retraining()
    assert study(args) == 0
    assert "all 2 jobs finished; nothing to run" in capsys.readouterr().out
    assert study(args + ["DRY=1"]) == 0
    listing = capsys.readouterr().out
    assert "2 jobs: 2 finished, 0 started, 0 to do" in listing
    assert "finished: sft seeds 0; consft[variant=dft] seeds 0" in listing
    for label, text in matrices.items():
        assert (base / label / "seed0" / "success_matrix.csv").read_text() == text
