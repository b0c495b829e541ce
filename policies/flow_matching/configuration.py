"""Configuration of the flow-matching policy: sizes, chunking, and the flow-matching schedule."""

from __future__ import annotations

from dataclasses import dataclass, replace

# name -> (hidden_dim, n_blocks, instruction_proj_dim)
POLICY_SIZES: dict[str, tuple[int, int, int]] = {
    "tiny": (64, 2, 32),  # tests: trains in seconds
    "default": (256, 3, 64),  # CPU benchmarks
    "large": (1024, 6, 256),  # GPU
    "paper": (2048, 8, 512),  # GPU, the scale of the paper's action experts
}


@dataclass(frozen=True)
class FlowMatchingConfig:
    state_dim: int
    action_dim: int
    size: str = "default"
    chunk_size: int = 4  # actions predicted per chunk (H)
    n_action_steps: int = 4  # actions executed before the next prediction
    instruction_dim: int = 384  # MiniLM-L6 sentence embedding
    time_embed_dim: int = 64
    num_inference_steps: int = 10  # Euler steps from t=1 (noise) to t=0 (actions)
    time_beta_alpha: float = 1.5  # t ~ Beta(1.5, 1): more weight near noise, as in pi0
    time_beta_beta: float = 1.0
    time_min: float = 0.001
    image_keys: tuple[str, ...] = ()  # camera observations fed through a small CNN when set
    image_size: int = 84

    def __post_init__(self):
        if self.size not in POLICY_SIZES:
            valid = ", ".join(POLICY_SIZES)
            raise ValueError(f"unknown policy size {self.size!r}; valid: {valid}")
        if not 1 <= self.n_action_steps <= self.chunk_size:
            raise ValueError(
                f"n_action_steps={self.n_action_steps} must be in [1, chunk_size={self.chunk_size}]"
            )

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
