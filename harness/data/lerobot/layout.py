"""A LeRobotDataset folder's layout: its format version, features, tasks, and where each
episode's frames are (its parquet file and rows, its video files and start times), read from
`meta/` with pyarrow and checked, so a malformed folder is one line naming the file.

    v3.0  meta/info.json, meta/tasks.parquet, meta/episodes/chunk-*/file-*.parquet (a row per
          episode: tasks, length, dataset_from_index/to_index, each video's chunk, file and
          from/to timestamps); data/chunk-*/file-*.parquet and videos/<key>/chunk-*/file-*.mp4
          hold many episodes each.
    v2.x  meta/info.json, meta/tasks.jsonl, meta/episodes.jsonl (and meta/episodes_stats.jsonl
          in v2.1, meta/stats.json in v2.0); one parquet file and one mp4 per episode and video
          key: data/chunk-XXX/episode_XXXXXX.parquet, videos/chunk-XXX/<key>/episode_XXXXXX.mp4.
Features of dtype `image` are PNG bytes in a struct column of the data files (no video).
"""

from __future__ import annotations

import hashlib
import json
import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from harness.common.errors import RetainError

VERSIONS = ("v2.0", "v2.1", "v3.0")
INFO = "meta/info.json"
DEFAULT_CHUNKS_SIZE = 1000  # files per chunk folder, LeRobot's default
CAMERA_DTYPES = ("image", "video")


class LeRobotError(RetainError):
    """A LeRobot dataset folder that is missing a part, is malformed, or disagrees with itself."""


def bad(path, why: str) -> LeRobotError:
    """The one-line error: the file, then what was wrong and what was expected."""
    return LeRobotError(f"{path}: {why}")


def first_line(err: Exception) -> str:
    text = str(err).strip()
    return text.splitlines()[0] if text else type(err).__name__


@dataclass(frozen=True)
class VideoSpan:
    path: Path
    start: float  # seconds into the file of the episode's first frame (v3.0; 0.0 in v2.x)


@dataclass(frozen=True)
class EpisodeEntry:
    index: int
    tasks: tuple[str, ...]
    length: int
    data: Path  # the parquet file holding its frames
    rows: tuple[int, int] | None  # v3.0: its frames' global `index` range [from, to); v2.x: None
    videos: dict[str, VideoSpan]  # video feature -> its frames' file and start


@dataclass(frozen=True)
class Layout:
    root: Path
    version: str
    fps: float
    features: dict[str, dict]
    tasks: dict[int, str]  # task_index -> text
    tasks_file: Path
    episodes: tuple[EpisodeEntry, ...]  # in episode_index order
    episodes_file: Path  # v2.x: meta/episodes.jsonl; v3.0: the meta/episodes folder
    fingerprint: str  # a hash of every file's path, size and time: a changed folder reads anew

    @property
    def info_file(self) -> Path:
        return self.root / INFO

    def camera_shape(self, key: str) -> tuple[int, int]:
        """(height, width) of a camera feature, channels first or last as its names say."""
        feature = self.features[key]
        shape = [int(s) for s in feature["shape"]]
        names = [str(n).lower() for n in (feature.get("names") or [])]
        if len(shape) != 3 or 3 not in (shape[0], shape[-1]):
            raise bad(self.info_file, f"feature {key!r} has shape {shape}; expected an RGB "
                                      "image's [height, width, 3]")
        channels_first = names[:1] in (["channel"], ["channels"]) or (shape[-1] != 3)
        return (shape[1], shape[2]) if channels_first else (shape[0], shape[1])


def is_dataset_folder(path: str | Path) -> bool:
    """Whether `path` looks like a LeRobot dataset (a meta/ folder or data/chunk-* folders),
    rather than a folder of LIBERO's HDF5 files."""
    folder = Path(path)
    return (folder / "meta").is_dir() or any(folder.glob("data/chunk-*"))


