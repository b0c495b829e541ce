"""LIBERO's 130 tasks, read from the installed `libero` package: suite, name, instruction.

Task names are LIBERO's own (its BDDL file names without `.bddl`, which are also its dataset
file names `<name>_demo.hdf5`), e.g. `pick_up_the_alphabet_soup_and_place_it_in_the_basket` or
`KITCHEN_SCENE3_turn_on_the_stove`. The 130 names are distinct across the five suites (LIBERO-90
and LIBERO-10 carry their scene in the name), so no qualification is needed; a test keeps it so.
Instructions are LIBERO's `Task.language`. They are NOT all distinct: LIBERO-90 repeats some
("open the top drawer of the cabinet") in different scenes, as LIBERO itself does.

Suite order is LIBERO's standard task order (task_order_index 0).
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from functools import cache

import suites.robosuite_quiet  # noqa: F401  (before LIBERO's envs import gym and robosuite)
from suites.base import SuiteError
from suites.libero.install import point_libero_at_config

SUITES = ("libero_spatial", "libero_object", "libero_goal", "libero_10", "libero_90")
# per-suite episode step limits of the public VLA evaluations (OpenVLA's LIBERO protocol)
MAX_STEPS = {"libero_spatial": 220, "libero_object": 280, "libero_goal": 300, "libero_10": 520,
             "libero_90": 400}
NUM_INIT_STATES = 50  # every task's init-state file holds 50 states
SETTLE_STEPS = 10  # no-op steps after an init state, while objects settle (not counted)

# state layout (see env.py): proprioception, then MAX_OBJECTS object slots of pos + quat
PROPRIO_DIM = 9  # eef position 3, eef quaternion (xyzw) 4, gripper finger joints 2
OBJECT_DIM = 7
MAX_OBJECTS = 8  # the most objects of any of the 130 tasks (measured; a test checks it)
STATE_DIM = PROPRIO_DIM + OBJECT_DIM * MAX_OBJECTS


@dataclass(frozen=True)
class LiberoTask:
    name: str
    suite: str  # libero_spatial, libero_object, ...
    index: int  # position in its suite's standard order
    instruction: str
    bddl_file: str  # absolute path
    init_states_file: str  # absolute path

    @property
    def max_steps(self) -> int:
        return MAX_STEPS[self.suite]


def _benchmark(suite: str):
    point_libero_at_config()
    import contextlib
    import io

    from libero.libero.benchmark import get_benchmark_dict

    with contextlib.redirect_stdout(io.StringIO()):  # it prints "[info] using task orders ..."
        return get_benchmark_dict()[suite]()


@cache
def all_tasks() -> dict[str, LiberoTask]:
    """name -> task, suites in SUITES order, each in LIBERO's standard order."""
    import os

    point_libero_at_config()
    from libero.libero import get_libero_path

    out: dict[str, LiberoTask] = {}
    for suite in SUITES:
        bench = _benchmark(suite)
        init_dir = get_libero_path("init_states")
        for i, task in enumerate(bench.tasks):
            if task.name in out:
                raise RuntimeError(f"LIBERO task name {task.name!r} is in two suites")
            out[task.name] = LiberoTask(
                task.name, suite, i, task.language, bench.get_task_bddl_file_path(i),
                os.path.join(init_dir, task.problem_folder, task.init_states_file))
    return out


@cache
def sets_joints_at_reset(task: str) -> bool:
    """Whether the task's BDDL starts an articulated object in a state (a drawer open, a stove
    on): LIBERO draws those joints at every reset (its property samplers), from numpy's global
    RNG before the placements."""
    from libero.libero.envs.bddl_utils import robosuite_parse_problem

    problem = robosuite_parse_problem(all_tasks()[task].bddl_file)
    return any(state[0] in ("open", "close", "turnon", "turnoff")
               for state in problem["initial_state"])


def suite_tasks(suite: str) -> list[str]:
    """One suite's task names in LIBERO's standard order."""
    return [t.name for t in all_tasks().values() if t.suite == suite]


@cache
def init_states(task: str):
    """The task's 50 fixed init states (flattened MuJoCo states), as LIBERO's benchmark loads them
    (a torch.save'd NumPy array), but with torch's weights-only unpickler allowing NumPy's array
    types alone: a file that names anything else is refused, and nothing it names is called."""
    import pickle

    import numpy as np
    import torch

    path = all_tasks()[task].init_states_file
    try:
        with torch.serialization.safe_globals(numpy_array_globals()):
            return np.asarray(torch.load(path, weights_only=True))
    except pickle.UnpicklingError as err:
        found = re.search(r"[Uu]nsupported (?:global: )?GLOBAL ([\w.]+)", str(err))
        raise SuiteError(f"LIBERO init-state file {path} was not loaded: it holds "
                         f"{found.group(1) if found else 'an object'}, not a NumPy array; "
                         "reinstall the libero package (make venv)") from None


def numpy_array_globals() -> list:
    """What a pickled NumPy array names, under NumPy 2's module names and the `numpy.core` ones
    of the NumPy 1 that wrote LIBERO's files: the array, its dtype (and dtype classes), and the
    array's rebuild function. Nothing that runs code."""
    import numpy as np
    from numpy._core.multiarray import _reconstruct

    dtypes = [type(np.dtype(t)) for t in np.typecodes["All"]]
    return [np.ndarray, np.dtype, *dtypes, _reconstruct,
            (_reconstruct, "numpy.core.multiarray._reconstruct")]
