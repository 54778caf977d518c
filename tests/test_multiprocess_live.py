"""Live sessions behave the same in one process and under ``--multiprocess`` (issue 37).

The twin process's :class:`~beavr_sim.teleop.twin_runs.TwinRuns` takes episode requests
through the single-process session's :class:`~beavr_sim.teleop.episodes.EpisodeRequests`: a
request that comes while the rig syncs to the episode's start is taken at the episode's first
step (one process: its first recorded tick), one that does not apply is logged and counted
(both layouts); a scene that fails while idle is reset, as one process resets it; the browser
view's recording panel shows the same episode line (``teleop.view.episode_line`` of
``episodes.episode_label``). And the Quest app's camera panel is streamed from the twin
process of a ``--multiprocess`` session.
"""

from __future__ import annotations

import logging
import time
from types import SimpleNamespace

import numpy as np
import pytest
import zmq
from fixtures_shared import ImageServer

from beavr_sim.datasets.episode_end import EpisodeEnd
from beavr_sim.datasets.features import RecordingConfig
from beavr_sim.teleop.episodes import EpisodeControl, EpisodeRequests, episode_label
from beavr_sim.teleop.runs import RunPlan
from beavr_sim.teleop.twin_runs import TwinRecording, TwinRuns
from beavr_sim.teleop.view import episode_line
from beavr_sim.wire.records import TwinState

WAIT_S = 60.0  # a readiness deadline (a loaded machine), never a pass/fail timing bound


class _Recorder:
    """The part of ``EpisodeRecorder`` :class:`TwinRuns` asks while an episode plays."""

    fault = ""

    def begin(self) -> None:
        pass


def live_runs() -> TwinRuns:
    """A live recording's runs (start and stop on requests), its recorder a stand-in."""
    env = SimpleNamespace(control_hz=30.0)
    runs = TwinRuns(RunPlan(recording=True, episodes=2, trace=False), env, stage=None, seed=0)
    runs.recording = TwinRecording(
        root="unused", repo_id="test/live", config=RecordingConfig(cameras=()), auto_start=False
    )
    runs.recorder = _Recorder()
    return runs


def state(failure: bool = False, truncated: bool = False) -> TwinState:
    zeros = np.zeros(3)
    return TwinState(0.0, zeros, zeros, zeros, False, failure, failure, truncated)


def test_a_stop_asked_while_the_rig_syncs_ends_the_episode_at_its_first_step():
    """One process leaves the request queued through the sync and its first recorded tick
    takes it; the twin process took and dropped it when the episode began."""
    runs = live_runs()
    runs.request("start", "keyboard")
    assert runs.idle_step(state()) == "start"  # reset, then the rig syncs ...
    runs.request("stop", "browser button")  # ... and meanwhile the operator stops
    runs.begin(seed=0)  # in sync: the episode starts
    assert runs.label() == "episode 1/2: REC"
    assert runs.stepped(state(), source_finished=False)  # ended at its first step
    assert runs.asked == ("stop",)


def test_a_request_that_does_not_apply_is_logged_and_counted(caplog):
    control = EpisodeControl()
    requests = EpisodeRequests(control)
    control.request("stop", "keyboard")
    control.request("start", "keyboard")
    with caplog.at_level(logging.WARNING, logger="beavr_sim.teleop.episodes"):
        assert requests.taker("toggle", "start", "quit")()  # idle: a start applies
    assert requests.last == ["start"] and requests.ignored == 1
    assert "episode request stop ignored: only toggle, start, quit apply now" in caplog.text
    runs = live_runs()
    runs.request("discard", "keyboard")
    assert runs.idle_step(state()) == "" and runs.requests_ignored == 1
    assert runs.report()["requests_ignored"] == 1


@pytest.mark.parametrize("how", ["failure", "truncated"])
def test_a_scene_that_fails_while_idle_is_reset(how):
    """One process resets the scene when its idle run ends without a request."""
    runs = live_runs()
    assert runs.idle_step(state()) == ""
    assert runs.idle_step(state(**{how: True})) == "reset"
    runs.request("toggle", "headset gesture")  # a start and the failure: the start wins
    assert runs.idle_step(state(failure=True)) == "start"


