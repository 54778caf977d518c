"""A viser view of the twin: geometry uploaded once, body poses and overlays updated per frame.

Every body that owns visible geoms becomes one scene frame; its geoms are children of that frame,
so an update sends one pose per body, never geometry. Binds 127.0.0.1 unless told otherwise.

Besides the robot and the scene (:meth:`TwinView.update`) it shows, per effector, what the
operator steers towards (``Operator.targets()``): the tracked hand skeleton (bones and joints,
drawn at the arm target), the arm target frame (axes) and the LEAP fingertip targets; the
collision guard's state (the blocked effector's geoms turn red until the guard clears; colours
are sent on transitions only) and the task's success (a green badge). The control panel has the
task and embodiment, pause / resume, reset, recording (start / stop, discard, the episode and its
state) and a readout of loop rate, latency and what the view itself costs (:class:`ViewCost`:
the loop's time in the view per tick, and viser's server thread encoding and sending to the
connected browsers).

The view never paces the loop: the caller asks :meth:`TwinView.due` (at most ``rate_hz``
updates per wall second, 30 by default) and only then builds and sends an update; button
presses are flags the caller takes at its tick boundary. Text that only counts (the status's
clock, the readout's numbers) is sent at most :data:`TEXT_RATE_HZ` times a second; a status
whose words change (success, paused, a hold) is sent at once.
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Mapping, Sequence
from itertools import pairwise

import mujoco
import numpy as np

from beavr_sim.robots.visuals import COLLISION_GROUP, RENDER_GEOM_GROUPS
from beavr_sim.viz.view_access import ViewAccess
from beavr_sim.wire.hand import FINGERS, JOINT_INDEX, JOINT_NAMES

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8080
#: Scene updates per wall second at most (the control loop may tick faster).
DEFAULT_RATE_HZ = 30.0
#: Geom groups uploaded: the scene, the robots' visuals, their collision geometry (hidden
#: unless ``show_collision``).
DRAWN_GROUPS = (*RENDER_GEOM_GROUPS, COLLISION_GROUP)
#: Colour of an effector's geoms while the collision guard blocks it.
WARNING_RGB = (230, 30, 30)
#: Hand skeleton colour per side; fingertip targets.
SIDE_RGB = {"right": (255, 140, 0), "left": (0, 150, 255)}
FINGERTIP_RGB = (230, 0, 200)
#: A body pose is sent when a coordinate (m, or quaternion component) changed by more.
POSE_TOLERANCE = 1e-6
#: Readout and status-clock text updates per wall second at most (nobody reads faster).
TEXT_RATE_HZ = 4.0

_BADGE = (
    '<div style="display:inline-block;padding:4px 10px;border-radius:6px;font-weight:600;'
    'color:white;background:{bg}">{text}</div>'
)


def _rgb(rgba: np.ndarray) -> tuple[int, int, int]:
    return tuple(int(round(255 * float(c))) for c in rgba[:3])


def skeleton_bones() -> tuple[tuple[int, int], ...]:
    """Bones of the 26-joint canonical hand (index pairs): wrist-palm, then each finger as a
    chain from the wrist through its joints to the tip (built from the joint names)."""
    bones = [(JOINT_INDEX["wrist"], JOINT_INDEX["palm"])]
    for finger in FINGERS:
        chain = [JOINT_INDEX["wrist"]] + [
            i for i, name in enumerate(JOINT_NAMES) if name.startswith(f"{finger}_")
        ]
        bones += list(pairwise(chain))
    return tuple(bones)


BONES = skeleton_bones()


def skeleton_segments(keypoints: np.ndarray) -> np.ndarray:
    """Line segments (bones x 2 x 3) of a 26 x 3 skeleton. A bone with an untracked (non-finite)
    end collapses to a point at a finite joint, so the segment count never changes."""
    p = np.asarray(keypoints, dtype=np.float64)
    if p.shape != (len(JOINT_NAMES), 3):
        raise ValueError(f"skeleton needs {len(JOINT_NAMES)} x 3 keypoints, got {p.shape}")
    finite = np.isfinite(p).all(axis=1)
    fallback = p[finite][0] if finite.any() else np.zeros(3)
    idx = np.asarray(BONES)
    a, b = p[idx[:, 0]], p[idx[:, 1]]
    fa, fb = finite[idx[:, 0], None], finite[idx[:, 1], None]
    a = np.where(fa, a, np.where(fb, b, fallback))
    b = np.where(fb, b, a)
    return np.stack([a, b], axis=1).astype(np.float32)


class RateMeter:
    """Events per second over the last ``window_s`` of wall time."""

    def __init__(self, window_s: float = 1.0):
        self.window_s = float(window_s)
        self._times: deque[float] = deque()

    def tick(self, now: float | None = None) -> None:
        now = time.perf_counter() if now is None else now
        self._times.append(now)
        while self._times and now - self._times[0] > self.window_s:
            self._times.popleft()

    def rate_hz(self) -> float | None:
        """None until two events fell in the window."""
        if len(self._times) < 2 or self._times[-1] <= self._times[0]:
            return None
        return (len(self._times) - 1) / (self._times[-1] - self._times[0])


def recent_p50(values: Sequence[float], n: int = 200) -> float | None:
    """Median of the last ``n`` values (None when empty)."""
    recent = values[-n:]
    return float(np.median(recent)) if len(recent) else None


def thread_cpu_clock(thread: threading.Thread | None) -> Callable[[], float] | None:
    """The CPU time (s) ``thread`` has used so far, as a function; None where the platform
    cannot tell (no per-thread CPU clocks) or the thread is not running."""
    try:
        clock = time.pthread_getcpuclockid(thread.ident)  # type: ignore[union-attr]
        time.clock_gettime(clock)
    except (AttributeError, OSError, TypeError, OverflowError):
        return None
    return lambda: time.clock_gettime(clock)


class ViewCost:
    """What the view costs, over the last ``window_s`` of wall time.

    ``busy`` (:meth:`add`): wall time the loop's thread spent on the view (taking buttons,
    asking for targets, building and queuing updates); ``server_cpu()``: the CPU time of
    viser's server thread so far (encoding and sending to the connected browsers, which
    competes with the loop for the GIL and the cores), or None when it cannot be read.
    """

    def __init__(self, window_s: float = 1.0, server_cpu: Callable[[], float] | None = None):
        self.window_s = float(window_s)
        self.server_cpu = server_cpu
        self._busy: deque[tuple[float, float]] = deque()  # (when, seconds)
        self._server: deque[tuple[float, float]] = deque()  # (when, CPU seconds so far)

    def add(self, busy_s: float, now: float | None = None) -> None:
        """The loop's thread spent ``busy_s`` on the view (ending ``now``)."""
        now = time.perf_counter() if now is None else now
        self._busy.append((now, busy_s))
        while self._busy and now - self._busy[0][0] > self.window_s:
            self._busy.popleft()

    def sample_server(self, now: float | None = None) -> None:
        """Read the server thread's CPU clock (once per update is enough)."""
        if self.server_cpu is None:
            return
        now = time.perf_counter() if now is None else now
        try:
            self._server.append((now, self.server_cpu()))
        except OSError:  # the thread ended
            self.server_cpu = None
            return
        while len(self._server) > 2 and now - self._server[1][0] >= self.window_s:
            self._server.popleft()

    def per_second(self, now: float | None = None) -> tuple[float, float | None]:
        """(the loop's seconds in the view, the server thread's CPU seconds) per wall second
        over the window; the second is None until two samples of it."""
        now = time.perf_counter() if now is None else now
        busy = sum(s for t, s in self._busy if now - t <= self.window_s) / self.window_s
        server = None
        if len(self._server) >= 2 and self._server[-1][0] > self._server[0][0]:
            (t0, c0), (t1, c1) = self._server[0], self._server[-1]
            server = max(c1 - c0, 0.0) / (t1 - t0)
        return busy, server

    def readout(self, loop_rate_hz: float | None, clients: int, now: float | None = None) -> str:
        """The panel's line: ms per tick in the loop's thread and sending, and the share of
        the wall time (at the loop's rate: of each control period)."""
        busy, server = self.per_second(now)
        total = busy + (server or 0.0)
        per_tick = f"**{1e3 * total / loop_rate_hz:.2f} ms/tick**" if loop_rate_hz else "- ms/tick"
        parts = f"loop {1e3 * busy / loop_rate_hz:.2f}" if loop_rate_hz else ""
        if server is not None and loop_rate_hz:
            parts += f", sending {1e3 * server / loop_rate_hz:.2f}"
        browsers = f"{clients} browser" + ("" if clients == 1 else "s")
        return (
            f"view {per_tick} ({parts}; {100 * total:.1f} % of the time) · {browsers}"
            if parts
            else f"view {per_tick} · {browsers}"
        )


