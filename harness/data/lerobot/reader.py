"""A benchmark's demos from a LeRobot dataset folder given as `demos_dir` (any suite).

Keys. Retain's `actions`, `state` and, with cameras on, `agentview_rgb` and `eye_in_hand_rgb`
are the first of CONVENTIONS' features the dataset has (LeRobot's `action`,
`observation.state`, `observation.images.image`, `observation.images.wrist_image`, ...; the
physical-intelligence/libero set's `actions`, `state`, `image`, `wrist_image`);
`lerobot_keys=state:observation.state,agentview_rgb:observation.images.front` overrides them.
Their widths must be the suite's (`suite=libero-proprio` for LIBERO's 8-D proprioception) and
the images `image_size` square; `lerobot_rotate_images=true` turns images 180 degrees (LIBERO's
community sets are stored so; openpi's LIBERO evaluation turns the renders likewise).

Tasks. A suite task's episodes are those whose task text is its instruction (case, spacing and
a final period aside), or the text or task_index `lerobot_tasks=task:3,other:pick up the ...`
names.

Checks. Every episode read is checked against the index: its frames' episode_index, frame_index
(and v3.0's global index) and count, each image's size, each video segment's frame times.
Anything off is a LeRobotError naming the file; nothing is returned from a task read halfway.
"""

from __future__ import annotations

import functools
import hashlib
import json
from pathlib import Path

import numpy as np

from harness.common.errors import RetainError
from harness.config.benchmark import BenchConfig
from harness.data.demos import Episode
from harness.data.lerobot.frames import (
    TIME_TOLERANCE,
    FrameError,
    SegmentError,
    decode_png,
    decode_video,
)
from harness.data.lerobot.layout import (
    CAMERA_DTYPES,
    EpisodeEntry,
    Layout,
    bad,
    fingerprint,
    open_layout,
    read_parquet,
)
from suites import Suite
from suites.base import AGENTVIEW, CAMERA_KEYS, EYE_IN_HAND, unknown

CONVENTIONS: dict[str, tuple[str, ...]] = {
    "actions": ("action", "actions"),
    "state": ("observation.state", "state"),
    AGENTVIEW: ("observation.images.image", "observation.images.agentview_rgb",
                "observation.images.agentview", "image", "agentview_rgb"),
    EYE_IN_HAND: ("observation.images.wrist_image", "observation.images.image2",
                  "observation.images.eye_in_hand_rgb", "observation.images.wrist",
                  "wrist_image", "eye_in_hand_rgb"),
}
"""Retain key -> the dataset features tried in order when `lerobot_keys` does not name one."""

PROPRIO_HINT = {("libero", 8): " (LIBERO's community sets carry 8-D proprioception, eef position, "
                               "axis-angle and gripper: use suite=libero-proprio)"}


def parse_mapping(text: str, setting: str, example: str) -> dict[str, str]:
    """"a:b,c:d" -> {"a": "b", "c": "d"} (the value may hold further colons)."""
    out: dict[str, str] = {}
    for item in str(text or "").split(","):
        if not item.strip():
            continue
        key, sep, value = item.partition(":")
        if not sep or not key.strip() or not value.strip():
            raise RetainError(f"malformed {setting} entry {item.strip()!r}: expected "
                              f"KEY:VALUE, e.g. {setting}={example}")
        out[key.strip()] = value.strip()
    return out


def key_overrides(cfg: BenchConfig) -> dict[str, str]:
    keys = parse_mapping(cfg.lerobot_keys, "lerobot_keys", "state:observation.state")
    unknown = sorted(set(keys) - set(CONVENTIONS))
    if unknown:
        raise RetainError(f"unknown key {unknown[0]!r} in lerobot_keys; valid: "
                          f"{', '.join(CONVENTIONS)}")
    return keys


def task_overrides(cfg: BenchConfig, suite: Suite) -> dict[str, str]:
    tasks = parse_mapping(cfg.lerobot_tasks, "lerobot_tasks", "TASK:TASK_INDEX")
    for task in tasks:
        if task not in suite.task_names():
            raise RetainError(f"lerobot_tasks: {unknown(f'{suite.name} task', task, suite.task_names())}")
    return tasks


