"""The parameter update: global-norm clipping and torch's fused AdamW over one flat buffer.

On a small CPU policy the update is memory-bound (parameters, gradients and both moments, about
17 MB a default-policy step through a 4 MB cache) and its per-call overhead is a tenth of a tiny
policy's step, so the parameters live in one flat buffer and the update is a handful of kernel
calls over it: the norm and the clipping, the fused AdamW kernel, zeroing the gradient.
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import torch


@contextmanager
def contiguous_parameters(params: list[torch.nn.Parameter]) -> Iterator[torch.nn.Parameter]:
    """Lay `params` and their gradients out in two flat buffers, yielding one flat parameter.

    Every parameter becomes a view into the flat buffer and its `.grad` a view into the flat
    gradient (backward accumulates into it in place, as DDP's `gradient_as_bucket_view` does), so
    the update is a few kernels over one tensor instead of a few per parameter. On exit the
    parameters get their own storage back.
    """
    flat = torch.nn.Parameter(torch.cat([p.detach().reshape(-1) for p in params]))
    flat.grad = torch.zeros_like(flat)
    offset = 0
    for p in params:
        n = p.numel()
        p.data = flat.data[offset:offset + n].view_as(p)
        p.grad = flat.grad[offset:offset + n].view_as(p)
        offset += n
    try:
        yield flat
    finally:
        for p in params:
            p.data = p.data.clone()
            p.grad = None


class ClippedAdamW:
    """The update a training step ends with: `clip_grad_norm_`, then torch's
    `AdamW(fused=True)`, then the gradient zeroed in place (backward accumulates into the flat
    gradient's views, so it is never set to None). Over one flat parameter each is one kernel
    call, on the CPU and on CUDA."""

    def __init__(self, flat: torch.nn.Parameter, lr: float, weight_decay: float,
                 grad_clip: float, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        self.flat, self.grad_clip = flat, grad_clip
        self.adamw = torch.optim.AdamW([flat], lr=lr, betas=betas, eps=eps,
                                       weight_decay=weight_decay, fused=True)

    def step(self) -> None:
        if self.grad_clip > 0:
            torch.nn.utils.clip_grad_norm_(self.flat, self.grad_clip)
        self.adamw.step()
        self.flat.grad.zero_()

    def state_dict(self) -> dict:
        return self.adamw.state_dict()

    def load_state_dict(self, state: dict) -> None:
        self.adamw.load_state_dict(state)

    @torch.no_grad()
    def frac_eps_dominated(self) -> float:
        """The share of scalars whose update denominator sqrt(v_hat) + eps is set by eps:
        sqrt(v_hat) < eps, where v_hat is the bias-corrected second moment."""
        state = self.adamw.state.get(self.flat)
        if not state:
            return float("nan")
        group = self.adamw.param_groups[0]
        correction = 1 - group["betas"][1] ** float(state["step"])
        return (state["exp_avg_sq"] < group["eps"] ** 2 * correction).float().mean().item()
