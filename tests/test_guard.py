"""The safety guard: commands into the table, past a limit, too fast or non-finite are
refused (the effector holds); objects never block."""

from __future__ import annotations

import math

import gymnasium as gym
import mujoco
import numpy as np
import pytest
from hypothesis import HealthCheck, event, given, settings
from hypothesis import strategies as st

import beavr_sim  # noqa: F401  (registers the envs)
from beavr_sim.naming import UnknownNameError
from beavr_sim.twin.guard import CollisionGuard, GuardConfig, Workspace
from beavr_sim.twin.twin import TwinInterface
from beavr_sim.wire.records import JointCommand
from beavr_sim.workcell import TABLE_TOP_Z

BOX_HALF_Z = 0.04  # Tape's box: 14 x 14 x 8 cm


@pytest.fixture(scope="module")
def twin():
    env = gym.make("beavr_sim/PickupBox-v0")
    twin = TwinInterface(env)
    twin.reset(seed=0)
    yield twin
    env.close()


def _into_table(twin) -> np.ndarray:
    """A full action whose arm reaches down through the table (found by sweeping the
    shoulder and elbow pitch)."""
    guard, q0 = twin.guard, twin.action.copy()
    sl = twin.slices["right"]
    for j2 in np.linspace(0.0, 2.0, 21):
        for j4 in np.linspace(0.0, 3.0, 31):
            q = q0.copy()
            q[sl.start + 1], q[sl.start + 3] = j2, j4
            verdict = guard.check(q, twin.env.data.qpos)
            if any("table" in a or "table" in b for a, b, _ in verdict.contacts):
                return q
    raise AssertionError("no arm configuration through the table found")


def test_home_and_objects_do_not_block(twin):
    verdict = twin.guard.check(twin.action, twin.env.data.qpos)
    assert verdict.ok and verdict.contacts == ()
    # Every geom is the robot's, the static scene's, or an object's (never guarded).
    model = twin.env.model
    owners = {twin.guard._owner[g] for g in range(model.ngeom)}
    assert owners == {"right", "static", None}
    box = [g for g in range(model.ngeom) if twin.guard._owner[g] is None]
    assert box, "the task's box should be an unguarded object"


def test_command_through_the_table_is_refused_and_robot_holds(twin):
    q_bad = _into_table(twin)
    before = twin.reset(seed=0)
    qpos, sl = twin.env.data.qpos, twin.slices["right"]
    # The jump from home is too fast for one tick: alone, the guard refuses it by speed; as a
    # configuration, it is in the table.
    assert twin.guard.check(q_bad, qpos, before).reasons["right"].startswith("velocity")
    alone = twin.guard.check(q_bad, qpos)
    assert any("table" in a or "table" in b for a, b, _ in alone.contacts)
    assert alone.reasons["right"].startswith(("workspace", "contact"))
    # The twin steps towards it at the speed cap until the arm would enter the table, then
    # refuses and holds.
    cmd = JointCommand("right", q_bad[sl], t_source=0.0, t_receive=0.0)
    applied, ticks = twin.commands_applied, 0
    while ticks < 100:
        ticks += 1
        state = twin.apply({"right": cmd})
        if state.guard_blocked:
            break
    assert state.guard_blocked_effectors == ("right",)
    assert twin.last_refusal.reasons["right"].startswith(("workspace", "contact"))
    assert twin.commands_applied == applied + ticks - 1  # a refused command is not counted
    assert twin.guard_blocks["right"] >= 1 and twin.step_limited["right"] >= ticks
    held = state.action.copy()
    state = twin.apply({"right": cmd})
    assert state.guard_blocked
    np.testing.assert_array_equal(state.action, held)  # the refused target never applied
    # A safe command afterwards goes through again (stepping back the way it came).
    ok = JointCommand("right", before[sl], t_source=0.0, t_receive=0.0)
    assert not twin.apply({"right": ok}).guard_blocked
    twin.reset(seed=0)


