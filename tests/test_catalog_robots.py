"""Every catalog robot loads, simulates and (slow) renders; named poses from SRDFs, read as untrusted input;
example-robot-data's SDF (Cassie) converted; the entries the catalog changes (pruned, locked, turned) checked
against independent constructions."""

from __future__ import annotations

import math
import xml.etree.ElementTree as ET
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from scipy.spatial.transform import Rotation

import multibody_sim as ms
from multibody_sim.catalog import catalog_urdf, example_robot_data_share
from multibody_sim.cli import main

CATALOG_NAMES = sorted(ms.CATALOG)
ROBOTS = example_robot_data_share() / "example-robot-data" / "robots"
# Default poses the files themselves put outside the URDF's limits (checked below against the files): neutral
# configurations of URDFs whose ranges exclude 0, a thumb at 0.001 rad past its 0 stop, and simple_humanoid's
# half_sitting, whose left leg limits mirror the right leg's.
OUTSIDE_LIMITS = {
    "allegro_left_hand": {"joint_12.0"},
    "allegro_right_hand": {"joint_12.0"},
    "alex_psyonic_hands": {"Left_thumb_q1", "Right_thumb_q1"},
    "laikago": {"FL_calf_joint", "FR_calf_joint", "RL_calf_joint", "RR_calf_joint"},
    "simple_humanoid": {"LLEG_HIP_P", "LLEG_KNEE", "LLEG_ANKLE_P", "RLEG_ANKLE_P"},
    "simple_humanoid_classical": {"LLEG_KNEE", "LLEG_ANKLE_P", "RLEG_ANKLE_P"},
}
STEPS = 20  # a short run: enough to see the robot move, cheap for the 73 entries (~0.2 s in all)


def stable_dt(robot: ms.Robot, q: np.ndarray) -> float:
    """1 ms, or less where the linearized dynamics at q are faster (damped light links): RK4 is stable for
    |dt·λ| < 2.78 on the negative real axis; 2 keeps a margin."""
    rho = ms.stiffness_ratio(robot, q, np.zeros(robot.nv)).spectral_radius
    return min(1e-3, 2.0 / rho) if rho > 0 else 1e-3


def urdf_limits(path: Path) -> dict[str, tuple[float, float]]:
    """Position limits of the URDF's revolute and prismatic joints, read with the standard library."""
    limits = {}
    for joint in ET.parse(path).getroot().findall("joint"):
        limit = joint.find("limit")
        if joint.get("type") in ("revolute", "prismatic") and limit is not None:
            lo, hi = float(limit.get("lower", 0)), float(limit.get("upper", 0))
            if lo < hi:
                limits[joint.get("name")] = (lo, hi)
    return limits


# ---- every robot ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", CATALOG_NAMES)
def test_every_catalog_robot_loads_and_simulates_from_its_default_pose(
    robot: Callable[..., ms.Robot], name: str
) -> None:
    loaded = robot(name)
    q0 = loaded.default_pose()
    dt = stable_dt(loaded, q0)
    trajectory = ms.simulate(loaded, q0, np.zeros(loaded.nv), duration=STEPS * dt, dt=dt)
    assert trajectory.status == "completed" and len(trajectory.t) == STEPS + 1
    assert np.all(np.isfinite(trajectory.q)) and np.all(np.isfinite(trajectory.v))
    # RK4 within its stability limit: the ledger closes (H - H(0) - work + dissipated) to round-off.
    assert np.abs(trajectory.energy_error).max() <= 1e-9 * loaded.energy_scale
    # Where the default pose lies outside the URDF's limits, it is the files' doing (see OUTSIDE_LIMITS).
    outside = {
        loaded.model.names[j]
        for j in range(1, loaded.model.njoints)
        if loaded.model.joints[j].nq == 1 and loaded.limit_excess(q0)[loaded.model.joints[j].idx_q] > 0
    }
    assert outside == OUTSIDE_LIMITS.get(name, set())
    limits = urdf_limits(catalog_urdf(ms.CATALOG[name])[0]) if outside else {}
    for joint in outside:
        lo, hi = limits[joint]
        value = q0[loaded.model.joints[loaded.model.getJointId(joint)].idx_q]
        assert not lo <= value <= hi


