"""A LeRobot checkpoint: where its folder is, what it is (its identity, its features and chunk),
and whether its weights really loaded.

`policy_path` names a folder (LeRobot's `config.json`, `model.safetensors` and processor files,
plus whatever Retain put beside them: a reduced size's `retain_architecture.json`, a local
`tokenizer/`, SmolVLA's `vlm/` config) or a hub id, which is downloaded where the hub is
reachable. Every failure is one line (`CheckpointError`) naming the path and what to do.
"""

from __future__ import annotations

import contextlib
import functools
import hashlib
import io
import os
import re
from dataclasses import dataclass
from pathlib import Path

import torch

WEIGHTS_FILE = "model.safetensors"
CONFIG_FILE = "config.json"
PRETRAINED_DIR = "pretrained_model"  # lerobot-train's checkpoints/<step>/pretrained_model/
HUB_ID = re.compile(r"^[A-Za-z0-9][\w.-]*/[\w.-]+$")


class CheckpointError(ValueError):
    """A checkpoint that cannot be used; the message is one line."""


def first_line(exc: BaseException) -> str:
    """An exception's message cut to its first line: every error here is one line."""
    text = str(exc).strip()
    return text.splitlines()[0] if text else ""


def hub_offline() -> bool:
    return os.environ.get("HF_HUB_OFFLINE", "").lower() in ("1", "true", "yes", "on")


@functools.lru_cache(maxsize=8)
def checkpoint_folder(path: str) -> Path:
    """The local folder of `path`: itself, or a hub id's downloaded snapshot."""
    local = Path(path).expanduser()
    if local.is_dir():
        if not (local / CONFIG_FILE).is_file() and (local / PRETRAINED_DIR).is_dir():
            local = local / PRETRAINED_DIR  # lerobot-train's checkpoints/<step>/ or last/
        if not (local / CONFIG_FILE).is_file():
            raise CheckpointError(f"policy_path {path!r} is a folder without LeRobot's "
                                  f"{CONFIG_FILE}: expected a saved LeRobot policy, or "
                                  f"lerobot-train's checkpoints/<step>/ holding "
                                  f"{PRETRAINED_DIR}/")
        return local.resolve()
    if not HUB_ID.match(path):
        raise CheckpointError(f"policy_path {path!r}: no such folder, and not a hub id "
                              f"(owner/name)")
    if hub_offline():
        raise CheckpointError(f"policy_path {path!r} is not a folder here and the hub is off "
                              f"(HF_HUB_OFFLINE=1): give a local folder, or run where the hub "
                              f"is reachable with HF_HUB_OFFLINE=0")
    from huggingface_hub import snapshot_download

    try:
        return Path(snapshot_download(path))
    except Exception as exc:  # no network, unknown repo, gated repo: one line either way
        reason = first_line(exc) or type(exc).__name__
        raise CheckpointError(f"policy_path {path!r}: the hub could not give it "
                              f"({type(exc).__name__}: {reason})") from None


def weights_file(folder: Path) -> Path:
    path = folder / WEIGHTS_FILE
    if not path.is_file():
        raise CheckpointError(f"checkpoint {folder} has no {WEIGHTS_FILE}: its weights cannot "
                              f"load (LeRobot would return a random model)")
    return path


def checkpoint_identity(path: str) -> str:
    """The checkpoint's weights digest: what a run key records of a `policy_path`."""
    return weights_digest(checkpoint_folder(path))


def weights_digest(folder: Path) -> str:
    """SHA-256 of the weights file: the checkpoint's identity in run keys."""
    path = weights_file(folder)
    stat = path.stat()
    return _digest(str(path), stat.st_size, stat.st_mtime_ns)


@functools.lru_cache(maxsize=8)
def _digest(path: str, size: int, mtime_ns: int) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 24), b""):
            h.update(block)
    return h.hexdigest()


def read_config(folder: Path):
    """LeRobot's config of the checkpoint (its own class, by the file's `type`). LeRobot's
    config classes register their `type` when their modules are imported, which
    `lerobot.policies` does: without it a fresh process knows no policy type at all."""
    import lerobot.policies  # noqa: F401 - registers PI0Config, PI05Config, SmolVLAConfig, ...
    from lerobot.configs import PreTrainedConfig

    try:
        with contextlib.redirect_stdout(io.StringIO()):
            return PreTrainedConfig.from_pretrained(folder)
    except Exception as exc:
        raise CheckpointError(f"checkpoint {folder}: its {CONFIG_FILE} does not parse "
                              f"({type(exc).__name__}: {first_line(exc)})"
                              ) from None


@dataclass(frozen=True)
class CheckpointSpec:
    """What the plan checks a suite against: the checkpoint's type, chunk and features."""

    kind: str  # LeRobot's policy type ("pi0", "pi05", "smolvla", ...)
    chunk_size: int
    n_action_steps: int
    state: tuple[str, int] | None  # (feature name, width)
    images: dict[str, tuple[int, int, int]]  # feature name -> (C, H, W)
    action_dim: int
    max_state_dim: int | None = None  # LeRobot pads state and actions up to these, never down
    max_action_dim: int | None = None