class Throttle:
    """True at most ``rate_hz`` times per second of wall time (every call when ``rate_hz <= 0``)."""

    def __init__(self, rate_hz: float):
        self.period = 1.0 / rate_hz if rate_hz > 0 else 0.0
        self._next = -float("inf")

    def due(self, now: float | None = None) -> bool:
        now = time.perf_counter() if now is None else now
        if now < self._next:
            return False
        # Keep the cadence (a tick a little early must not skip a period), but never bank
        # updates after a stall.
        self._next = max(self._next + self.period, now + 0.5 * self.period)
        return True


class GuardTint:
    """Robot geoms in :data:`WARNING_RGB` while the guard blocks their effector.

    ``geoms``: per effector, the (handle, own colour) of its geoms. :meth:`show` assigns
    colours only to the effectors whose state changed, so a steady state sends nothing.
    """

    def __init__(self, geoms: Mapping[str, Sequence[tuple[object, tuple[int, int, int]]]]):
        self.geoms = {name: list(items) for name, items in geoms.items()}
        self.blocked: frozenset[str] = frozenset()

    def show(self, blocked: Iterable[str]) -> int:
        """Set the blocked effectors; returns how many colours were sent."""
        blocked = frozenset(b for b in blocked if b in self.geoms)
        sent = 0
        for name in blocked ^ self.blocked:
            warn = name in blocked
            for handle, own in self.geoms[name]:
                handle.color = WARNING_RGB if warn else own
                sent += 1
        self.blocked = blocked
        return sent