def test_models_lists_every_robot_with_its_sizes_base_and_poses(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["models"]) == 0
    lines = capsys.readouterr().out.splitlines()
    rows = {line.split()[0]: line.split() for line in lines[1 : 1 + len(ms.CATALOG)]}
    assert list(rows) == list(ms.CATALOG)
    assert rows["solo12"][1:5] == ["19", "18", "floating", "standing*,straight_standing"]
    assert rows["talos"][1:5] == ["39", "38", "floating", "half_sitting*"]
    assert rows["z1"][1:5] == ["7", "7", "fixed", "arm_up*,home"]  # the loaders' reference pose, first
    assert rows["ur5"][1:5] == ["6", "6", "fixed", "-"]
    assert rows["cassie"][1:5] == ["29", "28", "floating", "standing*"]


# ---- named poses ---------------------------------------------------------------------------------------
def srdf_states(path: Path) -> dict[str, dict[str, list[float]]]:
    """The SRDF's group_states read with the standard library: {state: {joint: values}}."""
    states = {}
    for state in ET.parse(path).getroot().findall("group_state"):
        states[state.get("name")] = {j.get("name"): [float(x) for x in j.get("value").split()] for j in state}
    return states


WITH_SRDF = [name for name in CATALOG_NAMES if ms.CATALOG[name].srdf]


@pytest.mark.parametrize("name", WITH_SRDF)
def test_poses_hold_the_srdf_values(robot: Callable[..., ms.Robot], name: str) -> None:
    """Every joint a state names and the model has takes the file's value (an angle may move by whole turns into
    the joint's range; a quaternion is normalized); every other coordinate is neutral."""
    loaded = robot(name)
    states = srdf_states(ROBOTS / ms.CATALOG[name].srdf)
    model = loaded.model
    assert loaded.poses == tuple(s for s in states if any(model.existJointName(j) for j in states[s]))
    for state in loaded.poses:
        q = loaded.pose(state)
        expected = pin.neutral(model)
        for joint, values in states[state].items():
            if not model.existJointName(joint):
                continue
            j = model.joints[model.getJointId(joint)]
            if j.nq == 1:
                turns = (q[j.idx_q] - values[0]) / (2 * math.pi)
                assert turns == pytest.approx(round(turns), abs=1e-12)
                expected[j.idx_q] = q[j.idx_q]
            elif j.nq == 2 and len(values) == 1:
                expected[j.idx_q : j.idx_q + 2] = math.cos(values[0]), math.sin(values[0])
            else:
                block = np.array(values)
                block[-4:] /= np.linalg.norm(block[-4:])  # free-flyer or spherical: unit quaternion last
                expected[j.idx_q : j.idx_q + j.nq] = block
        np.testing.assert_allclose(q, expected, rtol=0, atol=1e-15)


def test_default_pose_rules(robot: Callable[..., ms.Robot]) -> None:
    # The loaders' reference pose where the SRDF has it ...
    assert robot("z1").default_pose_name == "arm_up" and robot("z1").poses == ("home", "arm_up")
    assert robot("b1_z1").default_pose_name == "standing_with_arm_home"
    assert robot("talos").default_pose_name == "half_sitting"
    # ... where there is no SRDF, neutral(), which stays the zero configuration.
    ur5 = robot("ur5")
    assert ur5.default_pose_name is None and ur5.poses == ()
    np.testing.assert_array_equal(ur5.default_pose(), ur5.neutral())
    np.testing.assert_array_equal(robot("solo12").neutral(), pin.neutral(robot("solo12").model))
    # pose() hands out copies.
    solo = robot("solo12")
    q = solo.pose("standing")
    q[:] = 0.0
    assert solo.pose("standing")[2] == pytest.approx(0.235)
    np.testing.assert_array_equal(solo.default_pose(), solo.pose("standing"))


def test_an_unknown_pose_lists_the_valid_ones(robot: Callable[..., ms.Robot]) -> None:
    with pytest.raises(ms.UnknownNameError) as caught:
        robot("solo12").pose("standin")
    assert (
        str(caught.value)
        == "unknown pose 'standin' for solo12 (did you mean standing? valid: standing, straight_standing)"
    )
    with pytest.raises(ms.UnknownNameError) as caught:
        robot("ur5").pose("home")
    assert str(caught.value) == (
        "unknown pose 'home': ur5 has no named poses (they come from an SRDF: srdf=FILE in load_robot, --srdf FILE "
        "on the command line)"
    )