def checkpoint_spec(path: str) -> CheckpointSpec:
    """The checkpoint's type, chunk and input and output features, from its config alone."""
    from lerobot.configs import FeatureType

    config = read_config(checkpoint_folder(path))
    inputs = config.input_features or {}
    states = [(k, int(f.shape[0])) for k, f in inputs.items() if f.type is FeatureType.STATE]
    images = {k: tuple(int(s) for s in f.shape) for k, f in inputs.items()
              if f.type is FeatureType.VISUAL}
    actions = [int(f.shape[0]) for f in (config.output_features or {}).values()
               if f.type is FeatureType.ACTION]
    if not actions:
        raise CheckpointError(f"checkpoint {path!r} declares no action output feature")
    pads = [getattr(config, name, None) for name in ("max_state_dim", "max_action_dim")]
    return CheckpointSpec(config.type, int(config.chunk_size), int(config.n_action_steps),
                          states[0] if states else None, images, actions[0],
                          *(int(p) if p is not None else None for p in pads))


def checkpoint_name(path: str) -> str:
    """A checkpoint's short name for labels: a hub id as it is, a folder by its own name, and
    lerobot-train's `<run>/checkpoints/<step>/pretrained_model` as `<run>-<step>` (its folder
    names alone say nothing)."""
    if not Path(path).expanduser().is_dir() and HUB_ID.match(path):
        return path
    folder = checkpoint_folder(path)
    if folder.name == PRETRAINED_DIR and folder.parent.parent.name == "checkpoints":
        return f"{folder.parents[2].name}-{folder.parent.name}"
    return folder.name


def check_loaded(model: torch.nn.Module, folder: Path) -> None:
    """Every weight of the file is in the model, equal, and every weight of the model came from
    the file (or shares its storage with one that did, as tied embeddings do). LeRobot's
    loaders can return a randomly initialised model after a failed load with only a printed
    warning; this turns that into an error."""
    from safetensors.torch import load_file

    stored = load_file(weights_file(folder))
    fix = getattr(model, "_fix_pytorch_state_dict_keys", None)  # PI0 / PI0.5 rename keys so
    if fix is not None:
        stored = fix(stored, model.config)
        stored = {k if k.startswith("model.") else f"model.{k}": v for k, v in stored.items()}
    own = model.state_dict()
    unknown = [k for k in stored if k not in own]
    if unknown:
        raise CheckpointError(f"checkpoint {folder}: {len(unknown)} weights of "
                              f"{WEIGHTS_FILE} are not in a {type(model).__name__} built from "
                              f"its config (e.g. {unknown[0]}): it did not load")
    differ = [k for k, v in stored.items()
              if own[k].shape != v.shape or not torch.equal(own[k].detach().cpu().to(v.dtype), v)]
    if differ:
        raise CheckpointError(f"checkpoint {folder}: {len(differ)} weights differ from "
                              f"{WEIGHTS_FILE} after loading (e.g. {differ[0]}): it did not load")
    loaded = {own[k].data_ptr() for k in stored}
    missing = [k for k, v in own.items() if k not in stored and v.data_ptr() not in loaded]
    if missing:
        raise CheckpointError(f"checkpoint {folder}: {len(missing)} weights of the model are "
                              f"not in {WEIGHTS_FILE} (e.g. {missing[0]}): they would stay "
                              f"random")


def weights_layout(folder: Path) -> dict[str, tuple[int, ...]]:
    """Every tensor's name and shape in the weights file, read from its header alone."""
    from safetensors import safe_open

    with safe_open(str(weights_file(folder)), "pt") as f:
        return {name: tuple(f.get_slice(name).get_shape()) for name in f.keys()}


def stage_mismatch(base: str, other: str) -> str | None:
    """How checkpoint `other` differs from `base` where a fine-tune of it may not (its type,
    features, chunk, the names and shapes of its weights), as the end of a sentence; None when
    it is the same architecture."""
    a, b = checkpoint_spec(base), checkpoint_spec(other)
    for field in ("kind", "state", "images", "action_dim", "chunk_size", "n_action_steps"):
        if getattr(a, field) != getattr(b, field):
            return (f"has {field} {getattr(b, field)!r}, the base's is {getattr(a, field)!r}: "
                    f"a fine-tune keeps its base's architecture and features")
    ours, theirs = weights_layout(checkpoint_folder(base)), weights_layout(checkpoint_folder(other))
    for name in sorted(set(ours) | set(theirs)):
        if ours.get(name) != theirs.get(name):
            return (f"has weights of another architecture than the base's ({name}: "
                    f"{theirs.get(name, 'missing')} against {ours.get(name, 'missing')})")
    return None
