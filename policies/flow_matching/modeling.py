"""A pi0-style flow-matching policy, scaled to what a CPU can train.

Observation tokens (instruction embedding from a frozen sentence encoder through a learned
projection, normalized state, optional camera features) condition an action expert that predicts
the velocity of a whole action chunk. Conventions (pi0): x_t = t * noise + (1 - t) * actions, so
t = 1 is pure noise and t = 0 the data; the target velocity is noise - actions; inference runs
Euler steps from t = 1 to t = 0. `forward` returns the per-sample loss [B]: methods reduce it.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from policies.flow_matching.configuration import FlowMatchingConfig
from policies.normalization import Normalizer

ARCHITECTURE_VERSION = 2  # part of the foundation cache key: bump when the network changes
STATE_STD_FLOOR, STATE_CLIP = 1e-2, 5.0
ACTION_STD_FLOOR, ACTION_CLIP = 5e-2, 5.0


def sinusoidal_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    """Embed scalar times t in [0, 1] ([B]) as [B, dim] sines and cosines."""
    half = dim // 2
    freqs = torch.exp(-math.log(1000.0) * torch.arange(half, device=t.device) / half)
    angles = (t[:, None] * 1000.0) * freqs[None]
    return torch.cat([angles.sin(), angles.cos()], dim=-1)


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


class FlowMatchingPolicy(nn.Module):
    def __init__(self, config: FlowMatchingConfig):
        super().__init__()
        self.config = config
        c, d = config, config.hidden_dim
        self.state_norm = Normalizer(c.state_dim, STATE_STD_FLOOR, STATE_CLIP)
        self.action_norm = Normalizer(c.action_dim, ACTION_STD_FLOOR, ACTION_CLIP)
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

    # -- training ----------------------------------------------------------------------------

    def sample_time(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """t ~ Beta(alpha, beta) scaled to [time_min, 1]; Beta(a, 1) by inverse CDF u^(1/a)."""
        c = self.config
        if c.time_beta_beta == 1.0:
            u = torch.rand(n, generator=generator, device=self.action_in.weight.device)
            t = u.pow(1.0 / c.time_beta_alpha)
        else:
            t = torch.distributions.Beta(c.time_beta_alpha, c.time_beta_beta).sample((n,))
        return t * (1.0 - c.time_min) + c.time_min

    def predicted_velocity(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """The velocity [B, H, A] the network predicts at x_t = t * noise + (1 - t) * actions, in
        the normalized action space, for the draws `batch["noise"]` [B, H, A] and `batch["time"]`
        [B]: what methods compare between two networks (distillation) or differentiate (MAS)."""
        actions = self.action_norm.normalize(batch["actions"])
        noise, t = batch["noise"], batch["time"]
        tt = t[:, None, None]
        x_t = tt * noise + (1.0 - tt) * actions
        return self.velocity(x_t, t, self.encode_observation(batch))

    def forward(
        self, batch: dict[str, torch.Tensor], generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """Per-sample flow-matching loss [B]. `batch["noise"]`/`batch["time"]` fix the draws."""
        actions = self.action_norm.normalize(batch["actions"])
        b = actions.shape[0]
        noise = batch.get("noise")
        if noise is None:
            noise = torch.randn(actions.shape, generator=generator, device=actions.device)
        t = batch.get("time")
        if t is None:
            t = self.sample_time(b, generator)
        velocity = self.predicted_velocity({**batch, "noise": noise, "time": t})
        error = (velocity - (noise - actions)) ** 2
        mask = batch.get("action_mask")
        if mask is None:
            return error.mean(dim=(1, 2))
        m = mask[:, :, None].to(error.dtype)
        return (error * m).sum(dim=(1, 2)) / (m.sum(dim=(1, 2)) * error.shape[-1]).clamp_min(1.0)

    # -- inference ---------------------------------------------------------------------------

    @torch.no_grad()
    def sample_actions(
        self, batch: dict[str, torch.Tensor], noise: torch.Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Action chunks [B, H, A] in environment units: Euler from noise (t=1) to data (t=0)."""
        c = self.config
        b = batch["state"].shape[0]
        x = noise
        if x is None:
            x = torch.randn((b, c.chunk_size, c.action_dim), generator=generator,
                            device=batch["state"].device)
        obs_embedding = self.encode_observation(batch)
        dt = 1.0 / c.num_inference_steps
        for i in range(c.num_inference_steps):
            t = torch.full((b,), 1.0 - i * dt, device=x.device)
            x = x - dt * self.velocity(x, t, obs_embedding)
        return self.action_norm.unnormalize(x)
