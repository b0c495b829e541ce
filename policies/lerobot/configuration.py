"""Configuration of the LeRobot policies (`policy=lerobot_pi0`, `lerobot_pi05`, `lerobot_smolvla`):
which of LeRobot's classes, at which size, or which checkpoint.

Without `path` the policy is LeRobot's class at a random init of `size`, pre-trained by Retain as
the foundation: `tiny` for tests, `small` for a CPU study, `default` for the published
architecture (PaliGemma 3B with a Gemma-300M action expert; SmolVLM2-500M, whose config comes
from the hub). With `path` (a checkpoint folder, or a hub id where the hub is reachable) the
checkpoint is the foundation, and its own config sets the architecture, chunk and features.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from policies.base import PolicyConfig


@dataclass(frozen=True)
class GemmaDims:
    """One Gemma of PI0's pair. LeRobot's attention hard-codes 8 query heads and 1 key-value
    head (`1 * 8 * head_dim`), so only the width, depth, MLP and head dimension shrink."""

    width: int
    depth: int
    mlp_dim: int
    head_dim: int


@dataclass(frozen=True)
class VisionDims:
    """The image tower (SigLIP for PaliGemma, SmolVLM's own): patches, widths, depth."""

    hidden: int
    intermediate: int
    layers: int
    heads: int
    patch: int


@dataclass(frozen=True)
class PaliGemmaSize:
    """A reduced PI0 / PI0.5: the VLM and the action expert (equal depths, as LeRobot pairs
    their layers) and the vision tower."""

    vlm: GemmaDims
    expert: GemmaDims
    vision: VisionDims


@dataclass(frozen=True)
class SmolVLMSize:
    """A reduced SmolVLM for SmolVLA: its text model (LeRobot's expert is 0.75 of its width and
    as deep) and its vision tower; written as a local VLM config folder, no patch needed."""

    width: int
    layers: int
    heads: int
    kv_heads: int
    intermediate: int
    vision: VisionDims


PALIGEMMA_SIZES: dict[str, PaliGemmaSize | None] = {
    # tests: a training step in about 0.1 s on one core at batch 32 with two 64-px cameras
    "tiny": PaliGemmaSize(GemmaDims(64, 2, 128, 8), GemmaDims(32, 2, 64, 8),
                          VisionDims(32, 64, 1, 2, 16)),
    # a CPU study: a few million parameters besides the token embeddings
    "small": PaliGemmaSize(GemmaDims(128, 4, 512, 16), GemmaDims(64, 4, 256, 16),
                           VisionDims(96, 384, 2, 4, 16)),
    "default": None,  # LeRobot's own: gemma_2b, gemma_300m, SigLIP-so400m
}

SMOLVLM_SIZES: dict[str, SmolVLMSize | None] = {
    "tiny": SmolVLMSize(64, 4, 4, 2, 128, VisionDims(32, 64, 1, 2, 16)),
    "small": SmolVLMSize(192, 8, 6, 2, 512, VisionDims(96, 384, 2, 4, 16)),
    "default": None,  # HuggingFaceTB/SmolVLM2-500M-Video-Instruct, from the hub
}


@dataclass(frozen=True)
class LeRobotConfig(PolicyConfig):
    """The harness's fields (PolicyConfig) and what the adapter needs besides.

    `features` maps Retain's observation keys ("state", "agentview_rgb", "eye_in_hand_rgb") to
    the checkpoint's input features, as the plan resolved them; `instructions` are the
    benchmark's instruction texts, which a batch's "instruction_id" indexes (LeRobot's own
    processors tokenize text, PI0.5's with the state in its prompt)."""

    KIND: ClassVar[str] = ""  # LeRobot's policy type: "pi0", "pi05", "smolvla"

    path: str = ""  # a checkpoint folder or hub id; "" is a random init at `size`
    weights: str = ""  # SHA-256 of the checkpoint's model.safetensors (its identity in run keys)
    instructions: tuple[str, ...] = ()
    features: tuple[tuple[str, str], ...] = ()
    rotate_images: bool = False  # the checkpoint's cameras are turned 180 degrees from the suite's


@dataclass(frozen=True)
class LeRobotPi0Config(LeRobotConfig):
    SIZES: ClassVar[dict[str, PaliGemmaSize | None]] = PALIGEMMA_SIZES
    KIND: ClassVar[str] = "pi0"


@dataclass(frozen=True)
class LeRobotPi05Config(LeRobotConfig):
    SIZES: ClassVar[dict[str, PaliGemmaSize | None]] = PALIGEMMA_SIZES
    KIND: ClassVar[str] = "pi05"


@dataclass(frozen=True)
class LeRobotSmolVLAConfig(LeRobotConfig):
    SIZES: ClassVar[dict[str, SmolVLMSize | None]] = SMOLVLM_SIZES
    KIND: ClassVar[str] = "smolvla"