def test_a_command_into_a_fixture_is_refused():
    """Tape's box is a fixture (a mocap body): a static obstacle like the table. The hand
    lowered onto it is refused by the contact rule naming the box, above the table."""
    env = gym.make("beavr_sim/Tape-v0")
    try:
        twin = TwinInterface(env)
        home = twin.reset(seed=0)
        model, data, guard = twin.env.model, twin.env.data, twin.guard
        box = twin.env.task.fixtures["box"]
        assert {guard._owner[g] for g in box.geom_ids} == {"static"}
        # The hand lowered from above the box's height (the shoulder pitching down), the box
        # moved (after the reset: the guard follows the fixtures) to under the fingertips
        # where they pass 5 cm above the table.
        up, down = home.copy(), home.copy()
        up[1] -= 0.4
        down[1] += 0.6
        rows = [up + (down - up) * k / 100 for k in range(101)]
        probe = mujoco.MjData(model)
        probe.qpos[:] = data.qpos
        tips = [model.site(f"right/{f}_tip").id for f in ("thumb", "index", "middle", "ring")]
        for q in rows:
            probe.qpos[twin.env.joints.qpos_adr] = q
            mujoco.mj_kinematics(model, probe)
            low = tips[int(np.argmin(probe.site_xpos[tips, 2]))]
            if probe.site_xpos[low, 2] < TABLE_TOP_Z + 0.05:
                break
        box.place(data, probe.site_xpos[low, :2])
        sl = twin.slices["right"]
        for q in rows:
            state = twin.apply({"right": JointCommand("right", q[sl], t_source=0, t_receive=0)})
            if state.guard_blocked:
                break
        assert state.guard_blocked_effectors == ("right",), "the hand went into the box"
        reason = twin.last_refusal.reasons["right"]
        assert reason.startswith("contact: right/") and reason.split(" ")[3] == "box/geom", reason
        assert any("box/geom" in (a, b) for a, b, _ in twin.last_refusal.contacts)
    finally:
        env.close()


def _descent_onto(twin, xy) -> list[np.ndarray] | None:
    """Full actions lowering the right hand onto ``xy`` (the base turned towards it, the
    elbow opened to its distance, the shoulder pitching down), from 8 cm above the box top on
    down; None if no elbow setting brings the lowest fingertip within 3 cm of ``xy`` where it
    passes 1 cm above the box top."""
    model, data, joints = twin.env.model, twin.env.data, twin.env.joints
    home = joints.home.astype(np.float64)
    probe = mujoco.MjData(model)
    probe.qpos[:] = data.qpos
    tips = [model.site(f"right/{f}_tip").id for f in ("thumb", "index", "middle", "ring")]
    base = model.body("right/link1").id

    def lowest_tip(q):
        probe.qpos[joints.qpos_adr] = q
        mujoco.mj_kinematics(model, probe)
        tip = probe.site_xpos[tips]
        return tip[int(np.argmin(tip[:, 2]))].copy(), probe.xpos[base].copy()

    tip, axis = lowest_tip(home)
    turn = math.atan2(*(np.asarray(xy) - axis[:2])[::-1]) - math.atan2(*(tip[:2] - axis[:2])[::-1])
    box_top = TABLE_TOP_Z + 2 * BOX_HALF_Z
    for elbow in np.linspace(0.0, 0.8, 33):
        up, down = home.copy(), home.copy()
        up[0] = down[0] = home[0] + turn
        up[3] = down[3] = home[3] + elbow
        up[1] -= 0.4
        down[1] += 0.6
        rows = [up + (down - up) * k / 200 for k in range(201)]
        heights = [lowest_tip(q) for q in rows]
        first = next(k for k, (low, _) in enumerate(heights) if low[2] < box_top + 0.08)
        for low, _ in heights:
            if low[2] < box_top + 0.01:
                if np.linalg.norm(low[:2] - xy) < 0.03:
                    return rows[first:]
                break
    return None


