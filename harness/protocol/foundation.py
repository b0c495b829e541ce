"""The foundation stage: multi-task pre-training, cached by a hash of its config, shared by all
methods (so every method starts from the same weights), with its stage-0 evaluation."""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass
from pathlib import Path

import torch

from harness.common.device import resolve_device
from harness.common.seeding import derive_seed, generator
from harness.config.benchmark import BenchConfig
from harness.data.lerobot.checkpoint import checkpoint_features, protocol_features
from harness.data.prepare import BenchmarkData, demo_spec
from harness.evaluate.recording import VideoSettings
from harness.evaluate.rollouts import Evaluator
from harness.evaluate.stages import StageRecord, evaluate_stage, load_checkpoint, save_checkpoint
from harness.evaluate.videos import VideoWriter
from harness.train.trainer import Snapshots, TrainSettings, train_stage
from methods import Method, TaskContext
from policies import get_policy, make_config, policy_for_config
from policies.flow_matching.modeling import ARCHITECTURE_VERSION
from policies.lerobot.checkpoint import checkpoint_identity
from suites import Suite
from suites.base import CAMERA_KEYS

FOUNDATION_VERSION = 7  # bump when the training code changes what a cached checkpoint holds
# (5: instruction embeddings encoded one text at a time, policies/text_encoder.py; 6: the update
# is clip_grad_norm_ then torch.optim.AdamW(fused=True), which rounds the clipped gradient
# differently from the fused kernel's divisor: mw-quick's foundation moved by up to 8.3e-7;
# 7: Python 3.12, torch 2.11, NumPy 2 and lerobot 0.6, whose CPU kernels round differently)


@dataclass
class Foundation:
    key: str
    policy_state: dict[str, torch.Tensor]
    final_loss: float
    stage0: StageRecord
    videos: Path | None = None  # stage 0's videos (in the cache, shared by every method)


def check_takes_a_path(cfg: BenchConfig) -> None:
    """ValueError when `policy_path` is given to a policy that loads no checkpoint (or the policy
    is unknown, naming the valid ones)."""
    if cfg.policy_path and "path" not in get_policy(cfg.policy).Config.__dataclass_fields__:
        raise ValueError(f"policy {cfg.policy!r} takes no policy_path; the LeRobot policies "
                         f"(lerobot_pi0, lerobot_pi05, lerobot_smolvla) do")


def policy_config(cfg: BenchConfig, suite: Suite):
    """The `cfg.policy` policy's config for this suite; ValueError on an unknown policy or size.
    Of the optional fields (policies/base.py) the harness fills those the Config declares."""
    check_takes_a_path(cfg)
    image_keys = CAMERA_KEYS if cfg.cameras else ()
    declared = get_policy(cfg.policy).Config.__dataclass_fields__
    optional = {}
    if "path" in declared:
        optional["path"] = cfg.policy_path
    if "instructions" in declared:  # a batch's "instruction_id" indexes them: cfg.all_tasks()
        optional["instructions"] = tuple(suite.instruction(t) for t in cfg.all_tasks())
    if "rotate_images" in declared:
        optional["rotate_images"] = cfg.lerobot_rotate_images
    if "features" in declared and cfg.policy_path:
        features = checkpoint_features(cfg, suite)
        optional["features"] = tuple(features.items())
        image_keys = tuple(k for k in image_keys if k in features)
    elif "features" in declared and (named := protocol_features(suite, image_keys)):
        optional["features"] = tuple(named.items())  # lerobot-eval's names (libero-lerobot)
    if "weights" in declared and cfg.policy_path:
        optional["weights"] = checkpoint_identity(cfg.policy_path)
    return make_config(cfg.policy, state_dim=suite.state_dim, action_dim=suite.action_dim,
                       size=cfg.policy_size, chunk_size=cfg.chunk_size,
                       n_action_steps=cfg.n_action_steps, image_keys=image_keys,
                       image_size=cfg.image_size, **optional)


def build_policy(cfg: BenchConfig, suite: Suite) -> torch.nn.Module:
    """A fresh policy on `cfg.device`, compiled when `cfg.compile` (its state dict unchanged)."""
    policy = policy_for_config(policy_config(cfg, suite)).to(resolve_device(cfg.device))
    if cfg.compile:
        policy.compile()
    return policy


def _hash(obj) -> str:
    return hashlib.sha256(json.dumps(obj, sort_keys=True, default=str).encode()).hexdigest()[:16]


