"""pi0 (`policy=pi0`): a prefix of image, language and state tokens, and an action expert that
attends to it and predicts the velocity of the action chunk.

- Prefix: each camera's image as ViT patch tokens (one encoder shared by the cameras, plus a
  learned camera embedding), the instruction as MiniLM token embeddings (frozen table, learned
  projection and positions; the pooled sentence as one token when a batch has no token ids),
  and the normalized state as one token. A prefix transformer reads them bidirectionally.
- Action expert: one token per action of the noisy chunk, each the action's projection
  concatenated with the time's sinusoidal embedding through an MLP (pi0's action-time MLP).
- The two have their own weights but share every layer's attention, under pi0's block mask:
  the prefix attends only within itself, the action tokens to the prefix and to each other.
  Because the prefix never attends to the actions, its keys and values do not depend on them:
  `encode_observation` computes them once per observation and every Euler step reuses them
  (the KV cache). `joint_velocity` is the same network as one pass over prefix and actions
  under the mask, the reference the cache is tested against.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F  # noqa: N812
from torch import nn

from policies.base import FlowMatchingBase, sinusoidal_embedding
from policies.pi0.configuration import Pi0Config
from policies.text_encoder import token_embedding_table


def block_attention_mask(prefix_valid: torch.Tensor, n_actions: int) -> torch.Tensor:
    """[B, P + n, P + n] bool, True where query i may attend to key j: pi0's blocks (prefix =
    block 0, actions = block 1) let a token see the keys of its own and earlier blocks, and
    only valid (non-padding) keys."""
    b, p = prefix_valid.shape
    block = torch.cat([torch.zeros(p, dtype=torch.long), torch.ones(n_actions, dtype=torch.long)])
    block = block.to(prefix_valid.device)
    valid = torch.cat([prefix_valid, prefix_valid.new_ones(b, n_actions)], dim=1)
    return (block[None, :] <= block[:, None])[None] & valid[:, None, :]


def attend(q, k, v, mask=None):
    """Multi-head attention over [B, heads, N, head_dim]; `mask` is bool, True = attend."""
    return F.scaled_dot_product_attention(q, k, v, attn_mask=mask)


class LayerWeights(nn.Module):
    """One layer's weights for one stream of tokens: pre-norm query/key/value projections, and
    (unless the layer only feeds keys and values to the expert) the output projection and MLP."""

    def __init__(self, width: int, heads: int, head_dim: int, mlp_ratio: int,
                 keys_only: bool = False):
        super().__init__()
        self.heads, self.head_dim, self.keys_only = heads, head_dim, keys_only
        self.attn_norm = nn.RMSNorm(width)
        self.qkv = nn.Linear(width, (2 if keys_only else 3) * heads * head_dim, bias=False)
        if not keys_only:
            self.out = nn.Linear(heads * head_dim, width, bias=False)
            self.mlp_norm = nn.RMSNorm(width)
            self.mlp = nn.Sequential(nn.Linear(width, mlp_ratio * width),
                                     nn.GELU(approximate="tanh"),
                                     nn.Linear(mlp_ratio * width, width))

    def project(self, h: torch.Tensor):
        """(q or None, k, v), each [B, heads, N, head_dim]."""
        parts = self.qkv(self.attn_norm(h)).unflatten(-1, (-1, self.heads, self.head_dim))
        parts = parts.permute(2, 0, 3, 1, 4)
        return (None, *parts) if self.keys_only else tuple(parts)

    def finish(self, h: torch.Tensor, attended: torch.Tensor) -> torch.Tensor:
        h = h + self.out(attended.transpose(1, 2).flatten(2))
        return h + self.mlp(self.mlp_norm(h))


class VisionEncoder(nn.Module):
    """A ViT: uint8 [B, H, W, 3] -> [B, patches, out_width] patch tokens."""

    def __init__(self, width: int, depth: int, heads: int, patch: int, image_size: int,
                 out_width: int):
        super().__init__()
        self.patchify = nn.Conv2d(3, width, patch, stride=patch)
        self.position = nn.Parameter(0.02 * torch.randn((image_size // patch) ** 2, width))
        self.blocks = nn.ModuleList(LayerWeights(width, heads, width // heads, 4)
                                    for _ in range(depth))
        self.norm = nn.RMSNorm(width)
        self.out = nn.Linear(width, out_width)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        x = images.permute(0, 3, 1, 2).float() / 127.5 - 1.0
        h = self.patchify(x).flatten(2).transpose(1, 2) + self.position
        for block in self.blocks:
            q, k, v = block.project(h)
            h = block.finish(h, attend(q, k, v))
        return self.out(self.norm(h))


@dataclass
class PrefixCache:
    """The prefix's keys and values at every layer, and which of its tokens are valid."""

    keys_values: list[tuple[torch.Tensor, torch.Tensor]]
    valid: torch.Tensor  # [B, P] bool