SRDF_HEADER = '<?xml version="1.0"?>\n'


def ur5_srdf(tmp_path: Path, body: str, name: str = "poses.srdf") -> Path:
    path = tmp_path / name
    path.write_text(f'{SRDF_HEADER}<robot name="ur5">{body}</robot>')
    return path


def test_a_urdf_path_takes_an_srdf_and_prefers_default_standing_half_sitting(tmp_path: Path) -> None:
    urdf = catalog_urdf(ms.CATALOG["ur5"])[0]
    srdf = ur5_srdf(
        tmp_path,
        '<group_state name="up" group="arm"><joint name="elbow_joint" value="0.5"/></group_state>'
        '<group_state name="standing" group="arm"><joint name="shoulder_pan_joint" value="0.25"/>'
        '<joint name="no_such_joint" value="3"/></group_state>',
    )
    arm = ms.load_robot(urdf, srdf=srdf)
    assert arm.poses == ("up", "standing") and arm.default_pose_name == "standing"
    np.testing.assert_array_equal(arm.pose("up"), [0, 0, 0.5, 0, 0, 0])
    np.testing.assert_array_equal(arm.default_pose(), [0.25, 0, 0, 0, 0, 0])  # unknown joints are skipped
    assert arm.source["load_robot"]["srdf"] == str(srdf)  # the metadata reloads it with its poses
    # A catalog robot takes another SRDF in place of its own.
    assert ms.load_robot("ur5", srdf=srdf).poses == ("up", "standing")


BAD_SRDF = {
    "doctype": (
        '<!DOCTYPE robot [<!ENTITY v "0.7">]><robot name="ur5"><group_state name="a" group="g">'
        '<joint name="elbow_joint" value="&v;"/></group_state></robot>',
        "DOCTYPE declarations are not allowed in a SRDF (entities could expand)",
    ),
    "malformed": ('<robot name="ur5"><group_state name="a">', "malformed XML ("),
    "not an srdf": ('<sdf version="1.6"/>', "not an SRDF: the root element is <sdf>, expected <robot>"),
    "no name": (
        '<robot name="ur5"><group_state group="g"><joint name="elbow_joint" value="1"/></group_state></robot>',
        "a <group_state> has no 'name' attribute",
    ),
    "twice": (
        '<robot name="ur5"><group_state name="a" group="g"><joint name="elbow_joint" value="1"/></group_state>'
        '<group_state name="a" group="g"><joint name="elbow_joint" value="2"/></group_state></robot>',
        "group_state 'a' is defined twice",
    ),
    "not a number": (
        '<robot name="ur5"><group_state name="a" group="g"><joint name="elbow_joint" value="abc"/></group_state>'
        "</robot>",
        "group_state 'a', joint 'elbow_joint': value 'abc' is not a list of numbers",
    ),
    "nan": (
        '<robot name="ur5"><group_state name="a" group="g"><joint name="elbow_joint" value="nan"/></group_state>'
        "</robot>",
        "group_state 'a', joint 'elbow_joint': value 'nan' must be finite numbers",
    ),
    "count": (
        '<robot name="ur5"><group_state name="a" group="g"><joint name="elbow_joint" value="1 2 3"/></group_state>'
        "</robot>",
        "group_state 'a', joint 'elbow_joint': has 3 value(s), the joint has 1 coordinate(s)",
    ),
    "no value": (
        '<robot name="ur5"><group_state name="a" group="g"><joint name="elbow_joint"/></group_state></robot>',
        "group_state 'a': a <joint> needs both 'name' and 'value' attributes",
    ),
    "another robot's": (
        '<robot name="x"><group_state name="a" group="g"><joint name="knee" value="1"/></group_state></robot>',
        "none of its group_state joints is a joint of the model (1 state(s)): is it this robot's SRDF?",
    ),
}


@pytest.mark.parametrize("case", BAD_SRDF)
def test_a_bad_srdf_is_refused_in_one_line(case: str, tmp_path: Path) -> None:
    text, message = BAD_SRDF[case]
    path = tmp_path / "bad.srdf"
    path.write_text(text)
    with pytest.raises(ms.ModelError) as caught:
        ms.load_robot("ur5", srdf=path)
    assert str(caught.value).startswith(f"{path}: {message}")
    assert "\n" not in str(caught.value)


