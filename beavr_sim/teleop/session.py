"""Assembling a teleop session from options: env, source, operator, twin, views; running it.

This is the single-process runner (the CLI's default). ``--multiprocess`` runs the same
components in separate processes (``beavr_sim.teleop.processes``).

On a mirrored rig every episode (a ``--repeat`` play, a recorded episode, a browser Reset)
starts the same way (:class:`HardwareSync`): the twin is reset to the task's start pose, the
mirror is told (``begin_episode``) and brings every device there by its guarded, speed-capped
catch-up while the loop ticks with no hand frames taken (the operator holds; a trace is not
consumed), and only once the mirror is in sync is the twin reset again (the same seeded start,
so the episode is the one its simulation would be) and the episode started. A rig that does not
come in sync within ``sync_timeout_s``, or a device that failed and was not re-armed, ends the
session (:attr:`TeleopSummary.stopped_early`, :attr:`TeleopSummary.failed_devices`). The
session's summary counts every run (:class:`~beavr_sim.teleop.pipeline.RunRecord`).
"""

from __future__ import annotations

import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import gymnasium as gym

from beavr_sim.cameras.poses import rig_placed_cameras
from beavr_sim.datasets.cli import recording_config
from beavr_sim.datasets.episode_end import EpisodeEnd, end_recorded_episode
from beavr_sim.datasets.features import RecordingConfig, lerobot_features
from beavr_sim.datasets.recorder import (
    EpisodeRecorder,
    run_recorded_episode,
)
from beavr_sim.datasets.writer import EpisodeWriter
from beavr_sim.envs.camera_pose import PlacedCamera
from beavr_sim.envs.scene import DEFAULT_HAND_VARIANT
from beavr_sim.hardware.mirror import Fixtures
from beavr_sim.hardware.rig import RigConfig
from beavr_sim.headset.address_gate import parse_allow_list
from beavr_sim.headset.quest_io import HeadsetImagePublisher
from beavr_sim.headset.sources import HandSource, QuestSource, TraceSource, WebXRSource
from beavr_sim.headset.validation import StreamValidator
from beavr_sim.headset.webxr_server import WebXRConfig
from beavr_sim.naming import check_name
from beavr_sim.operator.operator import Operator
from beavr_sim.robots.embodiment import DEFAULT_EMBODIMENT, embodiment_layout
from beavr_sim.robots.parts import LEAP_HAND
from beavr_sim.tasks.registry import canonical_task_name
from beavr_sim.teleop.announce import announce_view, announce_webxr
from beavr_sim.teleop.camera_viewers import (
    CameraViewers,
    parse_quest_cameras,
    start_camera_stream,
)
from beavr_sim.teleop.console import CONSOLE
from beavr_sim.teleop.episodes import (
    STARTS,
    STOPS,
    EpisodeControl,
    EpisodeRequests,
    KeyboardControl,
    episode_label,
)
from beavr_sim.teleop.images import HeadsetRenderer, ScenePose, headset_camera
from beavr_sim.teleop.interrupt import never
from beavr_sim.teleop.mirroring import (
    MIRROR_SWITCH_INTERVAL_S,
    BrowserEstop,
    HeadsetEstop,
    MirrorFollower,
    RigChoice,
    RigSync,
    connect_mirror,
    episode_fault,
    failed_for_good,
    hardware_summary,
    hardware_watch,
)
from beavr_sim.teleop.pipeline import (
    TeleopLoop,
    TeleopSummary,
    ThreadedListener,
)
from beavr_sim.teleop.processes import run_multiprocess
from beavr_sim.teleop.runs import RunPlan, SessionRuns, episode_seeds
from beavr_sim.teleop.twin_camera_feed import twin_feed
from beavr_sim.teleop.twin_runs import connect_real_cameras
from beavr_sim.teleop.view import attach_view
from beavr_sim.traces.bundled import find_bundled_trace
from beavr_sim.twin.twin import TwinInterface
from beavr_sim.wire.access import SessionToken, is_loopback, new_token_value
from beavr_sim.wire.ports import TransportConfig
from beavr_sim.wire.records import Tick

SOURCES = ("quest", "trace", "webxr")

#: The longest ``--emulate-faults`` spec accepted (it is one line of the emulators' language).
MAX_FAULT_SPEC_CHARS = 500


