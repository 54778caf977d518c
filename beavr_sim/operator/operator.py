"""The operator: tracked hands in, joint targets per effector out (one implementation).

Side and embodiment are data: each effector of the embodiment is driven by the hand of its
side through an :class:`EffectorOperator`; nothing branches on left or right. Per frame
(:meth:`Operator.observe`) the keypoints are smoothed, the palm pose computed, checked for
tracking jumps and filtered; per control tick (:meth:`Operator.command`) the arm IK steps
towards the mapped target and the fingers are retargeted.

Filtering (:mod:`beavr_sim.operator.filters`) is set in seconds, so its delay does not depend
on the headset's frame rate: a One-Euro filter on each keypoint over its valid (tracked,
finite) samples only, 33 ms of lag at rest (``keypoint_min_cutoff_hz`` 4.8 Hz), less as the
joint moves faster (``keypoint_beta``), then an 11 ms first-order filter on the palm pose
(``pose_tau_position_s``, ``pose_tau_rotation_s``): about 44 ms on a slow palm in all, as the
former 5-frame average and 0.6 pose gain gave at 60 Hz (37 ms at 72 Hz, 89 ms at 30 Hz). A
joint untracked in the newest frame is untracked: the retargeting holds a finger whose tip,
distal or intermediate joint is, and resumes it when tracking returns.

Session control:

- pause: the source's pause stream (``HandFrame.paused``), a left-hand pinch (rising edge of
  ``HandFrame.pinch`` toggles), or the UI (:meth:`Operator.set_paused`). Paused effectors
  hold their last command; on resume every mapping is re-anchored so nothing jumps.
- gesture: a left-hand pinch held for ``long_pinch_s`` (source time) is the "record" gesture
  (start / stop a recorded episode): the pause its press toggled is undone and ``"record"``
  is queued for :meth:`Operator.take_gestures`. The robot holds during the gesture. Both
  hands pinching at once (rising edge) is the emergency-stop gesture ``"estop"`` (a mirrored
  session latches its e-stop on it). At most :data:`MAX_PENDING_GESTURES` wait to be taken
  (the oldest go first: a session that never takes the record gesture keeps a few).
- tracking loss: no usable frame (palm joints tracked) for ``tracking_timeout_s``: the effector
  holds where it is and a warning is logged; when tracking returns it continues from the same
  anchor (the hand may have moved meanwhile, within the jump limit).
- end of the source: once the runner says no frame will ever come again
  (:meth:`Operator.set_source_ended`: a trace played to its end), the same wait ends in a
  ``"source_ended"`` hold instead: the effector holds where it is, an INFO line says so, and
  neither a warning nor a tracking loss is counted (a finite recording ending is not a fault).
  A hand already lost before the end stays ``"tracking_lost"``.
- jumps: a palm that moved faster than ``max_hand_speed`` (and more than ``min_jump``) since
  the last accepted frame is a tracking glitch: the frame is ignored and counted. If the hand
  stays at the new place for ``reanchor_after`` frames, the mapping re-anchors there.
- resolution: switching between high (1.0) and low (0.6) motion scale re-anchors, so the new
  scale applies to motion from that instant and the robot does not jump.
- reset (:meth:`Operator.reset`): re-home: IK state from the measured joints, mappings released.

Nothing in the per-frame and per-tick path raises, and no tick holds silently. Every held
tick is counted by reason in ``OperatorStats.holds`` (:data:`HOLD_REASONS`); the reasons
beyond the session rules above:

- ``"error"``: an exception while taking a frame or computing a command (a bug, a solver
  failure). The command repeats the last command's positions, the IK and the retargeting
  continue from them; a frame that failed holds the effector until a frame is used again.
  Counted in ``OperatorStats.errors`` and logged (the 1st, 10th, 100th, then every 1000th).
  Malformed frames (wrong shapes, stamps not finite, an unknown side, a degenerate palm) are
  dropped and counted in ``malformed_frames``; joints flagged tracked but NaN/inf are used as
  untracked ones.
- ``"ik_infeasible"``: the arm IK's QP had no solution (e.g. already closer to the table than
  the collision margin): the arm holds its previous joints (``hold=True``) while the fingers
  still follow the hand in that tick (both runners' twins apply the command's positions).
- ``"retarget_infeasible"``: the LEAP retargeting's QP had no solution (a model-file hand's
  damped least-squares retargeting, :mod:`beavr_sim.operator.retarget_model`, always has
  one): the fingers hold their previous joints while the arm moves, so the command is not a
  hold (``hold=False``) but carries the reason; counted in ``holds`` like the others. A tick where both QPs failed
  has reason ``"ik_infeasible"`` and counts under both.

Infeasible ticks are logged at the same rate as errors, per reason.
"""

