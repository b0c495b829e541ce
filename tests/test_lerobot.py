"""LeRobot datasets in and out (harness/data/lerobot): folders of format v2.1 (videos), v2.0 (images
in the parquet files, as physical-intelligence/libero) and v3.0 (many episodes per video file),
each written here with pyarrow and PyAV as LeRobot lays them out, read as a benchmark's
demos_dir; the writer's folder read back; and every malformed input as one line naming the file,
with nothing cached from it."""

from __future__ import annotations

import json
from fractions import Fraction
from pathlib import Path

import av
import numpy as np
import pandas as pd
import pyarrow as pa
import pyarrow.parquet as pq
import pytest

from harness.common.errors import RetainError
from harness.config.benchmark import BenchConfig
from harness.data.demos import Episode
from harness.data.lerobot.writer import write_dataset
from harness.data.prepare import user_demos
from suites.base import Suite

SIZE, FPS = 32, 10
TASKS = {"lift": "Lift the red cube.", "push": "push the blue block to the goal"}


class TableSuite(Suite):
    """A suite of two tasks and given widths, without a simulator: reading demos needs none."""

    max_episode_steps = 50

    def __init__(self, name="toy", state_dim=8, action_dim=7):
        super().__init__()
        self.name, self.state_dim, self.action_dim = name, state_dim, action_dim

    def task_names(self):
        return list(TASKS)

    def instruction(self, task):
        return TASKS[self.check_task(task)].lower().rstrip(".")

    def make_env(self, task, cameras=False, image_size=84):
        raise AssertionError("reading a dataset built a simulator")


SUITE = TableSuite()


def config(tmp_path: Path, folder: Path, **settings) -> BenchConfig:
    settings = {"demos_per_task": 2, "heldout_demos_per_task": 1, "image_size": SIZE, **settings}
    return BenchConfig("t", "toy", ["lift"], ["push"], demos_dir=str(folder),
                       cache_dir=str(tmp_path / "cache"), **settings)


def frames(length: int, shade: int) -> np.ndarray:
    """Flat frames, brighter each step (lossy video keeps them close), [T, S, S, 3] uint8."""
    values = (shade + 6 * np.arange(length))[:, None, None, None] + np.array([0, 40, 80])
    return np.broadcast_to(values, (length, SIZE, SIZE, 3)).clip(0, 255).astype(np.uint8).copy()


def make_episodes(lengths=(5, 6, 4), seed=0, action_dim=7, state_dim=8) -> list[Episode]:
    rng = np.random.default_rng(seed)
    out = []
    for i, n in enumerate(lengths):
        image = frames(n, 10 * i)
        image[:, :4, :4] = 255  # a corner marks the top-left: a turn is visible
        out.append(Episode(rng.uniform(-1, 1, (n, action_dim)).astype(np.float32),
                           {"state": rng.normal(size=(n, state_dim)).astype(np.float32),
                            "agentview_rgb": image, "eye_in_hand_rgb": 255 - image}, seed=-1))
    return out


def encode_mp4(path: Path, images: np.ndarray, start_frame: int = 0, container=None):
    """H.264 at FPS, frame i shown at (start_frame + i) / FPS: PyAV, as a user's tool would."""
    own = container is None
    if own:
        path.parent.mkdir(parents=True, exist_ok=True)
        container = av.open(str(path), "w")
        stream = container.add_stream("libx264", rate=FPS)
        stream.width = stream.height = SIZE
        stream.pix_fmt = "yuv420p"
    stream = container.streams.video[0]
    for i, image in enumerate(images):
        frame = av.VideoFrame.from_ndarray(image, format="rgb24")
        frame.pts, frame.time_base = start_frame + i, Fraction(1, FPS)
        for packet in stream.encode(frame):
            container.mux(packet)
    if own:
        for packet in stream.encode(None):
            container.mux(packet)
        container.close()
    return container


def png(image: np.ndarray) -> bytes:
    codec = av.CodecContext.create("png", "w")
    codec.width = codec.height = SIZE
    codec.pix_fmt = "rgb24"
    frame = av.VideoFrame.from_ndarray(image, format="rgb24")
    return b"".join(bytes(p) for p in codec.encode(frame) + codec.encode(None))


def vector(values: np.ndarray) -> pa.Array:
    return pa.array(list(values), pa.list_(pa.float32()))