def subtree_bodies(
    model: mujoco.MjModel, joints_by_effector: Mapping[str, Sequence[str]]
) -> dict[str, set[int]]:
    """Per effector, the bodies of its kinematic subtree: from the topmost body below the world
    that carries one of its joints (the arm's base) down to the fingertips."""
    parent = model.body_parentid
    out: dict[str, set[int]] = {}
    for name, joints in joints_by_effector.items():
        roots = set()
        for j in joints:
            b = int(model.jnt_bodyid[model.joint(j).id])
            while parent[b] != 0:
                b = int(parent[b])
            roots.add(b)
        members = set()
        for b in range(1, model.nbody):
            a = b
            while a != 0 and a not in roots:
                a = int(parent[a])
            if a != 0:
                members.add(b)
        out[name] = members
    return out


def _server_thread(server) -> threading.Thread | None:
    """viser's server thread (its event loop: encodes and sends to the browsers), or None
    when this viser's internals differ."""
    thread = getattr(getattr(server, "_websock_server", None), "_server_thread", None)
    return thread if isinstance(thread, threading.Thread) else None


def _pose_setters(handle):
    """``(set_position, set_wxyz)`` for a scene node that queue viser's pose messages directly,
    skipping the public setters' per-call cast and closeness check (the view compares all
    bodies in one vectorised step instead; a third of an update's time). Falls back to the
    public setters when this viser's internals differ."""
    try:
        from viser import _messages

        impl = handle._impl
        queue, name = impl.api._queue_scene_message, impl.name
        position, wxyz = impl.position, impl.wxyz
        position_msg, wxyz_msg = _messages.SetPositionMessage, _messages.SetOrientationMessage
        if position.shape != (3,) or wxyz.shape != (4,):
            raise AttributeError
    except (AttributeError, ImportError):
        return (
            lambda v: setattr(handle, "position", v),
            lambda v: setattr(handle, "wxyz", v),
        )

    def set_position(v: np.ndarray) -> None:
        position[:] = v
        queue(position_msg(name, tuple(float(x) for x in v)))

    def set_wxyz(v: np.ndarray) -> None:
        wxyz[:] = v
        queue(wxyz_msg(name, tuple(float(x) for x in v)))

    return set_position, set_wxyz


