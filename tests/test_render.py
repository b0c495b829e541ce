"""The render setting (suites/render.py): faithful keeps LIBERO's reflection pass (it moves
pixels); fast changes no physics and draws in its own GL context; the simplified-mesh cache is deterministic and keeps texture coordinates; and the
setting enters the run and demo keys only with cameras, refused with policy_path=."""

from __future__ import annotations

import dataclasses
import re

import mujoco
import numpy as np
import pytest

from harness.common.errors import RetainError
from harness.config.benchmark import resolve, run_key_settings
from harness.data.prepare import demo_spec
from suites import get_suite
from suites.libero import simplify
from suites.libero.env import CAMERAS, RENDER
from suites.render import apply_to_robosuite

SUITE = get_suite("libero")
SPATIAL_TASK = "pick_up_the_black_bowl_between_the_plate_and_the_ramekin_and_place_it_on_the_plate"
BOWL_MESH = "stable_scanned_objects/akita_black_bowl/visual/akita_black_bowl_vis.msh"


def views(env) -> list[np.ndarray]:
    """Both cameras' images of the env's current state, drawn in its own GL context."""
    sim = env.env.sim
    sim._render_context_offscreen.gl_ctx.make_current()
    size = env.env.env.camera_heights[0]
    return [sim.render(width=size, height=size, camera_name=c) for c in CAMERAS.values()]


def test_fast_render_changes_no_physics_draws_simplified_meshes_and_faithful_reflections(tmp_path, monkeypatch):
    """Two envs in one process, as an evaluation holds them: each draws in its own GL context
    (before suites.render made it current, the first-built env's views came out black)."""
    monkeypatch.setenv(simplify.CACHE_ENV, str(tmp_path))
    envs = {mode: SUITE.make_env(SPATIAL_TASK, cameras=True, image_size=64, render=mode)
            for mode in ("faithful", "fast")}
    try:
        faces = {m: e.env.sim.model._model.nmeshface for m, e in envs.items()}
        assert faces["fast"] < faces["faithful"] / 3, faces
        for env in envs.values():
            env.reset(3)
        rng = np.random.default_rng(0)
        for _ in range(8):
            action = rng.uniform(-1, 1, 7)
            obs = {m: e.step(action).obs for m, e in envs.items()}
            assert np.array_equal(envs["fast"].sim_state(), envs["faithful"].sim_state())
            assert np.array_equal(obs["fast"]["state"], obs["faithful"]["state"])
        fast, faithful = (obs[m]["agentview_rgb"].astype(int) for m in ("fast", "faithful"))
        assert 0 < np.abs(fast - faithful).mean() < 8  # apart, and only slightly
        # issue 62 measured LIBERO's images equal to the bit without the reflection pass (12
        # tasks); drawn in the env's own GL context they are not, so faithful keeps it
        assert RENDER["faithful"].reflections
        env = envs["faithful"]
        with_pass = views(env)
        apply_to_robosuite(env.env.sim, dataclasses.replace(RENDER["faithful"], reflections=False))
        moved = int((with_pass[0] != views(env)[0]).any(axis=2).sum())
        assert 0 < moved < 64 * 64 // 20, moved  # at 128 px: 227 of 16384 pixels, mean 1.1/255
    finally:
        for env in envs.values():
            env.close()


def test_simplified_mesh_is_cached_deterministically_and_keeps_its_texture_coordinates(
        tmp_path, monkeypatch):
    from libero.libero import get_libero_path

    source = f"{get_libero_path('assets')}/{BOWL_MESH}"
    copies = []
    for folder in ("a", "b"):
        monkeypatch.setenv(simplify.CACHE_ENV, str(tmp_path / folder))
        copies.append(simplify.simplified_file(source, 2000))
        assert simplify.simplified_file(source, 2000) == copies[-1]  # made once
    a, b = (open(c, "rb").read() for c in copies)
    assert a == b and [p.name for p in (tmp_path / "a").iterdir()] == [copies[0].split("/")[-1]]
    original, simplified = simplify.compiled_mesh(source), simplify.compiled_mesh(copies[0])
    assert len(original.faces) > 40_000 and len(simplified.faces) <= 2000
    # every kept vertex is one of the source's, with its own texture coordinates
    before = np.concatenate([original.vertices, original.texcoords], 1)
    after = np.concatenate([simplified.vertices, simplified.texcoords], 1)
    assert max(np.abs(before - row).max(axis=1).min() for row in after[::40]) < 1e-5
    smaller = simplify.simplified_file(source, 50_000)
    assert smaller is None  # at or under the cap: drawn as it is


