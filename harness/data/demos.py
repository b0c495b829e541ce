"""Scripted-expert demonstrations, cached on disk as HDF5 in the LIBERO / robomimic layout.

    data/                     attrs: instruction, task, suite, cache_key, settings (JSON), total
    data/demo_<i>/actions     [T, A] float32
    data/demo_<i>/obs/<key>   [T, ...] (state: [T, S] float32; images: [T, H, W, 3] uint8 under
                              LIBERO's names, agentview_rgb and eye_in_hand_rgb, gzip-compressed)
    data/demo_<i>/rewards     [T] float32, 1 at the step that succeeded
    data/demo_<i>/dones       [T] uint8, 1 at the last step
                              attrs: seed, num_samples
A suite may add its own keys (LIBERO: `problem_info`, `env_args`, `bddl_file_name` on `data`;
`obs/ee_states`, `obs/gripper_states`, `obs/joint_states`, `states`, `robot_states` per demo, as
LIBERO's create_dataset.py writes them); `data.attrs["extra_keys"]` lists the per-demo ones,
which are kept for other tools and not read back as observations.

Files are keyed by a hash of everything that produced them, written atomically, and checked on
read: a corrupt file or one made for other settings is an error, never silently reused.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

import h5py
import numpy as np

from harness.common.atomic import atomic_path
from harness.common.errors import DemoFileError
from suites import Suite
from suites.base import run_expert_episode
from suites.render import render_argument

FORMAT_VERSION = 1
MAX_ATTEMPTS_PER_DEMO = 4  # experts fail ~5% of the time; give up well before looping forever


@dataclass(frozen=True)
class Episode:
    actions: np.ndarray  # [T, A]
    obs: dict[str, np.ndarray]  # key -> [T, ...]
    seed: int
    extras: dict[str, np.ndarray] = field(default_factory=dict)  # path in the demo group -> [T, ...]

    def __len__(self) -> int:
        return len(self.actions)


@dataclass(frozen=True)
class DemoSpec:
    """Everything that determines a task's demo file; its hash is the cache key."""

    suite: str
    suite_version: str
    task: str
    split: str  # "demo" (training) or "heldout" (held-out loss)
    num_demos: int
    max_episode_steps: int
    cameras: bool = False
    image_size: int = 84
    format_version: int = FORMAT_VERSION
    source: str = ""  # the user's demos_dir where demos come from files, not the expert
    render: str = "faithful"  # how the images are drawn (suites/render.py); faithful without cameras

    def key(self) -> str:
        fields = asdict(self)
        if not self.source:  # keys made before `source` existed stay valid
            del fields["source"]
        if self.render == "faithful":  # and those made before `render`, whose images it draws
            del fields["render"]
        blob = json.dumps(fields, sort_keys=True)
        return hashlib.sha256(blob.encode()).hexdigest()[:16]

    def filename(self) -> str:
        return f"{self.task}.{self.split}.{self.key()}.hdf5"


def rollout_expert(suite: Suite, env, seed: int, max_steps: int) -> Episode | None:
    """One expert episode from `reset(seed)`; None unless it succeeds within `max_steps`."""
    run = run_expert_episode(env, seed, max_steps, record=True)
    if not run.success:
        return None
    stacked = {k: np.stack([o[k] for o in run.observations]) for k in run.observations[0]}
    extras = {k: np.stack([e[k] for e in run.extras]) for k in run.extras[0]}
    return Episode(np.stack(run.actions).astype(np.float32), stacked, seed, extras)


def generate_demos(suite: Suite, spec: DemoSpec, progress: bool = True) -> list[Episode]:
    """Run the task's expert on its seeded episodes until `num_demos` succeed."""
    from tqdm import tqdm

    env = suite.make_env(spec.task, cameras=spec.cameras, image_size=spec.image_size,
                         **render_argument(spec.render))
    seeds = suite.episode_keys(spec.task, spec.split, spec.num_demos * MAX_ATTEMPTS_PER_DEMO)
    episodes: list[Episode] = []
    bar = tqdm(total=spec.num_demos, desc=f"demos {spec.task} ({spec.split})", disable=not progress,
               leave=False)
    try:
        for seed in seeds:
            episode = rollout_expert(suite, env, seed, spec.max_episode_steps)
            if episode is not None:
                episodes.append(episode)
                bar.update(1)
            if len(episodes) == spec.num_demos:
                return episodes
    finally:
        bar.close()
        env.close()
    raise DemoFileError(
        f"expert for task {spec.task!r} succeeded on only {len(episodes)} of {len(seeds)} "
        f"episodes within {spec.max_episode_steps} steps; "
        + ("raise max_episode_steps" if suite.max_steps(spec.task) is None
           else "that is the task's own step limit: the expert needs mending (on LIBERO, "
                "demos_dir= trains on LIBERO's dataset files instead)")
    )


