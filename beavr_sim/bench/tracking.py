"""``python -m beavr_sim.bench tracking``: motion-to-motion lag and tracking error (issue 26).

Replays bundled traces through the in-process pipeline on the virtual clock (deterministic:
load does not change the numbers) and samples, per effector and control tick, four hand
positions in the robot's world frame (positions only, no orientation):

- A ``raw``: the relative-motion mapping applied to the palm of the newest raw frame of that
  side (no filters): where the arm target would be without filtering;
- B ``filtered``: the operator's mapped arm target (``EffectorTargets.T_world_target``,
  after the keypoint and pose filters);
- C ``ik``: the hand frame the arm IK reached (``EffectorTargets.T_world_hand``), what the
  joint command sent to the twin stands for;
- D ``sim``: the simulated hand (body ``{effector}/hand``) after the twin's step of that tick,
  i.e. one control period after A-C in wall-clock time (``lag_wall_ms`` adds that period).

Lags (ms) between consecutive stages and end to end (A -> D) by cross-correlation of the
velocities (:func:`lag_s`), tracking errors (mm) ``|C - D|`` and ``|B - C|`` per tick
(p50 / p95 / max). Sampled from the first tick at which the mapping is anchored; the first
:data:`SKIP_TICKS` after it are left out (the first frames and the anchoring).

Then a ramp test on the xArm twin (:func:`ramp`): joint 1 commanded along a 2 rad/s ramp
for 0.5 s through ``TwinInterface``; the lag is commanded minus measured position at the end
of the ramp (mrad), with the same for a LEAP finger joint at 1 rad/s.
"""

from __future__ import annotations

import math
from pathlib import Path

import gymnasium as gym
import numpy as np

from beavr_sim.assets import bundled_trace
from beavr_sim.traces.format import TraceReader
from beavr_sim.wire.hand import JOINT_INDEX
from beavr_sim.wire.records import JointCommand

#: (task, embodiment or None) of the traces the benchmark replays by default.
DEFAULT_TRACES = (("PickupBox", None), ("Pour", None), ("PickupBox", "rx1"))
#: Largest lag searched (s).
MAX_LAG_S = 0.3
#: Ticks after the mapping is anchored left out of the series.
SKIP_TICKS = 5
STAGES = ("raw", "filtered", "ik", "sim")


def lag_s(x: np.ndarray, y: np.ndarray, dt: float, max_lag_s: float = MAX_LAG_S) -> float:
    """How long ``y`` lags behind ``x`` (s), both sampled every ``dt`` (arrays N or N x D).

    The lag maximises the cross-correlation of the velocities (finite differences, mean
    removed, summed over the D axes, each lag's products averaged over its overlap) over lags
    0 .. ``max_lag_s`` in steps of ``dt``, refined to a fraction of a step by a cosine
    through the peak and its two neighbours (:func:`_peak_offset`; the neighbour below lag 0
    included, so a result may be down to half a step below 0). NaN if
    there is no motion or too few samples."""
    x = np.asarray(x, dtype=np.float64)
    y = np.asarray(y, dtype=np.float64)
    if x.ndim == 1:
        x, y = x[:, None], y[:, None]
    if x.shape != y.shape:
        raise ValueError(f"x and y differ in shape: {x.shape} vs {y.shape}")
    vx, vy = np.diff(x, axis=0), np.diff(y, axis=0)
    vx -= vx.mean(axis=0)
    vy -= vy.mean(axis=0)
    n = len(vx)
    k_max = int(round(max_lag_s / dt))
    if n < 2 * (k_max + 2) or not (np.any(vx) and np.any(vy)):
        return float("nan")

    def corr(k: int) -> float:  # mean of vx[t] . vy[t + k] over the overlap
        if k >= 0:
            return float(np.sum(vx[: n - k] * vy[k:]) / (n - k))
        return float(np.sum(vx[-k:] * vy[: n + k]) / (n + k))

    c = np.array([corr(k) for k in range(-1, k_max + 2)])  # lags -1 .. k_max + 1
    i = int(np.argmax(c[1 : k_max + 2])) + 1  # the peak within 0 .. k_max
    return ((i - 1) + _peak_offset(c[i - 1], c[i], c[i + 1])) * dt


