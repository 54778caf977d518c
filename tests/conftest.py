from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("MUJOCO_GL", "egl")

from beavr_sim.reference import find_reference_dir


@pytest.fixture(scope="session")
def reference_dir() -> Path:
    found = find_reference_dir()
    if found is None:
        pytest.skip(
            "reference models not found: ../shared/reference beside the checkout "
            "(or $BEAVR_REFERENCE_DIR) is absent"
        )
    return found


@pytest.fixture
def pickup_box_with_forced_hold():
    """``make(t0, t1) -> (loop, refusals)``: the bundled PickupBox trace in the in-process
    loop, its guard also refusing the right effector from ``t0`` to ``t1`` (episode seconds);
    ``refusals`` collects the guard's own refusal reasons after ``t1``. Envs closed after."""
    from beavr_sim.assets import bundled_trace
    from beavr_sim.teleop.session import SessionOptions, build_loop
    from beavr_sim.twin.guard import GuardVerdict

    loops = []

    def make(t0: float, t1: float):
        options = SessionOptions(
            task="PickupBox",
            source="trace",
            trace=bundled_trace("PickupBox"),
            viser=False,
            headless=True,
            progress=False,
        )
        loop = build_loop(options)
        loops.append(loop)
        twin, guard = loop.twin, loop.twin.guard
        check = guard.check
        refusals: list[str] = []

        def forced(action, qpos_now, previous=None, reference=None):
            verdict = check(action, qpos_now, previous, reference)
            elapsed = twin.env.elapsed_seconds
            if previous is not None and t0 <= elapsed < t1:
                reasons = {**verdict.reasons, "right": "forced: test hold"}
                return GuardVerdict(tuple(sorted(reasons)), verdict.contacts, reasons)
            if elapsed >= t1:
                refusals.extend(verdict.reasons.values())
            return verdict

        guard.check = forced
        return loop, refusals

    yield make
    for loop in loops:
        loop.twin.env.close()


@pytest.fixture
def quest_push():
    """``connect(context, transport, stream="quest_right") -> socket``: a PUSH socket connected
    to a Quest stream of the detector, as the headset app sends (linger 0). The test closes it
    before terminating its context."""
    import zmq

    def connect(context, transport, stream: str = "quest_right"):
        push = context.socket(zmq.PUSH)
        push.setsockopt(zmq.LINGER, 0)
        push.connect(transport.endpoint(stream, bind=False))
        return push

    return connect


@pytest.fixture
def quest_options():
    """``make(**overrides) -> SessionOptions``: a headless live Quest session (PickupBox, no
    browser view, no progress line) on free ports; ``options.transport`` names them."""
    from beavr_sim.teleop.session import SessionOptions
    from beavr_sim.wire.ports import PortConfig, TransportConfig

    def make(**overrides) -> SessionOptions:
        kwargs = {
            "task": "PickupBox",
            "source": "quest",
            "viser": False,
            "headless": True,
            "progress": False,
            "transport": TransportConfig(ports=PortConfig.free()),
        }
        return SessionOptions(**{**kwargs, **overrides})

    return make
