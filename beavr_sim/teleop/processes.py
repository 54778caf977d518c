"""``--multiprocess``: the operator (with the detector) and the twin as processes over ZeroMQ.

The same components as the single-process loop (``pipeline.py``), connected by the transport
(``transport.py``, ports from ``ports.py``). This module is the supervisor
(:class:`MultiprocessSession`, :func:`process_configs`, :func:`run_multiprocess`); the
processes are :func:`~beavr_sim.teleop.operator_process.operator_main` and
:func:`~beavr_sim.teleop.twin_process.twin_main`, each built from its frozen config
(:mod:`beavr_sim.teleop.process_config`):

    headset   --Quest app's PUSH strings-->  operator (detector + operator)
    operator  --commands (JointCommandMsg, topic = effector)-->  twin
    twin      --robot_state (RobotStateMsg, every tick: its heartbeat)-->  operator, supervisor
    supervisor --session (SessionMsg)-->  operator, twin
    twin      --camera panels (CameraPanelMsg, --camera-stream-hz, WebXR)-->  operator
    twin      --the page's twin (TwinSceneMsg once, TwinPosesMsg; WebXR, not headless)-->  operator

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

The per-frame path is the one of the single-process loop: both processes run its stages
(``stages.py``: the operator process an :class:`~beavr_sim.teleop.stages.OperatorStage`, the
twin process a :class:`~beavr_sim.teleop.stages.TwinStage`, whose hooks the mirror and
:class:`Attachment` s follow), each built from its frozen config (:class:`OperatorProcessConfig`,
:class:`TwinProcessConfig`) passed whole to the spawned process. The operator forwards the
both-hands-pinch e-stop to the twin (:class:`~beavr_sim.wire.messages.OperatorEventMsg`, which
latches the mirror); the twin's states carry whether the operator holds paused (the browser
view's Pause or e-stop, the mirror's latched e-stop). Mirrored, the twin brings the rig to the
episode's start pose before the episode (and after a reset) with the session's
:class:`~beavr_sim.teleop.mirroring.RigSync`, holding the start and dropping the operator's
commands meanwhile (lockstep: its states ask no tick); a rig that does not sync ends the
session (a ``done`` state; ``stopped_early`` in its report).

On the virtual and paced clocks (a trace) the processes run in lockstep: the twin publishes
the state of tick k, the operator answers it as one process's tick k (the frames up to k * dt,
every effector commanded), and the twin applies those commands and steps only once every
effector's arrived; paced, each tick's state is published at its wall deadline. A replay is
then the same episode as in one process, command for command.

The twin process plays the session's runs (a ``--repeat`` trace, recorded ``--episodes``:
:class:`~beavr_sim.teleop.twin_runs.TwinRuns`, with the single-process session's per-run
decisions) and records them (the recorder on its stage's ``after_step`` hook, fed the hands'
keypoints the operator sends on the command stream, :class:`~beavr_sim.wire.messages.HandKeypointsMsg`);
its states carry the run, and the operator plays a trace from its start on a new run. Live
recorded episodes start and stop on requests taken there: the supervisor's keyboard (session
commands ``record_*``), the browser view's buttons, the operator's record gesture (an
:class:`~beavr_sim.wire.messages.OperatorEventMsg`). Real cameras (``--camera``) are read there
next to the recorder and streamed from there (``--camera-stream-hz``:
:mod:`beavr_sim.teleop.twin_camera_stream`), its env places ``--camera-poses``' cameras, and
``--rerun`` logs from a hook of its stage (:mod:`beavr_sim.teleop.twin_rerun`). A single real-time run without recording
is ended by the supervisor (success, ``--max-seconds``). The WebXR page draws the twin from
its scene and poses sent by the twin process to the operator's page server
(:mod:`beavr_sim.teleop.twin_page_stream`).

Resets are numbered (epochs): the twin stamps every state with its epoch and drops commands
of an older one; the operator re-homes from the first state of a newer epoch only, and after
a reset request holds until that state comes (:class:`~beavr_sim.teleop.operator_process.OperatorRehome`). The twin's physics
ticks on a :class:`~beavr_sim.teleop.pipeline.TickSchedule` (after a stall: no catch-up
burst, the skipped periods counted); an operator exception holds that side's effectors for a
command (reason ``"error"``), it never ends the process.
"""

from __future__ import annotations

