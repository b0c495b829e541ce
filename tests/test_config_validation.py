"""Every setting's declared valid values are what the command line accepts: a value outside them
stops with one line naming the key, the value and what is valid (exit 2) before any demo,
foundation or MLflow run is made; a value inside them plans. hypothesis draws the values from
the declarations themselves (harness/config/validation.py), for every field of BenchConfig and every
hyperparameter of every registered method."""

from __future__ import annotations

import contextlib
import io
import math
import os
import subprocess
import sys
import tempfile
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated
from unittest import mock

import annotated_types as at
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from harness.common.errors import RetainError
from harness.config.benchmark import BenchConfig, resolve
from harness.config.validation import AtMost, check, constraints, declared_types, describe
from harness.run.cli import main
from harness.run.plan import plan
from methods import Method, MethodConfig, get_method, method_names

ROOT = Path(__file__).resolve().parents[1]
TINY = ["PROFILE=tiny"]
BASE = resolve(TINY)
FULL = resolve(["BENCH=mw-quick"])  # the benchmark's whole task lists, before tiny cuts them

# Settings whose valid values are a registry, the machine or the file system rather than a
# declared range (plan() checks those names, naming the valid ones): values a tiny plan accepts.
EXAMPLES: dict[str, st.SearchStrategy] = {
    "name": st.from_regex(r"[a-z][a-z0-9-]{0,12}", fullmatch=True),
    "suite": st.just("metaworld"),
    "policy": st.just("mlp"),
    "policy_size": st.sampled_from(["tiny", "default"]),
    "device": st.sampled_from(["cpu", "auto"]),
    "method": st.sampled_from([*method_names(), "all", "sft,ewc"]),
    "foundation_tasks": st.lists(st.sampled_from(FULL.foundation_tasks), min_size=1, unique=True),
    "stream_tasks": st.lists(st.sampled_from(FULL.stream_tasks), min_size=1, unique=True),
    "grid": st.sampled_from(["", "lr=0.0001,0.0003"]),
    "demos_dir": st.just(""),
    "policy_path": st.just(""),  # a LeRobot checkpoint folder or hub id: checked by the plan
    "lerobot_keys": st.just(""),  # a LeRobot folder's key and task maps: free text, read with it
    "lerobot_tasks": st.just(""),
    "results_dir": st.just("results"),  # made relative to a fresh folder in the test
    "cache_dir": st.just("cache"),
    "target": st.sampled_from([".*", r"blocks\..*"]),  # lora's regex
}
NOT_ON_COMMAND_LINE = {"method_params"}  # the hyperparameters, drawn one by one below


def settings_fields() -> list[tuple[str, type, object]]:
    """(method or "", settings class, defaults) for BenchConfig and every method's Config."""
    out = [("", BenchConfig, BASE)]
    for name in method_names():
        cls = get_method(name)
        out.append((name, cls.Config, cls.Config()))
    return [(owner, f, defaults) for owner, cls, defaults in out for f in declared_types(cls)
            if f not in NOT_ON_COMMAND_LINE]


def bounds(owner_defaults, key: str) -> tuple[float | None, bool, float | None, bool]:
    """(low, low is open, high, high is open) of a number field, its cross-field bounds
    included: chunk_size may not fall below the n_action_steps it bounds."""
    hints = declared_types(type(owner_defaults))
    _, metadata = constraints(hints[key])
    lo = hi = None
    lo_open = hi_open = False
    for m in metadata:
        if isinstance(m, (at.Ge, at.Gt)):
            lo, lo_open = (m.ge, False) if isinstance(m, at.Ge) else (m.gt, True)
        if isinstance(m, (at.Le, at.Lt)):
            hi, hi_open = (m.le, False) if isinstance(m, at.Le) else (m.lt, True)
        if isinstance(m, AtMost):
            hi = getattr(owner_defaults, m.other)
    return lo, lo_open, hi, hi_open


def cross_floor(owner_defaults, key: str) -> float | None:
    """The largest value of a field that `key` must stay at or above (AtMost on that field)."""
    hints = declared_types(type(owner_defaults))
    floors = [getattr(owner_defaults, f) for f, a in hints.items()
              if any(isinstance(m, AtMost) and m.other == key for m in constraints(a)[1])]
    return max(floors) if floors else None


def inside(owner_defaults, key: str) -> st.SearchStrategy | None:
    """Values the declaration accepts, as (command-line text, value the config then holds)."""
    base, metadata = constraints(declared_types(type(owner_defaults))[key])
    if key in EXAMPLES and typing.get_origin(base) is not typing.Literal:
        return EXAMPLES[key].map(lambda v: (",".join(v) if isinstance(v, list) else v, v))
    if typing.get_origin(base) is typing.Literal:
        return st.sampled_from(typing.get_args(base)).map(lambda v: (v, v))
    if base is bool:
        return st.booleans().map(lambda v: (str(v).lower(), v))
    if base in (int, float):
        lo, lo_open, hi, hi_open = bounds(owner_defaults, key)
        floor = cross_floor(owner_defaults, key)
        if floor is not None:
            lo, lo_open = max(lo, floor), False
        if base is int:
            low = -10_000 if lo is None else lo + lo_open
            high = low + 10_000 if hi is None else hi - hi_open
            return st.integers(low, high).map(lambda v: (str(v), v))
        return st.floats(min_value=lo, max_value=1e4 if hi is None else hi, exclude_min=lo_open,
                         exclude_max=hi_open, allow_nan=False, allow_infinity=False,
                         ).map(lambda v: (repr(v), v))
    return None  # text with no declared set and no example: nothing to draw from


