"""A LeRobot checkpoint as a user brings one, run the way a user runs it: folders written by
LeRobot's own API in lerobot-train's layout (tests/lerobot_checkpoints.py), and every command a
fresh `python -m harness` process, which imports nothing a test imported first (LeRobot's config
registry is empty there until its policy modules load).

The demos come from a small LeRobot dataset written here (`demos_dir=`), so no expert renders
cameras: the runs cost their evaluation's few rendered steps, not minutes of demos."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from safetensors.torch import load_file, save_file

from tests.lerobot_checkpoints import write_lerobot_checkpoint, write_synthetic_dataset

ROOT = Path(__file__).resolve().parents[1]
PX, STATE, ACTION = 32, 39, 4  # Meta-World's state and actions, small camera images
TASKS = ("reach-v3", "push-v3", "drawer-close-v3", "window-close-v3")  # mw-quick at PROFILE=tiny
POST_STATS = "policy_postprocessor_step_0_unnormalizer_processor.safetensors"
PRE_STATS = "policy_preprocessor_step_5_normalizer_processor.safetensors"


def harness(*args, timeout=900, **env_vars) -> subprocess.CompletedProcess:
    """`python -m harness ARGS` in a fresh process, from the repository's root."""
    env = {k: v for k, v in os.environ.items() if k not in ("RAY_ADDRESS", "MLFLOW_TRACKING_URI")}
    return subprocess.run([sys.executable, "-m", "harness", *args], capture_output=True,
                          text=True, timeout=timeout, cwd=ROOT,
                          env={**env, "HF_HUB_OFFLINE": "1", "PYTHONUNBUFFERED": "1", **env_vars})


def one_line_error(proc: subprocess.CompletedProcess) -> str:
    assert proc.returncode != 0
    lines = [line for line in (proc.stdout + proc.stderr).splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), lines[-5:]
    return lines[0]


def fine_tune(base: Path, out: Path, seed: int, scale: float, shift: float) -> Path:
    """A fine-tune of `base` as a user's own script makes one: the base's folder with every
    other weight tensor moved (LeRobot's safetensors API) and its processors' action mean
    shifted by `shift` (a new dataset's statistics)."""
    shutil.copytree(base, out)
    weights = load_file(out / "model.safetensors")
    g = torch.Generator().manual_seed(seed)
    for i, name in enumerate(sorted(weights)):
        if i % 2 == 0 and weights[name].is_floating_point():
            weights[name] = weights[name] + scale * torch.randn(weights[name].shape, generator=g)
    save_file(weights, out / "model.safetensors", metadata={"format": "pt"})
    shift_action_mean(out, shift)
    return out


def shift_action_mean(folder: Path, shift: float) -> None:
    """Both processors' saved action mean moved by `shift`, as another dataset's would be."""
    for name in (PRE_STATS, POST_STATS):
        stats = load_file(folder / name)
        stats["action.mean"] = stats["action.mean"] + shift
        save_file(stats, folder / name)


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    root = tmp_path_factory.mktemp("lerobot_cli")
    base = write_lerobot_checkpoint("smolvla", root / "base", STATE, ACTION, PX, step=20,
                                    max_state_dim=STATE)
    stages = [fine_tune(base, root / f"ft{i}" / "pretrained_model", seed=i, scale=0.05 * i,
                        shift=0.5 * i) for i in (1, 2)]
    return {"root": root, "base": root / "base" / "checkpoints" / "last", "stages": stages,
            "demos": write_synthetic_dataset(root / "dataset", "metaworld", list(TASKS), PX)}


def tiny_run(setup, results: Path, *args) -> list[str]:
    return ["bench", "PROFILE=tiny", "policy=lerobot_smolvla", f"policy_path={setup['base']}",
            f"demos_dir={setup['demos']}", "demos_per_task=1", "eval_episodes=1",
            "eval_step_cap=8", "eval_workers=1", f"results_dir={results}",
            f"cache_dir={setup['root']}/cache", *args]


