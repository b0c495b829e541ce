"""From one BDDL goal predicate to a skill plan, using the scene as it is now."""

from __future__ import annotations

import numpy as np

from suites.libero.experts.scene import Scene
from suites.libero.experts.skills import Grasp, Phase, pick, place, slide, turn

CARRY_CLEARANCE = 0.07  # the carried object's bottom above the higher of start and goal surface
SLIDE = 2  # MuJoCo's mjJNT_SLIDE
RELEASE_GAP = 0.012  # the object's bottom above its resting surface when the hand opens


def _placement(scene: Scene, relation: str, target: str):
    """(xy function, resting-height function) for putting something in/on `target`."""
    if scene.is_site(target):
        size = scene.site_size(target)
        xy = lambda: scene.pos(target)[:2]  # noqa: E731
        if _is_drawer(scene, target):  # drop it in just above the drawer region's centre
            return xy, lambda: scene.pos(target)[2] + RELEASE_GAP
        if relation == "in":
            return xy, lambda: scene.pos(target)[2] + size[2] + RELEASE_GAP
        return xy, lambda: scene.pos(target)[2] + RELEASE_GAP
    return (lambda: scene.pos(target)[:2]), lambda: scene.box(target)[1][2] + RELEASE_GAP


def _is_drawer(scene: Scene, target: str) -> bool:
    """A region that moves on a slide joint (inside a drawer), not one on a free object."""
    if not scene.is_site(target) or not scene.env.object_sites_dict[target].joints:
        return False
    joint = scene.model.joint(scene.joint_name(target)).id
    return int(scene.model.jnt_type[joint]) == SLIDE


def plan_goal(scene: Scene, goal: list[str]) -> list[Phase]:
    relation = goal[0]
    if relation in ("in", "on"):
        obj, target = goal[1], goal[2]
        grasp = Grasp.plan(scene, obj)
        xy, rest_z = _placement(scene, relation, target)
        bottom = scene.support_top(obj)  # from inside a drawer: above its walls
        travel = max(bottom, rest_z()) + CARRY_CLEARANCE + grasp.below
        travel = max(travel, scene.eef_pos()[2] - 0.05)
        first = []
        if _is_drawer(scene, target) and not scene.check(["open", target]):
            first = plan_goal(scene, ["open", target])
        return first + pick(scene, obj, grasp, travel) + place(scene, obj, grasp, xy, rest_z, travel)
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
