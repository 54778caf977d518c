"""``--multiprocess``: the operator (with the detector) and the twin as processes over ZeroMQ.

The same components as the single-process loop (``pipeline.py``), connected by the transport
(``transport.py``, ports from ``ports.py``):

    headset   --Quest app's PUSH strings-->  operator (detector + operator)
    operator  --commands (JointCommandMsg, topic = effector)-->  twin
    twin      --robot_state (RobotStateMsg, every tick: its heartbeat)-->  operator, supervisor
    supervisor --session (SessionMsg)-->  operator, twin

The pipeline is event-driven: nothing waits for a fixed clock on the way from a hand frame to
the actuators. The operator process owns the headset's sockets (``headset/``: parse, validate,
count) in its event loop, together with the robot state and session streams: each valid frame
is observed when it arrives and that hand's effectors are commanded at once (frames queued
behind a newer one are observed and counted as superseded; a side without frames for 1.5
control periods is commanded on the clock: its holds). The detector is not a process of its
own: on a small machine every process hop costs more than the detector's work (see
docs/benchmarks.md, 2026-12-02). The twin guards each command when it arrives, writes it to
its actuators' targets and hands it to the hardware mirror at once, while its physics steps
one control period at a time on its own real-time clock (the mirror also gets the targets
once per period when no command came: its heartbeat).

Each process creates its own ZMQ context, owns its sockets in its main thread, and runs on
the real clock. Latest-only streams are conflated. Publishers wait for their subscribers
(readiness handshake) before the session starts. Killing any one process leaves the others
alive: the twin keeps the last targets (the robot holds) when commands stop, the operator
holds when hand frames stop; the supervisor reports the death and stops on its own terms.
Processes are started with the ``spawn`` method (no state inherited from the parent) and
report their final counters to the supervisor as JSON over a pipe.

Resets are numbered (epochs): the twin stamps every state with its epoch and drops commands
of an older one; the operator re-homes from the first state of a newer epoch only, and after
a reset request holds until that state comes (:class:`OperatorRehome`). The twin's physics
ticks on a :class:`~beavr_sim.teleop.pipeline.TickSchedule` (after a stall: no catch-up
burst, the skipped periods counted); an operator exception holds that side's effectors for a
command (reason ``"error"``), it never ends the process.
"""

from __future__ import annotations

import json
import logging
import math
import multiprocessing as mp
import sys
import time
from dataclasses import asdict

import numpy as np

from beavr_sim.teleop.pipeline import (
    MIN_COMMAND_DT_S,
    TeleopSummary,
    TickSchedule,
    _percentiles,
    count_hold,
    operator_call,
)
from beavr_sim.wire.ports import TransportConfig

log = logging.getLogger("beavr_sim.teleop.processes")

PROCESS_NAMES = ("operator", "twin")
#: Seconds without a message after which a stream's producer counts as dead.
LIVENESS_TIMEOUT_S = 0.5
HANDSHAKE_TIMEOUT_S = 10.0
#: A side without a hand frame for this many control periods is commanded on the clock (its
#: holds). More than one: a 30 Hz headset's frames come a period apart, with jitter, and a
#: clock command just before each would repeat the last frame's.
CLOCK_COMMAND_AFTER = 1.5


def _options_dict(options) -> dict:
    d = asdict(options)
    d["trace"] = str(options.trace) if options.trace is not None else None
    return d


