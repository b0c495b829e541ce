"""Configuration of the MLP flow-matching policy (`policy=mlp`): its sizes."""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import ClassVar

from policies.base import PolicyConfig

# name -> (hidden_dim, n_blocks, instruction_proj_dim)
POLICY_SIZES: dict[str, tuple[int, int, int]] = {
    "tiny": (64, 2, 32),  # tests: trains in seconds
    "default": (256, 3, 64),  # CPU benchmarks
    "large": (1024, 6, 256),  # GPU
    "paper": (2048, 8, 512),  # GPU, the scale of the paper's action experts
}


@dataclass(frozen=True)
class FlowMatchingConfig(PolicyConfig):
    SIZES: ClassVar[dict[str, tuple[int, int, int]]] = POLICY_SIZES

    instruction_dim: int = 384  # MiniLM-L6 sentence embedding
    time_embed_dim: int = 64

    @property
    def hidden_dim(self) -> int:
        return POLICY_SIZES[self.size][0]

    @property
    def n_blocks(self) -> int:
        return POLICY_SIZES[self.size][1]

    @property
    def instruction_proj_dim(self) -> int:
        return POLICY_SIZES[self.size][2]

    def with_size(self, size: str) -> FlowMatchingConfig:
        return replace(self, size=size)
