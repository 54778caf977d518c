"""The twin process's runs under ``--multiprocess``: the episode loop and the recorder.

The twin process owns the env, the hardware mirror and (``--record``) the dataset, so a
session's runs are played there: reset -> (mirrored) sync -> episode -> end, as often as the
session's :class:`~beavr_sim.teleop.runs.RunPlan` says, every decision taken by the same
:class:`~beavr_sim.teleop.runs.SessionRuns` the single-process session uses. The twin stamps
its states with the run; the operator process restarts a trace on a new run.

:class:`TwinRuns` contract:

- :meth:`TwinRuns.begin` starts an episode at the twin's current state (after the reset and,
  mirrored, after the sync: no frame from before the sync is recorded);
- the recorder is the twin stage's ``after_step`` hook: each step is recorded with the
  hand frames the operator observed for that tick (``frames()``, set by the twin process
  before the step; lockstep: the twin steps only once they came) through the same
  :meth:`~beavr_sim.datasets.recorder.EpisodeRecorder.record` as one process, and checked by
  the same :class:`~beavr_sim.datasets.recorder.HardwareWatch` when mirrored;
- :meth:`TwinRuns.stepped` says when the episode ends, by the single-process loop's rules
  (success, failure, the time limit, the end of a trace plus its tail, a hardware fault;
  recording: the recording's tail after success);
- live episodes (``TwinRecording.auto_start`` false: a headset's) start and stop on requests
  (:meth:`TwinRuns.request`: the supervisor's keyboard, the browser view's buttons, the
  operator's record gesture) taken once per step through the single-process session's
  :class:`~beavr_sim.teleop.episodes.EpisodeRequests`: until a start the twin follows the
  hands and nothing is recorded (:meth:`TwinRuns.idle_step`: a scene that fails or times out
  meanwhile is reset, as one process resets it); a stop saves the episode, a discard drops
  it, a quit saves it and ends the session; idle time counts towards ``max_seconds`` as in
  one process; a request that comes while the rig syncs to the episode's start is taken at
  its first step (never dropped), one that does not apply is logged and counted;
- :meth:`TwinRuns.label` is the episode line one process shows (idle / sync / REC: the
  browser view's recording panel);
- :meth:`TwinRuns.end` ends it through :func:`~beavr_sim.datasets.episode_end.end_recorded_episode`
  (a faulty episode discarded, or kept marked ``hardware_fault``; an interrupted one never
  saved) and says whether another run follows.
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from beavr_sim.datasets.episode_end import EpisodeEnd, end_recorded_episode
from beavr_sim.datasets.features import RecordingConfig, lerobot_features
from beavr_sim.datasets.recorder import EpisodeRecorder
from beavr_sim.datasets.writer import EpisodeWriter
from beavr_sim.teleop.episodes import (
    STARTS,
    STOPS,
    EpisodeControl,
    EpisodeRequests,
    episode_label,
)
from beavr_sim.teleop.mirroring import episode_fault, failed_for_good, hardware_watch
from beavr_sim.teleop.runs import RunPlan, SessionRuns, episode_seeds
from beavr_sim.wire.hand import HandFrame
from beavr_sim.wire.records import TwinState

#: Seconds a trace's episode plays on after its last frame (objects settle), as one process.
SOURCE_TAIL_S = 2.0


@dataclass(frozen=True)
class TwinRecording:
    """``--record`` in the twin process: the dataset's folder and repo id, what to record,
    whether a hardware-fault episode is kept (marked), and the source's name for the log."""

    root: str
    repo_id: str
    config: RecordingConfig
    keep_faulty: bool = False
    source: str = "trace"
    #: ``--camera NAME=SPEC`` real cameras, and the mirrored rig file whose ``[cameras.NAME]``
    #: tables add more (None: not a rig file).
    real_cameras: tuple[str, ...] = ()
    rig_file: str | None = None
    #: Start each episode at once (a trace); false: on a start request (live sources).
    auto_start: bool = True


def connect_real_cameras(camera_args: tuple[str, ...], rig_file: str | None, fps: int):
    """A recording's real cameras, connected (None when there are none); a camera that does
    not open fails here with one line naming it (``CameraError``)."""
    from beavr_sim.cameras.spec import session_cameras  # local: heavy (lerobot + torch, ~1 s)

    configs = session_cameras(camera_args, rig_file, fps)
    if not configs:
        return None
    from beavr_sim.cameras.real import RealCameras  # local: heavy (lerobot + torch, ~1 s)

    cameras = RealCameras(configs, control_period_s=1.0 / fps)
    cameras.connect()
    return cameras


