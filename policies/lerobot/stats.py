"""A LeRobot policy's normalization statistics, kept as buffers so they travel in its state dict.

LeRobot's processors normalize with a dataset's statistics (mean/std, min/max or quantiles, per
its `normalization_mapping`). Retain fits them on the foundation data (`fit`, the harness's
normalizer contract), or reads them from a checkpoint's processors (`load_stats`); the adapter
hands them to LeRobot's own normalizer steps. Fitting floors each spread, as Retain's own
normalizer does, so that a dimension constant in the foundation data (an empty object slot) does
not turn a new task's values into 1e8 standard deviations under LeRobot's eps of 1e-8.
"""

from __future__ import annotations

import torch
from torch import nn

STAT_NAMES = ("mean", "std", "min", "max", "q01", "q99", "q10", "q90")


class LeRobotStats(nn.Module):
    def __init__(self, dim: int, spread_floor: float):
        super().__init__()
        self.spread_floor = spread_floor
        for name in STAT_NAMES:
            low = name in ("min", "q01", "q10")
            start = torch.zeros(dim) if name == "mean" else torch.ones(dim) * (-1.0 if low else 1.0)
            self.register_buffer(name, start)
        self.version = 0  # bumped when the statistics change; the adapter re-reads them then

    @torch.no_grad()
    def fit(self, x: torch.Tensor) -> None:
        """Statistics of rows of `x` ([N, dim]), each spread floored."""
        x = x.double()
        mean = x.mean(0)
        floor = self.spread_floor
        values = {"mean": mean, "std": x.std(0, unbiased=False).clamp_min(floor)}
        for low, high, q in (("min", "max", None), ("q01", "q99", 0.01), ("q10", "q90", 0.10)):
            lo = x.min(0).values if q is None else torch.quantile(x, q, dim=0)
            hi = x.max(0).values if q is None else torch.quantile(x, 1 - q, dim=0)
            centre, spread = (lo + hi) / 2, ((hi - lo) / 2).clamp_min(floor)
            values[low], values[high] = centre - spread, centre + spread
        self.load_stats(values)

    @torch.no_grad()
    def load_stats(self, stats: dict) -> None:
        """Take the statistics LeRobot's processors hold (any of STAT_NAMES they have)."""
        for name in STAT_NAMES:
            if name in stats:
                getattr(self, name).copy_(torch.as_tensor(stats[name]).reshape(-1))
        self.version += 1

    def as_stats(self) -> dict[str, torch.Tensor]:
        """LeRobot's form: {stat name: [dim] tensor}."""
        return {name: getattr(self, name).detach().cpu() for name in STAT_NAMES}