def test_srdf_size_and_element_limits(tmp_path: Path) -> None:
    states = "".join(
        f'<group_state name="s{i}" group="g"><joint name="elbow_joint" value="{i}"/></group_state>'
        for i in range(60_000)
    )  # what took Pinocchio's own reader 8.5 s at 200,000 states
    many = ur5_srdf(tmp_path, states, "many.srdf")
    with pytest.raises(ms.ModelError, match="XML elements, more than the 100000 a SRDF may have"):
        ms.load_robot("ur5", srdf=many)
    big = tmp_path / "big.srdf"
    with big.open("wb") as f:
        f.truncate(ms.catalog.MAX_URDF_BYTES + 1)
    with pytest.raises(ms.ModelError, match="larger than the 33554432-byte limit for a SRDF"):
        ms.load_robot("ur5", srdf=big)
    with pytest.raises(ms.ModelError, match="cannot read SRDF"):
        ms.load_robot("ur5", srdf=tmp_path / "absent.srdf")


def test_a_floating_base_state_is_normalized_and_a_zero_quaternion_refused(tmp_path: Path) -> None:
    body = '<group_state name="up" group="g"><joint name="root_joint" value="0 0 0.3 0 0 0 2"/></group_state>'
    solo = ms.load_robot("solo12", srdf=ur5_srdf(tmp_path, body))
    np.testing.assert_array_equal(solo.pose("up")[:7], [0, 0, 0.3, 0, 0, 0, 1])
    zero = '<group_state name="z" group="g"><joint name="root_joint" value="0 0 0.3 0 0 0 0"/></group_state>'
    with pytest.raises(ms.ModelError, match="group_state 'z', joint 'root_joint': its quaternion"):
        ms.load_robot("solo12", srdf=ur5_srdf(tmp_path, zero, "zero.srdf"))


def test_pinocchios_own_srdf_reader_takes_bad_values_silently(tmp_path: Path) -> None:
    """Why srdf.py reads SRDFs itself: pin.loadReferenceConfigurations turns "abc" into 0 and goes on."""
    path = tmp_path / "bad.srdf"
    path.write_text(BAD_SRDF["not a number"][0])
    model = pin.buildModelFromUrdf(str(catalog_urdf(ms.CATALOG["ur5"])[0]))
    pin.loadReferenceConfigurations(model, str(path), False)
    (entry,) = list(model.referenceConfigurations)
    assert entry.key() == "a" and not entry.data().any()