def outside(owner_defaults, key: str) -> st.SearchStrategy | None:
    """Values the declaration refuses, as (command-line text, the value the error shows)."""
    base, metadata = constraints(declared_types(type(owner_defaults))[key])
    if typing.get_origin(base) is typing.Literal:
        allowed = typing.get_args(base)
        return st.from_regex(r"[a-z][a-z0-9_]{0,8}", fullmatch=True).filter(
            lambda v: v not in allowed).map(lambda v: (v, repr(v)))
    if base is bool:
        return st.just(("maybe", "'maybe'"))
    if base in (int, float):
        lo, lo_open, hi, hi_open = bounds(owner_defaults, key)
        draws = [st.just(("many", "'many'"))]  # not a number at all
        if base is int:
            if lo is not None:
                draws.append(st.integers(max_value=lo - 1 + lo_open).map(lambda v: (str(v), str(v))))
            if hi is not None:
                draws.append(st.integers(min_value=hi + 1 - hi_open).map(lambda v: (str(v), str(v))))
        else:
            draws.append(st.sampled_from([math.nan, math.inf, -math.inf]))
            if lo is not None:
                draws.append(st.floats(max_value=lo, allow_nan=False, allow_infinity=False)
                             .filter(lambda v: v <= lo if lo_open else v < lo))
            if hi is not None:
                draws.append(st.floats(min_value=hi, allow_nan=False, allow_infinity=False)
                             .filter(lambda v: v >= hi if hi_open else v > hi))
            draws[1:] = [d.map(lambda v: (repr(v), repr(v))) for d in draws[1:]]
        return st.one_of(draws)
    if any(isinstance(m, at.MinLen) and m.min_length > 0 for m in metadata):
        empty = "[]" if typing.get_origin(base) is list else "''"
        return st.just(("", empty))
    return None


CASES = [(owner, key, defaults) for owner, key, defaults in settings_fields()]


def _args(owner: str, key: str, text: str, folder: Path) -> list[str]:
    folders = [f"results_dir={folder / 'results'}", f"cache_dir={folder / 'cache'}"]
    if key in ("results_dir", "cache_dir") and text:
        text = str(folder / text)
    cli_key = "GRID" if key == "grid" and not owner else key
    return [*TINY, *folders, *([f"METHOD={owner}"] if owner else []), f"{cli_key}={text}"]


def _refuse_execution(*_args, **_kw):
    raise AssertionError("an invalid value got past planning")


@contextlib.contextmanager
def _no_tracking_uri():
    """The default store (results_dir/mlflow.db), so a made store would be seen in the folder."""
    saved = os.environ.pop("MLFLOW_TRACKING_URI", None)
    try:
        yield
    finally:
        if saved is not None:
            os.environ["MLFLOW_TRACKING_URI"] = saved


