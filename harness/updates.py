"""How much of the network a method rewrote: statistics of theta_i - theta_0.

A scalar counts as changed when |delta| exceeds rho times the RMS of its tensor in the
reference weights (rho = 1e-3 and 1e-2), so the threshold scales with each layer.
"""

from __future__ import annotations

import torch

RHOS = (1e-3, 1e-2)  # the headline thresholds (DESIGN.md)
LAYER_RHOS = (1e-5, 1e-4, 1e-3, 1e-2, 1e-1, 1.0)  # per layer: enough for a distribution plot


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
        rows.append(row)
        deltas.append(delta)
        total += delta.numel()
    flat = torch.cat(deltas)
    w_flat = torch.cat([w.flatten().double() for w in ref.values()])
    summary = {f"frac_changed_rho{rho:g}": changed[rho] / total for rho in RHOS}
    summary["hoyer_sparsity"] = hoyer_sparsity(flat)
    summary["relative_l2"] = float(flat.norm() / w_flat.norm().clamp_min(1e-12))
    return summary, rows
