"""Loads a LeRobot v3.0 folder the way LeRobot 0.4's LeRobotDataset loads a local one (load_info,
load_tasks with pandas, load_episodes, load_nested_dataset with get_hf_features_from_features'
features, __getitem__'s episode and task lookups, video frames at from_timestamp + timestamp
within its 1e-4 s tolerance), as a check of `make lerobot-export`'s output. LeRobot does not
install beside Retain's pins, so this runs in a separate environment:

    python3 -m venv /tmp/dsvenv && /tmp/dsvenv/bin/pip install "datasets>=4,<5" pandas pillow av
    /tmp/dsvenv/bin/python docs/lerobot_load_check.py exports/libero-quick
"""
import json
import sys
from pathlib import Path

import av
import datasets
import numpy as np
import pandas as pd

root = Path(sys.argv[1])
info = json.loads((root / "meta/info.json").read_text())
assert info["codebase_version"] == "v3.0"
for ft in info["features"].values():
    ft["shape"] = tuple(ft["shape"])
hf = {}  # LeRobot's get_hf_features_from_features
for key, ft in info["features"].items():
    if ft["dtype"] == "video":
        continue
    elif ft["dtype"] == "image":
        hf[key] = datasets.Image()
    elif ft["shape"] == (1,):
        hf[key] = datasets.Value(dtype=ft["dtype"])
    elif len(ft["shape"]) == 1:
        hf[key] = datasets.Sequence(length=ft["shape"][0], feature=datasets.Value(dtype=ft["dtype"]))
features = datasets.Features(hf)
data = datasets.concatenate_datasets([datasets.Dataset.from_parquet(str(p), features=features)
                                      for p in sorted((root / "data").glob("*/*.parquet"))])
tasks = pd.read_parquet(root / "meta/tasks.parquet")
episodes = datasets.concatenate_datasets([datasets.Dataset.from_parquet(str(p)) for p in
                                          sorted((root / "meta/episodes").glob("*/*.parquet"))])
episodes = episodes.select_columns([k for k in episodes.features if not k.startswith("stats/")])
stats = json.loads((root / "meta/stats.json").read_text())
assert len(data) == info["total_frames"] and len(episodes) == info["total_episodes"]
assert len(tasks) == info["total_tasks"]
videos = [k for k, f in info["features"].items() if f["dtype"] == "video"]
data = data.with_format("numpy")
checked = 0
for idx in range(0, len(data), max(1, len(data) // 50)):
    item = data[idx]
    ep = episodes[int(item["episode_index"])]  # LeRobot indexes its episodes by position
    assert ep["episode_index"] == item["episode_index"]
    assert ep["dataset_from_index"] <= item["index"] < ep["dataset_to_index"]
    task = tasks.iloc[int(item["task_index"])].name  # as __getitem__ names the task
    assert task in ep["tasks"], (task, ep["tasks"])
    for key in videos:
        path = root / info["video_path"].format(video_key=key,
                                                chunk_index=ep[f"videos/{key}/chunk_index"],
                                                file_index=ep[f"videos/{key}/file_index"])
        ts = ep[f"videos/{key}/from_timestamp"] + float(item["timestamp"])
        with av.open(str(path)) as container:
            stream = container.streams.video[0]
            container.seek(int(ts / stream.time_base), stream=stream)
            gap = min(abs(f.time - ts) for f in container.decode(stream) if f.time <= ts + 0.2)
        assert gap < 1e-4, (key, ts, gap)
    checked += 1
for key in info["features"]:
    for name in ("min", "max", "mean", "std", "count"):
        np.asarray(stats[key][name])
print(f"{root}: loads as LeRobot 0.4 loads it: {len(data)} frames, {len(episodes)} episodes, "
      f"{len(tasks)} tasks, {checked} frames looked up"
      + (f", video frames at their timestamps for {', '.join(videos)}" if videos else ""))