def foundation_key(cfg: BenchConfig, suite: Suite, seed: int) -> str:
    policy = {**policy_config(cfg, suite).__dict__}
    if cfg.policy != "mlp":  # mlp's keys predate the registry and stay valid
        policy["name"] = cfg.policy
        policy["architecture"] = getattr(get_policy(cfg.policy), "ARCHITECTURE_VERSION", 0)
    device = resolve_device(cfg.device)
    if device.type != "cpu" or cfg.compile:  # GPU and compiled numerics differ from the CPU's
        policy["device"] = [device.type, cfg.compile]
    return _hash({
        "version": [FOUNDATION_VERSION, ARCHITECTURE_VERSION], "seed": seed, "policy": policy,
        "demos": [demo_spec(cfg, suite, t, "demo").key() for t in cfg.foundation_tasks],
        "train": [cfg.foundation_steps, cfg.batch_size, cfg.foundation_lr, cfg.weight_decay,
                  cfg.grad_clip],
    })


def stage0_key(cfg: BenchConfig, suite: Suite) -> str:
    tasks = cfg.all_tasks()
    spec = {"eval": [cfg.eval_episodes, cfg.max_episode_steps, cfg.n_action_steps, cfg.eval_shards],
            "heldout": [demo_spec(cfg, suite, t, "heldout").key() for t in tasks]}
    if cfg.eval_step_cap:  # off, the key is as before the cap existed
        spec["eval"].append(cfg.eval_step_cap)
    if suite.evaluation_version:  # "", the key is as before the suite versioned its episodes
        spec["evaluation"] = suite.evaluation_version
    if cfg.spatial_episodes > 0:  # off, the key (and the cached record) is as before the probe
        spec["spatial"] = [cfg.spatial_episodes, suite.spatial_probe_version]
    return _hash(spec)


def load_or_train_foundation(cfg: BenchConfig, suite: Suite, data: BenchmarkData, seed: int,
                             evaluator: Evaluator, log=None) -> Foundation:
    key = foundation_key(cfg, suite, seed)
    directory = Path(cfg.cache_dir) / "foundation" / key
    weights, stage0_path = directory / "policy.pt", directory / f"stage0-{stage0_key(cfg, suite)}.pt"
    torch.manual_seed(derive_seed(seed, "foundation"))  # the initial weights depend on the seed only
    policy = build_policy(cfg, suite)
    if cfg.policy_path:  # a LeRobot checkpoint is the foundation: evaluated, never retrained
        final_loss = float("nan")
    elif weights.exists():
        saved = load_checkpoint(weights)
        policy.load_state_dict(saved["policy"])
        final_loss = saved["final_loss"]
    else:
        train = data.combined(cfg.foundation_tasks)
        policy.state_norm.fit(train.obs["state"])
        policy.action_norm.fit(train.actions.flatten(0, 1))
        ctx = TaskContext(stage=0, task="foundation", data=train, policy=policy,
                          foundation_loss=float("nan"), steps=cfg.foundation_steps)
        settings = TrainSettings(cfg.foundation_steps, cfg.batch_size, cfg.foundation_lr,
                                 cfg.weight_decay, cfg.grad_clip)
        snapshot = directory / "snapshot.pt"
        result = train_stage(ctx, Method(), settings, generator(seed, "foundation"), log,
                             snapshots=_snapshots(snapshot, cfg, seed),
                             progress=f"foundation seed {seed}" if cfg.progress else "")
        final_loss = result.final_loss
        save_checkpoint(weights, {"policy": policy.state_dict(), "final_loss": final_loss,
                                  "config": cfg.as_dict()})
        snapshot.unlink(missing_ok=True)
    videos = VideoSettings.of(cfg)
    videos_dir = directory / f"videos-{stage0_key(cfg, suite)}-{videos.key()}" if videos else None
    missing_videos = videos_dir is not None and not any(videos_dir.glob("stage0.json"))
    stage0 = StageRecord(**load_checkpoint(stage0_path)) if stage0_path.exists() else None
    if stage0 is None or missing_videos:  # a cached record without its videos: evaluated again,
        # the same episodes (a fixed policy, seeded noise), now recorded
        writer = VideoWriter(suite, videos, videos_dir, cfg.eval_episodes) if videos else None
        evaluated = evaluate_stage(policy, evaluator, cfg, data, seed, 0, "foundation",
                                   videos=writer)
        if stage0 is None:
            stage0 = evaluated
            stage0.train_loss = final_loss
            save_checkpoint(stage0_path, stage0.as_dict())
    return Foundation(key, policy.state_dict(), final_loss, stage0, videos_dir)


def _snapshots(path: Path, cfg: BenchConfig, seed: int) -> Snapshots:
    """The foundation's mid-training snapshots, beside its weights (the directory's key is the
    foundation's, so a snapshot never meets other settings)."""
    def load() -> dict | None:
        if not path.exists():
            return None
        state = load_checkpoint(path)
        print(f"[retain] foundation seed {seed}: resuming at step {state['step']} of "
              f"{cfg.foundation_steps}", flush=True)
        return state

    return Snapshots(load, lambda state: save_checkpoint(path, state), cfg.snapshot_minutes * 60)