def test_the_guard_follows_the_fixtures_to_every_reset():
    """Tape's box moves at every reset: a hand lowered onto it at its pose of a later reset
    is refused for the box (contact naming it) before any accepted command reaches into it,
    though the guard checked commands with the box elsewhere before."""
    env = gym.make("beavr_sim/Tape-v0")
    try:
        twin = TwinInterface(env)
        data, sl = twin.env.data, twin.slices["right"]
        box = twin.env.task.fixtures["box"]
        home = twin.reset(seed=0)
        first = box.pos(data)[:2].copy()
        for _ in range(3):  # the guard checks commands with the box of the first reset
            twin.apply({"right": JointCommand("right", home[sl], t_source=0, t_receive=0)})
        for seed in range(1, 400):  # a later reset that puts the box under a descent
            twin.reset(seed=seed)
            xy = box.pos(data)[:2].copy()
            rows = _descent_onto(twin, xy) if np.linalg.norm(xy - first) > 0.15 else None
            if rows is not None:
                break
        assert rows is not None, "no reset put the box under a descent of the hand"
        # The hand turns towards the box (at the speed cap) and comes down onto it.
        accepted = []
        for q in [rows[0]] * 40 + rows:
            state = twin.apply({"right": JointCommand("right", q[sl], t_source=0, t_receive=0)})
            if state.guard_blocked:
                break
            accepted.append(state.action.copy())
        # No accepted command (the path the hardware travels) reaches into the box where it
        # stands now: checked by a fresh guard told its pose.
        fresh = CollisionGuard(twin.env.model, twin.env.embodiment, twin.env.joints)
        fresh.set_fixtures(data.mocap_pos, data.mocap_quat)
        into_box = [
            v.reason()
            for v in (fresh.check(q, data.qpos) for q in accepted)
            if any("box/geom" in (a, b) for a, b, _ in v.contacts)
        ]
        assert not into_box, f"{len(into_box)} accepted commands into the box: {into_box[:2]}"
        assert state.guard_blocked_effectors == ("right",), "the hand went into the box"
        reason = twin.last_refusal.reasons["right"]
        assert reason.startswith("contact: right/") and reason.split(" ")[3] == "box/geom", reason
    finally:
        env.close()


def test_tolerance_is_respected(twin):
    q_bad = _into_table(twin)
    depth = max(d for _, _, d in twin.guard.check(q_bad, twin.env.data.qpos).contacts)
    lenient = CollisionGuard(
        twin.env.model,
        twin.env.embodiment,
        twin.env.joints,
        GuardConfig(
            tolerance=depth + 0.01,
            finger_tolerance=depth + 0.01,
            workspace_tolerance=1.0,
            finger_workspace_tolerance=1.0,
        ),
    )
    assert lenient.check(q_bad, twin.env.data.qpos).ok
    with pytest.raises(ValueError, match="tolerance"):
        GuardConfig(tolerance=-1.0)
    with pytest.raises(ValueError, match="finger_tolerance"):
        GuardConfig(finger_tolerance=float("nan"))


def test_fingertips_pressing_on_the_table_are_allowed(twin):
    """A grasp near the table commands fingertips a few mm into it: not refused."""
    guard, model = twin.guard, twin.env.model
    fingers = [
        g for g in range(model.ngeom) if guard._tolerance[g] == guard.config.finger_tolerance
    ]
    arm = [g for g in range(model.ngeom) if guard._tolerance[g] == guard.config.tolerance]
    assert fingers and arm
    names = {guard._geom_names[g] for g in fingers}
    assert any("distal" in n for n in names) and not any("link" in n for n in names)


