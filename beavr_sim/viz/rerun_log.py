"""Logging a teleop session to a Rerun recording (``.rrd``): ``--rerun F.rrd``.

:class:`RerunLogger` is a tick listener of :class:`~beavr_sim.teleop.pipeline.TeleopLoop`. It
owns one ``rr.RecordingStream`` that writes to the file (no global recording, no viewer
spawned) and logs, on the ``session_time`` timeline (seconds
from the first tick, continuing across episode resets) and the ``tick`` sequence:

- the operator's hands and the effectors' targets (3D, world frame, Z-up);
- the twin in 3D: every drawn geom once (static: meshes as ``Mesh3D``, primitives as boxes,
  ellipsoids, capsules, cylinders) under an entity per body, whose pose goes out per tick at
  ``twin_hz`` of session time; the collision geometry as wireframes under a separate path;
- the robot's joint positions and commands, holds, guard blocks, task success and latencies
  (scalars);
- events (episode starts, holds, guard blocks, success) as text logs, and the twin's camera
  images (JPEG, at a limited rate of session time: each one is an offscreen render).

Per-tick data is buffered per entity and sent in columns, one entity every few ticks in
turn, so that logging costs the loop a steady fraction of a millisecond per tick rather than
one ``log`` call per joint per tick. Static things (joint names, the hand skeleton's bones,
colours) are logged once.

The entity paths are listed in ``docs/formats.md``. Open the file with ``rerun F.rrd``.
"""

from __future__ import annotations

import io
import itertools
import math
import sys
from pathlib import Path

import mujoco
import numpy as np
import rerun as rr
from PIL import Image

from beavr_sim.envs.cameras import OffscreenCameras
from beavr_sim.envs.scene import camera_names
from beavr_sim.naming import check_name
from beavr_sim.robots.visuals import COLLISION_GROUP, RENDER_GEOM_GROUPS
from beavr_sim.wire.hand import FINGERS, JOINT_INDEX, JOINT_NAMES, SIDES

TIMELINE = "session_time"
TICK_TIMELINE = "tick"
#: Buffered per-tick data of an entity goes to the file about this often (and on close).
SEND_EVERY_S = 4.0

#: Bones of the 26-joint hand skeleton (pairs of canonical joint indices): wrist to each
#: fingertip, and across the knuckles. Drawn by the viewer from the annotation context.
BONES: tuple[tuple[int, int], ...] = tuple(
    pair
    for chain in (
        *(
            (JOINT_INDEX["wrist"], *(i for i, n in enumerate(JOINT_NAMES) if n.startswith(f + "_")))
            for f in FINGERS
        ),
        tuple(JOINT_INDEX[f"{f}_proximal"] for f in FINGERS[1:]),
    )
    for pair in itertools.pairwise(chain)
) + ((JOINT_INDEX["wrist"], JOINT_INDEX["palm"]),)

_HAND_CLASS = 0
_SIDE_COLORS = {"right": (230, 120, 40), "left": (60, 140, 230)}
_TARGET_COLOR = (40, 200, 120)
_SKELETON_COLOR = (200, 200, 200)
_ALL_JOINTS = np.arange(len(JOINT_NAMES))
#: The twin: an entity per body (its world pose), a child per geom (its pose in the body).
TWIN_PATH = "world/twin"
#: The collision geometry, the same bodies' poses: one subtree to show or hide.
COLLISION_PATH = "world/collision"
_COLLISION_COLOR = (255, 140, 0, 200)


def check_rrd_path(path: str | Path) -> Path:
    """``path`` as a Path if a Rerun recording can be written there; raises a clear error
    otherwise (wrong suffix, missing folder, a folder in the way)."""
    path = Path(path).expanduser()
    if path.suffix != ".rrd":
        raise ValueError(f"--rerun needs a .rrd file name, got {str(path)!r}")
    if path.is_dir():
        raise ValueError(f"--rerun {path} is a folder; give a file name such as {path}/session.rrd")
    if not path.parent.is_dir():
        raise FileNotFoundError(f"--rerun {path}: folder {path.parent} does not exist")
    return path


