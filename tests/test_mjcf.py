"""MJCF files load through Pinocchio's MJCF parser behind the untrusted-input checks, and their accelerations agree
with MuJoCo's own mj_forward on the same file."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest

import multibody_sim as ms

mujoco = pytest.importorskip("mujoco", reason="the test extra installs mujoco (pip install -e '.[test]')")
gymnasium = pytest.importorskip("gymnasium", reason="the test extra installs gymnasium (pip install -e '.[test]')")

DATA = Path(__file__).resolve().parent / "data" / "mjcf"
# A real model from a pip package: Gymnasium's MuJoCo ant (a free-flying torso on four two-joint legs).
ANT = Path(gymnasium.__file__).resolve().parent / "envs" / "mujoco" / "assets" / "ant.xml"
MODELS = [DATA / "three_link_arm.xml", DATA / "floating_arm.xml", ANT]


def exact(message: str) -> str:
    return f"^{re.escape(message)}$"


def mujoco_model(path: Path, robot: ms.Robot) -> tuple[object, object]:
    """MuJoCo's model of the same file with what Pinocchio's ABA does not model turned off (FIELD_NOTES): contacts,
    limit and equality constraints, friction loss, joint springs; and a ball joint's damping, which Pinocchio's
    MJCF parser does not read, set to what the robot has."""
    model = mujoco.MjModel.from_xml_path(str(path))
    disable = mujoco.mjtDisableBit
    model.opt.disableflags |= (
        disable.mjDSBL_CONTACT | disable.mjDSBL_LIMIT | disable.mjDSBL_EQUALITY | disable.mjDSBL_FRICTIONLOSS
    )
    model.jnt_stiffness[:] = 0.0
    ball = [
        model.jnt_dofadr[j] + k
        for j in range(model.njnt)
        if model.jnt_type[j] == mujoco.mjtJoint.mjJNT_BALL
        for k in range(3)
    ]
    np.testing.assert_array_equal(np.delete(model.dof_damping, ball), np.delete(robot.damping, ball))
    model.dof_damping[ball] = robot.damping[ball]
    return model, mujoco.MjData(model)


def to_mujoco(robot: ms.Robot, q: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(qpos, qvel, R): MuJoCo's free joint is [x y z qw qx qy qz] with its linear velocity in the world frame;
    Pinocchio's free-flyer [x y z qx qy qz qw] with both velocities in the body frame. A ball joint's quaternion
    is scalar first too."""
    qpos, qvel, rotation = q.copy(), v.copy(), np.eye(3)
    for jid in range(1, robot.model.njoints):
        joint = robot.model.joints[jid]
        i = joint.idx_q
        if joint.shortname() == "JointModelFreeFlyer":
            x, y, z, w = q[i + 3 : i + 7]
            qpos[i + 3 : i + 7] = w, x, y, z
            rotation = pin.Quaternion(w, x, y, z).toRotationMatrix()
            qvel[joint.idx_v : joint.idx_v + 3] = rotation @ v[joint.idx_v : joint.idx_v + 3]
        elif joint.shortname() == "JointModelSpherical":
            x, y, z, w = q[i : i + 4]
            qpos[i : i + 4] = w, x, y, z
    return qpos, qvel, rotation


@pytest.mark.parametrize("path", MODELS, ids=lambda p: p.stem)
def test_accelerations_agree_with_mujoco(path: Path) -> None:
    robot = ms.load_robot(path)
    model, data = mujoco_model(path, robot)
    assert (model.nq, model.nv) == (robot.nq, robot.nv)
    assert robot.total_mass == pytest.approx(float(model.body_mass.sum()), rel=1e-12)
    np.testing.assert_array_equal(robot.model.gravity.linear, model.opt.gravity)
    rng = np.random.default_rng(0)
    for _ in range(5):
        q = robot.random_configuration(rng)
        v = rng.normal(size=robot.nv)
        tau = rng.normal(size=robot.nv)
        if robot.floating_base:
            tau[:6] = 0.0
        ours = robot.forward_dynamics(q, v, tau)
        data.qpos[:], data.qvel[:], rotation = to_mujoco(robot, q, v)
        data.qfrc_applied[:] = tau
        mujoco.mj_forward(model, data)
        expected = data.qacc.copy()
        if robot.floating_base:  # MuJoCo differentiates the world-frame linear velocity: R (a + w x v)
            ours[:3] = rotation @ (ours[:3] + np.cross(v[3:6], v[:3]))
        assert np.abs(ours - expected).max() <= 1e-10 * np.abs(expected).max()


