"""The LeRobot reader's figures; printed, never asserted (a busy machine gives slow figures).

    python -m harness.perf.lerobot read [--dataset DIR] [--episodes 20] [--length 150] [--size 128]
        frames/s of the reader on a video dataset (a synthetic one written by the writer unless
        --dataset names one) against plain PyAV decoding of the same mp4 files, both to RGB
        arrays kept in memory, with the same decoder settings.
    python -m harness.perf.lerobot roundtrip BENCH=libero-quick PROFILE=tiny [images=png] [...]
        a benchmark's training data from its cached HDF5 demos, then from the same demos
        exported as a LeRobot dataset and read back as demos_dir: equal bit for bit or not,
        per task, split and key (exit status 1 if not).
"""

from __future__ import annotations

import argparse
import copy
import shutil
import statistics
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from harness.common.errors import USER_ERRORS, RetainError

REPEATS = 5


def synthetic_video_dataset(folder: Path, episodes: int, length: int, size: int) -> Path:
    """Two cameras of smooth moving patterns (rendered scenes compress alike), 7-D actions."""
    from harness.data.demos import Episode
    from harness.data.lerobot.writer import write_dataset

    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:size, 0:size].astype(np.float32) / size

    def frames(phase: float) -> np.ndarray:
        t = np.arange(length, dtype=np.float32)[:, None, None] / length + phase
        r = 0.5 + 0.5 * np.sin(6 * xx + 4 * t)
        g = 0.5 + 0.5 * np.cos(5 * yy - 3 * t)
        b = ((xx - 0.5 - 0.3 * np.sin(2 * np.pi * t)) ** 2 + (yy - 0.5) ** 2 < 0.02)
        return (np.stack([r, g, np.broadcast_to(b, r.shape)], -1) * 255).astype(np.uint8)

    demos = [Episode(rng.uniform(-1, 1, (length, 7)).astype(np.float32),
                     {"state": rng.normal(size=(length, 8)).astype(np.float32),
                      "agentview_rgb": frames(i / episodes),
                      "eye_in_hand_rgb": frames(0.5 + i / episodes)[:, ::-1].copy()}, seed=i)
             for i in range(episodes)]
    out = folder / "synthetic"
    write_dataset(out, [("move the pattern", demos)], fps=20)
    return out


def bench_read(dataset: Path) -> None:
    import av

    from harness.data.lerobot.layout import open_layout
    from harness.data.lerobot.reader import CONVENTIONS, read_entries

    layout = open_layout(dataset)
    videos = [k for k, f in layout.features.items() if f["dtype"] == "video"]
    if not videos:
        raise RetainError(f"{layout.info_file}: no video features; expected a video dataset")
    keys = {k: next(c for c in CONVENTIONS[k] if c in layout.features) for k in ("actions", "state")}
    keys.update({k: k for k in videos})
    size = layout.camera_shape(videos[0])[0]
    entries = list(layout.episodes)
    files = sorted({e.videos[k].path for e in entries for k in videos})
    frames = sum(e.length for e in entries) * len(videos)

    def reader() -> None:
        read_entries(layout, keys, entries, size)

    def plain() -> list[np.ndarray]:
        kept = []  # as the reader keeps its frames (fresh memory costs page faults)
        for path in files:
            with av.open(str(path)) as container:
                stream = container.streams.video[0]
                stream.thread_type = "AUTO"
                kept += [frame.to_ndarray(format="rgb24") for frame in container.decode(stream)]
        return kept

    times: dict[str, list[float]] = {"reader": [], "pyav": []}
    runs = [("reader", reader), ("pyav", plain)]
    for i in range(REPEATS):  # interleaved, each first in turn, so a busy spell slows both
        for name, run in runs[::-1] if i % 2 else runs:
            start = time.perf_counter()
            run()
            times[name].append(time.perf_counter() - start)
    codec = layout.features[videos[0]].get("info", {}).get("video.codec", "?")
    print(f"{dataset}: {len(entries)} episodes, {len(videos)} video keys, {frames} frames "
          f"({size}x{size}, {codec}) in {len(files)} mp4 files; median of {REPEATS}")
    rates = {name: frames / statistics.median(t) for name, t in times.items()}
    print(f"  reader (parquet + episode index + checks + decode): {rates['reader']:8.0f} frames/s")
    print(f"  plain PyAV decode of the same files, kept:          {rates['pyav']:8.0f} frames/s")
    print(f"  reader / plain PyAV: {rates['reader'] / rates['pyav']:.2f}")