def features(keys: dict[str, str], camera_dtype: str | None, widths=(7, 8)) -> dict:
    out = {keys["actions"]: {"dtype": "float32", "shape": [widths[0]], "names": None},
           keys["state"]: {"dtype": "float32", "shape": [widths[1]], "names": None}}
    for key in ("agentview_rgb", "eye_in_hand_rgb"):
        if camera_dtype:
            out[keys[key]] = {"dtype": camera_dtype, "shape": [SIZE, SIZE, 3],
                              "names": ["height", "width", "channel"]}
    for name in ("timestamp", "frame_index", "episode_index", "index", "task_index"):
        out[name] = {"dtype": "float32" if name == "timestamp" else "int64", "shape": [1],
                     "names": None}
    return out


V2_KEYS = {"actions": "action", "state": "observation.state",
           "agentview_rgb": "observation.images.image",
           "eye_in_hand_rgb": "observation.images.wrist_image"}
PI_KEYS = {"actions": "actions", "state": "state", "agentview_rgb": "image",
           "eye_in_hand_rgb": "wrist_image"}


def write_v2(root: Path, episodes: list[tuple[str, Episode]], version: str = "v2.1",
             cameras: str | None = "video", keys: dict[str, str] = V2_KEYS) -> Path:
    """A v2.x folder, one parquet file (and mp4 per camera) per episode."""
    info = {"codebase_version": version, "robot_type": "panda", "fps": FPS, "chunks_size": 1000,
            "total_episodes": len(episodes), "total_frames": sum(len(e) for _, e in episodes),
            "data_path": "data/chunk-{episode_chunk:03d}/episode_{episode_index:06d}.parquet",
            "video_path": ("videos/chunk-{episode_chunk:03d}/{video_key}/"
                           "episode_{episode_index:06d}.mp4") if cameras == "video" else None,
            "features": features(keys, cameras, (episodes[0][1].actions.shape[1],
                                                 episodes[0][1].obs["state"].shape[1]))}
    texts = list(dict.fromkeys(t for t, _ in episodes))
    (root / "meta").mkdir(parents=True)
    (root / "meta/info.json").write_text(json.dumps(info, indent=4))
    (root / "meta/tasks.jsonl").write_text("".join(
        json.dumps({"task_index": i, "task": t}) + "\n" for i, t in enumerate(texts)))
    (root / "meta/episodes.jsonl").write_text("".join(
        json.dumps({"episode_index": i, "tasks": [t], "length": len(e)}) + "\n"
        for i, (t, e) in enumerate(episodes)))
    stats = "episodes_stats.jsonl" if version == "v2.1" else "stats.json"
    (root / "meta" / stats).write_text("{}\n")
    start = 0
    for i, (text, episode) in enumerate(episodes):
        n = len(episode)
        columns = {keys["actions"]: vector(episode.actions),
                   keys["state"]: vector(episode.obs["state"]),
                   "timestamp": pa.array(np.arange(n) / FPS, pa.float32()),
                   "frame_index": pa.array(np.arange(n)), "episode_index": pa.array([i] * n),
                   "index": pa.array(np.arange(start, start + n)),
                   "task_index": pa.array([texts.index(text)] * n)}
        for key in ("agentview_rgb", "eye_in_hand_rgb"):
            if cameras == "image":
                columns[keys[key]] = pa.array(
                    [{"bytes": png(f), "path": None} for f in episode.obs[key]],
                    pa.struct([("bytes", pa.binary()), ("path", pa.string())]))
            elif cameras == "video":
                encode_mp4(root / f"videos/chunk-000/{keys[key]}/episode_{i:06d}.mp4",
                           episode.obs[key])
        path = root / f"data/chunk-000/episode_{i:06d}.parquet"
        path.parent.mkdir(parents=True, exist_ok=True)
        pq.write_table(pa.table(columns), path)
        start += n
    return root