def test_an_mjcf_robot_simulates_and_keeps_the_files_settings() -> None:
    arm = ms.load_robot(DATA / "three_link_arm.xml")
    assert arm.source["format"] == "mjcf" and arm.name == "three_link_arm" and not arm.floating_base
    np.testing.assert_array_equal(arm.damping, [0.4, 0.2, 0.05])
    np.testing.assert_array_equal(arm.model.armature, [0.02, 0.01, 0.0])
    assert (arm.lower_limit[1], arm.upper_limit[1]) == (-2.0, 2.0)  # angle="radian"
    trajectory = ms.simulate(arm, [0.3, 0.5, -0.2], [0.0, 1.0, 0.0], duration=0.2, dt=1e-3)
    assert np.abs(trajectory.energy_error).max() < 1e-9
    assert trajectory.dissipated[-1] > 0  # its damping is in the ledger
    floating = ms.load_robot(DATA / "floating_arm.xml")
    assert floating.floating_base and floating.joint_names[0] == "root"
    # The file decides the base.
    for name, floating, said in (
        ("three_link_arm", True, "has no free joint"),
        ("floating_arm", False, "has a free joint"),
    ):
        path = DATA / f"{name}.xml"
        with pytest.raises(ms.ModelError) as caught:
            ms.load_robot(path, floating_base=floating)
        assert str(caught.value) == (
            f"{path}: an MJCF file declares its base (its root body {said}): floating_base={floating} cannot change "
            "it; leave floating_base=None or edit the file's <freejoint/>"
        )


def write(tmp_path: Path, text: str, name: str = "model.xml") -> Path:
    path = tmp_path / name
    path.write_text(text)
    return path


BODY = '<body name="b"><joint type="hinge"/><geom type="sphere" size="0.1"/></body>'


def test_hostile_mjcf_is_refused_in_one_line(tmp_path: Path) -> None:
    doctype = write(tmp_path, f'<!DOCTYPE mujoco [<!ENTITY x "1">]><mujoco><worldbody>{BODY}</worldbody></mujoco>')
    with pytest.raises(
        ms.ModelError, match=exact(f"{doctype}: DOCTYPE declarations are not allowed in a MJCF (entities could expand)")
    ):
        ms.load_robot(doctype)
    include = write(tmp_path, '<mujoco><include file="../../etc/other.xml"/></mujoco>', "include.xml")
    with pytest.raises(
        ms.ModelError,
        match=exact(
            f"{include}: <include> is not supported (Pinocchio's MJCF parser does not follow it): inline the "
            "included file"
        ),
    ):
        ms.load_robot(include)
    for name, asset in (
        ("mesh", '<mesh name="m" file="/etc/passwd"/>'),
        ("texture", '<texture name="t" type="2d" file="../../secret.png"/>'),
    ):
        escaping = write(
            tmp_path, f"<mujoco><asset>{asset}</asset><worldbody>{BODY}</worldbody></mujoco>", f"{name}.xml"
        )
        with pytest.raises(ms.ModelError) as caught:
            ms.load_robot(escaping)
        assert str(caught.value).startswith(f"{escaping}: {name} '") and "resolves outside the allowed folders" in str(
            caught.value
        )
    meshdir = write(
        tmp_path,
        f'<mujoco><compiler meshdir="../.."/><asset><mesh name="m" file="x.stl"/></asset><worldbody>{BODY}'
        "</worldbody></mujoco>",
        "meshdir.xml",
    )
    with pytest.raises(ms.ModelError, match="resolves outside the allowed folders"):
        ms.load_robot(meshdir)
    many = write(tmp_path, "<mujoco><worldbody>" + BODY * 1001 + "</worldbody></mujoco>", "many.xml")
    with pytest.raises(
        ms.ModelError, match=exact(f"{many}: the robot has 1001 bodies, more than the 1000 this simulator accepts")
    ):
        ms.load_robot(many)
    empty = write(tmp_path, "<mujoco><worldbody/></mujoco>", "empty.xml")
    with pytest.raises(ms.ModelError, match=exact(f"{empty}: Pinocchio cannot build the model (No such node (body))")):
        ms.load_robot(empty)
    gravity = write(tmp_path, f'<mujoco><option gravity="0 nan -9"/><worldbody>{BODY}</worldbody></mujoco>', "g.xml")
    with pytest.raises(
        ms.ModelError, match=exact(f"{gravity}: <option gravity>: expected 3 finite numbers, got '0 nan -9'")
    ):
        ms.load_robot(gravity)


def test_a_mesh_inside_the_models_folder_is_accepted(tmp_path: Path) -> None:
    (tmp_path / "meshes").mkdir()
    model = write(
        tmp_path,
        f'<mujoco><compiler meshdir="meshes"/><asset><mesh name="m" file="absent.stl"/></asset><worldbody>{BODY}'
        "</worldbody></mujoco>",
    )
    from multibody_sim.catalog import check_mjcf, parse_xml

    root = parse_xml(model.read_bytes(), model, "MJCF", "")
    assert check_mjcf(root, model, package_dirs=[tmp_path]) is False  # inside the folder, and no free joint
