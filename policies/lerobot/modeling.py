"""LeRobot's PI0, PI0.5 and SmolVLA behind Retain's policy contract (`policies/base.py`).

The network, its loss and its sampling are LeRobot's own: `forward` is LeRobot's
`forward(batch, reduction="none")` with the flow-matching draws (noise, time) fixed by Retain
(so held-out losses, ConSFT's stage-start losses and EWC's Fisher see fixed draws), and
`sample_actions` is LeRobot's `predict_action_chunk` from Retain's noise. Observations go
through LeRobot's own processors: Retain's keys are renamed to the checkpoint's features
(`config.features`), images become LeRobot's float CHW in [0, 1], each row's instruction text
(`config.instructions[instruction_id]`) is tokenized by the policy's tokenizer (PI0.5's prompt
also carries the discretized state), and state and actions are normalized with the statistics
in `state_norm` / `action_norm` (fitted on the foundation data, or the checkpoint's own).

LeRobot pads actions to `max_action_dim` and draws noise there too, so the noise a caller fixes
is [B, H, noise_dim] (`policies.base.noise_shape`); the suite's A dimensions come back.
"""

from __future__ import annotations

import contextlib
import dataclasses
import io
import json
import logging
import shutil
import tempfile
from pathlib import Path
from typing import ClassVar

import torch
from torch import nn

from policies.base import beta_time, randn_from
from policies.lerobot.checkpoint import (
    CheckpointError,
    check_loaded,
    checkpoint_folder,
    first_line,
    hub_offline,
    read_config,
)
from policies.lerobot.configuration import (
    LeRobotConfig,
    LeRobotPi0Config,
    LeRobotPi05Config,
    LeRobotSmolVLAConfig,
)
from policies.lerobot.reduced import (
    minilm_tokenizer,
    read_architecture,
    reduced_paligemma,
    write_architecture,
    write_smolvlm_folder,
)
from policies.lerobot.stats import LeRobotStats

STATE_FEATURE, ACTION_FEATURE = "observation.state", "action"
STATE_SPREAD_FLOOR, ACTION_SPREAD_FLOOR = 1e-2, 5e-2  # Retain's normalizer floors
TOKENIZER_DIR, VLM_DIR = "tokenizer", "vlm"  # a checkpoint's own tokenizer and VLM config
PALIGEMMA_TOKENIZER = "google/paligemma-3b-pt-224"  # what LeRobot's PI0 / PI0.5 processors load


def default_features(image_keys: tuple[str, ...]) -> dict[str, str]:
    """A random init's feature names: LeRobot's state, a camera under its Retain name."""
    return {"state": STATE_FEATURE, **{k: f"observation.images.{k}" for k in image_keys}}


