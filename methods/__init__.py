"""Fine-tuning methods, one module each, all subclasses of `Method`, registered by name.

`get_method("consft")` finds a registered method; `get_method("my_pkg.my_module:MyMethod")`
imports a user's class from their own module without touching this repository.
"""

from __future__ import annotations

import importlib
import importlib.util
import sys
from pathlib import Path

from methods.base import Method, MethodConfig, TaskContext

_REGISTRY: dict[str, type[Method]] = {}


def register_method(cls: type[Method]) -> type[Method]:
    """Class decorator: make a method available as `METHOD=<cls.name>`."""
    _REGISTRY[cls.name] = cls
    return cls


register_method(Method)


def _load_builtins() -> None:
    import pkgutil

    import methods as pkg

    for info in pkgutil.iter_modules(pkg.__path__):
        importlib.import_module(f"methods.{info.name}")


def _import(module_name: str):
    """A module by dotted name, or by path when it ends in .py."""
    if not module_name.endswith(".py"):
        return importlib.import_module(module_name)

    path = Path(module_name).expanduser().resolve()
    if not path.exists():
        raise ImportError(f"no such file {path}")
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[path.stem] = module
    spec.loader.exec_module(module)
    return module


def method_names() -> list[str]:
    _load_builtins()
    return sorted(_REGISTRY)


def get_method(spec: str) -> type[Method]:
    """A method class from a registered name or `module.path:ClassName`."""
    if ":" in spec:
        module_name, _, class_name = spec.rpartition(":")
        try:
            module = _import(module_name)
        except (ImportError, OSError) as exc:
            raise ValueError(f"cannot import method module {module_name!r} ({exc})") from None
        cls = getattr(module, class_name, None)
        if cls is None:
            raise ValueError(f"module {module_name!r} has no class {class_name!r}")
        if not (isinstance(cls, type) and issubclass(cls, Method)):
            raise ValueError(f"{spec!r} is not a method: it must subclass methods.Method")
        return cls
    _load_builtins()
    if spec not in _REGISTRY:
        valid = ", ".join(sorted(_REGISTRY))
        raise ValueError(f"unknown method {spec!r}; valid: {valid}, module.path:ClassName or file.py:ClassName")
    return _REGISTRY[spec]


__all__ = ["Method", "MethodConfig", "TaskContext", "register_method", "method_names", "get_method"]