def open_layout(root: str | Path) -> Layout:
    root = Path(root).resolve()
    if not root.is_dir():
        raise LeRobotError(f"demos_dir {str(root)!r} is not a folder")
    info_path = root / INFO
    if not info_path.is_file():
        raise bad(info_path, "missing; expected a LeRobotDataset's meta/info.json "
                             f"(codebase_version {', '.join(VERSIONS)})")
    info = read_json(info_path)
    if not isinstance(info, dict):
        raise bad(info_path, "expected a JSON object")
    version = info.get("codebase_version")
    if version not in VERSIONS:
        raise bad(info_path, f"unknown codebase_version {version!r}; expected one of "
                             f"{', '.join(VERSIONS)}")
    for key in ("fps", "features", "data_path"):
        if key not in info:
            raise bad(info_path, f"missing key {key!r}")
    features = _features(info_path, info["features"])
    videos = [k for k, f in features.items() if f["dtype"] == "video"]
    if videos and not info.get("video_path"):
        raise bad(info_path, f"missing key 'video_path' (feature {videos[0]!r} is a video)")
    try:
        fps = float(info["fps"])
    except (TypeError, ValueError):
        fps = 0.0
    if fps <= 0:
        raise bad(info_path, f"fps {info['fps']!r}; expected a positive number")
    read_meta = _v3_meta if version == "v3.0" else _v2_meta
    tasks, tasks_file, episodes, episodes_file = read_meta(root, info, videos)
    return Layout(root, version, fps, features, tasks, tasks_file, episodes, episodes_file,
                  fingerprint(root))


def _features(path: Path, features) -> dict[str, dict]:
    if not isinstance(features, dict) or not features:
        raise bad(path, "'features' is empty or not a mapping; expected feature -> "
                        "{dtype, shape}")
    for key, feature in features.items():
        if (not isinstance(feature, dict) or "dtype" not in feature
                or not isinstance(feature.get("shape"), (list, tuple))):
            raise bad(path, f"feature {key!r} has no dtype or shape")
    return features


def read_json(path: Path):
    try:
        return json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as err:
        raise bad(path, f"not readable JSON ({first_line(err)})") from None


def read_jsonl(path: Path, what: str) -> list[dict]:
    if not path.is_file():
        raise bad(path, f"missing; expected {what}, one JSON object a line")
    rows = []
    try:
        lines = path.read_text().splitlines()
    except (OSError, UnicodeDecodeError) as err:
        raise bad(path, f"not readable ({first_line(err)})") from None
    for number, line in enumerate(lines, 1):
        if line.strip():
            try:
                row = json.loads(line)
            except json.JSONDecodeError:
                raise bad(path, f"line {number} is not JSON; expected {what}") from None
            if not isinstance(row, dict):
                raise bad(path, f"line {number} is not a JSON object; expected {what}")
            rows.append(row)
    return rows