class Pi0Policy(FlowMatchingBase):
    Config = Pi0Config
    ARCHITECTURE_VERSION = 1  # part of the foundation cache key: bump when the network changes
    # LoRA's default: the action expert (its layers, the chunk's projections and time MLP)
    lora_target = r"(action_in|action_time_mlp\..*|expert_layers\..*|action_out)"

    def __init__(self, config: Pi0Config):
        super().__init__(config)
        c, d = config, config.dims
        pw, ew = d.prefix_width, d.expert_width
        if c.image_keys:
            self.vision = VisionEncoder(d.vit_width, d.vit_depth, d.vit_heads, d.patch_size,
                                        c.image_size, pw)
            self.camera_embedding = nn.Parameter(torch.zeros(len(c.image_keys), pw))
        # MiniLM's token embeddings, frozen and shared; not in the state dict (the wheel has it)
        self.register_buffer("token_table", token_embedding_table(), persistent=False)
        self.language_proj = nn.Linear(c.token_dim, pw)
        self.language_position = nn.Parameter(0.02 * torch.randn(c.max_language_tokens, pw))
        self.state_proj = nn.Linear(c.state_dim, pw)
        self.prefix_layers = nn.ModuleList(
            LayerWeights(pw, d.heads, d.head_dim, d.mlp_ratio, keys_only=i == d.depth - 1)
            for i in range(d.depth))
        self.action_in = nn.Linear(c.action_dim, ew)
        self.action_position = nn.Parameter(0.02 * torch.randn(c.chunk_size, ew))
        self.action_time_mlp = nn.Sequential(nn.Linear(2 * ew, ew), nn.SiLU(), nn.Linear(ew, ew))
        self.expert_layers = nn.ModuleList(LayerWeights(ew, d.heads, d.head_dim, d.mlp_ratio)
                                           for _ in range(d.depth))
        self.final_norm = nn.RMSNorm(ew)
        self.action_out = nn.Linear(ew, c.action_dim)

    # -- tokens ------------------------------------------------------------------------------

    def prefix_tokens(self, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
        """[B, P, prefix_width] tokens (cameras, language, state) and [B, P] validity."""
        state = self.state_proj(self.state_norm.normalize(batch["state"]))[:, None]
        b = state.shape[0]
        parts, valid = [], []
        for i, key in enumerate(self.config.image_keys):
            patches = self.vision(batch[key]) + self.camera_embedding[i]
            parts.append(patches)
            valid.append(torch.ones(patches.shape[:2], dtype=torch.bool, device=state.device))
        ids = batch.get("instruction_tokens")
        if ids is None:  # the pooled sentence as one token
            language = self.language_proj(batch["instruction"])[:, None]
            valid.append(torch.ones(b, 1, dtype=torch.bool, device=state.device))
        else:
            language = self.language_proj(self.token_table[ids])
            valid.append(ids != 0)
        parts.append(language + self.language_position[:language.shape[1]])
        parts.append(state)
        valid.append(torch.ones(b, 1, dtype=torch.bool, device=state.device))
        return torch.cat(parts, dim=1), torch.cat(valid, dim=1)

    def action_tokens(self, x_t: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
        """[B, H, expert_width]: each noisy action with the time, through pi0's MLP."""
        a = self.action_in(x_t) + self.action_position
        time = sinusoidal_embedding(t, a.shape[-1]).to(a.dtype)[:, None].expand_as(a)
        return self.action_time_mlp(torch.cat([a, time], dim=-1))

    # -- the network -------------------------------------------------------------------------

    def encode_observation(self, batch: dict[str, torch.Tensor]) -> PrefixCache:
        """The prefix's keys and values at every layer (its own attention needs no actions)."""
        h, valid = self.prefix_tokens(batch)
        mask = valid[:, None, None, :]
        keys_values = []
        for layer in self.prefix_layers:
            q, k, v = layer.project(h)
            keys_values.append((k, v))
            if q is not None:
                h = layer.finish(h, attend(q, k, v, mask))
        return PrefixCache(keys_values, valid)

    def velocity(self, x_t: torch.Tensor, t: torch.Tensor, prefix: PrefixCache) -> torch.Tensor:
        """The action expert: its queries attend to the cached prefix and to the actions."""
        h = self.action_tokens(x_t, t)
        valid = torch.cat([prefix.valid, prefix.valid.new_ones(h.shape[:2])], dim=1)
        mask = valid[:, None, None, :]
        for layer, (pk, pv) in zip(self.expert_layers, prefix.keys_values):
            q, k, v = layer.project(h)
            h = layer.finish(h, attend(q, torch.cat([pk, k], 2), torch.cat([pv, v], 2), mask))
        return self.action_out(self.final_norm(h))

    def joint_velocity(self, batch: dict[str, torch.Tensor], x_t: torch.Tensor, t: torch.Tensor
                       ) -> tuple[list[torch.Tensor], torch.Tensor]:
        """One pass over [prefix; actions] under `block_attention_mask`, with no cache: the
        prefix's hidden states after each layer that has an output, and the velocity."""
        hp, prefix_valid = self.prefix_tokens(batch)
        he = self.action_tokens(x_t, t)
        p = hp.shape[1]
        mask = block_attention_mask(prefix_valid, he.shape[1])[:, None]
        prefix_states = []
        for prefix_layer, expert_layer in zip(self.prefix_layers, self.expert_layers):
            qp, kp, vp = prefix_layer.project(hp)
            qe, ke, ve = expert_layer.project(he)
            k, v = torch.cat([kp, ke], 2), torch.cat([vp, ve], 2)
            if qp is None:  # the last prefix layer only lends its keys and values
                he = expert_layer.finish(he, attend(qe, k, v, mask[:, :, p:]))
                continue
            out = attend(torch.cat([qp, qe], 2), k, v, mask)
            hp = prefix_layer.finish(hp, out[:, :, :p])
            he = expert_layer.finish(he, out[:, :, p:])
            prefix_states.append(hp)
        return prefix_states, self.action_out(self.final_norm(he))

    @torch.no_grad()
    def sample_actions_without_cache(self, batch: dict[str, torch.Tensor], noise: torch.Tensor
                                     ) -> torch.Tensor:
        """`sample_actions` recomputing the whole prefix at every Euler step (the reference)."""
        return self.integrate(noise, lambda x, t: self.joint_velocity(batch, x, t)[1])
