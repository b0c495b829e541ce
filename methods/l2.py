"""L2 towards the foundation weights: loss + lambda/2 * ||theta - theta_0||^2."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from annotated_types import Ge

from methods import register_method
from methods.anchored import AnchoredMethod
from methods.base import MethodConfig, TaskContext, snapshot


@dataclass
class L2Config(MethodConfig):
    strength: Annotated[float, Ge(0)] = 1.0  # lambda


@register_method
class L2ToReference(AnchoredMethod):
    name = "l2"
    Config = L2Config

    def after_task(self, ctx: TaskContext) -> None:
        if ctx.stage == 0:  # the foundation weights are the reference for the whole stream
            self.anchor = snapshot(ctx.policy)
