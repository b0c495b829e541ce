"""From one BDDL goal predicate to a skill plan, using the scene as it is now."""

from __future__ import annotations

import numpy as np

from suites.libero.experts.scene import Scene
from suites.libero.experts.skills import GRIPPER_SPAN, Grasp, Phase, pick, place, push, slide, turn

CARRY_CLEARANCE = 0.07  # the carried object's bottom above the higher of start and goal surface
SLIDE = 2  # MuJoCo's mjJNT_SLIDE
RELEASE_GAP = 0.012  # the object's bottom above its resting surface when the hand opens
DRAWER_MARGIN = 0.015  # an object dropped in a drawer stays this far inside its front wall
FLAT = 0.035  # a wide object lower than this (a plate) is pushed, not picked
PUSH_SAMPLE = 0.01  # spacing of the checks along a push path
PUSH_MARGIN = 0.01  # what a pushed object should keep from others on its way
OVERHANG = 0.15  # a part this little above an object's top hangs over it (the hand's height)
HAND_ROOM = 0.03  # an object withdrawn from under a part ends this far clear of it
WITHDRAW_STEP, WITHDRAW_MAX = 0.005, 0.2  # m
UNDER_GAP = 0.02  # what a withdrawn object's top keeps from the bottom of what hangs over it


def _placement(scene: Scene, relation: str, obj: str, target: str):
    """(xy function, resting-height function) for putting something in/on `target`."""
    if scene.is_site(target):
        size = scene.site_size(target)
        xy = lambda: scene.pos(target)[:2]  # noqa: E731
        if _is_drawer(scene, target):  # drop it in just above the drawer's floor
            return _drawer_xy(scene, target, obj), lambda: scene.pos(target)[2] + RELEASE_GAP
        if relation == "in":
            return xy, lambda: scene.pos(target)[2] + size[2] + RELEASE_GAP
        return xy, lambda: scene.pos(target)[2] + RELEASE_GAP
    return (lambda: scene.pos(target)[:2]), lambda: scene.box(target)[1][2] + RELEASE_GAP


def _drawer_xy(scene: Scene, region: str, obj: str):
    """Where to drop an object in a drawer's region: as far out toward the drawer's front as
    the region holds it (the region's front edge is the front wall), since the back of an open
    drawer stays under the cabinet's top."""
    axis, _, _ = scene.joint(scene.joint_name(region))
    props = scene.thing(scene.site_parent(region)).object_properties["articulation"]
    out = axis * np.sign(np.mean(props["default_open_ranges"])
                         - np.mean(props["default_close_ranges"]))
    out[2] = 0.0
    out /= np.linalg.norm(out)
    # the region's half-extent along `out`, taken as LIBERO's containment test takes it
    reach = np.abs(scene.mat(region) @ scene.site_size(region)) @ np.abs(out)
    radius = scene.footprint(obj)[1] / 2

    def xy():
        return scene.pos(region)[:2] + out[:2] * max(reach - radius - DRAWER_MARGIN, 0.0)
    return xy


def _is_drawer(scene: Scene, target: str) -> bool:
    """A region that moves on a slide joint (inside a drawer), not one on a free object."""
    if not scene.is_site(target) or not scene.env.object_sites_dict[target].joints:
        return False
    joint = scene.model.joint(scene.joint_name(target)).id
    return int(scene.model.jnt_type[joint]) == SLIDE


def _pushable(scene: Scene, obj: str, target: str) -> bool:
    """A flat, wide object going to a region of the surface it already stands on."""
    lo, hi = scene.box(obj)
    return (scene.is_site(target) and hi[2] - lo[2] < FLAT
            and scene.footprint(obj)[0] > GRIPPER_SPAN
            and abs(scene.pos(target)[2] - lo[2]) < FLAT)


def _push_legs(scene: Scene, obj: str, region: str) -> list[np.ndarray]:
    """Where in the region to push the object (the point of it furthest from other things,
    up to the room the object needs), and the way there: straight, or with one turn (x first
    or y first), whichever passes the fewest times too near other things on the surface."""
    start = scene.pos(obj)[:2]
    room = scene.footprint(obj)[1] / 2 + PUSH_MARGIN
    bottom = scene.box(obj)[0][2]
    boxes = [scene.box(o) for o in [*scene.env.objects_dict, *scene.env.fixtures_dict]
             if o != obj and o in scene.env.obj_body_id]
    boxes = [(lo[:2], hi[:2]) for lo, hi in boxes if hi[2] > bottom + 0.01 and lo[2] < bottom + 0.05]

    def gap(p):
        return min([np.linalg.norm(np.maximum(np.maximum(lo - p, p - hi), 0.0))
                    for lo, hi in boxes] + [room])

    half = np.abs(scene.mat(region) @ scene.site_size(region))[:2] * 0.8  # inside LIBERO's test
    grid = scene.pos(region)[:2] + np.stack(np.meshgrid(*[np.linspace(-1, 1, 5)] * 2), -1
                                            ).reshape(-1, 2) * half
    goal = max(grid, key=lambda p: (gap(p), -np.linalg.norm(p - scene.pos(region)[:2])))

    def hits(legs):
        count, prev = 0, start
        for end in legs:
            n = max(int(np.linalg.norm(end - prev) / PUSH_SAMPLE), 1)
            count += sum(gap(prev + f * (end - prev)) < room for f in np.linspace(0, 1, n + 1))
            prev = end
        return count

    ways = [[goal], [np.array([start[0], goal[1]]), goal], [np.array([goal[0], start[1]]), goal]]
    return min(ways, key=hits)