def test_a_lerobot_checkpoint_and_its_fine_tunes_run_end_to_end_in_a_fresh_process(setup):
    """SFT from a lerobot-train checkpoint (`checkpoints/last`) beside the user's two fine-tunes
    measured as stages (`METHOD=checkpoints`), then `make report`'s command: both rows, the
    fine-tunes' update sparsity equal to a direct diff of the weight files."""
    results = setup["root"] / "results"
    paths = ",".join(str(p) for p in setup["stages"])
    proc = harness(*tiny_run(setup, results, "METHOD=sft,checkpoints", f"stage_paths={paths}",
                             "label=my-ft", "executor=serial"), RETAIN_PROGRESS_EVERY="0")
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    # progress in a log: a line per step and per episode here (the interval is 0)
    assert "seed 0: stage 2/2 (window-close-v3): 100%| 10/10 steps [" in proc.stdout
    assert "evaluation (eval) of 4 tasks: 100%| 4/4 episodes [" in proc.stdout
    bench = results / "mw-quick-tiny"
    labels = sorted(p.name for p in bench.iterdir() if p.is_dir())
    assert len(labels) == 2 and labels[0].startswith("my-ft[") and labels[1].startswith("sft[")
    assert not any(str(setup["root"]) in label for label in labels)  # no path in a label
    mine = next(bench.glob("my-ft*/seed0"))
    metrics = json.loads((mine / "metrics.json").read_text())
    stages = metrics["stages"]
    assert len(stages) == 3 and all(np.isnan(s["train_loss"]) for s in stages)  # nothing trained
    config = (mine / "config.yaml").read_text()
    assert str(setup["stages"][0]) in config  # the full paths stay in the config

    # update sparsity against the base: the run's figure is a direct diff of the two files
    base = load_file(setup["base"] / "pretrained_model" / "model.safetensors")
    last = load_file(setup["stages"][1] / "model.safetensors")
    rows = {r["layer"]: r for r in _csv(mine / "updates_per_layer.csv")}
    changed = total = 0
    for layer, row in rows.items():
        name = layer.removeprefix("model.")
        w0, w = base[name].double(), last[name].double()
        rms = w0.pow(2).mean().sqrt().clamp_min(1e-12)
        frac = float(((w - w0).abs() / rms > 1e-2).double().mean())
        assert frac == pytest.approx(float(row["frac_changed_rho0.01"]), abs=1e-9), layer
        changed, total = changed + frac * w0.numel(), total + w0.numel()
    assert 0 < changed / total < 1  # every other tensor moved
    assert metrics["metrics"]["update_frac_changed_rho0.01"] == pytest.approx(changed / total)

    report = subprocess.run([sys.executable, "-m", "harness.report", "EXPERIMENT=mw-quick-tiny",
                             f"results_dir={results}"], capture_output=True, text=True,
                            cwd=ROOT, timeout=300)
    assert report.returncode == 0, report.stderr[-3000:]
    table = (results / "mw-quick-tiny" / "report" / "summary.md").read_text()
    assert "| my-ft" in table and "| sft" in table  # a row each, side by side


def _csv(path: Path) -> list[dict]:
    import csv

    with open(path) as f:
        return list(csv.DictReader(f))


