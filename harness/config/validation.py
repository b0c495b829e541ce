"""Every setting declares its valid values where it is defined; `check` tests them all.

A field of `BenchConfig` or of a method's Config states them in its annotation, with the
constraints of annotated_types (the ones pydantic reads), one line per field:

    steps_per_task: Annotated[int, Ge(1)] = 1500
    replay_ratio: Annotated[float, Interval(ge=0, lt=1)] = 0.5
    reference: Literal["previous", "foundation"] = "previous"
    jobs: Annotated[int, Ge(0), doc("0: as many as the cores and memory allow")] = 0
    n_action_steps: Annotated[int, Ge(1), AtMost("chunk_size")] = 4

A plain `int`, `float` or `str` accepts any value of its type, except that no float setting is
ever NaN or infinite. `check(settings)` validates every field with pydantic, strictly (no text
for a number, no bool for an integer), and raises a one-line RetainError naming the key, the bad
value and what is valid: `bad value -5 for steps_per_task: expected an integer >= 1`.
"""

from __future__ import annotations

import dataclasses
import functools
import types
import typing
from dataclasses import dataclass
from typing import Any, Literal

import annotated_types as at
from pydantic import ConfigDict, TypeAdapter, ValidationError

from harness.common.errors import RetainError

_STRICT = ConfigDict(strict=True, allow_inf_nan=False)
_NOUNS = {int: "an integer", float: "a number", str: "text", bool: "true or false"}


@dataclass(frozen=True)
class AtMost:
    """An upper bound set by another field of the same settings (n_action_steps <= chunk_size)."""

    other: str


def check(settings: Any, owner: str = "") -> None:
    """Raise a RetainError for the first field of the dataclass `settings` outside its declared
    values; `owner` ("consft") names the method whose hyperparameters these are."""
    for f in dataclasses.fields(settings):
        annotation = declared_types(type(settings))[f.name]
        value = getattr(settings, f.name)
        if not _valid(annotation, value, settings):
            where = f" (method {owner})" if owner else ""
            raise RetainError(f"bad value {value!r} for {f.name}{where}: "
                              f"expected {describe(annotation, settings)}")


@functools.cache
def declared_types(cls: type) -> dict[str, Any]:
    """Each field's resolved annotation, its declared constraints (Annotated) kept."""
    return typing.get_type_hints(cls, include_extras=True)


def constraints(annotation: Any) -> tuple[Any, list[Any]]:
    """(the type, its declared constraints): Interval(ge=0, lt=1) becomes [Ge(0), Lt(1)]."""
    if typing.get_origin(annotation) is not typing.Annotated:
        return annotation, []
    base, *metadata = typing.get_args(annotation)
    flat: list[Any] = []
    for m in metadata:
        flat += list(m) if isinstance(m, at.GroupedMetadata) else [m]
    return base, flat


def _valid(annotation: Any, value: Any, settings: Any) -> bool:
    try:
        _adapter(annotation).validate_python(value)
    except ValidationError:
        return False
    _, metadata = constraints(annotation)
    return all(value <= getattr(settings, m.other) for m in metadata if isinstance(m, AtMost))


@functools.cache
def _adapter(annotation: Any) -> TypeAdapter:
    return TypeAdapter(annotation, config=_STRICT)


def describe(annotation: Any, settings: Any = None) -> str:
    """What a field accepts, in words: "an integer >= 1", "a number in [0, 1)", "one of
    clip, dft, ratio", with the declared doc ("0: probe off") in parentheses."""
    base, metadata = constraints(annotation)
    text = _noun(base)
    lower = [(m.ge, "[", ">=") if isinstance(m, at.Ge) else (m.gt, "(", ">") for m in metadata
             if isinstance(m, (at.Ge, at.Gt))]
    upper = [(m.le, "]", "<=") if isinstance(m, at.Le) else (m.lt, ")", "<") for m in metadata
             if isinstance(m, (at.Le, at.Lt))]
    upper += [(f"{m.other}={getattr(settings, m.other)}" if settings is not None else m.other,
               "]", "<=") for m in metadata if isinstance(m, AtMost)]
    if any(isinstance(m, at.MinLen) and m.min_length > 0 for m in metadata):
        text = "non-empty text" if base is str else text.replace("a list", "a non-empty list", 1)
    if lower and upper:
        (lo, left, _), (hi, right, _) = lower[0], upper[0]
        text += f" in {left}{lo}, {hi}{right}"
    elif lower or upper:
        bound, _, op = (lower or upper)[0]
        text += f" {op} {bound}"
    notes = [m.documentation for m in metadata if isinstance(m, at.DocInfo)]
    return text + "".join(f" ({n})" for n in notes)


def _noun(base: Any) -> str:
    origin, args = typing.get_origin(base), typing.get_args(base)
    if origin is Literal:
        return "one of " + ", ".join(repr(a) if a == "" else str(a) for a in args)
    if origin in (typing.Union, types.UnionType):
        return " or ".join(_noun(a) for a in args)
    if origin is list:
        if not args:
            return "a list"
        item = _noun(args[0])
        return f"a list of ({item})" if " or " in item else f"a list of {item}"
    if origin is dict:
        return "a mapping"
    return _NOUNS.get(base, getattr(base, "__name__", str(base)))
