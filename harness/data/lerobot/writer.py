"""Episodes as a LeRobotDataset v3.0 folder, the layout LeRobot 0.4 and later load:

    meta/info.json      codebase_version v3.0, fps, features, data_path, video_path, totals
    meta/stats.json     per feature min, max, mean, std, count, q01 q10 q50 q90 q99 (images per
                        channel in [0, 1], shape [3, 1, 1], as LeRobot computes them)
    meta/tasks.parquet  task text (the index) -> task_index, written by pandas as LeRobot does
    meta/episodes/chunk-000/file-000.parquet
                        a row per episode: tasks, length, dataset_from/to_index, its data file,
                        each video's file and from/to timestamps, its own stats (stats/...)
    data/chunk-000/file-000.parquet ...
                        action, observation.state, timestamp, frame_index, episode_index,
                        index, task_index; images as PNG bytes when written as images
    videos/<key>/chunk-000/file-000.mp4 ...
                        AV1 (LeRobot's settings), episodes one after another

A new data (and video) file starts past DATA_FILE_MB (or VIDEO_FILE_MB). Everything is written
into a temporary folder beside `out` and renamed into place at the end: a reader never sees a
half-written dataset.
"""

from __future__ import annotations

import json
import os
import shutil
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from harness.common.errors import RetainError
from harness.data.demos import Episode
from harness.data.lerobot.frames import VIDEO_PIX_FMT, VideoWriter, encode_png
from harness.data.lerobot.layout import DEFAULT_CHUNKS_SIZE
from suites.base import AGENTVIEW, CAMERA_KEYS, EYE_IN_HAND

CODEBASE_VERSION = "v3.0"
FEATURES = {"actions": "action", "state": "observation.state",
            AGENTVIEW: "observation.images.image", EYE_IN_HAND: "observation.images.wrist_image"}
"""Retain key -> the feature written: LeRobot's names, and the LIBERO sets' camera names."""
DATA_FILE_MB, VIDEO_FILE_MB = 100, 500  # LeRobot's defaults
DATA_PATH = "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet"
VIDEO_PATH = "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4"
EPISODES_PATH = "meta/episodes/chunk-000/file-000.parquet"
INDEX_FEATURES = {"timestamp": "float32", "frame_index": "int64", "episode_index": "int64",
                  "index": "int64", "task_index": "int64"}
QUANTILES = {"q01": 0.01, "q10": 0.10, "q50": 0.50, "q90": 0.90, "q99": 0.99}
STAT_IMAGES = 100  # frames per episode an image's stats are taken from (evenly spaced)
IMAGE_MODES = ("video", "png")


@dataclass
class Written:
    path: Path
    episodes: int = 0
    frames: int = 0
    tasks: int = 0
    files: int = 0
    bytes: int = 0
    cameras: list[str] = field(default_factory=list)


def write_dataset(out: str | Path, tasks: Iterable[tuple[str, list[Episode]]], fps: float,
                  robot_type: str = "", images: str = "video",
                  rotate_images: bool = False) -> Written:
    """Write each (task text, episodes) in order. Episodes need `actions` and obs `state`, and
    either both cameras or none; `images` "video" (AV1 mp4) or "png" (lossless, in the parquet
    files); `rotate_images` turns them 180 degrees (LIBERO's community convention)."""
    out = Path(out).resolve()
    fps = int(fps) if float(fps).is_integer() else float(fps)
    if images not in IMAGE_MODES:
        raise RetainError(f"unknown images={images!r}; valid: {', '.join(IMAGE_MODES)}")
    if out.exists():
        raise RetainError(f"{out} already exists; expected a new folder for the dataset")
    tmp = out.with_name(f".{out.name}.{os.getpid()}.tmp")
    shutil.rmtree(tmp, ignore_errors=True)
    try:
        writer = _Writer(tmp, fps, images, rotate_images)
        for text, episodes in tasks:
            for episode in episodes:
                writer.add(text, episode)
        written = writer.finish(robot_type)
        os.rename(tmp, out)
    finally:
        shutil.rmtree(tmp, ignore_errors=True)
    written.path = out
    written.bytes = sum(f.stat().st_size for f in out.rglob("*") if f.is_file())
    written.files = sum(1 for f in out.rglob("*") if f.is_file())
    return written