class LeRobotPolicy(nn.Module):
    """One of LeRobot's policies (`self.model`) with its processors and statistics."""

    Config: ClassVar[type[LeRobotConfig]] = LeRobotConfig
    ARCHITECTURE_VERSION = 1
    supports_vmap = False  # its processors tokenize text: per-sample gradients loop instead
    needs_cameras = True  # LeRobot's PI0, PI0.5 and SmolVLA need at least one image

    def __init__(self, config: LeRobotConfig):
        super().__init__()
        self.config = config
        self.state_norm = LeRobotStats(config.state_dim, STATE_SPREAD_FLOOR)
        self.action_norm = LeRobotStats(config.action_dim, ACTION_SPREAD_FLOOR)
        if config.path and not config.features:
            raise ValueError("a LeRobot checkpoint needs config.features: which of its input "
                             "features each of Retain's observations is (the plan sets them)")
        self.features = dict(config.features) or default_features(config.image_keys)
        self._scratch = None  # a reduced SmolVLA's VLM folder, for a random init
        if config.path:
            self.model, self._tokenizer = self._load(checkpoint_folder(config.path))
        else:
            self.model, self._tokenizer = self._build()
        self.noise_dim = int(self.model.config.max_action_dim)
        self._other_stats: dict = {}  # a checkpoint's statistics of features Retain never sets
        pre, post = self._make_processors()
        if config.path:
            self._other_stats = self._take_stats(pre)
        # the processors and the statistics' versions and device they were made with
        self._processors = (pre, post, self._versions(), torch.device("cpu"))
        self.register_load_state_dict_post_hook(lambda module, keys: module._stats_changed())

    # -- building and loading ---------------------------------------------------------------

    def _lerobot_config(self):
        """LeRobot's config for a random init at `config.size`, from the suite's shapes."""
        from lerobot.configs import FeatureType, PolicyFeature
        from lerobot.policies.factory import make_policy_config

        c = self.config
        s = c.image_size
        inputs = {self.features["state"]: PolicyFeature(FeatureType.STATE, (c.state_dim,))}
        inputs.update({self.features[k]: PolicyFeature(FeatureType.VISUAL, (3, s, s))
                       for k in c.image_keys})
        fields = dict(device="cpu", chunk_size=c.chunk_size, n_action_steps=c.n_action_steps,
                      # LeRobot pads state and actions to these (32 unless a suite needs more:
                      # Meta-World's state is 39-D, LIBERO's object poses 65-D)
                      max_state_dim=max(32, c.state_dim), max_action_dim=max(32, c.action_dim),
                      input_features=inputs,
                      output_features={ACTION_FEATURE: PolicyFeature(FeatureType.ACTION,
                                                                     (c.action_dim,))})
        if c.KIND == "smolvla":
            fields.update(resize_imgs_with_padding=(s, s), load_vlm_weights=False,
                          num_steps=c.num_inference_steps,
                          # Retain pre-trains the whole network from scratch
                          freeze_vision_encoder=False, train_expert_only=False)
            size = c.SIZES[c.size]
            if size is not None:
                self._scratch = Path(tempfile.mkdtemp(prefix="retain-smolvlm-"))
                write_smolvlm_folder(size, s, self._scratch / VLM_DIR)
                fields.update(vlm_model_name=str(self._scratch / VLM_DIR),
                              num_vlm_layers=size.layers)
        else:
            fields.update(image_resolution=(s, s), num_inference_steps=c.num_inference_steps)
        return make_policy_config(c.KIND, **fields)

    def _build(self):
        from lerobot.policies.factory import get_policy_class

        lr_config = self._lerobot_config()
        size = self.config.SIZES[self.config.size]
        cls = get_policy_class(self.config.KIND)
        if size is None:  # the published architecture: its VLM config and tokenizer are hub files
            try:
                if self.config.KIND != "smolvla":  # before 4B parameters are built, not after
                    from transformers import AutoTokenizer

                    AutoTokenizer.from_pretrained(PALIGEMMA_TOKENIZER)
                with _quiet():
                    return cls(lr_config), None
            except Exception as exc:
                raise _hub_error(self.config, exc) from None
        if self.config.KIND == "smolvla":
            with _quiet():
                return cls(lr_config), None
        tokenizer = minilm_tokenizer()
        with reduced_paligemma(size, tokenizer), _quiet():
            return cls(lr_config), tokenizer

    def _load(self, folder: Path):
        """The checkpoint's own class, config and weights, checked (never a random model)."""
        from lerobot.policies.factory import get_policy_class

        lr_config = read_config(folder)
        if lr_config.type != self.config.KIND:
            raise CheckpointError(f"policy_path {self.config.path!r} holds a {lr_config.type!r} "
                                  f"policy, not {self.config.KIND!r}: use policy=lerobot_"
                                  f"{lr_config.type}")
        lr_config.device = "cpu"  # Retain moves the policy where it trains
        tokenizer = None
        if (folder / TOKENIZER_DIR).is_dir():
            from transformers import AutoTokenizer

            tokenizer = AutoTokenizer.from_pretrained(str(folder / TOKENIZER_DIR))
        if (folder / VLM_DIR).is_dir():  # SmolVLA's VLM config, kept inside the folder
            lr_config.vlm_model_name = str(folder / VLM_DIR)
        size = read_architecture(folder)
        patch = (reduced_paligemma(size, tokenizer) if size is not None
                 else contextlib.nullcontext())
        cls = get_policy_class(lr_config.type)
        try:
            with patch, _quiet():
                model = cls.from_pretrained(str(folder), config=lr_config)
                check_loaded(model, folder)
        except CheckpointError:
            raise
        except Exception as exc:
            raise CheckpointError(f"checkpoint {folder} did not load: {type(exc).__name__}: "
                                  f"{first_line(exc)}") from None
        return model, tokenizer

    def _make_processors(self):
        """LeRobot's own pipelines: the checkpoint's (its statistics, renames, tokenizer), or
        made for a random init by LeRobot's factory (statistics from the buffers)."""
        from lerobot.policies.factory import make_pre_post_processors

        overrides = {"device_processor": {"device": "cpu"}}
        if self._tokenizer is not None:
            overrides["tokenizer_processor"] = {"tokenizer": self._tokenizer}
        elif self.config.path and (checkpoint_folder(self.config.path) / VLM_DIR).is_dir():
            # SmolVLA's tokenizer is its VLM's, kept inside the folder (save_folder); the saved
            # processor still names the scratch folder it was made from, gone with its policy
            vlm = str(checkpoint_folder(self.config.path) / VLM_DIR)
            overrides["tokenizer_processor"] = {"tokenizer_name": vlm}
        try:
            with _quiet():
                if self.config.path:
                    return make_pre_post_processors(
                        self.model.config, pretrained_path=str(checkpoint_folder(self.config.path)),
                        preprocessor_overrides=overrides, postprocessor_overrides={})
                size = self.config.SIZES[self.config.size]
                patch = (reduced_paligemma(size, self._tokenizer)
                         if self._tokenizer is not None else contextlib.nullcontext())
                with patch:
                    return make_pre_post_processors(self.model.config,
                                                    dataset_stats=self._stats())
        except Exception as exc:
            if self.config.path:
                raise CheckpointError(f"checkpoint {self.config.path!r}: its processors did not "
                                      f"load ({type(exc).__name__}: {first_line(exc)})") from None
            if self.config.SIZES[self.config.size] is None:
                raise _hub_error(self.config, exc) from None
            raise

    def _take_stats(self, pre) -> dict:
        """A checkpoint's statistics into the buffers; the other features' are returned."""
        from lerobot.processor import NormalizerProcessorStep

        stats = next((dict(step.stats) for step in pre.steps
                      if isinstance(step, NormalizerProcessorStep) and step.stats), {})
        state = stats.pop(self.features["state"], None)
        action = stats.pop(ACTION_FEATURE, None)
        if state is not None:
            self.state_norm.load_stats(state)
        if action is not None:
            self.action_norm.load_stats(action)
        return stats

    def _stats(self) -> dict:
        return {**self._other_stats, self.features["state"]: self.state_norm.as_stats(),
                ACTION_FEATURE: self.action_norm.as_stats()}

    def _versions(self) -> tuple[int, int]:
        return self.state_norm.version, self.action_norm.version

    def _stats_changed(self) -> None:
        self.state_norm.version += 1  # the buffers were loaded: the processors re-read them

    def processors(self):
        """LeRobot's pre- and post-processor, with the current statistics and device."""
        from lerobot.processor.normalize_processor import hotswap_stats

        pre, post, versions, device = self._processors
        if versions != self._versions() or device != self.device:
            stats = self._stats()
            pre, post = hotswap_stats(pre, stats), hotswap_stats(post, stats)
            _set_device(pre, self.device)
            self._processors = (pre, post, self._versions(), self.device)
        return pre, post

    @property
    def lora_target(self) -> str:
        """LeRobot's own PEFT targets for this policy (its `_get_default_peft_targets`), under
        the adapter's module names; LoRA's default."""
        targets = self.model._get_default_peft_targets() or {}
        return f"model\\.(?:{targets['target_modules']})" if targets else ""

    # -- the contract -----------------------------------------------------------------------

    @property
    def device(self) -> torch.device:
        return self.state_norm.mean.device

    def sample_time(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """LeRobot's schedule, t ~ Beta(alpha, beta) * scale + offset, from Retain's generator."""
        c = self.model.config
        alpha = getattr(c, "time_sampling_beta_alpha", 1.5)
        beta = getattr(c, "time_sampling_beta_beta", 1.0)
        scale = getattr(c, "time_sampling_scale", 0.999)
        offset = getattr(c, "time_sampling_offset", 0.001)
        return beta_time(n, alpha, beta, scale, offset, generator, self.device)

    def _lerobot_batch(self, batch: dict[str, torch.Tensor], actions: bool) -> dict:
        """Retain's batch as LeRobot's processors take it, then through them."""
        pre, _ = self.processors()
        raw = {self.features["state"]: batch["state"].float()}
        for key in self.config.image_keys:
            image = batch[key].permute(0, 3, 1, 2).float() / 255.0  # uint8 HWC -> [0, 1] CHW
            raw[self.features[key]] = image.flip(2, 3) if self.config.rotate_images else image
        ids = batch.get("instruction_id")
        if ids is None or not self.config.instructions:
            raise ValueError("a LeRobot policy reads each row's instruction text: the batch "
                             "needs 'instruction_id' and the config its 'instructions'")
        raw["task"] = [self.config.instructions[i] for i in ids.tolist()]
        if actions:
            raw[ACTION_FEATURE] = batch["actions"].float()
            mask = batch.get("action_mask")
            if mask is not None:
                raw["action_is_pad"] = ~mask.bool()
        return pre({k: v.to(self.device) if torch.is_tensor(v) else v for k, v in raw.items()})

    def _draws(self, batch, n: int, generator):
        shape = (n, self.model.config.chunk_size, self.noise_dim)
        noise = batch.get("noise")
        if noise is None:
            noise = randn_from(shape, generator, self.device)
        elif tuple(noise.shape) != shape:
            raise ValueError(f"noise of shape {tuple(noise.shape)} for a LeRobot policy; "
                             f"expected {shape} (policies.base.noise_shape: LeRobot pads "
                             f"actions to max_action_dim)")
        t = batch.get("time")
        if t is None:
            t = self.sample_time(n, generator)
        return noise.to(self.device), t.to(self.device)

    def forward(self, batch: dict[str, torch.Tensor],
                generator: torch.Generator | None = None) -> torch.Tensor:
        """LeRobot's per-sample loss [B] at Retain's (or the batch's) noise and time."""
        lr_batch = self._lerobot_batch(batch, actions=True)
        noise, t = self._draws(batch, batch["state"].shape[0], generator)
        with fixed_draws(self.model.model, noise, t):
            loss, _ = self.model.forward(lr_batch, reduction="none")
        return loss

    def predicted_velocity(self, batch: dict[str, torch.Tensor]) -> torch.Tensor:
        """LeRobot's velocity [B, H, A] at the batch's noise and time (normalized actions): the
        output of its `action_out_proj` during its own forward."""
        captured = []
        hook = self.model.model.action_out_proj.register_forward_hook(
            lambda module, args, out: captured.append(out))
        try:
            self.forward(batch)
        finally:
            hook.remove()
        chunk = self.model.config.chunk_size
        return captured[-1][:, -chunk:, :self.config.action_dim]

    @torch.no_grad()
    def sample_actions(self, batch: dict[str, torch.Tensor], noise: torch.Tensor | None = None,
                       generator: torch.Generator | None = None) -> torch.Tensor:
        """LeRobot's action chunk [B, H, A] in environment units, from `noise` at t = 1."""
        n = batch["state"].shape[0]
        noise, _ = self._draws({"noise": noise, "time": torch.zeros(n)}, n, generator)
        _, post = self.processors()
        actions = self.model.predict_action_chunk(self._lerobot_batch(batch, actions=False),
                                                  noise=noise)
        return post(actions).to(self.device)

    # -- a checkpoint folder ----------------------------------------------------------------

    def load_checkpoint_weights(self, path: str) -> None:
        """Another checkpoint of this architecture (a fine-tune of this one) into this policy:
        its weights and its processors' statistics, loaded and checked as `policy_path` is."""
        other = type(self)(dataclasses.replace(self.config, path=path))
        self.load_state_dict(other.state_dict())

    def save_folder(self, folder: str | Path) -> Path:
        """This policy as one checkpoint folder that `policy_path=` loads (and LeRobot reads):
        config, weights, processors with the current statistics, and what a reduced size needs
        (its architecture record, tokenizer, SmolVLA's VLM config), referred to inside it."""
        folder = Path(folder)
        tmp = folder.with_name(f".{folder.name}.partial")
        shutil.rmtree(tmp, ignore_errors=True)
        with _quiet():
            self.model.save_pretrained(tmp)
            pre, post = self.processors()
            pre.save_pretrained(tmp)
            post.save_pretrained(tmp)
        if self._tokenizer is not None:
            self._tokenizer.save_pretrained(tmp / TOKENIZER_DIR)
            size = (read_architecture(checkpoint_folder(self.config.path)) if self.config.path
                    else self.config.SIZES[self.config.size])
            write_architecture(tmp, self.config.size, size)
        vlm = getattr(self.model.config, "vlm_model_name", None)  # SmolVLA's, when local
        if vlm and Path(vlm).is_dir():
            shutil.copytree(vlm, tmp / VLM_DIR)
            config = json.loads((tmp / "config.json").read_text())
            config["vlm_model_name"] = VLM_DIR  # Retain resolves it inside the folder
            (tmp / "config.json").write_text(json.dumps(config, indent=4))
        shutil.rmtree(folder, ignore_errors=True)
        tmp.rename(folder)
        return folder

    def __del__(self):
        if getattr(self, "_scratch", None) is not None:
            shutil.rmtree(self._scratch, ignore_errors=True)


class LeRobotPi0Policy(LeRobotPolicy):
    """`policy=lerobot_pi0`: LeRobot's PI0Policy."""

    Config = LeRobotPi0Config


class LeRobotPi05Policy(LeRobotPolicy):
    """`policy=lerobot_pi05`: LeRobot's PI05Policy."""

    Config = LeRobotPi05Config


class LeRobotSmolVLAPolicy(LeRobotPolicy):
    """`policy=lerobot_smolvla`: LeRobot's SmolVLAPolicy."""

    Config = LeRobotSmolVLAConfig


@contextlib.contextmanager
def fixed_draws(model: nn.Module, noise: torch.Tensor, time: torch.Tensor):
    """LeRobot's flow-matching model draws its noise and times inside `forward`; while active,
    its `sample_noise` and `sample_time` return these instead (instance attributes shadow the
    methods, and are removed on exit)."""
    model.sample_noise = lambda shape, device: noise
    model.sample_time = lambda n, device: time
    try:
        yield
    finally:
        del model.sample_noise, model.sample_time


def _set_device(pipeline, device: torch.device) -> None:
    from lerobot.processor import DeviceProcessorStep

    for step in pipeline.steps:
        if isinstance(step, DeviceProcessorStep) and step.device != device.type:
            step.device = str(device)
            step.__post_init__()


@contextlib.contextmanager
def _quiet():
    """LeRobot prints banners and loading notes on stdout and logs warnings about key renames;
    Retain's output stays its own (a failed load is Retain's error, `check_loaded`)."""
    logging.disable(logging.WARNING)
    try:
        with contextlib.redirect_stdout(io.StringIO()):
            yield
    finally:
        logging.disable(logging.NOTSET)


def _hub_error(config: LeRobotConfig, exc: BaseException) -> CheckpointError:
    where = ("the hub is off (HF_HUB_OFFLINE=1)" if hub_offline()
             else f"{type(exc).__name__}: {first_line(exc)}")
    return CheckpointError(
        f"lerobot_{config.KIND} at policy_size={config.size} needs files from the hub "
        f"(its VLM config or tokenizer), and {where}; use policy_size=tiny or small, or a local "
        f"checkpoint folder as policy_path")