def _peak_offset(c0: float, c1: float, c2: float) -> float:
    """Where (in steps, -0.5 .. 0.5 from the middle sample) the peak of samples c0, c1, c2 is:
    a cosine ``A cos(w (k - d))`` through them (exact for a sinusoid, less biased than a
    parabola for the peaked correlations of smooth motion), a parabola where no cosine fits."""
    frac = 0.0
    ratio = (c0 + c2) / (2.0 * c1) if c1 > 0 else 2.0
    if -1.0 < ratio < 1.0:
        w = math.acos(ratio)
        frac = math.atan((c2 - c0) / (2.0 * c1 * math.sin(w))) / w
    elif c0 - 2.0 * c1 + c2 < 0:
        frac = 0.5 * (c0 - c2) / (c0 - 2.0 * c1 + c2)
    return float(np.clip(frac, -0.5, 0.5))


def _newest_palm(frames, side: str) -> np.ndarray | None:
    """The raw palm pose of the newest frame of ``side`` whose palm joints are tracked."""
    from beavr_sim.operator.palm import T_world_palm  # local: heavy (the pipeline: mink, scipy)

    palm = [JOINT_INDEX[j] for j in ("wrist", "middle_proximal", "index_proximal")]
    palm.append(JOINT_INDEX["little_proximal"])
    for frame in reversed(frames):
        if frame.side != side or not np.all(np.asarray(frame.tracked)[palm]):
            continue
        joints = np.asarray(frame.joints, dtype=np.float64)
        if not np.isfinite(joints[palm]).all():
            continue
        try:
            return T_world_palm(joints, side)
        except ValueError:  # degenerate palm: the operator drops it too
            continue
    return None


class StageRecorder:
    """A tick listener that records the four stages' positions per effector (NaN where a
    stage has no value yet: no raw frame, mapping not anchored)."""

    def __init__(self, loop):
        import mujoco

        self.loop = loop
        env = loop.twin.env
        self._model = env.model
        self._scratch = mujoco.MjData(env.model)
        self._hand = {name: env.model.body(f"{name}/hand").id for name in loop.operator.effectors}
        self.series: dict[str, list[np.ndarray]] = {name: [] for name in loop.operator.effectors}
        self._raw: dict[str, np.ndarray | None] = dict.fromkeys(loop.operator.effectors)

    def __call__(self, tick) -> None:
        import mujoco

        data = self.loop.twin.env.data
        # The twin's data hold body poses of the step's last kinematics pass (before the last
        # integration): recompute them for the qpos after the step, on a scratch copy.
        self._scratch.qpos[:] = data.qpos
        self._scratch.mocap_pos[:] = data.mocap_pos
        self._scratch.mocap_quat[:] = data.mocap_quat
        mujoco.mj_kinematics(self._model, self._scratch)
        nan3 = np.full(3, np.nan)
        for name, op in self.loop.operator.effectors.items():
            T_raw = _newest_palm(tick.frames, op.side)
            if T_raw is not None:
                self._raw[name] = T_raw
            targets = op.targets()
            raw = filtered = nan3
            if targets.T_world_target is not None and op.mapping.anchored:
                filtered = targets.T_world_target[:3, 3]
                if self._raw[name] is not None:
                    raw = op.mapping.robot_target(self._raw[name], op._resolution)[:3, 3]
            sim = self._scratch.xpos[self._hand[name]]
            self.series[name].append(
                np.stack([raw, filtered, targets.T_world_hand[:3, 3], sim]).copy()
            )

    def arrays(self) -> dict[str, np.ndarray]:
        """Per effector: (ticks, 4 stages, 3) from the first tick with every stage known, plus
        :data:`SKIP_TICKS`; a later gap (tracking lost) holds the last value."""
        out = {}
        for name, rows in self.series.items():
            a = np.asarray(rows) if rows else np.empty((0, 4, 3))
            ok = np.isfinite(a).all(axis=(1, 2))
            if not ok.any():
                out[name] = a[:0]
                continue
            a = a[int(np.argmax(ok)) + SKIP_TICKS :].copy()
            for t in range(1, len(a)):  # hold the last value over NaN gaps
                bad = ~np.isfinite(a[t])
                a[t][bad] = a[t - 1][bad]
            out[name] = a
        return out


