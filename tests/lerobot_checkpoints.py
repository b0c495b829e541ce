"""Tiny LeRobot checkpoints written by LeRobot's own API, in lerobot-train's layout, and a
small LeRobot dataset for a suite's tasks (`demos_dir=`: a run with cameras without the minutes
of rendering the experts' demos).

lerobot-train saves `<output>/checkpoints/<step>/pretrained_model/` (the policy's
`save_pretrained`, then its pre- and post-processor's) and points `checkpoints/last` at the newest
step. This writes the same with LeRobot's classes alone: `make_policy_config`, the policy class,
`make_pre_post_processors(config, dataset_stats=...)` and the three `save_pretrained` calls, so the
tests load what a user brings rather than what Retain's own `save_folder` writes.

Offline, two things a published checkpoint would fetch from the hub stay local: SmolVLA's VLM
config (a folder named by `vlm_model_name`, as a user would point it at a downloaded one) and, for
PI0 / PI0.5 at a reduced size, the tokenizer and the size's record that Retain's loader reads
(`tokenizer/`, `retain_architecture.json`), since LeRobot's PaliGemma names only published sizes.

Run as a script, it writes one in a process of its own:
    python -m tests.lerobot_checkpoints KIND OUTPUT STATE_DIM ACTION_DIM IMAGE_SIZE [STEP]
"""

from __future__ import annotations

import sys
from pathlib import Path

import torch

IMAGE_FEATURES = ("observation.images.image", "observation.images.wrist_image")


def write_lerobot_checkpoint(kind: str, output: Path, state_dim: int, action_dim: int,
                             image_size: int, step: int = 10, seed: int = 0, chunk_size: int = 4,
                             n_action_steps: int = 4, state_stats: dict | None = None,
                             image_features: tuple[str, ...] = IMAGE_FEATURES,
                             max_state_dim: int = 32) -> Path:
    """A tiny `kind` ("pi0", "pi05", "smolvla") policy saved as lerobot-train saves one; returns
    its `pretrained_model/` folder. LeRobot's own default `max_state_dim` is 32: a wider state
    needs a wider one (a checkpoint without is one that cannot run)."""
    from lerobot.configs import FeatureType, PolicyFeature
    from lerobot.policies.factory import (
        get_policy_class,
        make_policy_config,
        make_pre_post_processors,
    )

    from policies.lerobot.configuration import PALIGEMMA_SIZES, SMOLVLM_SIZES
    from policies.lerobot.reduced import (
        minilm_tokenizer,
        reduced_paligemma,
        write_architecture,
        write_smolvlm_folder,
    )

    output = Path(output)
    folder = output / "checkpoints" / f"{step:06d}" / "pretrained_model"
    folder.mkdir(parents=True)
    inputs = {"observation.state": PolicyFeature(FeatureType.STATE, (state_dim,))}
    inputs.update({k: PolicyFeature(FeatureType.VISUAL, (3, image_size, image_size))
                   for k in image_features})
    fields = dict(device="cpu", chunk_size=chunk_size, n_action_steps=n_action_steps,
                  max_state_dim=max_state_dim, max_action_dim=max(32, action_dim),
                  input_features=inputs,
                  output_features={"action": PolicyFeature(FeatureType.ACTION, (action_dim,))})
    g = torch.Generator().manual_seed(seed + 1)
    stats = {"observation.state": state_stats or {
                 "mean": torch.randn(state_dim, generator=g), "std": torch.rand(state_dim, generator=g) + 0.5,
                 "min": -torch.ones(state_dim) * 2, "max": torch.ones(state_dim) * 2,
                 "q01": -torch.ones(state_dim), "q99": torch.ones(state_dim)},
             "action": {"mean": torch.randn(action_dim, generator=g) * 0.1,
                        "std": torch.rand(action_dim, generator=g) * 0.5 + 0.2,
                        "min": -torch.ones(action_dim), "max": torch.ones(action_dim),
                        "q01": -torch.ones(action_dim) * 0.9, "q99": torch.ones(action_dim) * 0.9}}
    torch.manual_seed(seed)
    if kind == "smolvla":
        size = SMOLVLM_SIZES["tiny"]
        vlm = write_smolvlm_folder(size, image_size, output / "smolvlm")  # the "downloaded" VLM
        config = make_policy_config(kind, **fields, vlm_model_name=str(vlm),
                                    load_vlm_weights=False, num_vlm_layers=size.layers,
                                    resize_imgs_with_padding=(image_size, image_size))
        policy = get_policy_class(kind)(config)
        pre, post = make_pre_post_processors(config, dataset_stats=stats)
    else:
        size, tokenizer = PALIGEMMA_SIZES["tiny"], minilm_tokenizer()
        config = make_policy_config(kind, **fields, image_resolution=(image_size, image_size))
        with reduced_paligemma(size, tokenizer):
            policy = get_policy_class(kind)(config)
            pre, post = make_pre_post_processors(config, dataset_stats=stats)
        tokenizer.save_pretrained(folder / "tokenizer")
        write_architecture(folder, "tiny", size)
    policy.save_pretrained(folder)
    pre.save_pretrained(folder)
    post.save_pretrained(folder)
    last = output / "checkpoints" / "last"
    last.unlink(missing_ok=True)
    last.symlink_to(f"{step:06d}")  # lerobot-train's own link: a relative one
    return folder


def write_synthetic_dataset(folder: Path, suite_name: str, tasks: list[str], image_size: int,
                            episodes_per_task: int = 2, length: int = 8, seed: int = 0) -> Path:
    """Short random episodes of each task (state and actions of the suite's widths, both cameras)
    as a LeRobot v3.0 dataset with PNG images, matched to the tasks by their instructions."""
    import numpy as np

    from harness.data.demos import Episode
    from harness.data.lerobot.writer import write_dataset
    from suites import get_suite

    suite = get_suite(suite_name)
    rng = np.random.default_rng(seed)

    def episode() -> Episode:
        images = rng.integers(0, 256, (length, image_size, image_size, 3), dtype=np.uint8)
        return Episode(rng.uniform(-1, 1, (length, suite.action_dim)).astype(np.float32),
                       {"state": rng.normal(size=(length, suite.state_dim)).astype(np.float32),
                        "agentview_rgb": images, "eye_in_hand_rgb": images[:, ::-1]}, seed=-1)

    write_dataset(folder, [(suite.instruction(t), [episode() for _ in range(episodes_per_task)])
                           for t in tasks], fps=20, images="png")
    return folder


if __name__ == "__main__":
    kind, out, state, action, px = sys.argv[1:6]
    step = int(sys.argv[6]) if len(sys.argv) > 6 else 10
    print(write_lerobot_checkpoint(kind, Path(out), int(state), int(action), int(px), step))
