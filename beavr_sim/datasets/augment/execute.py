"""One new scene from a segmented source: each palm carried with its references, the arms
through the operator's IK and the twin's guard, the fingers as in the source.

Pieces (:mod:`.coordination`): per arm, consecutive segments with the same reference move
rigidly together; all arms follow the source's clock (lockstep), and a piece that waits for
another arm (sequential constraint) or shares its transform (coordination) is anchored there.
At a piece's anchor its transform is T_world_ref_new * inv(T_world_ref_src)
(:func:`~.frames.carry`) with the reference's pose in the source at that frame and in the new
scene now; over :attr:`ExecuteConfig.blend_fraction` of its lead (the frames from the anchor to
the end of its first segment) the palm target moves from the arm's previous transform of the
source palm to this one's (:func:`~.frames.blend`): the bridge. Before an arm's first piece
its palm follows the source's untransformed. Every tick each arm's IK steps towards its
target (one control period at its joint speed limit) with the fingers where the source's
were, and the commands go through :class:`~beavr_sim.twin.twin.TwinInterface` (step limit at
the joint speed caps, collision guard): nothing reaches the twin unguarded. A refused command
leaves the twin holding; the IKs are resynced to the held joints. A body (RX-1's torso) is not
commanded: it holds.

After the source's last frame the last commands hold for up to
:attr:`ExecuteConfig.settle_s` while the task's checker decides. A success ticks on for the
recording's tail; anything else is a failure with one reason (see :func:`failure_reason`).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from beavr_sim.datasets.augment.coordination import WORLD, coordinate
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
    """The twin (env, guard, step limit) and the operator's arm IK of every effector for one
    task: built once per process, reset per episode."""

    def __init__(self, task: str, embodiment: str):
        self.env = make_env(task, embodiment)
        self.twin = TwinInterface(self.env)
        self.arms = tuple(e.name for e in self.env.embodiment.effectors)
        self.ik = {
            a: ArmIK(self.env.embodiment, a, self.twin.dt, ArmIKConfig(iterations=3))
            for a in self.arms
        }
        self.slice = {a: self.env.joints.slices[a] for a in self.arms}
        self.things = Things.of(self.env)

    def reset(self, seed: int) -> None:
        q = self.twin.reset(seed)
        obstacles = fixture_obstacles(self.env.model, self.env.data)
        for a, ik in self.ik.items():
            ik.reset(q[self.slice[a]])
            ik.set_obstacles(obstacles)

    def tick(
        self, targets: dict[str, np.ndarray], fingers: dict[str, np.ndarray]
    ) -> tuple[dict[str, JointCommand], TwinState]:
        """One control period: every arm's IK towards its target with its fingers, through
        the twin."""
        t = self.env.elapsed_seconds
        commands = {}
        for a, ik in self.ik.items():
            ik.set_fingers(fingers[a])
            arm = ik.step(targets[a])
            commands[a] = JointCommand(a, np.concatenate([arm, fingers[a]]), t, t)
        state = self.twin.apply(commands)
        if state.guard_blocked:  # the twin holds: the IKs start again from the held joints
            for a, ik in self.ik.items():
                ik.reset(self.twin.action[self.slice[a]], posture=ik.posture)
        return commands, state


@dataclass
class _Arm:
    """One arm's carrying state during :func:`execute`."""

    T_prev: np.ndarray = field(default_factory=lambda: np.eye(4))
    T_cur: np.ndarray = field(default_factory=lambda: np.eye(4))
    anchor: int = 0
    blend_frames: int = 1


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
    pieces = coordinate(segments, traj.speed)
    outcome = Outcome(success=False)
    blocks0 = sum(rig.twin.guard_blocks.values())
    limited0 = sum(rig.twin.step_limited.values())
    arms = {a: _Arm() for a in rig.arms}
    shared: dict[int, np.ndarray] = {}
    state: TwinState | None = None
    targets = {a: traj.palm[a][0] for a in rig.arms}
    fingers = {a: actions[0][traj.hand[a]].astype(np.float64) for a in rig.arms}
    anchors: dict[int, list] = {}
    for p in pieces:
        anchors.setdefault(p.anchor, []).append(p)

    def tick() -> TwinState:
        cmds, st = rig.tick(targets, fingers)
        outcome.frames += 1
        if listener is not None:
            listener(Tick(st.t, (), cmds, st))
        return st

    ran_out = False
    for i in range(traj.frames):
        for piece in anchors.get(i, ()):
            arm, ref = arms[piece.arm], piece.reference
            T = shared.get(piece.group) if piece.group is not None else None
            if ref == WORLD:  # a retreat: back to the source's own palm (coordination)
                T = np.eye(4)
            elif T is None:
                at = max(i - 1, 0)
                src_pos = traj.pos[ref][at] if i else traj.start_pos[ref]
                src_yaw = traj.yaw[ref][at] if i else traj.start_yaw[ref]
                new_pos, new_yaw = rig.things.pose(rig.env, ref)
                T = carry(src_pos, src_yaw, new_pos, new_yaw, traj.things.symmetry[ref])
                if piece.group is not None:
                    shared[piece.group] = T
            arm.T_prev, arm.T_cur = arm.T_cur, T
            arm.blend_frames = max(1, int(config.blend_fraction * piece.lead))
            arm.anchor = i
            turn = float(np.arctan2(T[1, 0], T[0, 0]))
            outcome.transforms.append([*np.round(T[:3, 3], 4).tolist(), round(turn, 4)])
        for a, arm in arms.items():
            w = smoothstep((i - arm.anchor + 1) / arm.blend_frames)
            targets[a] = blend(arm.T_prev @ traj.palm[a][i], arm.T_cur @ traj.palm[a][i], w)
            fingers[a] = actions[i][traj.hand[a]].astype(np.float64)
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
