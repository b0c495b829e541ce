"""Task suites: simulated environments, scripted experts, and their registry by name."""

from __future__ import annotations

import importlib
from collections.abc import Callable

from suites.base import (
    Observation,
    StepResult,
    Suite,
    SuiteError,
    TaskEnv,
    UnknownName,
    episode_seeds,
    unknown,
)

_SUITES: dict[str, str] = {
    # name -> module that defines and registers it; imported lazily (simulators are slow to load)
    "metaworld": "suites.metaworld",
    "libero": "suites.libero",
    "libero-proprio": "suites.libero.proprio",  # LIBERO's community datasets' 8-D state
    "libero-lerobot": "suites.libero.lerobot_protocol",  # lerobot-eval's LIBERO protocol
    "metaworld-lerobot": "suites.metaworld.lerobot_protocol",  # lerobot-eval's Meta-World
    "bimanual": "suites.bimanual",
}
_FACTORIES: dict[str, Callable[[], Suite]] = {}


def register_suite(name: str):
    """Class decorator: make a suite constructible by name."""

    def wrap(cls):
        _FACTORIES[name] = cls
        cls.name = name
        return cls

    return wrap


def suite_names() -> list[str]:
    return sorted(_SUITES)


def get_suite(name: str) -> Suite:
    if name not in _SUITES:
        raise unknown("suite", name, _SUITES)
    if name not in _FACTORIES:
        importlib.import_module(_SUITES[name])
    return _FACTORIES[name]()


__all__ = [
    "Suite", "TaskEnv", "StepResult", "Observation", "episode_seeds", "unknown", "UnknownName",
    "SuiteError",
    "register_suite", "suite_names", "get_suite",
]