class _Writer:
    def __init__(self, root: Path, fps: float, images: str, rotate: bool):
        self.root, self.fps, self.images, self.rotate = root, fps, images, rotate
        self.features: dict[str, dict] | None = None
        self.cameras: list[str] = []
        self.task_index: dict[str, int] = {}
        self.episode_rows: list[dict] = []
        self.frames = 0
        self.file_number = 0
        self.buffer: dict[str, list] = {}
        self.buffer_bytes = 0
        self.videos: dict[str, VideoWriter] = {}
        self.vectors: dict[str, list[np.ndarray]] = {}
        self.image_counts: dict[str, np.ndarray] = {}

    # -- per episode ----------------------------------------------------------------------------

    def add(self, text: str, episode: Episode) -> None:
        if self.features is None:
            self._start(episode)
        cameras = sorted(k for k in episode.obs if k in CAMERA_KEYS)
        if cameras != self.cameras or "state" not in episode.obs:
            raise RetainError(f"episode {len(self.episode_rows)} ({text!r}) has observations "
                              f"{sorted(episode.obs)}; expected state and {self.cameras or 'no cameras'}"
                              " like the first")
        index = len(self.episode_rows)
        task = self.task_index.setdefault(text, len(self.task_index))
        length = len(episode)
        chunk, file = divmod(self.file_number, DEFAULT_CHUNKS_SIZE)
        columns = {
            FEATURES["actions"]: np.asarray(episode.actions, np.float32),
            FEATURES["state"]: np.asarray(episode.obs["state"], np.float32),
            "timestamp": (np.arange(length) / self.fps).astype(np.float32),
            "frame_index": np.arange(length, dtype=np.int64),
            "episode_index": np.full(length, index, np.int64),
            "index": np.arange(self.frames, self.frames + length, dtype=np.int64),
            "task_index": np.full(length, task, np.int64),
        }
        row = {"episode_index": index, "tasks": [text], "length": length,
               "data/chunk_index": chunk, "data/file_index": file,
               "dataset_from_index": self.frames, "dataset_to_index": self.frames + length}
        stats = {name: _vector_stats(values) for name, values in columns.items()}
        for name in (FEATURES["actions"], FEATURES["state"], *INDEX_FEATURES):
            self.vectors.setdefault(name, []).append(columns[name].reshape(length, -1))
        for key in self.cameras:
            frames = np.asarray(episode.obs[key], np.uint8)
            if self.rotate:
                frames = np.ascontiguousarray(frames[:, ::-1, ::-1])
            name = FEATURES[key]
            counts = _channel_counts(frames)
            self.image_counts[name] = self.image_counts.get(name, 0) + counts
            stats[name] = _image_stats(counts)
            if self.images == "png":
                columns[name] = [encode_png(f) for f in frames]
                self.buffer_bytes += sum(len(b) for b in columns[name])
            else:
                video = self._video(name, frames.shape[1:3])
                start = video.frames / self.fps
                video.write(frames)
                row.update({f"videos/{name}/chunk_index": chunk,
                            f"videos/{name}/file_index": file,
                            f"videos/{name}/from_timestamp": start,
                            f"videos/{name}/to_timestamp": video.frames / self.fps})
        row.update({"meta/episodes/chunk_index": 0, "meta/episodes/file_index": 0})
        row.update({f"stats/{name}/{stat}": value for name, s in stats.items()
                    for stat, value in s.items()})
        self.episode_rows.append(row)
        for name, values in columns.items():
            self.buffer.setdefault(name, []).append(values)
        self.buffer_bytes += sum(v.nbytes for v in columns.values() if isinstance(v, np.ndarray))
        self.frames += length
        if (self.buffer_bytes > DATA_FILE_MB * 2**20
                or any(v.bytes > VIDEO_FILE_MB * 2**20 for v in self.videos.values())):
            self._flush()

    def _start(self, episode: Episode) -> None:
        self.cameras = sorted(k for k in episode.obs if k in CAMERA_KEYS)
        features = {}
        for key in ("actions", "state"):
            width = (episode.actions if key == "actions" else episode.obs["state"]).shape[1]
            features[FEATURES[key]] = {"dtype": "float32", "shape": [int(width)],
                                       "names": [f"{key}_{i}" for i in range(width)]}
        for key in self.cameras:
            height, width = episode.obs[key].shape[1:3]
            feature = {"dtype": self.images if self.images == "video" else "image",
                       "shape": [int(height), int(width), 3],
                       "names": ["height", "width", "channels"]}
            if self.images == "video":
                feature["info"] = {"video.height": int(height), "video.width": int(width),
                                   "video.codec": "av1", "video.pix_fmt": VIDEO_PIX_FMT,
                                   "video.is_depth_map": False, "video.fps": self.fps,
                                   "video.channels": 3, "has_audio": False}
            features[FEATURES[key]] = feature
        for name, dtype in INDEX_FEATURES.items():
            features[name] = {"dtype": dtype, "shape": [1], "names": None}
        self.features = features

    def _video(self, name: str, size: tuple[int, int]) -> VideoWriter:
        if name not in self.videos:
            chunk, file = divmod(self.file_number, DEFAULT_CHUNKS_SIZE)
            path = self.root / VIDEO_PATH.format(video_key=name, chunk_index=chunk, file_index=file)
            self.videos[name] = VideoWriter(path, self.fps, *size)
        return self.videos[name]

    # -- files ------------------------------------------------------------------------------------

    def _flush(self) -> None:
        """Close the current data file (and video files); the next episode starts new ones."""
        import pyarrow as pa
        import pyarrow.parquet as pq

        if not self.buffer:
            return
        arrays, hf = {}, {}
        for name, parts in self.buffer.items():
            feature = self.features[name]
            if feature["dtype"] == "image":
                values = [b for part in parts for b in part]
                arrays[name] = pa.StructArray.from_arrays(
                    [pa.array(values, pa.binary()), pa.array([None] * len(values), pa.string())],
                    names=["bytes", "path"])
                hf[name] = {"_type": "Image"}
            elif name in INDEX_FEATURES:
                arrays[name] = pa.array(np.concatenate(parts))
                hf[name] = {"dtype": feature["dtype"], "_type": "Value"}
            else:
                values = np.concatenate(parts)
                arrays[name] = pa.FixedSizeListArray.from_arrays(pa.array(values.ravel()),
                                                                 values.shape[1])
                hf[name] = {"feature": {"dtype": "float32", "_type": "Value"},
                            "length": int(values.shape[1]), "_type": "Sequence"}
        table = pa.table(arrays).replace_schema_metadata(
            {"huggingface": json.dumps({"info": {"features": hf}})})
        chunk, file = divmod(self.file_number, DEFAULT_CHUNKS_SIZE)
        path = self.root / DATA_PATH.format(chunk_index=chunk, file_index=file)
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(table, path, compression="snappy")
        for video in self.videos.values():
            video.close()
        self.buffer, self.buffer_bytes, self.videos = {}, 0, {}
        self.file_number += 1

    def finish(self, robot_type: str) -> Written:
        import pandas as pd
        import pyarrow as pa
        import pyarrow.parquet as pq

        if not self.episode_rows:
            raise RetainError("no episodes to write")
        self._flush()
        meta = self.root / "meta"
        (meta / "episodes/chunk-000").mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.Table.from_pylist(self.episode_rows), self.root / EPISODES_PATH)
        tasks = pd.DataFrame({"task_index": list(self.task_index.values())},
                             index=pd.Index(list(self.task_index), name="task"))
        tasks.to_parquet(meta / "tasks.parquet")
        stats = {name: _vector_stats(np.concatenate(parts)) for name, parts in self.vectors.items()}
        stats.update({name: _image_stats(counts) for name, counts in self.image_counts.items()})
        _write_json(meta / "stats.json", stats)
        info = {
            "codebase_version": CODEBASE_VERSION, "robot_type": robot_type or None,
            "total_episodes": len(self.episode_rows), "total_frames": self.frames,
            "total_tasks": len(self.task_index), "chunks_size": DEFAULT_CHUNKS_SIZE,
            "data_files_size_in_mb": DATA_FILE_MB, "video_files_size_in_mb": VIDEO_FILE_MB,
            "fps": self.fps, "splits": {"train": f"0:{len(self.episode_rows)}"},
            "data_path": DATA_PATH,
            "video_path": VIDEO_PATH if self.cameras and self.images == "video" else None,
            "features": self.features,
        }
        _write_json(meta / "info.json", info)
        return Written(Path(), len(self.episode_rows), self.frames, len(self.task_index),
                       cameras=[FEATURES[k] for k in self.cameras])


