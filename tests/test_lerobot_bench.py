"""LeRobot's PI0 through whole benchmark runs: the paper's LIBERO protocol with LIBERO's two
cameras from a random init pre-trained as the foundation, and a checkpoint that is the
foundation itself (evaluated at stage 0, never retrained)."""

import json

import numpy as np
import pytest
import torch

from harness.run.cli import main
from policies import get_policy
from suites.base import CAMERA_KEYS


# LIBERO's cameras render in software here, about 105 ms a view at any size: this run's eight
# expert demos with two views a step are 5-9 minutes of a core, past make test's budget
@pytest.mark.slow
def test_libero_paper_tiny_with_lerobots_pi0_on_both_cameras(tmp_path):
    # LIBERO renders its two cameras at about 70 ms a step on a CPU core (Mesa): tiny's two base
    # and two target tasks with one demo each, one evaluation and check episode, and episodes
    # cut at 15 steps keep it to a few minutes
    args = ["bench", "BENCH=libero-paper", "PROFILE=tiny", "METHOD=consft",
            "policy=lerobot_pi0", "image_size=32", f"results_dir={tmp_path}/results",
            f"cache_dir={tmp_path}/cache", "progress=false", "eval_workers=1",
            "demos_per_task=1", "eval_episodes=1", "check_episodes=1", "eval_step_cap=15"]
    assert main(args) == 0
    runs = list((tmp_path / "results" / "libero-paper-tiny").glob("consft*/seed0"))
    assert len(runs) == 1
    run = runs[0]
    for name in ("success_matrix.csv", "metrics.json", "config.yaml", "success_matrix.png"):
        assert (run / name).stat().st_size > 0, name
    config = (run / "config.yaml").read_text()
    assert "policy: lerobot_pi0" in config and "cameras: true" in config
    lines = (run / "success_matrix.csv").read_text().splitlines()
    assert len(lines) == 1 + 2  # a header, stage 0 and the one grouped Spatial stage
    metrics = json.loads((run / "metrics.json").read_text())["metrics"]
    assert np.isfinite(metrics["heldout_loss_ratio"]) and metrics["heldout_loss_ratio"] > 0
    from harness.data.demos import read_demo_file  # the demos carry LIBERO's two cameras

    demo = next((tmp_path / "cache" / "demos" / "libero").glob("*.hdf5"))
    spec, episodes = read_demo_file(demo)
    assert set(CAMERA_KEYS) <= set(episodes[0].obs)
    assert episodes[0].obs[CAMERA_KEYS[0]].shape[1:] == (32, 32, 3)


def test_libero_paper_tiny_with_lerobots_pi0_on_both_cameras_at_fast_render(tmp_path):
    """The same run in make test: LIBERO's views at render=fast (about 15 ms a view against
    85-150), and the demos from a small LeRobot dataset of the tiny benchmark's tasks rather
    than the experts' rendered ones, so that what remains is LeRobot's PI0 pre-trained, fine-tuned
    and rolled out in LIBERO on both cameras."""
    from harness.config.benchmark import resolve
    from tests.lerobot_checkpoints import write_synthetic_dataset

    tasks = resolve(["BENCH=libero-paper", "PROFILE=tiny"]).all_tasks()
    demos = write_synthetic_dataset(tmp_path / "dataset", "libero", tasks, 32)
    args = ["bench", "BENCH=libero-paper", "PROFILE=tiny", "METHOD=consft",
            "policy=lerobot_pi0", "image_size=32", "render=fast", f"demos_dir={demos}",
            f"results_dir={tmp_path}/results", f"cache_dir={tmp_path}/cache", "progress=false",
            "executor=serial", "eval_workers=1", "demos_per_task=1", "eval_episodes=1",
            "check_episodes=1", "eval_step_cap=10"]
    assert main(args) == 0
    run = next((tmp_path / "results" / "libero-paper-tiny").glob("consft*/seed0"))
    config = (run / "config.yaml").read_text()
    assert "policy: lerobot_pi0" in config and "render: fast" in config
    stages = json.loads((run / "metrics.json").read_text())["stages"]
    assert len(stages) == 2 and all(np.isfinite(s["train_loss"]) for s in stages)
    rows = [line.split(",")[2:] for line in (run / "success_matrix.csv").read_text().splitlines()[1:]]
    assert len(rows) == 2 and all(0 <= float(v) <= 1 for row in rows for v in row)  # rolled out


@pytest.fixture
def checkpoint(tmp_path):
    """A tiny PI0 for Meta-World (39-D state, 4-D actions) saved as a LeRobot folder."""
    cls = get_policy("lerobot_pi0")
    torch.manual_seed(0)
    policy = cls(cls.Config(state_dim=39, action_dim=4, size="tiny", chunk_size=4,
                            n_action_steps=4, image_keys=CAMERA_KEYS, image_size=32,
                            instructions=("a",)))
    return policy.save_folder(tmp_path / "ckpt")


@pytest.mark.slow  # Meta-World's cameras, rendered in software: minutes
def test_a_checkpoint_is_the_foundation_evaluated_never_retrained(checkpoint, tmp_path,
                                                                   monkeypatch):
    import harness.protocol.foundation as foundation

    def fail(*args, **kwargs):
        raise AssertionError("the checkpoint was retrained")

    monkeypatch.setattr(foundation, "train_stage", fail)
    args = ["bench", "PROFILE=tiny", "METHOD=sft", f"policy_path={checkpoint}",
            "policy=lerobot_pi0", f"results_dir={tmp_path}/results",
            f"cache_dir={tmp_path}/cache", "progress=false", "eval_workers=1",
            "demos_per_task=1", "eval_episodes=1", "eval_step_cap=15"]  # cameras: slow on a CPU
    assert main(args) == 0
    run = next((tmp_path / "results" / "mw-quick-tiny").glob("sft*/seed0"))
    stages = json.loads((run / "metrics.json").read_text())["stages"]
    assert len(stages) == 3 and np.isnan(stages[0]["train_loss"])  # stage 0: not trained here
    from harness.config.benchmark import resolve
    from harness.protocol.foundation import foundation_key
    from suites import get_suite

    cfg = resolve(["PROFILE=tiny", "policy=lerobot_pi0", f"policy_path={checkpoint}",
                   "cameras=true", "image_size=32"])
    suite = get_suite(cfg.suite)
    before = foundation_key(cfg, suite, 0)
    from safetensors.torch import load_file, save_file

    weights = load_file(checkpoint / "model.safetensors")
    name = next(iter(weights))
    weights[name] = weights[name] + 1.0
    save_file(weights, checkpoint / "model.safetensors")
    assert foundation_key(cfg, suite, 0) != before  # the run key records the weights
