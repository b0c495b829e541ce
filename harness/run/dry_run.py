"""The policy's dry run at plan time: before any demo is made, the policy the run will use (built,
or loaded from `policy_path`) computes its per-sample loss and one action chunk on one sample of
the suite's shapes. A checkpoint that cannot take the suite's state, cameras or instruction then
fails in seconds with one line naming the shapes, not after minutes of demos in a worker's
traceback."""

from __future__ import annotations

import gc

import torch

from harness.common.errors import RetainError
from harness.config.benchmark import BenchConfig
from policies import policy_for_config
from policies.lerobot.checkpoint import CheckpointError, first_line
from suites import Suite

# MiniLM's [CLS] "task" [SEP]: a token row of the instruction encoder's vocabulary
SAMPLE_TOKENS = (101, 4708, 102)
INSTRUCTION_DIM = 384  # the sentence encoder's pooled embedding


def sample_batch(config) -> dict[str, torch.Tensor]:
    """One sample of the shapes a batch of the suite has for this policy config (zeros: only
    the shapes are on trial)."""
    batch = {"state": torch.zeros(1, config.state_dim),
             "actions": torch.zeros(1, config.chunk_size, config.action_dim),
             "action_mask": torch.ones(1, config.chunk_size, dtype=torch.bool),
             "instruction": torch.zeros(1, INSTRUCTION_DIM),
             "instruction_tokens": torch.tensor([SAMPLE_TOKENS]),
             "instruction_id": torch.zeros(1, dtype=torch.long)}
    for key in config.image_keys:
        batch[key] = torch.zeros(1, config.image_size, config.image_size, 3, dtype=torch.uint8)
    return batch


def shapes_text(config) -> str:
    """The sample's shapes as the error names them: "state 39-D, actions 4 x 4, cameras
    agentview_rgb, eye_in_hand_rgb at 64x64"."""
    text = f"state {config.state_dim}-D, actions {config.chunk_size} x {config.action_dim}"
    if config.image_keys:
        px = config.image_size
        text += f", cameras {', '.join(config.image_keys)} at {px}x{px}"
    return text + ", an instruction"


def dry_run_policy(config, cfg: BenchConfig, suite: Suite) -> None:
    """Build the run's policy from its `config` (`policy_config`'s, as the plan resolved it) on
    the CPU and run its loss and sampling once; RetainError (one line naming the policy and the
    shapes) on any failure."""
    what = f"policy_path {cfg.policy_path!r}" if cfg.policy_path else f"policy {cfg.policy!r}"
    try:
        policy = policy_for_config(config)
    except CheckpointError as exc:
        raise RetainError(str(exc)) from None
    except Exception as exc:
        raise RetainError(f"{what} could not be built for suite {suite.name!r} "
                          f"({shapes_text(config)}): {type(exc).__name__}: {first_line(exc)}"
                          ) from None
    batch = sample_batch(config)
    try:
        with torch.no_grad():
            loss = policy(batch)
            actions = policy.sample_actions(batch, generator=torch.Generator().manual_seed(0))
    except Exception as exc:
        raise RetainError(f"{what} fails on one sample of suite {suite.name!r} "
                          f"({shapes_text(config)}): {type(exc).__name__}: {first_line(exc)}"
                          ) from None
    finally:
        del policy
        gc.collect()
    expected = (1, config.chunk_size, config.action_dim)
    if tuple(loss.shape) != (1,):
        raise RetainError(f"{what} returns a loss of shape {list(loss.shape)} for one sample; "
                          f"the policy contract is a per-sample loss [B]")
    if tuple(actions.shape) != expected:
        raise RetainError(f"{what} samples actions of shape {list(actions.shape)}; suite "
                          f"{suite.name!r} needs {list(expected)} (chunk x action width)")
