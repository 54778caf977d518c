"""The operator: tracked hands in, joint targets per effector out (one implementation).

Side and embodiment are data: each effector of the embodiment is driven by the hand of its
side through an :class:`EffectorOperator`; nothing branches on left or right. Per frame
(:meth:`Operator.observe`) the keypoints are smoothed, the palm pose computed, checked for
tracking jumps and filtered; per control tick (:meth:`Operator.command`) the arm IK steps
towards the mapped target and the fingers are retargeted.

Session control:

- pause: the source's pause stream (``HandFrame.paused``), a left-hand pinch (rising edge of
  ``HandFrame.pinch`` toggles), or the UI (:meth:`Operator.set_paused`). Paused effectors
  hold their last command; on resume every mapping is re-anchored so nothing jumps.
- gesture: a left-hand pinch held for ``long_pinch_s`` (source time) is the "record" gesture
  (start / stop a recorded episode): the pause its press toggled is undone and ``"record"``
  is queued for :meth:`Operator.take_gestures`. The robot holds during the gesture. Both
  hands pinching at once (rising edge) is the emergency-stop gesture ``"estop"`` (a mirrored
  session latches its e-stop on it).
- tracking loss: no usable frame (palm joints tracked) for ``tracking_timeout_s``: the effector
  holds where it is and a warning is logged; when tracking returns it continues from the same
  anchor (the hand may have moved meanwhile, within the jump limit).
- jumps: a palm that moved faster than ``max_hand_speed`` (and more than ``min_jump``) since
  the last accepted frame is a tracking glitch: the frame is ignored and counted. If the hand
  stays at the new place for ``reanchor_after`` frames, the mapping re-anchors there.
- resolution: switching between high (1.0) and low (0.6) motion scale re-anchors, so the new
  scale applies to motion from that instant and the robot does not jump.
- reset (:meth:`Operator.reset`): re-home: IK state from the measured joints, mappings released.
"""

from __future__ import annotations

import logging
import math
import time
from dataclasses import dataclass, field

import numpy as np

from beavr_sim.naming import check_name
from beavr_sim.operator import kernels
from beavr_sim.operator.arm_ik import ArmIK, ArmIKConfig
from beavr_sim.operator.arm_mapping import RelativeMotionMapping, axis_map
from beavr_sim.operator.filters import KeypointSmoother, PoseSmoother
from beavr_sim.operator.palm import T_world_palm
from beavr_sim.operator.retarget import LeapRetargeter, RetargetConfig, human_template
from beavr_sim.robots import Embodiment
from beavr_sim.wire.hand import JOINT_INDEX, SIDES, HandFrame
from beavr_sim.wire.records import JointCommand

log = logging.getLogger("beavr_sim.operator.operator")

WRIST = JOINT_INDEX["wrist"]

HOLD_REASONS = ("", "waiting", "paused", "tracking_lost")
GESTURES = ("record", "estop")


@dataclass(frozen=True)
class OperatorConfig:
    """Filtering, safety and solver settings of the operator (see the module docstring)."""

    keypoint_window: int = 5
    alpha_position: float = 0.6
    alpha_rotation: float = 0.6
    tracking_timeout_s: float = 0.25
    max_hand_speed: float = 3.0  # m/s
    min_jump: float = 0.05  # m
    reanchor_after: int = 10  # frames
    pinch_pauses: bool = True
    long_pinch_s: float = 1.0
    arm_ik: ArmIKConfig = field(default_factory=ArmIKConfig)
    retarget: RetargetConfig = field(default_factory=RetargetConfig)

    def __post_init__(self) -> None:
        if self.keypoint_window < 1:
            raise ValueError(f"keypoint_window must be >= 1, got {self.keypoint_window}")
        for name in ("tracking_timeout_s", "max_hand_speed", "min_jump", "long_pinch_s"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)!r}")
        if self.reanchor_after < 1:
            raise ValueError(f"reanchor_after must be >= 1, got {self.reanchor_after}")


@dataclass(frozen=True)
class EffectorTargets:
    """What one effector is steering towards, in the world frame (for views and logs).

    ``T_world_target``: the arm's hand-frame target (None until the mapping is anchored);
    ``T_world_hand``: the hand frame the IK reached; ``finger_targets_world``: the LEAP tip and
    distal targets (8 x 3, placed on ``T_world_hand``); ``keypoints_world``: the operator's
    hand skeleton (26 canonical joints) drawn at the arm target with the finger scale, so the
    human hand and the robot hand overlap. The last two are None before the first frame.
    """

    effector: str
    side: str
    T_world_target: np.ndarray | None
    T_world_hand: np.ndarray
    finger_targets_world: np.ndarray | None
    keypoints_world: np.ndarray | None
    hold: bool
    reason: str


