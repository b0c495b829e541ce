"""Configuration of the pi0 policy (`policy=pi0`): the widths and depths of its three parts.

A ViT encodes each camera into patch tokens; a prefix transformer reads image, language and
state tokens; an action expert of the same depth reads the noisy chunk and, layer by layer,
attends to the prefix's keys and values (pi0's two weight sets over one attention).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

from policies.base import PolicyConfig


@dataclass(frozen=True)
class Pi0Size:
    prefix_width: int
    expert_width: int
    depth: int  # layers of the prefix transformer and of the action expert (paired)
    heads: int  # attention heads, shared by prefix and expert (as pi0's Gemma pair)
    head_dim: int
    mlp_ratio: int
    vit_width: int  # the image encoder (used only when the config names image keys)
    vit_depth: int
    vit_heads: int
    patch_size: int  # an image's border beyond a whole number of patches is not seen


PI0_SIZES: dict[str, Pi0Size] = {
    # tests: seconds on a CPU
    "tiny": Pi0Size(32, 32, 2, 2, 16, 2, vit_width=32, vit_depth=1, vit_heads=2, patch_size=12),
    # CPU benchmarks, state and language only: about 1.7M parameters
    "default": Pi0Size(128, 128, 4, 4, 32, 4, vit_width=128, vit_depth=2, vit_heads=4,
                       patch_size=12),
    # GPU: a ViT-B encoder, a 12-layer 768-wide prefix and a 12-layer 1024-wide expert
    "large": Pi0Size(768, 1024, 12, 8, 128, 4, vit_width=768, vit_depth=12, vit_heads=12,
                     patch_size=16),
}


@dataclass(frozen=True)
class Pi0Config(PolicyConfig):
    SIZES: ClassVar[dict[str, Pi0Size]] = PI0_SIZES

    token_dim: int = 384  # MiniLM-L6's token embeddings
    max_language_tokens: int = 32  # MiniLM token ids per instruction (text_encoder's length)
    time_embed_dim: int = 64

    @property
    def dims(self) -> Pi0Size:
        return PI0_SIZES[self.size]