@dataclass
class SessionOptions:
    task: str
    embodiment: str | None = None
    source: str = "quest"
    trace: Path | None = None
    seed: int | None = None
    clock: str | None = None
    headless: bool = False
    viser: bool = True
    viser_host: str = "127.0.0.1"
    viser_port: int = 8080
    #: Browser view updates per wall second at most (the loop itself is never slowed).
    viser_rate_hz: float = 30.0
    #: The browser view draws the robots' collision geometry over their visual geometry.
    show_collision: bool = False
    headset_host: str = "127.0.0.1"
    headset_image_hz: float = 10.0
    headset_image_size: tuple[int, int] = (640, 360)
    multiprocess: bool = False
    max_seconds: float | None = None
    progress: bool = True
    #: Trace only: play it this many times (0: until Ctrl-C), resetting the episode between.
    repeat: int = 1
    #: Ports and hosts; default: the standard ports, headset sockets on ``headset_host``.
    transport: TransportConfig | None = None
    #: Record a LeRobot dataset into this folder (None: no recording).
    record: Path | None = None
    repo_id: str | None = None
    #: Recorded episodes (each from a reset; a trace source replays its trace each time).
    episodes: int = 1
    #: What to record (cameras, image size, ...); default ``RecordingConfig()``.
    recording: object | None = None
    #: Start each recorded episode at once (default for traces) instead of on a start request
    #: (keyboard, browser button, headset gesture: the default for live sources).
    auto_start: bool | None = None
    #: Log the session to this Rerun recording (``.rrd``; None: no log).
    rerun: Path | None = None
    #: Camera images in the Rerun log per second of session time (0: none).
    rerun_image_hz: float = 5.0
    #: Twin body poses (the 3D twin) in the Rerun log per second of session time (0: none).
    rerun_twin_hz: float = 30.0
    #: Send every guarded command to the rig's hardware too (implies the real clock).
    mirror_hardware: bool = False
    #: Rig file (TOML) or "emulated" (protocol emulators for every device); default
    #: ``rig.toml`` in the working folder.
    hardware_config: str | None = None
    #: Mirror everything but the final write to the devices.
    dry_run: bool = False
    #: The twin's LEAP hands: "full" or "lite" (their torque cap). With ``mirror_hardware``
    #: the rig's hands decide (``LeapHandConfig.variant``; giving another is an error); else
    #: default "full".
    leap_variant: str | None = None
    #: ``--source webxr``: where the page is served (loopback unless a LAN address is given:
    #: then HTTPS, self-signed) and its port (default ``PortConfig.webxr``).
    webxr_host: str = "127.0.0.1"
    webxr_port: int | None = None
    #: ``--token``: the session token, required on every address; None: a fresh one, required
    #: off loopback only (``beavr_sim.wire.access``).
    token: str | None = None
    #: ``--headset-allow``: "IP[,IP]" the Quest app's sockets accept, or "any"; None: any, but
    #: refused with ``mirror_hardware`` on a non-loopback ``headset_host``.
    headset_allow: str | None = None
    #: Recording on a mirrored rig: keep an episode the hardware spoilt (a device held, failed
    #: or diverged) in the dataset, marked ``hardware_fault`` in ``meta/beavr_episodes.jsonl``
    #: (default: discard it).
    keep_faulty_episodes: bool = False
    #: Mirrored rig: how long (wall s) the devices may take to reach an episode's start pose
    #: before the episode is a hardware fault and the session ends; None: the rig file's
    #: ``MirrorConfig.sync_timeout_s``.
    sync_timeout_s: float | None = None
    #: ``--hardware-config emulated``: faults the emulators inject, in their spec language
    #: (``hardware.rig.parse_fault_specs``); None: none.
    emulate_faults: str | None = None
    #: ``--camera NAME=SPEC`` (``beavr_sim.cameras.spec``): real cameras recorded next to the
    #: twin's renders (plus a mirrored rig file's ``[cameras.NAME]`` tables).
    real_cameras: tuple[str, ...] = ()
    #: ``--camera-stream-hz``: camera panels per second to the viewers (0: off; the real
    #: cameras and the twin's renders of them, or the twin's cameras alone) and
    #: ``--camera-view`` (``auto`` or one of ``beavr_sim.cameras.stream.VIEWS``).
    camera_stream_hz: float = 0.0
    camera_view: str = "auto"
    #: ``--quest-cameras``: the streamed panels the Quest app's camera panel shows (None:
    #: every panel of a session with real cameras; without, the twin's headset images).
    quest_cameras: tuple[str, ...] | None = None
    #: ``--camera-poses F.toml``: a file of ``[cameras.NAME]`` tables (a rig file) whose
    #: ``T_world_camera`` poses place the twin's cameras (``beavr_sim.cameras.poses``).
    camera_poses: str | Path | None = None

    def __post_init__(self) -> None:
        self.camera_stream_config()  # a bad rate or view fails here, before anything starts
        if self.quest_cameras is not None and not (
            self.camera_stream_hz > 0 and self.source == "quest" and not self.headless
        ):
            raise ValueError(
                "--quest-cameras chooses the streamed panels the Quest app shows: it needs "
                "--camera-stream-hz HZ and --source quest (not --headless)"
            )
        if self.real_cameras:
            from beavr_sim.cameras.spec import (
                parse_camera_arg,
            )  # local: heavy (lerobot + torch, ~1 s)

            for arg in self.real_cameras:
                parse_camera_arg(arg)  # a bad spec fails here, before anything starts
            if self.record is None and not self.camera_stream_hz > 0:
                raise ValueError(
                    "--camera records real cameras into a dataset or streams them to the "
                    "viewers; add --record or --camera-stream-hz HZ"
                )
        self._placed_cameras: tuple[PlacedCamera, ...] = ()
        if self.camera_poses is not None:
            self._placed_cameras = rig_placed_cameras(self.camera_poses)
            if not self._placed_cameras:
                raise ValueError(
                    f"--camera-poses {self.camera_poses}: no [cameras.NAME] table has a "
                    "T_world_camera (docs/cameras.md)"
                )
        self._token_value = self.token or new_token_value()  # one per session
        if self.transport is None:
            self.transport = TransportConfig(
                headset_host=self.headset_host, headset_allow=self._headset_allow()
            )

        self.task = canonical_task_name(self.task)
        check_name("source", self.source, SOURCES)
        if self.source == "trace":
            self.trace = (
                Path(self.trace)
                if self.trace is not None
                else find_bundled_trace(self.task, self.embodiment)
            )
            if not self.trace.is_file():
                raise FileNotFoundError(f"trace file not found: {self.trace}")
        elif self.trace is not None:
            raise ValueError("--trace needs --source trace")
        if self.source == "webxr":
            self.webxr_config()  # raises on a bad host or port
        if self.mirror_hardware:
            if self.clock == "virtual":
                raise ValueError(
                    "--mirror-hardware runs at the real control rate: --clock real or paced"
                )
            # A trace replays deterministically at the real rate; a headset (and the
            # multiprocess layout) on the wall clock.
            paced = self.source == "trace" and not self.multiprocess
            self.clock = self.clock or ("paced" if paced else "real")
            if self.hardware_config is None:
                if not Path("rig.toml").is_file():
                    raise ValueError(
                        "--mirror-hardware needs a rig: --hardware-config F.toml (see "
                        "docs/hardware.md), or --hardware-config emulated to try it with "
                        "emulated devices (no rig.toml in this folder)"
                    )
                self.hardware_config = "rig.toml"
        elif self.dry_run or self.hardware_config is not None:
            raise ValueError("--dry-run and --hardware-config need --mirror-hardware")
        self.leap_variant = self._twin_leap_variant()
        if self.clock is None:  # --multiprocess: the real clock unless one is asked for
            virtual = self.source == "trace" and not self.viser and not self.multiprocess
            self.clock = "virtual" if virtual else "real"
        check_name("clock", self.clock, ("real", "virtual", "paced"))
        if self.clock != "real" and self.source != "trace":
            raise ValueError(f"a {self.clock} clock needs a recorded source (--source trace)")
        if self.max_seconds is not None and not self.max_seconds > 0:
            raise ValueError(f"max_seconds must be positive, got {self.max_seconds}")
        if self.repeat < 0 or (self.repeat != 1 and self.source != "trace"):
            raise ValueError("--repeat needs --source trace and a count >= 0 (0: forever)")
        if not self.headset_image_hz > 0:
            raise ValueError(f"headset image rate must be positive, got {self.headset_image_hz}")
        if self.record is not None:
            self.record = Path(self.record)
            self.recording = self.recording or RecordingConfig()
            self._check_placed_recordable()
            if self.episodes < 1:
                raise ValueError(f"--episodes must be >= 1, got {self.episodes}")
            self.repo_id = self.repo_id or f"beavr_sim/{self.task.lower()}"
        elif self.episodes != 1:
            raise ValueError(
                "--episodes needs --record (it counts recorded episodes; --repeat N plays a "
                "trace N times without recording)"
            )
        if self.auto_start is None:
            self.auto_start = self.source == "trace"
        if self.rerun is not None:
            from beavr_sim.viz.rerun_log import check_rrd_path  # local: heavy (rerun, ~360 ms)

            self.rerun = check_rrd_path(self.rerun)
        if not 0 <= self.rerun_image_hz < float("inf"):
            raise ValueError(f"--rerun-image-hz must be >= 0 (0: none), got {self.rerun_image_hz}")
        if not 0 <= self.rerun_twin_hz < float("inf"):
            raise ValueError(f"--rerun-twin-hz must be >= 0 (0: none), got {self.rerun_twin_hz}")
        if self.keep_faulty_episodes and self.record is None:
            raise ValueError("--keep-faulty-episodes needs --record")
        if self.sync_timeout_s is not None and not 0 < self.sync_timeout_s < float("inf"):
            raise ValueError(f"--sync-timeout must be positive, got {self.sync_timeout_s}")
        if self.emulate_faults is not None:
            spec = self.emulate_faults.strip()
            if self.hardware_config != "emulated":
                raise ValueError(
                    "--emulate-faults needs --mirror-hardware --hardware-config emulated (it "
                    "injects faults into the protocol emulators, never into a real rig)"
                )
            if not spec or len(spec) > MAX_FAULT_SPEC_CHARS or not spec.isprintable():
                raise ValueError(
                    "--emulate-faults takes one line of fault specs (printable, 1 to "
                    f"{MAX_FAULT_SPEC_CHARS} characters), got {self.emulate_faults!r}"
                )
            self.emulate_faults = spec

    def _check_placed_recordable(self) -> None:
        """The recording's placed cameras are the ones ``--camera-poses`` places."""
        placed = {c.name for c in self._placed_cameras}
        unplaced = [n for n in self.recording.placed_cameras if n not in placed]
        if unplaced:
            raise ValueError(
                f"--cameras {', '.join(unplaced)}: no such twin camera; a camera of a new name "
                "is recordable where --camera-poses places it (a [cameras.NAME] table with "
                f"T_world_camera; placed here: {', '.join(sorted(placed)) or 'none'})"
            )

    def camera_stream_config(self):
        """The real cameras' stream to the viewers (``CameraStream``'s config)."""
        from beavr_sim.cameras.stream import StreamConfig  # local: heavy (OpenCV, ~170 ms)

        return StreamConfig(
            rate_hz=self.camera_stream_hz, view=self.camera_view, quest_panels=self.quest_cameras
        )

    @property
    def streamed_twin_depth(self) -> tuple[str, ...]:
        """The twin cameras whose depth is a streamed panel (``NAME_depth``) in a session
        without real cameras: those whose depth is recorded (``--cameras NAME:depth``)."""
        return tuple(self.recording.depth_cameras) if self.record is not None else ()

    def webxr_config(self):
        """The WebXR page server's :class:`~beavr_sim.headset.webxr_server.WebXRConfig`."""

        port = self.transport.ports.webxr if self.webxr_port is None else self.webxr_port
        return WebXRConfig(
            host=self.webxr_host, port=port, token=self.session_token(self.webxr_host)
        )

    def _headset_allow(self) -> frozenset[str] | None:
        """The Quest sockets' allow-list; refuses an open LAN bind that could move hardware."""
        allowed = None if self.headset_allow is None else parse_allow_list(self.headset_allow)
        if self.mirror_hardware and not is_loopback(self.headset_host):
            if self.headset_allow is None:
                raise ValueError(
                    f"--headset-host {self.headset_host} with --mirror-hardware: anyone on the "
                    "network could move the robot; give --headset-allow HEADSET_IP "
                    "(or --headset-allow any)"
                )
            if allowed is None:
                print(
                    "warning: --headset-allow any: the Quest sockets take hands from any host "
                    "on the network and the robot is mirrored",
                    file=sys.stderr,
                )
        return allowed

    def camera_rig_file(self) -> str | None:
        """The mirrored rig file whose ``[cameras.NAME]`` tables are real cameras (None:
        not mirroring, or the emulated rig)."""
        rig = self.hardware_config if self.mirror_hardware else None
        return None if rig == "emulated" else rig

    @property
    def placed_cameras(self) -> tuple[PlacedCamera, ...]:
        """The twin cameras ``--camera-poses`` places (none: ())."""
        return self._placed_cameras

    def session_token(self, host: str) -> SessionToken:
        """This session's token for a server bound to ``host`` (the loopback rule)."""
        return SessionToken.for_host(host, self.token, value=self._token_value)

    def _twin_leap_variant(self) -> str:
        """The twin's LEAP variant: the mirrored rig's hands', else the chosen one, else full."""

        chosen = self.leap_variant
        if chosen is not None:
            check_name("LEAP variant", chosen, LEAP_HAND.variants)
        if self.mirror_hardware and self.hardware_config != "emulated":
            rig = RigConfig.from_toml(self.hardware_config).leap_variant()
            if rig is not None:
                if chosen not in (None, rig):
                    raise ValueError(
                        f"--leap-variant {chosen} but the rig's LEAP hands ({self.hardware_config})"
                        f" are {rig!r}: with --mirror-hardware the twin simulates the rig's hands;"
                        " leave out --leap-variant"
                    )
                return rig
        return chosen or DEFAULT_HAND_VARIANT

    @classmethod
    def from_args(cls, args) -> SessionOptions:

        size = str(args.headset_image_size).lower().split("x")
        if len(size) != 2 or not all(s.isdigit() and int(s) > 0 for s in size):
            raise ValueError(
                f"--headset-image-size must be WxH, e.g. 640x360, got {args.headset_image_size!r}"
            )
        poses = getattr(args, "camera_poses", None)
        # --cameras may name a camera --camera-poses places (read again, validated, below).
        placed = tuple(c.name for c in rig_placed_cameras(poses)) if poses is not None else ()
        return cls(
            task=args.task,
            embodiment=args.embodiment,
            source=args.source,
            trace=args.trace,
            seed=args.seed,
            clock=args.clock,
            headless=args.headless,
            viser=not args.no_viser,
            viser_host=args.viser_host,
            viser_port=args.viser_port,
            viser_rate_hz=getattr(args, "viser_rate_hz", 30.0),
            show_collision=getattr(args, "show_collision", False),
            headset_host=args.headset_host,
            headset_image_hz=args.headset_image_hz,
            headset_image_size=(int(size[0]), int(size[1])),
            multiprocess=args.multiprocess,
            max_seconds=args.max_seconds,
            progress=not args.quiet,
            repeat=args.repeat,
            record=args.record,
            repo_id=args.repo_id,
            episodes=args.episodes,
            recording=recording_config(args, placed) if args.record is not None else None,
            auto_start=args.auto_start,
            rerun=getattr(args, "rerun", None),
            rerun_image_hz=getattr(args, "rerun_image_hz", 5.0),
            rerun_twin_hz=getattr(args, "rerun_twin_hz", 30.0),
            mirror_hardware=getattr(args, "mirror_hardware", False),
            hardware_config=getattr(args, "hardware_config", None),
            leap_variant=getattr(args, "leap_variant", None),
            dry_run=getattr(args, "dry_run", False),
            webxr_host=getattr(args, "webxr_host", "127.0.0.1"),
            webxr_port=getattr(args, "webxr_port", None),
            token=getattr(args, "token", None),
            headset_allow=getattr(args, "headset_allow", None),
            keep_faulty_episodes=getattr(args, "keep_faulty_episodes", False),
            sync_timeout_s=getattr(args, "sync_timeout", None),
            emulate_faults=getattr(args, "emulate_faults", None),
            real_cameras=tuple(getattr(args, "camera", None) or ()),
            camera_stream_hz=getattr(args, "camera_stream_hz", 0.0),
            camera_view=getattr(args, "camera_view", "auto"),
            quest_cameras=parse_quest_cameras(getattr(args, "quest_cameras", None)),
            camera_poses=poses,
        )


