"""Synthetic VR traces: a task's scripted expert, as a human operator would have performed it.

``python -m beavr_sim.traces synth --task T --seed S --out F [--embodiment E]``

The expert runs closed loop through the real teleop pipeline: each control tick it decides
where each robot hand should go and how its fingers should be shaped (its ``pose`` and
``fingers`` targets); a *synthetic operator* turns that into tracked human hands, and those
frames - exactly as written to the trace - drive the operator, which drives the twin. So the
trace is what a VR operator who watched the twin would have produced, and replaying it
through the pipeline reproduces the episode exactly (same frames, same virtual clock).

The synthetic operator:

- arm: the palm pose that the operator's relative motion mapping sends to the expert's hand
  target (``RelativeMotionMapping.hand_for`` with the operator's own anchor, as a person
  corrects by watching the robot); before the anchor exists, a still palm in front of the
  chest (``SynthConfig.palm_start``);
- fingers: the human hand model of ``beavr_sim.operator.retarget.human_keypoints_for`` (an
  adult palm template, finger points mapped back from the LEAP hand through the inverse of
  the retargeting's scale), posed at that palm;
- tracking: frames at ``frame_hz`` (the Quest tracks at 60-90 Hz), palm poses interpolated
  between control ticks, i.i.d. Gaussian noise of ``noise_mm`` on every joint coordinate,
  and ``dropouts`` short gaps (``dropout_s``) with no frame at all, as when tracking drops.
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import asdict, dataclass, field
from pathlib import Path

import gymnasium as gym
import numpy as np

from beavr_sim.experts.registry import expert_class
from beavr_sim.headset.sources import FrameListSource
from beavr_sim.naming import UnknownNameError
from beavr_sim.operator.filters import slerp
from beavr_sim.operator.operator import Operator, OperatorConfig
from beavr_sim.operator.retarget import human_keypoints_for
from beavr_sim.tasks.registry import canonical_task_name
from beavr_sim.teleop.pipeline import TeleopLoop, TeleopSummary
from beavr_sim.traces.format import (
    TraceMetadata,
    TraceReader,
    TraceWriter,
    hand_from_json,
    hand_to_json,
)
from beavr_sim.twin.twin import TwinInterface
from beavr_sim.wire.hand import HandFrame

#: Palm down, fingers forward (+x), per side, in front of a standing operator (headset world
#: frame, right-handed Z-up, metres).
PALM_START = {"right": (0.35, -0.2, 1.05), "left": (0.35, 0.2, 1.05)}


@dataclass(frozen=True)
class SynthConfig:
    frame_hz: float = 60.0
    noise_mm: float = 1.0
    dropouts: int = 3
    dropout_s: tuple[float, float] = (0.05, 0.2)
    palm_start: dict = field(default_factory=lambda: dict(PALM_START))
    #: Frames of a still hand before the expert starts (the operator anchors on them).
    still_s: float = 0.3

    def __post_init__(self) -> None:
        if not self.frame_hz > 0:
            raise ValueError(f"frame_hz must be positive, got {self.frame_hz}")
        if self.noise_mm < 0 or self.dropouts < 0:
            raise ValueError("noise_mm and dropouts must be >= 0")
        lo, hi = self.dropout_s
        if not 0 < lo <= hi:
            raise ValueError(f"dropout_s must be 0 < min <= max, got {self.dropout_s}")


def _palm_down(position) -> np.ndarray:
    T = np.eye(4)
    T[:3, :3] = np.column_stack([[0, 0, -1.0], [0, 1.0, 0], [1.0, 0, 0]])  # x palmar, z fingers
    T[:3, 3] = position
    return T


def _interpolate(T_a: np.ndarray, T_b: np.ndarray, s: float) -> np.ndarray:
    T = np.eye(4)
    T[:3, 3] = (1 - s) * T_a[:3, 3] + s * T_b[:3, 3]
    T[:3, :3] = slerp(T_a[:3, :3], T_b[:3, :3], s)
    return T


@dataclass
class SynthResult:
    frames: list[HandFrame]
    summary: TeleopSummary
    metadata: dict


def synthesize(
    task: str,
    seed: int,
    embodiment: str = "xarm7_leap_right",
    config: SynthConfig | None = None,
    operator_config: OperatorConfig | None = None,
    quantize=None,
) -> SynthResult:
    """Run the expert through the pipeline once; returns the frames and the episode summary.

    ``quantize(frame) -> frame`` rounds a frame as the trace file stores it, so the pipeline
    sees exactly what a replay will see.
    """
    config = config or SynthConfig()
    env = gym.make(f"beavr_sim/{task}-v0", embodiment=embodiment).unwrapped
    expert = expert_class(task)(env)
    twin = TwinInterface(env)
    operator = Operator(env.embodiment, 1.0 / env.control_hz, operator_config)
    source = FrameListSource([])
    loop = TeleopLoop(twin, operator, source)
    loop.reset(seed)
    expert.reset()
    rng = np.random.default_rng(seed)
    dt = loop.dt
    sides = {e.name: e.side for e in env.embodiment.effectors}
    start = {name: _palm_down(config.palm_start[side]) for name, side in sides.items()}
    previous = dict(start)
    horizon = env.max_episode_seconds
    gaps = []
    for _ in range(config.dropouts):
        t0 = rng.uniform(1.0, max(1.5, horizon - 2.0))
        gaps.append((t0, t0 + rng.uniform(*config.dropout_s)))
    frame_dt = 1.0 / config.frame_hz
    frames: list[HandFrame] = []
    n_frame = 0
    still_ticks = int(round(config.still_s / dt))
    summary = None
    while True:
        k = loop.ticks
        t_tick = k * dt
        if k >= still_ticks:
            expert.act()
        desired = {}
        for name in sides:
            mapping = operator.effectors[name].mapping
            if mapping.anchored and k >= still_ticks:
                desired[name] = mapping.hand_for(expert.pose[name].as_matrix())
            else:
                desired[name] = previous[name]
        # Frames in (t_previous_tick, t_tick], palm poses interpolated.
        while n_frame * frame_dt <= t_tick + 1e-9:
            t_f = n_frame * frame_dt
            s = 1.0 if k == 0 else min(1.0, max(0.0, (t_f - (t_tick - dt)) / dt))
            n_frame += 1
            if any(a <= t_f < b for a, b in gaps):
                continue
            for name, side in sides.items():
                T_palm = _interpolate(previous[name], desired[name], s)
                q_hand = expert.fingers[name]
                kp = human_keypoints_for(q_hand, side)
                joints = kp @ T_palm[:3, :3].T + T_palm[:3, 3]
                joints = joints + rng.normal(0.0, config.noise_mm * 1e-3, joints.shape)
                frame = HandFrame(side=side, t_source=t_f, t_receive=t_f, joints=joints)
                if quantize is not None:
                    frame = quantize(frame)
                source.push(frame)
                frames.append(frame)
        previous = desired
        tick = loop.tick()
        if tick.state.success or tick.state.failure or tick.state.truncated:
            break
    summary = loop.summary(success=tick.state.success)
    env.close()
    metadata = TraceMetadata(
        source="synth",
        frame_rate_hz=config.frame_hz,
        task=task,
        embodiment=embodiment,
        seed=seed,
        generator={
            "name": "beavr_sim.synthetic.trace",
            "expert": type(expert).__name__,
            **{k: list(v) if isinstance(v, tuple) else v for k, v in asdict(config).items()},
            "episode_success": bool(summary.success),
            "episode_seconds": summary.duration_s,
        },
    )
    return SynthResult(frames=frames, summary=summary, metadata=metadata)


def quantize(frame: HandFrame) -> HandFrame:
    """The frame exactly as a trace file stores it (0.1 mm)."""
    return hand_from_json(hand_to_json(frame))


def write_trace(path: Path, result: SynthResult) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with TraceWriter(path, result.metadata) as writer:
        for frame in result.frames:
            writer.write_hand(frame)
    return path


def replay(path: Path, **kwargs) -> TeleopSummary:
    """Replay a trace through the in-process pipeline on the virtual clock."""
    from beavr_sim.teleop.session import (  # local: heavy (the pipeline: mink, scipy)
        SessionOptions,
        build_loop,
    )

    options = SessionOptions(
        task=TraceReader(path).metadata.task,
        source="trace",
        trace=Path(path),
        viser=False,
        headless=True,
        progress=False,
        **kwargs,
    )
    loop = build_loop(options)
    try:
        return loop.run()
    finally:
        loop.twin.env.close()


def main(argv: list[str] | None = None) -> int:

    parser = argparse.ArgumentParser(
        prog="python -m beavr_sim.traces synth",
        description="Synthesise a VR trace from a task's scripted expert (closed loop through "
        "the teleop pipeline); prints one JSON line.",
    )
    parser.add_argument("--task", required=True)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--embodiment", default="xarm7_leap_right")
    parser.add_argument("--frame-hz", type=float, default=SynthConfig.frame_hz)
    parser.add_argument("--noise-mm", type=float, default=SynthConfig.noise_mm)
    parser.add_argument("--dropouts", type=int, default=SynthConfig.dropouts)
    parser.add_argument(
        "--tries",
        type=int,
        default=1,
        help="seeds to try (seed, seed+1, ...) until an episode succeeds (default 1)",
    )
    parser.add_argument("--no-verify", action="store_true", help="skip the replay check")
    parser.add_argument(
        "--keep-failed", action="store_true", help="write the trace even if the episode failed"
    )
    args = parser.parse_args(argv)
    try:
        task = canonical_task_name(args.task)
        config = SynthConfig(frame_hz=args.frame_hz, noise_mm=args.noise_mm, dropouts=args.dropouts)
        for seed in range(args.seed, args.seed + max(1, args.tries)):
            result = synthesize(task, seed, args.embodiment, config, quantize=quantize)
            print(
                f"seed {seed}: {'success' if result.summary.success else 'failed'} "
                f"after {result.summary.duration_s:.1f} s",
                file=sys.stderr,
            )
            if result.summary.success:
                break
    except (UnknownNameError, ValueError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    if not result.summary.success and not args.keep_failed:
        print(
            f"error: no successful episode in {max(1, args.tries)} tries; nothing written "
            "(--keep-failed writes the last one)",
            file=sys.stderr,
        )
        return 1
    write_trace(args.out, result)
    report = {
        "out": str(args.out),
        "task": task,
        "embodiment": args.embodiment,
        "seed": seed,
        "success": result.summary.success,
        "frames": len(result.frames),
        "duration_s": result.summary.duration_s,
    }
    if not args.no_verify:
        replayed = replay(args.out)
        report["replay_success"] = replayed.success
        report["replay_duration_s"] = replayed.duration_s
    print(json.dumps(report))
    return 0 if result.summary.success else 1