def write_demo_file(path: Path, episodes: list[Episode], spec: DemoSpec, instruction: str,
                    attrs: dict[str, str] | None = None) -> None:
    with atomic_path(path) as tmp:
        with h5py.File(tmp, "w") as f:
            data = f.create_group("data")
            data.attrs.update(attrs or {})
            data.attrs.update(instruction=instruction, task=spec.task, suite=spec.suite,
                              cache_key=spec.key(), settings=json.dumps(asdict(spec), sort_keys=True),
                              total=sum(len(e) for e in episodes))
            extra_keys = sorted({k for e in episodes for k in e.extras})
            if extra_keys:
                data.attrs["extra_keys"] = json.dumps(extra_keys)
            for i, episode in enumerate(episodes):
                demo = data.create_group(f"demo_{i}")
                demo.attrs.update(seed=episode.seed, num_samples=len(episode))
                demo.create_dataset("actions", data=episode.actions)
                for key, value in episode.obs.items():
                    demo.create_dataset(f"obs/{key}", data=value, **_storage(value))
                for key, value in episode.extras.items():
                    demo.create_dataset(key, data=value)
                rewards = np.zeros(len(episode), np.float32)
                rewards[-1] = 1.0
                demo.create_dataset("rewards", data=rewards)
                demo.create_dataset("dones", data=(rewards > 0).astype(np.uint8))


def _storage(value: np.ndarray) -> dict:
    """Images ([T, H, W, 3] uint8) are stored gzip-compressed, one chunk per frame: rendered
    scenes shrink several times, and gzip is in every HDF5 build (LIBERO's readers included)."""
    if value.dtype == np.uint8 and value.ndim == 4:
        return dict(compression="gzip", compression_opts=1, chunks=(1, *value.shape[1:]))
    return {}


def read_demo_file(path: Path, expected: DemoSpec | None = None) -> tuple[str, list[Episode]]:
    """(instruction, episodes). Raises DemoFileError, one line, on a corrupt or mismatched file."""
    try:
        with h5py.File(path, "r") as f:
            if "data" not in f:
                raise DemoFileError(f"demo file {path} has no 'data' group; expected the robomimic layout")
            data = f["data"]
            if expected is not None and data.attrs.get("cache_key") != expected.key():
                made_for = data.attrs.get("settings", "unknown settings")
                raise DemoFileError(
                    f"demo file {path} was made for other settings ({made_for}); expected "
                    f"{json.dumps(asdict(expected), sort_keys=True)}: delete it to regenerate"
                )
            names = sorted((k for k in data if k.startswith("demo_")), key=lambda k: int(k[5:]))
            if not names:
                raise DemoFileError(f"demo file {path} holds no demo_<i> groups")
            extra_keys = set(json.loads(data.attrs.get("extra_keys", "[]")))
            episodes = []
            for name in names:
                demo = data[name]
                for key in ("actions", "obs"):
                    if key not in demo:
                        raise DemoFileError(f"demo file {path}: {name} is missing '{key}'")
                obs = {k: demo["obs"][k][()] for k in demo["obs"] if f"obs/{k}" not in extra_keys}
                episodes.append(Episode(demo["actions"][()], obs, int(demo.attrs.get("seed", -1))))
            return str(data.attrs.get("instruction", "")), episodes
    except DemoFileError:
        raise
    except (OSError, KeyError, ValueError) as exc:
        reason = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise DemoFileError(f"demo file {path} is corrupt ({reason}): delete it to regenerate") from None


def cached_demo_path(cache_dir: Path, spec: DemoSpec) -> Path:
    return Path(cache_dir) / "demos" / spec.suite / spec.filename()


def load_or_generate(suite: Suite, spec: DemoSpec, cache_dir: Path, progress: bool = True) -> list[Episode]:
    """The task's demos from the cache, generating and caching them the first time."""
    path = cached_demo_path(cache_dir, spec)
    if path.exists():
        return read_demo_file(path, spec)[1]
    episodes = generate_demos(suite, spec, progress=progress)
    write_demo_file(path, episodes, spec, suite.instruction(spec.task), suite.demo_file_attrs(spec.task))
    return episodes