def dataset(cfg: BenchConfig) -> Layout:
    """The folder's layout, read once per process while its files stay the same."""
    root = Path(cfg.demos_dir).resolve()
    return _opened(str(root), fingerprint(root))


@functools.lru_cache(maxsize=4)
def _opened(root: str, files: str) -> Layout:
    return open_layout(root)


def feature_keys(cfg: BenchConfig, suite: Suite) -> dict[str, str]:
    """Retain key -> the dataset's feature, checked against the suite and image_size."""
    layout, overrides = dataset(cfg), key_overrides(cfg)
    info = layout.info_file
    wanted = ["actions", "state"] + (list(CAMERA_KEYS) if cfg.cameras else [])
    keys = {}
    for key in wanted:
        if key in overrides:
            feature = overrides[key]
            if feature not in layout.features:
                raise bad(info, f"missing key {feature!r} (lerobot_keys {key}:{feature}); its "
                                f"features: {_preview(layout.features)}")
        else:
            feature = next((c for c in CONVENTIONS[key] if c in layout.features), "")
            if not feature:
                raise bad(info, f"missing key for {key}: none of {', '.join(CONVENTIONS[key])}; "
                                f"its features: {_preview(layout.features)}; name one with "
                                f"lerobot_keys={key}:FEATURE")
        keys[key] = feature
    widths = {"actions": suite.action_dim, "state": suite.state_dim}
    for key, width in widths.items():
        feature = layout.features[keys[key]]
        shape = list(feature["shape"])
        if feature["dtype"] in CAMERA_DTYPES or len(shape) != 1:
            raise bad(info, f"feature {keys[key]!r} ({key}) is {feature['dtype']} {shape}; "
                            "expected a vector")
        if shape[0] != width:
            raise bad(info, f"feature {keys[key]!r} ({key}) has {shape[0]} values; suite "
                            f"{suite.name!r} expects {width}"
                            f"{PROPRIO_HINT.get((suite.name, shape[0]), '') if key == 'state' else ''}")
    for key in wanted[2:]:
        feature = layout.features[keys[key]]
        if feature["dtype"] not in CAMERA_DTYPES:
            raise bad(info, f"feature {keys[key]!r} ({key}) has dtype {feature['dtype']!r}; "
                            "expected image or video")
        height, width = layout.camera_shape(keys[key])
        if (height, width) != (cfg.image_size, cfg.image_size):
            hint = f"; set image_size={height}" if height == width else ""
            raise bad(info, f"feature {keys[key]!r} ({key}) holds {width}x{height} images, not "
                            f"image_size={cfg.image_size}{hint}")
    return keys


def _preview(names, most: int = 8) -> str:
    names = list(names)
    more = f" (+{len(names) - most} more)" if len(names) > most else ""
    return ", ".join(map(str, names[:most])) + more


def normalized(text: str) -> str:
    return " ".join(str(text).lower().split()).rstrip(".").strip()


def task_entries(cfg: BenchConfig, suite: Suite, task: str) -> list[EpisodeEntry]:
    """The task's episodes in the dataset, in episode order (checked, not read)."""
    layout = dataset(cfg)
    target = task_overrides(cfg, suite).get(task)
    if target is not None and target.isdigit():
        if int(target) not in layout.tasks:
            raise bad(layout.tasks_file, f"no task_index {target} (lerobot_tasks "
                                         f"{task}:{target}); it holds {len(layout.tasks)} tasks")
        text = layout.tasks[int(target)]
    else:
        text = target if target is not None else suite.instruction(task)
    wanted = normalized(text)
    entries = [e for e in layout.episodes if any(normalized(t) == wanted for t in e.tasks)]
    if not entries:
        texts = sorted({t for e in layout.episodes for t in e.tasks})
        raise bad(layout.episodes_file, f"no episodes of task {task!r} ({text!r}); its tasks: "
                                        f"{_preview(repr(t) for t in texts)}; name the task "
                                        f"with lerobot_tasks={task}:TASK_INDEX")
    return entries


