"""The task table: scenes (what is on the table) and tasks (what to do in a scene), as plain data.

Three families mirror LIBERO's suites: *object* (which object goes to the basket), *goal* (one
scene, many goals) and *spatial* (identical cubes; which one is meant depends on where it is).
Everything a task needs — scene, target, success kind — is here, so adding a task is one entry.
"""

from __future__ import annotations

from dataclasses import dataclass

MAX_OBJECTS = 3  # object slots in the state vector; every scene fills at most this many
MAX_FIXTURES = 2  # fixture slots (bin, marker, region), position only
PROPRIO_DIM = 9  # end-effector position and quaternion, two finger joints
STATE_DIM = PROPRIO_DIM + 7 * MAX_OBJECTS + 3 * MAX_FIXTURES  # layout: env.py's docstring


@dataclass(frozen=True)
class Scene:
    """Objects (in state-slot order) placed on shuffled, jittered spots, plus fixed fixtures.

    Which object lands on which spot is drawn per episode, so a policy must read the language
    (object family) or compare positions (spatial family) rather than memorise a slot.
    """

    name: str
    objects: tuple[str, ...]  # model kinds, see scene.OBJECT_MODELS
    spots: tuple[tuple[float, float], ...]  # candidate (x, y) centres, table frame
    jitter: float  # uniform +-jitter (m) around a spot
    fixtures: tuple[tuple[str, tuple[float, float]], ...]  # (kind, (x, y)) in state-slot order


@dataclass(frozen=True)
class Task:
    """`kind` is "place" (pick `obj`, put it on `target`), "lift" or "push" (to `target`).

    `obj` is a slot index, or "left"/"middle"/"right" for the spatial family (resolved after
    reset by the object's y). `target` is a fixture kind ("bin", "marker", "region") or
    "slot:<i>" to stack on another object.
    """

    name: str
    family: str
    scene: Scene
    instruction: str
    kind: str
    obj: int | str
    target: str | None = None


_ROW = ((-0.05, -0.15), (-0.05, 0.0), (-0.05, 0.15))  # three spots in a row, robot's right to left
_BIN = ("bin", (0.17, 0.0))

OBJECT_SCENES = (
    Scene("kitchen_a", ("milk", "bread", "cereal"), _ROW, 0.02, (_BIN,)),
    Scene("kitchen_b", ("can", "lemon", "bottle"), _ROW, 0.02, (_BIN,)),
)
GOAL_SCENE = Scene(
    "goal",
    ("red_cube", "green_cube"),
    ((-0.08, -0.1), (-0.08, 0.1)),
    0.03,
    (("marker", (0.02, 0.0)), ("region", (0.16, 0.0))),
)
SPATIAL_SCENE = Scene("spatial", ("blue_cube",) * 3, _ROW, 0.02, (_BIN,))


def _object_tasks() -> list[Task]:
    names = {"milk": "milk carton", "cereal": "cereal box", "can": "soda can"}
    tasks = []
    for scene in OBJECT_SCENES:
        for slot, kind in enumerate(scene.objects):
            noun = names.get(kind, kind)
            tasks.append(Task(f"object_{kind}_to_bin", "object", scene,
                              f"pick up the {noun} and place it in the basket", "place", slot, "bin"))
    return tasks


def _goal_tasks() -> list[Task]:
    s = GOAL_SCENE
    return [
        Task("goal_lift_red", "goal", s, "lift the red cube", "lift", 0),
        Task("goal_stack_red_on_green", "goal", s, "stack the red cube on the green cube",
             "place", 0, "slot:1"),
        Task("goal_stack_green_on_red", "goal", s, "stack the green cube on the red cube",
             "place", 1, "slot:0"),
        Task("goal_red_to_marker", "goal", s, "put the red cube on the yellow marker",
             "place", 0, "marker"),
        Task("goal_green_to_marker", "goal", s, "put the green cube on the yellow marker",
             "place", 1, "marker"),
        Task("goal_push_red_to_region", "goal", s, "push the red cube into the blue area",
             "push", 0, "region"),
    ]


def _spatial_tasks() -> list[Task]:
    where = {"left": "on the left", "middle": "in the middle", "right": "on the right"}
    return [Task(f"spatial_{side}_cube_to_bin", "spatial", SPATIAL_SCENE,
                 f"pick up the cube {phrase} and place it in the basket", "place", side, "bin")
            for side, phrase in where.items()]


TASKS: dict[str, Task] = {t.name: t for t in _object_tasks() + _goal_tasks() + _spatial_tasks()}