def write_v3(root: Path, episodes: list[tuple[str, Episode]], keys=V2_KEYS) -> Path:
    """A v3.0 folder: every episode in one data file and one mp4 per camera."""
    texts = list(dict.fromkeys(t for t, _ in episodes))
    info = {"codebase_version": "v3.0", "fps": FPS, "chunks_size": 1000,
            "data_path": "data/chunk-{chunk_index:03d}/file-{file_index:03d}.parquet",
            "video_path": "videos/{video_key}/chunk-{chunk_index:03d}/file-{file_index:03d}.mp4",
            "features": features(keys, "video")}
    (root / "meta/episodes/chunk-000").mkdir(parents=True)
    (root / "meta/info.json").write_text(json.dumps(info))
    pd.DataFrame({"task_index": range(len(texts))}, index=pd.Index(texts, name="task")) \
        .to_parquet(root / "meta/tasks.parquet")
    rows, data, start = [], [], 0
    containers = {}
    for i, (text, episode) in enumerate(episodes):
        n = len(episode)
        row = {"episode_index": i, "tasks": [text], "length": n, "data/chunk_index": 0,
               "data/file_index": 0, "dataset_from_index": start, "dataset_to_index": start + n}
        for key in ("agentview_rgb", "eye_in_hand_rgb"):
            name = keys[key]
            path = root / f"videos/{name}/chunk-000/file-000.mp4"
            if name not in containers:
                path.parent.mkdir(parents=True, exist_ok=True)
                containers[name] = av.open(str(path), "w")
                stream = containers[name].add_stream("libx264", rate=FPS)
                stream.width = stream.height = SIZE
                stream.pix_fmt = "yuv420p"
            encode_mp4(path, episode.obs[key], start, containers[name])
            row.update({f"videos/{name}/chunk_index": 0, f"videos/{name}/file_index": 0,
                        f"videos/{name}/from_timestamp": start / FPS,
                        f"videos/{name}/to_timestamp": (start + n) / FPS})
        rows.append(row)
        data.append({keys["actions"]: list(episode.actions), keys["state"]: list(episode.obs["state"]),
                     "timestamp": list(np.arange(n) / FPS), "frame_index": list(range(n)),
                     "episode_index": [i] * n, "index": list(range(start, start + n)),
                     "task_index": [texts.index(text)] * n})
        start += n
    for container in containers.values():
        for packet in container.streams.video[0].encode(None):
            container.mux(packet)
        container.close()
    table = pa.table({k: pa.array([v for d in data for v in d[k]],
                                  pa.list_(pa.float32()) if k in (keys["actions"], keys["state"])
                                  else (pa.float32() if k == "timestamp" else pa.int64()))
                      for k in data[0]})
    (root / "data/chunk-000").mkdir(parents=True)
    pq.write_table(table, root / "data/chunk-000/file-000.parquet", row_group_size=7)
    pq.write_table(pa.Table.from_pylist(rows), root / "meta/episodes/chunk-000/file-000.parquet")
    return root


def by_task(episodes: list[Episode]) -> list[tuple[str, Episode]]:
    """Episodes 0-2 of `lift` (its instruction in the dataset's own case and period), 3-5 of push."""
    return [(TASKS["lift"], e) for e in episodes[:3]] + [(TASKS["push"], e) for e in episodes[3:]]


def assert_same_vectors(read: list[Episode], written: list[Episode]) -> None:
    assert [len(e) for e in read] == [len(e) for e in written]
    for a, b in zip(read, written):
        assert a.actions.dtype == np.float32 and np.array_equal(a.actions, b.actions)
        assert np.array_equal(a.obs["state"], b.obs["state"])


def assert_close_images(read: list[Episode], written: list[Episode], tolerance: float) -> None:
    for a, b in zip(read, written):
        for key in ("agentview_rgb", "eye_in_hand_rgb"):
            assert a.obs[key].shape == b.obs[key].shape and a.obs[key].dtype == np.uint8
            assert np.abs(a.obs[key].astype(int) - b.obs[key]).mean() <= tolerance, key


def cached_files(tmp_path: Path) -> list[Path]:
    return sorted((tmp_path / "cache").rglob("*.hdf5"))


def test_v21_video_folder_trains_by_task_text(tmp_path):
    episodes = make_episodes((5, 6, 4, 7, 3, 5))
    folder = write_v2(tmp_path / "v21", by_task(episodes))
    splits = user_demos(config(tmp_path, folder, cameras=True), SUITE, "lift")
    assert_same_vectors(splits["demo"] + splits["heldout"], episodes[:3])  # the last held out
    assert_close_images(splits["demo"] + splits["heldout"], episodes[:3], tolerance=3)
    push = user_demos(config(tmp_path, folder), SUITE, "push")
    assert_same_vectors(push["demo"] + push["heldout"], episodes[3:])
    assert set(push["demo"][0].obs) == {"state"}  # cameras off: no image is decoded
    assert len(cached_files(tmp_path)) == 4  # cached like generated demos: read once