@dataclass
class OperatorStats:
    frames: int = 0
    jumps_rejected: int = 0
    untracked_frames: int = 0
    reanchors: int = 0
    tracking_losses: int = 0


class EffectorOperator:
    """Hand frames of one side -> joint targets of one effector."""

    def __init__(self, embodiment: Embodiment, effector: str, dt: float, config: OperatorConfig):
        self.config = config
        self.effector = embodiment.effector(effector)
        self.side = self.effector.side
        self.ik = ArmIK(embodiment, effector, dt, config.arm_ik)
        self.retargeter = LeapRetargeter(self.side, config.retarget)
        self.mapping = RelativeMotionMapping(axis_map(embodiment.name, self.side))
        self.keypoints = KeypointSmoother(config.keypoint_window)
        self.pose_filter = PoseSmoother(config.alpha_position, config.alpha_rotation)
        self.stats = OperatorStats()
        self.n_arm = len(self.effector.arm_joints)
        self._warm_up(dt)

    def _warm_up(self, dt: float) -> None:
        """Run the per-frame and per-tick code once on the template hand, then re-home.

        The per-tick arithmetic is in numba kernels (:mod:`beavr_sim.operator.kernels`),
        compiled on their first call (about 10 s on a small machine, once after install;
        later processes load them from the on-disk cache in a fraction of a second). This
        does it here, before any frame arrives, rather than in the first control tick."""
        t0 = time.perf_counter()
        self.reset(self.ik.joints.home)
        joints = human_template(self.side)
        for i in range(2):
            self.observe(HandFrame(self.side, i * dt, i * dt, joints))
        self.command(dt, paused=False)
        self.stats = OperatorStats()
        self.reset(self.ik.joints.home)
        elapsed = time.perf_counter() - t0
        if elapsed > 1.0:
            log.info("compiled the operator's kernels in %.1f s (cached for later runs)", elapsed)

    def reset(self, q_effector: np.ndarray) -> None:
        """Re-home: IK from these joints (arm then hand), mapping released, filters cleared."""
        q_effector = np.asarray(q_effector, dtype=np.float64)
        self.ik.reset(q_effector)
        self.retargeter.reset(q_effector[self.n_arm :])
        self.mapping.release()
        self.keypoints.reset()
        self.pose_filter.reset()
        self._q_hand = q_effector[self.n_arm :].copy()
        self._T_palm: np.ndarray | None = None  # filtered palm pose
        self._smoothed: tuple[np.ndarray, np.ndarray] | None = None  # joints, palm pose
        self._keypoints_palm: np.ndarray | None = None
        self._tracked: np.ndarray | None = None
        self._p_accepted: np.ndarray | None = None  # raw palm position last accepted
        self._t_accepted = -np.inf
        self._t_seen = -np.inf
        self._jump_streak: list[np.ndarray] = []
        self._t_source = self._t_receive = float("nan")
        self._resolution = "high"
        self._lost = False
        self._fresh = False
        self._T_target: np.ndarray | None = None
        self._last_reason = "waiting"

    def resync(self, q_effector: np.ndarray) -> None:
        """Continue from these joints (arm then hand): the guard held the effector there, so the
        next command steps from what the robot was given, not from the refused target. The
        mapping's anchor, the filters and the IK's posture are kept."""
        q_effector = np.asarray(q_effector, dtype=np.float64)
        self.ik.reset(q_effector, posture=self.ik.posture)
        self._q_hand = q_effector[self.n_arm :].copy()
        self.retargeter.reset(self._q_hand)
        self.ik.set_fingers(self._q_hand)

    def release(self) -> None:
        """Forget the anchor: the next tracked frame anchors again (resume)."""
        self.mapping.release()
        self.keypoints.reset()
        self.pose_filter.reset()
        self._p_accepted = None
        self._jump_streak = []

    # ----------------------------------------------------------------- per frame
    def observe(self, frame: HandFrame) -> bool:
        """Take one hand frame of this side; returns whether it was used."""
        self.stats.frames += 1
        if not frame.palm_frame_tracked:
            self.stats.untracked_frames += 1
            return False
        # The palm frame's origin is the wrist: the jump check needs no rotation.
        p_wrist = frame.joints[WRIST]
        if self._is_jump(p_wrist, frame.t_receive):
            return False
        self._p_accepted, self._t_accepted = p_wrist.copy(), frame.t_receive
        joints = self.keypoints(frame.joints)
        T_smooth = T_world_palm(joints, self.side)
        self._T_palm = self.pose_filter(T_smooth)
        # Keypoints in the palm frame: computed when a tick uses them (the last frame's).
        self._smoothed = joints, T_smooth
        self._keypoints_palm = None
        self._tracked = frame.tracked
        self._t_source, self._t_receive = frame.t_source, frame.t_receive
        if frame.resolution != self._resolution and self.mapping.anchored:
            # A new motion scale applies from here: re-anchor so the robot does not jump.
            self.mapping.release()
        self._resolution = frame.resolution
        self._fresh = True
        return True

    @property
    def _palm_keypoints(self) -> np.ndarray | None:
        """The smoothed keypoints of the last used frame in its (unfiltered) palm frame."""
        if self._keypoints_palm is None and self._smoothed is not None:
            joints, T_palm = self._smoothed
            self._keypoints_palm = np.empty(joints.shape)
            kernels.in_frame(joints, T_palm, self._keypoints_palm)
        return self._keypoints_palm

    def _is_jump(self, p: np.ndarray, t: float) -> bool:
        if self._p_accepted is None:
            self._t_seen = t
            return False
        # Speed from the last accepted position over the time since the previous frame of
        # this side (accepted or not): a gap in tracking allows a longer move, a stream of
        # frames at a glitched place does not.
        distance = math.dist(p.tolist(), self._p_accepted.tolist())
        elapsed = max(t - self._t_seen, 1e-3)
        self._t_seen = t
        if distance <= self.config.min_jump or distance / elapsed <= self.config.max_hand_speed:
            self._jump_streak = []
            return False
        self.stats.jumps_rejected += 1
        self._jump_streak.append(p)
        if len(self._jump_streak) == 1:
            log.warning(
                "%s hand jumped %.0f mm in %.0f ms: ignoring the frame, holding",
                self.side,
                distance * 1e3,
                elapsed * 1e3,
            )
        streak = np.array(self._jump_streak)
        if len(streak) >= self.config.reanchor_after and np.ptp(streak, axis=0).max() < 0.02:
            log.warning("%s hand stays where it jumped to: re-anchoring there", self.side)
            self.release()
            self.stats.reanchors += 1
            return False
        return True

    # ----------------------------------------------------------------- per tick
    def command(self, now: float, paused: bool) -> JointCommand:
        """Joint targets for this control tick (time ``now``, the receive clock)."""
        reason = ""
        if paused:
            reason = "paused"
        elif self._T_palm is None:
            reason = "waiting"
        elif now - self._t_accepted > self.config.tracking_timeout_s:
            reason = "tracking_lost"
        if reason == "tracking_lost" and not self._lost:
            self.stats.tracking_losses += 1
            log.warning(
                "%s hand lost (no tracked frame for %.2f s): holding",
                self.side,
                now - self._t_accepted,
            )
        self._lost = reason == "tracking_lost"

        if reason:
            q_arm = self.ik.q[: self.n_arm]
        else:
            if not self.mapping.anchored:
                self.mapping.anchor(self._T_palm, self.ik.T_world_hand())
                self.stats.reanchors += 1
            target = self.mapping.robot_target(self._T_palm, self._resolution)
            self._T_target = target
            if self._fresh:
                self._q_hand = self.retargeter.retarget(self._palm_keypoints, self._tracked)
                self.ik.set_fingers(self._q_hand)
                self._fresh = False
            q_arm = self.ik.step(target)
        positions = np.concatenate([q_arm, self._q_hand])
        positions = np.minimum(np.maximum(positions, self.ik.joints.lower), self.ik.joints.upper)
        self._last_reason = reason
        return JointCommand(
            effector=self.effector.name,
            positions=positions,
            t_source=self._t_source,
            t_receive=self._t_receive,
            hold=bool(reason),
            reason=reason,
        )

    def targets(self) -> EffectorTargets:
        """The current targets in the world frame (computed on demand, not per tick)."""
        T_world_hand = self.ik.T_world_hand()
        fingers = skeleton = None
        if self._palm_keypoints is not None:
            hand_map = self.retargeter.map
            fingers = self.retargeter.targets(self._palm_keypoints)
            fingers = fingers @ T_world_hand[:3, :3].T + T_world_hand[:3, 3]
            T_at = self._T_target if self._T_target is not None else T_world_hand
            p_hand = hand_map.origin_offset + self.retargeter.config.finger_scale * (
                self._palm_keypoints
            )
            skeleton = p_hand @ T_at[:3, :3].T + T_at[:3, 3]
        return EffectorTargets(
            effector=self.effector.name,
            side=self.side,
            T_world_target=None if self._T_target is None else self._T_target.copy(),
            T_world_hand=T_world_hand,
            finger_targets_world=fingers,
            keypoints_world=skeleton,
            hold=bool(self._last_reason),
            reason=self._last_reason,
        )