def roundtrip(args: list[str]) -> bool:
    import torch

    from harness.config.benchmark import resolve
    from harness.data.prepare import prepare_data
    from harness.run.execute import make_missing_demos
    from harness.run.lerobot_export import export, split_args
    from suites import get_suite

    own, rest = split_args(args)
    if "out" in own:
        raise RetainError("roundtrip writes its own temporary dataset; leave out= unset")
    cfg = resolve(rest)
    if cfg.demos_dir:
        raise RetainError("roundtrip compares the expert's cached demos with their export; "
                          "leave demos_dir unset")
    suite = get_suite(cfg.suite)
    torch.set_num_threads(cfg.torch_threads)
    make_missing_demos(cfg, suite)
    start = time.perf_counter()
    direct = prepare_data(cfg, suite)
    t_direct = time.perf_counter() - start
    folder = Path(tempfile.mkdtemp(prefix="lerobot-roundtrip-"))
    try:
        start = time.perf_counter()
        written = export(args + [f"out={folder / 'dataset'}"])
        t_export = time.perf_counter() - start
        back = copy.deepcopy(cfg)
        back.demos_dir, back.cache_dir = str(written.path), str(folder / "cache")
        # the same instruction embeddings (MiniLM's last bits depend on the thread count): only
        # the demos are compared, and only the read-back demos are cached apart
        shutil.copytree(Path(cfg.cache_dir) / "instructions", folder / "cache/instructions")
        start = time.perf_counter()
        read = prepare_data(back, suite)
        t_read = time.perf_counter() - start
        print(f"{cfg.name}: {written.episodes} episodes, {written.frames} frames, "
              f"{written.bytes / 2**20:.1f} MiB as LeRobot v3.0; training data from the HDF5 "
              f"cache {t_direct:.1f}s, export {t_export:.1f}s, read back {t_read:.1f}s")
        same = True
        for split in ("train", "heldout"):
            for task in cfg.all_tasks():
                a, b = getattr(direct, split)[task], getattr(read, split)[task]
                parts = {f"obs/{k}": (a.obs[k], b.obs.get(k)) for k in a.obs}
                parts.update({"actions": (a.actions, b.actions),
                              "action_mask": (a.action_mask, b.action_mask),
                              "instruction": (a.instruction_table, b.instruction_table),
                              "instruction_tokens": (a.instruction_tokens, b.instruction_tokens)})
                verdicts = {name: _compare(x, y) for name, (x, y) in parts.items()}
                same &= all(v == "identical" for v in verdicts.values()) \
                    and set(a.obs) == set(b.obs)
                print(f"  {task} {split}: {len(a)} samples; "
                      + ", ".join(f"{k} {v}" for k, v in verdicts.items()))
        print(f"bit-identical training data: {'yes' if same else 'no'}")
        return same
    finally:
        shutil.rmtree(folder, ignore_errors=True)


def _compare(x, y) -> str:
    import torch

    if x is None or y is None:
        return "identical" if x is None and y is None else "missing"
    if x.shape != y.shape or x.dtype != y.dtype:
        return f"differs ({tuple(x.shape)} {x.dtype} vs {tuple(y.shape)} {y.dtype})"
    if torch.equal(x, y):
        return "identical"
    return f"differs (max |diff| {float((x.double() - y.double()).abs().max()):.3g})"


def main(argv: list[str]) -> int:
    what = argv[0] if argv else ""
    try:
        if what == "read":
            parser = argparse.ArgumentParser(prog="python -m harness.perf.lerobot read")
            parser.add_argument("--dataset", type=Path)
            parser.add_argument("--episodes", type=int, default=20)
            parser.add_argument("--length", type=int, default=150)
            parser.add_argument("--size", type=int, default=128)
            args = parser.parse_args(argv[1:])
            with tempfile.TemporaryDirectory(prefix="lerobot-read-") as tmp:
                dataset = args.dataset or synthetic_video_dataset(Path(tmp), args.episodes,
                                                                  args.length, args.size)
                bench_read(dataset)
            return 0
        if what == "roundtrip":
            return 0 if roundtrip(argv[1:]) else 1
    except USER_ERRORS as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print("usage: python -m harness.perf.lerobot {read [--dataset DIR] [--episodes N] "
          "[--length N] [--size N],roundtrip BENCH=... [KEY=VALUE ...]}", file=sys.stderr)
    return 2


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
