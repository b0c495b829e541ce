"""How much of the network a method rewrote: statistics of theta_i - theta_0.

A scalar counts as changed when |delta| exceeds rho times the RMS of its tensor in the
reference weights (rho = 1e-3 and 1e-2), so the threshold scales with each layer. The ConSFT
paper's own measure (its Eq. 8) is per scalar instead: the share of scalars whose relative
deviation |theta - theta_0| / |theta_0| stays below delta = 1e-3.
"""

from __future__ import annotations

import torch

RHOS = (1e-3, 1e-2)  # the headline thresholds (DESIGN.md)
LAYER_RHOS = (1e-5, 1e-4, 1e-3, 1e-2, 1e-1, 1.0)  # per layer: enough for a distribution plot
PAPER_DELTA = 1e-3  # the paper's Eq. 8 threshold


def _within_delta(w0: torch.Tensor, w: torch.Tensor, delta: float) -> torch.Tensor:
    """Per scalar: |w - w0| <= delta * |w0| (a scalar at 0 that stays at 0 counts as kept)."""
    return (w - w0).abs() <= delta * w0.abs()


def paper_sparsity(ref: dict[str, torch.Tensor], cur: dict[str, torch.Tensor],
                   delta: float = PAPER_DELTA) -> tuple[float, dict[str, float]]:
    """The paper's Eq. 8: the share of scalars with |theta - theta_0| / |theta_0| < delta,
    over the whole network (weighted by size) and per layer."""
    kept, total, layers = 0, 0, {}
    for name, w0 in ref.items():
        n = int(_within_delta(w0, cur[name], delta).sum())
        layers[name] = n / max(1, w0.numel())
        kept, total = kept + n, total + w0.numel()
    return kept / max(1, total), layers


def hoyer_sparsity(x: torch.Tensor) -> float:
    """(sqrt(n) - |x|_1 / |x|_2) / (sqrt(n) - 1): 0 for a uniform vector, 1 for one non-zero."""
    n = x.numel()
    l2 = x.norm()
    if n < 2 or l2 == 0:
        return 0.0
    return float((n**0.5 - x.abs().sum() / l2) / (n**0.5 - 1))


def update_stats(ref: dict[str, torch.Tensor], cur: dict[str, torch.Tensor]
                 ) -> tuple[dict[str, float], list[dict]]:
    """(whole-network figures, per-layer rows) for cur - ref, both name -> learned weights."""
    deltas, rows = [], []
    changed = {rho: 0 for rho in RHOS}
    total = 0
    for name, w0 in ref.items():
        delta = (cur[name] - w0).flatten().double()
        rms = w0.double().pow(2).mean().sqrt().clamp_min(1e-12)
        row = {"layer": name, "numel": delta.numel(),
               "relative_l2": float(delta.norm() / w0.double().norm().clamp_min(1e-12))}
        ratio = delta.abs() / rms
        for rho in LAYER_RHOS:
            frac = (ratio > rho).double().mean().item()
            row[f"frac_changed_rho{rho:g}"] = frac
            if rho in changed:
                changed[rho] += frac * delta.numel()
        row["eq8_sparsity"] = float(_within_delta(w0, cur[name], PAPER_DELTA).double().mean())
        rows.append(row)
        deltas.append(delta)
        total += delta.numel()
    flat = torch.cat(deltas)
    w_flat = torch.cat([w.flatten().double() for w in ref.values()])
    summary = {f"frac_changed_rho{rho:g}": changed[rho] / total for rho in RHOS}
    summary["hoyer_sparsity"] = hoyer_sparsity(flat)
    summary["relative_l2"] = float(flat.norm() / w_flat.norm().clamp_min(1e-12))
    summary["eq8_sparsity"] = paper_sparsity(ref, cur)[0]
    return summary, rows