class TwinRuns:
    """The runs of the twin process; see the module docstring. ``frames()``: the hand frames
    of the step just made (the recorder's keypoints); ``stop_on_success``: a run ends at task
    success (a trace); ``progress``: say each run's line on stderr."""

    def __init__(
        self,
        plan: RunPlan,
        env,
        stage,
        mirror=None,
        recording: TwinRecording | None = None,
        *,
        frames: Callable[[], Sequence[HandFrame]] = tuple,
        stop_on_success: bool = True,
        progress: bool = False,
        seed: int | None = None,
    ):
        self.plan = plan
        self.runs = SessionRuns(plan)
        self._seed_of = episode_seeds(seed, plan.trace or recording is None)
        self.env = env
        self.mirror = mirror
        self.recording = recording
        self.stop_on_success = stop_on_success
        self.progress = progress
        self.frames = frames
        self.dt = 1.0 / env.control_hz
        self.recorder: EpisodeRecorder | None = None
        self.writer: EpisodeWriter | None = None
        self.real_cameras = None
        if recording is not None:
            self._open_recorder(recording, stage)
        #: The current episode: playing, its ticks, its success, when the source ended, the
        #: recording's tail left (None: not in it), its ticks when the run part ended.
        self.playing = False
        self.ticks = 0
        self.success = False
        self._finished_at: float | None = None
        self._tail: int | None = None
        self._run_ticks = 0
        self._limit: float | None = None
        self.seed: int | None = None
        #: Live recording: the episode requests (any thread) and those that ended the episode.
        self.control = EpisodeControl()
        self._requests = EpisodeRequests(self.control)
        self.asked: tuple[str, ...] = ()
        self._said_idle = False

    @staticmethod
    def _live(recording: TwinRecording | None) -> bool:
        return recording is not None and not recording.auto_start

    @property
    def waits_for_start(self) -> bool:
        """Episodes start on a start request (a live recording), not at once."""
        return self._live(self.recording)

    def request(self, what: str, origin: str = "") -> None:
        """An episode request (one of ``episodes.REQUESTS``), taken at the next step."""
        self.control.request(what, origin)

    def next_seed(self) -> int | None:
        """The next episode's seed: the session's (a trace's every time); live recorded
        episodes seed, seed + 1, ... as in one process."""
        return self._seed_of(self.runs.attempts)

    def idle_step(self, state: TwinState) -> str:
        """A step (its ``state``) while waiting for a start (the twin follows the hands,
        nothing recorded): ``"start"`` (a start request came: reset, sync and begin the next
        episode), ``"end"`` (a quit, or the session's time is up), ``"reset"`` (the scene
        failed or timed out meanwhile: reset it and go on waiting, as one process) or ``""``."""
        if self.progress and not self._said_idle:
            self._said_idle = True
            print("\n" + episode_label(self.runs.name(), "idle"), file=sys.stderr)
        self.runs.played += self.dt
        took = self._requests.taker(*STARTS)()
        if "quit" in self._requests.last or self.runs.time_up():
            return "end"
        if took:
            return "start"
        return "reset" if state.failure or state.truncated else ""

    def label(self, syncing: bool = False) -> str:
        """The episode line of one process's session (``episodes.episode_label``): recording,
        the rig syncing (``syncing``) to the next episode's start, or idle."""
        phase = "rec" if self.playing else "sync" if syncing else "idle"
        return episode_label(self.runs.name(), phase, self.runs.last_outcome)

    @property
    def requests_ignored(self) -> int:
        """Episode requests refused because they did not apply when taken (each logged)."""
        return self._requests.ignored

    def _open_recorder(self, recording: TwinRecording, stage) -> None:
        config = recording.config
        env = self.env
        if int(round(env.control_hz)) != config.fps:
            raise ValueError(f"--fps must equal the env's control rate ({env.control_hz:g} Hz)")
        real = connect_real_cameras(recording.real_cameras, recording.rig_file, config.fps)
        self.real_cameras = real
        shapes = {n: real.frame_shape(n) for n in real.names} if real is not None else None
        try:
            self.writer = EpisodeWriter(
                recording.root,
                recording.repo_id,
                lerobot_features(
                    env.embodiment, config, env.environment_state_names, real_cameras=shapes
                ),
                config.fps,
                robot_type=env.embodiment.name,
                use_videos=config.use_videos,
            )
        except BaseException:
            if real is not None:
                real.close()
            raise
        if self.writer.num_episodes:
            print(
                f"{recording.root}: appending to the {self.writer.num_episodes} episodes "
                "already there (a new folder starts a new dataset)",
                file=sys.stderr,
            )
        watch = None
        if self.mirror is not None:
            watch = hardware_watch(self.mirror, env, config.fps)
        self.recorder = EpisodeRecorder(
            self.writer,
            env,
            config,
            watch=watch,
            real_cameras=real,
        )
        stage.after_step.append(self._record)

    # ------------------------------------------------------------------ frames
    def _record(self, state: TwinState) -> None:
        if self.recorder is not None and self.playing:
            self.recorder.record(state, self.frames())

    # ------------------------------------------------------------------ an episode
    @property
    def fault(self) -> str:
        """The episode's hardware fault so far (recording: the recorder's per-frame check)."""
        return self.recorder.fault if self.recorder is not None else ""

    @property
    def name(self) -> str:
        return self.runs.name()

    def begin(self, seed: int | None) -> None:
        """An episode starts at the twin's current state (reset and, mirrored, synced)."""
        self.seed = seed
        self.playing = True
        self.ticks = 0
        self.success = False
        self._finished_at = None
        self._tail = None
        self._run_ticks = 0
        self.asked = ()
        self._said_idle = False
        # (Requests that came while the rig synced stay queued: the first step takes them,
        # as one process's first recorded tick does.)
        limit = self.recording.config.episode_seconds if self.recording is not None else None
        self._limit = self.runs.episode_limit(limit)
        if self.recorder is not None:
            self.recorder.begin()
            if self.progress:
                print("\n" + episode_label(self.runs.name(), "rec"), file=sys.stderr)

    def stepped(self, state: TwinState, source_finished: bool) -> bool:
        """One step of the episode happened: whether the episode ended (the single-process
        loop's rules; see the module docstring)."""
        self.ticks += 1
        if self._tail is not None:  # the recording's tail after success
            self._tail -= 1
            return self._tail <= 0 or bool(self.fault)
        self.success = self.success or bool(state.success)
        elapsed = self.ticks * self.dt
        if self.recorder is not None and self._requests.taker(*STOPS)():
            self.asked = tuple(self._requests.last)  # stop, discard or quit: no tail
            self._run_ticks = self.ticks
            return True
        ended = (state.success and self.stop_on_success) or state.failure or bool(self.fault)
        # not recording: a device failed for good ends the run (nobody re-arms it here)
        ended = ended or (self.recorder is None and self._failed())
        ended = ended or state.truncated or (self._limit is not None and elapsed >= self._limit)
        if source_finished and not ended:
            self._finished_at = elapsed if self._finished_at is None else self._finished_at
            ended = elapsed - self._finished_at >= SOURCE_TAIL_S
        if not ended:
            return False
        self._run_ticks = self.ticks
        if self.recording is not None and self.success and not self.fault:
            tail = int(round(self.recording.config.tail_seconds * self.recording.config.fps))
            if tail > 0:
                self._tail = tail
                return False
        return True

    def _failed(self) -> bool:
        return self.mirror is not None and bool(failed_for_good(self.mirror))

    @property
    def duration_s(self) -> float:
        """The episode's play time (s; a recording's tail not included, as one process)."""
        return (self._run_ticks or self.ticks) * self.dt

    def end(self, sync_s: float | None = None, interrupted: bool = False) -> bool:
        """End the episode in progress (``interrupted``: cut by Ctrl-C / the session's stop:
        never saved); returns whether another run follows."""
        if not self.playing:
            return False
        self.playing = False
        runs = self.runs
        name = runs.name()
        if self._run_ticks == 0:
            self._run_ticks = self.ticks
        if self.recorder is not None:
            end = EpisodeEnd(
                fault=self.recorder.fault,
                interrupted=interrupted,
                asked=self.asked,
                task_success=self.success,
                keep_faulty=self.recording.keep_faulty,
            )
            written = end_recorded_episode(
                self.recorder, end, seed=self.seed, source=self.recording.source
            )
            record = runs.recorded(end, written, self.duration_s, sync_s)
            line = runs.episode_line(
                name, record, end, written, f"{self.writer.num_episodes} in {self.recording.root}"
            )
        else:
            fault = episode_fault(self.mirror) if self.mirror is not None else ""
            record = runs.played_run(self.success, self.duration_s, fault, sync_s)
            line = runs.run_line(record)
        if self.progress:
            print("\n" + line, file=sys.stderr)
        if interrupted or "quit" in self.asked or self.runs.time_up():
            return False
        if self.mirror is not None and failed_for_good(self.mirror):
            runs.stop(f"{name}: {record.hardware_fault or episode_fault(self.mirror)}")
            return False
        real = self.real_cameras
        if real is not None and real.failed_for_good():
            runs.stop(f"{name}: camera {', '.join(real.failed_for_good())} stopped for good")
            return False
        if self.recorder is not None and runs.too_many_faults():
            return False
        return runs.more()

    def sync_failed(self, fault: str, sync_s: float | None) -> None:
        """The rig did not reach the next run's start: counted; the session ends."""
        self.runs.sync_failed(fault, sync_s)
        if self.progress:
            print(
                f"\n{self.runs.name()}: HARDWARE FAULT: {fault}; the session ends", file=sys.stderr
            )

    def close(self) -> None:
        if self.recorder is not None:
            self.recorder.close()
        if self.writer is not None:
            self.writer.close()
        if self.real_cameras is not None:
            self.real_cameras.close()

    def report(self) -> dict:
        """The runs for the session's summary (:meth:`TeleopSummary.take_runs`)."""
        return {
            **self.runs.tally.report(),
            "stopped_early": self.runs.stopped,
            "requests_ignored": self.requests_ignored,
        }
