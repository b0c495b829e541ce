"""PackNet (Mallya & Lazebnik, 2018), as LIBERO's lifelong PackNet: one network, its weights
packed task by task.

After each task (the foundation, stage 0, included), among the Linear/Conv weights that task was
free to train, the `prune_ratio` smallest by magnitude in each layer are set to 0 and freed for
later tasks; the rest become the task's own and never change again. The task is then retrained
briefly with only its own weights (the freed ones held at 0). A later task trains only the freed
weights. Evaluating task i shows the network as it was for task i: weights owned by later tasks
(and free ones) are zeroed, so the method must be told the task at evaluation.

Biases, norms and every parameter that is not a Linear/Conv weight keep the foundation's values
(LIBERO never trains them after the first task, nor does the paper).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Annotated

import torch
from annotated_types import Ge, Gt, Interval, doc
from torch import nn

from methods import register_method
from methods.base import Method, MethodConfig, TaskContext

FREE = -1  # owner of a weight no task has kept yet
PRUNABLE = (nn.Linear, nn.Conv1d, nn.Conv2d, nn.Conv3d)


@dataclass
class PackNetConfig(MethodConfig):
    # of a task's trainable weights, the fraction freed (LIBERO's 0.75)
    prune_ratio: Annotated[float, Interval(gt=0, lt=1)] = 0.75
    # post-prune retraining, in steps as a fraction of the stage's (LIBERO: 50 epochs after 50)
    post_prune_fraction: Annotated[float, Ge(0), doc("0: no retraining")] = 1.0
    post_prune_lr: Annotated[float, Gt(0)] = 3e-4  # AdamW, as the benchmark's default lr
    post_prune_batch: Annotated[int, Ge(1)] = 256
    post_prune_grad_clip: Annotated[float, Ge(0), doc("0: no clipping")] = 1.0


def prunable_weights(policy: nn.Module, frozen: frozenset[str] = frozenset()
                     ) -> dict[str, nn.Parameter]:
    """The weights PackNet packs: those of every Linear and Conv layer, by parameter name, but
    the ones the policy keeps frozen (a checkpoint's vision tower, say)."""
    weights = {f"{name}.weight" if name else "weight": m.weight
               for name, m in policy.named_modules() if isinstance(m, PRUNABLE)}
    return {n: p for n, p in weights.items() if n not in frozen}


@register_method
class PackNet(Method):
    name = "packnet"
    Config = PackNetConfig
    task_aware_eval = True

    def __init__(self, config: PackNetConfig | None = None):
        super().__init__(config)
        # parameter name -> stage that owns each weight (FREE if none): all PackNet keeps
        self.owner: dict[str, torch.Tensor] | None = None
        self._weights: dict[str, nn.Parameter] = {}  # this stage: the packed weights, by name
        self._trainable: dict[str, torch.Tensor] = {}  # this stage: which weights may move
        self._held: dict[str, torch.Tensor] = {}  # this stage: the values of those that may not
        self._frozen: frozenset[str] | None = None  # parameters the policy froze itself

    def _ensure_owner(self, policy: nn.Module) -> dict[str, nn.Parameter]:
        if self._frozen is None:  # as the policy was found, before any stage set its flags
            self._frozen = frozenset(n for n, p in policy.named_parameters() if not p.requires_grad)
        weights = prunable_weights(policy, self._frozen)
        if self.owner is None:
            self.owner = {n: torch.full(p.shape, FREE, dtype=torch.int16) for n, p in weights.items()}
        self.owner = {n: self.owner[n].to(p.device) for n, p in weights.items()}  # as loaded: CPU
        return weights

    def _hold(self, weights: dict[str, nn.Parameter], trainable: dict[str, torch.Tensor]) -> None:
        self._weights, self._trainable = weights, trainable
        self._held = {n: p.detach().clone() for n, p in weights.items()}

    # -- training a task: only the free weights --------------------------------------------------

    def before_task(self, ctx: TaskContext) -> None:
        weights = self._ensure_owner(ctx.policy)
        packed = {id(p) for p in weights.values()}
        for p in ctx.policy.parameters():
            p.requires_grad_(id(p) in packed)
        self._hold(weights, {n: self.owner[n] == FREE for n in weights})

    def after_backward(self, policy: nn.Module) -> None:
        """Zero the gradient of kept weights, so that clipping sees only what may move."""
        for n, p in self._weights.items():
            if p.grad is not None:  # None: no loss reaches it (a VLA's unused lm_head)
                p.grad.mul_(self._trainable[n])

    @torch.no_grad()
    def after_step(self, policy: nn.Module) -> None:
        """Put kept weights back: AdamW's weight decay would move them even with no gradient."""
        for n, p in self._weights.items():
            p.copy_(torch.where(self._trainable[n], p, self._held[n]))

    # -- after a task: prune, then retrain the task's own weights ------------------------------

    def after_task(self, ctx: TaskContext) -> None:
        weights = self._ensure_owner(ctx.policy)
        self._prune(weights, ctx.stage)
        steps = round(self.config.post_prune_fraction * ctx.steps)
        if steps > 0:
            self._retrain(ctx, weights, steps)
        for n, p in ctx.policy.named_parameters():  # the policy as found
            p.requires_grad_(n not in self._frozen)
        self._weights, self._trainable, self._held = {}, {}, {}

    @torch.no_grad()
    def _prune(self, weights: dict[str, nn.Parameter], stage: int) -> None:
        """Per layer, free the `prune_ratio` smallest of the weights this stage trained."""
        for n, p in weights.items():
            owner, flat = self.owner[n].view(-1), p.detach().view(-1)
            candidates = torch.nonzero(owner == FREE).flatten()
            freed = round(self.config.prune_ratio * len(candidates))
            order = torch.argsort(flat[candidates].abs(), stable=True)
            owner[candidates] = stage
            owner[candidates[order[:freed]]] = FREE
            flat[candidates[order[:freed]]] = 0.0

    def _retrain(self, ctx: TaskContext, weights: dict[str, nn.Parameter], steps: int) -> None:
        """LIBERO's post-prune fine-tuning: a fresh AdamW on the task's data, only the weights
        the task keeps moving (freed ones stay 0, earlier tasks' stay fixed)."""
        c, policy = self.config, ctx.policy
        names, params = list(weights), list(weights.values())
        self._hold(weights, {n: self.owner[n] == ctx.stage for n in names})
        optimizer = torch.optim.AdamW(params, lr=c.post_prune_lr, weight_decay=0.0)
        g = torch.Generator().manual_seed(3000 + ctx.stage)
        was_training = policy.training
        policy.train()
        for _ in range(steps):
            per_sample = policy(ctx.data.sample(c.post_prune_batch, g), generator=g)
            # allow_unused: a weight no loss reaches (a VLA's unused lm_head) gets no gradient
            grads = torch.autograd.grad(per_sample.mean(), params, allow_unused=True)
            for n, p, grad in zip(names, params, grads):
                p.grad = None if grad is None else grad * self._trainable[n]
            if c.post_prune_grad_clip > 0:
                nn.utils.clip_grad_norm_(params, c.post_prune_grad_clip)
            optimizer.step()
            self.after_step(policy)
        for p in params:
            p.grad = None
        policy.train(was_training)

    # -- evaluation: the network as it was for the task -----------------------------------------

    @contextlib.contextmanager
    def evaluation_view(self, policy: nn.Module, task: str, stream: list[str]) -> Iterator[None]:
        """Zero the weights of tasks after `task` (and free ones); put them back on exit."""
        if self.owner is None:
            yield
            return
        level = stream.index(task) + 1 if task in stream else 0
        weights = self._ensure_owner(policy)
        saved = {n: p.detach().clone() for n, p in weights.items()}
        with torch.no_grad():
            for n, p in weights.items():
                owner = self.owner[n]
                p.mul_((owner != FREE) & (owner <= level))
        try:
            yield
        finally:
            with torch.no_grad():
                for n, p in weights.items():
                    p.copy_(saved[n])

    # -- checkpoints ---------------------------------------------------------------------------

    def state_dict(self):
        return {"owner": self.owner}

    def load_state_dict(self, state):
        self.owner = state["owner"]
