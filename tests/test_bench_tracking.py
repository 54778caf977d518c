"""``python -m beavr_sim.bench tracking`` (issue 26): the lag estimator recovers known delays,
and the benchmark reports finite lags and errors on a bundled trace and the ramp test."""

from __future__ import annotations

import math

import numpy as np
import pytest

from beavr_sim.assets import bundled_trace
from beavr_sim.bench import tracking

DT = 1.0 / 30.0


def _smooth(seed: int, delay_s: float, seconds: float = 20.0) -> tuple[np.ndarray, np.ndarray]:
    """A smooth random 3-D signal (a sum of sinusoids of 0.2 .. 3 Hz) sampled at 30 Hz, and
    the same signal delayed by ``delay_s`` (continuous time, not a whole number of samples)."""
    rng = np.random.default_rng(seed)
    f = rng.uniform(0.2, 3.0, (12, 1, 1))
    a = rng.normal(size=(12, 1, 3)) / f
    phase = rng.uniform(0.0, 2 * np.pi, (12, 1, 3))
    t = (np.arange(int(seconds / DT)) * DT)[None, :, None]
    x = (a * np.sin(2 * np.pi * f * t + phase)).sum(axis=0)
    y = (a * np.sin(2 * np.pi * f * (t - delay_s) + phase)).sum(axis=0)
    return x, y


@pytest.mark.parametrize("seed", range(5))
def test_lag_recovers_a_known_delay(seed):
    x, y = _smooth(seed, 0.047)
    assert tracking.lag_s(x, y, DT) * 1e3 == pytest.approx(47.0, abs=3.0)


@pytest.mark.parametrize("delay_ms", [0.0, 10.0, 120.0, 250.0])
def test_lag_over_the_range(delay_ms):
    x, y = _smooth(7, delay_ms / 1e3)
    assert tracking.lag_s(x, y, DT) * 1e3 == pytest.approx(delay_ms, abs=3.0)


def test_lag_of_a_1d_signal_and_no_motion():
    x, y = _smooth(3, 0.1)
    assert tracking.lag_s(x[:, 0], y[:, 0], DT) == pytest.approx(0.1, abs=0.005)
    still = np.zeros((300, 3))
    assert math.isnan(tracking.lag_s(still, still, DT))
    assert math.isnan(tracking.lag_s(x[:10], y[:10], DT))  # too short for the lag range
    with pytest.raises(ValueError):
        tracking.lag_s(x, y[:, :2], DT)


def test_benchmark_on_one_trace_and_the_ramps():
    result = tracking.run_trace(bundled_trace("PickupBox"), max_ticks=200)
    assert result["embodiment"] == "xarm7_leap_right"
    block = result["effectors"]["right"]
    assert block["ticks"] > 100
    lags = block["lag_ms"]
    half_tick_ms = 0.5e3 / result["control_hz"]
    for name in ("raw_to_filtered", "ik_to_sim", "raw_to_sim"):
        assert math.isfinite(lags[name]), name
        assert -half_tick_ms <= lags[name] <= tracking.MAX_LAG_S * 1e3, name
    assert lags["raw_to_sim"] >= lags["ik_to_sim"]
    for name, wall in block["lag_wall_ms"].items():
        assert wall == pytest.approx(lags[name] + 2 * half_tick_ms, abs=0.11), name
    for stats in block["error_mm"].values():
        assert 0 < stats["p50"] <= stats["p95"] <= stats["max"] < 1e3

    ramp = tracking.ramp(seconds=0.3, settle_s=0.2)
    for joint in ("arm", "finger"):
        r = ramp[joint]
        assert r["guard_blocked_ticks"] == 0
        assert math.isfinite(r["lag_end_mrad"])
        assert abs(r["lag_at_rest_mrad"]) < 5.0
    # The xArm follows a ramp (servo model with velocity feed-forward, issue 26); the LEAP
    # finger is a plain position servo and trails it.
    assert abs(ramp["arm"]["lag_end_mrad"]) < 20.0
    assert ramp["finger"]["lag_end_mrad"] > 0
    assert ramp["arm"]["joint"].endswith("joint1")