def test_each_stage_is_evaluated_with_its_own_folders_statistics(setup, tmp_path):
    """A fine-tune's saved action statistics are the ones its actions come out with: a folder
    whose saved action mean is 0.5 higher predicts actions 0.5 higher, from the same weights."""
    from policies import get_policy

    cls = get_policy("lerobot_smolvla")
    features = (("state", "observation.state"), ("agentview_rgb", "observation.images.image"),
                ("eye_in_hand_rgb", "observation.images.wrist_image"))
    shifted = tmp_path / "shifted"
    shutil.copytree(setup["base"] / "pretrained_model", shifted)
    shift_action_mean(shifted, 0.5)

    def actions(path):
        config = cls.Config(state_dim=STATE, action_dim=ACTION, size="tiny", chunk_size=4,
                            n_action_steps=4, image_keys=("agentview_rgb", "eye_in_hand_rgb"),
                            image_size=PX, instructions=("reach the goal",), path=str(path),
                            features=features)
        policy = cls(config)
        g = torch.Generator().manual_seed(0)
        batch = {"state": torch.randn(2, STATE, generator=g),
                 "instruction_id": torch.zeros(2, dtype=torch.long),
                 **{k: torch.randint(0, 256, (2, PX, PX, 3), dtype=torch.uint8, generator=g)
                    for k in config.image_keys}}
        noise = torch.randn(2, 4, policy.noise_dim, generator=g)
        return policy, policy.sample_actions(batch, noise=noise)

    base_policy, before = actions(setup["base"])
    moved_policy, after = actions(shifted)
    assert torch.allclose(after - before, torch.full_like(before, 0.5), atol=1e-5)
    # and loading that folder into the base's policy, as a stage does, gives its actions too
    base_policy.load_checkpoint_weights(str(shifted))
    g = torch.Generator().manual_seed(0)
    batch = {"state": torch.randn(2, STATE, generator=g),
             "instruction_id": torch.zeros(2, dtype=torch.long),
             **{k: torch.randint(0, 256, (2, PX, PX, 3), dtype=torch.uint8, generator=g)
                for k in ("agentview_rgb", "eye_in_hand_rgb")}}
    noise = torch.randn(2, 4, base_policy.noise_dim, generator=g)
    assert torch.allclose(base_policy.sample_actions(batch, noise=noise), after, atol=1e-6)


PLAN = """
import sys
from harness.run.plan import plan
print(plan(sys.argv[1:]).variants[0].label)
"""


