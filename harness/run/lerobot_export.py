"""`python -m harness lerobot-export BENCH=libero-quick out=exports/libero-quick [images=png]`
(`make lerobot-export`): a benchmark's demos as a LeRobotDataset v3.0 folder.

The demos are the ones a run of the same settings trains on: the expert's, generated and cached
as `harness bench` makes them (one worker process per core), or the user's `demos_dir`. Each
task's training demos come first, then its held-out demos, so the folder read back as
`demos_dir` with the same `demos_per_task` and `heldout_demos_per_task` gives the same split.
With `cameras=true` the images are AV1 videos (`images=png`: lossless PNG in the parquet files).
"""

from __future__ import annotations

import time
from pathlib import Path

from harness.common.errors import RetainError
from harness.config.benchmark import parse_overrides, resolve
from harness.data.lerobot.writer import IMAGE_MODES, Written, write_dataset
from suites import UnknownName, get_suite

CONTROL_FPS = {"libero": 20, "libero-proprio": 20, "libero-lerobot": 20, "bimanual": 20,
               "metaworld": 80, "metaworld-lerobot": 80}
"""Steps per second of each suite's control (LIBERO and robosuite at 20 Hz, Meta-World's
MuJoCo at 0.0125 s a step), the dataset's fps."""
ROBOT_TYPES = {"libero": "panda", "libero-proprio": "panda", "libero-lerobot": "panda",
               "bimanual": "bimanual_panda", "metaworld": "sawyer", "metaworld-lerobot": "sawyer"}
OWN_KEYS = ("out", "images", "fps")


def split_args(args: list[str]) -> tuple[dict[str, str], list[str]]:
    """(this command's own settings, the benchmark's overrides)."""
    own, rest = {}, []
    for arg in args:
        key = arg.partition("=")[0]
        if key in OWN_KEYS:
            own.update(parse_overrides([arg]))
        else:
            rest.append(arg)
    return own, rest


def export(args: list[str]) -> Written:
    from harness.data.prepare import task_demos
    from harness.run.execute import make_missing_demos

    own, rest = split_args(args)
    if not own.get("out"):
        raise RetainError("lerobot-export needs out=FOLDER, the new dataset's folder, e.g. "
                          "out=exports/libero-quick")
    images = own.get("images", "video")
    if images not in IMAGE_MODES:
        raise RetainError(f"unknown images={images!r}; valid: {', '.join(IMAGE_MODES)}")
    cfg = resolve(rest)
    try:
        suite = get_suite(cfg.suite)
        tasks = [suite.check_task(t) for t in cfg.all_tasks()]
    except UnknownName as err:
        raise RetainError(str(err)) from None
    fps = own.get("fps") or CONTROL_FPS.get(suite.name)
    try:
        fps = float(fps)
    except (TypeError, ValueError):
        fps = 0.0
    if fps <= 0:
        raise RetainError(f"bad value {own.get('fps')!r} for fps: expected the steps per second "
                          f"of suite {suite.name!r}'s control, a positive number")
    out = Path(own["out"])
    if out.exists():
        raise RetainError(f"{out} already exists; expected a new folder for the dataset")
    make_missing_demos(cfg, suite)

    def demos():
        for task in tasks:
            splits = task_demos(cfg, suite, task)
            yield suite.instruction(task), splits["demo"] + splits["heldout"]

    return write_dataset(out, demos(), fps, ROBOT_TYPES.get(suite.name, ""), images,
                         cfg.lerobot_rotate_images)


def main(args: list[str]) -> int:
    start = time.time()
    written = export(args)
    print(f"[retain] {written.path}: LeRobotDataset v3.0, {written.episodes} episodes, "
          f"{written.frames} frames, {written.tasks} tasks"
          + (f", cameras {', '.join(written.cameras)}" if written.cameras else "")
          + f"; {written.files} files, {written.bytes / 2**20:.1f} MiB, "
          f"{time.time() - start:.0f}s", flush=True)
    return 0