from __future__ import annotations

import logging
import math
import time
from collections import deque
from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from beavr_sim.naming import check_name
from beavr_sim.operator import kernels
from beavr_sim.operator.arm_ik import ArmIK, ArmIKConfig
from beavr_sim.operator.arm_mapping import RelativeMotionMapping, axis_map
from beavr_sim.operator.filters import KeypointFilter, PoseFilter
from beavr_sim.operator.obstacles import Obstacle
from beavr_sim.operator.palm import T_world_palm
from beavr_sim.operator.retarget import LeapRetargeter, RetargetConfig, human_template
from beavr_sim.operator.retarget_model import ModelHandRetargeter
from beavr_sim.robots import Embodiment
from beavr_sim.robots.hand_file import load_hand
from beavr_sim.wire.hand import (
    JOINT_INDEX,
    N_JOINTS,
    PALM_FRAME_JOINTS,
    PALMAR_NORMAL_SIGN,
    RESOLUTIONS,
    SIDES,
    HandFrame,
)
from beavr_sim.wire.records import JointCommand

log = logging.getLogger("beavr_sim.operator.operator")

WRIST = JOINT_INDEX["wrist"]
_PALM_IDS = np.array([JOINT_INDEX[n] for n in PALM_FRAME_JOINTS], dtype=np.int64)
_PALM_POSE_JOINTS = tuple(
    JOINT_INDEX[n] for n in ("wrist", "middle_proximal", "index_proximal", "little_proximal")
)

#: ``JointCommand.reason`` values ("": tracking). All but ``"retarget_infeasible"`` come with
#: ``hold=True`` (see the module docstring).
HOLD_REASONS = (
    "",
    "waiting",
    "paused",
    "tracking_lost",
    "source_ended",
    "error",
    "ik_infeasible",
    "retarget_infeasible",
)
GESTURES = ("record", "estop")
#: Gestures kept until taken; older ones are dropped.
MAX_PENDING_GESTURES = 16


def log_due(count: int) -> bool:
    """Whether the ``count``-th occurrence of something is logged: the 1st, 10th, 100th and
    every 1000th (a problem every tick stays visible without flooding the log)."""
    return count in (1, 10, 100) or (count > 0 and count % 1000 == 0)