# ---------------------------------------------------------------------------- operator
def operator_main(options: dict, transport: TransportConfig, conn) -> None:
    import zmq

    from beavr_sim.headset.sources import QuestSource, TraceSource
    from beavr_sim.headset.validation import StreamValidator
    from beavr_sim.operator.operator import Operator
    from beavr_sim.robots import make_embodiment
    from beavr_sim.wire.messages import JointCommandMsg, RobotStateMsg, SessionMsg
    from beavr_sim.wire.transport import Publisher, Subscriber

    context = zmq.Context()
    embodiment = make_embodiment(options["embodiment"])
    dt = 1.0 / options["control_hz"]
    operator = Operator(embodiment, dt)
    # The detector: the headset's sockets (or a trace in real time) in this process's event
    # loop; every valid frame is observed (none is dropped unseen).
    validator = StreamValidator()
    if options["source"] == "trace":
        source = TraceSource(options["trace"], real_time=True)
    else:
        source = QuestSource(context, transport, validator, latest_only=False)
    # A trace starts playing when the supervisor says every process is ready ("resume"), so
    # the operator anchors on its first frames as it would in one process.
    started = options["source"] != "trace"
    received = 0
    state = Subscriber(
        context,
        transport.endpoint("robot_state", bind=False),
        b"state",
        RobotStateMsg,
        liveness_timeout_s=LIVENESS_TIMEOUT_S,
    )
    session = Subscriber(
        context, transport.endpoint("session", bind=False), b"session", SessionMsg, conflate=False
    )
    commands = Publisher(context, transport.endpoint("commands", bind=True))
    commands.wait_for_subscribers(len(embodiment.effectors), HANDSHAKE_TIMEOUT_S)
    # Start from the twin's measured joints.
    first = state.recv(HANDSHAKE_TIMEOUT_S)
    slices, start = {}, 0
    for e in embodiment.effectors:
        slices[e.name] = slice(start, start + len(e.joints))
        start += len(e.joints)
    rehome = OperatorRehome(operator, slices)
    if first is not None:
        rehome.on_state(first)
    conn.send_bytes(b"ready")
    compute_ms: list[float] = []
    holds: dict[str, dict[str, int]] = {}
    errors: dict[str, int] = {}
    sides = list(options["sides"])
    side_effectors = {
        side: [e.name for e in embodiment.effectors if e.side == side] for side in sides
    }
    #: Per side: frames observed but not commanded on their own (a newer one was queued).
    superseded = dict.fromkeys(sides, 0)
    frames_commanded = dict.fromkeys(sides, 0)
    clock_commands = dict.fromkeys(sides, 0)
    # Each side's effectors are commanded when its hand frame arrives; a side without a
    # frame for CLOCK_COMMAND_AFTER control periods is commanded on the clock (holds:
    # tracking lost, paused, waiting), so the twin always hears from the operator.
    last_command = dict.fromkeys(sides, time.monotonic())
    poller = zmq.Poller()
    for socket in (*source.sockets, state.socket, session.socket):
        poller.register(socket, zmq.POLLIN)
    overruns = 0

    def guarded(what: str, fn, *args) -> tuple[bool, object]:
        return operator_call(errors, what, fn, *args)

    def send_hold(now: float, reason: str, names) -> None:
        """These effectors hold (the twin keeps their last targets)."""
        for name in names:
            count_hold(holds, name, reason)
            commands.send(
                name.encode(),
                JointCommandMsg(
                    effector=name,
                    t_source=0.0,
                    t_command=now,
                    positions=[],
                    hold=True,
                    reason=reason,
                    epoch=rehome.epoch,
                ),
            )

    def command_side(side: str, ok: bool) -> None:
        """Command ``side``'s effectors now, from what the operator has observed."""
        now = time.monotonic()
        dt_side = min(max(now - last_command[side], MIN_COMMAND_DT_S), dt)
        last_command[side] = now
        names = side_effectors[side]
        if rehome.waiting:
            # Hold until the twin's state after the reset comes: re-homing to a state from
            # before it would drive the robot back where it was.
            rehome.warn_if_late(now)
            send_hold(now, "resetting", names)
            return
        if ok:
            ok, out = guarded("command", operator.command, now, side, dt_side)
        if not ok:
            send_hold(now, "error", names)
            return
        for name, cmd in out.items():
            if cmd.hold:
                count_hold(holds, name, cmd.reason)
            t_source = cmd.t_source if np.isfinite(cmd.t_source) else 0.0
            commands.send(
                name.encode(),
                JointCommandMsg(
                    effector=name,
                    t_source=t_source,
                    t_command=now,
                    positions=cmd.positions.tolist(),
                    hold=cmd.hold,
                    reason=cmd.reason,
                    epoch=rehome.epoch,
                ),
            )

    receiver = getattr(source, "receiver", None)
    try:
        while True:
            due = min(last_command.values()) + CLOCK_COMMAND_AFTER * dt
            frame_due = source.next_due() if started else None
            if frame_due is not None:
                due = min(due, frame_due)
            poller.poll(max(0, math.ceil((due - time.monotonic()) * 1000)))
            msg = session.recv(0.0)
            if msg is not None:
                if msg.command == "stop":
                    break
                if msg.command in ("pause", "resume"):
                    operator.set_paused(msg.command == "pause")
                    started = started or msg.command == "resume"
                if msg.command == "reset":
                    rehome.expect(msg.epoch)
            latest = state.recv_latest(0.0)
            if latest is not None:
                guarded("reset", rehome.on_state, latest)
            by_side: dict[str, list] = {}
            for frame in source.poll(time.monotonic()) if started else ():
                received += 1
                if (source.validates or validator.check(frame) is None) and frame.side in sides:
                    by_side.setdefault(frame.side, []).append(frame)
            for side, frames in by_side.items():
                t0 = time.perf_counter()
                ok = True
                if not rehome.waiting:  # frames from before the reset are dropped
                    for frame in frames:
                        ok = guarded("observe", operator.observe, frame)[0] and ok
                    superseded[side] += len(frames) - 1
                    frames_commanded[side] += 1
                command_side(side, ok)
                compute_ms.append((time.perf_counter() - t0) * 1e3)
            now = time.monotonic()
            for side in sides:
                if now - last_command[side] >= CLOCK_COMMAND_AFTER * dt:
                    if now - last_command[side] > 1.1 * CLOCK_COMMAND_AFTER * dt:
                        overruns += 1
                    clock_commands[side] += 1
                    command_side(side, True)
    finally:
        conn.send_bytes(
            json.dumps(
                {
                    "compute_ms": _percentiles(compute_ms),
                    "operator": {n: asdict(op.stats) for n, op in operator.effectors.items()},
                    "holds": holds,
                    "errors": errors,
                    "reset_epoch": rehome.epoch,
                    "overruns": overruns,
                    "missed_ticks": 0,
                    "frames_superseded": superseded,
                    "frames_commanded": frames_commanded,
                    "clock_commands": clock_commands,
                    "detector": {
                        "frames_received": received,
                        "frames_rejected": validator.rejected,
                        "rejected_by_reason": validator.rejected_by_reason,
                        # Quest source: payloads per stream, and frames replaced by a newer
                        # one in the same poll (0: every frame is passed on)
                        "quest_received": dict(receiver.received) if receiver else {},
                        "frames_superseded": dict(receiver.superseded) if receiver else {},
                    },
                }
            ).encode()
        )
        source.close()
        for s in (state, session, commands):
            s.close()
        context.term()


