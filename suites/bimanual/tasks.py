"""The suite's tasks: scene, success test and scripted expert of each, as data.

Eight two-arm tasks. `lift_pot` is robosuite's own TwoArmLift; the others are scenes built from
robosuite object models (boxes, a stick, a bin) by `scene.make_scene_env`. Each expert is a
list of coordinated phases from `script` (pick / place moves zipped across the arms).
Positions are world metres: table top at z = 0.8, robots on the -x edge, +y on their left.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from suites.bimanual.scene import ROBOT_INDEX, Item, Marker, make_scene_env
from suites.bimanual.script import Move, Phase, in_turn, pick, place, together
from suites.bimanual.world import World
from suites.robosuite_common import CLOSED, OPEN, TABLE_TOP

Z_AXIS = np.array([0.0, 0.0, 1.0])
RED, GREEN, BLUE, WOOD = (0.85, 0.2, 0.2, 1), (0.2, 0.75, 0.3, 1), (0.2, 0.4, 0.85, 1), (0.65, 0.5, 0.3, 1)


@dataclass(frozen=True)
class TaskSpec:
    """Everything the suite needs to know about one task.

    objects: names whose pose (position + quaternion) fills the state's object slots, in order.
    points:  names whose position fills the state's point slots (targets, grasp handles).
    quat_ref: per object, the quaternion (w, x, y, z) whose hemisphere its reported quaternion is kept in,
              so the sign never flips within the task's range of orientations.
    """

    name: str
    instruction: str
    build: Callable[[dict], object]  # robosuite kwargs -> robosuite env
    names: Callable[[object], tuple[dict[str, str], dict[str, str]]]  # env -> (bodies, sites) for read_world
    objects: tuple[str, ...]
    points: tuple[str, ...]
    success: Callable[[World, object], bool]
    expert: Callable[[World], list[Phase]]  # built from the first World of an episode
    quat_ref: dict[str, tuple[float, float, float, float]] = field(default_factory=dict)


# ---------------------------------------------------------------- helpers shared by the task specs


def at(name: str, local: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> Callable[[World], np.ndarray]:
    """Live point `local` (in the body's yaw-rotated frame) of a named body or site."""
    local = np.asarray(local)

    def point(w: World) -> np.ndarray:
        if not local.any():
            return w.pos[name]
        c, s = np.cos(w.yaw(name)), np.sin(w.yaw(name))
        return w.pos[name] + np.array([c * local[0] - s * local[1], s * local[0] + c * local[1], local[2]])

    return point


def heading(name: str, plus: float = 0.0) -> Callable[[World], float]:
    """Live yaw of a body (+ `plus`), for turning the fingers to match it."""
    return lambda w: w.yaw(name) + plus


def carried_onto(arm: str, held: str, onto: str) -> Callable[[World], np.ndarray]:
    """Where `arm`'s grip site must go for the object it holds to sit centred over `onto`
    (corrects for the object having slipped off-centre in the fingers)."""
    return lambda w: w.pos[onto] + (w.eef_pos[arm] - w.pos[held])


def const(value) -> Callable[[World], object]:
    return lambda w: value


def held(env, arm: str, obj: str) -> bool:
    """Both fingerpads of `arm` touch the object (robosuite's grasp test)."""
    gripper = env.robots[ROBOT_INDEX[arm]].gripper["right"]
    return env._check_grasp(gripper=gripper, object_geoms=env.objects[obj])


def released(env, obj: str) -> bool:
    return not (held(env, "left", obj) or held(env, "right", obj))


def xy_dist(w: World, a: str, b: str) -> float:
    return float(np.linalg.norm(w.pos[a][:2] - w.pos[b][:2]))


def resting(w: World, obj: str, half_height: float, slack: float = 0.01) -> bool:
    return w.pos[obj][2] < TABLE_TOP + half_height + slack


def inside_bin(w: World, obj: str, bin_: str, half: float, height: float) -> bool:
    """Object centre within the bin's inner footprint and below its rim (the bin body is at its centre)."""
    c, s = np.cos(-w.yaw(bin_)), np.sin(-w.yaw(bin_))
    d = w.pos[obj] - w.pos[bin_]
    local = np.array([c * d[0] - s * d[1], s * d[0] + c * d[1]])
    return bool(np.all(np.abs(local) < half) and d[2] < height / 2)


def box(size, rgba, density=400.0, friction=(1.5, 0.005, 0.0001)):
    """Factory for a robosuite BoxObject of half-size `size`."""

    def make(name):
        from robosuite.models.objects import BoxObject

        return BoxObject(name=name, size=list(size), rgba=list(rgba), density=density, friction=list(friction))

    return make


def bin_model(size, density=150.0):
    def make(name):
        from robosuite.models.objects import Bin

        return Bin(name=name, bin_size=size, wall_thickness=0.01, transparent_walls=False, density=density,
                   friction=(1.5, 0.005, 0.0001))

    return make


def scene_task(name, instruction, items, markers, success, expert, sites=None, quat_ref=None) -> TaskSpec:
    """A TaskSpec on the suite's own table scene: objects are the items, points are the markers."""

    def build(kwargs):
        return make_scene_env(tuple(items), tuple(markers), **kwargs)

    def names(env):
        bodies = {n: obj.root_body for n, obj in env.objects.items()}
        bodies.update({n: pad.root_body for n, pad in env.pads.items()})
        return bodies, dict(sites or {})

    return TaskSpec(name, instruction, build, names, tuple(i.name for i in items), tuple(m.name for m in markers),
                    success, expert, quat_ref or {})


# ---------------------------------------------------------------- tasks

CUBE = 0.022  # half size of the small cubes


def _lift_pot() -> TaskSpec:
    """robosuite TwoArmLift: grasp the pot's two handles (one per arm) and lift it level."""

    def build(kwargs):
        import robosuite

        return robosuite.make("TwoArmLift", **kwargs)

    def names(env):
        sites = {f"handle{i}": env.pot.important_sites[f"handle{i}"] for i in range(2)}
        return {"pot": env.pot.root_body}, sites

    def success(w, env):
        return bool(env._check_success()) and w.tilt("pot") < np.pi / 6

    def expert(w0):
        # Each arm takes the handle on its own side; the fingers close along the pot-centre -> handle line.
        left, right = sorted(("handle0", "handle1"), key=lambda h: -w0.pos[h][1])

        def radial(handle):
            return lambda w: float(np.arctan2(*(w.pos[handle] - w.pos["pot"])[1::-1]))

        return together(pick(at(left), radial(left), lift=0.18), pick(at(right), radial(right), lift=0.18))

    return TaskSpec("lift_pot", "lift the pot by both handles", build, names, ("pot",), ("handle0", "handle1"),
                    success, expert, quat_ref={"pot": (0.0, 0.0, 0.0, 1.0)})


def _lift_box() -> TaskSpec:
    half = (0.025, 0.2, 0.025)
    grip = 0.15  # grasp points along the box, either side of its centre

    def success(w, env):
        return w.pos["box"][2] > TABLE_TOP + half[2] + 0.08 and w.tilt("box") < 0.35

    def expert(w0):
        return together(pick(at("box", (0, grip, 0)), heading("box"), lift=0.14),
                        pick(at("box", (0, -grip, 0)), heading("box"), lift=0.14))

    items = [Item("box", box(half, WOOD, density=250), x=(-0.08, 0.04), y=(-0.03, 0.03), yaw=(-0.25, 0.25))]
    return scene_task("lift_box", "lift the long box together with both arms", items, [], success, expert)


def _cube_pair(x=(-0.12, 0.0), y=(0.14, 0.28)) -> list[Item]:
    """A red cube on the left half of the table and a green one mirrored on the right."""
    return [Item("cube_left", box((CUBE,) * 3, RED), x=x, y=y, yaw=(-0.5, 0.5)),
            Item("cube_right", box((CUBE,) * 3, GREEN), x=x, y=(-y[1], -y[0]), yaw=(-0.5, 0.5))]


def _dual_lift() -> TaskSpec:
    def success(w, env):
        return all(w.pos[c][2] > TABLE_TOP + CUBE + 0.08 for c in ("cube_left", "cube_right"))

    def expert(w0):
        return together(pick(at("cube_left"), heading("cube_left")), pick(at("cube_right"), heading("cube_right")))

    return scene_task("dual_lift", "lift both cubes at the same time", _cube_pair(), [], success, expert)


def _dual_place() -> TaskSpec:
    markers = [Marker("target_left", x=(0.04, 0.14), y=(0.14, 0.3), rgba=RED[:3] + (0.5,)),
               Marker("target_right", x=(0.04, 0.14), y=(-0.3, -0.14), rgba=GREEN[:3] + (0.5,))]

    def success(w, env):
        return all(xy_dist(w, f"cube_{s}", f"target_{s}") < 0.03 and resting(w, f"cube_{s}", CUBE)
                   for s in ("left", "right"))

    def moves(side):
        return pick(at(f"cube_{side}"), heading(f"cube_{side}")) + place(at(f"target_{side}"), CUBE + 0.005)

    return scene_task("dual_place", "put each cube on the pad of its colour", _cube_pair(), markers, success,
                      lambda w0: together(moves("left"), moves("right")))


def _handover_stick() -> TaskSpec:
    half = (0.015, 0.11, 0.015)
    hold = 0.065  # each arm grasps this far from the stick's centre, on its own side
    meet = np.array([0.0, 0.0, 1.0])  # stick centre when the arms swap it

    def success(w, env):
        return xy_dist(w, "stick", "target") < 0.04 and resting(w, "stick", half[2]) and released(env, "stick")

    def expert(w0):
        right_meet = const(meet + [0, -hold, 0])
        left_meet = const(meet + [0, hold, 0])
        return (
            in_turn("right", pick(at("stick", (0, -hold, 0)), heading("stick"), lift=0.12))
            + together([Move(to=left_meet, offset=(0, 0, 0.1), grip=OPEN, yaw=const(0.0), tol=0.02)],
                       [Move(to=right_meet, grip=CLOSED, yaw=const(0.0), tol=0.01)])
            + in_turn("left", [Move(to=at("stick", (0, hold, 0)), grip=OPEN, yaw=heading("stick"), tol=0.01),
                               Move(grip=CLOSED, wait=8)])
            + in_turn("right", [Move(grip=OPEN, wait=6), Move(offset=(0, -0.08, 0.08), grip=OPEN, tol=0.02)])
            + in_turn("left", place(at("target", (0, hold, 0)), half[2] + 0.005, yaw=const(0.0)))
        )

    items = [Item("stick", box(half, BLUE, density=500), x=(-0.1, 0.04), y=(-0.3, -0.2), yaw=(-0.3, 0.3))]
    markers = [Marker("target", x=(-0.06, 0.08), y=(0.2, 0.28), rgba=BLUE[:3] + (0.5,), radius=0.04)]
    return scene_task("handover_stick", "hand the stick from the right arm to the left arm and put it on the pad",
                      items, markers, success, expert)


def _stack_cubes() -> TaskSpec:
    big = 0.028

    def success(w, env):
        top, bottom = w.pos["cube_right"], w.pos["cube_left"]
        return (np.linalg.norm(top[:2] - bottom[:2]) < 0.02 and abs(top[2] - bottom[2] - big - CUBE) < 0.01
                and xy_dist(w, "cube_left", "target") < 0.04 and released(env, "cube_right"))

    def expert(w0):
        left = (pick(at("cube_left"), heading("cube_left")) + place(at("target"), big + 0.005)
                + [Move(offset=(0, 0.15, 0), grip=OPEN, tol=0.03)])
        right = pick(at("cube_right"), heading("cube_right"), lift=0.16)
        on_top = place(carried_onto("right", "cube_right", "cube_left"), big + CUBE + 0.005, yaw=heading("cube_left"))
        return together(left, right) + in_turn("right", on_top)

    items = [Item("cube_left", box((big,) * 3, RED), x=(-0.12, 0.0), y=(0.16, 0.28), yaw=(-0.5, 0.5)),
             Item("cube_right", box((CUBE,) * 3, GREEN), x=(-0.12, 0.0), y=(-0.28, -0.16), yaw=(-0.5, 0.5))]
    markers = [Marker("target", x=(0.0, 0.08), y=(-0.04, 0.04))]
    return scene_task("stack_cubes", "the left arm puts the red cube on the pad, then the right arm stacks the "
                      "green cube on it", items, markers, success, expert)


BIN_SIZE = (0.16, 0.16, 0.06)


def _cubes_into_bin() -> TaskSpec:
    inner = BIN_SIZE[0] / 2 - 0.01

    def success(w, env):
        return all(inside_bin(w, c, "bin", inner, BIN_SIZE[2]) for c in ("cube_left", "cube_right"))

    def drop(side):
        return [Move(to=at("bin"), offset=(0, 0.03 if side == "left" else -0.03, 0.16), grip=CLOSED, tol=0.02),
                Move(grip=OPEN, wait=6),
                Move(offset=(0, 0.12 if side == "left" else -0.12, 0.02), grip=OPEN, tol=0.03)]

    def expert(w0):
        return (together(pick(at("cube_left"), heading("cube_left")), pick(at("cube_right"), heading("cube_right")))
                + in_turn("left", drop("left")) + in_turn("right", drop("right")))

    items = [Item("bin", bin_model(BIN_SIZE), x=(0.0, 0.08), y=(-0.03, 0.03), yaw=(-0.2, 0.2))] + _cube_pair(
        y=(0.17, 0.28))
    return scene_task("cubes_into_bin", "put both cubes into the bin", items, [], success, expert)


def _hold_bin_place() -> TaskSpec:
    size = (0.2, 0.2, 0.05)
    inner = size[0] / 2 - 0.01

    def success(w, env):
        return inside_bin(w, "cube_right", "bin", inner, size[2]) and w.pos["bin"][2] > TABLE_TOP + 0.04

    def expert(w0):
        # The left hand straddles the bin's +y wall and so covers the bin's +y half: the right arm turns its
        # fingers along x (hand thin in y) and drops the cube over the -y half.
        wall = (0.0, size[1] / 2 - 0.005, size[2] / 2 - 0.02)
        hold = pick(at("bin", wall), heading("bin", np.pi / 2), lift=0.06)
        right = pick(at("cube_right"), heading("cube_right"), lift=0.16)
        into = [Move(to=at("bin", (0.0, -0.055, 0.0)), offset=(0, 0, 0.12), grip=CLOSED, yaw=heading("bin"),
                     tol=0.015),
                Move(grip=OPEN, wait=12),
                Move(offset=(0, 0, 0.08), grip=OPEN, tol=0.03)]
        return together(hold, right) + in_turn("right", into)

    items = [Item("bin", bin_model(size, density=100), x=(-0.04, 0.04), y=(0.02, 0.06), yaw=(-0.2, 0.2)),
             Item("cube_right", box((CUBE,) * 3, GREEN), x=(-0.12, 0.0), y=(-0.3, -0.2), yaw=(-0.5, 0.5))]
    return scene_task("hold_bin_place", "the left arm lifts the bin and holds it while the right arm drops the "
                      "cube into it", items, [], success, expert)


TASKS: dict[str, TaskSpec] = {
    spec.name: spec
    for spec in (_lift_pot(), _lift_box(), _dual_lift(), _dual_place(), _handover_stick(),
                 _stack_cubes(), _cubes_into_bin(), _hold_bin_place())
}
