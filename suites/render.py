"""How a suite draws its camera views: the `render` setting.

`faithful` (the default) draws the suite's own images, as before the setting existed (LIBERO's
reflection pass, thought free, moves pixels: tests/test_render.py). `fast` trades a small,
measured image difference for CPU time: no shadows or multisampling (and on Meta-World and
bimanual no reflections), and on LIBERO its heavy visual meshes swapped for simplified copies
(suites/libero/simplify.py). A policy trained on one mode's images is
evaluated on the same mode's: the setting enters the run key and the demo caches whenever
cameras are on (harness/config/benchmark.py, harness/data/prepare.py).
"""

from __future__ import annotations

from dataclasses import dataclass

RENDER_MODES = ("faithful", "fast")


@dataclass(frozen=True)
class RenderSettings:
    """What a suite's renderer draws; applied to the model and scene before a view is drawn."""

    reflections: bool = True
    shadows: bool = True
    samples: int | None = None  # multisampling's samples a pixel; 0: off; None: the model's own
    mesh_faces: int = 0  # each visual mesh capped at this many faces; 0: meshes as they are


FAST = RenderSettings(reflections=False, shadows=False, samples=0)
MODES = {"faithful": RenderSettings(), "fast": FAST}  # a suite with no mode of its own (LIBERO's)


def check_render(mode: str) -> str:
    """The mode, or a one-line ValueError naming the valid ones."""
    if mode not in RENDER_MODES:
        raise ValueError(f"bad value {mode!r} for render: expected one of {', '.join(RENDER_MODES)}")
    return mode


def apply_to_model(model, settings: RenderSettings) -> None:
    """Model-level settings, read when a GL context is made (multisampling): call before."""
    if settings.samples is not None:
        model.vis.quality.offsamples = settings.samples


def apply_to_scene(scene, settings: RenderSettings) -> None:
    """Scene flags, read at every draw: a renderer keeps them until changed."""
    import mujoco

    flags = mujoco.mjtRndFlag
    scene.flags[flags.mjRND_REFLECTION] = int(settings.reflections)
    scene.flags[flags.mjRND_SHADOW] = int(settings.shadows)


def apply_to_robosuite(sim, settings: RenderSettings) -> None:
    """The settings on a robosuite sim's offscreen renderer (made by robosuite at a reset, and
    again after a reload): its scene flags, its GL context remade where the multisampling
    asked for differs from the one it was made with, and that context made current before
    each draw (`_own_context_first`)."""
    context = sim._render_context_offscreen
    if context is None:
        return
    _own_context_first(context)
    apply_to_scene(context.scn, settings)
    model = sim.model._model
    before = model.vis.quality.offsamples
    apply_to_model(model, settings)
    if model.vis.quality.offsamples != before:
        context.gl_ctx.make_current()
        context.con.free()
        context._set_mujoco_context_and_buffers()


def render_argument(mode: str) -> dict[str, str]:
    """`Suite.make_env`'s keyword for a mode: none for faithful, so that a suite written
    without the setting (a user's, the LeRobot-protocol suites) still builds its envs."""
    return {} if mode == "faithful" else {"render": mode}


def check_suite_renders(suite, mode: str) -> None:
    """A one-line ValueError where `mode` is not faithful and the suite's `make_env` takes no
    `render` (it would draw its own images under another mode's caches)."""
    import inspect

    if mode != "faithful" and "render" not in inspect.signature(suite.make_env).parameters:
        raise ValueError(f"render={mode} for suite {suite.name!r}, which draws its own images "
                         f"only: leave render=faithful")


def _own_context_first(context) -> None:
    """Make a robosuite renderer draw in its own GL context. robosuite draws in whichever
    context is current, and every env has its own: with two LIBERO envs in a process (an
    evaluation holds one per task) the first env's views came out black or 52.8/255 apart
    on average (tests/test_render.py)."""
    if getattr(context, "_retain_own_context", False):
        return
    draw = context.render

    def render(*args, **kwargs):
        context.gl_ctx.make_current()
        return draw(*args, **kwargs)

    context.render, context._retain_own_context = render, True
