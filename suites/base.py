"""The contract every task suite fulfils, so the harness never knows which simulator it drives.

A suite names its tasks, gives each a language instruction, and builds a `TaskEnv`: a simulator
reset to a seeded initial state, stepped with actions in [-1, 1], reporting success from simulator
state, and able to ask its scripted expert (which reads privileged state) for the next action.
"""

from __future__ import annotations

import hashlib
import os
from abc import ABC, abstractmethod
from dataclasses import dataclass, field

import numpy as np

Observation = dict[str, np.ndarray]
"""Observation keys: "state" (float32 vector: proprioception and object state) always; with
cameras on, the `CAMERA_KEYS` images too (uint8 [S, S, 3], upright: row 0 is the top)."""

AGENTVIEW, EYE_IN_HAND = "agentview_rgb", "eye_in_hand_rgb"
CAMERA_KEYS = (AGENTVIEW, EYE_IN_HAND)
"""Camera observation keys, named as in LIBERO's datasets (obs/agentview_rgb, obs/eye_in_hand_rgb):
a fixed view of the workspace and a camera on the gripper. Every suite renders both, so a policy
trained on one suite's images reads another's."""


class SuiteError(Exception):
    """A user-facing error from a suite (assets missing, no expert, no spatial probe): one line
    naming the bad value and what is valid. The harness prints it as it prints its own errors;
    it lives here because suites sit upstream of the harness and never import it."""


class UnknownName(ValueError):
    """A name (task, suite, benchmark, method) that is not among the valid choices."""


def unknown(kind: str, value: str, valid) -> UnknownName:
    """One-line error naming the bad value and what is valid."""
    choices = ", ".join(sorted(valid))
    return UnknownName(f"unknown {kind} {value!r}; valid: {choices}")


@dataclass(frozen=True)
class StepResult:
    obs: Observation
    success: bool


class TaskEnv(ABC):
    """One task's simulator. Episodes start from `reset(seed)`: the same seed, the same state."""

    @abstractmethod
    def reset(self, seed: int) -> Observation: ...

    @abstractmethod
    def step(self, action: np.ndarray) -> StepResult: ...

    @abstractmethod
    def expert_action(self) -> np.ndarray:
        """The scripted expert's action for the current state (it may read privileged state)."""

    def demo_extras(self) -> dict[str, np.ndarray]:
        """Extra arrays a demo file keeps for the current step beside the observation, at paths
        inside its demo group (LIBERO's "obs/ee_states", "states", ...); none by default."""
        return {}

    # -- videos: the state is recorded during an episode, the frames drawn from it afterwards
    def view_state(self) -> np.ndarray:
        """What the scene looks like now, as a flat array `render_state` draws again: the
        simulator's state and whatever else a view depends on (LIBERO's fixture poses, which it
        writes into the model at each reset). Cheap enough to take every step of an evaluation
        episode; the episode itself is not changed."""
        raise SuiteError(f"{type(self).__name__} cannot record its state for videos; suites "
                         "with videos: bimanual, libero, metaworld")

    def render_state(self, state: np.ndarray, camera: str, size: int) -> np.ndarray:
        """A recorded `view_state` seen from `camera` ("" for the suite's `video_camera`), as an
        upright uint8 [size, size, 3] image. It may move this env's own state: rendering
        happens on an env of its own, built with cameras on, after the episodes."""
        raise SuiteError(f"{type(self).__name__} cannot render a state for videos; suites "
                         "with videos: bimanual, libero, metaworld")

    def close(self) -> None:  # noqa: B027 - optional
        pass


