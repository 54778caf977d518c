"""Visual geometry (issue 24): drawn, never colliding, no mass, physics bit-identical."""

from __future__ import annotations

import socket

import mujoco
import numpy as np
import pytest

import beavr_sim.envs.beavr_env as beavr_env
from beavr_sim.assets import assets_dir
from beavr_sim.envs.cameras import OffscreenCameras, render_option
from beavr_sim.envs.scene import build_scene_spec
from beavr_sim.robots import mesh_build
from beavr_sim.robots.embodiment import make_embodiment
from beavr_sim.robots.visuals import (
    COLLISION_GROUP,
    VISUAL_GROUP,
    add_visuals,
    strip_visuals,
)
from beavr_sim.teleop.__main__ import build_parser
from beavr_sim.teleop.session import SessionOptions, build_loop

EMBODIMENTS = ("xarm7_leap_right", "xarm7_leap_bimanual", "rx1")
BODY_FIELDS = (
    "body_mass",
    "body_inertia",
    "body_ipos",
    "body_iquat",
    "body_subtreemass",
    "body_pos",
    "body_quat",
    "dof_armature",
    "dof_damping",
    "jnt_range",
    "actuator_gainprm",
)


def _model(embodiment: str, visuals: bool) -> mujoco.MjModel:
    return build_scene_spec(make_embodiment(embodiment), 48, 64, visuals=visuals).compile()


@pytest.mark.parametrize("embodiment", EMBODIMENTS)
def test_visual_geoms_collide_with_nothing_and_weigh_nothing(embodiment):
    spec = build_scene_spec(make_embodiment(embodiment), 48, 64, visuals=True)
    m = spec.compile()
    visual = m.geom_group == VISUAL_GROUP
    assert visual.sum() >= 20
    assert (m.geom_contype[visual] == 0).all() and (m.geom_conaffinity[visual] == 0).all()
    robot = np.array([m.body(m.geom_bodyid[g]).name.count("/") > 0 for g in range(m.ngeom)])
    colliding = (m.geom_contype != 0) | (m.geom_conaffinity != 0)
    # every colliding robot geom is in the collision group, hidden by the views' option
    assert (m.geom_group[robot & colliding] == COLLISION_GROUP).all()
    assert not render_option().geomgroup[COLLISION_GROUP]
    assert render_option(show_collision=True).geomgroup[COLLISION_GROUP]
    meshes = (m.geom_type[visual] == mujoco.mjtGeom.mjGEOM_MESH).sum()
    # per arm 8 xArm links, per hand 17 LEAP links; the RX-1 arms are primitives
    assert meshes == {"xarm7_leap_right": 25, "xarm7_leap_bimanual": 50, "rx1": 34}[embodiment]

    # Masses, inertias and every physics array equal those of the compile without visuals,
    # and of this spec with its visuals stripped again.
    plain = _model(embodiment, visuals=False)
    strip_visuals(spec)
    stripped = spec.compile()
    for field in BODY_FIELDS:
        np.testing.assert_array_equal(getattr(m, field), getattr(plain, field), err_msg=field)
        np.testing.assert_array_equal(getattr(stripped, field), getattr(plain, field))
    assert stripped.ngeom == plain.ngeom and stripped.nmesh == 0


def test_unknown_part_lists_the_parts():
    with pytest.raises(ValueError, match=r"xarm7_leap/xarm7\.xml"):
        add_visuals(mujoco.MjSpec(), "xarm8.xml")


def _replay(task: str, embodiment: str | None, monkeypatch, visuals: bool) -> np.ndarray:
    real = build_scene_spec

    def scene(*args, **kwargs):
        return real(*args, **{**kwargs, "visuals": visuals})

    monkeypatch.setattr(beavr_env, "build_scene_spec", scene)
    options = SessionOptions(
        task=task,
        embodiment=embodiment,
        source="trace",
        viser=False,
        headless=True,
        progress=False,
    )
    loop = build_loop(options)
    loop.run()
    env = loop.twin.env
    assert (env.model.geom_group == VISUAL_GROUP).any() == visuals
    q = env.data.qpos.copy()
    env.close()
    return q


@pytest.mark.parametrize("embodiment", [None])  # rx1 checked by hand: identical too
def test_bundled_trace_replays_bit_identically_with_and_without_visuals(embodiment, monkeypatch):
    with_visuals = _replay("PickupBox", embodiment, monkeypatch, visuals=True)
    without = _replay("PickupBox", embodiment, monkeypatch, visuals=False)
    assert with_visuals.tobytes() == without.tobytes()


def test_cameras_draw_the_visual_meshes_not_the_collision_geometry():
    env = beavr_env.BeavrEnv(task="PickupBox", camera_height=48, camera_width=64)
    try:
        env.reset(seed=0)
        shown = OffscreenCameras(env.model, 48, 64).render(env.data, "front")
        collision = OffscreenCameras(env.model, 48, 64, show_collision=True)
        with_collision = collision.render(env.data, "front")
        hidden = OffscreenCameras(env.model, 48, 64)
        hidden.option.geomgroup[VISUAL_GROUP] = 0
        no_robot = hidden.render(env.data, "front")
        assert np.abs(shown.astype(int) - no_robot).sum() > 1000  # the visuals are drawn
        assert np.abs(shown.astype(int) - with_collision).sum() > 100
    finally:
        env.close()


def test_generated_meshes_are_the_committed_ones_and_deterministic():
    if not mesh_build.DEFAULT_REFERENCE.is_dir():
        pytest.skip(f"reference models not found at {mesh_build.DEFAULT_REFERENCE}")
    first = mesh_build.build()
    second = mesh_build.build()
    assert first == second
    committed = sorted((assets_dir() / "meshes").rglob("*.stl"))
    assert sorted(first) == committed
    for path, data in first.items():
        assert path.read_bytes() == data, (
            f"{path} is stale: python -m beavr_sim.robots.mesh_build build"
        )
    total = sum(p.stat().st_size for p in committed)
    assert total < 4_000_000


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_show_collision_option_and_toggle():
    pytest.importorskip("viser", reason="viser (extra 'viz') not installed")
    from beavr_sim.viz.twin_view import TwinView

    args = build_parser().parse_args(["--task", "PickupBox", "--show-collision"])
    assert SessionOptions.from_args(args).show_collision
    args = build_parser().parse_args(["--task", "PickupBox"])
    assert not SessionOptions.from_args(args).show_collision

    model = _model("xarm7_leap_right", visuals=True)
    view = TwinView(model, port=_free_port())
    try:
        assert view.collision_handles
        assert not any(h.visible for h in view.collision_handles)
        meshes = (model.geom_type == mujoco.mjtGeom.mjGEOM_MESH).sum()
        assert len(view.geom_handles) > meshes
        view.collision_checkbox.value = True
        view.set_show_collision(True)
        assert all(h.visible for h in view.collision_handles)
        view.set_show_collision(False)
        assert not any(h.visible for h in view.collision_handles)
    finally:
        view.close()