def test_arms_driven_into_each_other_are_refused():
    """Bimanual: the two arms swung towards each other collide; both commands are refused."""
    env = gym.make("beavr_sim/PickPlace-v0", embodiment="xarm7_leap_bimanual")
    try:
        twin = TwinInterface(env)
        twin.reset(seed=0)
        q0 = twin.action.copy()
        right, left = twin.slices["right"], twin.slices["left"]

        def arms_touch(v):
            return [c for c in v.contacts if {c[0][:4], c[1][:4]} == {"left", "righ"}]

        verdicts = []
        for yaw in np.linspace(0.0, 1.6, 17):
            q = q0.copy()
            q[right.start], q[left.start] = yaw, -yaw  # shoulders turn towards each other
            q[right.start + 1] = q[left.start + 1] = 0.0
            q[right.start + 3] = q[left.start + 3] = 1.0
            verdicts.append((yaw, twin.guard.check(q, twin.env.data.qpos)))
        touching = [(yaw, v) for yaw, v in verdicts if arms_touch(v)]
        assert touching, "the arms never met"
        yaw, verdict = touching[0]
        assert verdict.blocked == ("left", "right")
        assert verdicts[0][1].ok  # facing forward they are apart
        q = q0.copy()
        q[right.start], q[left.start] = yaw, -yaw
        q[right.start + 3] = q[left.start + 3] = 1.0
        q[right.start + 1] = q[left.start + 1] = 0.0
        commands = {
            name: JointCommand(name, q[sl], t_source=0.0, t_receive=0.0)
            for name, sl in twin.slices.items()
        }
        # Through the twin, the arms step towards it at the speed cap until they would meet.
        for _ in range(60):
            state = twin.apply(commands)
            if state.guard_blocked:
                break
        assert state.guard_blocked_effectors == ("left", "right")
        assert all(r.startswith("contact") for r in twin.last_refusal.reasons.values())
        assert arms_touch(twin.last_refusal)
        assert not np.array_equal(state.action, q)  # held short of the collision
    finally:
        env.close()


# --------------------------------------------------------------------------- the rules
def _stream(guard, rows, start, qpos):
    """Rows as successive commands from ``start``; returns the accepted flags and verdicts."""
    guard.reset()
    previous, out = start.copy(), []
    for q in rows:
        safe, verdict = guard.filter(q, previous, qpos)
        out.append(verdict)
        previous = safe
    return out


FINGERS = ("thumb_", "index_", "middle_", "ring_")
#: How far (mm) the guard lets finger geometry and the rest of the robot into the table (its
#: default workspace tolerances, written out: a looser default fails the tests that use them).
FINGER_DEPTH_MM, ARM_DEPTH_MM = 12.0, 5.0


def _lowest_points(env, q) -> dict[str, float]:
    """The lowest point (world z, m) of the right effector's moving collision geometry at
    ``q``: of its finger links (``"fingers"``) and of the rest (``"arm"``: links, palm). Exact
    for the primitives the model collides with, written out here (not the guard's code)."""
    model, data = env.model, mujoco.MjData(env.model)
    data.qpos[:] = env.data.qpos
    data.qpos[env.joints.qpos_adr] = q
    mujoco.mj_kinematics(model, data)
    low = {"fingers": np.inf, "arm": np.inf}
    for g in range(model.ngeom):
        body = model.body(model.geom_bodyid[g]).name
        moves = model.body_weldid[model.geom_bodyid[g]] != 0  # not the base on the table
        if not (body.startswith("right/") and moves) or not (
            model.geom_contype[g] or model.geom_conaffinity[g]
        ):
            continue
        size, kind = model.geom_size[g], model.geom_type[g]
        r = data.geom_xmat[g].reshape(3, 3)[2]  # world z of the geom's local axes
        if kind == mujoco.mjtGeom.mjGEOM_SPHERE:
            half = size[0]
        elif kind == mujoco.mjtGeom.mjGEOM_CAPSULE:
            half = abs(r[2]) * size[1] + size[0]
        elif kind == mujoco.mjtGeom.mjGEOM_CYLINDER:
            half = abs(r[2]) * size[1] + size[0] * math.sqrt(max(0.0, 1 - r[2] ** 2))
        elif kind == mujoco.mjtGeom.mjGEOM_BOX:
            half = float(np.abs(r) @ size)
        else:
            raise AssertionError(f"geom type {kind} of {body} not measured here")
        part = "fingers" if body.split("/")[1].startswith(FINGERS) else "arm"
        low[part] = min(low[part], float(data.geom_xpos[g, 2] - half))
    return low


