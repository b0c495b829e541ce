"""Fine-tunes made elsewhere, measured as stages: `METHOD=checkpoints stage_paths=a,b,c`.

A user who fine-tuned a LeRobot checkpoint with lerobot-train (or openpi, or their own script)
gives the base as `policy_path` and one folder per stream stage. The protocol stays one: the
base is the foundation (evaluated at stage 0), and each stage trains zero steps and loads its
folder instead, weights and processors' statistics (a lerobot-train fine-tune normalizes with
its own dataset's statistics, not the base's). Every metric then follows as for a method that
trained: retention, plasticity, forgetting, held-out loss, update sparsity against the base.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated

from annotated_types import doc

from methods import register_method
from methods.base import Method, MethodConfig, TaskContext


@dataclass
class CheckpointsConfig(MethodConfig):
    # one LeRobot checkpoint folder per stream stage, comma-separated: a pretrained_model/, or
    # lerobot-train's checkpoints/<step>/ or checkpoints/last/
    stage_paths: Annotated[str, doc("folders, one per stage, comma-separated")] = ""
    # the run's name in tables, plots and results/ ("" is "checkpoints")
    label: Annotated[str, doc("a name for the fine-tunes")] = ""

    def paths(self) -> list[str]:
        return [p.strip() for p in self.stage_paths.split(",") if p.strip()]


@register_method
class CheckpointStages(Method):
    """Loads each stage's checkpoint instead of training: a fine-tune made elsewhere, measured
    from its base on the same evaluation episodes as any method."""

    name = "checkpoints"
    Config = CheckpointsConfig
    trains = False
    label_omits = ("stage_paths", "label")  # the label is the user's name, not the folders

    def __init__(self, config: CheckpointsConfig | None = None):
        super().__init__(config)
        if not self.config.paths():
            raise ValueError("METHOD=checkpoints needs stage_paths=: one LeRobot checkpoint "
                             "folder per stream stage, comma-separated")
        if any(c in self.config.label for c in "/[] "):
            raise ValueError(f"bad value {self.config.label!r} for label (method checkpoints): "
                             f"a name without spaces, slashes or brackets")

    @property
    def label(self) -> str:
        return self.config.label or self.name

    def check_setup(self, policy_config, stages: int) -> None:
        """The base is a LeRobot checkpoint, there is one folder per stage, and each is the
        base's architecture with the base's features and chunk."""
        from policies.lerobot.checkpoint import stage_mismatch

        base = getattr(policy_config, "path", "")
        if not base:
            raise ValueError("METHOD=checkpoints measures fine-tunes of a LeRobot checkpoint: "
                             "give the base as policy_path= (with policy=lerobot_pi0, "
                             "lerobot_pi05 or lerobot_smolvla)")
        paths = self.config.paths()
        if len(paths) != stages:
            raise ValueError(f"stage_paths names {len(paths)} folders; the benchmark has "
                             f"{stages} stream stages: one folder per stage")
        for stage, path in enumerate(paths, start=1):
            mismatch = stage_mismatch(base, path)
            if mismatch:
                raise ValueError(f"stage {stage}'s checkpoint {path!r} {mismatch}")

    def before_task(self, ctx: TaskContext) -> None:
        """Stage i's folder, weights and statistics, into the policy (stage 0 is the base)."""
        if ctx.stage > 0:
            ctx.policy.load_checkpoint_weights(self.config.paths()[ctx.stage - 1])

    def hyperparameters(self) -> dict:
        """The folders and their weights' digests: a run key changes with any folder's weights."""
        from policies.lerobot.checkpoint import checkpoint_identity

        return {**super().hyperparameters(),
                "stage_weights": [checkpoint_identity(p) for p in self.config.paths()]}
