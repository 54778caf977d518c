"""Robot files (beavr_sim.robots.robot_file / from_file): parsing errors that name the key and
the valid choices, and a robot built from our own xArm7 MJCF through a robot file matching the
built-in xArm7 + LEAP where it should (limits, home, masses, the IK's pairs), and a URDF arm."""

from __future__ import annotations

import math
import textwrap

import mujoco
import numpy as np
import pytest

from beavr_sim.assets import mjcf_path
from beavr_sim.naming import UnknownNameError
from beavr_sim.robots import make_embodiment
from beavr_sim.robots.embodiment import embodiment_layout
from beavr_sim.robots.from_file import FLANGE_SITE
from beavr_sim.robots.robot_file import RobotFileError, read_robot_file

XARM_HOME_DEG = [0, -25, -1, 26, 0, 50, 0]


def xarm_toml(**replace: str) -> str:
    """A robot file naming our own xArm7 MJCF: the built-in xarm7_leap_right, from a file."""
    fields = {
        "model": f'"{mjcf_path("xarm7_leap/xarm7.xml")}"',
        "flange": '{ site = "ee" }',
        "joints": str([f"joint{i}" for i in range(1, 8)]).replace("'", '"'),
        "home_deg": str(XARM_HOME_DEG),
        "base_body": '"link_base"',
        "side": '"right"',
        "hand": '"leap"',
        "extra": "",
    }
    fields.update(replace)
    return textwrap.dedent(
        f"""\
        name = "xarm_from_file"
        [arms.xarm]
        model = {fields["model"]}
        base_body = {fields["base_body"]}
        flange = {fields["flange"]}
        joints = {fields["joints"]}
        home_deg = {fields["home_deg"]}
        max_velocity_deg_s = 180.0
        servo = {{ kp = 1000.0 }}
        {fields["extra"]}
        [[effectors]]
        name = "right"
        side = {fields["side"]}
        arm = "xarm"
        hand = {fields["hand"]}
        """
    )


@pytest.fixture(autouse=True)
def part_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))


@pytest.fixture
def write(tmp_path):
    def write(text: str, name: str = "robot.toml"):
        path = tmp_path / name
        path.write_text(text)
        return path

    return write


@pytest.mark.parametrize(
    ("replace", "message"),
    [
        ({"extra": "colour = 1"}, "arms.xarm: unknown key 'colour'; valid keys: model,"),
        (
            {"side": '"middle"'},
            "effectors[0].side: Unknown side 'middle'. Valid sides: left, right",
        ),
        ({"hand": '"shadow"'}, "effectors[0].hand: Unknown hand 'shadow'. Valid hands: leap"),
        ({"model": '"missing.xml"'}, "arms.xarm.model:"),
        ({"home_deg": "[0, 1]"}, "arms.xarm.home_deg: expected a list of 7 numbers"),
        ({"flange": '{ body = "link7", site = "ee" }'}, "give exactly one of 'body' or 'site'"),
        (
            {
                "extra": "[[effectors]]\nname = 'x'\nside = 'left'\narm = 'xarm'\n"
                "[[effectors]]\nname = 'y'\nside = 'left'\narm = 'xarm'"
            },
            "effectors: expected one or two [[effectors]], got 3",
        ),
    ],
)
def test_a_bad_robot_file_names_the_key_and_the_valid_choices(write, replace, message):
    with pytest.raises(RobotFileError, match=r"robot\.toml: ") as err:
        read_robot_file(write(xarm_toml(**replace)))
    assert message in str(err.value)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize(
    ("replace", "message"),
    [
        ({"joints": '["joint1", "joint2", "joint3", "joint4", "joint5", "joint6", "jointX"]'},
         "arms.xarm.joints: no joint 'jointX'; joints: joint1,"),
        ({"joints": '["joint1", "joint2", "joint3", "joint4", "joint5", "joint6"]',
          "home_deg": "[0, -25, -1, 26, 0, 50]"},
         "the model also has joints ['joint7'] under 'link_base': list them in joints, or name "
         "their bodies in remove_bodies"),
        ({"flange": '{ site = "tool" }'}, "arms.xarm.flange.site: no site 'tool'; sites: ee"),
        ({"extra": 'remove_bodies = ["gripper"]'}, "arms.xarm.remove_bodies: no body 'gripper'"),
        ({"home_deg": "[0, -25, -1, -26, 0, 50, 0]"},
         "arms.xarm.home_deg: joint4 = -26.0 deg is outside its limits [-11.0, 225.0] deg"),
    ],
)  # fmt: skip
def test_a_robot_file_whose_names_miss_the_model_says_which_names_it_has(write, replace, message):
    path = write(xarm_toml(**replace))
    with pytest.raises(RobotFileError) as err:
        make_embodiment(str(path))
    assert message in str(err.value)


