"""The MLP flow-matching policy (`policy=mlp`), scaled to what a CPU can train.

Observation tokens (instruction embedding from a frozen sentence encoder through a learned
projection, normalized state, optional camera features) condition an action expert, a residual
MLP over the flattened chunk, that predicts the velocity of a whole action chunk. The schedule,
loss and sampling are `policies.base.FlowMatchingBase`'s.
"""

from __future__ import annotations

import torch
from torch import nn

from policies.base import FlowMatchingBase, sinusoidal_embedding
from policies.flow_matching.configuration import FlowMatchingConfig

ARCHITECTURE_VERSION = 2  # part of the foundation cache key: bump when the network changes


class ImageEncoder(nn.Module):
    """A small CNN per camera: uint8 [B, H, W, 3] -> [B, out_dim]."""

    def __init__(self, out_dim: int):
        super().__init__()
        self.net = nn.Sequential(
            nn.Conv2d(3, 32, 5, stride=2), nn.GELU(),
            nn.Conv2d(32, 64, 3, stride=2), nn.GELU(),
            nn.Conv2d(64, 64, 3, stride=2), nn.GELU(),
            nn.AdaptiveAvgPool2d(1), nn.Flatten(), nn.Linear(64, out_dim),
        )

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = images.permute(0, 3, 1, 2).float() / 127.5 - 1.0
        return self.net(x)


class ConditionedBlock(nn.Module):
    """Residual MLP block; the observation-and-time conditioning is added to its input, so every
    block sees it (cheaper than adaLN's per-block projection, which matters on a CPU)."""

    def __init__(self, dim: int):
        super().__init__()
        self.norm = nn.LayerNorm(dim)
        self.mlp = nn.Sequential(nn.Linear(dim, dim), nn.GELU(), nn.Linear(dim, dim))

    def forward(self, h: torch.Tensor, cond: torch.Tensor) -> torch.Tensor:
        return h + self.mlp(self.norm(h) + cond)


class FlowMatchingPolicy(FlowMatchingBase):
    Config = FlowMatchingConfig
    lora_target = r"(action_in|blocks\..*|action_out\..*)"  # LoRA's default: the action expert

    def __init__(self, config: FlowMatchingConfig):
        super().__init__(config)
        c, d = config, config.hidden_dim
        self.instruction_proj = nn.Linear(c.instruction_dim, c.instruction_proj_dim)
        self.image_encoders = nn.ModuleDict({k: ImageEncoder(d) for k in c.image_keys})
        obs_dim = c.instruction_proj_dim + c.state_dim + d * len(c.image_keys)
        self.obs_encoder = nn.Sequential(nn.Linear(obs_dim, d), nn.GELU(), nn.Linear(d, d))
        self.time_encoder = nn.Sequential(nn.Linear(c.time_embed_dim, d), nn.GELU(), nn.Linear(d, d))
        chunk_dim = c.chunk_size * c.action_dim
        self.action_in = nn.Linear(chunk_dim, d)
        self.blocks = nn.ModuleList(ConditionedBlock(d) for _ in range(c.n_blocks))
        self.action_out = nn.Sequential(nn.LayerNorm(d), nn.Linear(d, chunk_dim))

    # -- the network -------------------------------------------------------------------------

    def encode_observation(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        parts = [self.instruction_proj(batch["instruction"]), self.state_norm.normalize(batch["state"])]
        parts += [enc(batch[key]) for key, enc in self.image_encoders.items()]
        return self.obs_encoder(torch.cat(parts, dim=-1))

    def velocity(self, x_t: torch.Tensor, t: torch.Tensor, obs_embedding: torch.Tensor) -> torch.Tensor:
        """Predicted velocity d x_t / d t for normalized action chunks x_t [B, H, A]."""
        cond = obs_embedding + self.time_encoder(sinusoidal_embedding(t, self.config.time_embed_dim))
        h = self.action_in(x_t.flatten(1))
        for block in self.blocks:
            h = block(h, cond)
        return self.action_out(h).view_as(x_t)