class ProgressLine:
    """One status line on stderr, refreshed once a second."""

    def __init__(self, loop: TeleopLoop, enabled: bool = True):
        self.loop = loop
        self.enabled = enabled
        self._last = 0.0
        self.success = False
        #: Shown first (e.g. the recorded episode and its state).
        self.label = ""
        #: What the hardware is doing, shown after the label ("syncing hardware",
        #: "HARDWARE FAULT: ..."); "" while it follows.
        self.status = ""

    def __call__(self, tick: Tick) -> None:
        self.success = self.success or tick.state.success
        now = time.perf_counter()
        if not self.enabled or now - self._last < 1.0:
            return
        self._last = now
        lat = self.loop.latencies_ms[-200:]
        lat_s = f"{sorted(lat)[len(lat) // 2]:.2f} ms" if lat else "-"
        head = "  ".join(part for part in (self.label, self.status) if part)
        CONSOLE.progress(
            f"{head + '  ' if head else ''}t={tick.state.t:6.1f} s"
            f"  frames={self.loop.frames_received}"
            f"  rejected={self.loop.validator.rejected}  latency p50={lat_s}"
            f"  {'SUCCESS' if self.success else ''}   "
        )


class _NoFrames(HandSource):
    """Stands in for the session's source while the hardware syncs: no frames, and the real
    source (a trace) is not consumed meanwhile."""

    def __init__(self, real_time: bool):
        self.real_time = real_time

    def poll(self, now: float) -> list:
        return []

    def wait(self, timeout_s: float, clock=time.monotonic) -> list:
        time.sleep(max(0.0, timeout_s))
        return []


