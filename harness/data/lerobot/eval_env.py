"""The env a LeRobot checkpoint was trained for, from lerobot-train's `train_config.json` beside
its weights (its `env` section: type, task, render size), so that under lerobot-eval's protocol
the plan renders at the size lerobot-eval would and refuses a checkpoint made for another env."""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

TRAIN_CONFIG = "train_config.json"


@dataclass(frozen=True)
class TrainedEnv:
    env_type: str  # "libero", "metaworld", ...
    task: str  # "libero_spatial", "libero_10,libero_goal", "metaworld-push-v3", ...
    image_size: int | None  # observation_height where the section has it


def trained_env(folder: Path) -> TrainedEnv | None:
    """The checkpoint's env section, or None where the folder has no train_config.json or the
    file names no env (lerobot-train without --env)."""
    path = folder / TRAIN_CONFIG
    if not path.is_file():
        return None
    try:
        env = json.loads(path.read_text()).get("env")
    except (json.JSONDecodeError, AttributeError) as exc:
        raise ValueError(f"{path}: not lerobot-train's config ({exc})") from None
    if not isinstance(env, dict) or not env.get("type"):
        return None
    height, width = env.get("observation_height"), env.get("observation_width")
    if height is not None and width is not None and height != width:
        raise ValueError(f"{path}: the env renders {height}x{width}; Retain renders square images")
    return TrainedEnv(str(env["type"]), str(env.get("task") or ""),
                      None if height is None else int(height))