class Operator:
    """All effectors of an embodiment, plus the session state (pause, pinch, reset)."""

    def __init__(self, embodiment: Embodiment, dt: float, config: OperatorConfig | None = None):
        self.config = config or OperatorConfig()
        self.embodiment = embodiment
        self.effectors = {
            e.name: EffectorOperator(embodiment, e.name, dt, self.config)
            for e in embodiment.effectors
        }
        self._by_side = {s: [op for op in self.effectors.values() if op.side == s] for s in SIDES}
        self._ui_paused = False
        self._stream_paused = False
        self._pinch_paused = False
        self._last_pinch = {s: False for s in SIDES}
        self._pinch_start: float | None = None  # source time of the held pinch's press
        self._gestures: list[str] = []
        self._was_paused = False

    @property
    def paused(self) -> bool:
        return self._ui_paused or self._stream_paused or self._pinch_paused

    def set_paused(self, paused: bool) -> None:
        """Pause or resume from the UI (browser view, keyboard)."""
        self._ui_paused = bool(paused)

    def reset(self, q_measured: np.ndarray, joint_slices: dict[str, slice]) -> None:
        """Re-home from measured joints (full action vector; ``joint_slices`` per effector)."""
        for name, op in self.effectors.items():
            op.reset(np.asarray(q_measured)[joint_slices[name]])
        self._pinch_paused = False

    def resync(self, effector: str, q_effector: np.ndarray) -> None:
        """Continue ``effector`` from the joints the guard held it at (see
        :meth:`EffectorOperator.resync`)."""
        self.effectors[check_name("effector", effector, self.effectors)].resync(q_effector)

    def observe(self, frame: HandFrame) -> None:
        """Take one hand frame (any side)."""
        self._stream_paused = frame.paused
        if self.config.pinch_pauses and frame.side == "left":
            if frame.pinch and not self._last_pinch["left"]:
                self._pinch_paused = not self._pinch_paused
                self._pinch_start = frame.t_source
                log.info("left-hand pinch: %s", "pause" if self._pinch_paused else "resume")
            elif not frame.pinch:
                self._pinch_start = None
            elif (
                self._pinch_start is not None
                and frame.t_source - self._pinch_start >= self.config.long_pinch_s
            ):
                self._pinch_start = None  # one gesture per press
                self._pinch_paused = not self._pinch_paused  # undo the press's toggle
                self._gestures.append("record")
                log.info("left-hand long pinch: record gesture")
        both_before = all(self._last_pinch.values())
        self._last_pinch[frame.side] = frame.pinch
        if all(self._last_pinch.values()) and not both_before:
            self._gestures.append("estop")
            log.warning("both hands pinch: emergency-stop gesture")
        for op in self._by_side[frame.side]:
            op.observe(frame)

    def take_gestures(self, *kinds: str) -> list[str]:
        """Gestures recognised since they were last taken, of ``kinds`` (default: all):
        ``"record"`` (a long left pinch), ``"estop"`` (both hands pinch at once)."""
        for kind in kinds:
            check_name("gesture", kind, GESTURES)
        taken = [g for g in self._gestures if not kinds or g in kinds]
        self._gestures = [g for g in self._gestures if kinds and g not in kinds]
        return taken

    def targets(self) -> dict[str, EffectorTargets]:
        """Each effector's current targets in the world frame (views, logs)."""
        return {name: op.targets() for name, op in self.effectors.items()}

    def command(self, now: float) -> dict[str, JointCommand]:
        """One control tick: a command per effector."""
        paused = self.paused
        if self._was_paused and not paused:
            for op in self.effectors.values():
                op.release()  # re-anchor at resume: nothing jumps
        self._was_paused = paused
        return {name: op.command(now, paused) for name, op in self.effectors.items()}
