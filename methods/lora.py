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
    # adapters. "": the policy's own `lora_target` (FlowMatchingPolicy's action expert; a LeRobot
    # policy's LeRobot PEFT defaults). ".*": every Linear layer.
    target: str = ""


@register_method
class LoRA(Method):
    name = "lora"
    Config = LoRAConfig

    def __init__(self, config: LoRAConfig | None = None):
        super().__init__(config)
        c = self.config
        try:
            re.compile(c.target)
        except re.error as exc:
            raise ValueError(f"target={c.target!r} is not a regular expression ({exc})") from None
        self._tuner = None  # peft's LoraModel while a task trains
        self._trainable: dict[str, bool] = {}  # the policy's own flags, restored after a task

    def target_modules(self, policy: torch.nn.Module) -> list[str]:
        """Names of the Linear layers that `target` selects; an error lists the candidates."""
        target = self.config.target or getattr(policy, "lora_target", "")
        linear = [n for n, m in policy.named_modules() if isinstance(m, torch.nn.Linear)]
        if not target:
            raise ValueError(f"lora needs target=REGEX for {type(policy).__name__}, which names "
                             f"no lora_target; its Linear layers: {_preview(linear)}")
        names = [n for n in linear if re.fullmatch(target, n)]
        if not names:
            raise ValueError(f"lora target={target!r} matches no Linear layer; the policy's: "
                             f"{_preview(linear)}")
        return names

    def before_task(self, ctx: TaskContext) -> None:
        """Fresh adapters on the targeted layers; every other parameter frozen (peft's marking),
        so the trainer optimizes the adapters alone."""
        names = self.target_modules(ctx.policy)
        self._trainable = {n: p.requires_grad for n, p in ctx.policy.named_parameters()}
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
        for n, p in ctx.policy.named_parameters():  # as found (a checkpoint may freeze parts)
            p.requires_grad_(self._trainable.get(n, True))


def _preview(names: list[str], most: int = 12) -> str:
    shown = ", ".join(names[:most])
    return shown + (f", ... ({len(names)} in all)" if len(names) > most else "")