class HardwareSync:
    """Brings a mirrored rig to an episode's start pose before the episode starts (see the
    module docstring; the sync itself is :class:`~beavr_sim.teleop.mirroring.RigSync`, the
    one the multiprocess twin runs); a tick listener of the loop, so a browser Reset
    (:meth:`start` from the view) syncs the same way as the session's own episode starts
    (:meth:`run`).

    ``interactive``: someone can re-arm a failed device meanwhile (keyboard, browser), so a
    failed device waits for the timeout instead of ending the sync at once."""

    def __init__(
        self,
        loop: TeleopLoop,
        mirror,
        progress: ProgressLine,
        timeout_s: float,
        interactive: bool = False,
        clock=time.monotonic,
    ):
        self.loop = loop
        self.mirror = mirror
        self.progress = progress
        self.rig = RigSync(mirror, timeout_s, interactive, clock)
        self._source: HandSource | None = None

    @property
    def interactive(self) -> bool:
        return self.rig.interactive

    @property
    def syncing(self) -> bool:
        return self.rig.syncing

    @property
    def fault(self) -> str:
        """Why the last sync did not complete ("" when it did, or none ran)."""
        return self.rig.fault

    @property
    def synced(self) -> int:
        return self.rig.synced

    @property
    def last_sync_s(self) -> float:
        return self.rig.last_sync_s

    def start(self) -> None:
        """The twin was just reset to the episode's start: tell the mirror, and hold the
        operator (no frames: it holds) until the devices are there. (Not by pausing it: a
        resume re-anchors the operator, and the episode after the sync would not be the one
        its simulation is.)"""
        self.rig.begin(self.loop.twin.action.copy(), Fixtures.of(self.loop.twin.env.data))
        if not isinstance(self.loop.source, _NoFrames):  # (a new one since a start: kept)
            self._source = self.loop.source
            self.loop.source = _NoFrames(self._source.real_time)
        self.progress.status = "syncing hardware"

    def __call__(self, tick: Tick) -> None:
        fault = self.rig.poll()
        if fault is None:
            return
        self._finish()
        if not fault:
            self.loop.reset(self.loop.seed)  # the seeded start again: the simulated episode

    def run(self) -> str:
        """:meth:`start`, then tick until in sync; returns the fault ("" when in sync)."""
        self.start()
        while self.syncing and not self.loop.interrupted():
            tick = self.loop.tick()
            self.progress(tick)
        if self.syncing:  # Ctrl-C / SIGTERM before the rig was in sync
            self.rig.end("interrupted before the rig was in sync")
            self._finish()
        return self.fault

    def _finish(self) -> None:
        if self._source is not None:
            self.loop.source = self._source
            self._source = None
        fault = self.rig.fault
        self.progress.status = f"HARDWARE FAULT: {fault}" if fault else ""


