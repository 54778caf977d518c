"""The twin process of ``--multiprocess``: :func:`twin_main`.

It owns the env, the twin stage (its hooks: the mirror, the recorder, rerun, the camera and
page streams, :class:`~beavr_sim.teleop.process_config.Attachment` s), the hardware mirror
and the session's runs (:mod:`beavr_sim.teleop.twin_runs`): commands are guarded and applied
when they arrive, the physics steps on its own clock (or in lockstep), and every step's
state is published. The layout as a whole: :mod:`beavr_sim.teleop.processes`.
"""

from __future__ import annotations

import json
import logging
import math
import sys
import time
from collections.abc import Callable

import gymnasium as gym
import zmq

import beavr_sim  # noqa: F401  (registers the envs the twin process makes)
from beavr_sim.cameras.errors import CameraError
from beavr_sim.hardware.device import MirrorError
from beavr_sim.hardware.mirror import Fixtures
from beavr_sim.headset.quest_io import HeadsetImagePublisher
from beavr_sim.naming import UnknownNameError
from beavr_sim.teleop.announce import announce_view
from beavr_sim.teleop.episodes import (
    request_of,
)
from beavr_sim.teleop.images import HeadsetRenderer, ScenePose, headset_camera
from beavr_sim.teleop.mirroring import (
    MIRROR_SWITCH_INTERVAL_S,
    BrowserEstop,
    MirrorFollower,
    RigChoice,
    RigSync,
    connect_mirror,
    episode_fault,
    hardware_summary,
)
from beavr_sim.teleop.pipeline import (
    LatencyLog,
    ThreadedListener,
    TickSchedule,
    concrete_seed,
)
from beavr_sim.teleop.process_config import (
    FIXTURES_FOR_S,
    HANDSHAKE_TIMEOUT_S,
    KEYPOINTS_TOPIC,
    LIVENESS_TIMEOUT_S,
    OPERATOR_EVENT_TOPIC,
    TwinProcessConfig,
    command_from_wire,
    fixtures_to_wire,
    keypoints_from_wire,
    leave_ctrl_c_to_the_session,
)
from beavr_sim.teleop.stages import TwinStage
from beavr_sim.teleop.twin_camera_stream import (
    PANEL_TOPIC,
    PagePanels,
    attach_camera_stream,
    check_quest_panels,
)
from beavr_sim.teleop.twin_page_stream import (
    POSES_TOPIC,
    SCENE_TOPIC,
    TwinPageFeed,
)
from beavr_sim.teleop.twin_rerun import attach_rerun
from beavr_sim.teleop.twin_runs import TwinRuns, connect_real_cameras
from beavr_sim.teleop.view import episode_line
from beavr_sim.twin.twin import TwinInterface
from beavr_sim.viz.twin_view import TwinView, subtree_bodies
from beavr_sim.viz.view_access import ViewAccess
from beavr_sim.wire.access import SessionToken
from beavr_sim.wire.messages import (
    HandKeypointsMsg,
    JointCommandMsg,
    OperatorEventMsg,
    RobotStateMsg,
    SessionMsg,
)
from beavr_sim.wire.ports import TransportConfig
from beavr_sim.wire.records import JointCommand, TwinState
from beavr_sim.wire.transport import Publisher, Subscriber

log = logging.getLogger("beavr_sim.teleop.processes")

#: Lockstep: seconds without the operator's commands for a tick before the twin asks again
#: (publishes the same state once more; a lost message never stalls the episode).
LOCKSTEP_ASK_AGAIN_S = 0.2