def _depth_mm(env, q, part: str = "fingers") -> float:
    """How far (mm) the lowest point of ``part``'s collision geometry is below the table top."""
    return (TABLE_TOP_Z - _lowest_points(env, q)[part]) * 1e3


def test_descent_into_the_thin_table_is_stopped_above_it(twin):
    """The descent of issue 18: arm joint 1 at 0.5 rad, joints 2 and 4 from home towards 1.45
    and 1.2 rad, at a slow, legal speed. A contacts-only check accepts configurations with the
    fingers' geometry well over 12 mm into the 4 cm table top (a capsule past the box's middle
    reports a shallow penetration or none); the guard stops the hand on the table and holds:
    measured on the robot's collision geometry (every finger and arm geom), not a site."""
    env = twin.env
    home = env.joints.home.astype(np.float64)
    goal = home.copy()
    goal[0], goal[1], goal[3] = 0.5, 1.45, 1.2
    rows = [home + (goal - home) * k / 300 for k in range(1, 301)]
    contacts_only = CollisionGuard(
        env.model,
        env.embodiment,
        env.joints,
        GuardConfig(workspace_tolerance=10.0, finger_workspace_tolerance=10.0, max_path_samples=1),
    )
    fingers_mm, arm_mm = FINGER_DEPTH_MM, ARM_DEPTH_MM
    hole = [
        depth
        for q in rows
        if contacts_only.check(q, env.data.qpos).ok and (depth := _depth_mm(env, q)) > fingers_mm
    ]
    assert hole, "the contacts-only check no longer shows the thin-table hole"
    verdicts = _stream(twin.guard, rows, home, env.data.qpos)
    accepted = [q for q, v in zip(rows, verdicts, strict=True) if v.ok]
    refused = [v for v in verdicts if not v.ok]
    assert refused and accepted
    # Every accepted row keeps the fingers' geometry within 12 mm of the table top and the
    # rest of the robot within 5 mm (the workspace tolerances); once refused, the hand holds
    # there (every later row is refused).
    assert max(_depth_mm(env, q) for q in accepted) <= fingers_mm + 1e-6
    assert max(_depth_mm(env, q, "arm") for q in accepted) <= arm_mm + 1e-6
    first = next(i for i, v in enumerate(verdicts) if not v.ok)
    assert all(not v.ok for v in verdicts[first:])
    assert verdicts[first].reasons["right"].startswith(("workspace", "contact"))
    # The refusal came near the table, not far above it: the last accepted row has a finger
    # within 2 cm of the table top.
    assert _depth_mm(env, accepted[-1]) > -20.0


def test_each_rule_names_itself(twin):
    env, guard = twin.env, twin.guard
    home = env.joints.home.astype(np.float64)
    qpos = env.data.qpos
    sl = twin.slices["right"]
    q = home.copy()
    q[sl.start + 2] = np.nan
    verdict = guard.check(q, qpos)
    assert verdict.blocked == ("right",) and verdict.reasons["right"].startswith("non-finite")
    assert "right/joint3" in verdict.reasons["right"]
    q = home.copy()
    q[sl.start + 3] = env.joints.upper[sl.start + 3] + 0.01
    assert guard.check(q, qpos).reasons["right"].startswith("joint limit: right/joint4")
    # Speed: a step of 0.2 rad in one 1/30 s tick is 6 rad/s on an arm joint (cap pi).
    guard.reset()
    q = home.copy()
    q[sl.start] += 0.2
    assert guard.check(q, qpos, previous=home).reasons["right"].startswith("velocity: right/joint1")
    q[sl.start] = home[sl.start] + 0.09  # 2.7 rad/s: under the cap
    assert guard.check(q, qpos, previous=home).ok
    # Acceleration: full speed one way, then the other, in consecutive ticks.
    guard.reset()
    step = home.copy()
    step[sl.start] += 0.09
    safe, verdict = guard.filter(step, home, qpos)
    assert verdict.ok
    verdict = guard.check(home, qpos, previous=safe)  # -2.7 rad/s: 162 rad/s^2
    assert verdict.reasons["right"].startswith("acceleration: right/joint1")
    guard.reset()