def build_loop(options: SessionOptions, context=None):
    """The env, source and loop for ``options`` (single process)."""

    validator = StreamValidator()
    seed = options.seed
    embodiment = options.embodiment
    if options.source == "trace":
        source = TraceSource(options.trace, real_time=options.clock == "real")
        meta = source.metadata
        if meta.get("task") and meta["task"] != options.task:
            raise ValueError(
                f"trace {options.trace} was recorded for task {meta['task']}, not {options.task}"
            )
        trace_embodiment = meta.get("embodiment")
        if (
            embodiment is not None
            and trace_embodiment
            and embodiment_layout(embodiment) != embodiment_layout(trace_embodiment)
        ):
            raise ValueError(f"trace {options.trace} drives {trace_embodiment}, not {embodiment}")
        embodiment = embodiment or trace_embodiment
        seed = meta.get("seed") if seed is None else seed
    elif options.source == "webxr":
        source = WebXRSource(options.webxr_config(), validator)
    else:
        # Every frame reaches the loop (it counts the frames a newer one supersedes).
        source = QuestSource(context, options.transport, validator, latest_only=False)
    embodiment = embodiment or DEFAULT_EMBODIMENT
    kwargs = {}
    if options.source != "trace":
        kwargs["max_episode_seconds"] = 1e9  # live: episodes end by the operator, not a timer
    if options.leap_variant:
        kwargs["hand_variant"] = options.leap_variant
    if options.placed_cameras:
        kwargs["placed_cameras"] = options.placed_cameras
    env = gym.make(f"beavr_sim/{options.task}-v0", embodiment=embodiment, **kwargs).unwrapped
    operator = Operator(env.embodiment, 1.0 / env.control_hz)
    loop = TeleopLoop(
        TwinInterface(env),
        operator,
        source,
        validator=validator,
        real_time=options.clock == "real",
        paced=options.clock == "paced",
    )
    loop.reset(seed)
    return loop