#: The twin's states carry the task's fixtures for this long after each reset (episode time,
#: s): the operator takes them from the first such state of the epoch, and the states after
#: stay small.
FIXTURES_FOR_S = 2.0


def fixtures_to_wire(env) -> list:
    """The env's fixtures as its reset placed them, for the robot state messages."""
    from beavr_sim.operator.obstacles import fixture_obstacles
    from beavr_sim.wire.messages import FixtureMsg

    return [
        FixtureMsg(
            name=o.name,
            pos=list(o.pos),
            quat=list(o.quat),
            geoms=[[float(g.type), *g.size, *g.pos, *g.quat] for g in o.geoms],
        )
        for o in fixture_obstacles(env.model, env.data)
    ]


def obstacles_from_wire(fixtures) -> tuple:
    """:func:`fixtures_to_wire`'s messages back as the operator's obstacles."""
    from beavr_sim.operator.obstacles import Obstacle, ObstacleGeom

    return tuple(
        Obstacle(
            f.name,
            tuple(ObstacleGeom(int(g[0]), g[1:4], g[4:7], g[7:11]) for g in f.geoms),
            tuple(f.pos),
            tuple(f.quat),
        )
        for f in fixtures
    )


class OperatorRehome:
    """The operator process's side of reset epochs.

    The twin stamps every robot state with its reset epoch (how many resets it has done).
    The operator re-homes from the first state of every newer epoch (a reset from the
    supervisor or the twin's own browser view) and ignores older ones. A reset request
    (:meth:`expect`) names the epoch the twin's states will carry at least after it; until
    one comes the operator holds (:attr:`waiting`), so it never re-homes to a state published
    before the reset, which the latest-only state stream can still hand it.
    """

    #: Seconds after a reset request without the twin's new state before a warning.
    WARN_AFTER_S = 1.0

    def __init__(self, operator, slices: dict[str, slice], clock=time.monotonic):
        self.operator = operator
        self.slices = slices
        self.clock = clock
        #: Epoch of the state the operator last re-homed from.
        self.epoch = 0
        self.homed = False  # no state yet: hold
        self.expected = 0
        self._since: float | None = None
        self._warned = False
        self._fixtures_epoch = -1  # the epoch whose fixtures the IK has

    @property
    def waiting(self) -> bool:
        """Holding: no state yet, or none since the reset requested last."""
        return not self.homed or self.epoch < self.expected

    def expect(self, epoch: int) -> None:
        """A reset was requested: hold until a state of ``epoch`` (0: the next epoch)."""
        self.expected = max(self.expected, epoch if epoch > 0 else self.epoch + 1)
        self._since, self._warned = self.clock(), False

    def on_state(self, msg) -> None:
        """Take a robot state: re-home on a newer epoch, continue from the guard's held
        action within the current one, ignore an older one."""
        if msg.epoch > self.epoch or not self.homed:
            self.operator.reset(np.asarray(msg.positions), self.slices)
            self._fixtures_epoch = -1
            self.epoch, self.homed = msg.epoch, True
            if not self.waiting:
                self._since = None
        if msg.epoch == self.epoch and msg.fixtures and self._fixtures_epoch != msg.epoch:
            self._fixtures_epoch = msg.epoch  # tried once per epoch
            try:
                self.operator.set_obstacles(obstacles_from_wire(msg.fixtures))
            except (ValueError, RuntimeError) as exc:  # the guard still keeps the robot off
                log.warning("fixtures of epoch %d not usable by the IK: %s", msg.epoch, exc)
        if msg.epoch == self.epoch and msg.guard_blocked_effectors:  # continue where held
            for name in msg.guard_blocked_effectors:
                if name in self.slices:
                    self.operator.resync(name, np.asarray(msg.action)[self.slices[name]])

    def warn_if_late(self, now: float) -> None:
        if self._since is not None and not self._warned and now - self._since > self.WARN_AFTER_S:
            self._warned = True
            log.warning(
                "no robot state after the reset (epoch %d) for %.1f s: holding until it comes",
                self.expected,
                now - self._since,
            )


