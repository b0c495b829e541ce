"""The parameter update: global-norm clipping and AdamW over one flat buffer.

On a small CPU policy the update is memory-bound (parameters, gradients and both moments, about
17 MB a default-policy step through a 4 MB cache) and its per-call overhead is a tenth of a tiny
policy's step, so it is a handful of kernel calls over one flat buffer: the norm, the fused AdamW
kernel (which also applies the clipping, as its gradient divisor) and zeroing the gradient.
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


class FlatAdamW:
    """`clip_grad_norm_` then `torch.optim.AdamW(fused=True)` for one flat parameter, then the
    gradient zeroed, without `Optimizer.step`'s per-call bookkeeping (a third of the update on
    the tiny policy) or a separate pass to scale the gradient. `torch._fused_adamw_` is the kernel
    `AdamW(fused=True)` calls; `tests/test_trainer.py` holds this class to `torch.optim.AdamW`, so
    a torch upgrade that changes the kernel fails there. The kernel has CPU and CUDA versions;
    every tensor it gets lives on the parameters' device."""

    def __init__(self, flat: torch.nn.Parameter, lr: float, weight_decay: float,
                 grad_clip: float, betas: tuple[float, float] = (0.9, 0.999), eps: float = 1e-8):
        self.flat, self.grad_clip, self.beta2, self.eps = flat, grad_clip, betas[1], eps
        self.hyper = dict(lr=lr, beta1=betas[0], beta2=betas[1], weight_decay=weight_decay,
                          eps=eps, amsgrad=False, maximize=False)
        self.exp_avg, self.exp_avg_sq = torch.zeros_like(flat), torch.zeros_like(flat)
        # the kernel reads it, as in torch, from the parameters' device (CPU or CUDA)
        self.step_count = torch.zeros((), dtype=torch.float32, device=flat.device)

    def step(self) -> None:
        grad = self.flat.grad
        divisor = None  # the kernel divides the gradient by it before the update
        if self.grad_clip > 0:
            divisor = ((torch.linalg.vector_norm(grad) + 1e-6) / self.grad_clip).clamp_min(1.0)
        self.step_count += 1
        torch._fused_adamw_([self.flat.data], [grad], [self.exp_avg], [self.exp_avg_sq], [],
                            [self.step_count], grad_scale=divisor, **self.hyper)
        grad.zero_()  # backward accumulates into it in place

    @torch.no_grad()
    def frac_eps_dominated(self) -> float:
        """The share of scalars whose update denominator sqrt(v_hat) + eps is set by eps:
        sqrt(v_hat) < eps, where v_hat is the bias-corrected second moment."""
        correction = 1 - self.beta2 ** float(self.step_count)
        if correction <= 0:
            return float("nan")
        return (self.exp_avg_sq < self.eps ** 2 * correction).float().mean().item()