@settings(max_examples=100, deadline=None)
@given(case=st.sampled_from(CASES), valid=st.booleans(), data=st.data())
def test_declared_values_decide_what_plans_and_what_stops(tmp_path_factory, case, valid, data):
    owner, key, defaults = case
    strategy = inside(defaults, key) if valid else outside(defaults, key)
    if strategy is None:  # free text (a regex, a GRID) has no value outside its declaration
        return
    text, expected = data.draw(strategy, label=f"{owner or 'bench'}.{key}")
    folder = Path(tempfile.mkdtemp(dir=tmp_path_factory.getbasetemp()))
    args = _args(owner, key, text, folder)
    if valid:
        p = plan(args)
        held = [getattr(v.method.config if owner else v.cfg, key) for v in p.variants]
        if key in ("results_dir", "cache_dir"):
            expected = str(folder / expected)
        assert held and all(h == expected for h in held), (args, held)
        return
    err = io.StringIO()
    with _no_tracking_uri(), contextlib.redirect_stderr(err), \
            mock.patch("harness.run.cli.execute", _refuse_execution):
        code = main(["bench", *args])
    lines = [line for line in err.getvalue().splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1, (args, err.getvalue())
    assert lines[0].startswith(f"error: bad value {expected} for {key}"), (args, lines[0])
    assert "expected " in lines[0]
    assert list(folder.iterdir()) == []  # no demo, no foundation, no MLflow store


# --- the issue's own examples, through the real command in a fresh process ---------------------

@pytest.mark.parametrize("args, message", [
    (["steps_per_task=-5"], "bad value -5 for steps_per_task: expected an integer >= 1"),
    (["eval_episodes=0"], "bad value 0 for eval_episodes: expected an integer >= 1"),
])
def test_the_command_refuses_before_making_anything(tmp_path, args, message):
    env = {k: v for k, v in os.environ.items() if k != "MLFLOW_TRACKING_URI"}
    env["PYTHONPATH"] = str(ROOT)
    proc = subprocess.run([sys.executable, "-m", "harness", "bench", "PROFILE=tiny",
                           "results_dir=results", "cache_dir=cache", *args],
                          cwd=tmp_path, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and proc.stderr == f"error: {message}\n", proc.stderr
    assert list(tmp_path.iterdir()) == []  # no cache, no results, no mlflow.db, no mlruns


@pytest.mark.parametrize("args, message", [
    (["n_action_steps=5"], "bad value 5 for n_action_steps: expected an integer in [1, chunk_size=4]"),
    (["GRID=lr=1e-4,-1"], "bad value -1.0 for lr: expected a number > 0"),
    (["METHOD=er", "replay_ratio=1"],
     "bad value 1.0 for replay_ratio (method er): expected a number in [0, 1)"),
    (["METHOD=lora", "rank=0"], "bad value 0 for rank (method lora): expected an integer >= 1"),
])
def test_cross_field_grid_and_hyperparameter_values_are_refused(tmp_path, args, message):
    err = io.StringIO()
    with _no_tracking_uri(), contextlib.redirect_stderr(err), \
            mock.patch("harness.run.cli.execute", _refuse_execution):
        code = main(["bench", *TINY, f"results_dir={tmp_path}/results",
                     f"cache_dir={tmp_path}/cache", *args])
    assert code == 2 and err.getvalue() == f"error: {message}\n"
    assert list(tmp_path.iterdir()) == []


def test_a_negative_consft_temperature_is_refused():
    with pytest.raises(RetainError, match=r"^bad value -1.0 for kappa \(method consft\)"):
        plan([*TINY, "METHOD=consft", "kappa=-1"])


# --- the declarations themselves --------------------------------------------------------------

@pytest.mark.parametrize("owner", ["", *method_names()])
def test_every_number_and_choice_declares_its_valid_values(owner):
    """A number declares a bound, a text a set (Literal) or non-emptiness, unless it is free
    text with examples above; a new method's author is told here what is missing."""
    cls = get_method(owner).Config if owner else BenchConfig
    missing = []
    for key, annotation in declared_types(cls).items():
        base, metadata = constraints(annotation)
        if base in (int, float) and not any(isinstance(m, (at.Ge, at.Gt, at.Le, at.Lt))
                                            for m in metadata):
            missing.append(key)
        if base is str and not metadata and key not in EXAMPLES:
            missing.append(key)
    assert missing == [], f"{owner or 'BenchConfig'}: declare the valid values of {missing}"


def test_descriptions_read_as_the_user_sees_them():
    hints = declared_types(BenchConfig)
    assert describe(hints["steps_per_task"]) == "an integer >= 1"
    assert describe(hints["lr"]) == "a number > 0"
    assert describe(hints["executor"]) == "one of serial, local, ray"
    assert describe(hints["profile"]) == "one of '', quick, standard, tiny, paper"
    assert describe(hints["stream_tasks"]) == "a non-empty list of text"
    assert describe(hints["jobs"]) == "an integer >= 0 (0: as many as the cores and memory allow)"
    assert describe(hints["n_action_steps"], BASE) == "an integer in [1, chunk_size=4]"
    er = declared_types(get_method("er").Config)
    assert describe(er["replay_ratio"]) == "a number in [0, 1)"


def test_check_catches_what_code_sets_directly():
    """Not only the command line: a config changed in code (a study, a test) is checked too."""
    cfg = resolve(TINY)
    cfg.chunk_size = 2  # n_action_steps stays 4
    with pytest.raises(RetainError, match=r"^bad value 4 for n_action_steps: expected an integer "
                                          r"in \[1, chunk_size=2\]$"):
        check(cfg)
    cfg.chunk_size, cfg.lr = 4, float("inf")
    with pytest.raises(RetainError, match="^bad value inf for lr: expected a number > 0$"):
        check(cfg)


@dataclass
class _UserConfig(MethodConfig):
    ratio: Annotated[float, at.Interval(ge=0, lt=1)] = 0.5
    samples: Annotated[int, at.Ge(0), at.doc("0: all of them")] = 0


class _UserMethod(Method):
    name = "user_method"
    Config = _UserConfig


def test_a_users_method_is_checked_as_documented():
    """docs/adding-a-method.md's declarations, on a method that is not registered."""
    from harness.protocol.stream import make_method

    assert make_method(_UserMethod, {"ratio": "0.25"}).config.ratio == 0.25
    with pytest.raises(RetainError, match=r"^bad value 1.5 for ratio \(method user_method\): "
                                          r"expected a number in \[0, 1\)$"):
        make_method(_UserMethod, {"ratio": "1.5"})
    with pytest.raises(RetainError, match=r"^bad value -1 for samples \(method user_method\): "
                                          r"expected an integer >= 0 \(0: all of them\)$"):
        make_method(_UserMethod, {"samples": "-1"})