# ---------------------------------------------------------------------------- twin
def twin_main(options: dict, transport: TransportConfig, conn) -> None:
    import gymnasium as gym
    import zmq

    import beavr_sim  # noqa: F401
    from beavr_sim.twin.twin import TwinInterface
    from beavr_sim.wire.messages import JointCommandMsg, RobotStateMsg, SessionMsg
    from beavr_sim.wire.records import JointCommand
    from beavr_sim.wire.transport import Publisher, Subscriber

    context = zmq.Context()
    kwargs = {} if options["source"] == "trace" else {"max_episode_seconds": 1e9}
    if options.get("leap_variant"):
        kwargs["hand_variant"] = options["leap_variant"]
    env = gym.make(
        f"beavr_sim/{options['task']}-v0", embodiment=options["embodiment"], **kwargs
    ).unwrapped
    twin = TwinInterface(env)
    twin.reset(options["seed"])
    mirror = None
    closers = []
    if options.get("mirror_hardware"):
        from beavr_sim.hardware.device import MirrorError
        from beavr_sim.hardware.mirror import Fixtures
        from beavr_sim.teleop.mirroring import MIRROR_SWITCH_INTERVAL_S, connect_mirror

        try:
            mirror, q_measured = connect_mirror(options, env, closers)
        except (MirrorError, ValueError, FileNotFoundError) as exc:
            for close in reversed(closers):
                close()
            conn.send_bytes(f"error: {exc}".encode())
            env.close()
            return
        twin.reset(options["seed"], q_measured)  # the twin starts where the robot stands
        sys.setswitchinterval(MIRROR_SWITCH_INTERVAL_S)  # see teleop/mirroring.py
        mirror.start(twin.action)
        mirror.begin_episode(twin.action.copy(), Fixtures.of(env.data))  # its guard: fixtures
    fixtures = fixtures_to_wire(env)
    subs = {
        e.name: Subscriber(
            context,
            transport.endpoint("commands", bind=False),
            e.name.encode(),
            JointCommandMsg,
            liveness_timeout_s=LIVENESS_TIMEOUT_S,
        )
        for e in env.embodiment.effectors
    }
    session = Subscriber(
        context, transport.endpoint("session", bind=False), b"session", SessionMsg, conflate=False
    )
    state_pub = Publisher(context, transport.endpoint("robot_state", bind=True))
    state_pub.wait_for_subscribers(2, HANDSHAKE_TIMEOUT_S)  # operator + supervisor
    view = None
    if options["viser"]:
        from beavr_sim.viz.twin_view import TwinView, subtree_bodies

        joints = env.joints
        view = TwinView(
            env.render_model,
            host=options["viser_host"],
            port=options["viser_port"],
            task=env.task.name,
            embodiment=env.embodiment.name,
            effector_bodies=subtree_bodies(
                env.model, {n: joints.names[sl] for n, sl in joints.slices.items()}
            ),
            rate_hz=options.get("viser_rate_hz", 30.0),
            show_collision=options.get("show_collision", False),
            mirroring=mirror is not None,
        )
        print(f"browser view: {view.url}", file=sys.stderr, flush=True)
    browser_estop = None
    if view is not None and mirror is not None:
        from beavr_sim.teleop.mirroring import BrowserEstop

        browser_estop = BrowserEstop(view, mirror)
    poller = zmq.Poller()
    for sub in (*subs.values(), session):
        poller.register(sub.socket, zmq.POLLIN)
    conn.send_bytes(b"ready")
    latencies: list[float] = []
    blocked: set[str] = set()  # effectors the guard blocked since the last view update
    success = False
    details: dict = {}
    dt = 1.0 / env.control_hz
    # The physics steps on its own real-time clock, one control period at a time; commands
    # are guarded and written to the actuators (and handed to the mirror) when they arrive,
    # in between. A stall moves the grid on (no catch-up steps).
    schedule = TickSchedule(dt)
    schedule.restart(time.monotonic() + dt)
    last_t_source: dict[str, float] = {}
    # Optional timing log for ``python -m beavr_sim.bench latency`` (off unless the option
    # names a file): every command applied, (t_apply, t_source) per effector, and every
    # action handed to the hardware mirror, (t_submit, {effector: t_source in effect}).
    latency_log = options.get("latency_log")
    applied_log: dict[str, list] = {e.name: [] for e in env.embodiment.effectors}
    # and per command applied: (detector's stamp, operator's command time, twin took it,
    # applied), to say where the time goes
    stage_log: dict[str, list] = {e.name: [] for e in env.embodiment.effectors}
    submit_log: list = []
    in_effect: dict[str, float] = {}
    epoch = 0  # resets done: stamped on every state; commands of an older epoch are dropped
    stale: dict[str, int] = {}
    positions = twin.action.copy()  # the twin's measured joints after its last step
    submitted = False  # an action went to the mirror since the last step
    command_poller = zmq.Poller()
    for sub in subs.values():
        command_poller.register(sub.socket, zmq.POLLIN)

    def take_commands() -> None:
        """Every effector's newest command, guarded, written to the actuators' targets and
        handed to the mirror at once."""
        nonlocal submitted
        t_take = time.monotonic()
        applied, t_command = {}, {}
        for name, sub in subs.items():
            cmd = sub.recv_latest(0.0)
            if cmd is None:
                continue
            if cmd.epoch < epoch:  # computed from the pose before a reset: hold
                stale[name] = stale.get(name, 0) + 1
                continue
            if cmd.hold or not cmd.positions:
                continue  # holding: keep the last targets
            applied[name] = JointCommand(
                effector=name,
                positions=np.asarray(cmd.positions),
                t_source=cmd.t_source,
                t_receive=cmd.t_source,
            )
            t_command[name] = cmd.t_command
        if not applied:
            return
        outcome = twin.command(applied)
        t_apply = twin.applied_monotonic
        for name in outcome.accepted:
            t_source = applied[name].t_source
            if t_source > 0 and t_source != last_t_source.get(name):
                latencies.append((t_apply - t_source) * 1e3)
                last_t_source[name] = t_source
            if latency_log:
                applied_log[name].append((t_apply, t_source))
                stage_log[name].append((t_source, t_command[name], t_take, t_apply))
                in_effect[name] = t_source
        if mirror is not None:  # the guarded action, the moment it is applied
            if latency_log:
                submit_log.append((time.monotonic(), dict(in_effect)))
            mirror.submit(twin.action.copy(), positions, outcome.blocked)
            submitted = True

    def between_substeps() -> None:
        # Commands that arrive while the physics steps are taken between its substeps.
        if command_poller.poll(0):
            take_commands()

    env.between_substeps = between_substeps
    try:
        while True:
            remaining = schedule.next - time.monotonic()
            if remaining > 0:
                poller.poll(math.ceil(remaining * 1000))
            msg = session.recv(0.0)
            if msg is not None and msg.command == "stop":
                break
            reset = msg is not None and msg.command == "reset"
            if reset or (view is not None and view.take_reset()):  # supervisor or browser
                positions = twin.reset(options["seed"])
                epoch = max(epoch + 1, msg.epoch if reset else 0)
                fixtures = fixtures_to_wire(env)
                if mirror is not None:  # the devices catch up with the twin's start, guarded
                    mirror.begin_episode(twin.action.copy(), Fixtures.of(env.data))
            if msg is not None and mirror is not None and msg.command == "estop":
                mirror.estop("keyboard")
            if msg is not None and mirror is not None and msg.command == "release":
                mirror.release()
            take_commands()
            now = time.monotonic()
            if now < schedule.next:
                continue
            schedule.take(now)
            st = twin.step()
            positions = st.positions
            if mirror is not None:
                if not submitted:  # no command this period: the same targets (heartbeat)
                    if latency_log:
                        submit_log.append((time.monotonic(), dict(in_effect)))
                    mirror.submit(st.action, st.positions, st.guard_blocked_effectors)
                submitted = False
                if browser_estop is not None:
                    browser_estop(None)
            success = success or st.success
            details = {k: v for k, v in st.info.items() if k.startswith("task/")}
            state_pub.send(
                b"state",
                RobotStateMsg(
                    t=st.t,
                    positions=st.positions.tolist(),
                    velocities=st.velocities.tolist(),
                    success=success,
                    guard_blocked=st.guard_blocked,
                    guard_blocked_effectors=list(st.guard_blocked_effectors),
                    action=st.action.tolist() if st.guard_blocked_effectors else [],
                    epoch=epoch,
                    fixtures=fixtures if st.t < FIXTURES_FOR_S else [],
                ),
            )
            if view is not None:
                if st.guard_blocked:  # shown at the next update even if it cleared since
                    blocked |= set(st.guard_blocked_effectors or view.guard.geoms)
                if view.due():
                    view.update(
                        env.data,
                        status=f"t = {st.t:5.1f} s · {'success' if success else 'running'}",
                        guard_blocked=blocked,
                        success=success,
                    )
                    blocked = set()
    finally:
        hardware = {}
        if mirror is not None:
            mirror.close()
            hardware = mirror.summary()
        if latency_log:
            _write_latency_log(
                latency_log, env.control_hz, applied_log, submit_log, mirror, stage_log
            )
        for close in reversed(closers):
            close()
        conn.send_bytes(
            json.dumps(
                {
                    "hardware": hardware,
                    "success": success,
                    "objects": {
                        n: o.pos(env.data).round(3).tolist()
                        for n, o in {**env.task.objects, **env.task.fixtures}.items()
                    },
                    "task_details": {
                        k: v for k, v in details.items() if isinstance(v, (bool, int, float, str))
                    },
                    "commands_applied": twin.commands_applied,
                    "guard_blocks": dict(twin.guard_blocks),
                    "step_limited": {
                        n: int(v) for n, v in getattr(twin, "step_limited", {}).items()
                    },
                    "stale_commands": stale,
                    "reset_epoch": epoch,
                    "overruns": schedule.overruns,
                    "missed_ticks": schedule.missed_ticks,
                    "latency_ms": _percentiles(latencies),
                    "duration_s": env.elapsed_seconds,
                    "task": env.task.name,
                    "embodiment": env.embodiment.name,
                }
            ).encode()
        )
        if view is not None:
            view.close()
        state_pub.close()
        for s in (*subs.values(), session):
            s.close()
        env.close()
        context.term()


