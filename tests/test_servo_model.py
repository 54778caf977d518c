"""The emulators' servo model: one servo (floats) and many (arrays) step alike, to the bit."""

import math

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from beavr_sim.hardware.servo_model import step_towards

finite = st.floats(-1e4, 1e4, allow_nan=False)
servos = st.lists(st.tuples(finite, finite, finite), min_size=1, max_size=8)


@settings(max_examples=300, deadline=None)
@given(
    servos=servos,
    dt=st.sampled_from([1e-3, 0.01, 1 / 30, 0.1]),
    max_speed=st.floats(0.1, 5000.0),
    accel=st.sampled_from([math.inf, 20.0, 150.0, 1e4]),
)
def test_one_servo_steps_as_each_of_many(servos, dt, max_speed, accel):
    p, g, v = (np.array(col, dtype=np.float64) for col in zip(*servos, strict=True))
    g[::3] = p[::3]  # some servos on their goal
    many_p, many_v = step_towards(p, g, dt, max_speed, v, accel)
    per_servo_accel = np.where(np.arange(p.size) % 2, accel, math.inf)
    mixed_p, mixed_v = step_towards(p, g, dt, max_speed, v, per_servo_accel)
    for i in range(p.size):
        one = step_towards(float(p[i]), float(g[i]), dt, max_speed, float(v[i]), accel)
        assert one == (many_p[i], many_v[i])
        assert isinstance(one[0], float) and isinstance(one[1], float)
        a_i = float(per_servo_accel[i])
        assert step_towards(float(p[i]), float(g[i]), dt, max_speed, float(v[i]), a_i) == (
            mixed_p[i],
            mixed_v[i],
        )
        # never past the goal, never faster than the cap (braking may undercut it)
        lo, hi = sorted((p[i], g[i]))
        assert lo <= one[0] <= hi or abs(one[0] - p[i]) <= abs(v[i]) * dt + 1e-9
        if math.isinf(accel):
            assert abs(one[1]) <= max_speed * (1 + 1e-12)
