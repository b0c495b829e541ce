"""What every flow-matching policy shares: its config's common fields, the flow-matching schedule
(time sampling, the noisy chunk and its target velocity, the masked per-sample loss) and Euler
sampling. A policy supplies only its network: `encode_observation` and `velocity`.

THE POLICY CONTRACT (what the harness and every method rely on; `docs/adding-a-policy.md`):

- The class has a `Config` attribute, a dataclass constructed as `Config(state_dim=, action_dim=,
  size=, chunk_size=, n_action_steps=, image_keys=, image_size=)`; an unknown `size` raises a
  ValueError naming the valid ones. Each policy has its own Config class: the evaluation workers
  find the policy to rebuild from the config's class.
- `policy = Cls(config)`; `policy.config.chunk_size` and `policy.config.action_dim` are read.
- `policy.state_norm` and `policy.action_norm` are `Normalizer`s the harness fits on the
  foundation data before training.
- `forward(batch, generator=None)` -> per-sample loss [B]. `batch` holds "state" [B, S],
  "actions" [B, H, A] (environment units), "action_mask" [B, H], "instruction" [B, 384] (the
  pooled instruction embedding), "instruction_tokens" [B, L] (the instruction's MiniLM token ids,
  0 = padding) and the image keys the config names (uint8 [B, H, W, 3]); "noise" [B, H, A] and
  "time" [B], when present, fix the draws.
- `sample_time(n, generator)` -> [n] times in (0, 1].
- `sample_actions(batch, noise=None, generator=None)` -> [B, H, A] in environment units.
- `predicted_velocity(batch)` -> [B, H, A]: the network's velocity in the normalized action
  space at x_t = time * noise + (1 - time) * actions, with the caller's batch["noise"] and
  batch["time"] (what distillation and MAS compare).
- Optionally `noise_dim`: a policy that pads its actions (LeRobot's, to max_action_dim) draws
  its noise as [B, H, noise_dim]; callers that fix "noise" use `noise_shape(policy, B)`.
- Optionally `needs_cameras = True`: the plan turns cameras on for a policy that reads images.
- Optionally its Config declares any of `path` (`policy_path`), `instructions` (the benchmark's
  instruction texts, which a batch's "instruction_id" [B] indexes), `features` (Retain's
  observation keys to the policy's own names) and `rotate_images`; the harness fills those it
  declares (harness/protocol/foundation.py).

- Optionally `ARCHITECTURE_VERSION` (a class attribute, part of the foundation cache key): bump
  it when the network changes, so cached foundations of the old network are not reused.

Subclassing `FlowMatchingBase` gives all of it from the two network methods.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, ClassVar

import torch
from torch import nn

from policies.normalization import Normalizer

STATE_STD_FLOOR, STATE_CLIP = 1e-2, 5.0
ACTION_STD_FLOOR, ACTION_CLIP = 5e-2, 5.0


@dataclass(frozen=True)
class PolicyConfig:
    """The fields the harness sets, and the flow-matching schedule (pi0's)."""

    SIZES: ClassVar[dict[str, Any]] = {"default": None}  # a subclass names its own sizes

    state_dim: int
    action_dim: int
    size: str = "default"
    chunk_size: int = 4  # actions predicted per chunk (H)
    n_action_steps: int = 4  # actions executed before the next prediction
    num_inference_steps: int = 10  # Euler steps from t=1 (noise) to t=0 (actions)
    time_beta_alpha: float = 1.5  # t ~ Beta(1.5, 1): more weight near noise, as in pi0
    time_beta_beta: float = 1.0
    time_min: float = 0.001
    image_keys: tuple[str, ...] = ()  # camera observations the policy consumes
    image_size: int = 84

    def __post_init__(self):
        if self.size not in self.SIZES:
            raise ValueError(f"unknown policy size {self.size!r} for {type(self).__name__}; "
                             f"valid: {', '.join(self.SIZES)}")
        if not 1 <= self.n_action_steps <= self.chunk_size:
            raise ValueError(
                f"n_action_steps={self.n_action_steps} must be in [1, chunk_size={self.chunk_size}]"
            )


def sinusoidal_embedding(t: torch.Tensor, dim: int) -> torch.Tensor:
    """Embed scalar times t in [0, 1] ([B]) as [B, dim] sines and cosines."""
    half = dim // 2
    freqs = torch.exp(-math.log(1000.0) * torch.arange(half, device=t.device) / half)
    angles = (t[:, None] * 1000.0) * freqs[None]
    return torch.cat([angles.sin(), angles.cos()], dim=-1)


class FlowMatchingBase(nn.Module):
    """Conventions (pi0): x_t = t * noise + (1 - t) * actions, so t = 1 is pure noise and t = 0
    the data; the target velocity is noise - actions; inference runs Euler steps from t = 1 to
    t = 0. Subclasses implement `encode_observation(batch) -> context` and
    `velocity(x_t, t, context) -> [B, H, A]`; the context is computed once per observation and
    reused by every Euler step (pi0's prefix cache)."""

    Config: ClassVar[type[PolicyConfig]] = PolicyConfig

    def __init__(self, config: PolicyConfig):
        super().__init__()
        self.config = config
        self.state_norm = Normalizer(config.state_dim, STATE_STD_FLOOR, STATE_CLIP)
        self.action_norm = Normalizer(config.action_dim, ACTION_STD_FLOOR, ACTION_CLIP)

    # -- the network (subclasses) ------------------------------------------------------------

    def encode_observation(self, batch: dict[str, torch.Tensor]) -> Any:
        raise NotImplementedError

    def velocity(self, x_t: torch.Tensor, t: torch.Tensor, context: Any) -> torch.Tensor:
        """Predicted velocity d x_t / d t for normalized action chunks x_t [B, H, A]."""
        raise NotImplementedError

    # -- training ----------------------------------------------------------------------------

    @property
    def device(self) -> torch.device:
        return self.action_norm.mean.device

    def sample_time(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """t ~ Beta(alpha, beta) scaled to [time_min, 1]."""
        c = self.config
        return beta_time(n, c.time_beta_alpha, c.time_beta_beta, 1.0 - c.time_min, c.time_min,
                         generator, self.device)

    def _draws(self, batch: dict[str, torch.Tensor], actions: torch.Tensor,
               generator: torch.Generator | None) -> tuple[torch.Tensor, torch.Tensor]:
        """The batch's noise and times, or fresh ones (noise first: the generator's order)."""
        noise = batch.get("noise")
        if noise is None:
            noise = randn_from(actions.shape, generator, actions.device)
        t = batch.get("time")
        if t is None:
            t = self.sample_time(actions.shape[0], generator)
        return noise, t

    def _on_device(self, batch: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
        """`batch` with its tensors on the policy's device (itself when they are there), so a
        method may hand a GPU policy the CPU samples it keeps."""
        if batch["state"].device == self.device:
            return batch
        return {k: v.to(self.device) if torch.is_tensor(v) else v for k, v in batch.items()}

    def forward(
        self, batch: dict[str, torch.Tensor], generator: torch.Generator | None = None
    ) -> torch.Tensor:
        """Per-sample flow-matching loss [B]. `batch["noise"]`/`batch["time"]` fix the draws."""
        batch = self._on_device(batch)
        actions = self.action_norm.normalize(batch["actions"])
        noise, t = self._draws(batch, actions, generator)
        tt = t[:, None, None]
        x_t = tt * noise + (1.0 - tt) * actions
        predicted = self.velocity(x_t, t, self.encode_observation(batch))
        error = (predicted.float() - (noise - actions)) ** 2
        mask = batch.get("action_mask")
        if mask is None:
            return error.mean(dim=(1, 2))
        m = mask[:, :, None].to(error.dtype)
        return (error * m).sum(dim=(1, 2)) / (m.sum(dim=(1, 2)) * error.shape[-1]).clamp_min(1.0)

    def predicted_velocity(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """The velocity [B, H, A] (normalized action space) at the caller's batch["noise"] and
        batch["time"]: what distillation and MAS compare between networks."""
        batch = self._on_device(batch)
        actions = self.action_norm.normalize(batch["actions"])
        tt = batch["time"][:, None, None]
        x_t = tt * batch["noise"] + (1.0 - tt) * actions
        return self.velocity(x_t, batch["time"], self.encode_observation(batch))

    # -- inference ---------------------------------------------------------------------------

    @torch.no_grad()
    def sample_actions(
        self, batch: dict[str, torch.Tensor], noise: torch.Tensor | None = None,
        generator: torch.Generator | None = None,
    ) -> torch.Tensor:
        """Action chunks [B, H, A] in environment units: Euler from noise (t=1) to data (t=0),
        the observation encoded once for all steps."""
        c = self.config
        batch = self._on_device(batch)
        x = noise if noise is None else noise.to(self.device)
        if x is None:
            shape = (batch["state"].shape[0], c.chunk_size, c.action_dim)
            x = randn_from(shape, generator, batch["state"].device)
        context = self.encode_observation(batch)
        return self.integrate(x, lambda x_t, t: self.velocity(x_t, t, context))

    def integrate(self, noise: torch.Tensor, velocity) -> torch.Tensor:
        """`num_inference_steps` Euler steps of `velocity(x_t, t)` from `noise` at t = 1."""
        x, b = noise, noise.shape[0]
        dt = 1.0 / self.config.num_inference_steps
        for i in range(self.config.num_inference_steps):
            t = torch.full((b,), 1.0 - i * dt, device=x.device)
            x = x - dt * velocity(x, t)
        return self.action_norm.unnormalize(x)


def beta_time(n: int, alpha: float, beta: float, scale: float, offset: float,
              generator: torch.Generator | None, device: torch.device) -> torch.Tensor:
    """n flow-matching times t = Beta(alpha, beta) * scale + offset (pi0's schedule); Beta(a, 1)
    by inverse CDF u^(1/a), from `generator`."""
    if beta == 1.0:
        gen_device = generator.device if generator is not None else device
        t = torch.rand(n, generator=generator, device=gen_device).to(device).pow(1.0 / alpha)
    else:
        t = torch.distributions.Beta(alpha, beta).sample((n,)).to(device)
    return t * scale + offset


def noise_shape(policy, n: int) -> tuple[int, int, int]:
    """The shape of n samples' flow-matching noise, [n, H, A], or [n, H, policy.noise_dim] for a
    policy that pads its actions (LeRobot's VLAs draw noise over max_action_dim)."""
    c = policy.config
    return (n, c.chunk_size, getattr(policy, "noise_dim", c.action_dim))


def randn_from(shape, generator: torch.Generator | None, device: torch.device) -> torch.Tensor:
    """Standard normal draws from `generator` (on its own device, so a CPU generator seeds a
    GPU run reproducibly), placed on `device`."""
    if generator is None:
        return torch.randn(shape, device=device)
    return torch.randn(shape, generator=generator, device=generator.device).to(device)
