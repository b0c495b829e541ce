"""Suite -> training data: every task's demos (cached), chunked, with its instruction embedded
(the pooled sentence embedding, and the MiniLM token ids for policies that read tokens)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from harness.common.errors import RetainError
from harness.config.benchmark import BenchConfig
from harness.data.datasets import TrainingData, chunk_episodes
from harness.data.demos import (
    DemoSpec,
    Episode,
    cached_demo_path,
    load_or_generate,
    read_demo_file,
    write_demo_file,
)
from policies.text_encoder import embed_instructions, tokenize_instructions
from suites import Suite, get_suite
from suites.render import check_suite_renders


@dataclass
class BenchmarkData:
    train: dict[str, TrainingData]  # task -> training samples
    heldout: dict[str, TrainingData]  # task -> held-out samples (the held-out loss ratio)
    # task -> {"instruction": [384] embedding, "instruction_tokens": [L] token ids}
    instructions: dict[str, dict[str, np.ndarray]]
    # task -> training demos it has: demos_per_task, or fewer where demos_dir holds fewer
    demos_used: dict[str, int] = field(default_factory=dict)

    def short_of_demos(self, wanted: int) -> dict[str, int]:
        """The tasks that train on fewer than `wanted` (demos_per_task) demos, and how many."""
        return {t: n for t, n in self.demos_used.items() if n < wanted}

    def combined(self, tasks: list[str]) -> TrainingData:
        """The training samples of several tasks together: the foundation's, or a stage's."""
        return TrainingData.concat([self.train[t] for t in tasks])


def demo_spec(cfg: BenchConfig, suite: Suite, task: str, split: str) -> DemoSpec:
    if cfg.cameras:  # at plan time: every key needs its demos' spec
        try:
            check_suite_renders(suite, cfg.render)
        except ValueError as exc:
            raise RetainError(str(exc)) from None
    n = cfg.demos_per_task if split == "demo" else cfg.heldout_demos_per_task
    return DemoSpec(suite=suite.name, suite_version=suite.version(task), task=task, split=split,
                    num_demos=n, max_episode_steps=suite.step_limit(task, cfg.max_episode_steps),
                    cameras=cfg.cameras, image_size=cfg.image_size,
                    source=user_file(cfg, suite, task) if cfg.demos_dir else "",
                    render=cfg.render if cfg.cameras else "faithful")


@dataclass(frozen=True)
class DemoJob:
    """One missing demo file, made in a worker process (names, not objects: it is pickled)."""

    suite: str
    spec: DemoSpec
    cache_dir: str

    @property
    def label(self) -> str:
        return f"demos {self.spec.task} ({self.spec.split})"


def missing_demo_jobs(cfg: BenchConfig, suite: Suite) -> list[DemoJob]:
    """The demo files the expert still has to make (none where demos come from demos_dir)."""
    if cfg.demos_dir:
        return []
    specs = [demo_spec(cfg, suite, task, split) for task in cfg.all_tasks()
             for split in ("demo", "heldout")]
    return [DemoJob(suite.name, spec, cfg.cache_dir) for spec in specs
            if not cached_demo_path(Path(cfg.cache_dir), spec).exists()]


def make_demo_file(job: DemoJob) -> int:
    """Generate and cache one demo file; its episodes are seeded by their keys alone, so the
    file is the same whichever process makes it and however many run at once."""
    episodes = load_or_generate(get_suite(job.suite), job.spec, Path(job.cache_dir), progress=False)
    return len(episodes)


def prepare_data(cfg: BenchConfig, suite: Suite) -> BenchmarkData:
    tasks = cfg.all_tasks()
    cache = Path(cfg.cache_dir)
    if cfg.demos_dir:  # every task's file found before any long work
        for task in tasks:
            user_file(cfg, suite, task)
    texts = [suite.instruction(t) for t in tasks]
    embeddings = embed_instructions(texts, cache / "instructions")
    token_ids = tokenize_instructions(texts, cache / "instructions")
    token_ids = token_ids[:, :max(1, int((token_ids != 0).sum(1).max()))]  # no all-padding column
    data = BenchmarkData({}, {}, {})
    for index, (task, embedding, tokens) in enumerate(zip(tasks, embeddings, token_ids)):
        # "instruction_id": the task's index in cfg.all_tasks(), which orders the instruction
        # texts a policy that tokenizes them itself is given (harness/protocol/foundation.py)
        data.instructions[task] = {"instruction": embedding, "instruction_tokens": tokens,
                                   "instruction_id": np.int64(index)}
        splits = task_demos(cfg, suite, task)
        data.demos_used[task] = len(splits["demo"])
        data.train[task] = chunk_episodes(splits["demo"], task, embedding, cfg.chunk_size, tokens,
                                          index)
        data.heldout[task] = chunk_episodes(splits["heldout"], task, embedding, cfg.chunk_size,
                                            tokens, index)
    return data


def task_demos(cfg: BenchConfig, suite: Suite, task: str) -> dict[str, list[Episode]]:
    """A task's "demo" and "heldout" episodes: the user's (demos_dir) or the expert's, cached."""
    if cfg.demos_dir:
        return user_demos(cfg, suite, task)
    return {split: load_or_generate(suite, demo_spec(cfg, suite, task, split),
                                    Path(cfg.cache_dir), cfg.progress)
            for split in ("demo", "heldout")}


