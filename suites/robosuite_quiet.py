"""Imported by the robosuite suites before robosuite itself: robosuite warns at import time
(no private macro file, optional robot models absent) and per unused controller part, and gym
0.26 (which LIBERO imports) prints a four-line deprecation notice to stderr when imported; all
would greet every run with lines that say nothing about it. Errors still come through."""

import contextlib
import io
import logging

with contextlib.redirect_stderr(io.StringIO()):
    try:
        import gym  # noqa: F401
    except ImportError:
        pass


class _ErrorsOnly(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno >= logging.ERROR


for _name in ("robosuite_logs", "robosuite"):
    logging.getLogger(_name).addFilter(_ErrorsOnly())
