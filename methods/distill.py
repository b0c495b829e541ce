"""Learning without Forgetting (Li & Hoiem, 2017) for flow matching: distil a frozen reference
network's velocity field on the current task's observations.

    loss = mean_i l_i + lambda * mean_i ||v_theta(x_t, t, o_i) - v_ref(x_t, t, o_i)||^2

at the same draws (t, noise) for both networks, the ones the flow-matching loss l_i uses, so the
penalty measures how the policy's field moved where it is trained. ||.||^2 is averaged over the
chunk's valid steps and action dimensions, as l_i is, so lambda = 1 weighs both alike.

The reference is a frozen deep copy of the network, run beside the policy at every step: the
"parallel reference network" ConSFT claims to avoid, and the reason the report marks it.
- `reference=previous` (default, LwF's): the model before the current task, copied at the task's
  start; the penalty is zero at the first step of every task and grows as the policy moves.
- `reference=foundation`: the foundation, copied after stage 0 and kept for the whole stream.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from typing import Annotated, Literal

import torch
from annotated_types import Ge

from methods import register_method
from methods.base import Method, MethodConfig, TaskContext
from policies.base import noise_shape, randn_from


@dataclass
class DistillConfig(MethodConfig):
    # lambda (LwF's lambda_o is 1; mw-quick sweep, docs/methods.md)
    strength: Annotated[float, Ge(0)] = 0.1
    # previous: the model before this task; foundation: stage 0's
    reference: Literal["previous", "foundation"] = "previous"


@register_method
class Distill(Method):
    name = "distill"
    Config = DistillConfig
    uses_reference_copy = True

    def __init__(self, config: DistillConfig | None = None):
        super().__init__(config)
        self.reference_state: dict[str, torch.Tensor] | None = None  # the copy's weights
        self._reference: torch.nn.Module | None = None  # the copy, built from them

    def _copy(self, policy: torch.nn.Module) -> None:
        self._reference = copy.deepcopy(policy).requires_grad_(False).eval()
        self.reference_state = self._reference.state_dict()  # shares the copy's storage

    def after_task(self, ctx: TaskContext) -> None:
        if ctx.stage == 0 and self.config.reference == "foundation":
            self._copy(ctx.policy)

    def before_task(self, ctx: TaskContext) -> None:
        if self.config.reference == "previous":
            self._copy(ctx.policy)
        else:  # built now from a loaded checkpoint, before the trainer lays out the weights
            self.reference(ctx.policy)

    def reference(self, policy: torch.nn.Module) -> torch.nn.Module:
        """The frozen copy; rebuilt from its weights after a checkpoint was loaded."""
        if self._reference is None:
            if self.reference_state is None:
                raise ValueError("distill has no reference network: with reference=foundation "
                                 "it needs stage 0's after_task, else the task's before_task")
            self._reference = copy.deepcopy(policy).requires_grad_(False).eval()
            self._reference.load_state_dict(self.reference_state)
            self.reference_state = self._reference.state_dict()
        return self._reference

    def sample_batch(self, ctx: TaskContext, batch_size: int, generator: torch.Generator) -> dict:
        """The batch with its (noise, time) draws fixed, so both networks see the same x_t. They
        are drawn in the order and from the generator the policy's forward would use, so the
        flow-matching losses are those plain SFT would compute."""
        batch = super().sample_batch(ctx, batch_size, generator)
        actions = batch["actions"]
        batch["noise"] = randn_from(noise_shape(ctx.policy, len(actions)), generator,
                                    actions.device)
        batch["time"] = ctx.policy.sample_time(len(actions), generator)
        return batch

    def penalty(self, batch: dict, policy: torch.nn.Module) -> torch.Tensor:
        """mean_i ||v_theta - v_ref||^2 over the valid chunk steps, as l_i averages."""
        student = policy.predicted_velocity(batch)
        with torch.no_grad():
            teacher = self.reference(policy).predicted_velocity(batch)
        sq = (student - teacher) ** 2
        mask = batch.get("action_mask")
        if mask is None:
            return sq.mean()
        m = mask[:, :, None].to(sq.dtype)
        per_sample = (sq * m).sum(dim=(1, 2)) / (m.sum(dim=(1, 2)) * sq.shape[-1]).clamp_min(1.0)
        return per_sample.mean()

    def loss(self, per_sample, batch, policy):
        penalty = self.penalty(batch, policy)
        return (per_sample.mean() + self.config.strength * penalty,
                {"distill/penalty": penalty.item()})

    def state_dict(self):
        return {"reference": self.reference_state}

    def load_state_dict(self, state):
        self.reference_state, self._reference = state["reference"], None
