"""Progress of long work: foundation pre-training, a stage's steps, an evaluation's episodes.

On a terminal, tqdm's bar updates in place (on stderr). In a log (stderr not a terminal, or
several jobs sharing one terminal: `RETAIN_PROGRESS=lines`), the same status is a line on
stdout every few minutes (`RETAIN_PROGRESS_EVERY` seconds, 180 by default), and a last one when
work that took that long ends: "[retain] foundation seed 0: 45%| 1800/4000 steps
[02:10<02:39, 13.8 steps/s]". Work shorter than the interval prints nothing in a log.
"""

from __future__ import annotations

import os
import sys
import time

from tqdm import tqdm

LINE_FORMAT = "{desc}: {percentage:3.0f}%| {n_fmt}/{total_fmt} {unit} [{elapsed}<{remaining}, {rate_fmt}]"


def log_every_seconds() -> float:
    return float(os.environ.get("RETAIN_PROGRESS_EVERY", "180"))


def in_place() -> bool:
    """A bar updated in place: stderr is a terminal that this process has to itself."""
    return os.environ.get("RETAIN_PROGRESS", "") != "lines" and sys.stderr.isatty()


class Progress:
    """`update()` after each unit of work; `close()` at its end (or use it as a context)."""

    def __init__(self, total: int, desc: str, unit: str = "steps", enabled: bool = True,
                 initial: int = 0):
        self.total, self.desc, self.unit, self.n, self.initial = total, desc, unit, initial, initial
        self.enabled = enabled and total > 0
        self.start = self.last_line = time.monotonic()
        self.every = log_every_seconds()
        self.bar = (tqdm(total=total, initial=initial, desc=desc, unit=f" {unit}", leave=False,
                         dynamic_ncols=True, file=sys.stderr)
                    if self.enabled and in_place() else None)

    def update(self, n: int = 1) -> None:
        self.n += n
        if self.bar is not None:
            self.bar.update(n)
        elif self.enabled and time.monotonic() - self.last_line >= self.every:
            self._line()

    def line(self) -> str:
        """The status as a log line shows it."""
        elapsed = time.monotonic() - self.start
        rate = (self.n - self.initial) / elapsed if elapsed > 0 else None  # this process's pace
        return "[retain] " + tqdm.format_meter(self.n, self.total, elapsed, prefix=self.desc,
                                               unit=self.unit, rate=rate, bar_format=LINE_FORMAT)

    def _line(self) -> None:
        print(self.line(), flush=True)
        self.last_line = time.monotonic()

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()
        elif self.enabled and time.monotonic() - self.start >= self.every:
            self._line()
        self.enabled = False

    def __enter__(self) -> Progress:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
