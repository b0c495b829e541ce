"""Fine-tuning methods, one module each, all subclasses of `Method`, registered by name.

`get_method("consft")` finds a registered method; `get_method("my_pkg.my_module:MyMethod")`
imports a user's class from their own module without touching this repository.
"""

from __future__ import annotations

import importlib

from methods.base import Method, MethodConfig, TaskContext
from policies.user_class import load_class

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


def method_names() -> list[str]:
    """The fine-tuning methods (what METHOD=all runs); `checkpoints`, whose stages load weights
    instead of training, is registered but not one of them."""
    _load_builtins()
    return sorted(name for name, cls in _REGISTRY.items() if cls.trains)


def get_method(spec: str) -> type[Method]:
    """A method class from a registered name or `module.path:ClassName`."""
    if ":" in spec:
        cls = load_class(spec, "method")
        if not (isinstance(cls, type) and issubclass(cls, Method)):
            raise ValueError(f"{spec!r} is not a method: it must subclass methods.Method")
        _load_builtins()
        if _REGISTRY.get(cls.name, cls) is not cls:  # its runs would be filed as that method's
            raise ValueError(f"{spec!r} needs a name of its own (a class attribute such as "
                             f"name = \"my_method\"): {cls.name!r} is a built-in method's")
        if cls.evaluation_view is not Method.evaluation_view and not cls.task_aware_eval:
            raise ValueError(f"{spec!r} overrides evaluation_view but does not set "
                             f"task_aware_eval = True, so its view would never be entered")
        return cls
    _load_builtins()
    if spec not in _REGISTRY:
        valid = ", ".join(sorted(_REGISTRY))
        raise ValueError(f"unknown method {spec!r}; valid: {valid}, module.path:ClassName or file.py:ClassName")
    return _REGISTRY[spec]


__all__ = ["Method", "MethodConfig", "TaskContext", "register_method", "method_names", "get_method"]
