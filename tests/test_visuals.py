"""Visual geometry (issue 24): drawn, never colliding, no mass, physics bit-identical."""

from __future__ import annotations

import socket

import mujoco
import numpy as np
import pytest

import beavr_sim.envs.beavr_env as beavr_env
from beavr_sim.assets import assets_dir, mjcf_path
from beavr_sim.envs.cameras import OffscreenCameras, render_option
from beavr_sim.envs.scene import build_scene_spec
from beavr_sim.robots import mesh_build
from beavr_sim.robots.embodiment import make_embodiment
from beavr_sim.robots.meshes import Mesh, read_stl
from beavr_sim.robots.visuals import (
    COLLISION_GROUP,
    VISUAL_GROUP,
    XARM_GREY,
    XARM_WHITE,
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
    # per arm 8 xArm links (7 of them in two parts: shell and joint caps), per hand 17 LEAP
    # links; the RX-1 arms are primitives
    assert meshes == {"xarm7_leap_right": 32, "xarm7_leap_bimanual": 64, "rx1": 34}[embodiment]

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
        model, data = env.render_model, env.render_data()
        shown = OffscreenCameras(model, 48, 64).render(data, "front")
        collision = OffscreenCameras(model, 48, 64, show_collision=True)
        with_collision = collision.render(data, "front")
        hidden = OffscreenCameras(model, 48, 64)
        hidden.option.geomgroup[VISUAL_GROUP] = 0
        no_robot = hidden.render(data, "front")
        assert np.abs(shown.astype(int) - no_robot).sum() > 1000  # the visuals are drawn
        assert np.abs(shown.astype(int) - with_collision).sum() > 100
        np.testing.assert_array_equal(env.render_camera("front"), shown)  # the env's camera
    finally:
        env.close()


@pytest.mark.parametrize("embodiment", ["xarm7_leap_bimanual", "rx1"])
def test_the_env_steps_a_model_without_visuals_and_draws_one_with_them(embodiment):
    """Physics steps the collision-only model (visual geoms cost the collision phase time
    even though they never collide); the render model adds the visual geoms only, and its
    data follows the physics state body for body."""
    env = beavr_env.BeavrEnv(task="Pour", embodiment=embodiment)
    try:
        env.reset(seed=1)
        plain = _model(embodiment, visuals=False)
        assert not (env.model.geom_group == VISUAL_GROUP).any()
        assert env.model.ngeom > plain.ngeom  # the task's objects
        render = env.render_model
        assert (render.geom_group == VISUAL_GROUP).any() and render.ngeom > env.model.ngeom
        for size in ("nbody", "nq", "nv", "nmocap", "ncam", "njnt", "nu"):
            assert getattr(render, size) == getattr(env.model, size), size
        rng = np.random.default_rng(0)
        for _ in range(3):
            env.step(env.agent_pos + rng.normal(0, 0.05, env.agent_pos.shape).astype(np.float32))
            shown = env.render_data()
            # The physics data's poses are from the start of its last substep (mj_step
            # integrates after computing them): recompute them at its current positions.
            physics = mujoco.MjData(env.model)
            physics.qpos[:], physics.mocap_pos[:] = env.data.qpos, env.data.mocap_pos
            physics.mocap_quat[:] = env.data.mocap_quat
            mujoco.mj_kinematics(env.model, physics)
            mujoco.mj_comPos(env.model, physics)
            mujoco.mj_camlight(env.model, physics)
            np.testing.assert_array_equal(shown.qpos, env.data.qpos)
            np.testing.assert_allclose(shown.xpos, physics.xpos, atol=1e-12)
            np.testing.assert_allclose(shown.xquat, physics.xquat, atol=1e-12)
            np.testing.assert_allclose(shown.cam_xpos, physics.cam_xpos, atol=1e-12)
            np.testing.assert_allclose(shown.mocap_pos, env.data.mocap_pos)
        assert env.render_model is render  # compiled once
    finally:
        env.close()


def test_generated_meshes_are_the_committed_ones_and_deterministic(capsys):
    if not mesh_build.DEFAULT_REFERENCE.is_dir():
        pytest.skip(f"reference models not found at {mesh_build.DEFAULT_REFERENCE}")
    first = mesh_build.build()
    committed = sorted((assets_dir() / "meshes").rglob("*.stl"))
    assert sorted(first) == committed
    for path, data in first.items():
        assert path.read_bytes() == data, (
            f"{path} is stale: python -m beavr_sim.robots.mesh_build build"
        )
    # A second build (the CLI's check) gives the same bytes again: deterministic.
    assert mesh_build.main(["check"]) == 0, capsys.readouterr().out


def test_visual_meshes_fit_the_asset_budget():
    files = sorted((assets_dir() / "meshes").rglob("*.stl"))
    assert sum(p.stat().st_size for p in files) < 10_000_000
    # what one arm and hand draw: the render cost (docs/models.md "Visual geometry")
    assert sum(len(read_stl(p).faces) for p in files) < 40_000


def _stl(name: str) -> Mesh:
    return read_stl(assets_dir() / "meshes" / f"{name}.stl")


def test_xarm_links_have_white_shells_and_grey_joint_caps():
    m = _model("xarm7_leap_right", visuals=True)
    for i in range(1, 8):
        body = m.body(f"right/link{i}").id
        rgba = {
            tuple(m.geom_rgba[g])
            for g in range(m.ngeom)
            if m.geom_bodyid[g] == body and m.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH
        }
        assert rgba == {tuple(np.float32(XARM_WHITE)), tuple(np.float32(XARM_GREY))}, i
    # The caps are round patches about the joints that cross the arm (2, 4, 6), on both
    # links each joins; link7's grey part is the flange.
    spec = mujoco.MjSpec.from_file(str(mjcf_path("xarm7_leap/xarm7.xml")))
    axes = mesh_build.crossing_axes(spec)
    assert [b for b, a in axes.items() if a] == [f"link{i}" for i in range(1, 7)]
    for body in (f"link{i}" for i in range(1, 7)):
        cap, shell = _stl(f"xarm7/{body}_housing"), _stl(f"xarm7/{body}_shell")
        assert len(cap.faces) < len(shell.faces) / 4
        ((origin, axis),) = axes[body]
        rel = cap.vertices - origin
        radial = np.linalg.norm(rel - np.outer(rel @ axis, axis), axis=1)
        assert radial.max() <= mesh_build.CAP_RADIUS + mesh_build.CELL["xarm7"], body
        # the cap's rim is shared with the shell: no crack between the two parts
        rim = radial > mesh_build.CAP_RADIUS - 1e-6
        shell_points = {tuple(v) for v in shell.vertices.astype(np.float32)}
        assert rim.any() and all(
            tuple(v) in shell_points for v in cap.vertices[rim].astype(np.float32)
        )


def _gap_to_palm(side: str, body: str, mesh: str) -> np.ndarray:
    """Per vertex of ``mesh`` on ``body`` (zero pose): its distance to the nearest palm vertex."""
    m = mujoco.MjModel.from_xml_path(str(mjcf_path(f"xarm7_leap/leap_{side}.xml")))
    d = mujoco.MjData(m)
    mujoco.mj_kinematics(m, d)
    R_palm, p_palm = d.body("palm").xmat.reshape(3, 3), d.body("palm").xpos
    R = R_palm.T @ d.body(body).xmat.reshape(3, 3)
    p = R_palm.T @ (d.body(body).xpos - p_palm)
    points = _stl(f"leap/{mesh}").vertices @ R.T + p
    palm = _stl(f"leap/palm_{side}").vertices
    return np.sqrt(((points[:, None] - palm[None]) ** 2).sum(axis=-1)).min(axis=1)


def test_left_thumb_base_meets_the_mirrored_palm_as_on_the_right():
    right = _gap_to_palm("right", "thumb_base", "thumb_base")
    left = _gap_to_palm("left", "thumb_base", "thumb_base")
    # Before the fix the left thumb base was 6.8 mm from the palm at its nearest, none of
    # it within 4 mm (the palm was mirrored onto the finger mounts, 29 mm across).
    assert right.min() < 0.002 and left.min() < 0.002
    near_right, near_left = (right < 0.004).mean(), (left < 0.004).mean()
    assert 0.5 * near_right < near_left < 2 * near_right
    # and the finger modules sit on their blocks alike on both hands
    for finger in ("index", "middle", "ring"):
        r = _gap_to_palm("right", f"{finger}_base", "finger_base")
        lf = _gap_to_palm("left", f"{finger}_base", "finger_base")
        assert abs((r < 0.004).mean() - (lf < 0.004).mean()) < 0.05, finger


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


def test_camera_sets_compile_the_render_model_only_for_a_camera():
    from beavr_sim.datasets.recorder import CameraSet

    env = beavr_env.BeavrEnv(task="PickupBox")
    try:
        env.reset(seed=0)
        none = CameraSet.of_env(env, (), 48, 64)
        assert none.render_env(env) == {} and env._render_model is None  # state-only: no cost
        front = CameraSet.of_env(env, ("front",), 48, 64)
        assert env._render_model is not None
        assert front.render_env(env)["front"].shape == (48, 64, 3)
        front.close()
        with pytest.raises(ValueError, match="need a model"):
            CameraSet(None, ("front",), 48, 64)
    finally:
        env.close()