# ---- poses on the command line, in scenes ---------------------------------------------------------------
def test_run_starts_from_the_default_pose_or_a_named_one(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    solo = ms.load_robot("solo12")
    for extra, pose in (([], "standing"), (["--q0", "straight_standing"], "straight_standing")):
        out = tmp_path / f"{pose}.npz"
        assert main(["run", "solo12", "--duration", "0.01", "--out", str(out), *extra]) == 0
        np.testing.assert_array_equal(ms.Trajectory.load(out).q[0], solo.pose(pose))
    capsys.readouterr()
    assert main(["run", "solo12", "--q0", "kneeling"]) == 2
    assert capsys.readouterr().err == (
        "multibody-sim: error: unknown pose 'kneeling' for solo12 (valid: standing, straight_standing)\n"
    )
    assert main(["run", "solo12", "--q0", "1", "x"]) == 2
    assert capsys.readouterr().err == (
        "multibody-sim: error: --q0: 'x' is not a number (give one pose name (standing, straight_standing) or 19 "
        "numbers)\n"
    )


def test_a_scene_without_initial_q_starts_from_the_default_pose() -> None:
    solo = ms.load_robot("solo12")
    scene = ms.make_scene(robot={"source": "solo12"})
    np.testing.assert_array_equal(scene.q0, solo.default_pose())
    assert scene.poses == solo.poses
    # With legs locked, the poses live on the reduced model: the arms keep their half_sitting angles.
    talos = ms.load_robot("talos")
    legs = [name for name in talos.joint_names if name.startswith("leg_")]
    upper = ms.make_scene(robot={"source": "talos", "base": "fixed"}, lock=dict.fromkeys(legs, 0.0))
    fixed = ms.load_robot("talos", floating_base=False)
    for name in ("arm_left_2_joint", "arm_right_4_joint", "torso_2_joint"):
        i = upper.model.joints[upper.model.getJointId(name)].idx_q
        j = fixed.model.joints[fixed.model.getJointId(name)].idx_q
        assert upper.q0[i] == fixed.default_pose()[j] != 0.0
    # [initial] q by joint starts from the default pose too.
    partial = ms.make_scene(robot={"source": "solo12"}, initial={"q": {"FL_KFE": -1.0}})
    expected = solo.default_pose()
    expected[solo.model.joints[solo.model.getJointId("FL_KFE")].idx_q] = -1.0
    np.testing.assert_array_equal(partial.q0, expected)


# ---- entries the catalog changes -------------------------------------------------------------------------
def test_talos_legs_is_the_loaders_legs_only_model(robot: Callable[..., ms.Robot]) -> None:
    """example-robot-data's loader built talos_legs by copying joints 1..13 of talos_reduced (the free-flyer and
    the twelve leg joints) with their bodies into a new model; the same construction here must agree."""
    full = pin.buildModelFromUrdf(str(catalog_urdf(ms.CATALOG["talos"])[0]), pin.JointModelFreeFlyer())
    legs = pin.Model()
    for j in range(1, 14):
        jid = legs.addJoint(full.parents[j], full.joints[j], full.jointPlacements[j], full.names[j])
        legs.appendBodyToJoint(jid, full.inertias[j], pin.SE3.Identity())
    ours = robot("talos_legs")
    assert [ours.model.names[j] for j in range(ours.model.njoints)] == list(legs.names)
    data = legs.createData()
    rng = np.random.default_rng(0)
    for _ in range(3):
        q = ours.random_configuration(rng)
        M = pin.crba(legs, data, q)
        np.testing.assert_allclose(ours.mass_matrix(q), np.triu(M) + np.triu(M, 1).T, rtol=1e-12, atol=1e-12)
        tau = np.r_[np.zeros(6), rng.normal(size=12)]  # at rest, so that the URDF's damping plays no part
        expected = pin.aba(legs, data, q, np.zeros(18), tau)
        np.testing.assert_allclose(ours.forward_dynamics(q, np.zeros(18), tau), expected, rtol=1e-10, atol=1e-10)
    assert ours.total_mass == pytest.approx(sum(legs.inertias[j].mass for j in range(1, 14)))
    # The torso, arms and head are gone, mass and all: talos' mass minus their links' (read from the URDF).
    urdf = ET.parse(catalog_urdf(ms.CATALOG["talos"])[0]).getroot()
    joints = {j.find("child").get("link"): j.find("parent").get("link") for j in urdf.findall("joint")}

    def above_torso(link: str) -> bool:
        while link in joints:
            if link == "torso_1_link":
                return True
            link = joints[link]
        return False

    upper = sum(
        float(m.get("value"))
        for link in urdf.findall("link")
        if above_torso(link.get("name"))
        for m in link.findall("inertial/mass")
    )
    assert upper > 30.0
    assert ours.total_mass == pytest.approx(robot("talos").total_mass - upper, rel=1e-12)


def test_romeo_and_icub_lock_the_joints_they_must(robot: Callable[..., ms.Robot]) -> None:
    """romeo's finger links have no mass at all and icub's head is a point mass on the neck-yaw axis: with those
    joints free, M is singular (checked here with Pinocchio on the unchanged URDFs)."""
    for name, locked in (("romeo", 24), ("icub", 1)):
        path = catalog_urdf(ms.CATALOG[name])[0]
        model = pin.buildModelFromUrdf(str(path), pin.JointModelFreeFlyer())
        q = pin.neutral(model) if name == "romeo" else _icub_pose(model)
        M = pin.crba(model, model.createData(), q)
        eigenvalues = np.linalg.eigvalsh(np.triu(M) + np.triu(M, 1).T)
        assert eigenvalues[0] < 1e-12 * eigenvalues[-1]
        assert len(ms.CATALOG[name].locked) == locked
        assert robot(name).nv == model.nv - locked
        assert not set(ms.CATALOG[name].locked) & set(robot(name).joint_names)


def _icub_pose(model: pin.Model) -> np.ndarray:
    """icub's half_sitting from its SRDF, on the unchanged model (where the head's singularity shows)."""
    states = srdf_states(ROBOTS / "icub_description/srdf/icub.srdf")
    q = pin.neutral(model)
    for joint, values in states["half_sitting"].items():
        if model.existJointName(joint) and model.joints[model.getJointId(joint)].nq == len(values) == 1:
            q[model.joints[model.getJointId(joint)].idx_q] = values[0]
    return q


def test_human_stands_upright(robot: Callable[..., ms.Robot]) -> None:
    """human.urdf is drawn with y up; the catalog turns its base so that z is up, as the loaders did."""
    human = robot("human")
    data = human.model.createData()
    pin.framesForwardKinematics(human.model, data, human.neutral())
    height = {name: data.oMf[human.model.getFrameId(name)].translation[2] for name in ("middle_head", "left_foot")}
    assert height["middle_head"] - height["left_foot"] > 1.4  # a 1.80 m body, head above feet
    # Gravity pulls it down its own length: the base's linear acceleration is -g along world z.
    a = human.forward_dynamics(human.neutral(), np.zeros(human.nv), np.zeros(human.nv))
    rotation = data.oMi[1].rotation
    np.testing.assert_allclose(rotation @ a[:3], [0, 0, -9.81], atol=1e-9)


# ---- Cassie, converted from its SDF ----------------------------------------------------------------------
def sdf_pose(text: str | None) -> np.ndarray:
    """An SDF <pose> (x y z roll pitch yaw, fixed axes) as a 4x4 matrix, with scipy."""
    values = [float(v) for v in (text or "0 0 0 0 0 0").split()]
    matrix = np.eye(4)
    matrix[:3, :3] = Rotation.from_euler("xyz", values[3:]).as_matrix()
    matrix[:3, 3] = values[:3]
    return matrix


def test_cassie_matches_its_sdf(robot: Callable[..., ms.Robot]) -> None:
    """At the zero configuration the model's links sit where the SDF puts them (URDF puts a link's frame on its
    joint, so a joint's <pose> in its child's frame shows there); its joints turn about the SDF's axes; its mass
    is the SDF links' sum."""
    cassie = robot("cassie")
    model = cassie.model
    sdf = ET.parse(catalog_urdf(ms.CATALOG["cassie"])[0]).getroot().find("model")
    links = {link.get("name"): link for link in sdf.findall("link")}
    root = np.linalg.inv(sdf_pose(links["pelvis"].findtext("pose")))  # the free-flyer's frame is the pelvis'
    data = model.createData()
    q = cassie.neutral()
    pin.framesForwardKinematics(model, data, q)
    tree_joint = {j.findtext("child"): j for j in sdf.findall("joint") if j.get("type") != "ball"}
    for name, link in links.items():
        placement = data.oMf[model.getFrameId(name)].homogeneous
        joint_pose = sdf_pose(tree_joint[name].findtext("pose")) if name in tree_joint else np.eye(4)
        expected = root @ sdf_pose(link.findtext("pose")) @ joint_pose
        np.testing.assert_allclose(placement, expected, atol=1e-12, err_msg=name)
    assert cassie.total_mass == pytest.approx(sum(float(link.findtext("inertial/mass")) for link in links.values()))
    # The whole robot's rotational inertia about the pelvis origin (M's base block at q = 0), summed from the SDF's
    # inertials by the parallel-axis theorem: every inertial's placement and orientation enters.
    inertia = np.zeros((3, 3))
    for link in links.values():
        pose = root @ sdf_pose(link.findtext("pose")) @ sdf_pose(link.findtext("inertial/pose"))
        i = {
            key: float(link.findtext(f"inertial/inertia/{key}") or 0)
            for key in ("ixx", "iyy", "izz", "ixy", "ixz", "iyz")
        }
        local = np.array(
            [[i["ixx"], i["ixy"], i["ixz"]], [i["ixy"], i["iyy"], i["iyz"]], [i["ixz"], i["iyz"], i["izz"]]]
        )
        c, rotation, m = pose[:3, 3], pose[:3, :3], float(link.findtext("inertial/mass"))
        inertia += rotation @ local @ rotation.T + m * (c @ c * np.eye(3) - np.outer(c, c))
    np.testing.assert_allclose(cassie.mass_matrix(q)[3:6, 3:6], inertia, rtol=1e-12, atol=1e-12)
    pin.computeJointJacobians(model, data, q)
    for joint in sdf.findall("joint"):
        if joint.get("type") == "ball":  # the four loop closures: not in the tree
            assert not model.existJointName(joint.get("name"))
            continue
        child = links[joint.findtext("child")]
        frame = root @ sdf_pose(child.findtext("pose")) @ sdf_pose(joint.findtext("pose"))
        axis = frame[:3, :3] @ np.array([float(v) for v in joint.findtext("axis/xyz").split()])
        jid = model.getJointId(joint.get("name"))
        column = pin.getJointJacobian(model, data, jid, pin.LOCAL_WORLD_ALIGNED)[3:, model.joints[jid].idx_v]
        np.testing.assert_allclose(column, axis / np.linalg.norm(axis), atol=1e-12, err_msg=joint.get("name"))


def test_an_sdf_file_loads_like_the_urdf_it_stands_for(tmp_path: Path) -> None:
    sdf = tmp_path / "arm.sdf"
    sdf.write_text(
        """<?xml version="1.0"?><sdf version="1.6"><model name="arm">
        <link name="base"><inertial><mass>1</mass><inertia><ixx>0.1</ixx><iyy>0.1</iyy><izz>0.1</izz></inertia>
        </inertial></link>
        <link name="upper"><pose>0 0 0.5 0 0.3 0</pose><inertial><pose>0 0 -0.25 0 0 0</pose><mass>2</mass>
        <inertia><ixx>0.02</ixx><iyy>0.03</iyy><izz>0.01</izz></inertia></inertial></link>
        <joint name="shoulder" type="revolute"><parent>base</parent><child>upper</child><pose>0 0 0 0 0 0</pose>
        <axis><xyz>0 1 0</xyz><limit><lower>-2</lower><upper>2</upper><effort>10</effort><velocity>3</velocity></limit>
        <dynamics><damping>0.5</damping></dynamics></axis></joint></model></sdf>"""
    )
    urdf = tmp_path / "arm.urdf"
    urdf.write_text(
        """<?xml version="1.0"?><robot name="arm">
        <link name="base"><inertial><mass value="1"/><inertia ixx="0.1" ixy="0" ixz="0" iyy="0.1" iyz="0" izz="0.1"/>
        </inertial></link>
        <link name="upper"><inertial><origin xyz="0 0 -0.25"/><mass value="2"/>
        <inertia ixx="0.02" ixy="0" ixz="0" iyy="0.03" iyz="0" izz="0.01"/></inertial></link>
        <joint name="shoulder" type="revolute"><parent link="base"/><child link="upper"/>
        <origin xyz="0 0 0.5" rpy="0 0.3 0"/><axis xyz="0 1 0"/><limit lower="-2" upper="2" effort="10" velocity="3"/>
        <dynamics damping="0.5"/></joint></robot>"""
    )
    a, b = ms.load_robot(sdf), ms.load_robot(urdf)
    assert a.source["derivation"] == "sdf" and (a.nq, a.nv) == (b.nq, b.nv) == (1, 1)
    for q in ([0.0], [1.1]):
        np.testing.assert_allclose(a.mass_matrix(q), b.mass_matrix(q), rtol=1e-14)
        np.testing.assert_allclose(a.forward_dynamics(q, [0.4], [1.0]), b.forward_dynamics(q, [0.4], [1.0]), rtol=1e-13)
    assert (a.lower_limit[0], a.upper_limit[0], a.effort_limit[0], a.damping[0]) == (-2, 2, 10, 0.5)


def test_an_sdf_with_a_ball_joint_in_its_tree_is_refused(tmp_path: Path) -> None:
    sdf = tmp_path / "ball.sdf"
    sdf.write_text(
        '<sdf version="1.6"><model name="m"><link name="a"/><link name="b"><inertial><mass>1</mass></inertial>'
        "</link><joint name='j' type='ball'><parent>a</parent><child>b</child></joint></model></sdf>"
    )
    with pytest.raises(ms.ModelError) as caught:
        ms.load_robot(sdf)
    assert str(caught.value) == (
        f"{sdf}: joint 'j' of type 'ball' is in the tree and URDF cannot express it "
        "(supported: revolute, prismatic, fixed, continuous)"
    )
    doctype = tmp_path / "doctype.sdf"
    doctype.write_text('<!DOCTYPE sdf [<!ENTITY x "1">]><sdf version="1.6"><model name="m"/></sdf>')
    with pytest.raises(ms.ModelError, match="DOCTYPE declarations are not allowed in a SDF"):
        ms.load_robot(doctype)