def _write_json(path: Path, value) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(value, indent=4, ensure_ascii=False) + "\n")


def _vector_stats(values: np.ndarray) -> dict[str, list]:
    """LeRobot's stats of a [T] or [T, D] feature over its frames (lists of D numbers)."""
    values = np.asarray(values, np.float64).reshape(len(values), -1)
    stats = {"min": values.min(0), "max": values.max(0), "mean": values.mean(0),
             "std": values.std(0), "count": np.array([len(values)])}
    stats.update({name: np.quantile(values, q, axis=0) for name, q in QUANTILES.items()})
    return {k: v.tolist() for k, v in stats.items()}


def _channel_counts(frames: np.ndarray) -> np.ndarray:
    """[3, 256] histograms of uint8 values per channel over up to STAT_IMAGES frames, plus the
    frame count in column 256: exact stats per episode, and summed, over the dataset."""
    pick = np.unique(np.linspace(0, len(frames) - 1, min(len(frames), STAT_IMAGES)).round()
                     .astype(int))
    sample = frames[pick].reshape(-1, 3)
    counts = np.zeros((3, 257), np.int64)
    for c in range(3):
        counts[c, :256] = np.bincount(sample[:, c], minlength=256)
    counts[:, 256] = len(pick)
    return counts


def _image_stats(counts: np.ndarray) -> dict[str, list]:
    """Per channel over the sampled pixels, values in [0, 1], each of shape [3, 1, 1]."""
    levels = np.arange(256) / 255.0
    hist = counts[:, :256].astype(np.float64)
    total = hist.sum(1)
    mean = (hist * levels).sum(1) / total
    std = np.sqrt((hist * (levels - mean[:, None]) ** 2).sum(1) / total)
    cumulative = np.cumsum(hist, 1) / total[:, None]
    stats = {"min": [levels[np.flatnonzero(h)[0]] for h in hist],
             "max": [levels[np.flatnonzero(h)[-1]] for h in hist],
             "mean": mean, "std": std}
    stats.update({name: [levels[np.searchsorted(c, q)] for c in cumulative]
                  for name, q in QUANTILES.items()})
    out = {k: np.asarray(v, np.float64).reshape(3, 1, 1).tolist() for k, v in stats.items()}
    out["count"] = [int(counts[0, 256])]
    return out
