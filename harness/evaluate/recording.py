"""Which evaluation episodes become videos, and where their files go.

Videos show forgetting: the same episode before fine-tuning, after the task's own stage and
after the last stage. So for every chosen task (`video_tasks`, default all), its first
`video_episodes` evaluation episodes are recorded at stage 0 and after the last stage, and a
stream task's also after its own stage. Recording keeps the simulator's state each step of the
ordinary evaluation (the episodes are unchanged); frames are drawn afterwards (videos.py).
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import asdict, dataclass
from pathlib import Path

from harness.common.atomic import write_text
from harness.config.benchmark import BenchConfig

INDEX = "stage{stage}.json"  # a stage's videos, listed in its run's videos/ folder
VIDEO_VERSION = 1  # bump when a video's frames change (the caption, the encoding): the cached
# stage-0 videos are then made anew


@dataclass(frozen=True)
class VideoSettings:
    tasks: tuple[str, ...]  # the tasks with videos, in the benchmark's order
    stages: tuple[tuple[str, ...], ...]  # the stream tasks of stages 1..k
    episodes: int  # per task: its first N evaluation episodes
    size: int  # pixels, square
    camera: str  # "" for the suite's own view of the workspace
    fps: int
    render: str = "faithful"  # how frames are drawn (suites/render.py), as the cameras are

    @classmethod
    def of(cls, cfg: BenchConfig) -> VideoSettings | None:
        """The run's settings, or None when videos are off."""
        if not cfg.videos:
            return None
        chosen = set(cfg.video_tasks or cfg.all_tasks())
        return cls(tuple(t for t in cfg.all_tasks() if t in chosen),
                   tuple(tuple(s) for s in cfg.stream_stages()), cfg.video_episodes,
                   cfg.video_size, cfg.video_camera, cfg.video_fps, cfg.render)

    def episodes_at(self, stage: int) -> frozenset[tuple[str, int]]:
        """(task, episode index) of the episodes recorded after `stage`."""
        last = len(self.stages)
        if stage in (0, last):
            tasks = self.tasks
        else:
            tasks = tuple(t for t in self.tasks if t in self.stages[stage - 1])
        return frozenset((t, i) for t in tasks for i in range(self.episodes))

    def key(self) -> str:
        """What a stage-0 video depends on besides the foundation and its evaluation."""
        parts = [VIDEO_VERSION, sorted(self.tasks), self.episodes, self.size, self.camera,
                 self.fps]
        if self.render != "faithful":  # frames drawn fast (with cameras off, not in the
            parts.append(self.render)  # foundation's key) are never a faithful video's
        blob = json.dumps(parts)
        return hashlib.sha256(blob.encode()).hexdigest()[:12]


@dataclass(frozen=True)
class VideoEntry:
    """One video file and the episode it shows: a row of the report's grid."""

    file: str  # relative to the videos/ folder
    task: str
    stage: int
    trained_on: str  # the stage's name ("foundation" at stage 0)
    episode: int  # index among the task's evaluation episodes
    success: bool
    steps: int
    instruction: str


def write_index(directory: Path, stage: int, entries: list[VideoEntry]) -> Path:
    path = directory / INDEX.format(stage=stage)
    write_text(path, json.dumps([asdict(e) for e in entries], indent=1) + "\n")
    return path


def read_indexes(directory: Path) -> list[VideoEntry]:
    """Every stage's entries in a videos/ folder (none when it has no index)."""
    entries = []
    for path in sorted(Path(directory).glob(INDEX.format(stage="*"))):
        entries += [VideoEntry(**row) for row in json.loads(path.read_text())]
    return entries