def _write_latency_log(path, control_hz, applied_log, submit_log, mirror, stage_log) -> None:
    """The twin's timing log (``options["latency_log"]``) as JSON: see ``bench/latency.py``."""
    links = []
    if mirror is not None:
        for link, effector in zip(mirror.links, mirror._link_effector, strict=True):
            links.append(
                {
                    "name": link.name,
                    "effector": effector,
                    # monotonic time the writer took the tick, and ms from the tick's
                    # hand-off to the first write having left the driver
                    "write_times": list(link.stats.write_times),
                    "write_latency_ms": list(link.stats.write_latency_ms),
                }
            )
    with open(path, "w") as f:
        json.dump(
            {
                "control_hz": control_hz,
                "applied": applied_log,
                "stages": stage_log,
                "submits": submit_log,
                "links": links,
            },
            f,
        )


TARGETS = {"operator": operator_main, "twin": twin_main}


class MultiprocessSession:
    """Starts the three processes, watches them, stops them; see the module docstring."""

    def __init__(self, options, transport: TransportConfig | None = None):
        from beavr_sim.robots import make_embodiment
        from beavr_sim.robots.embodiment import DEFAULT_EMBODIMENT

        self.transport = transport or options.transport or TransportConfig()
        opts = _options_dict(options)
        opts.pop("transport", None)
        if options.source == "trace":
            from beavr_sim.traces.format import TraceReader

            meta = TraceReader(options.trace).metadata
            opts["embodiment"] = opts["embodiment"] or meta.embodiment or None
            opts["seed"] = opts["seed"] if opts["seed"] is not None else meta.seed
        opts["embodiment"] = opts["embodiment"] or DEFAULT_EMBODIMENT
        embodiment = make_embodiment(opts["embodiment"])
        opts["sides"] = sorted({e.side for e in embodiment.effectors})
        opts["control_hz"] = 30.0
        self.options = opts
        self.ctx = mp.get_context("spawn")
        self.processes: dict[str, mp.process.BaseProcess] = {}
        self.pipes: dict[str, object] = {}
        self.results: dict[str, dict] = {}
        self.exits: dict[str, int | None] = {}
        #: Resets requested (each names the reset epoch the operator waits for).
        self.resets = 0

    def start(self) -> None:
        import zmq

        from beavr_sim.wire.messages import RobotStateMsg, SessionMsg
        from beavr_sim.wire.transport import Publisher, Subscriber

        self.context = zmq.Context()
        self.session_pub = Publisher(self.context, self.transport.endpoint("session", bind=True))
        self.state_sub = Subscriber(
            self.context,
            self.transport.endpoint("robot_state", bind=False),
            b"state",
            RobotStateMsg,
            liveness_timeout_s=LIVENESS_TIMEOUT_S,
        )
        self._session_type = SessionMsg
        for name in ("twin", "operator"):
            parent, child = self.ctx.Pipe()
            proc = self.ctx.Process(
                target=TARGETS[name],
                args=(self.options, self.transport, child),
                name=name,
                daemon=True,
            )
            proc.start()
            self.processes[name], self.pipes[name] = proc, parent
        for name, pipe in self.pipes.items():
            if not pipe.poll(60.0):
                self.stop()
                raise RuntimeError(f"{name} process did not become ready within 60 s")
            reply = pipe.recv_bytes()
            if reply != b"ready":
                self.stop()
                from beavr_sim.hardware.device import MirrorError

                raise MirrorError(reply.decode(errors="replace").removeprefix("error: "))
        self.session_pub.wait_for_subscribers(len(TARGETS), HANDSHAKE_TIMEOUT_S)
        self.send("resume")  # everyone is ready: the operator starts a trace now

    def send(self, command: str) -> None:
        """Send a session command; a ``"reset"`` names the epoch the twin will be in after it
        (at least: a reset from the twin's browser view counts too)."""
        epoch = 0
        if command == "reset":
            self.resets += 1
            epoch = self.resets
        self.session_pub.send(
            b"session", self._session_type(command=command, t=time.monotonic(), epoch=epoch)
        )

    def dead(self) -> list[str]:
        return [n for n, p in self.processes.items() if not p.is_alive()]

    def stop(self) -> None:
        self.send("stop")
        for name, proc in self.processes.items():
            pipe = self.pipes[name]
            if pipe.poll(5.0 if proc.is_alive() else 0.1):
                try:
                    self.results[name] = json.loads(pipe.recv_bytes())
                except (EOFError, ValueError):
                    pass
            proc.join(5.0)
            if proc.is_alive():
                proc.kill()
                proc.join(1.0)
            self.exits[name] = proc.exitcode
        self.session_pub.close()
        self.state_sub.close()
        self.context.term()

    def run(self, max_seconds: float | None, stop_on_success: bool) -> TeleopSummary:
        self.start()
        requests: list[str] = []  # from the keyboard thread; sent from this one
        if self.options.get("mirror_hardware") and sys.stdin is not None and sys.stdin.isatty():
            from beavr_sim.teleop.episodes import KeyboardControl

            keyboard = KeyboardControl(
                None,
                actions={
                    "e": ("emergency stop (every device holds)", lambda: requests.append("estop")),
                    "r": ("release the emergency stop", lambda: requests.append("release")),
                },
            )
            print(keyboard.help, file=sys.stderr)
        reported: set[str] = set()
        t0 = time.monotonic()
        success = False
        try:
            while True:
                state = self.state_sub.recv_latest(0.1)
                while requests:
                    self.send(requests.pop(0))
                if state is not None:
                    success = success or state.success
                for name in self.dead():
                    if name not in reported:
                        reported.add(name)
                        log.error(
                            "%s process died (exit code %s); the others keep running and the "
                            "robot holds",
                            name,
                            self.processes[name].exitcode,
                        )
                elapsed = time.monotonic() - t0
                if (success and stop_on_success) or (max_seconds and elapsed >= max_seconds):
                    break
                if "twin" in reported:
                    break
        finally:
            self.stop()
        return self.summary(success, died=reported)

    def summary(self, success: bool = False, died=()) -> TeleopSummary:
        """The session's summary from the processes' final reports (after :meth:`stop`);
        ``died``: processes that died while it ran."""
        op, twin = self.results.get("operator", {}), self.results.get("twin", {})
        det = op.get("detector", {})
        return TeleopSummary(
            task=twin.get("task", self.options["task"]),
            embodiment=twin.get("embodiment", self.options["embodiment"]),
            success=bool(twin.get("success", success)),
            frames_received=det.get("frames_received", 0),
            frames_rejected=det.get("frames_rejected", 0),
            commands_applied=twin.get("commands_applied", 0),
            duration_s=twin.get("duration_s", 0.0),
            latency_ms=twin.get("latency_ms", _percentiles([])),
            rejected_by_reason=det.get("rejected_by_reason", {}),
            holds=merged_holds(op, twin),
            operator=op.get("operator", {}),
            processes={n: ("died" if n in died else "ok") for n in self.processes},
            guard_blocks=twin.get("guard_blocks", {}),
            hardware=twin.get("hardware", {}),
            overruns=op.get("overruns", 0) + twin.get("overruns", 0),
            missed_ticks=op.get("missed_ticks", 0) + twin.get("missed_ticks", 0),
            frames_superseded=sum(det.get("frames_superseded", {}).values())
            + sum(op.get("frames_superseded", {}).values()),
        )


def merged_holds(operator: dict, twin: dict) -> dict[str, dict[str, int]]:
    """The summary's holds (effector -> reason -> ticks) from the processes' reports: the
    operator's hold reasons, and the twin's guard refusals, step clamps and commands dropped
    as computed before a reset."""
    holds = {name: dict(by_reason) for name, by_reason in operator.get("holds", {}).items()}
    for key, reason in (
        ("guard_blocks", "guard"),
        ("step_limited", "step_limit"),
        ("stale_commands", "stale_after_reset"),
    ):
        for name, n in twin.get(key, {}).items():
            if n:
                count_hold(holds, name, reason, int(n))
    return holds


def run_multiprocess(options) -> TeleopSummary:
    return MultiprocessSession(options).run(
        options.max_seconds, stop_on_success=options.source == "trace"
    )
