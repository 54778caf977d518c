"""``--multiprocess``: detector, operator and twin as separate processes over ZeroMQ.

The same components as the single-process loop (``pipeline.py``), connected by the transport
(``transport.py``, ports from ``config.py``):

    detector  --hands_right/hands_left (HandFrameMsg)-->  operator
    operator  --commands (JointCommandMsg, topic = effector)-->  twin
    twin      --robot_state (RobotStateMsg, every tick: its heartbeat)-->  operator, supervisor
    supervisor --session (SessionMsg)-->  operator, twin

Each process creates its own ZMQ context, owns its sockets in its main thread, and runs on
the real clock. Latest-only streams are conflated. Publishers wait for their subscribers
(readiness handshake) before the session starts. Killing any one process leaves the others
alive: the twin keeps the last targets (the robot holds) when commands stop, the operator
holds when hand frames stop; the supervisor reports the death and stops on its own terms.
Processes are started with the ``spawn`` method (no state inherited from the parent) and
report their final counters to the supervisor as JSON over a pipe.
"""

from __future__ import annotations

import json
import logging
import multiprocessing as mp
import sys
import time
from dataclasses import asdict

import numpy as np

from beavr_sim.teleop.pipeline import TeleopSummary, _percentiles
from beavr_sim.wire.ports import TransportConfig

log = logging.getLogger("beavr_sim.teleop.processes")

PROCESS_NAMES = ("detector", "operator", "twin")
#: Seconds without a message after which a stream's producer counts as dead.
LIVENESS_TIMEOUT_S = 0.5
HANDSHAKE_TIMEOUT_S = 10.0


def _options_dict(options) -> dict:
    d = asdict(options)
    d["trace"] = str(options.trace) if options.trace is not None else None
    return d


def _stop_requested(session_sub) -> str | None:
    msg = session_sub.recv(0.0)
    return None if msg is None else msg.command


# ---------------------------------------------------------------------------- detector
def detector_main(options: dict, transport: TransportConfig, conn) -> None:
    import zmq

    from beavr_sim.headset.sources import QuestSource, TraceSource
    from beavr_sim.headset.validation import StreamValidator
    from beavr_sim.wire.messages import HandFrameMsg, SessionMsg
    from beavr_sim.wire.transport import Publisher, Subscriber

    context = zmq.Context()
    validator = StreamValidator()
    pubs = {
        side: Publisher(context, transport.endpoint(f"hands_{side}", bind=True))
        for side in ("right", "left")
    }
    session = Subscriber(
        context, transport.endpoint("session", bind=False), b"session", SessionMsg, conflate=False
    )
    if options["source"] == "trace":
        source = TraceSource(options["trace"], real_time=True)
    else:
        source = QuestSource(context, transport, validator)
    sides = options["sides"]
    for side in sides:
        pubs[side].wait_for_subscribers(1, HANDSHAKE_TIMEOUT_S)
    conn.send_bytes(b"ready")
    received = 0
    # A trace starts playing when the supervisor says every process is ready ("resume"), so
    # the operator anchors on its first frames as it would in one process.
    started = options["source"] != "trace"
    try:
        while True:
            command = _stop_requested(session)
            if command == "stop":
                break
            if not started:
                started = command == "resume"
                time.sleep(0.002)
                continue
            for frame in source.poll(time.monotonic()):
                received += 1
                valid = source.validates or validator.check(frame) is None
                if valid and frame.side in pubs:
                    pubs[frame.side].send(frame.side.encode(), HandFrameMsg.from_frame(frame))
            time.sleep(0.002)
    finally:
        conn.send_bytes(
            json.dumps(
                {
                    "frames_received": received,
                    "frames_rejected": validator.rejected,
                    "rejected_by_reason": validator.rejected_by_reason,
                }
            ).encode()
        )
        source.close()
        for p in pubs.values():
            p.close()
        session.close()
        context.term()