def test_images_in_parquet_folder_with_pi_keys_rotated(tmp_path):
    """physical-intelligence/libero's layout: v2.0, PNG images in the parquet files, the keys
    image, wrist_image, state and actions, images turned 180 degrees."""
    episodes = make_episodes((4, 5, 3, 4, 6, 2))
    folder = write_v2(tmp_path / "pi", by_task(episodes), "v2.0", "image", PI_KEYS)
    cfg = config(tmp_path, folder, cameras=True, lerobot_rotate_images=True)
    splits = user_demos(cfg, SUITE, "push")
    read = splits["demo"] + splits["heldout"]
    assert_same_vectors(read, episodes[3:])
    for a, b in zip(read, episodes[3:]):  # PNG is lossless: exact, once turned back
        assert np.array_equal(a.obs["agentview_rgb"], b.obs["agentview_rgb"][:, ::-1, ::-1])
        assert np.array_equal(a.obs["eye_in_hand_rgb"], b.obs["eye_in_hand_rgb"][:, ::-1, ::-1])


def test_v30_video_folder_with_many_episodes_per_file(tmp_path):
    episodes = make_episodes((5, 6, 4, 7, 3, 5))
    folder = write_v3(tmp_path / "v30", by_task(episodes))
    cfg = config(tmp_path, folder, cameras=True, demos_per_task=1)
    splits = user_demos(cfg, SUITE, "push")  # episodes 3-5 sit mid-file, from 1.5 s on
    assert_same_vectors(splits["demo"] + splits["heldout"], [episodes[3], episodes[5]])
    assert_close_images(splits["demo"] + splits["heldout"], [episodes[3], episodes[5]], 3)


def test_export_then_read_back_gives_the_same_actions_states_and_instructions(tmp_path):
    """The `lerobot-export` command's v3.0 folder (of a Meta-World benchmark whose demos come
    from another dataset, here a v2.1 folder), read back as demos_dir."""
    from harness.data.lerobot.layout import open_layout
    from harness.run.lerobot_export import export
    from suites import get_suite

    metaworld = get_suite("metaworld")
    episodes = make_episodes((5, 6, 4, 7, 3, 5), action_dim=4, state_dim=39)
    source = write_v2(tmp_path / "source", by_task(episodes), cameras=None)
    out = tmp_path / "exported"
    bench = ["BENCH=mw-quick", "foundation_tasks=reach-v3", "stream_tasks=push-v3",
             "demos_per_task=2", "heldout_demos_per_task=1"]
    written = export(bench + [f"out={out}", f"demos_dir={source}", "fps=10",
                              f"cache_dir={tmp_path / 'c1'}", "lerobot_tasks=reach-v3:0,push-v3:1",
                              "lerobot_keys=state:observation.state"])
    assert (written.episodes, written.frames, written.tasks) == (6, 30, 2)
    layout = open_layout(out)
    assert layout.version == "v3.0" and layout.fps == 10
    instructions = [metaworld.instruction(t) for t in ("reach-v3", "push-v3")]
    assert list(layout.tasks.values()) == instructions
    info = json.loads((out / "meta/info.json").read_text())
    assert info["total_frames"] == 30 and info["video_path"] is None
    stats = json.loads((out / "meta/stats.json").read_text())
    assert stats["action"]["count"] == [30] and len(stats["observation.state"]["q99"]) == 39
    assert stats["action"]["max"] == episodes_max([e.actions for e in episodes])
    tasks = pd.read_parquet(out / "meta/tasks.parquet")  # as LeRobot reads it: text -> index
    assert tasks.loc[instructions[1]].task_index == 1
    from harness.config.benchmark import resolve

    cfg = resolve(bench + [f"demos_dir={out}", f"cache_dir={tmp_path / 'c2'}"])
    for task, expected in (("reach-v3", episodes[:3]), ("push-v3", episodes[3:])):
        splits = user_demos(cfg, metaworld, task)
        assert_same_vectors(splits["demo"] + splits["heldout"], expected)


def episodes_max(arrays: list[np.ndarray]) -> list[float]:
    return np.concatenate(arrays).max(0).astype(np.float64).tolist()