def read_parquet(path: Path, columns: list[str] | None = None, what: str = "",
                 filters=None):
    """The table (only `columns`), or one line naming the file: missing, unreadable, or
    without a column."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    if not path.is_file():
        raise bad(path, f"missing; expected {what or 'a parquet file'}")
    try:
        names = pq.read_schema(path).names
        for column in columns or ():
            if column not in names:
                raise bad(path, f"missing key {column!r}" + (f" ({what})" if what else ""))
        return pq.read_table(path, columns=columns, filters=filters)
    except (OSError, pa.ArrowException) as err:
        raise bad(path, f"not a readable parquet file ({first_line(err)})") from None


def _field(path: Path, row: dict, key: str, kind, where: str):
    if key not in row:
        raise bad(path, f"missing key {key!r} in {where}")
    value = row[key]
    if kind is int and isinstance(value, (int, np.integer)) and not isinstance(value, bool):
        return int(value)
    if kind is float and isinstance(value, (int, float, np.integer, np.floating)):
        return float(value)
    if kind is list and isinstance(value, (list, tuple, np.ndarray)):
        return [str(v) for v in value]
    if kind is str and isinstance(value, str):
        return value
    raise bad(path, f"{key} = {value!r} in {where}; expected {kind.__name__}")


def _template(info_path: Path, key: str, template: str, **fields) -> str:
    try:
        return template.format(**fields)
    except (KeyError, IndexError, ValueError) as err:
        raise bad(info_path, f"{key} {template!r} has a field other than "
                             f"{', '.join(fields)} ({first_line(err)})") from None


def _v2_meta(root: Path, info: dict, videos: list[str]):
    info_path = root / INFO
    tasks_file, episodes_file = root / "meta/tasks.jsonl", root / "meta/episodes.jsonl"
    tasks = {}
    for i, row in enumerate(read_jsonl(tasks_file, "{task_index, task}"), 1):
        tasks[_field(tasks_file, row, "task_index", int, f"line {i}")] = \
            _field(tasks_file, row, "task", str, f"line {i}")
    chunks = int(info.get("chunks_size") or DEFAULT_CHUNKS_SIZE)
    episodes = []
    for i, row in enumerate(read_jsonl(episodes_file, "{episode_index, tasks, length}"), 1):
        index = _field(episodes_file, row, "episode_index", int, f"line {i}")
        chunk = index // chunks
        data = root / _template(info_path, "data_path", info["data_path"], episode_chunk=chunk,
                                episode_index=index)
        spans = {key: VideoSpan(root / _template(info_path, "video_path", info["video_path"],
                                                 episode_chunk=chunk, video_key=key,
                                                 episode_index=index), 0.0)
                 for key in videos}
        episodes.append(EpisodeEntry(index, tuple(_field(episodes_file, row, "tasks", list,
                                                         f"line {i}")),
                                     _field(episodes_file, row, "length", int, f"line {i}"),
                                     data, None, spans))
    return tasks, tasks_file, _in_order(episodes_file, episodes), episodes_file


def _v3_meta(root: Path, info: dict, videos: list[str]):
    info_path = root / INFO
    tasks_file = root / "meta/tasks.parquet"
    table = read_parquet(tasks_file, what="the tasks (task text -> task_index)")
    names = table.column_names
    if "task_index" not in names:
        raise bad(tasks_file, "missing key 'task_index'")
    text = next((n for n in ("task", "__index_level_0__") if n in names), None)
    if text is None:
        raise bad(tasks_file, "missing key 'task' (the task text, LeRobot's index column)")
    tasks = {int(i): str(t) for i, t in zip(table.column("task_index").to_pylist(),
                                            table.column(text).to_pylist())}
    folder = root / "meta/episodes"
    files = sorted(folder.glob("chunk-*/file-*.parquet"))
    if not files:
        raise bad(folder, "missing; expected chunk-*/file-*.parquet files listing the episodes")
    columns = ["episode_index", "tasks", "length", "data/chunk_index", "data/file_index",
               "dataset_from_index", "dataset_to_index"]
    for key in videos:
        columns += [f"videos/{key}/{c}" for c in ("chunk_index", "file_index", "from_timestamp")]
    episodes = []
    for path in files:
        for row in read_parquet(path, columns, "the episodes' index").to_pylist():
            where = f"episode {row.get('episode_index')}"
            index = _field(path, row, "episode_index", int, "a row")
            start = _field(path, row, "dataset_from_index", int, where)
            end = _field(path, row, "dataset_to_index", int, where)
            length = _field(path, row, "length", int, where)
            if end - start != length:
                raise bad(path, f"{where} spans frames {start}..{end}, not its length {length}")
            data = root / _template(info_path, "data_path", info["data_path"],
                                    chunk_index=_field(path, row, "data/chunk_index", int, where),
                                    file_index=_field(path, row, "data/file_index", int, where))
            spans = {}
            for key in videos:
                video = root / _template(
                    info_path, "video_path", info["video_path"], video_key=key,
                    chunk_index=_field(path, row, f"videos/{key}/chunk_index", int, where),
                    file_index=_field(path, row, f"videos/{key}/file_index", int, where))
                spans[key] = VideoSpan(video, _field(path, row, f"videos/{key}/from_timestamp",
                                                     float, where))
            episodes.append(EpisodeEntry(index, tuple(_field(path, row, "tasks", list, where)),
                                         length, data, (start, end), spans))
    return tasks, tasks_file, _in_order(folder, episodes), folder


def _in_order(path: Path, episodes: list[EpisodeEntry]) -> tuple[EpisodeEntry, ...]:
    ordered = sorted(episodes, key=lambda e: e.index)
    for a, b in zip(ordered, ordered[1:]):
        if a.index == b.index:
            raise bad(path, f"episode {a.index} is listed twice")
    for e in ordered:
        if e.length <= 0:
            raise bad(path, f"episode {e.index} has length {e.length}; expected at least 1")
    return tuple(ordered)


def fingerprint(root: Path) -> str:
    """Every file's path, size and modification time under meta/, data/, videos/ and images/."""
    digest = hashlib.sha256()
    for part in ("meta", "data", "videos", "images"):
        for folder, dirs, files in os.walk(root / part):
            dirs.sort()
            for name in sorted(files):
                stat = os.stat(os.path.join(folder, name))
                rel = os.path.relpath(os.path.join(folder, name), root)
                digest.update(f"{rel}:{stat.st_size}:{stat.st_mtime_ns}\n".encode())
    return digest.hexdigest()[:16]