def run_session(
    options: SessionOptions,
    on_loop: Callable[[TeleopLoop], None] | None = None,
    interrupted: Callable[[], bool] = never,
) -> TeleopSummary:
    """Run the session of ``options``; ``on_loop``: called with the single-process loop once
    it is built, before it runs (attach listeners and command hooks to it). ``interrupted``
    (asked every tick; :class:`~beavr_sim.teleop.interrupt.StopSignal`): true ends the session
    in order, the episode in progress dropped, and returns its summary so far."""
    if options.multiprocess:
        return run_multiprocess(options, interrupted)
    context = None
    if options.source == "quest" or not options.headless:
        import zmq

        context = zmq.Context()
    loop = build_loop(options, context)
    loop.interrupted = interrupted
    closers = [loop.source.close, loop.twin.env.close]
    if on_loop is not None:
        on_loop(loop)
    control = None
    progress = ProgressLine(loop, options.progress)
    mirror = None
    keys = {}
    if options.record is not None:
        control = EpisodeControl()
    sync = None
    viewers: dict[str, object] = {}
    try:
        interactive = sys.stdin is not None and sys.stdin.isatty()
        if options.mirror_hardware:
            mirror = start_mirror(options, loop, closers)
            keys = {
                "e": ("emergency stop (every device holds)", lambda: mirror.estop("keyboard")),
                "r": ("release the emergency stop", mirror.release),
                "a": ("re-arm failed devices", lambda: rearm(mirror)),
            }
            timeout_s = options.sync_timeout_s or mirror.rig.mirror.sync_timeout_s
            sync = HardwareSync(loop, mirror, progress, timeout_s, interactive)
            loop.listeners.append(sync)
        if interactive and ((control is not None and not options.auto_start) or keys):
            keyboard = KeyboardControl(control if not options.auto_start else None, actions=keys)
            print(keyboard.help, file=sys.stderr)
        if options.rerun is not None:
            from beavr_sim.viz.rerun_log import RerunLogger  # local: heavy (rerun, ~360 ms)

            logger = RerunLogger(
                options.rerun,
                loop,
                image_hz=options.rerun_image_hz,
                twin_hz=options.rerun_twin_hz,
                source=options.source,
            )
            closers.append(logger.close)
            loop.listeners.append(logger)
            print(f"rerun log: {options.rerun} (open: rerun {options.rerun})", file=sys.stderr)
        if options.viser:
            view = attach_view(
                loop,
                options.viser_host,
                options.viser_port,
                progress,
                control,
                mirroring=mirror is not None,
                rate_hz=options.viser_rate_hz,
                show_collision=options.show_collision,
                on_reset=sync.start if sync is not None else None,
                token=options.session_token(options.viser_host),
            )
            if mirror is not None:
                loop.listeners.append(BrowserEstop(view, mirror))
            closers.append(view.close)
            viewers["view"] = view
            announce_view(view.url, options.session_token(options.viser_host))
        if options.source == "webxr":
            url = loop.source.url
            announce_webxr(url, options.webxr_config().token)
            viewers["webxr"] = loop.source.server
            if not options.headless:  # the twin drawn in the headset
                env = loop.twin.env
                info = {"task": env.task.name, "embodiment": env.embodiment.label}
                loop.listeners.append(
                    loop.source.twin_feed(env.render_model, env.data, loop.operator, info)
                )
        if not options.headless and options.source == "quest":
            publisher = HeadsetImagePublisher(
                context,
                options.transport,
                rate_hz=options.headset_image_hz,
            )
            closers.append(publisher.close)
        streams_cameras = options.camera_stream_hz > 0 and (
            options.real_cameras or options.mirror_hardware or options.quest_cameras is not None
        )
        if not options.headless and options.source == "quest" and streams_cameras:
            viewers["quest"] = publisher  # the panel shows the streamed panels, not the twin
        elif not options.headless and options.source == "quest":
            images = headset_listener(
                publisher, loop, options.headset_image_size, 1.0 / options.headset_image_hz
            )
            closers.append(images.close)  # before the publisher: its thread sends
            loop.listeners.append(images)
        if options.camera_stream_hz > 0:
            viewers.update(twin_camera_panels(options, loop))
        if options.record is not None:
            summary = record_episodes(
                options,
                loop,
                progress,
                control,
                mirror=mirror,
                sync=sync,
                viewers=CameraViewers(**viewers),
            )
        else:
            real = None
            if options.camera_stream_hz > 0:  # the cameras watch a session that records nothing
                real = _real_cameras(options, int(round(loop.twin.env.control_hz)))
            if real is not None:
                closers.append(real.close)
            stream = start_camera_stream(
                real, options.camera_stream_config(), CameraViewers(**viewers)
            )
            if stream is not None:
                closers.append(stream.close)  # before the cameras and viewers it reads, sends to
            summary = _play_runs(options, loop, progress, mirror, sync)
        CONSOLE.end_line()
        if mirror is not None:
            summary.failed_devices = list(mirror.failed_devices)
            mirror.close()
            summary.hardware = hardware_summary(mirror)
        return summary
    finally:
        for close in reversed(closers):
            close()
        if context is not None:
            context.term()


def twin_camera_panels(options: SessionOptions, loop: TeleopLoop) -> dict[str, object]:
    """The twin's renders for the streamed camera panels: a tick listener of ``loop`` copying
    the pose at the stream's rate, and the twin-only panels (the cameras ``--camera-poses``
    places, else the headset's camera, and the recorded twin depth cameras' ``NAME_depth``)
    shown when the session has no real camera."""
    placed = tuple(c.name for c in options.placed_cameras)
    feed, panels = twin_feed(loop.twin.env, options.camera_stream_hz, placed)
    loop.listeners.append(feed)
    return {"twin": feed, "twin_panels": panels, "twin_depth": options.streamed_twin_depth}


def rearm(mirror) -> None:
    """The operator's re-arm (keyboard): failed devices reconnect and catch up; says which
    are still failed."""
    still = mirror.rearm()
    print(
        f"\nre-armed; still failed: {', '.join(still)}" if still else "\nre-armed every device",
        file=sys.stderr,
    )