@dataclass(frozen=True)
class OperatorConfig:
    """Filtering, safety and solver settings of the operator (see the module docstring).

    Filter constants are in seconds (or Hz), so the smoothing delay does not depend on the
    frame rate: keypoints lag ``1 / (2 pi keypoint_min_cutoff_hz)`` at rest (33 ms), less by
    ``keypoint_beta`` Hz of cutoff per m/s of joint speed (27 ms at 0.5 m/s), whose estimate
    is low-passed at ``keypoint_d_cutoff_hz``; the palm pose then lags ``pose_tau_*_s``
    (11 ms): about 44 ms on a slow palm in all, 33 ms on the finger keypoints. These are the
    former frame-count filters' delays at 60 Hz, the bundled traces' rate: those traces were
    recorded closed loop through the operator, and their replays depend on its delay.
    """

    keypoint_min_cutoff_hz: float = 4.8  # Hz: 33 ms of lag at rest
    keypoint_beta: float = 2.0  # Hz per m/s: 27 ms at 0.5 m/s
    keypoint_d_cutoff_hz: float = 1.0  # Hz
    pose_tau_position_s: float = 0.011  # s: 11 ms of lag
    pose_tau_rotation_s: float = 0.011  # s
    tracking_timeout_s: float = 0.25
    max_hand_speed: float = 3.0  # m/s
    min_jump: float = 0.05  # m
    reanchor_after: int = 10  # frames
    pinch_pauses: bool = True
    long_pinch_s: float = 1.0
    arm_ik: ArmIKConfig = field(default_factory=ArmIKConfig)
    retarget: RetargetConfig = field(default_factory=RetargetConfig)

    def __post_init__(self) -> None:
        for name in (
            "keypoint_min_cutoff_hz",
            "keypoint_d_cutoff_hz",
            "tracking_timeout_s",
            "max_hand_speed",
            "min_jump",
            "long_pinch_s",
        ):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) > 0):
                raise ValueError(f"{name} must be finite and positive, got {getattr(self, name)!r}")
        for name in ("keypoint_beta", "pose_tau_position_s", "pose_tau_rotation_s"):
            if not (math.isfinite(getattr(self, name)) and getattr(self, name) >= 0):
                raise ValueError(f"{name} must be finite and >= 0, got {getattr(self, name)!r}")
        if self.reanchor_after < 1:
            raise ValueError(f"reanchor_after must be >= 1, got {self.reanchor_after}")