@pytest.mark.parametrize("images", ["png", "video"])
def test_writer_round_trips_cameras(tmp_path, images):
    episodes = make_episodes((5, 6, 4, 7, 3, 5))
    write_dataset(tmp_path / "ds", [(TASKS["lift"], episodes[:3]), (TASKS["push"], episodes[3:])],
                  fps=FPS, images=images)
    feature = json.loads((tmp_path / "ds/meta/info.json").read_text())["features"]
    assert feature["observation.images.image"]["dtype"] == ("image" if images == "png" else "video")
    splits = user_demos(config(tmp_path, tmp_path / "ds", cameras=True), SUITE, "push")
    read = splits["demo"] + splits["heldout"]
    assert_same_vectors(read, episodes[3:])
    assert_close_images(read, episodes[3:], tolerance=0 if images == "png" else 4)


def test_key_overrides_and_explicit_task_mapping(tmp_path):
    episodes = make_episodes((5, 6, 4, 7, 3, 5))
    keys = {"actions": "act", "state": "proprio", "agentview_rgb": "front",
            "eye_in_hand_rgb": "hand"}
    folder = write_v2(tmp_path / "own", [("teleop A", e) for e in episodes[:3]]
                      + [("teleop B", e) for e in episodes[3:]], cameras="image", keys=keys)
    cfg = config(tmp_path, folder, cameras=True,
                 lerobot_keys="actions:act,state:proprio,agentview_rgb:front,eye_in_hand_rgb:hand",
                 lerobot_tasks="lift:1,push:teleop A")
    lift = user_demos(cfg, SUITE, "lift")
    assert_same_vectors(lift["demo"] + lift["heldout"], episodes[3:])
    with pytest.raises(RetainError, match="missing key for actions: none of action, actions"):
        user_demos(config(tmp_path, folder, lerobot_tasks="lift:1"), SUITE, "lift")
    with pytest.raises(RetainError, match="unknown key 'wrist' in lerobot_keys"):
        user_demos(config(tmp_path, folder, lerobot_keys="wrist:hand"), SUITE, "lift")
    with pytest.raises(RetainError, match="malformed lerobot_keys entry 'state': expected KEY:"):
        user_demos(config(tmp_path, folder, lerobot_keys="state"), SUITE, "lift")
    with pytest.raises(RetainError, match="lerobot_tasks: unknown toy task 'lfit'; valid: lift, "
                                          "push"):
        user_demos(config(tmp_path, folder, lerobot_keys="actions:act,state:proprio",
                          lerobot_tasks="lfit:1"), SUITE, "lift")


def one_line_naming(err, path: Path) -> str:
    text = str(err.value)
    assert "\n" not in text and str(path) in text, text
    return text


def test_missing_info_json_and_unknown_version(tmp_path):
    folder = write_v2(tmp_path / "ds", by_task(make_episodes((3, 3, 3, 3, 3, 3))), cameras=None)
    info = folder / "meta/info.json"
    saved = info.read_text()
    info.unlink()
    with pytest.raises(RetainError, match="missing; expected a LeRobotDataset's meta/info.json") as err:
        user_demos(config(tmp_path, folder), SUITE, "lift")
    one_line_naming(err, info)
    info.write_text(saved.replace('"v2.1"', '"v1.6"'))
    with pytest.raises(RetainError, match="unknown codebase_version 'v1.6'; expected one of v2.0, "
                                          "v2.1, v3.0") as err:
        user_demos(config(tmp_path, folder), SUITE, "lift")
    one_line_naming(err, info)
    assert cached_files(tmp_path) == []


def test_missing_key_and_wrong_width(tmp_path):
    folder = write_v2(tmp_path / "ds", by_task(make_episodes((3, 3, 3, 3, 3, 3))), cameras=None)
    with pytest.raises(RetainError, match="missing key for agentview_rgb: none of") as err:
        user_demos(config(tmp_path, folder, cameras=True), SUITE, "lift")
    one_line_naming(err, folder / "meta/info.json")
    with pytest.raises(RetainError, match=r"has 8 values; suite 'libero' expects 65 \(LIBERO's "
                                          r"community sets .* use suite=libero-proprio\)") as err:
        user_demos(config(tmp_path, folder), TableSuite("libero", state_dim=65), "lift")
    one_line_naming(err, folder / "meta/info.json")
    data = folder / "data/chunk-000/episode_000001.parquet"  # info.json promises it; it lacks it
    pq.write_table(pq.read_table(data).drop_columns(["observation.state"]), data)
    with pytest.raises(RetainError, match="missing key 'observation.state'") as err:
        user_demos(config(tmp_path, folder), SUITE, "lift")
    one_line_naming(err, data)
    assert cached_files(tmp_path) == []


