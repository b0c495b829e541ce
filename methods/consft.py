"""Conservative SFT (ConSFT) as the paper defines it: scale each sample's loss by the model's
confidence, with a temperature annealed over the stage.

Source: Zhang et al., 2026, "Preserving Foundational Capabilities in Flow-Matching VLAs through
Conservative SFT" (arXiv 2605.08879 v2): Eq. 5 and 11-12, appendix C.1, table 5. L_i is sample
i's flow-matching loss (the policy's per-sample loss: a mean over the chunk's steps and action
dimensions, the paper leaving the reduction open) and sg() stops the gradient.

`paper` (default; App. C.1 as written)
    loss   = mean(sg(w_i) * L_i)                                                 (Eq. 5)
    w_i    = max(w_min, exp(-kappa * L_i / tau(t)))
    rho(t) = (exp(-lambda * min(t/T, 1)^c) - exp(-lambda)) / (1 - exp(-lambda))  (Eq. 11)
    tau(t) = min(tau_start / max(rho(t), eps), tau_end)                          (Eq. 12)
  t is the optimizer step within the stage; tau rises from tau_start at t = 0 to tau_end by
  t = T, after which the objective is close to SFT. eps, which the paper leaves open, is 1e-8:
  any eps below tau_start / tau_end gives tau_end at t >= T.

`kappa_temp`: the other reading of App. C.1, kappa multiplying the temperature,
    w_i = max(w_min, exp(-L_i / (kappa * tau(t))))

`dft`: Eq. 5 at a fixed temperature, w_i = exp(-L_i / tau_fixed) (tau_fixed 1 is the paper's
  likelihood ratio exp(-L_i) itself): an ablation without the schedule and the floor.

`ratio`: the trust-region ratio the paper approximates, r_i = exp((L_i_old - L_i) / tau_fixed),
  loss = -mean(min(r_i, clip(r_i, 1 - clip_eps, 1 + clip_eps))), with L_i_old sample i's loss at
  the stage start under the same (t, noise) draws that every later step reuses for that sample,
  so no live reference network is kept. An ablation.

It keeps no copy of the network and no earlier data. Each step it logs tau(t), the mean weight,
the share of samples at the floor and quantiles of the per-sample loss, so a reader can see
where tau_start sits against the losses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Literal

import torch
from annotated_types import Ge, Gt, Interval

from methods import register_method
from methods.base import Method, MethodConfig, TaskContext
from policies.base import noise_shape, randn_from

LOSS_QUANTILES = (0.1, 0.5, 0.9)


@dataclass
class ConSFTConfig(MethodConfig):
    variant: Literal["paper", "kappa_temp", "dft", "ratio"] = "paper"
    tau_start: Annotated[float, Gt(0)] = 0.003  # tau(0); a per-task setting in the paper
    tau_end: Annotated[float, Gt(0)] = 5.0  # tau(t) for t >= T
    kappa: Annotated[float, Gt(0)] = 25.0
    lam: Annotated[float, Gt(0)] = 0.8  # lambda of Eq. 11: the schedule's curvature
    c: Annotated[float, Gt(0)] = 3.5  # the exponent of t/T in Eq. 11
    w_min: Annotated[float, Interval(ge=0, le=1)] = 1e-3  # the floor on the weight
    # T: steps from tau_start to tau_end; a per-task setting in the paper (table 5)
    anneal_steps: Annotated[int, Ge(1)] = 2000
    eps: Annotated[float, Gt(0)] = 1e-8  # the floor on rho(t) in Eq. 12 (left open by the paper)
    tau_fixed: Annotated[float, Gt(0)] = 1.0  # the dft and ratio variants' temperature
    clip_eps: Annotated[float, Interval(gt=0, lt=1)] = 0.2  # the ratio variant's trust region


def annealing(t: int, c: ConSFTConfig) -> float:
    """rho(t) of Eq. 11: 1 at t = 0, falling to 0 at t = T."""
    x = min(t / c.anneal_steps, 1.0) ** c.c
    return (math.exp(-c.lam * x) - math.exp(-c.lam)) / (1 - math.exp(-c.lam))


def temperature(t: int, c: ConSFTConfig) -> float:
    """tau(t) of Eq. 12: tau_start at t = 0, never decreasing, tau_end from t = T on."""
    return min(c.tau_start / max(annealing(t, c), c.eps), c.tau_end)


@register_method
class ConSFT(Method):
    name = "consft"
    Config = ConSFTConfig

    def __init__(self, config: ConSFTConfig | None = None):
        super().__init__(config)
        self.t = 0  # optimizer steps taken in this stage
        self._old_loss: torch.Tensor | None = None  # ratio: [N] per-sample loss at stage start
        self._draws: tuple[torch.Tensor, torch.Tensor] | None = None  # ratio: fixed (noise, t)

    @torch.no_grad()
    def before_task(self, ctx: TaskContext) -> None:
        self.t = 0
        if self.config.variant == "ratio":
            g = torch.Generator().manual_seed(ctx.stage)
            n = len(ctx.data)
            noise = randn_from(noise_shape(ctx.policy, n), g, ctx.data.actions.device)
            time = ctx.policy.sample_time(n, g)
            self._draws = (noise, time)
            self._old_loss = torch.cat([
                ctx.policy({**ctx.data.batch(idx), "noise": noise[idx], "time": time[idx]})
                for idx in torch.arange(n).split(1024)
            ])

    def sample_batch(self, ctx: TaskContext, batch_size: int, generator: torch.Generator) -> dict:
        batch = super().sample_batch(ctx, batch_size, generator)
        if self.config.variant == "ratio":
            noise, time = self._draws
            batch["noise"], batch["time"] = noise[batch["index"]], time[batch["index"]]
        return batch

    def weights(self, per_sample: torch.Tensor) -> torch.Tensor:
        """sg(w_i) at the current step, for the weighted variants (paper, kappa_temp, dft)."""
        c, losses = self.config, per_sample.detach().float()
        if c.variant == "dft":
            return torch.exp(-losses / c.tau_fixed)
        tau = temperature(self.t, c)
        scaled = c.kappa * losses / tau if c.variant == "paper" else losses / (c.kappa * tau)
        return torch.exp(-scaled).clamp_min(c.w_min)

    def loss(self, per_sample, batch, policy):
        c = self.config
        losses = per_sample.detach().float()
        # on the CPU: one copy of the batch's losses rather than a tensor sent up and three reads
        quantiles = torch.quantile(losses.cpu(), torch.tensor(LOSS_QUANTILES)).tolist()
        stats = {f"consft/loss_q{round(q * 100)}": v for q, v in zip(LOSS_QUANTILES, quantiles)}
        if c.variant == "ratio":
            log_ratio = (self._old_loss[batch["index"]] - per_sample) / c.tau_fixed
            # min(r, clip(r, 1-eps, 1+eps)) is min(r, 1+eps) for a positive advantage; clamping
            # the log first gives the same value and zero gradient past the clip without ever
            # forming exp(large) = inf, whose backward would be 0 * inf = NaN.
            objective = torch.exp(log_ratio.clamp(max=math.log1p(c.clip_eps)))
            r = torch.exp(log_ratio.detach())
            stats.update({"consft/ratio_mean": r.mean().item(),
                          "consft/frac_clipped": (r > 1 + c.clip_eps).float().mean().item(),
                          "consft/frac_below": (r < 1 - c.clip_eps).float().mean().item()})
            return -objective.mean(), stats
        w = self.weights(per_sample)
        stats.update({"consft/weight_mean": w.mean().item(),
                      "consft/frac_at_floor": (w <= c.w_min).float().mean().item()
                      if c.variant != "dft" else 0.0})
        if c.variant != "dft":
            stats["consft/tau"] = temperature(self.t, c)
        return (w.to(per_sample.dtype) * per_sample).mean(), stats

    def after_step(self, policy: torch.nn.Module) -> None:
        self.t += 1

    def after_task(self, ctx: TaskContext) -> None:
        self._old_loss, self._draws = None, None  # per-task state: nothing carried over