def test_render_enters_keys_only_with_cameras_and_is_refused_with_a_checkpoint():
    suite = get_suite("metaworld")
    base, fast = resolve(["PROFILE=tiny"]), resolve(["PROFILE=tiny", "render=fast"])
    assert run_key_settings(base) == run_key_settings(fast)  # no cameras: nothing drawn
    task = base.foundation_tasks[0]
    assert demo_spec(base, suite, task, "demo").key() == demo_spec(fast, suite, task, "demo").key()
    with_cameras = resolve(["PROFILE=tiny", "cameras=true"])
    fast_cameras = resolve(["PROFILE=tiny", "cameras=true", "render=fast"])
    assert "render" not in run_key_settings(with_cameras)  # faithful: keys made before stay
    assert run_key_settings(fast_cameras)["render"] == "fast"
    assert demo_spec(with_cameras, suite, task, "demo").key() != \
        demo_spec(fast_cameras, suite, task, "demo").key()
    with pytest.raises(RetainError, match=re.escape("bad value 'quick' for render")):
        resolve(["PROFILE=tiny", "render=quick"])
    with pytest.raises(RetainError, match="render=fast with policy_path=ckpt: a published"):
        resolve(["PROFILE=tiny", "render=fast", "policy_path=ckpt"])
    with pytest.raises(RetainError, match="render=fast for suite 'metaworld-lerobot', which "
                                          "draws its own images only: leave render=faithful"):
        demo_spec(fast_cameras, get_suite("metaworld-lerobot"), task, "demo")


def test_metaworld_fast_draws_without_shadows_or_multisampling_and_so_do_its_videos():
    suite = get_suite("metaworld")
    task = suite.task_names()[0]
    envs = {m: suite.make_env(task, cameras=True, image_size=64, render=m)
            for m in ("faithful", "fast")}
    try:
        images = {m: e.reset(0)["agentview_rgb"].astype(int) for m, e in envs.items()}
        assert envs["fast"]._env.model.vis.quality.offsamples == 0
        assert not envs["fast"]._renderer.scene.flags[mujoco.mjtRndFlag.mjRND_SHADOW]
        assert 0 < np.abs(images["fast"] - images["faithful"]).mean() < 12
        for mode, env in envs.items():  # a video frame is drawn in the env's mode: it is near
            # its own mode's observation (a few dozen pixels apart: the state is set anew)
            frame = env.render_state(env.view_state(), "", 64).astype(int)
            other = images["fast" if mode == "faithful" else "faithful"]
            assert np.abs(frame - images[mode]).mean() < np.abs(frame - other).mean() / 5, mode
    finally:
        for env in envs.values():
            env.close()


@pytest.mark.slow
def test_every_libero_mesh_file_simplifies_and_compiles(tmp_path, monkeypatch):
    """Every mesh file of LIBERO's assets and robosuite's Panda, at render=fast's cap: a copy
    MuJoCo compiles, with fewer faces than its source (seams may stop it above the cap), every
    vertex one of the source's with its texture coordinates."""
    from pathlib import Path

    import robosuite
    from libero.libero import get_libero_path

    monkeypatch.setenv(simplify.CACHE_ENV, str(tmp_path))
    roots = [Path(get_libero_path("assets")),
             Path(robosuite.__file__).parent / "models/assets/robots/panda"]
    files = sorted(str(p) for root in roots for p in root.rglob("*")
                   if p.suffix in (".msh", ".obj", ".stl"))
    assert len(files) > 300
    cap, simplified = RENDER["fast"].mesh_faces, 0
    for source in files:
        copy = simplify.simplified_file(source, cap)
        if copy is None:
            continue
        simplified += 1
        original, mesh = simplify.compiled_mesh(source), simplify.compiled_mesh(copy)
        assert len(mesh.faces) < len(original.faces), source
        assert len(mesh.texcoords) == (len(mesh.vertices) if len(original.texcoords) else 0)
        ours, theirs = (np.concatenate([m.vertices, m.texcoords], 1) if len(m.texcoords)
                        else m.vertices for m in (mesh, original))
        ours = ours[::97]
        scale = np.abs(original.vertices).max()
        worst = max(np.abs(theirs - row).max(axis=1).min() for row in ours)
        assert worst < 1e-5 * max(scale, 1), (source, worst)
    assert simplified > 20