# ---------------------------------------------------------------------------- operator
def operator_main(options: dict, transport: TransportConfig, conn) -> None:
    import zmq

    from beavr_sim.operator.operator import Operator
    from beavr_sim.robots import make_embodiment
    from beavr_sim.wire.messages import HandFrameMsg, JointCommandMsg, RobotStateMsg, SessionMsg
    from beavr_sim.wire.transport import Publisher, Subscriber

    context = zmq.Context()
    embodiment = make_embodiment(options["embodiment"])
    dt = 1.0 / options["control_hz"]
    operator = Operator(embodiment, dt)
    # Hand frames are not conflated: the operator's filters take every frame (drained each
    # tick); commands and robot state are latest-only.
    hands = {
        side: Subscriber(
            context,
            transport.endpoint(f"hands_{side}", bind=False),
            side.encode(),
            HandFrameMsg,
            liveness_timeout_s=LIVENESS_TIMEOUT_S,
            conflate=False,
        )
        for side in options["sides"]
    }
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
    if first is not None:
        operator.reset(np.asarray(first.positions), slices)
    conn.send_bytes(b"ready")
    compute_ms: list[float] = []
    next_tick = time.monotonic()
    try:
        while True:
            msg = session.recv(0.0)
            if msg is not None:
                if msg.command == "stop":
                    break
                if msg.command in ("pause", "resume"):
                    operator.set_paused(msg.command == "pause")
                if msg.command == "reset":
                    latest = state.recv_latest(1.0)
                    if latest is not None:
                        operator.reset(np.asarray(latest.positions), slices)
            held = state.recv(0.0)
            if held is not None and held.guard_blocked_effectors:  # continue where held
                for name in held.guard_blocked_effectors:
                    if name in slices:
                        operator.resync(name, np.asarray(held.action)[slices[name]])
            t0 = time.perf_counter()
            for sub in hands.values():
                while (frame_msg := sub.recv(0.0)) is not None:
                    operator.observe(frame_msg.to_frame())
            now = time.monotonic()
            for name, cmd in operator.command(now).items():
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
                    ),
                )
            compute_ms.append((time.perf_counter() - t0) * 1e3)
            next_tick += dt
            time.sleep(max(0.0, next_tick - time.monotonic()))
    finally:
        conn.send_bytes(
            json.dumps(
                {
                    "compute_ms": _percentiles(compute_ms),
                    "operator": {n: asdict(op.stats) for n, op in operator.effectors.items()},
                }
            ).encode()
        )
        for s in (*hands.values(), state, session, commands):
            s.close()
        context.term()


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
    env = gym.make(
        f"beavr_sim/{options['task']}-v0", embodiment=options["embodiment"], **kwargs
    ).unwrapped
    twin = TwinInterface(env)
    twin.reset(options["seed"])
    mirror = None
    closers = []
    if options.get("mirror_hardware"):
        from beavr_sim.hardware.device import MirrorError
        from beavr_sim.teleop.mirroring import connect_mirror

        try:
            mirror, q_measured = connect_mirror(options, env, closers)
        except (MirrorError, ValueError, FileNotFoundError) as exc:
            for close in reversed(closers):
                close()
            conn.send_bytes(f"error: {exc}".encode())
            env.close()
            return
        twin.reset(options["seed"], q_measured)  # the twin starts where the robot stands
        mirror.start(twin.action)
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
            env.model,
            host=options["viser_host"],
            port=options["viser_port"],
            task=env.task.name,
            embodiment=env.embodiment.name,
            effector_bodies=subtree_bodies(
                env.model, {n: joints.names[sl] for n, sl in joints.slices.items()}
            ),
            rate_hz=options.get("viser_rate_hz", 30.0),
            mirroring=mirror is not None,
        )
        print(f"browser view: {view.url}", file=sys.stderr, flush=True)
    browser_estop = None
    if view is not None and mirror is not None:
        from beavr_sim.teleop.mirroring import BrowserEstop

        browser_estop = BrowserEstop(view, mirror)
    poller = zmq.Poller()
    for sub in subs.values():
        poller.register(sub.socket, zmq.POLLIN)
    conn.send_bytes(b"ready")
    latencies: list[float] = []
    blocked: set[str] = set()  # effectors the guard blocked since the last view update
    success = False
    details: dict = {}
    dt = 1.0 / env.control_hz
    next_tick = time.monotonic()
    last_t_source: dict[str, float] = {}
    try:
        while True:
            msg = session.recv(0.0)
            if msg is not None and msg.command == "stop":
                break
            if msg is not None and msg.command == "reset":
                twin.reset(options["seed"])
            if msg is not None and mirror is not None and msg.command == "estop":
                mirror.estop("keyboard")
            if msg is not None and mirror is not None and msg.command == "release":
                mirror.release()
            # Step as soon as every effector's next command is in (the operator paces the
            # twin: least latency), or at the control period's end without it (the operator
            # is slow or dead: the robot holds its last targets).
            commands: dict = {}
            deadline = next_tick + dt
            while len(commands) < len(subs):
                for name, sub in subs.items():
                    cmd = sub.recv_latest(0.0)
                    if cmd is not None:
                        commands[name] = cmd
                remaining = deadline - time.monotonic()
                if len(commands) == len(subs) or remaining <= 0:
                    break
                poller_events = dict(poller.poll(max(1, int(remaining * 1000))))
                if not poller_events:
                    break
            applied = {}
            for name, cmd in commands.items():
                if cmd.hold or not cmd.positions:
                    continue  # holding: keep the last targets
                applied[name] = JointCommand(
                    effector=name,
                    positions=np.asarray(cmd.positions),
                    t_source=cmd.t_source,
                    t_receive=cmd.t_source,
                )
                if cmd.t_source > 0 and cmd.t_source != last_t_source.get(name):
                    latencies.append((time.monotonic() - cmd.t_source) * 1e3)
                    last_t_source[name] = cmd.t_source
            commands = applied
            st = twin.apply(commands)
            if mirror is not None:  # the same guarded action, the same tick
                mirror.submit(st.action, st.positions, st.guard_blocked_effectors)
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
            next_tick = max(next_tick + dt, time.monotonic() - dt)
    finally:
        hardware = {}
        if mirror is not None:
            mirror.close()
            hardware = mirror.summary()
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


TARGETS = {"detector": detector_main, "operator": operator_main, "twin": twin_main}


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
        for name in ("twin", "operator", "detector"):
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
        self.session_pub.wait_for_subscribers(3, HANDSHAKE_TIMEOUT_S)
        self.send("resume")  # everyone is ready: the detector starts a trace now

    def send(self, command: str) -> None:
        self.session_pub.send(b"session", self._session_type(command=command, t=time.monotonic()))

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
        det, twin = self.results.get("detector", {}), self.results.get("twin", {})
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
            operator=self.results.get("operator", {}).get("operator", {}),
            processes={n: ("died" if n in reported else "ok") for n in self.processes},
            hardware=twin.get("hardware", {}),
        )


def run_multiprocess(options) -> TeleopSummary:
    return MultiprocessSession(options).run(
        options.max_seconds, stop_on_success=options.source == "trace"
    )