class TwinProcess:
    """What an :class:`Attachment` gets in the twin process: the config, the env, the twin
    stage (attach to its ``after_command`` / ``after_step`` hooks), the mirror (None when not
    mirroring), per effector the newest command's operator stamp and the moment the twin took
    it (:attr:`received`: ``(t_command, t_take)``, monotonic), and for the step just made
    (read them in an ``after_step`` hook) its commands (:attr:`tick_commands`: the lockstep
    tick's; real time: those applied since the step before) and its hand frames
    (:attr:`frames`, oldest first: sent by the operator only when the session records
    keypoints or logs to Rerun)."""

    def __init__(self, config: TwinProcessConfig, env, stage: TwinStage, mirror):
        self.config = config
        self.env = env
        self.stage = stage
        self.mirror = mirror
        self.received: dict[str, tuple[float, float]] = {}
        self.tick_commands: dict[str, JointCommand] = {}
        self.frames: list = []


def make_twin_env(config: TwinProcessConfig):
    """The twin process's env (unwrapped): the task and embodiment at the control rate, no
    time limit when live, the LEAP variant and the placed cameras as one process's
    ``build_loop`` makes them."""
    kwargs: dict = {"control_hz": config.control_hz}
    if config.live:
        kwargs["max_episode_seconds"] = 1e9
    if config.leap_variant:
        kwargs["hand_variant"] = config.leap_variant
    if config.placed_cameras:
        kwargs["placed_cameras"] = config.placed_cameras
    return gym.make(f"beavr_sim/{config.task}-v0", embodiment=config.embodiment, **kwargs).unwrapped


#: The start reply of a twin process refusing an option it alone could check (a
#: ``--quest-cameras`` name that is no panel): the supervisor's bad input (exit 2).
BAD_INPUT = "bad input: "


def _fail_start(conn, env, closers: list[Callable[[], None]], exc: BaseException) -> None:
    """The twin process could not start (the rig, the dataset or a camera): close what was
    opened, newest first, and tell the supervisor in one line."""
    for close in reversed(closers):
        close()
    prefix = BAD_INPUT if isinstance(exc, UnknownNameError) else "error: "
    conn.send_bytes(f"{prefix}{exc}".encode())
    env.close()