def user_file(cfg: BenchConfig, suite: Suite, task: str) -> str:
    """The user's LIBERO file for `task` in `demos_dir`, with its size and modification time,
    or a LeRobot dataset's state for the task (any suite; harness/data/lerobot): part of the
    demo-cache key, so a replaced file is read again."""
    from harness.data.lerobot.layout import is_dataset_folder

    if is_dataset_folder(cfg.demos_dir):
        from harness.data.lerobot.reader import source

        return source(cfg, suite, task)
    if not suite.name.startswith("libero"):
        raise RetainError(f"demos_dir reads LIBERO dataset files or a LeRobot dataset folder; "
                          f"{cfg.demos_dir} is neither, and suite {suite.name!r} makes its own")
    from suites.libero.files import task_file

    try:
        path = task_file(cfg.demos_dir, task).resolve()
    except ValueError as err:
        raise RetainError(str(err)) from None
    stat = path.stat()
    return f"{path}:{stat.st_size}:{stat.st_mtime_ns}"


def user_demos(cfg: BenchConfig, suite: Suite, task: str) -> dict[str, list[Episode]]:
    """A task's demos from the user's LIBERO dataset files (`demos_dir`, matched by task name)
    or LeRobot dataset folder (matched by instruction): the last `heldout_demos_per_task` are
    held out, the first `demos_per_task` of the rest train. Rebuilding the state from a LIBERO
    file's sim states, or decoding a dataset's videos, takes seconds, so the result is cached
    like generated demos (keyed by the files' paths, sizes and times)."""
    from harness.data.lerobot.layout import is_dataset_folder

    specs = {split: demo_spec(cfg, suite, task, split) for split in ("demo", "heldout")}
    paths = {split: Path(cfg.cache_dir) / "demos" / suite.name / spec.filename()
             for split, spec in specs.items()}
    if all(p.exists() for p in paths.values()):
        return {split: read_demo_file(paths[split], spec)[1] for split, spec in specs.items()}
    splits = (lerobot_demos(cfg, suite, task) if is_dataset_folder(cfg.demos_dir)
              else libero_file_demos(cfg, suite, task, specs["demo"].source))
    for split, spec in specs.items():
        write_demo_file(paths[split], splits[split], spec, suite.instruction(task))
    return splits


def short_demos_text(cfg: BenchConfig, short: dict[str, int]) -> str:
    """One line for the tasks that train on fewer demos than demos_per_task: what was used."""
    counts = sorted(set(short.values()))
    tasks = ", ".join(list(short)[:4]) + (f" and {len(short) - 4} more" if len(short) > 4 else "")
    return (f"demos_dir holds fewer demos than demos_per_task={cfg.demos_per_task} plus "
            f"heldout_demos_per_task={cfg.heldout_demos_per_task} for {len(short)} task(s) "
            f"({tasks}): they train on {'/'.join(map(str, counts))} demo(s) each "
            "(recorded as demos_used in config.yaml and MLflow)")


def split_demos(items: list, cfg: BenchConfig, where, task: str) -> dict[str, list]:
    """The last `heldout_demos_per_task` are held out, the first `demos_per_task` of the rest
    train (all of the rest where there are fewer: `BenchmarkData.demos_used` records how many,
    and the run prints and records them)."""
    held = cfg.heldout_demos_per_task
    if len(items) <= held:
        raise RetainError(f"{where} holds {len(items)} demos of task {task!r}; it needs more than "
                          f"heldout_demos_per_task={held}")
    return {"demo": items[:len(items) - held][:cfg.demos_per_task],
            "heldout": items[len(items) - held:]}


def lerobot_demos(cfg: BenchConfig, suite: Suite, task: str) -> dict[str, list[Episode]]:
    """A task's demos from a LeRobot dataset folder: only the episodes used are decoded."""
    from harness.data.lerobot.reader import dataset, read_episodes, task_entries

    chosen = split_demos(task_entries(cfg, suite, task), cfg, dataset(cfg).episodes_file, task)
    return {split: read_episodes(cfg, suite, entries) for split, entries in chosen.items()}


def libero_file_demos(cfg: BenchConfig, suite: Suite, task: str,
                      source: str) -> dict[str, list[Episode]]:
    """A task's demos from its LIBERO HDF5 file (`source`, as `user_file` gives it)."""
    from suites.libero.files import read_libero_file

    path = Path(source.rsplit(":", 2)[0])
    env = suite.make_env(task)
    try:
        episodes = read_libero_file(path, env, cfg.cameras, cfg.image_size).episodes
    except ValueError as err:
        raise RetainError(str(err)) from None
    finally:
        env.close()
    return split_demos([Episode(e["actions"], e["obs"], seed=-1) for e in episodes], cfg, path,
                       task)