class _Overlay:
    """One effector's targets in the scene: skeleton bones and joints, target axes, fingertips."""

    def __init__(self, scene, name: str, side: str):
        color = SIDE_RGB.get(side, (200, 200, 200))
        root = f"/targets/{name}"
        zeros = np.zeros((len(BONES), 2, 3), np.float32)
        self.bones = scene.add_line_segments(
            f"{root}/skeleton", zeros, color, thickness=3.0, thickness_units="screen", visible=False
        )
        self.joints = scene.add_point_cloud(
            f"{root}/joints",
            np.zeros((len(JOINT_NAMES), 3), np.float32),
            color,
            point_size=0.008,
            point_shape="circle",
            precision="float32",
            visible=False,
        )
        self.frame = scene.add_frame(
            f"{root}/arm_target", axes_length=0.12, axes_radius=0.005, visible=False
        )
        self.tips = scene.add_point_cloud(
            f"{root}/fingertips",
            np.zeros((8, 3), np.float32),
            FINGERTIP_RGB,
            point_size=0.012,
            point_shape="diamond",
            precision="float32",
            visible=False,
        )

    def show(self, targets) -> None:
        kp = targets.keypoints_world
        for handle in (self.bones, self.joints):
            if handle.visible != (kp is not None):
                handle.visible = kp is not None
        if kp is not None:
            segments = skeleton_segments(kp)
            self.bones.points = segments
            kp = np.asarray(kp, np.float32)
            self.joints.points = np.where(np.isfinite(kp), kp, segments[0, 0])
        T = targets.T_world_target
        if self.frame.visible != (T is not None):
            self.frame.visible = T is not None
        if T is not None:
            q = np.zeros(4)
            mujoco.mju_mat2Quat(q, np.ascontiguousarray(T[:3, :3]).reshape(9))
            self.frame.position = T[:3, 3]
            self.frame.wxyz = q
        tips = targets.finger_targets_world
        if self.tips.visible != (tips is not None):
            self.tips.visible = tips is not None
        if tips is not None:
            self.tips.points = np.asarray(tips, np.float32)


