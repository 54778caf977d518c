"""The browser view attached to a teleop loop (single process): :func:`attach_view`.

:class:`ViewListener` runs after every tick, in the loop's thread. Each tick it only takes the
buttons (pause / resume goes to the operator; Reset resets the episode and replays a recorded
source from its start; while recording it drops the episode in progress), counts the tick for the loop-rate readout and remembers
whether the collision guard blocked; at most ``rate_hz`` times per wall second (the view's
:meth:`~beavr_sim.viz.twin_view.TwinView.due`) it asks the operator for its targets and sends
one update: poses, hand skeletons, arm target frames, fingertip targets, guard colours,
success, status and readouts. A guard block between two updates is shown at the next one.
Its time on every tick goes to the view's cost readout (:class:`~beavr_sim.viz.twin_view.ViewCost`).
"""

from __future__ import annotations

import re
import time

from beavr_sim.teleop.pipeline import TeleopLoop
from beavr_sim.viz.twin_view import DEFAULT_RATE_HZ, RateMeter, TwinView, recent_p50, subtree_bodies
from beavr_sim.viz.view_access import ViewAccess
from beavr_sim.wire.access import SessionToken
from beavr_sim.wire.records import Tick

_EPISODE = re.compile(r"episode (\d+)/(\d+): (REC|idle|sync)(?:.*? · last: (.+)$)?")
#: The panel's word for each phase of ``teleop.episodes.episode_label``.
_PHASE_WORDS = {"REC": "**recording**", "idle": "idle", "sync": "syncing the rig"}


def episode_line(label: str) -> str:
    """The recording panel's line from the session's episode label
    (:func:`~beavr_sim.teleop.episodes.episode_label`, both layouts):
    ``"episode 2/5: REC · last: saved"`` -> ``"episode **2** of **5** · **recording** · last:
    saved"``."""
    m = _EPISODE.match(label or "")
    if m is None:
        return label or "idle"
    last = f" · last: {m.group(4)}" if m.group(4) else ""
    return f"episode **{m.group(1)}** of **{m.group(2)}** · {_PHASE_WORDS[m.group(3)]}{last}"


class ViewListener:
    """Browser view of a running loop: see the module docstring."""

    def __init__(self, view, loop: TeleopLoop, progress=None, control=None, on_reset=None):
        self.view = view
        self.loop = loop
        self.progress = progress
        self.control = control  # recording: a reset drops the episode in progress
        #: Called after a Reset reset the loop (a mirrored rig syncs to the new start).
        self.on_reset = on_reset
        self.success = False
        self.rate = RateMeter(1.0)
        self._blocked: set[str] = set()
        self.resets = 0
        self._t = -float("inf")
        self._in_update = 0.0  # this tick's time in view.update (counted by the view)

    def __call__(self, tick: Tick) -> None:
        now = time.perf_counter()
        try:
            self._tick(tick, now)
        finally:  # the view's cost outside its update (which counts its own)
            self.view.account(time.perf_counter() - now - self._in_update)
            self._in_update = 0.0

    def _tick(self, tick: Tick, now: float) -> None:
        self.rate.tick(now)
        state = tick.state
        if state.t < self._t:  # a new episode (the session replays the trace, or a reset)
            self.success = False
        self._t = state.t
        self.success = self.success or state.success
        if state.guard_blocked:
            self._blocked |= set(state.guard_blocked_effectors or self.view.guard.geoms)
        view = self.view
        self.loop.operator.set_paused(view.paused or view.estop_requested)
        if view.take_reset():
            if self.control is not None:
                self.control.request("discard", "browser reset")
            rewind = getattr(self.loop.source, "rewind", None)
            if rewind is not None:  # a recorded source plays from its start again
                rewind()
                self.loop.replace_source(self.loop.source)  # its clock starts over
            self.loop.reset(self.loop.seed)
            if self.on_reset is not None:
                self.on_reset()
            self.success = False
            self._t = -float("inf")
            self.resets += 1
        if not view.due(now):
            return
        targets = self.loop.operator.targets()
        holds = tuple(sorted({c.reason for c in tick.commands.values() if c.hold}))
        env = self.loop.twin.env
        label = self.progress.label if self.progress is not None else ""
        paused = self.loop.operator.paused
        status = (
            f"t = {state.t:5.1f} s · "
            + ("**success**" if self.success else "running")
            + (f" · holding ({', '.join(holds)})" if holds else "")
            + (" · **paused**" if paused else "")
        )
        started = time.perf_counter()
        view.update(
            env.data,
            status=status,
            status_words=(self.success, holds, paused),
            targets=targets,
            guard_blocked=self._blocked,
            success=self.success,
            loop_rate_hz=self.rate.rate_hz(),
            latency_ms=recent_p50(self.loop.latencies_ms),
            episode=episode_line(label) if self.control is not None else None,
        )
        self._in_update = time.perf_counter() - started
        self._blocked = set()


def attach_view(
    loop: TeleopLoop,
    host: str,
    port: int,
    progress=None,
    control=None,
    *,
    mirroring: bool = False,
    rate_hz: float = DEFAULT_RATE_HZ,
    show_collision: bool = False,
    on_reset=None,
    token: SessionToken | None = None,
) -> TwinView:
    """A :class:`TwinView` of ``loop``'s twin, driven by a :class:`ViewListener` appended to
    the loop's listeners. ``mirroring``: the session drives hardware; the view gets an
    emergency-stop button whose state (``view.estop_requested``) the session follows.
    ``show_collision``: the robots' collision geometry drawn too (a panel checkbox toggles it).
    ``on_reset``: called after the Reset button reset the loop (the mirrored rig's sync).
    ``token``: the session token clients enter for the controls that move the robot."""
    env = loop.twin.env
    joints = env.joints
    by_effector = {name: joints.names[sl] for name, sl in joints.slices.items()}

    view = TwinView(
        env.render_model,
        host=host,
        port=port,
        title="beavr_sim twin",
        episode_control=control,
        task=env.task.name,
        embodiment=env.embodiment.label,
        effector_bodies=subtree_bodies(env.model, by_effector),
        mirroring=mirroring,
        rate_hz=rate_hz,
        show_collision=show_collision,
        access=None if token is None else ViewAccess(token),
    )
    loop.listeners.append(ViewListener(view, loop, progress, control, on_reset))
    return view