@pytest.mark.parametrize("kind", ["pi0", "pi05"])
def test_pi0_and_pi05_checkpoints_pass_the_plan_and_its_dry_run_in_a_fresh_process(kind,
                                                                                   tmp_path):
    """The plan, with its policy dry run (the loss and one action chunk on the suite's shapes),
    on a PI0 / PI0.5 written by LeRobot's API, in a process that imported nothing before; the
    label names lerobot-train's run and step and the weights' digest, not the path."""
    write_lerobot_checkpoint(kind, tmp_path / "my_run", STATE, ACTION, PX, max_state_dim=STATE)
    path = tmp_path / "my_run" / "checkpoints" / "000010"  # lerobot-train's step folder
    proc = subprocess.run([sys.executable, "-c", PLAN, "PROFILE=tiny", f"policy=lerobot_{kind}",
                           f"policy_path={path}"], capture_output=True, text=True, cwd=ROOT,
                          timeout=300, env={**os.environ, "HF_HUB_OFFLINE": "1"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    label = proc.stdout.strip().splitlines()[-1]
    assert label.startswith(f"sft[policy=lerobot_{kind} policy_path=my_run-000010@"), label
    assert str(tmp_path) not in label


def test_a_policy_that_fails_on_the_suites_shapes_is_refused_at_plan_time(tmp_path):
    """Whatever breaks on one sample (here a user's policy that returns the wrong chunk) is one
    line naming the policy and the shapes, before any demo."""
    from harness.common.errors import RetainError
    from harness.run.plan import plan

    policy_file = tmp_path / "short_chunk.py"
    policy_file.write_text(
        "from dataclasses import dataclass\n"
        "from policies import FlowMatchingConfig, FlowMatchingPolicy\n"
        "@dataclass(frozen=True)\n"
        "class ShortChunkConfig(FlowMatchingConfig):\n"
        "    pass\n"
        "class ShortChunk(FlowMatchingPolicy):\n"
        "    Config = ShortChunkConfig\n"
        "    def sample_actions(self, batch, noise=None, generator=None):\n"
        "        return super().sample_actions(batch, noise, generator)[:, :1]\n")
    with pytest.raises(RetainError) as err:
        plan(["PROFILE=tiny", f"policy={policy_file}:ShortChunk"])
    message = str(err.value)
    assert "samples actions of shape [1, 1, 4]; suite 'metaworld' needs [1, 4, 4]" in message
    assert "\n" not in message


@pytest.mark.parametrize("args, expected", [
    (["policy=mlp", "policy_path={base}"], "policy 'mlp' takes no policy_path"),
    (["policy=lerobot_smolvla", "policy_path={narrow}"],
     "pads its state to max_state_dim=32, and suite 'metaworld''s state is 39-D"),
    (["policy=lerobot_pi0", "policy_size=default"], "lerobot_pi0 at policy_size=default needs"),
    (["policy=lerobot_pi05", "policy_size=default"], "lerobot_pi05 at policy_size=default needs"),
    (["policy=lerobot_smolvla", "policy_size=default"],
     "lerobot_smolvla at policy_size=default needs"),
])
def test_refusals_are_one_line_in_seconds_in_a_fresh_process(args, expected, setup, tmp_path):
    narrow = setup["root"] / "narrow"
    if not narrow.exists():  # LeRobot's default max_state_dim of 32, for a 39-D state
        write_lerobot_checkpoint("smolvla", narrow, STATE, ACTION, PX)
    paths = {"base": setup["base"], "narrow": narrow / "checkpoints" / "last",
             "ft1": setup["stages"][0]}
    args = [a.format(**paths) for a in args]
    proc = harness("bench", "PROFILE=tiny", f"results_dir={tmp_path}/r", f"cache_dir={tmp_path}/c",
                   *args, timeout=120)
    line = one_line_error(proc)
    assert expected in line, line
    assert not (tmp_path / "c").exists()  # refused before any demo


def test_fine_tunes_that_do_not_fit_their_base_are_refused_at_plan_time(setup):
    from harness.common.errors import RetainError
    from harness.run.plan import plan

    narrow = setup["root"] / "narrow"
    if not narrow.exists():
        write_lerobot_checkpoint("smolvla", narrow, STATE, ACTION, PX)
    ft1 = setup["stages"][0]
    base = ["PROFILE=tiny", "policy=lerobot_smolvla", f"policy_path={setup['base']}",
            "METHOD=checkpoints"]
    cases = [([f"stage_paths={ft1}"],  # one folder for two stages
              "stage_paths names 1 folders; the benchmark has 2 stream stages"),
             ([f"stage_paths={ft1},{narrow / 'checkpoints' / 'last'}"],  # another state width
              "stage 2's checkpoint"),
             ([f"stage_paths={ft1},{ft1}", "policy_path=", "policy=mlp"],
              "METHOD=checkpoints measures fine-tunes of a LeRobot checkpoint"),
             (["label=my ft", f"stage_paths={ft1},{ft1}"], "bad value 'my ft' for label")]
    for args, expected in cases:
        with pytest.raises(RetainError) as err:
            plan([*base, *args])
        assert expected in str(err.value) and "\n" not in str(err.value), str(err.value)
    with pytest.raises(RetainError, match="has weights of another architecture than the base's"):
        plan([*base, f"stage_paths={ft1},{narrow / 'checkpoints' / 'last'}"])


@pytest.mark.slow  # two more fresh runs of a minute or more each
@pytest.mark.parametrize("kind", ["pi0", "pi05"])
def test_pi0_and_pi05_checkpoints_run_end_to_end_in_a_fresh_process(kind, setup, tmp_path):
    """SFT from a PI0 / PI0.5 written by LeRobot's API (lerobot-train's `checkpoints/last`)."""
    write_lerobot_checkpoint(kind, tmp_path / "run", STATE, ACTION, PX, max_state_dim=STATE)
    args = [a for a in tiny_run(setup, tmp_path / "results", "METHOD=sft")
            if not a.startswith(("policy", "cache_dir"))]
    proc = harness(*args, f"policy=lerobot_{kind}", f"cache_dir={tmp_path}/cache",
                   f"policy_path={tmp_path / 'run' / 'checkpoints' / 'last'}")
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    run = next((tmp_path / "results" / "mw-quick-tiny").glob("sft*/seed0"))
    stages = json.loads((run / "metrics.json").read_text())["stages"]
    assert len(stages) == 3 and np.isnan(stages[0]["train_loss"])  # the checkpoint, not retrained
    assert all(np.isfinite(s["train_loss"]) for s in stages[1:])
    assert f"policy: lerobot_{kind}" in (run / "config.yaml").read_text()
