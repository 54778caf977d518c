"""One new scene from a segmented source: the palm carried with its references, the arm
through the operator's IK and the twin's guard, the fingers as in the source.

Pieces: consecutive segments with the same reference (approach and grasp of an object;
transport and release to its destination) move rigidly together. When a piece starts, its
transform is T_world_ref_new * inv(T_world_ref_src) (:func:`~.frames.carry`) with the
reference's pose in the source at that frame and in the new scene now; over the piece's
first :attr:`ExecuteConfig.blend_fraction` of its first segment (approach, transport) the
palm target moves from the previous piece's transform of the source palm to this one's
(:func:`~.frames.blend`): the bridge. Every tick the IK steps towards the target (one
control period at its joint speed limit) with the fingers where the source's were, and the
command goes through :class:`~beavr_sim.twin.twin.TwinInterface` (step limit at the joint
speed caps, collision guard): nothing reaches the twin unguarded. A refused command leaves
the twin holding; the IK is resynced to the held joints.

After the source's last frame the last command holds for up to
:attr:`ExecuteConfig.settle_s` while the task's checker decides. A success ticks on for the
recording's tail; anything else is a failure with one reason (see :func:`failure_reason`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from beavr_sim.datasets.augment.frames import blend, carry, smoothstep
from beavr_sim.datasets.augment.replay import Things, Trajectory, make_env
from beavr_sim.datasets.augment.segments import Segment
from beavr_sim.operator.arm_ik import ArmIK, ArmIKConfig
from beavr_sim.operator.obstacles import fixture_obstacles
from beavr_sim.twin.twin import TwinInterface
from beavr_sim.wire.records import JointCommand, Tick, TwinState


@dataclass(frozen=True)
class ExecuteConfig:
    #: Of a piece's first segment (approach, transport), the frames spent bridging from the
    #: previous piece: long enough that the bridge adds little speed (a held cup slips when
    #: the bridge hurries), short enough that the grasp and the placement are exact.
    blend_fraction: float = 0.7
    settle_s: float = 3.0  # hold after the source's last frame, waiting for the checker
    tail_seconds: float = 0.5  # ticks recorded after success (RecordingConfig.tail_seconds)

    def __post_init__(self) -> None:
        if not 0 < self.blend_fraction <= 1:
            raise ValueError(f"blend_fraction must be in (0, 1], got {self.blend_fraction}")
        if min(self.settle_s, self.tail_seconds) < 0:
            raise ValueError("settle_s and tail_seconds must be >= 0")


@dataclass(frozen=True)
class Piece:
    reference: str
    start: int
    stop: int
    lead: int  # frames of its first segment


def pieces_of(segments: list[Segment]) -> list[Piece]:
    """Consecutive segments with the same reference, joined."""
    out: list[Piece] = []
    for seg in segments:
        if out and out[-1].reference == seg.reference and out[-1].stop == seg.start:
            out[-1] = Piece(seg.reference, out[-1].start, seg.stop, out[-1].lead)
        else:
            out.append(Piece(seg.reference, seg.start, seg.stop, seg.stop - seg.start))
    return out


def checker_details(state: TwinState | None) -> dict:
    """The checker's details at ``state`` (``task/...`` of the env's info), names unprefixed."""
    info = state.info if state is not None else {}
    return {k.removeprefix("task/"): v for k, v in info.items() if k.startswith("task/")}


def failure_reason(state: TwinState | None, ran_out: bool) -> str:
    """One line, the same for failures alike (failures are counted by it): ``fallen: item``,
    ``time limit: not in_area``, ``not lifted``, ``checker said no`` (a checker with counts,
    not conditions: the counts are in :func:`checker_details`)."""
    if state is None:
        return "no tick"
    details = checker_details(state)
    if details.get("fallen"):
        return f"fallen: {details['fallen']}"
    unmet = next((k for k, v in details.items() if v is False), "")
    why = f"not {unmet}" if unmet else "checker said no"
    if state.truncated and not ran_out:
        return f"time limit: {why}"
    return why


@dataclass
class Outcome:
    success: bool
    reason: str = ""
    details: dict = field(default_factory=dict)  # the checker's, at the end
    frames: int = 0
    guard_blocks: int = 0
    step_limited: int = 0
    #: Per piece, the carrying transform: translation (m) and turn about z (rad).
    transforms: list[list[float]] = field(default_factory=list)


class Rig:
    """The twin (env, guard, step limit) and the operator's arm IK for one task: built once
    per process, reset per episode."""

    def __init__(self, task: str, embodiment: str):
        self.env = make_env(task, embodiment)
        self.twin = TwinInterface(self.env)
        self.effector = self.env.embodiment.effectors[0]
        self.ik = ArmIK(
            self.env.embodiment, self.effector.name, self.twin.dt, ArmIKConfig(iterations=3)
        )
        self.slice = self.env.joints.slices[self.effector.name]
        self.n_arm = len(self.effector.arm_joints)
        self.things = Things.of(self.env)

    def reset(self, seed: int) -> None:
        q = self.twin.reset(seed)
        self.ik.reset(q[self.slice])
        self.ik.set_obstacles(fixture_obstacles(self.env.model, self.env.data))

    def tick(self, target: np.ndarray, fingers: np.ndarray) -> tuple[JointCommand, TwinState]:
        """One control period: IK towards ``target`` with ``fingers``, through the twin."""
        self.ik.set_fingers(fingers)
        arm = self.ik.step(target)
        t = self.env.elapsed_seconds
        cmd = JointCommand(self.effector.name, np.concatenate([arm, fingers]), t, t)
        state = self.twin.apply({self.effector.name: cmd})
        if state.guard_blocked:  # the twin holds: the IK starts again from the held joints
            self.ik.reset(self.twin.action[self.slice], posture=self.ik.posture)
        return cmd, state


def execute(
    rig: Rig,
    traj: Trajectory,
    segments: list[Segment],
    seed: int,
    config: ExecuteConfig,
    listener=None,
) -> Outcome:
    """Run one new episode at ``seed`` (see the module docstring); ``listener`` gets every
    tick (the recorder). The rig must be reset at ``seed`` by the caller first."""
    fps = rig.env.control_hz
    actions = traj.episode.actions
    pieces = pieces_of(segments)
    outcome = Outcome(success=False)
    blocks0 = sum(rig.twin.guard_blocks.values())
    limited0 = sum(rig.twin.step_limited.values())
    T_prev = T_cur = np.eye(4)
    blend_frames = 1
    piece_start = 0
    state: TwinState | None = None
    target = traj.palm[0]
    fingers = actions[0][traj.hand].astype(np.float64)
    starts = {p.start: p for p in pieces}

    def tick() -> TwinState:
        cmd, st = rig.tick(target, fingers)
        outcome.frames += 1
        if listener is not None:
            listener(Tick(st.t, (), {cmd.effector: cmd}, st))
        return st

    ran_out = False
    for i in range(traj.frames):
        piece = starts.get(i)
        if piece is not None:
            ref = piece.reference
            at = max(i - 1, 0)
            src_pos = traj.pos[ref][at] if i else traj.start_pos[ref]
            src_yaw = traj.yaw[ref][at] if i else traj.start_yaw[ref]
            new_pos, new_yaw = rig.things.pose(rig.env, ref)
            T_prev, T_cur = (
                T_cur,
                carry(src_pos, src_yaw, new_pos, new_yaw, traj.things.symmetry[ref]),
            )
            blend_frames = max(1, int(config.blend_fraction * piece.lead))
            piece_start = i
            turn = float(np.arctan2(T_cur[1, 0], T_cur[0, 0]))
            outcome.transforms.append([*np.round(T_cur[:3, 3], 4).tolist(), round(turn, 4)])
        w = smoothstep((i - piece_start + 1) / blend_frames)
        target = blend(T_prev @ traj.palm[i], T_cur @ traj.palm[i], w)
        fingers = actions[i][traj.hand].astype(np.float64)
        state = tick()
        if state.success or state.failure or state.truncated:
            break
    else:
        ran_out = True
        for _ in range(int(round(config.settle_s * fps))):
            state = tick()
            if state.success or state.failure or state.truncated:
                break
    outcome.success = bool(state is not None and state.success)
    if outcome.success:
        for _ in range(int(round(config.tail_seconds * fps))):
            tick()
    else:
        outcome.reason = failure_reason(state, ran_out)
    outcome.details = {
        k: v if isinstance(v, bool | int | str) else float(v)
        for k, v in checker_details(state).items()
    }
    outcome.guard_blocks = sum(rig.twin.guard_blocks.values()) - blocks0
    outcome.step_limited = sum(rig.twin.step_limited.values()) - limited0
    return outcome