def test_workspace_box_is_checked_along_the_path(twin):
    """Both ends inside the box, the swing between them leaves it: refused, naming the path."""
    env = twin.env
    sl = twin.slices["right"]
    home = env.joints.home.astype(np.float64)
    left, right = home.copy(), home.copy()
    left[sl.start], right[sl.start] = 1.2, -1.2  # the hand swings through straight ahead
    box = Workspace(lower=(-0.6, -0.8, 0.7), upper=(0.3, 0.8, 2.0))
    guard = CollisionGuard(
        env.model, env.embodiment, env.joints, GuardConfig(workspaces={"right": box})
    )
    qpos = env.data.qpos
    assert guard.check(left, qpos).ok and guard.check(right, qpos).ok
    straight = home.copy()
    straight[sl.start] = 0.0
    assert not guard.check(straight, qpos).ok
    verdict = guard.check(right, qpos, previous=left)  # no dt: no speed rule, path only
    assert verdict.blocked == ("right",)
    assert "% of the path" in verdict.reasons["right"] and "workspace" in verdict.reasons["right"]
    with pytest.raises(UnknownNameError, match="Valid"):
        CollisionGuard(env.model, env.embodiment, env.joints, GuardConfig(workspaces={"up": box}))
    with pytest.raises(ValueError, match="lower < upper"):
        Workspace(lower=(0, 0, 1), upper=(1, 1, 0))


#: The caps the guard enforces (GuardConfig's defaults, from the xArm7's and the LEAP hand's
#: own limits), written out so that a looser rule or default fails here.
ARM_MAX_VELOCITY, HAND_MAX_VELOCITY = math.pi, 8.0
ARM_MAX_ACCELERATION, HAND_MAX_ACCELERATION = 150.0, 250.0
#: Kinds of command in a generated stream: mostly small legal steps near the current pose,
#: some unsafe ones mixed in (what each must be refused for).
KINDS = ["small"] * 8 + ["fast", "jerk", "limit", "limit", "nan"]
EXPECTED_RULE = {"fast": "velocity", "jerk": "acceleration", "limit": "joint limit",
                 "nan": "non-finite"}  # fmt: skip


@st.composite
def command_streams(draw):
    """(kind, joint, per-joint fractions in [-1, 1], how far past the cap, towards the
    upper limit) per command."""
    n = draw(st.integers(1, 10))
    return [
        (
            draw(st.sampled_from(KINDS)),
            draw(st.integers(0, 22)),
            np.array(draw(st.lists(st.floats(-1.0, 1.0), min_size=23, max_size=23))),
            draw(st.floats(1.3, 4.0)),
            draw(st.booleans()),
        )
        for _ in range(n)
    ]


