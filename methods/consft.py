"""Conservative SFT (ConSFT): scale each sample's learning signal by the model's confidence.

The paper's exact formula is not public; this is our reading, with three variants as options of
one class. l_i is sample i's flow-matching loss, sg() stops the gradient.

`clip` (default)
    w_i  = clip(exp(-(l_i - l_ref) / tau), w_min, 1),   tau = kappa * l_ref
    loss = mean(sg(w_i) * l_i)
  - l_ref is the loss at which the model counts as confident: the foundation's own final
    training loss (a scalar in its checkpoint; `reference=foundation`), or the `quantile` of the
    per-sample losses on the new task at the stage start (`reference=quantile`).
  - exp(-(l_i - l_ref)/tau): a sample the model finds surprising (l_i >> l_ref) would produce a
    large update; it is suppressed exponentially, as a trust region bounds an RL policy step.
  - tau = kappa * l_ref makes the temperature relative to the loss scale, so kappa means the
    same on any suite.
  - w_min: the floor, so that no sample is ignored for ever; a new task's initial loss can be
    orders of magnitude above l_ref, and without it learning would never start.
  - the upper clip at 1: a confident sample is never up-weighted above plain SFT.
  - sg(w_i): the weight is a coefficient, not a path for gradients (as in DFT).
  As training lowers l_i, weights rise towards 1: the progressive dynamic.

`dft`
    w_i = sg(exp(-l_i / tau)),  loss = mean(w_i * l_i)
  The flow-matching analogue of dynamic fine-tuning (the token probability becomes exp(-l/tau)).

`ratio`
    r_i = exp((l_i_old - l_i) / tau),  loss = -mean(min(r_i, clip(r_i, 1 - eps, 1 + eps)))
  A PPO-style clipped ratio with advantage 1: l_i_old is sample i's loss at the stage start,
  cached with the same (t, noise) draws that every later step reuses for that sample, so no live
  reference network is kept. Once a sample's loss has fallen by tau * log(1 + eps) it is past
  the clip and contributes no gradient.

It keeps no copy of the network and no earlier data; it logs its weight statistics each step.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from methods import register_method
from methods.base import Method, MethodConfig, TaskContext

VARIANTS = ("clip", "dft", "ratio")
REFERENCES = ("foundation", "quantile")


@dataclass
class ConSFTConfig(MethodConfig):
    variant: str = "clip"
    kappa: float = 4.0  # temperature tau = kappa * l_ref (sweep: docs/methods.md)
    w_min: float = 0.1  # floor on the weight (clip variant)
    reference: str = "foundation"  # where l_ref comes from
    quantile: float = 0.5  # with reference=quantile
    eps: float = 0.2  # ratio variant: PPO clip range
    reference_samples: int = 2048  # samples used to measure quantile losses at the stage start


@register_method
class ConSFT(Method):
    name = "consft"
    Config = ConSFTConfig

    def __init__(self, config: ConSFTConfig | None = None):
        super().__init__(config)
        c = self.config
        if c.variant not in VARIANTS:
            raise ValueError(f"unknown consft variant {c.variant!r}; valid: {', '.join(VARIANTS)}")
        if c.reference not in REFERENCES:
            raise ValueError(f"unknown consft reference {c.reference!r}; valid: {', '.join(REFERENCES)}")
        self.l_ref = float("nan")
        self._old_loss: torch.Tensor | None = None  # ratio: [N] per-sample loss at stage start
        self._draws: tuple[torch.Tensor, torch.Tensor] | None = None  # ratio: fixed (noise, t)

    @property
    def tau(self) -> float:
        return self.config.kappa * self.l_ref

    @torch.no_grad()
    def before_task(self, ctx: TaskContext) -> None:
        c = self.config
        g = torch.Generator().manual_seed(ctx.stage)
        if c.variant == "ratio":
            n = len(ctx.data)
            noise = torch.randn(ctx.data.actions.shape, generator=g)
            time = ctx.policy.sample_time(n, g)
            self._draws = (noise, time)
            self._old_loss = torch.cat([
                ctx.policy({**ctx.data.batch(idx), "noise": noise[idx], "time": time[idx]})
                for idx in torch.arange(n).split(1024)
            ])
        if c.reference == "foundation":
            self.l_ref = ctx.foundation_loss
        else:
            sample = ctx.data.sample(min(c.reference_samples, len(ctx.data)), g)
            self.l_ref = torch.quantile(ctx.policy(sample, generator=g), c.quantile).item()
        if not (self.l_ref > 0 and math.isfinite(self.l_ref)):
            raise ValueError(f"consft needs a positive reference loss, got {self.l_ref}")

    def sample_batch(self, ctx: TaskContext, batch_size: int, generator: torch.Generator) -> dict:
        batch = super().sample_batch(ctx, batch_size, generator)
        if self.config.variant == "ratio":
            noise, time = self._draws
            batch["noise"], batch["time"] = noise[batch["index"]], time[batch["index"]]
        return batch

    def weights(self, per_sample: torch.Tensor) -> torch.Tensor:
        """sg(w_i) for the clip and dft variants."""
        losses = per_sample.detach()
        if self.config.variant == "clip":
            return torch.exp(-(losses - self.l_ref) / self.tau).clamp(self.config.w_min, 1.0)
        return torch.exp(-losses / self.tau)

    def loss(self, per_sample, batch, policy):
        c = self.config
        if c.variant == "ratio":
            log_ratio = (self._old_loss[batch["index"]] - per_sample) / self.tau
            # min(r, clip(r, 1-eps, 1+eps)) is min(r, 1+eps) for a positive advantage; clamping
            # the log first gives the same value and zero gradient past the clip without ever
            # forming exp(large) = inf, whose backward would be 0 * inf = NaN.
            objective = torch.exp(log_ratio.clamp(max=math.log1p(c.eps)))
            r = torch.exp(log_ratio.detach())
            stats = {"consft/ratio_mean": r.mean().item(),
                     "consft/frac_clipped": (r > 1 + c.eps).float().mean().item(),
                     "consft/frac_below": (r < 1 - c.eps).float().mean().item()}
            return -objective.mean(), stats
        w = self.weights(per_sample)
        stats = {"consft/weight_mean": w.mean().item(),
                 "consft/frac_at_floor": (w <= c.w_min * (1 + 1e-6)).float().mean().item()
                 if c.variant == "clip" else 0.0,
                 "consft/frac_at_one": (w >= 1 - 1e-6).float().mean().item(),
                 "consft/l_ref": self.l_ref}
        return (w * per_sample).mean(), stats

    def after_task(self, ctx: TaskContext) -> None:
        self._old_loss, self._draws = None, None  # per-task state: nothing carried over