import dataclasses
import json
import logging
import multiprocessing as mp
import sys
import time

import zmq

import beavr_sim  # noqa: F401  (registers the envs the twin process makes)
from beavr_sim.envs.beavr_env import DEFAULT_CONTROL_HZ
from beavr_sim.hardware.device import MirrorError
from beavr_sim.robots import make_embodiment
from beavr_sim.robots.embodiment import DEFAULT_EMBODIMENT
from beavr_sim.teleop.episodes import (
    EpisodeControl,
    KeyboardControl,
    session_command,
)
from beavr_sim.teleop.operator_process import (
    operator_main,
)
from beavr_sim.teleop.pipeline import (
    TeleopSummary,
    _percentiles,
)
from beavr_sim.teleop.process_config import (
    HANDSHAKE_TIMEOUT_S,
    LIVENESS_TIMEOUT_S,
    STOP_RECORDING_S,
    Attachment,
    HeadsetImagesConfig,
    OperatorProcessConfig,
    TwinProcessConfig,
    ViewConfig,
)
from beavr_sim.teleop.runs import RunPlan
from beavr_sim.teleop.stages import OperatorConfig, count_hold
from beavr_sim.teleop.twin_camera_stream import (
    TwinCameraStream,
)
from beavr_sim.teleop.twin_page_stream import (
    TwinPageStream,
)
from beavr_sim.teleop.twin_process import (
    BAD_INPUT,
    twin_main,
)
from beavr_sim.teleop.twin_rerun import TwinRerun
from beavr_sim.teleop.twin_runs import TwinRecording
from beavr_sim.traces.format import TraceReader
from beavr_sim.wire.messages import (
    RobotStateMsg,
    SessionMsg,
)
from beavr_sim.wire.ports import TransportConfig
from beavr_sim.wire.transport import Publisher, Subscriber

log = logging.getLogger("beavr_sim.teleop.processes")

TARGETS = {"operator": operator_main, "twin": twin_main}