def test_an_embodiment_that_is_neither_built_in_nor_a_file_lists_the_built_ins(tmp_path):
    with pytest.raises(UnknownNameError, match="xarm7_leap_right") as err:
        make_embodiment("franka")
    assert "robot file" in str(err.value)
    with pytest.raises(FileNotFoundError, match="built-in embodiments: xarm7_leap_right"):
        make_embodiment(str(tmp_path / "absent.toml"))


def test_the_xarm7_from_a_robot_file_is_the_built_in_one(write):
    path = write(xarm_toml())
    ours = make_embodiment(str(path))
    builtin = make_embodiment("xarm7_leap_right")
    assert ours.name == str(path) and embodiment_layout(ours.spec) == "xarm7_leap_right"
    arm = ours.spec.effectors[0].arm
    assert arm.upper_arm_links == ("link_base", "link1", "link2", "link3")  # derived
    assert arm.forearm_links == ("link5", "link6", "link7")
    assert arm.servo.max_velocity == pytest.approx(math.pi)
    models = []
    for embodiment in (ours, builtin):
        scene = mujoco.MjSpec()
        embodiment.attach_to(scene)
        model = scene.compile()
        models.append((model, embodiment.bind(model)))
    (m1, j1), (m2, j2) = models
    np.testing.assert_allclose(j1.lower, j2.lower)  # limits read from the model
    np.testing.assert_allclose(j1.upper, j2.upper)
    np.testing.assert_allclose(j1.home, j2.home)
    np.testing.assert_allclose(m1.body_mass, m2.body_mass)  # inertia frozen as compiled
    np.testing.assert_allclose(m1.body_inertia, m2.body_inertia, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(m1.body_gravcomp, m2.body_gravcomp)
    arm_act = j1.actuator_ids[:7]
    np.testing.assert_allclose(m1.actuator_gainprm[arm_act, 0], 1000.0)  # the file's servo kp
    np.testing.assert_allclose(m1.actuator_biasprm[arm_act, 2], -100.0)  # default kv = kp / 10
    # The servo's kv is the joints' damping: the model's own (the built-in's MJCF has some)
    # would cap the joints' speed at force_limit / damping under the torque cap.
    assert m2.dof_damping[j2.qvel_adr[:7]].all() and not m1.dof_damping[j1.qvel_adr[:7]].any()
    d1, d2 = mujoco.MjData(m1), mujoco.MjData(m2)
    for m, d, j in ((m1, d1, j1), (m2, d2, j2)):
        d.qpos[j.qpos_adr] = j.home
        mujoco.mj_kinematics(m, d)
    np.testing.assert_allclose(d1.site("right/" + FLANGE_SITE).xpos, d2.site("right/ee").xpos)
    np.testing.assert_allclose(d1.site("right/palm_centre").xpos, d2.site("right/palm_centre").xpos)


URDF = """\
<robot name="two_link">
  <link name="base"><inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01"
    ixy="0" ixz="0" iyz="0"/></inertial>
    <collision><geometry><cylinder radius="0.05" length="0.1"/></geometry></collision></link>
  <link name="upper"><inertial><mass value="1"/><inertia ixx="0.01" iyy="0.01" izz="0.01"
    ixy="0" ixz="0" iyz="0"/></inertial>
    <collision><origin xyz="0 0 0.15"/><geometry><box size="0.05 0.05 0.3"/></geometry>
    </collision></link>
  <link name="fore"><inertial><mass value="0.5"/><inertia ixx="0.01" iyy="0.01" izz="0.01"
    ixy="0" ixz="0" iyz="0"/></inertial>
    <collision><origin xyz="0 0 0.1"/><geometry><box size="0.04 0.04 0.2"/></geometry>
    </collision></link>
  <joint name="shoulder" type="revolute"><parent link="base"/><child link="upper"/>
    <origin xyz="0 0 0.1"/><axis xyz="0 1 0"/><limit lower="-1.5" upper="1.5" effort="30"
    velocity="2"/></joint>
  <joint name="elbow" type="revolute"><parent link="upper"/><child link="fore"/>
    <origin xyz="0 0 0.3"/><axis xyz="0 1 0"/><limit lower="-2" upper="0.5" effort="20"
    velocity="2"/></joint>
</robot>
"""


def test_a_urdf_arm_becomes_a_part_with_its_limits_and_servos(write):
    write(URDF, "two_link.urdf")
    path = write(
        xarm_toml(
            model='"two_link.urdf"',
            base_body='"base"',
            flange='{ body = "fore", pos = [0.0, 0.0, 0.2] }',
            joints='["shoulder", "elbow"]',
            home_deg="[10, -20]",
        )
    )
    embodiment = make_embodiment(str(path))
    arm = embodiment.spec.effectors[0].arm
    assert arm.upper_arm_links == ("base",) and arm.forearm_links == ("fore",)
    part = mujoco.MjModel.from_xml_path(arm.mjcf)
    np.testing.assert_allclose(part.jnt_range, [[-1.5, 1.5], [-2.0, 0.5]])
    assert part.nu == 2 and part.actuator_gainprm[0, 0] == 1000.0
    np.testing.assert_allclose(part.actuator_ctrlrange, part.jnt_range)
    # The URDF's effort limits cap the servos.
    np.testing.assert_allclose(part.actuator_forcerange, [[-30, 30], [-20, 20]])
    data = mujoco.MjData(part)
    mujoco.mj_kinematics(part, data)
    np.testing.assert_allclose(data.site(FLANGE_SITE).xpos, [0, 0, 0.6], atol=1e-9)


def test_a_joint_without_limits_asks_for_them_in_the_file(write):
    write(URDF.replace('type="revolute"><parent link="upper"/>',
                       'type="continuous"><parent link="upper"/>'), "two_link.urdf")  # fmt: skip
    toml = xarm_toml(
        model='"two_link.urdf"', base_body='"base"', flange='{ body = "fore" }', joints='["shoulder", "elbow"]',
        home_deg="[0, 0]",
    )  # fmt: skip
    with pytest.raises(RobotFileError, match=r"'elbow' has no limits in the model; give them as "
                       r"limits_deg.elbow = \[lower, upper\]"):  # fmt: skip
        make_embodiment(str(write(toml)))
    toml = toml.replace("servo = {", "limits_deg = { elbow = [-90, 90] }\nservo = {")
    arm = make_embodiment(str(write(toml))).spec.effectors[0].arm
    part = mujoco.MjModel.from_xml_path(arm.mjcf)
    np.testing.assert_allclose(part.jnt_range[1], np.radians([-90, 90]), atol=1e-5)  # MJCF text


def test_two_arms_from_one_file_are_the_bimanual_layout(write):
    text = xarm_toml(extra="home_deg_by_side = { left = [0, -25, 1, 26, 0, 50, 0] }")
    text += textwrap.dedent(
        """\
        base_pos = [0.0, -0.3, 0.0]
        [[effectors]]
        name = "left"
        side = "left"
        arm = "xarm"
        base_pos = [0.0, 0.3, 0.0]
        """
    )
    embodiment = make_embodiment(str(write(text)))
    builtin = make_embodiment("xarm7_leap_bimanual")
    assert embodiment_layout(embodiment.spec) == "xarm7_leap_bimanual"
    ours = {e.name: e for e in embodiment.spec.effectors}
    for e in builtin.spec.effectors:
        assert ours[e.name].base_pos == pytest.approx(e.base_pos)
        assert ours[e.name].arm.home(e.side) == pytest.approx(e.arm.home(e.side))
    scene = mujoco.MjSpec()
    embodiment.attach_to(scene)
    joints = embodiment.bind(scene.compile())
    assert joints.size == 2 * (7 + 16)


def test_the_check_names_what_is_missing_and_prints_the_derived_facts(write, capsys):
    from beavr_sim.robots.__main__ import main

    path = write(xarm_toml().replace('name = "right"', 'name = "arm"'))
    assert main(["check", str(path)]) == 1  # no built-in has an effector "arm": no task
    out = capsys.readouterr().out
    assert "check_env (no task): not run (no task)" in out
    assert "  - layout: no built-in embodiment has these effectors" in out
    assert "    joint4: [-11.0, 225.0]  home 26.0" in out  # limits from the model
    assert "finger scales (human -> hand): thumb " in out
    assert main(["check", str(path.with_name("absent.toml"))]) == 2
    assert "does not exist" in capsys.readouterr().err


def leap_table(name: str = "leapfile") -> str:
    """A ``[hands.NAME]`` table naming our own LEAP MJCF: the LEAP hand as a model-file hand,
    its joints in motor order (the model's is another). Its ``palm`` body is turned -90 deg
    about y in the hand frame: the root's x is the palm frame's z, its z the palm frame's -x."""
    return textwrap.dedent(
        f"""\
        [hands.{name}]
        model = "{mjcf_path("xarm7_leap/leap_right.xml")}"
        root = "palm"
        palm_axes = ["z", "y", "-x"]
        joints = {[f"leap_{i}" for i in range(16)]}
        [hands.{name}.fingers]
        thumb = "site:thumb_tip"
        index = "site:index_tip"
        middle = "site:middle_tip"
        ring = "site:ring_tip"
        """
    )


@pytest.mark.parametrize(
    ("hand", "table", "message"),
    [
        ('"leapfle"', leap_table(), "effectors[0].hand: Unknown hand 'leapfle'"),
        ('"leapfle"', leap_table(), "Valid hands: leap, leapfile"),
        ('"leap"', leap_table("leap"), "hands.leap: 'leap' is a built-in hand"),
        (
            '"leapfile"',
            leap_table() + 'colour = "red"\n',
            "hands.leapfile.fingers.colour: Unknown finger 'colour'. Valid fingers: index,",
        ),
    ],
)
def test_an_effector_names_a_hand_table_or_a_built_in(write, hand, table, message):
    text = xarm_toml(hand=hand).replace("[[effectors]]", table + "[[effectors]]")
    with pytest.raises(RobotFileError) as err:
        read_robot_file(write(text))
    assert message in str(err.value) and "\n" not in str(err.value)


def test_the_leap_hand_from_its_model_file_lands_where_the_built_in_one_does(write):
    # The palm body sits at (-0.0115, 0.0224, 0.112) in the LEAP hand frame; a hand part puts
    # the root at the hand frame's origin, so the mount moves it there.
    text = xarm_toml(hand='"leapfile"').replace("[[effectors]]", leap_table() + "[[effectors]]")
    text += "mount = { pos = [-0.0115, 0.0224, 0.112] }\n"
    ours, builtin = make_embodiment(str(write(text))), make_embodiment("xarm7_leap_right")
    hand = ours.spec.effectors[0].hand
    assert hand.joints == tuple(f"leap_{i}" for i in range(16)) and hand.source is not None
    assert hand.collision_bodies == ("palm", "thumb_distal", "index_distal", "middle_distal",
                                     "ring_distal")  # fmt: skip
    poses = []
    for embodiment in (ours, builtin):
        scene = mujoco.MjSpec()
        embodiment.attach_to(scene)
        model = scene.compile()
        joints = embodiment.bind(model)
        data = mujoco.MjData(model)
        data.qpos[joints.qpos_adr] = joints.home + np.r_[np.zeros(7), np.full(16, 0.3)]
        mujoco.mj_kinematics(model, data)
        poses.append((model, joints, data))
    (m1, j1, d1), (_, j2, d2) = poses
    np.testing.assert_allclose(j1.lower, j2.lower)  # the hand's limits from its model
    np.testing.assert_allclose(j1.upper, j2.upper)
    for finger in ("thumb", "index", "middle", "ring"):
        np.testing.assert_allclose(
            d1.site(f"right/tip_{finger}").xpos, d2.site(f"right/{finger}_tip").xpos, atol=1e-6
        )
    assert not m1.dof_damping[j1.qvel_adr[7:]].any()  # the servos' kv is the damping
    np.testing.assert_allclose(m1.actuator_gainprm[j1.actuator_ids[7:], 0], 2.0)