class _Columns:
    """Per-tick data buffered per entity and sent as columns (``send_columns``), one entity
    per tick in turn: a steady, small cost per tick instead of one ``log`` per entity.

    Kinds: ``scalar`` (a float), ``points`` (N x 3 positions and optional keypoint ids),
    ``transform`` (a 4x4 pose, sent as translation + quaternion).
    """

    def __init__(self, rec: rr.RecordingStream, rows: int = 120):
        self.rec = rec
        self.rows = int(rows)
        self._steps = 0
        self.kinds: dict[str, str] = {}
        self.series: dict[str, tuple[list[float], list[int], list]] = {}
        self._order: list[str] = []
        self._next = 0

    def add(self, kind: str, path: str, t: float, tick: int, row) -> None:
        s = self.series.get(path)
        if s is None:
            s = self.series[path] = ([], [], [])
            self.kinds[path] = kind
            self._order.append(path)
        s[0].append(t)
        s[1].append(tick)
        s[2].append(row)

    def scalar(self, path: str, t: float, tick: int, value: float) -> None:
        self.add("scalar", path, t, tick, float(value))

    def points(self, path: str, t: float, tick: int, positions, ids=None) -> None:
        self.add("points", path, t, tick, (np.asarray(positions, dtype=np.float32), ids))

    def transform(self, path: str, t: float, tick: int, T: np.ndarray) -> None:
        q = np.empty(4)
        mujoco.mju_mat2Quat(q, np.ascontiguousarray(T[:3, :3]).ravel())
        self.add("transform", path, t, tick, (T[:3, 3].copy(), q[[1, 2, 3, 0]]))  # xyzw

    def _columns(self, kind: str, rows: list):
        if kind == "scalar":
            return rr.Scalars.columns(scalars=np.asarray(rows, dtype=np.float64))
        if kind == "points":
            positions = np.concatenate([p for p, _ in rows])
            fields = {"positions": positions}
            if rows[0][1] is not None:
                fields["keypoint_ids"] = np.concatenate([i for _, i in rows])
            return rr.Points3D.columns(**fields).partition([len(p) for p, _ in rows])
        if kind == "transform":
            return rr.Transform3D.columns(
                translation=np.array([tr for tr, _ in rows]),
                quaternion=np.array([q for _, q in rows]),
            )
        raise ValueError(f"unknown column kind {kind!r}")

    def send(self, path: str) -> None:
        times, ticks, rows = self.series[path]
        if not rows:
            return
        self.rec.send_columns(
            path,
            indexes=[
                rr.TimeColumn(TIMELINE, duration=np.asarray(times, dtype=np.float64)),
                rr.TimeColumn(TICK_TIMELINE, sequence=np.asarray(ticks, dtype=np.int64)),
            ],
            columns=self._columns(self.kinds[path], rows),
        )
        self.series[path] = ([], [], [])

    def step(self) -> None:
        """Once a tick: send the next entity's buffer (round robin) every few ticks, so that
        each entity goes out about every ``rows`` ticks (sending costs a few hundred
        microseconds per entity, almost whatever the number of rows)."""
        if not self._order:
            return
        self._steps += 1
        if self._steps % max(1, math.ceil(self.rows / len(self._order))):
            return
        self._next %= len(self._order)
        self.send(self._order[self._next])
        self._next += 1

    def send_all(self) -> None:
        for path in self._order:
            self.send(path)