def _err_stats(mm: np.ndarray) -> dict:
    return {
        "p50": round(float(np.percentile(mm, 50)), 2),
        "p95": round(float(np.percentile(mm, 95)), 2),
        "max": round(float(mm.max()), 2),
    }


def _ms(s: float) -> float | None:
    return None if not math.isfinite(s) else round(s * 1e3, 1)


def analyse(a: np.ndarray, dt: float) -> dict:
    """Lags (ms) and errors (mm) of one effector's stage series ``a`` (ticks x 4 x 3)."""
    raw, filtered, ik, sim = (a[:, i] for i in range(4))
    return {
        "ticks": len(a),
        "lag_ms": {
            "raw_to_filtered": _ms(lag_s(raw, filtered, dt)),
            "filtered_to_ik": _ms(lag_s(filtered, ik, dt)),
            "ik_to_sim": _ms(lag_s(ik, sim, dt)),
            "raw_to_ik": _ms(lag_s(raw, ik, dt)),
            "raw_to_sim": _ms(lag_s(raw, sim, dt)),
        },
        # In wall-clock time the sim sample comes one control period after the tick's
        # command (it is taken at the end of that tick's physics step): these add it.
        "lag_wall_ms": {
            "ik_to_sim": _ms(lag_s(ik, sim, dt) + dt),
            "raw_to_sim": _ms(lag_s(raw, sim, dt) + dt),
        },
        "error_mm": {
            "ik_to_sim": _err_stats(np.linalg.norm(ik - sim, axis=1) * 1e3),
            "filtered_to_ik": _err_stats(np.linalg.norm(filtered - ik, axis=1) * 1e3),
        },
        "hand_speed_m_s_p95": round(
            float(np.percentile(np.linalg.norm(np.diff(raw, axis=0), axis=1) / dt, 95)), 3
        ),
    }


def build_trace_loop(path: Path, clock: str):
    """(task name, the in-process teleop loop replaying the trace at ``path`` headless on
    ``clock``), as the benchmarks replay bundled traces."""
    from beavr_sim.teleop.session import (  # local: heavy (the pipeline: mink, scipy)
        SessionOptions,
        build_loop,
    )

    task = TraceReader(path).metadata.task
    options = SessionOptions(
        task=task,
        source="trace",
        trace=Path(path),
        viser=False,
        headless=True,
        progress=False,
        clock=clock,
    )
    return task, build_loop(options)


def run_trace(path: Path, max_ticks: int | None = None) -> dict:
    """The tracking block of one trace: per effector, :func:`analyse` of its stages."""
    task, loop = build_trace_loop(path, "virtual")
    recorder = StageRecorder(loop)
    loop.listeners.append(recorder)
    try:
        summary = loop.run(max_seconds=None if max_ticks is None else max_ticks * loop.dt)
    finally:
        loop.twin.env.close()
    return {
        "task": task,
        "embodiment": summary.embodiment,
        "success": summary.success,
        "control_hz": round(1.0 / loop.dt, 3),
        "effectors": {
            name: analyse(a, loop.dt) if len(a) > 2 else {"ticks": len(a)}
            for name, a in recorder.arrays().items()
        },
    }


