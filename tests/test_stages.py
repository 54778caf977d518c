"""The per-frame stages (``teleop/stages.py``) and the runners built on them.

``EXPECTED`` was recorded by running main at 0ac0037 (before the stages existed) with the
code of :func:`replay_digest` below, run on main's tree: a bundled trace replayed on the
virtual clock, every summary field but wall time (``loop_rate_hz``, the latency percentiles;
their count is kept), plus a digest of every command (positions, hold, reason) and of the
final ``qpos``. The digests hold for this machine's MuJoCo and numpy builds.
"""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from beavr_sim.teleop.session import SessionOptions, build_loop

EXPECTED = {
    "PickupBox/None": {
        "commands_applied": 269,
        "commands_sha256": "785a83b6413f78afec054a35b7a3068c49c0f7a82cc10c30589584ec6d14c65e",
        "duration_s": 8.966666666666667,
        "embodiment": "xarm7_leap_right",
        "frames_received": 534,
        "frames_rejected": 0,
        "frames_superseded": 0,
        "guard_blocks": {},
        "hardware": {},
        "holds": {},
        "latency_ms": {"n": 268},
        "listener_errors": {},
        "missed_ticks": 0,
        "operator": {
            "right": {
                "errors": 0,
                "frames": 534,
                "holds": {},
                "jumps_rejected": 0,
                "malformed_frames": 0,
                "reanchors": 1,
                "tracking_losses": 0,
                "untracked_frames": 0,
            }
        },
        "overruns": 0,
        "processes": {},
        "qpos_sha256": "4db3c94bdd7c92265628fa6ddc0a33f01a5f2fb5ae37567dd02314cd8068f463",
        "rejected_by_reason": {},
        "success": True,
        "task": "PickupBox",
        "ticks": 269,
    },
    "PickupBox/rx1": {
        "commands_applied": 382,
        "commands_sha256": "5e7182bb5045c66870a04a793db3a4b13d26475f7770f9400df56c3cf22e7ec7",
        "duration_s": 8.0,
        "embodiment": "rx1",
        "frames_received": 952,
        "frames_rejected": 0,
        "frames_superseded": 0,
        "guard_blocks": {"left": 49, "right": 49},
        "hardware": {},
        "holds": {"left": {"guard": 49}, "right": {"guard": 49}},
        "latency_ms": {"n": 380},
        "listener_errors": {},
        "missed_ticks": 0,
        "operator": {
            "left": {
                "errors": 0,
                "frames": 476,
                "holds": {},
                "jumps_rejected": 0,
                "malformed_frames": 0,
                "reanchors": 1,
                "tracking_losses": 0,
                "untracked_frames": 0,
            },
            "right": {
                "errors": 0,
                "frames": 476,
                "holds": {},
                "jumps_rejected": 0,
                "malformed_frames": 0,
                "reanchors": 1,
                "tracking_losses": 0,
                "untracked_frames": 0,
            },
        },
        "overruns": 0,
        "processes": {},
        "qpos_sha256": "909fb2fc321ae6169aee439c7cc0bab776e72466c694081eb5b634e2c5e6d193",
        "rejected_by_reason": {},
        "success": True,
        "task": "PickupBox",
        "ticks": 240,
    },
}


def replay_digest(task: str, embodiment: str | None, clock: str | None = None) -> dict:
    options = SessionOptions(
        task=task,
        embodiment=embodiment,
        source="trace",
        clock=clock,
        viser=False,
        headless=True,
        progress=False,
    )
    loop = build_loop(options)
    digest = hashlib.sha256()

    def listen(tick) -> None:
        for name in sorted(tick.commands):
            c = tick.commands[name]
            digest.update(name.encode())
            digest.update(np.asarray(c.positions, dtype=np.float64).tobytes())
            digest.update(bytes([c.hold]))
            digest.update(c.reason.encode())

    loop.listeners.append(listen)
    summary = loop.run().to_dict()
    q = loop.twin.env.data.qpos.copy()
    loop.twin.env.close()
    summary.pop("loop_rate_hz")
    summary["latency_ms"] = {"n": summary["latency_ms"]["n"]}
    summary["commands_sha256"] = digest.hexdigest()
    summary["qpos_sha256"] = hashlib.sha256(q.tobytes()).hexdigest()
    return summary


@pytest.mark.parametrize("key", sorted(EXPECTED))
def test_bundled_trace_replays_to_mains_summary_on_the_stages(key):
    task, embodiment = key.split("/")
    got = replay_digest(task, None if embodiment == "None" else embodiment)
    expected = EXPECTED[key]
    assert {k: got.get(k) for k in expected} == expected