def source(cfg: BenchConfig, suite: Suite, task: str) -> str:
    """What the task's demos are read from, for the demo-cache key: the folder, the state of
    its files, the keys, the episodes and the image turn. Checks all of them on the way."""
    layout = dataset(cfg)
    keys = feature_keys(cfg, suite)
    entries = task_entries(cfg, suite, task)
    blob = json.dumps({"files": layout.fingerprint, "keys": keys,
                       "episodes": [e.index for e in entries],
                       "rotate": cfg.lerobot_rotate_images}, sort_keys=True)
    return f"{layout.root}:lerobot-{layout.version}:{hashlib.sha256(blob.encode()).hexdigest()[:16]}"


def read_episodes(cfg: BenchConfig, suite: Suite, entries: list[EpisodeEntry]) -> list[Episode]:
    """The entries' episodes: actions and state float32, images uint8 [T, S, S, 3]."""
    return read_entries(dataset(cfg), feature_keys(cfg, suite), entries, cfg.image_size,
                        cfg.lerobot_rotate_images)


def read_entries(layout: Layout, keys: dict[str, str], entries: list[EpisodeEntry],
                 image_size: int, rotate: bool = False) -> list[Episode]:
    """The entries' episodes with `keys` (Retain key -> feature: actions, state, cameras),
    each data file read once."""
    by_file: dict[Path, list[EpisodeEntry]] = {}
    for entry in entries:
        by_file.setdefault(entry.data, []).append(entry)
    episodes: dict[int, Episode] = {}
    for path, group in by_file.items():
        episodes.update(_read_file(layout, keys, path, group, image_size, rotate))
    return [episodes[e.index] for e in entries]


def _read_file(layout: Layout, keys: dict[str, str], path: Path, group: list[EpisodeEntry],
               image_size: int, rotate: bool) -> dict[int, Episode]:
    import pyarrow as pa

    images = [k for k, f in keys.items() if layout.features[f]["dtype"] == "image"]
    videos = [k for k, f in keys.items() if layout.features[f]["dtype"] == "video"]
    v3 = group[0].rows is not None
    columns = sorted({keys["actions"], keys["state"], "episode_index", "frame_index"}
                     | {keys[k] for k in images} | ({"index"} if v3 else set())
                     | ({"timestamp"} if videos else set()))
    filters = [("episode_index", "in", [e.index for e in group])] if v3 else None
    table = read_parquet(path, columns, f"episode {group[0].index}'s frames", filters)
    episode_of = table.column("episode_index").to_numpy()
    parts: dict[int, tuple[np.ndarray, dict[str, np.ndarray]]] = {}
    for entry in group:
        rows = np.flatnonzero(episode_of == entry.index) if v3 else np.arange(table.num_rows)
        _check_frames(table, path, entry, rows)
        take = pa.array(rows)
        obs = {"state": _vectors(table, keys["state"], take, path)}
        for key in images:
            obs[key] = _pngs(table, keys[key], take, path, image_size)
        if videos:
            times = table.column("timestamp").take(take).to_numpy().astype(np.float64)
            if np.abs(times - np.arange(entry.length) / layout.fps).max() > TIME_TOLERANCE:
                raise bad(path, f"episode {entry.index}'s timestamps are not frame_index / fps "
                                f"({layout.fps:g}); its video frames cannot be matched")
        parts[entry.index] = _vectors(table, keys["actions"], take, path), obs
    for key in videos:
        for entry, frames in _videos(layout, group, keys[key], image_size):
            parts[entry.index][1][key] = frames
    if rotate:
        for _, obs in parts.values():
            for key in images + videos:
                obs[key] = np.ascontiguousarray(obs[key][:, ::-1, ::-1])
    return {index: Episode(actions, obs, seed=-1) for index, (actions, obs) in parts.items()}