class Suite(ABC):
    """A family of tasks on one simulator, with the dimensions every task shares."""

    name: str
    state_dim: int
    action_dim: int
    max_episode_steps: int
    # one simulator's resident memory in MB, without and with cameras (`make bench-envs`): an
    # evaluation worker holds one per task at once, so this bounds how many workers fit
    simulator_mb: tuple[float, float] = (250.0, 500.0)

    def __init__(self):
        os.environ.setdefault("MUJOCO_GL", "egl")  # headless rendering when cameras are on

    video_camera: str = ""
    """The camera a video shows when none is named: the suite's view of the whole workspace."""

    @abstractmethod
    def task_names(self) -> list[str]: ...

    @abstractmethod
    def instruction(self, task: str) -> str: ...

    @abstractmethod
    def make_env(self, task: str, cameras: bool = False, image_size: int = 84,
                 render: str = "faithful") -> TaskEnv:
        """The task's simulator; with `cameras` its observations hold the `CAMERA_KEYS` images
        at `image_size` x `image_size`, drawn as `render` says (suites/render.py), and without,
        nothing is rendered."""

    def check_task(self, task: str) -> str:
        if task not in self.task_names():
            raise unknown(f"{self.name} task", task, self.task_names())
        return task

    def version(self, task: str) -> str:
        """Part of a task's demo-cache key: bump when its observations, expert or success change
        (a suite may bump the tasks a change touched, and keep the others' demos)."""
        return "1"

    evaluation_version: str = ""
    """Names how the suite's evaluation episodes start, part of the stage-0 cache key: bump it
    when they change (a cached stage-0 evaluation is then made anew); "" keeps the keys made
    before it existed."""

    spatial_probe_version: str = ""
    """Names the suite's spatial probe (its widened initial states) and is part of the stage-0
    cache key; "" when the suite has none."""

    def episode_keys(self, task: str, split: str, n: int) -> list[int]:
        """The `reset` keys of a task's episodes of one split ("demo", "heldout", "eval",
        "spatial"): seeds by default, spatial ones marked with SPATIAL_KEYS; a suite with fixed
        initial states (LIBERO) maps them its own way."""
        if split == "spatial":
            self.check_spatial_probe()
            return [SPATIAL_KEYS | seed for seed in episode_seeds(self.name, task, split, n)]
        return episode_seeds(self.name, task, split, n)

    def check_spatial_probe(self) -> None:
        if not self.spatial_probe_version:
            raise SuiteError(f"suite {self.name!r} has no spatial probe (spatial_episodes must "
                             "be 0); suites with one: libero, metaworld")

    def max_steps(self, task: str) -> int | None:
        """The task's own episode step limit, part of the suite's protocol (LIBERO's per-suite
        limits), or None: the benchmark's max_episode_steps applies."""
        return None

    def step_limit(self, task: str, max_episode_steps: int) -> int:
        """The limit demos and evaluation use: the task's own where it has one."""
        own = self.max_steps(task)
        return max_episode_steps if own is None else own

    def demo_file_attrs(self, task: str) -> dict[str, str]:
        """Extra attributes of a demo file's `data` group (LIBERO's problem_info, ...)."""
        return {}


class TaskTableSuite(Suite):
    """A suite whose tasks are the entries of a table: name -> spec with an `instruction`."""

    @abstractmethod
    def tasks(self) -> dict: ...

    def task_names(self) -> list[str]:
        return list(self.tasks())

    def instruction(self, task: str) -> str:
        return self.tasks()[self.check_task(task)].instruction


@dataclass
class ExpertEpisode:
    success: bool
    steps: int
    observations: list[Observation]  # the observation before each action, when recorded
    actions: list[np.ndarray]
    extras: list[dict[str, np.ndarray]] = field(default_factory=list)  # env.demo_extras()


def run_expert_episode(env: TaskEnv, seed: int, max_steps: int, record: bool = False) -> ExpertEpisode:
    """The scripted expert from `reset(seed)` for at most `max_steps`, stopping at success: the
    one loop behind demo generation, the expert tables and the raw-speed benchmark."""
    obs = env.reset(seed)
    episode = ExpertEpisode(False, 0, [], [])
    for _ in range(max_steps):
        action = env.expert_action()
        if record:
            episode.observations.append(obs)
            episode.actions.append(action)
            episode.extras.append(env.demo_extras())
        result = env.step(action)
        obs, episode.steps = result.obs, episode.steps + 1
        if result.success:
            episode.success = True
            break
    return episode


SPATIAL_KEYS = 1 << 31
"""Reset keys at or above this start the spatial probe's widened initial states (object
positions beyond the demos' range). Seeds are below 2**31 and LIBERO's fresh-scene keys in
[2**30, 2**31), so no other episode's key reaches it."""


def is_spatial(key: int) -> bool:
    return key >= SPATIAL_KEYS


def episode_seeds(suite: str, task: str, split: str, n: int) -> list[int]:
    """Fixed initial-state seeds (below 2**31) for one task and split ("demo", "heldout",
    "eval", "spatial").

    Derived from names, not from a global RNG, so every method, stage and machine sees the
    same episodes, and adding a task never shifts another task's episodes.
    """
    out = []
    for i in range(n):
        digest = hashlib.sha256(f"{suite}/{task}/{split}/{i}".encode()).digest()
        out.append(int.from_bytes(digest[:4], "little") & 0x7FFFFFFF)
    return out
