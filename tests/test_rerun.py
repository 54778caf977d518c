"""Rerun logging of a teleop session (``--rerun F.rrd``): the file verifies with the rerun CLI
and holds the expected entities, with one row per tick where there should be."""

from __future__ import annotations

import dataclasses
import os
import shutil
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest

rr = pytest.importorskip("rerun")

from beavr_sim.teleop.session import SessionOptions, build_loop, run_session  # noqa: E402

SECONDS = 3.0


def _rerun_cli() -> str:
    cli = Path(sys.executable).parent / "rerun"
    found = str(cli) if cli.is_file() else shutil.which("rerun")
    assert found, "the rerun CLI (installed with rerun-sdk) is missing"
    return found


def _verify(path: Path) -> None:
    result = subprocess.run(
        [_rerun_cli(), "rrd", "verify", str(path)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert result.returncode == 0, f"rerun rrd verify failed:\n{result.stdout}\n{result.stderr}"


def _contents(path: Path) -> tuple[dict[str, int], dict[str, list]]:
    """Rows per entity path (on the timelines: static rows left out), and each entity's
    record batches (static and temporal)."""
    rows: dict[str, int] = defaultdict(int)
    batches: dict[str, list] = defaultdict(list)
    for chunk in rr.chunk.RrdReader(path).stream().to_chunks():
        rows[chunk.entity_path] += 0 if chunk.is_static else chunk.num_rows
        batches[chunk.entity_path].append(chunk.to_record_batch())
    return dict(rows), dict(batches)


def _column(batches: list, name: str) -> list:
    """The values of one column over the batches that have it (one list per row)."""
    return [v for rb in batches if name in rb.schema.names for v in rb.column(name).to_pylist()]


def _options(tmp_path: Path, **kwargs) -> SessionOptions:
    return SessionOptions(
        task="PickupBox", source="trace", viser=False, headless=True, progress=False, **kwargs
    )


def test_session_log_verifies_and_holds_hands_targets_joints_images(tmp_path):
    path = tmp_path / "session.rrd"
    options = _options(tmp_path, rerun=path, rerun_image_hz=5.0, max_seconds=SECONDS)
    summary = run_session(options)
    assert path.is_file()
    _verify(path)
    rows, batches = _contents(path)
    ticks = summary.ticks
    assert ticks == round(SECONDS * 30)
    per_tick = [
        "/robot/joints/right/joint1/position",
        "/robot/joints/right/joint1/command",
        "/robot/joints/right/leap_15/position",
        "/robot/joints/right/leap_15/command",
        "/robot/hold/right",
        "/guard/blocked",
        "/task/success",
        "/task/failure",
        "/world/targets/right/reached",
    ]
    for entity in per_tick:
        assert rows.get(entity) == ticks, (entity, rows.get(entity))
    # The trace's hand arrives (nearly) every tick; targets once the mapping is anchored.
    for entity in (
        "/world/hands/right/keypoints",
        "/world/targets/right/arm",
        "/world/targets/right/fingers",
        "/world/targets/right/skeleton",
        "/latency/ms",
    ):
        assert rows.get(entity, 0) > ticks // 2, (entity, rows.get(entity))
    # 5 images a second of session time, rendered small.
    assert abs(rows.get("/camera/front", 0) - SECONDS * 5) <= 1
    # Static: the session's task, embodiment and joint names; the hand skeleton's bones.
    session = batches["/session"]
    assert _column(session, "task") == [["PickupBox"]]
    assert _column(session, "joint_names")[0][0] == "right/joint1"
    assert any("AnnotationContext:context" in rb.schema.names for rb in batches["/world"])

    # Values: the logged joint positions are the twin's, one per tick in time order.
    q = np.array(_column(batches["/robot/joints/right/joint1/position"], "Scalars:scalars"))
    t = np.array(_column(batches["/task/success"], "tick"))
    assert q.shape == (ticks, 1) and np.ptp(q) > 1e-3, "the arm did not move in the log"
    assert sorted(t.tolist()) == list(range(ticks))
    keypoints = batches["/world/hands/right/keypoints"]
    positions = _column(keypoints, "Points3D:positions")
    assert all(len(p) == 26 for p in positions)  # the trace tracks every joint
    assert np.isfinite(np.array(positions, dtype=float)).all()


def test_guard_blocks_holds_and_success_are_events(tmp_path):
    """Events go to text logs: a guard block at warn level, the release, a new episode."""
    from beavr_sim.viz.rerun_log import RerunLogger

    path = tmp_path / "events.rrd"
    loop = build_loop(_options(tmp_path))
    try:
        with RerunLogger(path, loop, image_hz=0) as logger:
            loop.listeners.append(logger)
            for _ in range(6):
                loop.tick()
            apply = loop.twin.apply

            def blocked(commands):  # the collision guard refuses the right arm's command
                state = apply(commands)
                return dataclasses.replace(
                    state, guard_blocked=True, guard_blocked_effectors=("right",)
                )

            loop.twin.apply = blocked
            loop.tick()
            loop.twin.apply = apply
            loop.tick()  # not blocked: released
            loop.reset(loop.seed)  # a new episode: the virtual clock starts over
            loop.tick()
    finally:
        loop.source.close()
        loop.twin.env.close()
    _verify(path)
    _, batches = _contents(path)
    guard = batches["/guard/events"]
    texts = [v[0] for v in _column(guard, "TextLog:text")]
    levels = [v[0] for v in _column(guard, "TextLog:level")]
    assert texts == ["collision guard blocked the command of right", "guard released"]
    assert levels == ["WARN", "INFO"]
    assert (
        _column(batches["/guard/blocked"], "Scalars:scalars") == [[0.0]] * 6 + [[1.0]] + [[0.0]] * 2
    )
    events = [v[0] for v in _column(batches["/events"], "TextLog:text")]
    assert "episode 1 starts (reset)" in events
    # Session time keeps going across the reset (the tick's own clock starts over).
    times = sorted(d.total_seconds() for d in _column(batches["/guard/blocked"], "session_time"))
    assert len(times) == 9 and (np.diff(times) > 0).all(), times
    assert times[-1] == pytest.approx(8 * loop.dt, abs=1e-5)


def _quat_xyzw(wxyz) -> np.ndarray:
    return np.asarray(wxyz, dtype=float)[[1, 2, 3, 0]]


def test_the_twin_in_3d_meshes_once_and_body_poses_per_tick(tmp_path):
    """Every visual mesh once (static ``Mesh3D`` with the model mesh's vertex and face
    counts) under its body's entity, whose pose is logged each tick; the collision geometry
    under its own path; the static bodies' poses once."""
    import mujoco

    from beavr_sim.viz.rerun_log import COLLISION_PATH, TWIN_PATH, RerunLogger, geom_entity

    path = tmp_path / "twin.rrd"
    loop = build_loop(_options(tmp_path))
    ticks = 5
    try:
        model, data = loop.twin.env.render_model, loop.twin.env.data
        with RerunLogger(path, loop, image_hz=0) as logger:
            loop.listeners.append(logger)
            for _ in range(ticks):
                loop.tick()
        link = model.body("right/link1").id
        xpos, xquat = data.xpos[link].copy(), data.xquat[link].copy()
    finally:
        loop.source.close()
        loop.twin.env.close()
    _verify(path)
    rows, batches = _contents(path)
    assert logger.twin_errors == 0
    escape = rr.escape_entity_path_part
    twin, collision = f"/{TWIN_PATH}/", f"/{COLLISION_PATH}/"

    # Each visual mesh geom: one static Mesh3D with its mesh's vertex and face counts.
    meshes = [
        g
        for g in range(model.ngeom)
        if model.geom_type[g] == mujoco.mjtGeom.mjGEOM_MESH and model.geom_group[g] == 2
    ]
    assert meshes
    for g in meshes:
        entity = f"{twin}{geom_entity(model, g)}"
        assert entity in batches and rows[entity] == 0, entity  # static only
        vertices = _column(batches[entity], "Mesh3D:vertex_positions")
        faces = _column(batches[entity], "Mesh3D:triangle_indices")
        k = model.geom_dataid[g]
        assert len(vertices) == 1 and len(vertices[0]) == model.mesh_vertnum[k], entity
        assert len(faces[0]) == model.mesh_facenum[k], entity
        offset = _column(batches[entity], "Transform3D:translation")[0][0]
        np.testing.assert_allclose(offset, model.geom_pos[g], atol=1e-6)

    # A moving body: its world pose every tick, the last one the twin's.
    body = f"{twin}{escape('right/link1')}"
    assert rows[body] == ticks
    translation = _column(batches[body], "Transform3D:translation")
    quaternion = _column(batches[body], "Transform3D:quaternion")
    np.testing.assert_allclose(translation[-1][0], xpos, atol=1e-6)
    q = np.array(quaternion[-1][0])
    assert min(np.abs(q - _quat_xyzw(xquat)).max(), np.abs(q + _quat_xyzw(xquat)).max()) < 1e-6
    # The collision geometry: its own subtree, the same bodies' poses, wireframes.
    assert rows[f"{collision}{escape('right/link1')}"] == ticks
    collision_geoms = [e for e in batches if e.startswith(collision) and e.count("/") > 3]
    assert collision_geoms and not any(e.startswith(twin) and "collision" in e for e in batches)
    # A body that never moves (the table): its pose once, static.
    statics = [e for e in batches if e.startswith(twin) and e.count("/") == 3 and not rows[e]]
    assert statics and all(
        "Transform3D:translation" in rb.schema.names for e in statics for rb in batches[e]
    )


def test_twin_errors_in_the_tick_path_are_counted_never_raised(tmp_path):
    from beavr_sim.viz.rerun_log import RerunLogger

    path = tmp_path / "twin_errors.rrd"
    loop = build_loop(_options(tmp_path))
    try:
        with RerunLogger(path, loop, image_hz=0, twin_hz=1000) as logger:
            logger._twin_bodies = np.array([10**6])  # not a body: every tick fails
            for _ in range(3):
                logger(loop.tick())
        assert logger.twin_errors == 3
        assert not loop.listener_errors
        with RerunLogger(tmp_path / "no_twin.rrd", loop, image_hz=0, twin_hz=0) as quiet:
            logger_ticks = loop.tick()
            quiet(logger_ticks)
        assert quiet.poses is None
    finally:
        loop.source.close()
        loop.twin.env.close()
    _, batches = _contents(path)
    events = [v[0] for v in _column(batches["/events"], "TextLog:text")]
    assert any("the twin's poses not logged" in e for e in events), events
    assert any("3 errors in all" in e for e in events), events
    _, batches = _contents(tmp_path / "no_twin.rrd")
    assert not any(e.startswith("/world/twin") for e in batches)
    with pytest.raises(ValueError, match="twin rate"):
        RerunLogger(tmp_path / "bad.rrd", loop, image_hz=0, twin_hz=-1)


def test_bad_rerun_paths_are_clear_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        _options(tmp_path, rerun=tmp_path / "missing" / "f.rrd")
    with pytest.raises(ValueError, match=r"\.rrd"):
        _options(tmp_path, rerun=tmp_path / "f.txt")
    (tmp_path / "d.rrd").mkdir()
    with pytest.raises(ValueError, match="is a folder"):
        _options(tmp_path, rerun=tmp_path / "d.rrd")
    with pytest.raises(ValueError, match="rerun-image-hz"):
        _options(tmp_path, rerun=tmp_path / "f.rrd", rerun_image_hz=-1)
    with pytest.raises(ValueError, match="rerun-twin-hz"):
        _options(tmp_path, rerun=tmp_path / "f.rrd", rerun_twin_hz=float("nan"))
    assert _options(tmp_path, rerun=tmp_path / "f.rrd", multiprocess=True).rerun is not None


def test_cli_rerun_flag_writes_a_verified_log(tmp_path):
    path = tmp_path / "cli.rrd"
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    result = subprocess.run(
        [
            sys.executable,
            "-m",
            "beavr_sim.teleop",
            "--task",
            "pickup_box",
            "--source",
            "trace",
            "--headless",
            "--no-viser",
            "--quiet",
            "--max-seconds",
            "1",
            "--rerun",
            str(path),
            "--rerun-image-hz",
            "2",
            "--rerun-twin-hz",
            "10",
        ],
        capture_output=True,
        text=True,
        timeout=120,
        env=env,
    )
    assert result.returncode == 0, result.stderr
    _verify(path)
    rows, _ = _contents(path)
    assert rows["/robot/joints/right/joint1/position"] == 30
    assert rows["/camera/front"] == 2
    # --rerun-twin-hz 10 over 1 s of session time: about 10 poses per moving body.
    assert 9 <= rows["/world/twin/right\\/link1"] <= 11, rows.get("/world/twin/right\\/link1")