@dataclass(frozen=True)
class EffectorTargets:
    """What one effector is steering towards, in the world frame (for views and logs).

    ``T_world_target``: the arm's hand-frame target (None until the mapping is anchored);
    ``T_world_hand``: the hand frame the IK reached; ``finger_targets_world``: the LEAP tip and
    distal targets (8 x 3; a model-file hand's fingertip targets, one per finger; placed on
    ``T_world_hand``); ``keypoints_world``: the operator's
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
    """Counters of one effector since its operator was built (or the stats replaced).

    ``malformed_frames``: frames dropped as unreadable (or used without their NaN joints);
    ``errors``: exceptions caught in the per-frame and per-tick path; ``holds``: ticks per
    reason of :data:`HOLD_REASONS` (``"error"``, ``"ik_infeasible"``, ...), the
    ``"retarget_infeasible"`` ticks (fingers held, arm moving) included.
    """

    frames: int = 0
    jumps_rejected: int = 0
    untracked_frames: int = 0
    malformed_frames: int = 0
    reanchors: int = 0
    tracking_losses: int = 0
    errors: int = 0
    holds: dict[str, int] = field(default_factory=dict)


class EffectorOperator:
    """Hand frames of one side -> joint targets of one effector."""

    def __init__(self, embodiment: Embodiment, effector: str, dt: float, config: OperatorConfig):
        self.config = config
        self.effector = embodiment.effector(effector)
        self.side = self.effector.side
        self.ik = ArmIK(embodiment, effector, dt, config.arm_ik)
        hand = embodiment.spec.effectors[
            [e.name for e in embodiment.effectors].index(self.effector.name)
        ].hand
        #: The LEAP hand's retargeter, or a model-file hand's (the robot file's ``[hands]``).
        self.retargeter: LeapRetargeter | ModelHandRetargeter = (
            LeapRetargeter(self.side, config.retarget)
            if hand.source is None
            else ModelHandRetargeter(load_hand(hand.source), self.side, dt=dt)
        )
        self.mapping = RelativeMotionMapping(axis_map(embodiment.name, self.side))
        self.keypoints = KeypointFilter(
            config.keypoint_min_cutoff_hz, config.keypoint_beta, config.keypoint_d_cutoff_hz
        )
        self.pose_filter = PoseFilter(config.pose_tau_position_s, config.pose_tau_rotation_s)
        self._sign = PALMAR_NORMAL_SIGN[self.side]
        self._T_raw = np.empty((4, 4))  # the raw palm pose (checked, not used)
        self.stats = OperatorStats()
        #: The latest exception caught (where, type, message), for logs and views.
        self.last_error = ""
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
        if self.stats.errors:  # observe and command catch everything: surface it here
            raise RuntimeError(f"{self.effector.name} operator warm-up failed: {self.last_error}")
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
        self._last_positions = self._clip(q_effector)  # what the last command sent
        self._frame_failed = False  # the newest frame raised: hold until one is used
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
        self._ended = False  # holding for the end of the source (logged once)
        #: The runner said the source will send no more frames (:meth:`Operator.set_source_ended`).
        self.source_ended = False
        self._fresh = False
        self._T_target: np.ndarray | None = None
        self._last_reason = "waiting"
        self._last_hold = True

    def _clip(self, q: np.ndarray) -> np.ndarray:
        return np.minimum(np.maximum(q, self.ik.joints.lower), self.ik.joints.upper)

    def resync(self, q_effector: np.ndarray) -> None:
        """Continue from these joints (arm then hand): the guard held the effector there, so the
        next command steps from what the robot was given, not from the refused target. The
        mapping's anchor, the filters and the IK's posture are kept."""
        q_effector = np.asarray(q_effector, dtype=np.float64)
        self.ik.reset(q_effector, posture=self.ik.posture)
        self._q_hand = q_effector[self.n_arm :].copy()
        self.retargeter.reset(self._q_hand)
        self.ik.set_fingers(self._q_hand)
        self._last_positions = self._clip(q_effector)

    def release(self) -> None:
        """Forget the anchor: the next tracked frame anchors again (resume)."""
        self.mapping.release()
        self.keypoints.reset()
        self.pose_filter.reset()
        self._p_accepted = None
        self._jump_streak = []

    # ----------------------------------------------------------------- errors
    def _fail(self, where: str, exc: BaseException) -> None:
        """Count and log (rate-limited) an exception caught in ``where``."""
        self.stats.errors += 1
        self.last_error = f"{where}: {type(exc).__name__}: {exc}"
        n = self.stats.errors
        if log_due(n):
            log.warning(
                "%s operator: %s (%d errors so far): holding",
                self.effector.name,
                self.last_error,
                n,
                exc_info=exc if n == 1 else None,
            )

    def _malformed(self, why: str) -> None:
        """Count and log (rate-limited) a malformed frame."""
        self.stats.malformed_frames += 1
        n = self.stats.malformed_frames
        if log_due(n):
            log.warning("%s operator: malformed frame (%s), %d so far", self.effector.name, why, n)

    def _count_hold(self, reason: str) -> None:
        """Count a held tick; log the holds that are not session rules (rate-limited)."""
        n = self.stats.holds[reason] = self.stats.holds.get(reason, 0) + 1
        if reason in ("ik_infeasible", "retarget_infeasible") and log_due(n):
            what = "arm IK" if reason == "ik_infeasible" else "finger retargeting"
            solver = self.ik if reason == "ik_infeasible" else self.retargeter
            log.warning(
                "%s operator: the %s QP is infeasible (DAQP exit flag %s): holding the %s "
                "(%d ticks so far)",
                self.effector.name,
                what,
                getattr(solver, "last_exitflag", "?"),
                "arm" if reason == "ik_infeasible" else "fingers",
                n,
            )

    # ----------------------------------------------------------------- per frame
    def observe(self, frame: HandFrame) -> bool:
        """Take one hand frame of this side; returns whether it was used.

        Never raises. A malformed frame is dropped (``stats.malformed_frames``); an exception
        while using one is an error (``stats.errors``, logged): the filters start over and
        the effector holds (``"error"``) until a frame is used."""
        self.stats.frames += 1
        try:
            return self._observe(frame)
        except Exception as exc:
            self._frame_failed = True
            self.keypoints.reset()
            self.pose_filter.reset()
            self._fail("observe", exc)
            return False

    def _read(
        self, frame: HandFrame
    ) -> tuple[np.ndarray, np.ndarray, bool, float, float, str] | None:
        """The frame's joints, valid joints (tracked and finite), whether the palm frame's are
        valid, stamps and resolution, or None (counted, logged) when it is malformed."""
        try:
            side, resolution = frame.side, frame.resolution
            joints = np.asarray(frame.joints, dtype=np.float64)
            tracked = np.asarray(frame.tracked, dtype=bool)
            t_source, t_receive = float(frame.t_source), float(frame.t_receive)
        except (AttributeError, TypeError, ValueError) as exc:
            self._malformed(f"unreadable: {type(exc).__name__}: {exc}")
            return None
        if side != self.side:
            self._malformed(f"a {side!r} hand for the {self.side} effector")
        elif joints.shape != (N_JOINTS, 3) or tracked.shape != (N_JOINTS,):
            self._malformed(f"joints of shape {joints.shape}, tracked flags {tracked.shape}")
        elif not (math.isfinite(t_source) and math.isfinite(t_receive)):
            self._malformed(f"stamps {t_source!r}, {t_receive!r}")
        elif resolution not in RESOLUTIONS:
            self._malformed(f"resolution {resolution!r}")
        else:
            valid = np.empty(N_JOINTS, dtype=bool)
            bad, palm_valid = kernels.valid_joints(joints, tracked, _PALM_IDS, valid)
            if bad:
                self._malformed("NaN/inf in joints flagged tracked: using them as untracked")
            return joints, valid, palm_valid, t_source, t_receive, resolution
        return None

    def _observe(self, frame: HandFrame) -> bool:
        read = self._read(frame)
        if read is None:
            return False
        joints, valid, palm_valid, t_source, t_receive, resolution = read
        if not palm_valid:
            self.stats.untracked_frames += 1
            return False
        if kernels.palm_pose(joints, *_PALM_POSE_JOINTS, self._sign, self._T_raw):
            self._malformed("degenerate palm (wrist, knuckles in line or coincident)")
            return False
        # The palm frame's origin is the wrist: the jump check needs no rotation.
        p_wrist = joints[WRIST]
        if self._is_jump(p_wrist, t_receive):
            return False
        # Filters on the source's clock: the time the hand was where the frame says.
        smoothed = self.keypoints(joints, valid, t_source)
        T_smooth = T_world_palm(smoothed, self.side)
        T_palm = self.pose_filter(T_smooth, t_source)
        # Nothing below raises: the frame is used as a whole or not at all.
        self._p_accepted, self._t_accepted = p_wrist.copy(), t_receive
        self._T_palm = T_palm
        # Keypoints in the palm frame: computed when a tick uses them (the last frame's).
        self._smoothed = smoothed, T_smooth
        self._keypoints_palm = None
        self._tracked = valid  # untracked in the newest frame: untracked
        self._t_source, self._t_receive = t_source, t_receive
        if resolution != self._resolution and self.mapping.anchored:
            # A new motion scale applies from here: re-anchor so the robot does not jump.
            self.mapping.release()
        self._resolution = resolution
        self._fresh = True
        self._frame_failed = False
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
    def command(self, now: float, paused: bool, dt: float | None = None) -> JointCommand:
        """Joint targets for this control tick (time ``now``, the receive clock); ``dt``: the
        time this command stands for (default the control period; the event-driven operator
        sends one per hand frame, and passes the time since the previous one).

        Never raises: an exception is an ``"error"`` hold that repeats the last command's
        positions (see the module docstring for every reason)."""
        try:
            return self._command(now, paused, dt)
        except Exception as exc:
            return self._hold_on_error(exc)

    def _command(self, now: float, paused: bool, dt: float | None = None) -> JointCommand:
        reason = ""
        if paused:
            reason = "paused"
        elif self._frame_failed:
            reason = "error"
        elif self._T_palm is None:
            reason = "waiting"
        elif now - self._t_accepted > self.config.tracking_timeout_s:
            reason = "source_ended" if self.source_ended and not self._lost else "tracking_lost"
        if reason == "tracking_lost" and not self._lost:
            self.stats.tracking_losses += 1
            log.warning(
                "%s hand lost (no tracked frame for %.2f s): holding",
                self.side,
                now - self._t_accepted,
            )
        elif reason == "source_ended" and not self._ended:
            log.info(
                "%s hand: the source ended (its last frame %.2f s ago): holding",
                self.side,
                now - self._t_accepted,
            )
        self._lost = reason == "tracking_lost"
        self._ended = reason == "source_ended"

        fingers_held = False
        if reason:
            q_arm = self.ik.q[: self.n_arm]
        else:
            if not self.mapping.anchored:
                self.mapping.anchor(self._T_palm, self.ik.T_world_hand())
                self.stats.reanchors += 1
            target = self.mapping.robot_target(self._T_palm, self._resolution)
            self._T_target = target
            if self._fresh:
                self._fresh = False  # a frame that fails here is not retried every tick
                if isinstance(self.retargeter, ModelHandRetargeter):  # caps speed over dt
                    q_hand = self.retargeter.retarget(self._palm_keypoints, self._tracked, dt)
                else:
                    q_hand = self.retargeter.retarget(self._palm_keypoints, self._tracked)
                fingers_held = self.retargeter.infeasible
                self._q_hand = q_hand
                self.ik.set_fingers(q_hand)
            q_arm = self.ik.step(target, dt)
            if self.ik.infeasible:
                reason = "ik_infeasible"  # the arm did not move: its previous joints
        positions = self._clip(np.concatenate([q_arm, self._q_hand]))
        if not np.isfinite(positions).all():
            raise FloatingPointError(f"non-finite joint targets {positions}")
        if reason:
            self._count_hold(reason)
        if fingers_held:
            self._count_hold("retarget_infeasible")
        self._last_positions = positions
        self._last_hold = bool(reason)
        self._last_reason = reason or ("retarget_infeasible" if fingers_held else "")
        return JointCommand(
            effector=self.effector.name,
            positions=positions.copy(),
            t_source=self._t_source,
            t_receive=self._t_receive,
            hold=self._last_hold,
            reason=self._last_reason,
        )

    def _hold_on_error(self, exc: BaseException) -> JointCommand:
        """The ``"error"`` hold: the last command again; IK and retargeting continue from it."""
        self._fail("command", exc)
        self._count_hold("error")
        positions = self._last_positions
        try:
            self.ik.reset(positions, posture=self.ik.posture)
            self._q_hand = positions[self.n_arm :].copy()
            self.retargeter.reset(self._q_hand)
            self.ik.set_fingers(self._q_hand)
        except Exception as again:  # the solvers' state is beyond repair: say so, hold anyway
            self.last_error += f"; resuming from the last command failed: {again!r}"
        self._last_hold, self._last_reason = True, "error"
        return JointCommand(
            effector=self.effector.name,
            positions=positions.copy(),
            t_source=self._t_source,
            t_receive=self._t_receive,
            hold=True,
            reason="error",
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
            p_hand = hand_map.skeleton(self._palm_keypoints)
            skeleton = p_hand @ T_at[:3, :3].T + T_at[:3, 3]
        return EffectorTargets(
            effector=self.effector.name,
            side=self.side,
            T_world_target=None if self._T_target is None else self._T_target.copy(),
            T_world_hand=T_world_hand,
            finger_targets_world=fingers,
            keypoints_world=skeleton,
            hold=self._last_hold,
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
        self._gestures: deque[str] = deque(maxlen=MAX_PENDING_GESTURES)
        self._was_paused = False
        #: Frames no effector could take (no side, or a side this embodiment does not know),
        #: and exceptions caught in the session rules (pause, pinch); the effectors count
        #: their own in their stats.
        self.malformed_frames = 0
        self.errors = 0

    @property
    def paused(self) -> bool:
        return self._ui_paused or self._stream_paused or self._pinch_paused

    def set_paused(self, paused: bool) -> None:
        """Pause or resume from the UI (browser view, keyboard)."""
        self._ui_paused = bool(paused)

    def set_source_ended(self, ended: bool) -> None:
        """Whether the source will send no more frames (a trace played to its end; False
        again when it is replayed). Runners say it before each command: an effector waiting
        for frames then holds as ``"source_ended"``, not ``"tracking_lost"``."""
        for op in self.effectors.values():
            op.source_ended = bool(ended)

    def reset(self, q_measured: np.ndarray, joint_slices: dict[str, slice]) -> None:
        """Re-home from measured joints (full action vector; ``joint_slices`` per effector)."""
        for name, op in self.effectors.items():
            op.reset(np.asarray(q_measured)[joint_slices[name]])
        self._pinch_paused = False

    def set_obstacles(self, obstacles: Sequence[Obstacle]) -> None:
        """The task's fixtures (after each env reset: :func:`fixture_obstacles`) for every
        effector's IK: hands and forearms keep off them as off the table."""
        obstacles = tuple(obstacles)
        for op in self.effectors.values():
            op.ik.set_obstacles(obstacles)

    def resync(self, effector: str, q_effector: np.ndarray) -> None:
        """Continue ``effector`` from the joints the guard held it at (see
        :meth:`EffectorOperator.resync`)."""
        self.effectors[check_name("effector", effector, self.effectors)].resync(q_effector)

    def observe(self, frame: HandFrame) -> None:
        """Take one hand frame (any side). Never raises: a frame without a known side is
        counted (:attr:`malformed_frames`) and dropped; an exception in the session rules is
        counted (:attr:`errors`) and logged, and the effectors still take the frame."""
        try:
            side = frame.side
            effectors = self._by_side[side] if side in self._by_side else None
        except Exception:  # not a frame at all, or an unhashable side
            effectors = None
        if effectors is None:
            self.malformed_frames += 1
            if log_due(self.malformed_frames):
                log.warning(
                    "operator: dropped a frame without a known side (%s), %d so far",
                    type(frame).__name__,
                    self.malformed_frames,
                )
            return
        try:
            self._session(frame)
        except Exception as exc:
            self.errors += 1
            if log_due(self.errors):
                log.warning(
                    "operator: session rules failed on a %s frame: %r (%d errors so far)",
                    side,
                    exc,
                    self.errors,
                )
        for op in effectors:
            op.observe(frame)

    def _session(self, frame: HandFrame) -> None:
        """Pause stream, pinch pause, record and e-stop gestures."""
        self._stream_paused = bool(frame.paused)
        pinch = bool(frame.pinch)
        if self.config.pinch_pauses and frame.side == "left":
            if pinch and not self._last_pinch["left"]:
                self._pinch_paused = not self._pinch_paused
                self._pinch_start = frame.t_source
                log.info("left-hand pinch: %s", "pause" if self._pinch_paused else "resume")
            elif not pinch:
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
        self._last_pinch[frame.side] = pinch
        if all(self._last_pinch.values()) and not both_before:
            self._gestures.append("estop")
            log.warning("both hands pinch: emergency-stop gesture")

    def take_gestures(self, *kinds: str) -> list[str]:
        """Gestures recognised since they were last taken, of ``kinds`` (default: all):
        ``"record"`` (a long left pinch), ``"estop"`` (both hands pinch at once)."""
        for kind in kinds:
            check_name("gesture", kind, GESTURES)
        taken = [g for g in self._gestures if not kinds or g in kinds]
        self._gestures = deque(
            (g for g in self._gestures if kinds and g not in kinds), maxlen=MAX_PENDING_GESTURES
        )
        return taken

    def targets(self) -> dict[str, EffectorTargets]:
        """Each effector's current targets in the world frame (views, logs)."""
        return {name: op.targets() for name, op in self.effectors.items()}

    def command(
        self, now: float, side: str | None = None, dt: float | None = None
    ) -> dict[str, JointCommand]:
        """One control tick: a command per effector (of ``side`` only, when given: the
        event-driven operator commands a side's effectors when its hand frame arrives; ``dt``
        as in :meth:`EffectorOperator.command`). Never raises (see the module docstring for
        the holds that take an exception's place)."""
        paused = self.paused
        if self._was_paused and not paused:
            for op in self.effectors.values():
                try:
                    op.release()  # re-anchor at resume: nothing jumps
                except Exception as exc:
                    op._fail("release", exc)
        self._was_paused = paused
        return {
            name: op.command(now, paused, dt)
            for name, op in self.effectors.items()
            if side is None or op.side == side
        }
