"""Imported by the robosuite suites before robosuite itself: robosuite warns at import time
(no private macro file, optional robot models absent) and per unused controller part, which
would greet every run with lines that say nothing about it. Errors still come through."""

import logging


class _ErrorsOnly(logging.Filter):
    def filter(self, record: logging.LogRecord) -> bool:
        return record.levelno >= logging.ERROR


for _name in ("robosuite_logs", "robosuite"):
    logging.getLogger(_name).addFilter(_ErrorsOnly())
