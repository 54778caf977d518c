"""A hand from a model file: the Shadow hand inside the gymnasium-robotics 1.4.2 wheel (never
vendored; downloaded once at test time like the Franka's, skipped with a reason offline),
read from ``examples/robots/shadow_hand_right.toml``: its table's errors name the valid
choices, its reach and finger scales are derived from the model, and the fingertip
retargeter follows a human pinch without exceeding its speed cap or leaving the limits.
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np
import pytest
from fixtures_shared import robotics_wheel_on_path

from beavr_sim.operator.retarget import human_template
from beavr_sim.operator.retarget_model import ModelHandRetargeter
from beavr_sim.robots.hand_file import load_hand, read_hand_table
from beavr_sim.robots.robot_file import RobotFileError
from beavr_sim.wire.hand import JOINT_INDEX

HAND = Path(__file__).resolve().parents[1] / "examples" / "robots" / "shadow_hand_right.toml"


@pytest.fixture(scope="module")
def table():
    with robotics_wheel_on_path(), HAND.open("rb") as f:
        yield tomllib.load(f)["hands"]["shadow"]


@pytest.fixture(scope="module")
def shadow(table):
    return load_hand(read_hand_table(HAND, "shadow", table))


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"fingers": {"pinky": "site:x"}}, "Valid fingers: index"),
        ({"fingers": {"thumb": "tip"}}, "expected 'site:NAME' or 'body:NAME'"),
        ({"thumb": "index", "fingers": {"thumb": "site:robot0:S_thtip"}}, "Valid thumbs: thumb"),
        ({"human_fingers": {"index": "pinky"}}, "Valid human fingers"),
        ({"palm_axes": ["x", "x", "z"]}, "palm_axes"),
        ({"colour": "red"}, "valid keys"),
    ],
)
def test_a_bad_hand_table_names_the_key_and_the_valid_choices(table, change, message):
    with pytest.raises(RobotFileError, match=message):
        read_hand_table(HAND, "shadow", {**table, **change})


def test_names_the_model_lacks_are_listed_with_the_valid_ones(table):
    fingers = {**table["fingers"], "index": "site:robot0:S_nope"}
    with pytest.raises(RobotFileError, match=r"valid sites: .*robot0:S_fftip"):
        load_hand(read_hand_table(HAND, "shadow", {**table, "fingers": fingers}))
    with pytest.raises(RobotFileError, match=r"Valid root bod.*robot0:palm"):
        load_hand(read_hand_table(HAND, "shadow", {**table, "root": "palm"}))


def test_the_shadow_hand_is_derived_from_its_model(shadow):
    assert shadow.n_joints == 22  # the wrist's two joints sit at and above the root
    assert all(n.startswith("robot0:") and "WR" not in n for n in shadow.joint_names)
    assert (shadow.lower < shadow.upper).all()
    assert set(shadow.reach) == {"thumb", "index", "middle", "ring", "little"}
    assert 0.15 < shadow.reach["middle"] < 0.25


def pinch(amount: float) -> np.ndarray:
    """The template right hand with thumb and index tips moved ``amount`` of the way to their
    midpoint (distal joints half as far)."""
    k = human_template("right")
    t, i = JOINT_INDEX["thumb_tip"], JOINT_INDEX["index_tip"]
    mid = 0.5 * (k[t] + k[i])
    for finger in ("thumb", "index"):
        for part, w in (("tip", 1.0), ("distal", 0.5)):
            j = JOINT_INDEX[f"{finger}_{part}"]
            k[j] = k[j] + w * amount * (mid - k[j])
    return k


def test_the_fingers_follow_a_human_pinch_within_the_speed_cap(shadow):
    ik = ModelHandRetargeter(shadow, "right")
    dt = 1 / 30
    cap = np.radians(shadow.spec.max_velocity_deg_s) * dt
    amounts = np.concatenate([np.linspace(0, 1, 30), np.linspace(1, 0, 30), np.zeros(15)])
    human, robot, q_prev = [], [], ik.q.copy()
    for a in amounts:
        k = pinch(float(a))
        q = ik.step(k, dt)
        assert (np.abs(q - q_prev) <= cap + 1e-9).all()
        assert ((q >= shadow.lower) & (q <= shadow.upper)).all()
        q_prev = q
        human.append(np.linalg.norm(k[JOINT_INDEX["thumb_tip"]] - k[JOINT_INDEX["index_tip"]]))
        tips = ik.tips(q)
        robot.append(np.linalg.norm(tips[0] - tips[1]))
    assert np.corrcoef(human, robot)[0, 1] > 0.8
    assert min(robot) < 0.5 * max(robot)
    assert ik.holds == 0


def test_bad_keypoints_hold_the_last_command_and_are_counted(shadow):
    ik = ModelHandRetargeter(shadow, "right")
    q = ik.step(pinch(0.5), 1 / 30)
    bad = pinch(0.5)
    bad[JOINT_INDEX["thumb_tip"], 1] = np.nan  # a tip the solver uses
    for keypoints in (bad, None, np.zeros((5, 3)), "junk"):
        assert np.array_equal(ik.step(keypoints, 1 / 30), q)  # type: ignore[arg-type]
    assert ik.holds == 4


def test_a_finger_whose_tip_is_untracked_holds_and_the_others_follow(shadow):
    ik = ModelHandRetargeter(shadow, "right", dt=1 / 30)
    q0 = ik.retarget(pinch(0.0))
    tracked = np.ones(len(JOINT_INDEX), dtype=bool)
    tracked[JOINT_INDEX["index_tip"]] = False
    k = pinch(1.0)
    k[JOINT_INDEX["index_tip"]] = np.nan  # untracked: its position is meaningless
    for _ in range(10):
        q = ik.retarget(k, tracked)
    index = [i for i, n in enumerate(shadow.joint_names) if n.startswith("robot0:FF")]
    thumb = [i for i, n in enumerate(shadow.joint_names) if n.startswith("robot0:TH")]
    assert np.array_equal(q[index], q0[index])
    assert np.abs(q[thumb] - q0[thumb]).max() > 0.1
    assert ik.holds == 0