class _BodyPoses:
    """The moving bodies' world poses: one array per tick (a copy of ``xpos`` and ``xquat``
    of those bodies), sent as columns per body entity (and the same to its collision entity)
    once ``rows`` ticks are buffered, one body every few ticks, so that the cost per tick stays
    small and steady."""

    def __init__(self, rec: rr.RecordingStream, paths: list[tuple[str, ...]], rows: int):
        self.rec = rec
        self.paths = paths  # per body: its entity paths
        self.rows = max(1, int(rows))
        self._buffer: tuple[list, list, list, list] = ([], [], [], [])
        self._sending: tuple | None = None
        self._next = 0
        self._steps = 0

    def add(self, t: float, tick: int, positions: np.ndarray, quaternions_xyzw: np.ndarray):
        times, ticks, pos, quat = self._buffer
        times.append(t)
        ticks.append(tick)
        pos.append(positions)
        quat.append(quaternions_xyzw)
        if len(times) >= self.rows and self._sending is None:
            self._sending, self._next = self._take(), 0

    def _take(self) -> tuple | None:
        times, ticks, pos, quat = self._buffer
        if not times:
            return None
        self._buffer = ([], [], [], [])
        return (
            [
                rr.TimeColumn(TIMELINE, duration=np.asarray(times, dtype=np.float64)),
                rr.TimeColumn(TICK_TIMELINE, sequence=np.asarray(ticks, dtype=np.int64)),
            ],
            np.stack(pos),
            np.stack(quat),
        )

    def _send_next(self) -> None:
        indexes, pos, quat = self._sending
        i = self._next
        self._next += 1  # first: a body that fails to send is not tried again and again
        if self._next >= len(self.paths):
            self._sending = None
        columns = rr.Transform3D.columns(translation=pos[:, i], quaternion=quat[:, i])
        for path in self.paths[i]:
            self.rec.send_columns(path, indexes=indexes, columns=columns)

    def step(self) -> None:
        """Once a tick: the next body of the batch being sent, every few ticks."""
        self._steps += 1
        if self._sending is None or self._steps % max(1, self.rows // len(self.paths)):
            return
        self._send_next()

    def send_all(self) -> None:
        while self._sending is not None:
            self._send_next()
        self._sending, self._next = self._take(), 0
        while self._sending is not None:
            self._send_next()


class RerunLogger:
    """A :class:`TeleopLoop` tick listener that logs the session to ``path`` (``.rrd``).

    ``image_hz``: rate (session time) of the camera images, 0 for none; ``cameras``: which
    of the scene's cameras, rendered at ``image_size`` (height, width) and JPEG-encoded.
    ``twin_hz``: rate (session time) of the twin's body poses, 0 for no twin at all (the
    default, 30, is every tick at the default control rate); ``collision``: log the collision
    geometry too. Close it (or use it as a context manager) to flush the file.

    Nothing in the per-tick path raises for the twin: an error there is counted
    (:attr:`twin_errors`), the first one logged to ``events`` and stderr.
    """

    def __init__(
        self,
        path: str | Path,
        loop,
        *,
        image_hz: float = 5.0,
        cameras: tuple[str, ...] = ("front",),
        image_size: tuple[int, int] = (240, 320),
        jpeg_quality: int = 80,
        source: str | None = None,
        twin_hz: float = 30.0,
        collision: bool = True,
    ):
        if not (image_hz >= 0 and np.isfinite(image_hz)):
            raise ValueError(f"image rate must be >= 0 (0: no images), got {image_hz}")
        if not (twin_hz >= 0 and np.isfinite(twin_hz)):
            raise ValueError(f"twin rate must be >= 0 (0: no twin), got {twin_hz}")
        self.path = Path(path)
        self.loop = loop
        env = loop.twin.env
        self.env = env
        self.joint_names: tuple[str, ...] = tuple(env.joints.names)
        self.image_period = 1.0 / image_hz if image_hz > 0 else None
        self.cameras_names = tuple(cameras) if self.image_period else ()
        self.jpeg_quality = int(jpeg_quality)
        self._cameras = None
        if self.cameras_names:
            for c in self.cameras_names:
                check_name("camera", c, camera_names(env.embodiment))
            self._cameras = OffscreenCameras(env.render_model, *image_size)

        self.rec = rr.RecordingStream("beavr_sim_teleop")
        self.rec.save(self.path)
        self.columns = _Columns(self.rec, rows=max(1, round(SEND_EVERY_S * env.control_hz)))
        self._closed = False
        self._ticks = 0
        self._session_t = 0.0
        self._offset = 0.0
        self._prev_t: float | None = None
        self._prev_state_t: float | None = None
        self._episode = 0
        self._next_image_t = 0.0
        self._n_latencies = len(loop.latencies_ms)
        self._hold_reason: dict[str, str] = {}
        self._guard: tuple[str, ...] = ()
        self._success = False
        self.twin_period = 1.0 / twin_hz if twin_hz > 0 else None
        self._next_twin_t = 0.0
        #: Per-tick twin errors (never raised), and the moving bodies' entity paths.
        self.twin_errors = 0
        self._twin_bodies = np.zeros(0, dtype=int)
        self.poses: _BodyPoses | None = None
        self._log_static(source)
        if self.twin_period is not None:
            try:
                self._log_twin_static(collision)
            except Exception as exc:  # a viewer's extra: the session goes on without it
                self._twin_failed("the twin's geometry", exc)
                self.twin_period = None

    # ------------------------------------------------------------------ static
    def _log_static(self, source: str | None) -> None:
        env, rec = self.env, self.rec
        rec.send_recording_name(f"{env.task.name} / {env.embodiment.label}")
        rec.log("world", rr.ViewCoordinates.RIGHT_HAND_Z_UP, static=True)
        effectors = list(self.loop.twin.slices)
        values = {
            "task": env.task.name,
            "embodiment": env.embodiment.label,
            "control_hz": float(env.control_hz),
            "effectors": effectors,
            "joint_names": list(self.joint_names),
        }
        if source:
            values["source"] = source
        if self.cameras_names:
            values["cameras"] = list(self.cameras_names)
        rec.log("session", rr.AnyValues(**values), static=True)
        # One hand class for every skeleton under world/: joint names (hover) and bones.
        rec.log(
            "world",
            rr.AnnotationContext(
                [
                    rr.ClassDescription(
                        info=(_HAND_CLASS, "hand"),
                        keypoint_annotations=list(enumerate(JOINT_NAMES)),
                        keypoint_connections=BONES,
                    )
                ]
            ),
            static=True,
        )
        # What does not change per tick is static; per tick only positions (and ids) go out.
        for side in SIDES:
            rec.log(
                f"world/hands/{side}/keypoints",
                rr.Points3D.from_fields(
                    radii=0.006, colors=_SIDE_COLORS[side], class_ids=_HAND_CLASS
                ),
                static=True,
            )
        for name in effectors:
            base = f"world/targets/{name}"
            rec.log(f"{base}/arm", rr.TransformAxes3D(0.1), static=True)
            rec.log(f"{base}/reached", rr.TransformAxes3D(0.06), static=True)
            rec.log(
                f"{base}/fingers",
                rr.Points3D.from_fields(radii=0.008, colors=_TARGET_COLOR),
                static=True,
            )
            rec.log(
                f"{base}/skeleton",
                rr.Points3D.from_fields(
                    radii=0.004,
                    colors=_SKELETON_COLOR,
                    class_ids=_HAND_CLASS,
                    keypoint_ids=_ALL_JOINTS,
                ),
                static=True,
            )

    # ------------------------------------------------------------------ per tick
    def __call__(self, tick) -> None:
        if self._closed:
            return
        t = self._advance(tick)
        rec, k = self.rec, self._ticks
        rec.set_time(TIMELINE, duration=t)
        rec.set_time(TICK_TIMELINE, sequence=k)
        state = tick.state
        if self._prev_state_t is not None and state.t < self._prev_state_t:
            self._episode += 1
            self._success = False
            rec.log(
                "events",
                rr.TextLog(f"episode {self._episode} starts (reset)", level=rr.TextLogLevel.INFO),
            )
        self._prev_state_t = state.t

        cols = self.columns
        self._log_hands(tick.frames, t, k)
        self._log_targets(t, k)
        for name, q, u in zip(self.joint_names, state.positions, state.action, strict=True):
            cols.scalar(f"robot/joints/{name}/position", t, k, q)
            cols.scalar(f"robot/joints/{name}/command", t, k, u)
        for name, cmd in tick.commands.items():
            cols.scalar(f"robot/hold/{name}", t, k, float(cmd.hold))
            reason = cmd.reason if cmd.hold else ""
            if reason != self._hold_reason.get(name, ""):
                text = f"{name}: holding ({reason})" if reason else f"{name}: tracking"
                rec.log("events", rr.TextLog(text, level=rr.TextLogLevel.INFO))
            self._hold_reason[name] = reason
        blocked = tuple(state.guard_blocked_effectors) if state.guard_blocked else ()
        if state.guard_blocked and not blocked:
            blocked = ("an effector",)
        cols.scalar("guard/blocked", t, k, float(bool(blocked)))
        if blocked != self._guard:
            if blocked:
                text = f"collision guard blocked the command of {', '.join(blocked)}"
                rec.log("guard/events", rr.TextLog(text, level=rr.TextLogLevel.WARN))
            else:
                rec.log("guard/events", rr.TextLog("guard released", level=rr.TextLogLevel.INFO))
            self._guard = blocked
        cols.scalar("task/success", t, k, float(state.success))
        cols.scalar("task/failure", t, k, float(state.failure))
        if state.success and not self._success:
            rec.log("events", rr.TextLog("task success", level=rr.TextLogLevel.INFO))
        self._success = self._success or state.success
        lat = self.loop.latencies_ms
        if len(lat) < self._n_latencies:  # a new list: start over
            self._n_latencies = 0
        for v in lat[self._n_latencies :]:
            cols.scalar("latency/ms", t, k, v)
        self._n_latencies = len(lat)

        if self.image_period is not None and t >= self._next_image_t - 1e-9:
            # On a grid of the period (no drift); after a stall, on from now.
            self._next_image_t += self.image_period
            if self._next_image_t <= t:
                self._next_image_t = t + self.image_period
            self._log_images()
        if self.twin_period is not None and t >= self._next_twin_t - 1e-9:
            self._next_twin_t += self.twin_period
            if self._next_twin_t <= t:
                self._next_twin_t = t + self.twin_period
            self._log_twin(t, k)
        cols.step()
        self._ticks += 1

    def _advance(self, tick) -> float:
        """Session time: the tick's time plus an offset that starts the real clock at 0 and
        carries on across resets of the virtual clock (which start over at 0)."""
        t = float(tick.t)
        if self._prev_t is None:
            self._offset = -t if self.loop.real_time else 0.0
        elif t <= self._prev_t:  # a new episode on the virtual clock
            self._offset = self._session_t + self.loop.dt - t
        self._prev_t = t
        self._session_t = t + self._offset
        return self._session_t

    def _log_hands(self, frames, t: float, k: int) -> None:
        newest = {f.side: f for f in frames}  # frames come in order: keep each side's last
        for side, f in newest.items():
            ids = np.flatnonzero(f.tracked).astype(np.uint16)
            self.columns.points(f"world/hands/{side}/keypoints", t, k, f.joints[ids], ids)

    def _log_targets(self, t: float, k: int) -> None:
        cols = self.columns
        for name, tg in self.loop.operator.targets().items():
            base = f"world/targets/{name}"
            if tg.T_world_target is not None:
                cols.transform(f"{base}/arm", t, k, tg.T_world_target)
            cols.transform(f"{base}/reached", t, k, tg.T_world_hand)
            if tg.finger_targets_world is not None:
                cols.points(f"{base}/fingers", t, k, tg.finger_targets_world)
            if tg.keypoints_world is not None:
                cols.points(f"{base}/skeleton", t, k, tg.keypoints_world)

    # ------------------------------------------------------------------ the twin in 3D
    def _log_twin_static(self, collision: bool) -> None:
        """Every drawn geom once, static: ``{TWIN_PATH}/{body}/{geom}`` (visual geometry) and
        ``{COLLISION_PATH}/{body}/{geom}`` (collision geometry, wireframes), each with its pose
        in the body; the bodies that never move get their world pose here, once. (Geoms of
        the env's render model; body poses of its physics data: the bodies are the same.)"""
        m, d = self.env.render_model, self.env.data
        groups = {int(g) for g in RENDER_GEOM_GROUPS}
        bodies: dict[int, str] = {}
        for g in range(m.ngeom):
            group, kind = int(m.geom_group[g]), int(m.geom_type[g])
            is_collision = group == COLLISION_GROUP
            if (
                kind == mujoco.mjtGeom.mjGEOM_PLANE
                or m.geom_rgba[g, 3] <= 0
                or not (group in groups or (collision and is_collision))
            ):
                continue
            shape = _geom_archetype(m, g, is_collision)
            if shape is None:
                continue
            b = int(m.geom_bodyid[g])
            bodies[b] = body_entity(m, b)
            path = f"{COLLISION_PATH if is_collision else TWIN_PATH}/{geom_entity(m, g)}"
            self.rec.log(path, _transform(m.geom_pos[g], m.geom_quat[g]), shape, static=True)
        roots = (TWIN_PATH, COLLISION_PATH) if collision else (TWIN_PATH,)
        moving, paths = [], []
        for b, name in sorted(bodies.items()):
            if m.body_weldid[b] != 0 or m.body_mocapid[b] >= 0:
                moving.append(b)
                paths.append(tuple(f"{root}/{name}" for root in roots))
            else:
                for root in roots:
                    pose = _transform(d.xpos[b], d.xquat[b])
                    self.rec.log(f"{root}/{name}", pose, static=True)
        self._twin_bodies = np.array(moving, dtype=int)
        if moving:
            self.poses = _BodyPoses(self.rec, paths, self.columns.rows)

    def _log_twin(self, t: float, k: int) -> None:
        """The moving bodies' world poses (buffered columns); never raises."""
        if self.poses is None:
            return
        try:
            d, ids = self.env.data, self._twin_bodies
            self.poses.add(t, k, d.xpos[ids], d.xquat[ids][:, [1, 2, 3, 0]])  # copies; xyzw
            self.poses.step()
        except Exception as exc:
            self._twin_failed("the twin's poses", exc)

    def _twin_failed(self, what: str, exc: Exception) -> None:
        self.twin_errors += 1
        if self.twin_errors == 1:
            print(f"warning: rerun log: {what} not logged: {exc!r}", file=sys.stderr)
            try:
                self.rec.log(
                    "events",
                    rr.TextLog(f"{what} not logged: {exc!r}", level=rr.TextLogLevel.WARN),
                )
            except Exception:
                pass

    def _log_images(self) -> None:

        for name in self.cameras_names:
            try:
                pixels = self._cameras.render(self.env.render_data(), name)
            except Exception as exc:  # no GL here: go on without images, say so once
                print(f"warning: rerun log without camera images: {exc}", file=sys.stderr)
                self.rec.log(
                    "events",
                    rr.TextLog(f"no camera images: {exc}", level=rr.TextLogLevel.WARN),
                )
                self.image_period = None
                return
            buf = io.BytesIO()
            Image.fromarray(pixels).save(buf, format="JPEG", quality=self.jpeg_quality)
            self.rec.log(
                f"camera/{name}", rr.EncodedImage(contents=buf.getvalue(), media_type="image/jpeg")
            )

    # ------------------------------------------------------------------ closing
    def close(self) -> None:
        """Send what is buffered and close the file (idempotent)."""
        if self._closed:
            return
        self._closed = True
        try:
            if self.twin_errors > 1:
                text = f"the twin: {self.twin_errors} errors in all (the first one above)"
                self.rec.log("events", rr.TextLog(text, level=rr.TextLogLevel.WARN))
            self.columns.send_all()
            if self.poses is not None:
                try:
                    self.poses.send_all()
                except Exception as exc:
                    self._twin_failed("the twin's last poses", exc)
            self.rec.flush()
            self.rec.disconnect()
        finally:
            if self._cameras is not None:
                self._cameras.close()

    def __enter__(self) -> RerunLogger:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def body_entity(model: mujoco.MjModel, b: int) -> str:
    """A body's entity path under :data:`TWIN_PATH` / :data:`COLLISION_PATH`: its name as one
    path part (``right/link1`` -> ``right\\/link1``), ``body{id}`` if it has none."""
    return rr.escape_entity_path_part(model.body(b).name or f"body{b}")


def geom_entity(model: mujoco.MjModel, g: int) -> str:
    """A geom's entity path under :data:`TWIN_PATH` / :data:`COLLISION_PATH`: its body's, then
    its name (``geom{id}`` if it has none)."""
    name = rr.escape_entity_path_part(model.geom(g).name or f"geom{g}")
    return f"{body_entity(model, int(model.geom_bodyid[g]))}/{name}"


def _transform(position, quat_wxyz) -> rr.Transform3D:
    q = np.asarray(quat_wxyz, dtype=np.float64)
    return rr.Transform3D(
        translation=np.asarray(position, dtype=np.float32), quaternion=q[[1, 2, 3, 0]]
    )


def _vertex_normals(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """Area-weighted vertex normals (unit; a vertex of no face gets +z)."""
    a, b, c = (vertices[faces[:, i]] for i in range(3))
    face_normals = np.cross(b - a, c - a)
    normals = np.zeros_like(vertices)
    for i in range(3):
        np.add.at(normals, faces[:, i], face_normals)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.where(length > 0, normals / np.maximum(length, 1e-30), [0.0, 0.0, 1.0])
    return normals.astype(np.float32)


def _geom_archetype(model: mujoco.MjModel, g: int, collision: bool):
    """The geom in its own frame as a Rerun archetype (None for a kind not drawn): collision
    geometry as wireframes in one colour, visual geometry solid in its own."""
    kind = mujoco.mjtGeom(int(model.geom_type[g]))
    size = model.geom_size[g]
    if collision:
        color, fill = _COLLISION_COLOR, rr.components.FillMode.MajorWireframe
    else:
        rgba = model.geom_rgba[g]
        mat = int(model.geom_matid[g])
        if mat >= 0 and np.allclose(rgba, [0.5, 0.5, 0.5, 1.0]):  # MuJoCo: the material's
            rgba = model.mat_rgba[mat]
        color = tuple(int(round(255 * float(c))) for c in rgba)
        fill = rr.components.FillMode.Solid
    if kind == mujoco.mjtGeom.mjGEOM_MESH:
        k = int(model.geom_dataid[g])
        v0, nv = int(model.mesh_vertadr[k]), int(model.mesh_vertnum[k])
        f0, nf = int(model.mesh_faceadr[k]), int(model.mesh_facenum[k])
        vertices = np.asarray(model.mesh_vert[v0 : v0 + nv], dtype=np.float32)
        faces = np.asarray(model.mesh_face[f0 : f0 + nf], dtype=np.uint32)
        return rr.Mesh3D(
            vertex_positions=vertices,
            triangle_indices=faces,
            vertex_normals=_vertex_normals(vertices.astype(np.float64), faces),
            albedo_factor=color,
        )
    if kind == mujoco.mjtGeom.mjGEOM_BOX:
        return rr.Boxes3D(half_sizes=[size], colors=[color], fill_mode=fill)
    if kind == mujoco.mjtGeom.mjGEOM_SPHERE:
        return rr.Ellipsoids3D(half_sizes=[[size[0]] * 3], colors=[color], fill_mode=fill)
    if kind == mujoco.mjtGeom.mjGEOM_ELLIPSOID:
        return rr.Ellipsoids3D(half_sizes=[size], colors=[color], fill_mode=fill)
    if kind == mujoco.mjtGeom.mjGEOM_CAPSULE:  # Rerun's starts at its translation, along +z
        return rr.Capsules3D(
            lengths=[2 * size[1]],
            radii=[size[0]],
            translations=[[0.0, 0.0, -size[1]]],
            colors=[color],
            fill_mode=fill,
        )
    if kind == mujoco.mjtGeom.mjGEOM_CYLINDER:
        return rr.Cylinders3D(
            lengths=[2 * size[1]], radii=[size[0]], colors=[color], fill_mode=fill
        )
    return None