def test_task_with_no_episodes(tmp_path):
    episodes = make_episodes((3, 3, 3))
    folder = write_v2(tmp_path / "ds", [(TASKS["lift"], e) for e in episodes], cameras=None)
    with pytest.raises(RetainError, match="no episodes of task 'push' \\('push the blue block to "
                                          "the goal'\\); its tasks: 'Lift the red cube.'") as err:
        user_demos(config(tmp_path, folder), SUITE, "push")
    one_line_naming(err, folder / "meta/episodes.jsonl")
    with pytest.raises(RetainError, match="no task_index 7") as err:
        user_demos(config(tmp_path, folder, lerobot_tasks="push:7"), SUITE, "push")
    one_line_naming(err, folder / "meta/tasks.jsonl")


def test_corrupt_video_caches_nothing(tmp_path):
    episodes = make_episodes((5, 6, 4, 7, 3, 5))
    folder = write_v3(tmp_path / "ds", by_task(episodes))
    video = folder / "videos/observation.images.wrist_image/chunk-000/file-000.mp4"
    raw = video.read_bytes()
    video.unlink()
    encode_mp4(video, episodes[0].obs["eye_in_hand_rgb"])  # episode 0's frames only
    with pytest.raises(RetainError, match="holds 0 frames from 1.5000 s; expected 7 at 10 fps; "
                                          "expected episode 3's observation.images.wrist_image "
                                          "frames") as err:
        user_demos(config(tmp_path, folder, cameras=True), SUITE, "push")
    one_line_naming(err, video)
    video.write_bytes(b"\x00" * 64 + raw[64:200])
    with pytest.raises(RetainError, match="not a readable video") as err:
        user_demos(config(tmp_path, folder, cameras=True), SUITE, "lift")
    one_line_naming(err, video)
    assert cached_files(tmp_path) == []  # the other camera and the train split read fine


def test_corrupt_png(tmp_path):
    folder = write_v2(tmp_path / "ds", by_task(make_episodes((3, 3, 3, 3, 3, 3))), "v2.0",
                      "image")
    data = folder / "data/chunk-000/episode_000002.parquet"
    table = pq.read_table(data)
    broken = pa.array([{"bytes": b"\x89PNG broken", "path": None}] * 3, table.schema.field(
        "observation.images.image").type)
    pq.write_table(table.set_column(table.schema.get_field_index("observation.images.image"),
                                    "observation.images.image", broken), data)
    with pytest.raises(RetainError, match="column 'observation.images.image' row 0: not a "
                                          "readable PNG") as err:
        user_demos(config(tmp_path, folder, cameras=True), SUITE, "lift")
    one_line_naming(err, data)


@pytest.mark.parametrize("version", ["v2.1", "v3.0"])
def test_frames_that_disagree_with_the_episode_index(tmp_path, version):
    episodes = make_episodes((5, 6, 4, 7, 3, 5))
    folder = (write_v3 if version == "v3.0" else write_v2)(tmp_path / "ds", by_task(episodes))
    if version == "v3.0":
        data = folder / "data/chunk-000/file-000.parquet"
        table = pq.read_table(data)
        episode = table.column("episode_index").to_numpy().copy()
        episode[6] = 0  # episode 1's second frame labelled episode 0
        table = table.set_column(table.schema.get_field_index("episode_index"), "episode_index",
                                 pa.array(episode))
        expected = "holds 6 frames of episode 0; the episode index says 5"
    else:
        data = folder / "data/chunk-000/episode_000001.parquet"
        table = pq.read_table(data).slice(0, 5)  # a frame short
        expected = "holds 5 frames of episode 1; the episode index says 6"
    pq.write_table(table, data)
    with pytest.raises(RetainError, match=expected) as err:
        user_demos(config(tmp_path, folder, cameras=True), SUITE, "lift")
    one_line_naming(err, data)
    assert cached_files(tmp_path) == []


def test_export_refuses_an_existing_folder_and_bad_settings(tmp_path):
    from harness.run.lerobot_export import export

    (tmp_path / "there").mkdir()
    with pytest.raises(RetainError, match="already exists; expected a new folder"):
        export(["BENCH=mw-quick", f"out={tmp_path / 'there'}"])
    with pytest.raises(RetainError, match="needs out=FOLDER"):
        export(["BENCH=mw-quick"])
    with pytest.raises(RetainError, match="unknown images='gif'; valid: video, png"):
        export(["BENCH=mw-quick", f"out={tmp_path / 'new'}", "images=gif"])
