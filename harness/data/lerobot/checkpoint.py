"""A LeRobot checkpoint (`policy_path`) against the suite: which of Retain's observations each of
its input features is, and the settings it fixes (chunk, cameras, their size).

Feature names are matched as a dataset's are (`lerobot_keys` first, then the reader's
CONVENTIONS), and the images turned by `lerobot_rotate_images`: both describe the LeRobot side.
Every mismatch is one line naming the feature, found at plan time before anything runs.
"""

from __future__ import annotations

import functools

from harness.common.errors import RetainError
from harness.config.benchmark import BenchConfig
from harness.data.lerobot.eval_env import trained_env
from harness.data.lerobot.reader import CONVENTIONS, PROPRIO_HINT, key_overrides
from policies.lerobot.checkpoint import (
    CheckpointError,
    CheckpointSpec,
    checkpoint_folder,
    checkpoint_spec,
)
from suites import Suite
from suites.base import CAMERA_KEYS
from suites.lerobot_protocol import LeRobotProtocolSuite

# the settings a checkpoint fixes, which a command line may not set otherwise
FIXED_BY_CHECKPOINT = ("chunk_size", "n_action_steps", "cameras", "image_size")


@functools.lru_cache(maxsize=8)
def spec(path: str) -> CheckpointSpec:
    try:
        return checkpoint_spec(path)
    except CheckpointError as exc:
        raise RetainError(str(exc)) from None


def checkpoint_features(cfg: BenchConfig, suite: Suite) -> dict[str, str]:
    """Retain key ("state", a camera) -> the checkpoint's input feature, checked against the
    suite's state width, action width and cameras."""
    s = spec(cfg.policy_path)
    where = f"policy_path {cfg.policy_path!r}"
    overrides = key_overrides(cfg)
    if cfg.lerobot_rotate_images and isinstance(suite, LeRobotProtocolSuite):
        raise RetainError(f"lerobot_rotate_images=true with suite {suite.name!r}, whose images "
                          f"are already turned as lerobot-eval turns them: leave it false")
    if s.action_dim != suite.action_dim:
        raise RetainError(f"{where} acts in {s.action_dim} dimensions; suite {suite.name!r} "
                          f"takes {suite.action_dim}")
    if s.state is None:
        raise RetainError(f"{where} reads no state feature; Retain gives every policy the "
                          f"suite's state")
    state, width = s.state
    if "state" in overrides and overrides["state"] != state:
        raise RetainError(f"{where} has no state feature {overrides['state']!r} (lerobot_keys); "
                          f"its state is {state!r}")
    if width != suite.state_dim:
        raise RetainError(f"{where}'s {state!r} is {width}-D; suite {suite.name!r} gives "
                          f"{suite.state_dim}-D{PROPRIO_HINT.get((suite.name, width), '')}")
    for kind, wide, pad in (("state", suite.state_dim, s.max_state_dim),
                            ("action", suite.action_dim, s.max_action_dim)):
        if pad is not None and wide > pad:
            raise RetainError(f"{where} pads its {kind} to max_{kind}_dim={pad}, and suite "
                              f"{suite.name!r}'s {kind} is {wide}-D: LeRobot pads up, never "
                              f"down (train it with max_{kind}_dim >= {wide})")
    features = {"state": state}
    for name, shape in s.images.items():
        key = next((k for k in CAMERA_KEYS if overrides.get(k) == name), None) or next(
            (k for k in CAMERA_KEYS if k not in overrides and name in conventions(suite, k)),
            None)
        if key is None or key in features:
            raise RetainError(f"{where}'s image feature {name!r} is none of the suite's cameras "
                              f"({', '.join(CAMERA_KEYS)}); name it with lerobot_keys="
                              f"{CAMERA_KEYS[0]}:{name}")
        if len(shape) != 3 or shape[1] != shape[2]:
            raise RetainError(f"{where}'s image feature {name!r} is {list(shape)}; the suite "
                              f"renders square images (C, S, S)")
        features[key] = name
    sizes = {s.images[features[k]][1] for k in CAMERA_KEYS if k in features}
    if len(sizes) > 1:
        raise RetainError(f"{where}'s cameras have sizes {sorted(sizes)}; the suite renders one "
                          f"image_size for all")
    return features


def conventions(suite: Suite, key: str) -> tuple[str, ...]:
    """The feature names that are Retain's `key`: under lerobot-eval's protocol LeRobot's own
    name for it first (Meta-World's `observation.image`), then the datasets' conventions."""
    own = suite.lerobot.feature(key) if isinstance(suite, LeRobotProtocolSuite) else None
    return ((own,) if own else ()) + CONVENTIONS[key]


def protocol_features(suite: Suite, image_keys: tuple[str, ...]) -> dict[str, str] | None:
    """A random init's feature names under lerobot-eval's protocol (LeRobot's, where it names
    the camera), so the folder it saves reads as a LeRobot checkpoint of that env; None for a
    suite of Retain's own conventions."""
    if not isinstance(suite, LeRobotProtocolSuite):
        return None
    return {k: suite.lerobot.feature(k) or f"observation.images.{k}"
            for k in ("state", *image_keys)}


def render_size(cfg: BenchConfig, suite: Suite, trained: int) -> int:
    """The size the suite renders a checkpoint's cameras at: under lerobot-eval's protocol the
    size lerobot-eval renders (the checkpoint's train_config.json env section, else LeRobot's
    default for the env; the policy's processors resize to its own resolution, as in
    lerobot-eval), otherwise the size it was trained at."""
    if not isinstance(suite, LeRobotProtocolSuite):
        return trained
    try:
        env = trained_env(checkpoint_folder(cfg.policy_path))
    except (ValueError, CheckpointError) as exc:
        raise RetainError(str(exc)) from None
    if env is None:
        return suite.lerobot.image_size
    if env.env_type != suite.lerobot.env_type:
        raise RetainError(f"policy_path {cfg.policy_path!r} was trained for LeRobot's "
                          f"{env.env_type!r} env ({env.task}); suite {suite.name!r} is "
                          f"lerobot-eval's {suite.lerobot.env_type!r}")
    return env.image_size or suite.lerobot.image_size


def checkpoint_settings(cfg: BenchConfig, suite: Suite) -> dict:
    """The benchmark settings the checkpoint fixes: its chunk, n_action_steps, and its cameras
    at their resolution (`render_size`)."""
    s = spec(cfg.policy_path)
    features = checkpoint_features(cfg, suite)
    cameras = [k for k in CAMERA_KEYS if k in features]
    settings = {"chunk_size": s.chunk_size, "n_action_steps": s.n_action_steps,
                "cameras": bool(cameras)}
    if cameras:
        settings["image_size"] = render_size(cfg, suite, s.images[features[cameras[0]]][1])
    return settings


def adopt_checkpoint(cfg: BenchConfig, suite: Suite, given: dict[str, str]) -> dict:
    """Set what the checkpoint fixes on `cfg` and return it; a command-line value (`given`)
    that differs is refused in one line."""
    settings = checkpoint_settings(cfg, suite)
    for key, value in settings.items():
        if key in given and getattr(cfg, key) != value:
            raise RetainError(f"{key}={given[key]} conflicts with policy_path "
                              f"{cfg.policy_path!r}, whose {key} is {value}: a checkpoint sets "
                              f"its own")
        setattr(cfg, key, value)
    return settings