def _ramp_joint(twin, index: int, rate: float, seconds: float, settle_s: float) -> dict:
    """Hold the home pose ``settle_s``, then ramp action ``index`` at ``rate`` (rad/s) for
    ``seconds``; the lag (commanded - measured) at rest before the ramp and at its end."""
    twin.reset(seed=0)
    command = twin.action.copy()
    dt = twin.dt
    name = next(n for n, sl in twin.slices.items() if sl.start <= index < sl.stop)
    sl = twin.slices[name]

    def step(cmd: np.ndarray):
        return twin.apply({name: JointCommand(name, cmd[sl].copy(), t_source=0.0, t_receive=0.0)})

    for _ in range(int(round(settle_s / dt))):
        state = step(command)
    rest = float(command[index] - state.positions[index])
    q0 = command[index]
    lags, blocked = [], 0
    n = int(round(seconds / dt))
    for k in range(1, n + 1):
        command[index] = q0 + rate * k * dt
        state = step(command)
        blocked += state.guard_blocked
        lags.append(float(state.action[index] - state.positions[index]))
    end = lags[-1]
    return {
        "joint": twin.env.joints.names[index],
        "rate_rad_s": rate,
        "seconds": seconds,
        "lag_end_mrad": round(end * 1e3, 1),
        "lag_at_rest_mrad": round(rest * 1e3, 2),
        "lag_end_ms": round(end / rate * 1e3, 1),
        "lag_mrad_last_5_ticks": [round(v * 1e3, 1) for v in lags[-5:]],
        "guard_blocked_ticks": blocked,
    }


def ramp(
    embodiment: str = "xarm7_leap_right",
    arm_rate: float = 2.0,
    finger_rate: float = 1.0,
    seconds: float = 0.5,
    settle_s: float = 0.5,
) -> dict:
    """Ramp tests on the twin of ``embodiment``: its first arm joint at ``arm_rate`` and the
    index finger's flexion (``leap_1``) at ``finger_rate``, each for ``seconds``."""
    from beavr_sim.twin.twin import TwinInterface  # local: heavy (the pipeline: mink, scipy)

    env = gym.make("beavr_sim/PickupBox-v0", embodiment=embodiment)
    try:
        twin = TwinInterface(env)
        names = twin.env.joints.names
        sl = next(iter(twin.slices.values()))
        arm = sl.start
        finger = next(i for i in range(sl.start, sl.stop) if names[i].endswith("leap_1"))
        return {
            "embodiment": embodiment,
            "arm": _ramp_joint(twin, arm, arm_rate, seconds, settle_s),
            "finger": _ramp_joint(twin, finger, finger_rate, seconds, settle_s),
        }
    finally:
        env.close()


def run(traces: list[Path] | None = None, *, max_ticks: int | None = None) -> dict:
    """The benchmark's JSON-ready result: per trace the tracking blocks, then the ramps."""
    paths = traces or [bundled_trace(task, emb) for task, emb in DEFAULT_TRACES]
    result: dict = {"definitions": _DEFINITIONS, "traces": {}}
    for path in paths:
        key = f"{Path(path).parent.name}/{Path(path).name}"
        result["traces"][key] = run_trace(Path(path), max_ticks=max_ticks)
    result["ramp"] = ramp()
    result["targets"] = _TARGETS
    return result


_DEFINITIONS = {
    "stages": "raw: mapping(raw palm); filtered: mapped target; ik: IK hand; sim: twin hand body",
    "lag": "velocity cross-correlation peak over 0..300 ms, sub-tick by a cosine fit",
    "error": "|position difference| per control tick",
    "lag_wall_ms": "the lag plus one control period: the sim stage is sampled at the end of "
    "the tick's physics step, the others at its start",
}
_TARGETS = {
    "raw_to_sim_lag_ms": 50,
    "ik_to_sim_lag_ms": 20,
    "ik_to_sim_error_p95_mm": 10,
    "arm_ramp_lag_mrad": 20,
}