@settings(
    max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture]
)
@given(stream=command_streams())
def test_every_accepted_command_keeps_every_rule(twin, stream):
    """Generated command streams near a valid pose: small steps (at most half the speed cap,
    inside the joint range) are accepted unless the geometry refuses them; a step past the
    speed cap, a reversal at full speed, a target just past a limit (at a legal speed) and a
    NaN are refused by their rule. Whatever is accepted is finite, within the limits, within the speed and acceleration
    caps (written out above) of the last accepted command, and checks clean as a
    configuration; whatever is refused leaves the effector where it was."""
    env, guard = twin.env, twin.guard
    qpos, dt = env.data.qpos, guard.dt
    lower, upper = env.joints.lower, env.joints.upper
    hand = guard.hand_joints
    vmax = np.where(hand, HAND_MAX_VELOCITY, ARM_MAX_VELOCITY)
    amax = np.where(hand, HAND_MAX_ACCELERATION, ARM_MAX_ACCELERATION)
    guard.reset()
    state = {"previous": env.joints.home.astype(np.float64), "velocity": np.zeros(23)}

    def send(q: np.ndarray, kind: str) -> bool:
        previous, velocity = state["previous"], state["velocity"]
        safe, verdict = guard.filter(q, previous, qpos)
        event(f"{kind}: {'accepted' if verdict.ok else 'refused'}")
        if verdict.ok:
            step = (safe - previous) / dt
            np.testing.assert_array_equal(safe, q)
            assert np.isfinite(safe).all()
            assert (safe >= lower).all() and (safe <= upper).all()
            assert (np.abs(step) <= vmax * (1 + 1e-9)).all(), "accepted faster than the cap"
            assert (np.abs(step - velocity) <= amax * dt * (1 + 1e-9)).all(), "accepted a jerk"
            assert guard.check(safe, qpos).ok
            state["velocity"] = step
        else:
            np.testing.assert_array_equal(safe, previous)
            rule = verdict.reasons["right"].split(":")[0]
            if kind in ("small", "full speed"):
                assert rule in ("workspace", "contact"), verdict.reason()
            else:
                assert rule == EXPECTED_RULE[kind], verdict.reason()
            state["velocity"] = np.zeros(23)
        if kind in EXPECTED_RULE:
            assert not verdict.ok, f"{kind} command accepted"
        state["previous"] = safe
        return verdict.ok

    for kind, joint, fraction, excess, up in stream:
        previous = state["previous"]
        q = np.clip(previous + 0.5 * vmax * dt * fraction, lower, upper)
        away = 1.0 if upper[joint] - previous[joint] > previous[joint] - lower[joint] else -1.0
        if kind == "fast":  # one joint past its cap (away from its nearer limit, in range)
            room = abs((upper if away > 0 else lower)[joint] - previous[joint])
            if room < 1.3 * vmax[joint] * dt:
                continue
            q[joint] = previous[joint] + away * min(excess * vmax[joint] * dt, room)
        elif kind == "jerk":  # one arm joint at 0.9 x its cap, then reversing: 1.8 x in a tick
            joint %= 7
            q = previous.copy()
            q[joint] += away * 0.9 * vmax[joint] * dt
            if not send(q, "full speed"):
                continue
            q = q.copy()
            q[joint] -= away * 0.9 * vmax[joint] * dt  # back: -0.9 x cap
        elif kind == "limit":  # a finger joint walked to a limit, then 5 mrad past it
            joint = 7 + joint % 16
            past = 1.0 if up else -1.0
            limit = upper[joint] if past > 0 else lower[joint]
            walked = True
            while walked and abs(limit - state["previous"][joint]) > 0.5 * vmax[joint] * dt:
                q = state["previous"].copy()
                q[joint] += np.sign(limit - q[joint]) * 0.5 * vmax[joint] * dt
                walked = send(q, "small")
            if not walked:
                continue
            q = state["previous"].copy()
            q[joint] = limit + past * 0.005
        elif kind == "nan":
            q[joint] = np.nan
        send(q, kind)
    guard.reset()


@pytest.mark.parametrize("joint", [0, 10])  # an arm joint, a finger joint
def test_the_velocity_rule_refuses_exactly_what_the_twins_step_limit_would_shorten(twin, joint):
    """One speed cap: near the cap (just under, at it, within the rounding tolerance, just
    over), the guard's velocity rule fires on a step exactly when the twin's rate limit would
    clamp it over one control period."""
    env, guard = twin.env, twin.guard
    home, qpos = env.joints.home.astype(np.float64), env.data.qpos
    i = twin.slices["right"].start + joint
    reach = twin.rate_limit.reach(twin.dt)[i]
    away = 1.0 if env.joints.upper[i] - home[i] > home[i] - env.joints.lower[i] else -1.0
    for factor in (0.5, 1 - 1e-6, 1.0, 1 + 1e-10, 1 + 1e-6, 1.2):
        q = home.copy()
        q[i] += away * factor * reach
        guard.reset()
        verdict = guard.check(q, qpos, previous=home)
        fast = verdict.reasons.get("right", "").startswith("velocity")
        assert fast == bool(twin.rate_limit.clamp(home, q, twin.dt).limited.any()), factor
        assert fast == (factor > 1 + 1e-9), (factor, verdict.reason())