def _hardware_stop(mirror, interactive: bool):
    """``stop_when`` for a mirrored run: a device failed and nobody can re-arm it (a
    non-interactive session) ends the run at once; None without a mirror."""
    if mirror is None or interactive:
        return None
    return lambda: bool(failed_for_good(mirror))


def _play_runs(options: SessionOptions, loop: TeleopLoop, progress, mirror, sync) -> TeleopSummary:
    """The runs of a session without recording: the source once, or a trace ``--repeat``
    times (0: until Ctrl-C or ``--max-seconds``), each from a fresh reset and, mirrored, from a
    synced rig. Returns the last run's summary with every run counted."""

    runs = SessionRuns(RunPlan.of(options))
    summary = None
    stop_when = _hardware_stop(mirror, sync is not None and sync.interactive)
    while runs.more():
        if runs.attempts > 0:  # play the trace again from the start on a fresh episode
            loop.replace_source(TraceSource(options.trace, real_time=options.clock == "real"))
        if sync is not None or runs.attempts > 0:
            loop.reset(loop.seed)
        progress.success = False
        sync_s = None
        if sync is not None:
            fault = sync.run()
            sync_s = sync.last_sync_s
            if loop.interrupted():
                break
            if fault:
                runs.sync_failed(fault, sync_s)
                break
        summary = loop.run(
            max_seconds=runs.remaining(),
            stop_on_success=options.source == "trace",
            progress=progress,
            stop_when=stop_when,
        )
        fault = episode_fault(mirror) if mirror is not None else ""
        record = runs.played_run(bool(summary.success), summary.duration_s, fault, sync_s)
        if options.progress:
            print("\n" + runs.run_line(record), file=sys.stderr)
        if mirror is not None and failed_for_good(mirror) and stop_when is not None:
            runs.stop(f"run {record.run}: {fault}")
            break
        if loop.interrupted():
            break
    if summary is None:
        summary = loop.summary(False)
    summary.count_runs(runs.tally)
    summary.stopped_early = runs.stopped
    return summary


def _real_cameras(options: SessionOptions, fps: int):
    """The session's real cameras, connected (None when there are none); a camera that does
    not open fails here with one line naming it."""
    return connect_real_cameras(options.real_cameras, options.camera_rig_file(), fps)


def record_episodes(
    options: SessionOptions,
    loop: TeleopLoop,
    progress: ProgressLine,
    control=None,
    mirror=None,
    sync: HardwareSync | None = None,
    viewers: CameraViewers | None = None,
) -> TeleopSummary:
    """``--record``: episodes saved to the dataset each as soon as it ends; mirrored,
    ``observation.state`` is the hardware's measured joints.

    Mirrored (``mirror``, ``sync``): each episode starts from a synced rig, and every frame is
    checked (:class:`~beavr_sim.datasets.recorder.HardwareWatch`); an episode the hardware
    spoilt ends at the fault and is discarded, or kept and marked ``hardware_fault`` with
    ``options.keep_faulty_episodes``; it never counts as a saved episode. A rig that does not
    sync (a failed device) ends the session.

    An episode starts at once (``options.auto_start``: the default for traces) or on a start
    request (keyboard, browser button, headset gesture; live sources), always from a fresh
    reset; until then the twin follows the hands without recording. It ends at task success
    (plus the recording's tail), failure, the time limit, the end of a trace, or a stop
    (saved), discard (dropped) or quit (saved, then the session ends) request. A trace is
    replayed ``options.episodes`` times; a live session records until that many are saved,
    or ``options.max_seconds`` of session time (idle or recording) have passed. Ctrl-C or
    SIGTERM (``loop.interrupted``) ends the session and drops only the episode in progress.
    """

    config = options.recording
    env = loop.twin.env
    if int(round(env.control_hz)) != config.fps:
        raise ValueError(f"--fps must equal the env's control rate ({env.control_hz:g} Hz)")
    control = control or EpisodeControl()
    requests = EpisodeRequests(control, lambda: len(loop.operator.take_gestures("record")))
    trace = options.source == "trace"
    # A trace plays its own layout every time; live episodes get seed, seed + 1, ...
    seed_of = episode_seeds(loop.seed if trace or options.seed is not None else None, trace)

    note = repeated_trace_note(options, loop.seed)
    if note:
        print(note, file=sys.stderr)
    real = _real_cameras(options, config.fps)
    try:  # a bad --quest-cameras name fails here: the cameras closed
        stream = start_camera_stream(
            real, options.camera_stream_config(), viewers or CameraViewers()
        )
    except ValueError:
        if real is not None:
            real.close()
        raise
    writer = EpisodeWriter(
        options.record,
        options.repo_id,
        lerobot_features(
            env.embodiment,
            config,
            env.environment_state_names,
            real_cameras={n: real.frame_shape(n) for n in real.names} if real else None,
        ),
        config.fps,
        robot_type=env.embodiment.name,
        use_videos=config.use_videos,
    )
    if writer.num_episodes:  # an existing dataset: say so (a re-run appends, never replaces)
        print(
            f"{options.record}: appending to the {writer.num_episodes} episodes already there "
            "(a new folder starts a new dataset)",
            file=sys.stderr,
        )
    watch = None
    if mirror is not None:
        watch = hardware_watch(mirror, env, config.fps)
    recorder = EpisodeRecorder(writer, env, config, watch=watch, real_cameras=real)
    summary = None
    runs = SessionRuns(RunPlan.of(options))

    def out_of_time() -> bool:
        return loop.interrupted() or runs.time_up()

    def fresh_episode() -> str:
        """Reset (and, mirrored, sync) for the next episode; the sync's fault or ""."""
        if trace and runs.attempts > 0:
            loop.replace_source(TraceSource(options.trace, real_time=options.clock == "real"))
        loop.reset(seed_of(runs.attempts))
        progress.success = False
        return sync.run() if sync is not None else ""

    def sync_s() -> float | None:
        return sync.last_sync_s if sync is not None else None

    try:
        while runs.more():
            name = runs.name()
            if not options.auto_start:
                progress.label = episode_label(name, "idle", runs.last_outcome)
                while True:
                    idle = loop.run(
                        max_seconds=runs.remaining(),
                        stop_on_success=False,
                        progress=progress,
                        stop_when=requests.taker(*STARTS),
                    )
                    runs.played += idle.duration_s
                    if requests.last or (trace and loop.source.finished) or out_of_time():
                        break
                    loop.reset(loop.seed)  # the scene failed or timed out while idle
                if "quit" in requests.last or not requests.last or out_of_time():
                    break
            if runs.attempts > 0 or not options.auto_start or sync is not None:
                progress.label = episode_label(name, "sync", runs.last_outcome)
                fault = fresh_episode()
                if loop.interrupted():
                    break
                if fault:
                    runs.sync_failed(fault, sync_s())
                    if options.progress:
                        print(
                            f"\n{name}: HARDWARE FAULT: {fault}; the session ends", file=sys.stderr
                        )
                    break
            progress.label = episode_label(name, "rec", runs.last_outcome)
            remaining = runs.remaining()
            summary = run_recorded_episode(
                loop,
                recorder,
                config,
                progress=progress,
                stop_when=requests.taker(*STOPS),
                max_seconds=remaining,
            )
            asked = requests.last
            fault = recorder.fault
            # Ctrl-C / SIGTERM drops the episode in progress (never saved as if it had ended).
            end = EpisodeEnd(
                fault=fault,
                interrupted=loop.interrupted(),
                asked=tuple(asked),
                task_success=bool(summary.success),
                keep_faulty=options.keep_faulty_episodes,
            )
            written = end_recorded_episode(recorder, end, seed=loop.seed, source=options.source)
            record = runs.recorded(end, written, summary.duration_s, sync_s())
            if options.progress:
                where = f"{writer.num_episodes} in {options.record}"
                print("\n" + runs.episode_line(name, record, end, written, where), file=sys.stderr)
            progress.status = f"last episode: HARDWARE FAULT ({fault})" if fault else ""
            if "quit" in asked or out_of_time():
                break
            if mirror is not None and failed_for_good(mirror) and not (sync and sync.interactive):
                runs.stop(f"{name}: {fault or episode_fault(mirror)}")
                break
            if real is not None and real.failed_for_good():
                runs.stop(f"{name}: camera {', '.join(real.failed_for_good())} stopped for good")
                break
            if runs.too_many_faults():
                break
    finally:
        recorder.close()
        writer.close()
        if stream is not None:
            stream.close()
        if real is not None:
            real.close()
    if summary is None:
        summary = loop.summary(False)
    summary.count_runs(runs.tally)
    summary.stopped_early = runs.stopped
    return summary


