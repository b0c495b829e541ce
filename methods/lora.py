"""LoRA (Hu et al., 2021): each task trains low-rank adapters beside frozen base weights.

For every targeted Linear layer with weight W, a task trains A [r, in] and B [out, r] (B starts at
0, so a fresh adapter changes nothing) and the layer computes x W^T + (alpha / r) x A^T B^T. After
the task the adapter is merged, W <- W + (alpha / r) B A, and removed: checkpoints, evaluation
and the update measurements see a plain policy with its own parameter names, and the next task
starts fresh adapters on the merged weights. Adapters are peft's (`LoraModel`).
"""

from __future__ import annotations

import copy
import re
from dataclasses import dataclass
from typing import Annotated

import torch
from annotated_types import Ge, Gt, Interval

from methods import register_method
from methods.base import Method, MethodConfig, TaskContext

ADAPTER = "default"


@dataclass
class LoRAConfig(MethodConfig):
    rank: Annotated[int, Ge(1)] = 8  # r (the paper's RoBERTa/DeBERTa setting)
    # the update is scaled by alpha / rank (the paper sets alpha to r)
    alpha: Annotated[float, Gt(0)] = 8.0
    dropout: Annotated[float, Interval(ge=0, lt=1)] = 0.0  # on the adapter's input (peft's default)
    # Python regex, full-matched against module names; the Linear layers among the matches get
    # adapters. The default: the action expert of FlowMatchingPolicy. ".*": every Linear layer.
    target: str = r"(action_in|blocks\..*|action_out\..*)"


@register_method
class LoRA(Method):
    name = "lora"
    Config = LoRAConfig

    def __init__(self, config: LoRAConfig | None = None):
        super().__init__(config)
        c = self.config
        try:
            self._pattern = re.compile(c.target)
        except re.error as exc:
            raise ValueError(f"target={c.target!r} is not a regular expression ({exc})") from None
        self._tuner = None  # peft's LoraModel while a task trains

    def target_modules(self, policy: torch.nn.Module) -> list[str]:
        """Names of the Linear layers that `target` selects; an error lists the candidates."""
        linear = [n for n, m in policy.named_modules() if isinstance(m, torch.nn.Linear)]
        names = [n for n in linear if self._pattern.fullmatch(n)]
        if not names:
            raise ValueError(f"lora target={self.config.target!r} matches no Linear layer; "
                             f"the policy's: {', '.join(linear)}")
        return names

    def before_task(self, ctx: TaskContext) -> None:
        """Fresh adapters on the targeted layers; every other parameter frozen (peft's marking),
        so the trainer optimizes the adapters alone."""
        names = self.target_modules(ctx.policy)
        exact = "|".join(re.escape(n) for n in names)
        # imported here: peft brings transformers (over 100 MB resident), which a run of any
        # other method, importing every registered method, should not pay for
        from peft import LoraConfig
        from peft.tuners.lora import LoraModel

        config = LoraConfig(r=self.config.rank, lora_alpha=self.config.alpha,
                            lora_dropout=self.config.dropout, bias="none",
                            target_modules=f"^(?:{exact})$")
        self._tuner = LoraModel(ctx.policy, config, ADAPTER)

    def mid_task_policy(self, policy: torch.nn.Module) -> torch.nn.Module:
        """While a task trains: a copy with the adapters merged and removed, under the policy's
        own parameter names; the training policy keeps its adapters."""
        if self._tuner is None:
            return policy
        return copy.deepcopy(self._tuner).merge_and_unload()

    def after_task(self, ctx: TaskContext) -> None:
        """Merge the adapters into the base weights and remove them (nothing at stage 0)."""
        if self._tuner is None:
            return
        self._tuner.merge_and_unload()
        self._tuner = None
        for p in ctx.policy.parameters():
            p.requires_grad_(True)
