from __future__ import annotations

import logging

import numpy as np
import pytest

from beavr_sim.headset.validation import LOGGER_NAME, StreamValidator
from beavr_sim.naming import UnknownNameError
from beavr_sim.wire.hand import N_JOINTS, HandFrame


def frame(t_source: float, side: str = "right") -> HandFrame:
    return HandFrame(side, t_source, t_source + 0.01, np.zeros((N_JOINTS, 3)))


class FakeClock:
    def __init__(self) -> None:
        self.now = 100.0

    def __call__(self) -> float:
        return self.now


def test_order_and_duplicates_per_side():
    validator = StreamValidator(clock=FakeClock())
    assert [validator.check(frame(t)) for t in (1.0, 2.0, 3.0)] == [None, None, None]
    assert validator.check(frame(2.5)) == "out_of_order"
    assert validator.check(frame(3.0)) == "duplicate"
    assert validator.last_t_source("right") == 3.0
    assert validator.check(frame(1.0, "left")) is None  # sides are independent
    assert validator.check(frame(1.0, "left")) == "duplicate"
    assert validator.check(frame(3.0 + 1e-9)) is None
    assert validator.accepted == 5
    assert validator.rejected == 3
    assert validator.rejected_by_reason == {"out_of_order": 1, "duplicate": 2}


def test_reject_counts_parse_errors_and_counts_are_copies():
    validator = StreamValidator(clock=FakeClock())
    for reason in ("comma_decimal", "comma_decimal", "wrong_joint_count"):
        validator.reject(reason)
    by_reason = validator.rejected_by_reason
    by_reason["comma_decimal"] = 0
    assert validator.rejected_by_reason == {"comma_decimal": 2, "wrong_joint_count": 1}
    assert (validator.accepted, validator.rejected) == (0, 3)
    with pytest.raises(ValueError, match="non-empty"):
        validator.reject("")


def test_reset_forgets_the_last_time():
    validator = StreamValidator(clock=FakeClock())
    validator.check(frame(5.0))
    validator.check(frame(5.0, "left"))
    validator.reset("right")
    assert validator.check(frame(1.0)) is None
    assert validator.check(frame(1.0, "left")) == "out_of_order"
    validator.reset()
    assert validator.check(frame(0.5, "left")) is None
    with pytest.raises(UnknownNameError, match="right"):
        validator.reset("both")
    with pytest.raises(TypeError, match="HandFrame"):
        validator.check(np.zeros((N_JOINTS, 3)))  # type: ignore[arg-type]


def test_logging_is_rate_limited_per_reason(caplog):
    clock = FakeClock()
    validator = StreamValidator("quest", clock=clock, log_interval_s=5.0)
    caplog.set_level(logging.WARNING, logger=LOGGER_NAME)

    def lines() -> list[str]:
        return [r.getMessage() for r in caplog.records if r.name == LOGGER_NAME]

    validator.reject("comma_decimal", "joint 0: '0,1'")  # first: always logged
    assert len(lines()) == 1
    assert "quest stream" in lines()[0] and "comma_decimal" in lines()[0]
    assert "joint 0: '0,1'" in lines()[0]
    for _ in range(9):
        clock.now += 0.5  # up to 4.5 s after the first line: silent
        validator.reject("comma_decimal")
    assert len(lines()) == 1
    validator.reject("duplicate")  # another reason has its own first line
    assert len(lines()) == 2 and "duplicate" in lines()[1]
    clock.now += 0.5  # 5 s after the first comma_decimal line
    validator.reject("comma_decimal")
    assert len(lines()) == 3
    assert "rejected 10 frame(s) (comma_decimal)" in lines()[2]
    assert "11 in total" in lines()[2]
    clock.now += 4.75
    validator.reject("comma_decimal")
    assert len(lines()) == 3
    clock.now += 0.25
    validator.reject("comma_decimal")
    assert len(lines()) == 4 and "rejected 2 frame(s)" in lines()[3]
    assert all(r.levelno == logging.WARNING for r in caplog.records if r.name == LOGGER_NAME)
    assert validator.rejected_by_reason == {"comma_decimal": 13, "duplicate": 1}


def test_bad_interval():
    with pytest.raises(ValueError, match="log_interval_s"):
        StreamValidator(log_interval_s=-1.0)


def test_with_times_keeps_the_validated_arrays_and_checks_the_times():
    joints = np.random.default_rng(0).normal(size=(N_JOINTS, 3))
    joints[4] = np.nan
    frame = HandFrame("left", 1.0, 1.5, joints, pinch=True, resolution="low")
    moved = frame.with_times(2.0, 2.25)
    assert (moved.t_source, moved.t_receive) == (2.0, 2.25)
    assert (frame.t_source, frame.t_receive) == (1.0, 1.5)  # the original is unchanged
    assert moved.joints is frame.joints and moved.tracked is frame.tracked
    assert not moved.joints.flags.writeable and not moved.tracked[4]
    assert (moved.side, moved.pinch, moved.resolution) == ("left", True, "low")
    for bad in (float("nan"), float("inf")):
        with pytest.raises(ValueError, match="finite"):
            frame.with_times(bad, 0.0)
