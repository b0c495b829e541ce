"""Recorded episodes drawn and encoded: the frames come from the states an evaluation kept
(recording.py), drawn on an env of their own with the chosen camera and size, captioned with the
instruction, the stage and the outcome, and encoded with PyAV.

The codec is H.264 (libx264, yuv420p, in MP4 with the index up front): the `av` wheel ships
libx264, and H.264 in MP4 is what every browser plays, Debian's Chromium included (the report's
browser test checks it). x264 is deterministic: the same states give the same bytes.
"""

from __future__ import annotations

import functools
import textwrap
from pathlib import Path

import av
import numpy as np
from PIL import Image, ImageDraw, ImageFont

from harness.common.atomic import atomic_path
from harness.evaluate.recording import VideoEntry, VideoSettings, write_index
from harness.evaluate.rollouts import TaskEvaluation
from suites import Suite
from suites.render import render_argument

GREEN, RED, WHITE, GREY = (80, 220, 100), (240, 80, 70), (255, 255, 255), (170, 170, 170)


def font_px(width: int) -> int:
    """The caption's text height: readable at 64 px, a line of about 30 characters."""
    return max(9, width // 18)


@functools.cache
def _font(size: int) -> ImageFont.FreeTypeFont:
    return ImageFont.load_default(size=size)


def caption(frame: np.ndarray, lines: list[tuple[str, tuple[int, int, int]]]) -> np.ndarray:
    """`frame` with a black bar below it holding `lines` (text, colour); even height and width,
    as yuv420p needs."""
    height, width = frame.shape[:2]
    font = _font(font_px(width))
    line_px = font_px(width) + 3
    bar = len(lines) * line_px + 4
    out = Image.new("RGB", (width + width % 2, height + bar + (height + bar) % 2))
    out.paste(Image.fromarray(frame), (0, 0))
    draw = ImageDraw.Draw(out)
    for i, (text, colour) in enumerate(lines):
        draw.text((3, height + 2 + i * line_px), text, fill=colour, font=font)
    return np.asarray(out)


def caption_lines(instruction: str, stage: int, step: int, steps: int, success: bool,
                  width: int) -> list[tuple[str, tuple[int, int, int]]]:
    """The instruction (wrapped to two lines), then the stage and the step, or at the episode's
    end its outcome in colour."""
    chars = max(12, int(width / (font_px(width) * 0.55)))  # a glyph is about 0.55 em wide
    wrapped = (textwrap.wrap(instruction, chars)[:2] + ["", ""])[:2]  # one bar height for all
    if step < steps:
        return [(line, WHITE) for line in wrapped] + [(f"stage {stage}, step {step}", GREY)]
    outcome = f"stage {stage}, " + ("success" if success else "failure")
    return [(line, WHITE) for line in wrapped] + [(outcome, GREEN if success else RED)]


def encode(frames: list[np.ndarray], path: Path, fps: int) -> None:
    """H.264 MP4, written atomically (a killed run never leaves half a video)."""
    height, width = frames[0].shape[:2]
    with atomic_path(path) as tmp:
        with av.open(str(tmp), "w", format="mp4", options={"movflags": "+faststart"}) as out:
            stream = out.add_stream("libx264", rate=fps)
            stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
            stream.options = {"crf": "23", "preset": "veryfast", "threads": "1"}
            for frame in frames:
                for packet in stream.encode(av.VideoFrame.from_ndarray(frame, format="rgb24")):
                    out.mux(packet)
            for packet in stream.encode():
                out.mux(packet)


def check_camera(suite: Suite, settings: VideoSettings) -> None:
    """Draw one frame of the first video task now, so that a camera the scene lacks is a
    one-line error before the run, not after its foundation is trained."""
    task = settings.tasks[0]
    env = suite.make_env(task, cameras=True, image_size=32, **render_argument(settings.render))
    try:
        env.reset(suite.episode_keys(task, "eval", 1)[0])
        env.render_state(env.view_state(), settings.camera, 32)
    finally:
        env.close()


class VideoWriter:
    """Turns a stage's recorded episodes into videos in `directory`, with an index per stage."""

    def __init__(self, suite: Suite, settings: VideoSettings, directory: Path, eval_episodes: int):
        self.suite, self.settings, self.directory = suite, settings, Path(directory)
        self.eval_episodes = eval_episodes

    def episodes_at(self, stage: int) -> frozenset[tuple[str, int]]:
        return self.settings.episodes_at(stage)

    def write(self, stage: int, trained_on: str, results: dict[str, TaskEvaluation]
              ) -> list[VideoEntry]:
        """Draw and encode every recorded episode of `results`; returns the index's entries."""
        entries = []
        for task, result in results.items():
            if not result.recordings:
                continue
            keys = self.suite.episode_keys(task, "eval", self.eval_episodes)
            env = self.suite.make_env(task, cameras=True, image_size=self.settings.size,
                                      **render_argument(self.settings.render))
            try:
                for key, states in sorted(result.recordings.items()):
                    index = keys.index(key)
                    entries.append(self._video(env, task, stage, trained_on, index,
                                               result.successes[index], states))
            finally:
                env.close()
        write_index(self.directory, stage, entries)
        return entries

    def _video(self, env, task: str, stage: int, trained_on: str, episode: int, success: bool,
               states: np.ndarray) -> VideoEntry:
        s, instruction = self.settings, self.suite.instruction(task)
        steps = len(states) - 1
        frames = [caption(env.render_state(state, s.camera, s.size),
                          caption_lines(instruction, stage, t, steps, success, s.size))
                  for t, state in enumerate(states)]
        frames += frames[-1:] * s.fps  # the outcome stays on screen for a second
        name = f"stage{stage}_{task}_ep{episode}.mp4"
        encode(frames, self.directory / name, s.fps)
        return VideoEntry(name, task, stage, trained_on, episode, bool(success), steps, instruction)