def twin_main(config: TwinProcessConfig, transport: TransportConfig, conn) -> None:
    leave_ctrl_c_to_the_session()
    context = zmq.Context()
    env = make_twin_env(config)
    twin = TwinInterface(env)
    stage = TwinStage(twin, latencies=LatencyLog())
    #: The seed of the episode (a reset from the supervisor or the browser replays it).
    episode_seed = concrete_seed(config.seed)
    positions = twin.reset(episode_seed)  # the twin's measured joints after its last step
    mirror = None
    sync = None
    closers: list[Callable[[], None]] = []
    mirror_reset = None
    if config.mirror_hardware:
        try:
            mirror, q_measured = connect_mirror(RigChoice.of(config), env, closers)
        except (MirrorError, ValueError, FileNotFoundError) as exc:
            _fail_start(conn, env, closers, exc)
            return
        twin.follow_speed_caps(mirror.speed_caps)
        twin.reset(episode_seed, q_measured)  # the mirror starts where the robot is
        sys.setswitchinterval(MIRROR_SWITCH_INTERVAL_S)  # see teleop/mirroring.py
        mirror.start(twin.action)
        # The episode's start; the devices catch up with it before the operator's commands
        # are taken (as one process's HardwareSync).
        sync = RigSync(mirror, config.sync_timeout_s or mirror.rig.mirror.sync_timeout_s)
        positions = twin.reset(episode_seed)
        mirror_reset = MirrorFollower(stage, mirror, positions).reset
    try:  # the session's runs; recording: the dataset opened (a bad folder fails here)
        runs = TwinRuns(
            config.plan,
            env,
            stage,
            mirror,
            config.recording,
            frames=lambda: process.frames,
            stop_on_success=config.stop_on_success,
            progress=config.progress,
            seed=config.seed,
        )
        closers.append(runs.close)
        real = runs.real_cameras  # recording: the recorder's, streamed too
        streaming = config.camera_stream
        if streaming is not None and config.recording is None:
            real = connect_real_cameras(
                streaming.real_cameras, streaming.rig_file, int(round(env.control_hz))
            )
            if real is not None:
                closers.append(real.close)
        if streaming is not None:  # a --quest-cameras name that is no panel fails here
            check_quest_panels(streaming, env, real)
    except (ValueError, OSError, CameraError) as exc:
        _fail_start(conn, env, closers, exc)
        return
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
    events = Subscriber(
        context,
        transport.endpoint("commands", bind=False),
        OPERATOR_EVENT_TOPIC,
        OperatorEventMsg,
        conflate=False,
    )
    keypoints = None
    if config.wants_keypoints:
        keypoints = Subscriber(
            context,
            transport.endpoint("commands", bind=False),
            KEYPOINTS_TOPIC,
            HandKeypointsMsg,
            conflate=False,
        )
    session = Subscriber(
        context, transport.endpoint("session", bind=False), b"session", SessionMsg, conflate=False
    )
    state_pub = Publisher(context, transport.endpoint("robot_state", bind=True))
    page_twin = None
    if config.page_twin is not None:  # the twin drawn on the operator's page
        page_twin = TwinPageFeed(env, config.page_twin)
        stage.after_step.append(page_twin)
    # operator + supervisor (+ the operator's page panels, its page's scene and poses)
    page = config.camera_stream is not None and config.camera_stream.page
    subscribers = 2 + int(page) + 2 * int(page_twin is not None)
    state_pub.wait_for_subscribers(subscribers, HANDSHAKE_TIMEOUT_S)
    if page_twin is not None:
        state_pub.send(SCENE_TOPIC, page_twin.scene)
    view = None
    if config.view is not None:
        joints = env.joints
        view = TwinView(
            env.render_model,
            host=config.view.host,
            port=config.view.port,
            task=env.task.name,
            embodiment=env.embodiment.label,
            effector_bodies=subtree_bodies(
                env.model, {n: joints.names[sl] for n, sl in joints.slices.items()}
            ),
            rate_hz=config.view.rate_hz,
            show_collision=config.view.show_collision,
            mirroring=mirror is not None,
            access=None if config.view.token is None else ViewAccess(config.view.token),
            episode_control=runs.control if config.recording is not None else None,
        )
        announce_view(view.url, config.view.token or SessionToken("-", False))
    browser_estop = None
    if view is not None and mirror is not None:
        browser_estop = BrowserEstop(view, mirror)
    publisher = None
    page_panels: PagePanels | None = None
    # the Quest app's camera panel shows the streamed panels in place of the twin's images
    quest_panel = streaming is not None and streaming.quest_shows_panels(real)
    if config.headset_images is not None:
        images = config.headset_images
        publisher = HeadsetImagePublisher(context, transport, rate_hz=images.rate_hz)
        closers.append(publisher.close)
    if config.headset_images is not None and not quest_panel:
        renderer = HeadsetRenderer(
            publisher, env.render_model, headset_camera(env.embodiment), images.size
        )
        next_due = [0.0]

        def headset_pose(state: TwinState) -> ScenePose | None:
            now = time.monotonic()
            if now < next_due[0]:
                return None
            next_due[0] = now + 1.0 / images.rate_hz
            return ScenePose.of(env.data)

        # rendered and sent off the physics' thread; closed before the publisher
        headset = ThreadedListener(renderer, snapshot=headset_pose, name="headset_images")
        closers.append(headset.close)
        stage.after_step.append(headset)
    if streaming is not None:  # closed before the cameras, the view and the publisher
        page_panels = PagePanels() if streaming.page else None
        closers.append(
            attach_camera_stream(streaming, env, stage, real, view, publisher, page_panels)
        )
    process = TwinProcess(config, env, stage, mirror)
    if config.rerun is not None:
        closers.append(attach_rerun(process, config.rerun, real_time=not config.lockstep))
    finishers: list[Callable[[], None]] = []
    for attachment in config.attach:
        finish = attachment.resolve()(process, attachment.argument)
        if finish is not None:
            finishers.append(finish)
    poller = zmq.Poller()
    for sub in (*subs.values(), session, events, *([keypoints] if keypoints else [])):
        poller.register(sub.socket, zmq.POLLIN)
    conn.send_bytes(b"ready")
    blocked: set[str] = set()  # effectors the guard blocked since the last view update
    success = False
    details: dict = {}
    dt = 1.0 / env.control_hz
    # Real time: the physics steps on its own clock, one control period at a time; commands
    # are guarded and written to the actuators (and handed to the mirror) when they arrive,
    # in between. A stall moves the grid on (no catch-up steps). Paced lockstep: each tick's
    # state is published at its deadline.
    schedule = TickSchedule(dt)
    schedule.restart(time.monotonic() + dt)
    epoch = 0  # resets done: stamped on every state; commands of an older epoch are dropped
    stale: dict[str, int] = {}
    command_poller = zmq.Poller()
    for sub in subs.values():
        command_poller.register(sub.socket, zmq.POLLIN)
    slices = twin.slices
    # Lockstep: the tick whose commands (and keypoints) the twin waits for, those arrived,
    # the episode's end.
    tick = 0
    pending: dict[str, JointCommandMsg] = {}
    pending_keypoints: HandKeypointsMsg | None = None
    # Real time: the hand frames and commands taken since the last step (the next step's).
    pending_frames: list = []
    step_commands: dict[str, JointCommand] = {}
    done = False
    #: The session's runs: the run the states carry (a new one: the operator restarts a
    #: trace), whether the next episode start begins a new run, the source's end (real time).
    run = 0
    new_run_due = True
    source_finished_rt = False
    last_state: RobotStateMsg | None = None
    asked_at = -math.inf

    def state_message(st: TwinState | None, **lockstep) -> RobotStateMsg:
        paused = view is not None and (view.paused or view.estop_requested)
        paused = paused or (mirror is not None and mirror.estopped)
        if st is None:  # after a reset: the measured joints, at rest
            return RobotStateMsg(
                t=env.elapsed_seconds,
                positions=positions.tolist(),
                velocities=[0.0] * len(positions),
                success=success,
                epoch=epoch,
                fixtures=fixtures,
                paused=paused,
                run=run,
                **lockstep,
            )
        return RobotStateMsg(
            t=st.t,
            positions=st.positions.tolist(),
            velocities=st.velocities.tolist(),
            success=success,
            guard_blocked=st.guard_blocked,
            guard_blocked_effectors=list(st.guard_blocked_effectors),
            action=st.action.tolist() if st.guard_blocked_effectors else [],
            epoch=epoch,
            fixtures=fixtures if st.t < FIXTURES_FOR_S else [],
            paused=paused,
            run=run,
            **lockstep,
        )

    def publish(msg: RobotStateMsg) -> None:
        nonlocal last_state, asked_at
        last_state, asked_at = msg, time.monotonic()
        state_pub.send(b"state", msg)
        for panel in page_panels.take() if page_panels is not None else ():
            state_pub.send(PANEL_TOPIC, panel)
        poses = page_twin.take() if page_twin is not None else None
        if poses is not None:
            state_pub.send(POSES_TOPIC, poses)

    def take_keypoints() -> None:
        """The operator's keypoints: real time, this epoch's (for the next recorded step);
        lockstep, those of the tick the twin waits for."""
        nonlocal pending_keypoints
        msg = keypoints.recv(0.0) if keypoints is not None else None
        while msg is not None:
            if msg.epoch == epoch and not config.lockstep:
                pending_frames.extend(keypoints_from_wire(msg))
            elif msg.epoch == epoch and msg.tick == tick:
                pending_keypoints = msg
            msg = keypoints.recv(0.0)

    def take_commands() -> None:
        """Real time: every effector's newest command, guarded, written to the actuators'
        targets and handed to the hooks (the mirror) at once."""
        nonlocal source_finished_rt
        t_take = time.monotonic()
        applied = {}
        take_keypoints()
        for name, sub in subs.items():
            msg = sub.recv_latest(0.0)
            if msg is None:
                continue
            if msg.epoch < epoch:  # computed from the pose before a reset: hold
                stale[name] = stale.get(name, 0) + 1
                continue
            source_finished_rt = source_finished_rt or msg.source_finished
            cmd = command_from_wire(msg)
            if cmd is None:
                continue  # holding without targets: keep the last ones
            applied[name] = cmd
            process.received[name] = (msg.t_command, t_take)
        if applied:
            stage.command(applied)
            step_commands.update(applied)

    def take_tick_commands() -> None:
        """Lockstep: the commands (and keypoints) answering this tick's state."""
        take_keypoints()
        for name, sub in subs.items():
            msg = sub.recv_latest(0.0)
            if msg is None:
                continue
            if msg.epoch < epoch:
                stale[name] = stale.get(name, 0) + 1
            elif msg.epoch == epoch and msg.tick == tick:
                pending[name] = msg
                process.received[name] = (msg.t_command, time.monotonic())

    def tick_ready() -> bool:
        """Lockstep: every effector's command (and the keypoints) of this tick came."""
        return len(pending) == len(subs) and (keypoints is None or pending_keypoints is not None)

    def lockstep_step() -> TwinState:
        """One process's tick: every effector's command guarded and written, one step."""
        nonlocal tick, done, pending_keypoints
        cmds = {
            name: command_from_wire(msg, held=twin.action[slices[name]])
            for name, msg in sorted(pending.items())
        }
        source_finished = any(msg.source_finished for msg in pending.values())
        t_command = min(msg.t_command for msg in pending.values())
        pending.clear()
        # this tick's hand frames, for the hooks that record or log the step
        process.frames = keypoints_from_wire(pending_keypoints) if pending_keypoints else []
        pending_keypoints = None
        process.tick_commands = cmds
        st = stage.apply(cmds, entered_perf=0.0, latency=False)
        for name, cmd in cmds.items():
            if not (cmd.hold or name in st.guard_blocked_effectors) and cmd.t_source > 0:
                stage.latencies_ms.append((twin.applied_monotonic - t_command) * 1e3)
        tick += 1
        done = runs.stepped(st, source_finished) if runs.playing else False
        return st

    def between_substeps() -> None:
        # Commands that arrive while the physics steps are taken between its substeps (not
        # while the rig syncs: the twin holds the episode's start).
        if command_poller.poll(0) and not (sync is not None and sync.syncing):
            take_commands()

    def syncing_step() -> TwinState | None:
        """While the rig syncs: the operator's commands dropped (computed before the
        episode's start), the twin holds its start, one step a control period; None until
        the next period is due."""
        for name, sub in subs.items():
            if sub.recv_latest(0.0) is not None:
                held_for_sync[name] = held_for_sync.get(name, 0) + 1
        take_keypoints()  # (of frames before the episode's start: never recorded)
        pending_frames.clear()
        now = time.monotonic()
        if now < schedule.next:
            return None
        schedule.take(now)
        process.frames, process.tick_commands = [], {}
        return stage.step()

    def begin_run() -> None:
        """A run of the session starts here (after its reset and, mirrored, its sync)."""
        nonlocal run, new_run_due, source_finished_rt, success
        run, new_run_due, source_finished_rt, success = run + 1, False, False, False
        runs.begin(episode_seed)

    def start_episode() -> None:
        """After a reset, or a sync that completed: the episode starts (lockstep: tick 0;
        a new run where one is due, else the run goes on from a reset)."""
        nonlocal tick, done, success, pending_keypoints
        tick, done, success, pending_keypoints = 0, False, False, None
        pending.clear()
        if new_run_due:
            begin_run()
        if config.paced:
            schedule.restart()
            schedule.wait()
        publish(state_message(None, tick=0))

    def next_run() -> None:
        """The session's next run: the seeded start again (a new epoch); mirrored, once the
        rig is there."""
        nonlocal positions, epoch, fixtures, done, new_run_due, episode_seed
        done, new_run_due = False, True
        episode_seed = concrete_seed(runs.next_seed())
        positions = twin.reset(episode_seed)
        epoch += 1
        fixtures = fixtures_to_wire(env)
        if sync is not None:
            sync.begin(twin.action.copy(), Fixtures.of(env.data))
            mirror_reset(positions)
            publish(state_message(None))  # tick -1: the operator waits for the rig
        elif config.lockstep:
            start_episode()
        else:
            begin_run()

    def sync_s() -> float | None:
        return sync.last_sync_s if sync is not None else None

    def update_view(st: TwinState) -> None:
        """The browser view, at its rate: the scene, the guard's blocks, the status and
        (recording) the episode line one process shows."""
        nonlocal blocked
        if view is None:
            return
        if st.guard_blocked:  # shown at the next update even if it cleared since
            blocked |= set(st.guard_blocked_effectors or view.guard.geoms)
        if not view.due():
            return
        syncing = sync is not None and sync.syncing
        view.update(
            env.data,
            status=f"t = {st.t:5.1f} s · {'success' if success else 'running'}",
            guard_blocked=blocked,
            success=success,
            episode=episode_line(runs.label(syncing)) if config.recording is not None else None,
        )
        blocked = set()

    def reset_scene(min_epoch: int = 0) -> None:
        """The episode's seeded start again (a browser or supervisor Reset; a scene that
        failed while idle): a new epoch (the operator re-homes); mirrored, the devices catch
        up with the twin's start, guarded."""
        nonlocal positions, epoch, fixtures
        positions = twin.reset(episode_seed)
        epoch = max(epoch + 1, min_epoch)
        fixtures = fixtures_to_wire(env)
        if sync is not None:
            sync.begin(twin.action.copy(), Fixtures.of(env.data))
        if mirror_reset is not None:
            mirror_reset(positions)
        if config.lockstep and sync is None:
            start_episode()

    held_for_sync: dict[str, int] = {}
    sync_fault = ""
    #: A live recording waits for a start request (the twin follows, nothing recorded).
    idle = runs.waits_for_start
    if sync is not None:  # its timeout runs from here, not from the processes' handshake
        sync.begin(twin.action.copy(), Fixtures.of(env.data))
    if not config.lockstep:
        env.between_substeps = between_substeps
        if sync is None and not idle:
            begin_run()
    elif sync is None or not sync.syncing:
        start_episode()
    else:
        publish(state_message(None))  # tick -1: the operator waits for the rig
    try:
        while True:
            if config.lockstep:
                poller.poll(math.ceil(LOCKSTEP_ASK_AGAIN_S * 250))
            else:
                remaining = schedule.next - time.monotonic()
                if remaining > 0:
                    poller.poll(math.ceil(remaining * 1000))
            msg = session.recv(0.0)
            if msg is not None and msg.command == "stop":
                break
            reset = msg is not None and msg.command == "reset"
            browser_reset = not reset and view is not None and view.take_reset()
            if browser_reset and runs.playing and config.recording is not None:
                runs.request("discard", "browser reset")  # as one process's view drops it
            if reset or browser_reset:  # supervisor or browser
                reset_scene(msg.epoch if reset else 0)
            if msg is not None and mirror is not None and msg.command == "estop":
                mirror.estop("keyboard")
            if msg is not None and mirror is not None and msg.command == "release":
                mirror.release()
            asked = request_of(msg.command) if msg is not None else None
            if asked is not None:
                runs.request(asked, "keyboard")
            event = events.recv(0.0)
            while event is not None:
                if event.event == "estop" and mirror is not None:
                    mirror.estop("headset gesture: both hands pinch")
                if event.event == "record":
                    runs.request("toggle", "headset gesture")
                event = events.recv(0.0)
            if sync_fault:  # the session ends: the supervisor stops on the done state
                if time.monotonic() - asked_at > LOCKSTEP_ASK_AGAIN_S:
                    publish(last_state)
                continue
            if sync is not None and sync.syncing:
                st = syncing_step()
                if st is None:
                    continue
                positions = st.positions
                if browser_estop is not None:
                    browser_estop(None)
                update_view(st)
                result = sync.poll()
                if result and idle:  # a Reset's sync while idle: the next start syncs again
                    log.warning("the rig did not sync to the reset scene: %s", result)
                    if config.progress:
                        print(f"\nHARDWARE FAULT: {result}", file=sys.stderr)
                    publish(state_message(st))
                elif result:
                    sync_fault = result
                    runs.sync_failed(result, sync.last_sync_s)
                    publish(state_message(st, done=True))
                elif result == "":  # in sync: the seeded start again, a new epoch
                    positions = twin.reset(episode_seed)
                    epoch += 1
                    fixtures = fixtures_to_wire(env)
                    mirror_reset(positions)
                    if config.lockstep:
                        start_episode()
                    elif new_run_due and not idle:
                        begin_run()
                else:
                    publish(state_message(st))
                continue
            if done:  # the session's runs are over: the supervisor stops on the done state
                if time.monotonic() - asked_at > LOCKSTEP_ASK_AGAIN_S:
                    publish(last_state)  # the end, again
                continue
            if config.lockstep:
                take_tick_commands()
                if not tick_ready():
                    if time.monotonic() - asked_at > LOCKSTEP_ASK_AGAIN_S:
                        publish(last_state)  # ask again: a lost message never stalls
                    continue
                st = lockstep_step()
            else:
                take_commands()
                now = time.monotonic()
                if now < schedule.next:
                    continue
                schedule.take(now)
                process.frames, process.tick_commands = list(pending_frames), dict(step_commands)
                pending_frames.clear()
                step_commands.clear()
                st = stage.step()
                ended = runs.stepped(st, source_finished_rt) if runs.playing else False
                done = ended and config.ends_runs
                if idle:  # a live recording between episodes
                    what = runs.idle_step(st)
                    if what == "start":
                        idle = False
                        next_run()
                        continue
                    if what == "reset":  # the scene failed or timed out while idle
                        reset_scene()
                        continue
                    done = what == "end"
            positions = st.positions
            if browser_estop is not None:
                browser_estop(None)
            success = success or st.success
            details = {k: v for k, v in st.info.items() if k.startswith("task/")}
            if done and runs.end(sync_s()):  # the run ended; the next one follows
                if runs.waits_for_start:  # ... on a start request: idle until then
                    idle, done, new_run_due = True, False, True
                else:
                    next_run()
                    continue
            if config.paced and not done:
                schedule.wait()
            if config.lockstep:
                publish(state_message(st, tick=tick, done=done))
            else:
                publish(state_message(st, done=done))
            update_view(st)
    finally:
        env.between_substeps = None
        if runs.playing:  # stopped by the supervisor: a run it ended, or one cut short
            runs.end(sync_s(), interrupted=config.recording is not None)
        hardware = {}
        if mirror is not None:
            mirror.close()
            hardware = hardware_summary(mirror)
        for finish in finishers:
            try:
                finish()
            except Exception as exc:
                log.error("twin attachment failed at the end: %r", exc)
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
                    "held_for_sync": held_for_sync,
                    "sync_s": sync.last_sync_s if sync is not None else None,
                    "stopped_early": sync_fault or runs.runs.stopped,
                    "runs": runs.report(),
                    "hardware_fault": sync_fault or (episode_fault(mirror) if mirror else ""),
                    "failed_devices": list(mirror.failed_devices) if mirror is not None else [],
                    "reset_epoch": epoch,
                    "overruns": schedule.overruns,
                    "missed_ticks": schedule.missed_ticks,
                    "latency_ms": stage.latencies_ms.percentiles(),
                    "hook_errors": dict(stage.hook_errors),
                    "duration_s": env.elapsed_seconds,
                    "ticks": tick if config.lockstep else int(round(env.elapsed_seconds / dt)),
                    "task": env.task.name,
                    "embodiment": env.embodiment.label,
                }
            ).encode()
        )
        if view is not None:
            view.close()
        state_pub.close()
        for s in (*subs.values(), session, events, *([keypoints] if keypoints else [])):
            s.close()
        env.close()
        context.term()