def _check_frames(table, path: Path, entry: EpisodeEntry, rows: np.ndarray) -> None:
    """The frames a data file holds for an episode agree with the episode index."""
    episode = table.column("episode_index").to_numpy()[rows]
    if len(rows) != entry.length or (episode != entry.index).any():
        others = sorted(set(episode[episode != entry.index].tolist()))
        raise bad(path, f"holds {len(rows)} frames of episode {entry.index}"
                        + (f" and frames of episode {others[0]}" if others else "")
                        + f"; the episode index says {entry.length}")
    frames = table.column("frame_index").to_numpy()[rows]
    if not np.array_equal(frames, np.arange(entry.length)):
        raise bad(path, f"episode {entry.index}'s frame_index is not 0..{entry.length - 1} in "
                        "order, as the episode index says")
    if entry.rows is not None:
        index = table.column("index").to_numpy()[rows]
        if not np.array_equal(index, np.arange(*entry.rows)):
            raise bad(path, f"episode {entry.index}'s frames have index {index[0]}.."
                            f"{index[-1]}; the episode index says {entry.rows[0]}.."
                            f"{entry.rows[1] - 1}")


def _vectors(table, name: str, take, path: Path) -> np.ndarray:
    import pyarrow as pa

    values = table.column(name).take(take).combine_chunks()
    if values.null_count:
        raise bad(path, f"column {name!r} has empty rows; expected a vector in every frame")
    n = len(values)
    if pa.types.is_list(values.type) or pa.types.is_large_list(values.type) \
            or pa.types.is_fixed_size_list(values.type):
        flat = values.flatten().to_numpy(zero_copy_only=False)
        if n == 0 or flat.size % n or (pa.types.is_list(values.type)
                                       and len(set(values.value_lengths().to_pylist())) > 1):
            raise bad(path, f"column {name!r} holds vectors of different lengths")
        return flat.reshape(n, flat.size // n).astype(np.float32)
    if pa.types.is_integer(values.type) or pa.types.is_floating(values.type):
        return values.to_numpy(zero_copy_only=False).reshape(n, 1).astype(np.float32)
    raise bad(path, f"column {name!r} is {values.type}; expected a list of numbers")


def _pngs(table, name: str, take, path: Path, size: int) -> np.ndarray:
    import pyarrow as pa

    values = table.column(name).take(take).combine_chunks()
    if pa.types.is_struct(values.type):
        if values.type.get_field_index("bytes") < 0:
            raise bad(path, f"column {name!r} has no 'bytes' field; expected PNG bytes")
        values = values.field("bytes")
    images = []
    for row, data in enumerate(values.to_pylist()):
        if data is None:
            raise bad(path, f"column {name!r} row {row} has no PNG bytes (image files beside "
                            "the dataset are not read)")
        try:
            image = decode_png(data)
        except FrameError as err:
            raise bad(path, f"column {name!r} row {row}: {err}") from None
        if image.shape != (size, size, 3):
            raise bad(path, f"column {name!r} row {row} is {image.shape[1]}x{image.shape[0]}; "
                            f"expected {size}x{size} RGB")
        images.append(image)
    return np.stack(images)


def _videos(layout: Layout, entries: list[EpisodeEntry], feature: str, size: int):
    """(entry, frames) for each entry: each video file decoded once for all its episodes."""
    by_file: dict[Path, list[EpisodeEntry]] = {}
    for entry in entries:
        by_file.setdefault(entry.videos[feature].path, []).append(entry)
    for path, group in by_file.items():
        if not path.is_file():
            raise bad(path, f"missing; expected episode {group[0].index}'s {feature} video")
        try:
            frames = decode_video(path, [(e.videos[feature].start, e.length) for e in group],
                                  layout.fps)
        except SegmentError as err:
            raise bad(path, f"{err}; expected episode {group[err.segment].index}'s {feature} "
                            "frames") from None
        for entry, images in zip(group, frames):
            if images.shape[1:] != (size, size, 3):
                raise bad(path, f"frames are {images.shape[2]}x{images.shape[1]}; expected "
                                f"{size}x{size} as info.json says")
            yield entry, images
