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


# ------------------------------------------------------------------ both layouts
def command_digest(commands) -> bytes:
    """The bytes of one tick's commands (effector order): positions, hold, reason."""
    out = b""
    for name in sorted(commands):
        c = commands[name]
        out += name.encode() + np.asarray(c.positions, dtype=np.float64).tobytes()
        out += bytes([c.hold]) + c.reason.encode()
    return out


def digest_commands(process, path: str):
    """An attachment (``Attachment("test_stages:digest_commands", path)``): in the twin
    process, the digest of every lockstep tick's commands, written to ``path`` at the end."""
    digest = hashlib.sha256()
    ticks = [0]

    def after_step(state) -> None:
        digest.update(command_digest(process.tick_commands))
        ticks[0] += 1

    process.stage.after_step.append(after_step)

    def finish() -> None:
        with open(path, "w") as f:
            f.write(f"{digest.hexdigest()} {ticks[0]}")

    return finish


def one_process_digest(task: str, embodiment: str | None, clock: str):
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
    loop.listeners.append(lambda tick: digest.update(command_digest(tick.commands)))
    summary = loop.run()
    loop.twin.env.close()
    return digest.hexdigest(), summary


def multiprocess_digest(task: str, embodiment: str | None, clock: str, tmp_path):
    from beavr_sim.teleop.processes import Attachment, MultiprocessSession
    from beavr_sim.wire.ports import PortConfig, TransportConfig

    options = SessionOptions(
        task=task,
        embodiment=embodiment,
        source="trace",
        clock=clock,
        viser=False,
        headless=True,
        progress=False,
        multiprocess=True,
        transport=TransportConfig(ports=PortConfig.free()),
    )
    path = tmp_path / f"digest-{clock}-{embodiment}.txt"
    session = MultiprocessSession(
        options, attach=(Attachment(f"{__name__}:digest_commands", str(path)),)
    )
    summary = session.run(options.max_seconds, stop_on_success=True)
    digest, ticks = path.read_text().split()
    return digest, int(ticks), summary


@pytest.mark.parametrize(
    ("embodiment", "clock"), [(None, "virtual"), (None, "paced"), ("rx1", "virtual")]
)
def test_multiprocess_replays_a_trace_to_the_same_commands_as_one_process(
    embodiment, clock, tmp_path
):
    """The runner-equivalence test: a bundled trace through both layouts on the virtual and
    paced clocks gives the same commands, bit for bit (main refuses --clock paced with
    --multiprocess and runs --clock virtual on the real clock)."""
    expected, one = one_process_digest("PickupBox", embodiment, clock)
    digest, ticks, multi = multiprocess_digest("PickupBox", embodiment, clock, tmp_path)
    assert multi.processes == {"twin": "ok", "operator": "ok"}
    assert (digest, ticks) == (expected, one.ticks)
    for field in ("success", "frames_received", "commands_applied", "ticks", "holds"):
        assert getattr(multi, field) == getattr(one, field), field
    assert multi.latency_ms["n"] == one.latency_ms["n"]