class TwinView:
    """Live view of ``model``; call :meth:`update` with the current ``MjData``.

    ``task`` / ``embodiment``: shown in the panel. ``effector_bodies``: per effector, the
    bodies tinted while the guard blocks it (default: one ``"robot"`` group, the subtrees of
    the hinge and slide joints). ``episode_control`` (an ``EpisodeControl``): adds the record
    buttons. ``mirroring``: the twin drives hardware; adds an emergency-stop button that
    latches :attr:`estop_requested` (the session must stop the hardware on it). No session
    mirrors to hardware yet, so they pass False and no such button is shown.
    ``rate_hz``: scene updates per wall second at most (:meth:`due`).
    """

    def __init__(
        self,
        model: mujoco.MjModel,
        host: str = DEFAULT_HOST,
        port: int = DEFAULT_PORT,
        title: str = "beavr_sim twin",
        episode_control=None,
        *,
        task: str | None = None,
        embodiment: str | None = None,
        effector_bodies: Mapping[str, Iterable[int]] | None = None,
        mirroring: bool = False,
        rate_hz: float = DEFAULT_RATE_HZ,
        show_collision: bool = False,
        access: ViewAccess | None = None,
    ):
        import viser  # optional dependency (extra "viz")

        self.model = model
        # viser prints its banner on stdout: to stderr, stdout is the CLIs' JSON.
        with contextlib.redirect_stdout(sys.stderr):
            self.server = viser.ViserServer(host=host, port=port, verbose=False)
        self.host, self.port = host, self.server.get_port()
        self.rate_hz = float(rate_hz)
        self._throttle = Throttle(self.rate_hz)
        self._status_throttle = Throttle(TEXT_RATE_HZ)
        self._readout_throttle = Throttle(TEXT_RATE_HZ)
        self._readout_known: tuple[bool, bool] | None = None  # which numbers the readout has
        self._status_words: object = None  # the status without its clock, last sent
        #: What the view costs the loop (:class:`ViewCost`); :meth:`update` adds its own time,
        #: the caller its per-tick time outside it (:meth:`account`).
        self.cost = ViewCost(1.0, thread_cpu_clock(_server_thread(self.server)))
        self.server.scene.add_grid("/floor", width=4.0, height=4.0, cell_size=0.25)
        self.body_frames: dict[int, object] = {}
        self.geom_handles: list[object] = []
        #: The robots' collision geometry (geom group 3): hidden unless shown.
        self.collision_handles: list[object] = []
        self._geom_bodies: list[tuple[object, int, tuple[int, int, int]]] = []
        self._add_geoms(show_collision)
        # Bodies that can move (world-body geoms never do) and the poses last sent: an update
        # sends only the poses that changed (one vectorised comparison, not one per setter).
        self._moving = np.array([b for b in self.body_frames if b != 0], dtype=int)
        self._setters = [_pose_setters(self.body_frames[b]) for b in self._moving]
        self._sent_pos = np.full((len(self._moving), 3), np.nan)
        self._sent_quat = np.full((len(self._moving), 4), np.nan)
        if effector_bodies is None:
            hinge = [
                model.joint(j).name
                for j in range(model.njnt)
                if model.jnt_type[j] in (mujoco.mjtJoint.mjJNT_HINGE, mujoco.mjtJoint.mjJNT_SLIDE)
            ]
            effector_bodies = subtree_bodies(model, {"robot": hinge}) if hinge else {}
        self._aim_camera(set().union(*effector_bodies.values()) if effector_bodies else set())
        self.guard = GuardTint(
            {
                name: [(h, rgb) for h, b, rgb in self._geom_bodies if b in set(bodies)]
                for name, bodies in effector_bodies.items()
            }
        )
        self.overlays: dict[str, _Overlay] = {}
        self.updates = 0

        gui = self.server.gui
        self.title = gui.add_markdown(f"**{title}**")
        facts = [
            f"task **{task}**" if task else "",
            f"embodiment **{embodiment}**" if embodiment else "",
        ]
        self.info = gui.add_markdown(" · ".join(f for f in facts if f) or " ")
        self.success_badge = gui.add_html(
            _BADGE.format(bg="#2e7d32", text="&#10004; task success"), visible=False
        )
        self.guard_badge = gui.add_html(_BADGE.format(bg="#c62828", text="guard"), visible=False)
        self.status = gui.add_markdown(" ")

        self._paused = False
        self.reset_requested = False
        self.estop_requested = False
        #: Who may press which control (None: everyone everything).
        self.access = access
        self.access_note = None
        if access is not None and access.token.required:
            with gui.add_folder("Access"):
                self.access_note = gui.add_markdown(
                    "anyone may stop; enter the session token to resume, reset or record"
                )
            self.server.on_client_connect(self._add_token_field)
            self.server.on_client_disconnect(lambda client: access.forget(client.client_id))
        with gui.add_folder("Session"):
            self.pause_button = gui.add_button("Pause", icon=viser.Icon.PLAYER_PAUSE)
            self.pause_button.on_click(
                self._guarded(lambda: "resume" if self._paused else "pause", self._toggle_pause)
            )
            self.reset_button = gui.add_button("Reset", icon=viser.Icon.REFRESH)
            self.reset_button.on_click(
                self._guarded("reset", lambda: setattr(self, "reset_requested", True))
            )
            self.estop_button = None
            if mirroring:
                self.estop_button = gui.add_button(
                    "EMERGENCY STOP", color="red", icon=viser.Icon.HAND_STOP
                )
                self.estop_button.on_click(
                    self._guarded(
                        lambda: "release" if self.estop_requested else "estop", self._estop
                    )
                )
        self.episode = None
        if episode_control is not None:  # recording: start / stop and discard episodes
            with gui.add_folder("Recording"):
                self.episode = gui.add_markdown("episode: idle")
                record = gui.add_button("Record: start / stop episode", color="red")
                record.on_click(
                    self._guarded("record", lambda: episode_control.request("toggle", "browser"))
                )
                discard = gui.add_button("Discard episode")
                discard.on_click(
                    self._guarded("discard", lambda: episode_control.request("discard", "browser"))
                )
        with gui.add_folder("View"):
            self.collision_checkbox = gui.add_checkbox("Show collision geometry", show_collision)
            self.collision_checkbox.on_update(
                lambda _: self.set_show_collision(self.collision_checkbox.value)
            )
        with gui.add_folder("Loop"):
            self.readout = gui.add_markdown("loop rate -  \nlatency p50 -  \nview -")

    def _aim_camera(self, robot: set[int]) -> None:
        """Initial camera: the robot (at the model's reference pose) from the front right,
        above the table, at a distance that frames the arm's reach."""
        data = mujoco.MjData(self.model)
        mujoco.mj_forward(self.model, data)
        bodies = sorted(robot) or list(self._moving) or [0]
        focus = data.xpos[bodies].mean(axis=0)
        spread = float(np.linalg.norm(data.xpos[bodies] - focus, axis=1).max(initial=0.0))
        distance = max(1.4, 3.0 * spread)
        direction = np.array([0.7, -0.55, 0.45])
        self.server.initial_camera.look_at = focus
        self.server.initial_camera.position = focus + distance * direction / np.linalg.norm(
            direction
        )

    @property
    def clients(self) -> int:
        """Browsers connected now."""
        try:
            return len(self.server.get_clients())
        except Exception:  # a server shutting down
            return 0

    def account(self, busy_s: float, now: float | None = None) -> None:
        """The loop's thread spent ``busy_s`` on the view outside :meth:`update` (per tick:
        taking buttons, asking for targets): counted in the panel's view cost."""
        self.cost.add(busy_s, now)

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}"

    @property
    def paused(self) -> bool:
        """The operator pressed Pause (and not Resume since)."""
        return self._paused

    @property
    def refused(self) -> int:
        """Presses refused for want of the session token."""
        return 0 if self.access is None else sum(self.access.refused.values())

    def _guarded(self, action: str | Callable[[], str], press: Callable[[], None]):
        """An ``on_click`` handler running ``press`` when the clicking client may ``action``."""

        def on_click(event) -> None:
            name = action() if callable(action) else action
            client_id = getattr(event, "client_id", None)
            if self.access is None or self.access.permits(name, client_id):
                press()
            elif self.access_note is not None:
                self.access_note.content = (
                    f"**{name} refused**: enter the session token ({self.refused} refused)"
                )

        return on_click

    def _add_token_field(self, client) -> None:
        """A per-client token field (never shared with the other clients)."""
        field = client.gui.add_text("Session token", initial_value="")

        def entered(_) -> None:
            ok = self.access.enter(client.client_id, field.value)
            field.label = "Session token ✓" if ok else "Session token (wrong)"

        field.on_update(entered)

    def _toggle_pause(self) -> None:
        self._paused = not self._paused
        import viser

        self.pause_button.label = "Resume" if self._paused else "Pause"
        self.pause_button.icon = viser.Icon.PLAYER_PLAY if self._paused else viser.Icon.PLAYER_PAUSE

    def _estop(self) -> None:
        """The button: latch the emergency stop, or release it when latched."""
        self.set_estop(not self.estop_requested)

    def set_estop(self, latched: bool) -> None:
        """Show the emergency stop latched (the session holds the hardware) or released."""
        self.estop_requested = bool(latched)
        if self.estop_button is not None:
            self.estop_button.label = (
                "E-STOP LATCHED: click to release" if latched else "EMERGENCY STOP"
            )

    def take_reset(self) -> bool:
        """True once per Reset press."""
        requested, self.reset_requested = self.reset_requested, False
        return requested

    def due(self, now: float | None = None) -> bool:
        """Whether an update is due (at most ``rate_hz`` per wall second)."""
        return self._throttle.due(now)

    def set_show_collision(self, shown: bool) -> None:
        """Show or hide the robots' collision geometry (drawn over the visual geometry)."""
        self.show_collision = bool(shown)
        for handle in self.collision_handles:
            if handle.visible != self.show_collision:
                handle.visible = self.show_collision

    def _add_geoms(self, show_collision: bool) -> None:
        """Every drawn geom once: the scene, the robots' visual geometry (meshes uploaded
        here, once) and their collision geometry (visible if ``show_collision``)."""
        m = self.model
        scene = self.server.scene
        self.show_collision = bool(show_collision)
        for g in range(m.ngeom):
            group = int(m.geom_group[g])
            if group not in DRAWN_GROUPS or m.geom_rgba[g, 3] == 0:
                continue
            collision = group == COLLISION_GROUP
            visible = self.show_collision or not collision
            gtype, size, color = (
                mujoco.mjtGeom(int(m.geom_type[g])),
                m.geom_size[g],
                _rgb(m.geom_rgba[g]),
            )
            if gtype == mujoco.mjtGeom.mjGEOM_PLANE:
                continue  # the floor is the grid
            body = int(m.geom_bodyid[g])
            if body not in self.body_frames:
                self.body_frames[body] = scene.add_frame(f"/twin/b{body}", show_axes=False)
            name = f"/twin/b{body}/g{g}"
            pose = {"position": m.geom_pos[g], "wxyz": m.geom_quat[g]}
            added = []
            if gtype == mujoco.mjtGeom.mjGEOM_MESH:
                mesh = int(m.geom_dataid[g])
                v0, nv = m.mesh_vertadr[mesh], m.mesh_vertnum[mesh]
                f0, nf = m.mesh_faceadr[mesh], m.mesh_facenum[mesh]
                added.append(
                    scene.add_mesh_simple(
                        name,
                        np.asarray(m.mesh_vert[v0 : v0 + nv], dtype=np.float32),
                        np.asarray(m.mesh_face[f0 : f0 + nf], dtype=np.uint32),
                        color=color,
                        **pose,
                    )
                )
            elif gtype == mujoco.mjtGeom.mjGEOM_BOX:
                added.append(scene.add_box(name, color, tuple(2 * size), **pose))
            elif gtype == mujoco.mjtGeom.mjGEOM_SPHERE:
                added.append(scene.add_icosphere(name, float(size[0]), color, **pose))
            elif gtype in (mujoco.mjtGeom.mjGEOM_CAPSULE, mujoco.mjtGeom.mjGEOM_CYLINDER):
                added.append(
                    scene.add_cylinder(name, float(size[0]), float(2 * size[1]), color, **pose)
                )
                if gtype == mujoco.mjtGeom.mjGEOM_CAPSULE:
                    R = np.zeros(9)
                    mujoco.mju_quat2Mat(R, m.geom_quat[g])
                    axis = R.reshape(3, 3)[:, 2] * size[1]
                    for k, sign in enumerate((1, -1)):
                        added.append(
                            scene.add_icosphere(
                                f"{name}_cap{k}",
                                float(size[0]),
                                color,
                                position=m.geom_pos[g] + sign * axis,
                            )
                        )
            if not visible:
                for handle in added:
                    handle.visible = False
            if collision:
                self.collision_handles += added
            self.geom_handles += added
            self._geom_bodies += [(h, body, color) for h in added]

    def update(
        self,
        data: mujoco.MjData,
        status: str | None = None,
        *,
        status_words: object = None,
        targets: Mapping[str, object] | None = None,
        guard_blocked: Iterable[str] = (),
        success: bool | None = None,
        loop_rate_hz: float | None = None,
        latency_ms: float | None = None,
        episode: str | None = None,
    ) -> None:
        """Send every moving body's pose and the given overlays and readouts (one batch).

        ``targets``: ``Operator.targets()``; ``guard_blocked``: the effectors the guard blocks
        (their geoms turn red; colours change only on transitions). ``status`` is sent at most
        :data:`TEXT_RATE_HZ` times a second unless ``status_words`` (what it says besides
        numbers, e.g. success, paused, holds) changed, or are not given; so is the readout, unless
        one of its numbers appeared or went.
        """
        start = time.perf_counter()
        with self.server.atomic():
            pos, quat = data.xpos[self._moving], data.xquat[self._moving]
            # NaN (never sent) compares false: sent.
            moved_pos = ~(np.abs(pos - self._sent_pos) <= POSE_TOLERANCE).all(axis=1)
            moved_quat = ~(np.abs(quat - self._sent_quat) <= POSE_TOLERANCE).all(axis=1)
            for i in np.flatnonzero(moved_pos):
                self._setters[i][0](pos[i])
            for i in np.flatnonzero(moved_quat):
                self._setters[i][1](quat[i])
            self._sent_pos[moved_pos] = pos[moved_pos]
            self._sent_quat[moved_quat] = quat[moved_quat]
            for name, tgt in (targets or {}).items():
                if name not in self.overlays:
                    self.overlays[name] = _Overlay(self.server.scene, name, tgt.side)
                self.overlays[name].show(tgt)
            self.guard.show(guard_blocked)
        blocked = sorted(self.guard.blocked)
        if self.guard_badge.visible != bool(blocked):
            self.guard_badge.visible = bool(blocked)
        if blocked:
            content = _BADGE.format(bg="#c62828", text=f"collision guard: {', '.join(blocked)}")
            if self.guard_badge.content != content:
                self.guard_badge.content = content
        if success is not None and self.success_badge.visible != success:
            self.success_badge.visible = success
        if status is not None and self.status.content != status:
            words_changed = status_words is None or status_words != self._status_words
            if words_changed or self._status_throttle.due(start):
                self.status.content = status
                self._status_words = status_words
        # A number that appears (or goes) is sent at once, as changed status words are.
        known = (loop_rate_hz is not None, latency_ms is not None)
        if any(known) and (known != self._readout_known or self._readout_throttle.due(start)):
            self._readout_known = known
            rate = "-" if loop_rate_hz is None else f"{loop_rate_hz:.1f} Hz"
            lat = "-" if latency_ms is None else f"{latency_ms:.2f} ms"
            self.cost.sample_server(start)
            self.readout.content = (
                f"loop rate **{rate}**  \nlatency p50 **{lat}**  \n"
                + self.cost.readout(loop_rate_hz, self.clients, start)
            )
        if episode is not None and self.episode is not None and self.episode.content != episode:
            self.episode.content = episode
        self.updates += 1
        self.cost.add(time.perf_counter() - start)

    def add_camera_panel(self, shapes: Mapping[str, tuple[int, int, int]]):
        """A real-camera panel (``viz/camera_panel.py``) for cameras of frame ``shapes``: a
        sink for a ``CameraStream``, fed on the stream's thread."""
        from beavr_sim.viz.camera_panel import CameraPanel  # local: heavy (OpenCV, ~170 ms)

        self.camera_panel = CameraPanel(self.server.gui, shapes)
        return self.camera_panel

    def close(self) -> None:
        with contextlib.redirect_stdout(sys.stderr):
            self.server.stop()