def _box_gap(lo_a: np.ndarray, hi_a: np.ndarray, lo_b: np.ndarray, hi_b: np.ndarray) -> float:
    """The distance between two axis-aligned boxes (0 where they overlap)."""
    return float(np.linalg.norm(np.maximum(np.maximum(lo_b - hi_a, lo_a - hi_b), 0.0)))


def _overhangs(scene: Scene, obj: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """Boxes of the parts that hang low over the object (an open drawer over a bowl in
    front of it), overlapping it seen from above: the hand coming down to it passes beside
    them, and it cannot be lifted straight up."""
    lo, hi = scene.box(obj)
    return [(a, b) for a, b in scene.part_boxes(obj)
            if hi[2] - 0.005 <= a[2] < hi[2] + OVERHANG  # above it (to within 5 mm)
            and np.all(a[:2] < hi[:2]) and np.all(lo[:2] < b[:2])]


def _withdrawal(scene: Scene, obj: str, grasp: Grasp,
                over: list[tuple[np.ndarray, np.ndarray]]) -> tuple[float, np.ndarray]:
    """How to take the object out from under `over` before lifting it: (the rise that keeps
    it under them, the horizontal shift toward the grip side that takes it clear of them)."""
    lo, hi = scene.box(obj)
    way = grasp.offset[:2] - ((lo + hi) / 2 - scene.pos(obj))[:2]
    way /= np.linalg.norm(way)

    def clear(shift):
        return all(_box_gap(lo[:2] + shift, hi[:2] + shift, a[:2], b[:2]) >= HAND_ROOM
                   for a, b in over)
    shifts = [t * way for t in np.arange(0.0, WITHDRAW_MAX, WITHDRAW_STEP)]
    shift = next((s for s in shifts if clear(s)), shifts[-1])
    rise = min(a[2] for a, _ in over) - hi[2] - UNDER_GAP
    return max(float(rise), 0.0), shift


def plan_goal(scene: Scene, goal: list[str]) -> list[Phase]:
    relation = goal[0]
    if relation == "on" and _pushable(scene, goal[1], goal[2]):
        return push(scene, goal[1], _push_legs(scene, goal[1], goal[2]), lambda: scene.check(goal))
    if relation in ("in", "on"):
        obj, target = goal[1], goal[2]
        drawer = _is_drawer(scene, target)
        if drawer and not scene.check(["open", target]):
            # open it first; the pick is planned once it is open (it may then be in the way)
            return plan_goal(scene, ["open", target])
        over = _overhangs(scene, obj)
        middle = np.mean([(a + b) / 2 for a, b in over], axis=0) if over else None
        grasp = Grasp.plan(scene, obj, wrist_from=middle)
        xy, rest_z = _placement(scene, relation, obj, target)
        bottom = scene.support_top(obj)  # from inside a drawer: above its walls
        into = scene.body_top(scene.model.joint(scene.joint_name(target)).bodyid[0]) if drawer \
            else rest_z()  # into a drawer: over its walls
        travel = max(bottom, rest_z(), into) + CARRY_CLEARANCE + grasp.below
        travel = max(travel, scene.eef_pos()[2] - 0.05)
        withdraw = _withdrawal(scene, obj, grasp, over) if over else None
        return (pick(scene, obj, grasp, travel, withdraw)
                + place(scene, obj, grasp, xy, rest_z, travel))
    if relation in ("open", "close"):
        target = goal[1]
        joint = scene.joint_name(target)
        owner = scene.site_parent(target) if scene.is_site(target) else target
        props = scene.thing(owner).object_properties["articulation"]
        ranges = props["default_open_ranges" if relation == "open" else "default_close_ranges"]
        if scene.model.jnt_type[scene.model.joint(joint).id] == SLIDE:
            return slide(scene, joint, float(np.mean(ranges)), relation == "open",
                         lambda: scene.check(goal))
    if relation in ("turnon", "turnoff"):
        # LIBERO's stoves: on is a positive knob angle, off is back to zero.
        return turn(scene, scene.joint_name(goal[1]), 1.0 if relation == "turnon" else -1.0,
                    lambda: scene.check(goal))
    raise KeyError(f"no skill for goal predicate {goal!r}")