def test_the_episode_line_is_one_process_s_label_in_every_phase():
    runs = live_runs()
    assert runs.label() == episode_label("episode 1/2", "idle")
    assert episode_line(runs.label()) == "episode **1** of **2** · idle"
    assert episode_line(runs.label(syncing=True)) == "episode **1** of **2** · syncing the rig"
    runs.begin(seed=0)
    assert episode_line(runs.label(syncing=True)) == "episode **1** of **2** · **recording**"
    runs.playing = False  # the episode ended as a discard request asked
    runs.runs.recorded(EpisodeEnd(fault="", asked=("discard",)), written=False, duration_s=1.0)
    idle = "episode 1/2: idle (start: Enter, Record button, long left pinch) · last: discarded"
    assert runs.label() == idle
    assert episode_line(runs.label()) == "episode **1** of **2** · idle · last: discarded"
    with pytest.raises(ValueError, match="Valid episode phases: idle, rec, sync"):
        episode_label("episode 1/2", "paused")


def test_a_multiprocess_quest_session_streams_its_camera_to_the_quest_app_panel(quest_options):
    """``--source quest --camera front=... --camera-stream-hz --quest-cameras front`` under
    ``--multiprocess``: the twin process reads the camera, checks the chosen panel at its
    start, and the Quest app's camera socket gets its panels."""
    from beavr_sim.teleop.processes import MultiprocessSession

    camera = ImageServer()
    opts = quest_options(
        headless=False,  # the Quest app's image sockets
        multiprocess=True,
        camera_stream_hz=10.0,
        real_cameras=(f"front=zmq:127.0.0.1:{camera.port}",),
        quest_cameras=("front",),
    )
    context = zmq.Context()
    sub = context.socket(zmq.SUB)
    sub.setsockopt(zmq.LINGER, 0)
    sub.setsockopt(zmq.SUBSCRIBE, b"")
    sub.connect(opts.transport.endpoint("headset_camera", bind=False))
    session = MultiprocessSession(opts)
    try:
        session.start()
        received, deadline = None, time.monotonic() + WAIT_S
        while received is None and time.monotonic() < deadline:
            if sub.poll(100):
                received = sub.recv()
    finally:
        session.stop()
        sub.close(linger=0)
        context.term()
        camera.close()
    twin = session.results.get("twin", {})
    why = f"exits {session.exits}, camera frames served {camera.sent}, twin's report {twin}"
    assert received is not None, f"no camera panel reached the Quest app's socket: {why}"
    assert received[:2] == b"\xff\xd8"  # a JPEG
    assert session.exits["twin"] == 0, why


def test_a_quest_camera_name_only_the_twin_process_can_check_stops_the_start_as_bad_input(
    quest_options, capsys
):
    """``--quest-cameras`` naming no panel under ``--multiprocess``: the twin process refuses
    it at its start (only it opens the cameras), the supervisor stops every process and the
    command exits 2 with one line listing the valid panels, as one process does."""
    import multiprocessing

    from beavr_sim.teleop.__main__ import EXIT_BAD_INPUT, _run
    from beavr_sim.teleop.interrupt import StopSignal

    camera = ImageServer()
    opts = quest_options(
        headless=False,
        multiprocess=True,
        camera_stream_hz=10.0,
        real_cameras=(f"front=zmq:127.0.0.1:{camera.port}",),
        quest_cameras=("front", "frnot"),
    )
    try:
        code = _run(SimpleNamespace(debug=False), opts, StopSignal())
    finally:
        camera.close()
    assert code == EXIT_BAD_INPUT
    assert not multiprocessing.active_children(), multiprocessing.active_children()
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err  # one line, no traceback
    assert err[0].startswith("error: ") and "'frnot' (--quest-cameras)" in err[0], err
    assert "Valid Quest camera panels (--quest-cameras): front" in err[0], err