class MultiprocessSession:
    """Starts the three processes, watches them, stops them; see the module docstring."""

    def __init__(
        self,
        options,
        transport: TransportConfig | None = None,
        attach: tuple[Attachment, ...] = (),
    ):
        """``options``: a :class:`~beavr_sim.teleop.session.SessionOptions`; ``attach``: what
        attaches to the twin stage's hooks in the twin process (:class:`Attachment`)."""
        self.transport = transport or options.transport or TransportConfig()
        self.operator_config, self.twin_config = process_configs(options, attach)
        self.lockstep = self.twin_config.lockstep
        self.mirror_hardware = options.mirror_hardware
        self.ctx = mp.get_context("spawn")
        self.processes: dict[str, mp.process.BaseProcess] = {}
        self.pipes: dict[str, object] = {}
        self.results: dict[str, dict] = {}
        self.exits: dict[str, int | None] = {}
        #: Resets requested (each names the reset epoch the operator waits for).
        self.resets = 0
        #: Episode requests (keyboard, :meth:`request`) sent to the recording twin.
        self.episode_control = EpisodeControl()
        self.auto_start = bool(options.auto_start)

    @property
    def control_hz(self) -> float:
        return self.twin_config.control_hz

    def start(self) -> None:
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
        configs = {"operator": self.operator_config, "twin": self.twin_config}
        for name in ("twin", "operator"):
            parent, child = self.ctx.Pipe()
            proc = self.ctx.Process(
                target=TARGETS[name],
                args=(configs[name], self.transport, child),
                name=name,
                daemon=True,
            )
            proc.start()
            self.processes[name], self.pipes[name] = proc, parent
        for name, pipe in self.pipes.items():
            if not pipe.poll(60.0):
                self._abort_start()
                raise RuntimeError(f"{name} process did not become ready within 60 s")
            reply = pipe.recv_bytes()
            if reply != b"ready":
                self._abort_start(replied=name)
                text = reply.decode(errors="replace")
                if text.startswith(BAD_INPUT):  # a bad option only the process could check
                    raise ValueError(text.removeprefix(BAD_INPUT))
                raise MirrorError(text.removeprefix("error: "))
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

    def request(self, what: str, origin: str = "") -> None:
        """An episode request (``episodes.REQUESTS``) for the recording twin, from any
        thread; sent from :meth:`run`'s."""
        self.episode_control.request(what, origin)

    def dead(self) -> list[str]:
        return [n for n, p in self.processes.items() if not p.is_alive()]

    def _abort_start(self, replied: str = "") -> None:
        """A start that failed (a process answered an error, or one never became ready): no
        process has begun the session, so none has a report to give or a command to finish.
        The one that ``replied`` its error has closed what it opened and is exiting; the
        others are ended at once (a ``"stop"`` sent now may reach a process that has not
        subscribed yet, and would be waited for in vain)."""
        for name, proc in self.processes.items():
            if name != replied and proc.is_alive():
                proc.terminate()
        self._join_all()

    def stop(self) -> None:
        self.send("stop")
        for name, proc in self.processes.items():
            pipe = self.pipes[name]
            # a recording twin closes its dataset first: never killed while it writes
            patience = STOP_RECORDING_S if name == "twin" and self.twin_config.recording else 5.0
            if pipe.poll(patience if proc.is_alive() else 0.1):
                try:
                    self.results[name] = json.loads(pipe.recv_bytes())
                except (EOFError, ValueError):
                    pass
        self._join_all()

    def _join_all(self) -> None:
        """Every process joined (killed if it has not ended within 5 s), its exit code kept;
        the supervisor's sockets closed."""
        for name, proc in self.processes.items():
            proc.join(5.0)
            if proc.is_alive():
                proc.kill()
                proc.join(1.0)
            self.exits[name] = proc.exitcode
        self.session_pub.close()
        self.state_sub.close()
        self.context.term()

    def run(
        self, max_seconds: float | None, stop_on_success: bool, interrupted=lambda: False
    ) -> TeleopSummary:
        """``interrupted()`` true (Ctrl-C / SIGTERM) ends the session in order, as the end
        of a run does."""
        self.start()
        requests: list[str] = []  # from the keyboard thread; sent from this one
        live_recording = self.twin_config.recording is not None and not self.auto_start
        interactive = sys.stdin is not None and sys.stdin.isatty()
        if interactive and (self.mirror_hardware or live_recording):
            actions = {}
            if self.mirror_hardware:
                actions = {
                    "e": ("emergency stop (every device holds)", lambda: requests.append("estop")),
                    "r": ("release the emergency stop", lambda: requests.append("release")),
                }
            keyboard = KeyboardControl(
                self.episode_control if live_recording else None, actions=actions
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
                for what in self.episode_control.take():
                    self.send(session_command(what))
                if state is not None:
                    success = success or state.success
                    if state.done:  # the twin ended the episode as one process's loop would,
                        break  # or its rig did not sync
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
                ends_runs = self.twin_config.ends_runs  # else a single real-time run
                if not ends_runs and (
                    (success and stop_on_success) or (max_seconds and elapsed >= max_seconds)
                ):
                    break
                if "twin" in reported or (ends_runs and reported) or interrupted():
                    break  # the twin's runs need both processes (lockstep: every tick)
        finally:
            self.stop()
        return self.summary(success, died=reported)

    def summary(self, success: bool = False, died=()) -> TeleopSummary:
        """The session's summary from the processes' final reports (after :meth:`stop`);
        ``died``: processes that died while it ran."""
        op, twin = self.results.get("operator", {}), self.results.get("twin", {})
        det = op.get("detector", {})
        summary = TeleopSummary(
            task=twin.get("task", self.twin_config.task),
            embodiment=twin.get("embodiment", self.twin_config.embodiment),
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
            ticks=twin.get("ticks", 0),
            listener_errors=twin.get("hook_errors", {}),
            overruns=op.get("overruns", 0) + twin.get("overruns", 0),
            missed_ticks=op.get("missed_ticks", 0) + twin.get("missed_ticks", 0),
            frames_superseded=sum(det.get("frames_superseded", {}).values())
            + sum(op.get("frames_superseded", {}).values()),
            failed_devices=list(twin.get("failed_devices", [])),
            stopped_early=twin.get("stopped_early", ""),
        )
        if "runs" in twin:  # every run, as one process counts them (the twin played them)
            summary.take_runs(twin["runs"])
        return summary


def merged_holds(operator: dict, twin: dict) -> dict[str, dict[str, int]]:
    """The summary's holds (effector -> reason -> ticks) from the processes' reports: the
    operator's hold reasons, and the twin's guard refusals, step clamps and commands dropped
    as computed before a reset."""
    holds = {name: dict(by_reason) for name, by_reason in operator.get("holds", {}).items()}
    for key, reason in (
        ("guard_blocks", "guard"),
        ("step_limited", "step_limit"),
        ("stale_commands", "stale_after_reset"),
        ("held_for_sync", "syncing"),
    ):
        for name, n in twin.get(key, {}).items():
            if n:
                count_hold(holds, name, reason, int(n))
    return holds


def process_configs(
    options, attach: tuple[Attachment, ...] = ()
) -> tuple[OperatorProcessConfig, TwinProcessConfig]:
    """The two processes' configs from a :class:`~beavr_sim.teleop.session.SessionOptions`:
    a trace's embodiment and seed where the options leave them open, the env's control rate,
    lockstep on the virtual and paced clocks."""
    embodiment, seed = options.embodiment, options.seed
    if options.source == "trace":
        meta = TraceReader(options.trace).metadata
        embodiment = embodiment or meta.embodiment or None
        seed = seed if seed is not None else meta.seed
    embodiment = embodiment or DEFAULT_EMBODIMENT
    sides = tuple(sorted({e.side for e in make_embodiment(embodiment).effectors}))
    lockstep = options.clock in ("virtual", "paced")
    stage = OperatorConfig(embodiment=embodiment, control_hz=DEFAULT_CONTROL_HZ, sides=sides)
    view = None
    if options.viser:
        view = ViewConfig(
            host=options.viser_host,
            port=options.viser_port,
            rate_hz=options.viser_rate_hz,
            show_collision=options.show_collision,
            token=options.session_token(options.viser_host),
        )
    recording = None
    if options.record is not None:
        recording = TwinRecording(
            root=str(options.record),
            repo_id=options.repo_id,
            config=options.recording,
            keep_faulty=options.keep_faulty_episodes,
            source=options.source,
            real_cameras=tuple(options.real_cameras),
            rig_file=options.camera_rig_file(),
            auto_start=bool(options.auto_start),
        )
    operator = OperatorProcessConfig(
        stage=stage,
        source=options.source,
        trace=str(options.trace) if options.trace is not None else None,
        lockstep=lockstep,
        webxr=options.webxr_config() if options.source == "webxr" else None,
    )
    twin = TwinProcessConfig(
        task=options.task,
        embodiment=embodiment,
        control_hz=stage.control_hz,
        seed=seed,
        live=options.source != "trace",
        leap_variant=options.leap_variant,
        placed_cameras=tuple(options.placed_cameras),
        lockstep=lockstep,
        paced=options.clock == "paced",
        stop_on_success=options.source == "trace",
        plan=RunPlan.of(options),
        recording=recording,
        rerun=(
            TwinRerun(
                str(options.rerun), options.rerun_image_hz, options.rerun_twin_hz, options.source
            )
            if options.rerun is not None
            else None
        ),
        progress=options.progress,
        mirror_hardware=options.mirror_hardware,
        hardware_config=options.hardware_config,
        dry_run=options.dry_run,
        sync_timeout_s=options.sync_timeout_s,
        emulate_faults=options.emulate_faults,
        view=view,
        headset_images=(
            HeadsetImagesConfig(options.headset_image_hz, tuple(options.headset_image_size))
            if options.source == "quest" and not options.headless
            else None
        ),
        camera_stream=(
            TwinCameraStream(
                options.camera_stream_config(),
                placed=tuple(c.name for c in options.placed_cameras),
                depth=options.streamed_twin_depth,
                quest=options.source == "quest" and not options.headless,
                page=options.source == "webxr",
                real_cameras=tuple(options.real_cameras),
                rig_file=options.camera_rig_file(),
            )
            if options.camera_stream_hz > 0
            else None
        ),
        page_twin=(
            TwinPageStream(options.webxr_config().twin_rate_hz)
            if options.source == "webxr" and not options.headless
            else None
        ),
        attach=tuple(attach),
    )
    return (
        dataclasses.replace(
            operator,
            keypoints=twin.wants_keypoints,
            records=twin.recording is not None,
            camera_panels=twin.camera_stream is not None and twin.camera_stream.page,
            page_twin=twin.page_twin is not None,
        ),
        twin,
    )


def run_multiprocess(options, interrupted=lambda: False) -> TeleopSummary:
    return MultiprocessSession(options).run(
        options.max_seconds, stop_on_success=options.source == "trace", interrupted=interrupted
    )
