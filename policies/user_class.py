"""A user's class named as `my_pkg.my_module:MyClass` or `path/to/file.py:MyClass`: how both
registries (policies here, methods downstream) take a class from outside this repository."""

from __future__ import annotations

import importlib
import importlib.util
import sys
from pathlib import Path


def import_module(module_name: str):
    """A module by dotted name, or by path when it ends in .py. A file's folder joins sys.path,
    so spawned processes (evaluation workers, jobs; they inherit sys.path) import it by name."""
    if not module_name.endswith(".py"):
        return importlib.import_module(module_name)
    path = Path(module_name).expanduser().resolve()
    if not path.exists():
        raise ImportError(f"no such file {path}")
    if str(path.parent) not in sys.path:
        sys.path.insert(0, str(path.parent))
    if path.stem in sys.modules and getattr(sys.modules[path.stem], "__file__", None) == str(path):
        return sys.modules[path.stem]
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[path.stem] = module
    spec.loader.exec_module(module)
    return module


def load_class(spec: str, kind: str) -> type:
    """The class `spec` ("module:Class") names; ValueError, one line, naming what is wrong."""
    module_name, _, class_name = spec.rpartition(":")
    try:
        module = import_module(module_name)
    except (ImportError, OSError) as exc:
        raise ValueError(f"cannot import {kind} module {module_name!r} ({exc})") from None
    cls = getattr(module, class_name, None)
    if cls is None:
        raise ValueError(f"module {module_name!r} has no class {class_name!r}")
    return cls