def repeated_trace_note(options: SessionOptions, seed: int | None) -> str:
    """The line said when a trace is recorded more than once: every episode is the same
    demonstration. (A trace's hand motion was made for its seed's object layout; another seed
    would move the objects away from the hand, so the episodes cannot take seed, seed + 1, ...
    the way ``datasets generate`` does.) "" when it does not apply."""
    if options.source != "trace" or options.record is None or options.episodes < 2:
        return ""
    return (
        f"note: --source trace records the same demonstration {options.episodes} times "
        f"(seed {seed}, the trace's hand motion: identical episodes); for varied "
        f"demonstrations use python -m beavr_sim.datasets generate --task {options.task} "
        f"--episodes {options.episodes} --out DIR (a synthesized trace per seed)"
    )


def headset_listener(
    publisher, loop: TeleopLoop, size: tuple[int, int], period_s: float
) -> ThreadedListener:
    """Rendered twin images to the headset at most every ``period_s`` (wall), off the control
    thread: the tick only copies the pose (when an image is due); the render, the JPEG and the
    send happen on the listener's thread. Close it before the publisher."""
    env = loop.twin.env
    renderer = HeadsetRenderer(publisher, env.render_model, headset_camera(env.embodiment), size)
    next_due = [0.0]

    def snapshot(tick: Tick) -> ScenePose | None:
        now = time.monotonic()
        if now < next_due[0]:
            return None
        next_due[0] = now + period_s
        return ScenePose.of(env.data)

    return ThreadedListener(renderer, snapshot=snapshot, name="headset_images")


def start_mirror(options: SessionOptions, loop: TeleopLoop, closers: list):
    """Connect the rig, reset the twin to the measured hardware pose (no motion at start) and
    let the mirror follow the loop's twin stage (:class:`MirrorFollower`: it gets every
    guarded command the moment the twin applies it); the headset's e-stop gesture is the
    loop's first listener."""

    mirror, q_measured = connect_mirror(RigChoice.of(options), loop.twin.env, closers)
    loop.twin.follow_speed_caps(mirror.speed_caps)
    loop.reset(loop.seed, robot_qpos=q_measured)
    mirror.start(loop.twin.action)
    previous = sys.getswitchinterval()
    sys.setswitchinterval(MIRROR_SWITCH_INTERVAL_S)
    closers.append(lambda: sys.setswitchinterval(previous))
    MirrorFollower(loop.twin_stage, mirror)
    loop.listeners.insert(0, HeadsetEstop(mirror, loop.operator))
    return mirror
