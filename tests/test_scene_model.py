"""What a scene does to the robot's MODEL, against independent references.

Each modification is checked against something the scene code does not compute: Pinocchio's CRBA / RNEA on the
unmodified catalog model (rows and columns of the kept dofs for locked joints, a rotated gravity vector for a
posed base, Gᵀ M G for mimic joints), a URDF rewritten with lxml to carry the payload as an extra link, a
centre-of-mass Jacobian for gravity, energy-error convergence orders for energies, and exact error messages.
"""

from __future__ import annotations

import math
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
import pytest
from conftest import joint, link, urdf
from lxml import etree

import multibody_sim as ms
from multibody_sim.exceptions import InvalidArgumentError, SceneError
from multibody_sim.integrators import INTEGRATORS
from multibody_sim.scenes import Scene, load_scene, make_scene, shipped_scenes

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover
    import tomli as tomllib

# Reduced models merge inertias and re-root placements, so the same physics comes out through a different
# sequence of floating-point operations: equal to ~1e-14 relative. 1e-10 of the matrix scale is far above that
# and far below any modelling difference these tests look for (a gram of payload changes M by ~1e-3).
ROUND_OFF = 1e-10
G0 = np.array([0.0, 0.0, -9.81])  # Pinocchio's default gravity [m/s²]


# ---- helpers -----------------------------------------------------------------------------------------
def _close(actual: np.ndarray, expected: np.ndarray, what: str = "") -> None:
    """Equal to round-off relative to the expected array's scale."""
    expected = np.asarray(expected, dtype=float)
    scale = max(1.0, float(np.abs(expected).max(initial=0.0)))
    np.testing.assert_allclose(actual, expected, rtol=0.0, atol=ROUND_OFF * scale, err_msg=what)


def _terms(model: pin.Model, q: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(M, C v + g, g) of a model by CRBA and RNEA, on a Data of their own (no Robot method involved)."""
    data = model.createData()
    M = pin.crba(model, data, q)
    M = np.triu(M) + np.triu(M, 1).T
    zero = np.zeros(model.nv)
    nle = pin.rnea(model, data, q, v, zero).copy()
    g = pin.rnea(model, data, q, zero, zero).copy()
    return M, nle, g


def _joint_slices(model: pin.Model, name: str) -> tuple[slice, slice]:
    """(q slice, v slice) of a joint of a model, by name."""
    j = model.joints[model.getJointId(name)]
    return slice(j.idx_q, j.idx_q + j.nq), slice(j.idx_v, j.idx_v + j.nv)


def _lock_coordinates(model: pin.Model, name: str, value: float) -> np.ndarray:
    """The configuration entries of a 1-dof joint at position `value`: (value,) or (cos, sin) if continuous."""
    nq = model.joints[model.getJointId(name)].nq
    return np.array([value]) if nq == 1 else np.array([math.cos(value), math.sin(value)])


def _locked_full_state(
    robot: ms.Robot, lock: dict[str, float], rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A random full state with the locked joints at their lock values and at rest, and the kept indices.

    Returns:
        (q_full, v_full, kept_q, kept_v): the reduced model keeps the remaining joints in Pinocchio's order, so
        its q and v are the full ones with the locked joints' entries deleted.
    """
    model = robot.model
    q, v = robot.random_configuration(rng), rng.normal(size=robot.nv)
    locked_q, locked_v = [], []
    for name, value in lock.items():
        sq, sv = _joint_slices(model, name)
        q[sq] = _lock_coordinates(model, name, value)
        v[sv] = 0.0
        locked_q += list(range(sq.start, sq.stop))
        locked_v += list(range(sv.start, sv.stop))
    kept_q = np.setdiff1d(np.arange(robot.nq), locked_q)
    kept_v = np.setdiff1d(np.arange(robot.nv), locked_v)
    return q, v, kept_q, kept_v


def _rpy_matrix(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """URDF's roll-pitch-yaw: R = Rz(yaw) Ry(pitch) Rx(roll), written out (not Pinocchio's rpyToMatrix)."""
    cr, sr = math.cos(roll), math.sin(roll)
    cp, sp = math.cos(pitch), math.sin(pitch)
    cy, sy = math.cos(yaw), math.sin(yaw)
    rx = np.array([[1, 0, 0], [0, cr, -sr], [0, sr, cr]])
    ry = np.array([[cp, 0, sp], [0, 1, 0], [-sp, 0, cp]])
    rz = np.array([[cy, -sy, 0], [sy, cy, 0], [0, 0, 1]])
    return rz @ ry @ rx


def _urdf_tree(path: Path | str) -> Any:
    """A URDF parsed with lxml, without comments, visuals and collisions (meshes do not enter the dynamics)."""
    root = etree.parse(str(path), etree.XMLParser(remove_comments=True)).getroot()
    for element in [*root.iter("visual"), *root.iter("collision")]:
        element.getparent().remove(element)
    return root


def _numbers(values: Any) -> str:
    return " ".join(repr(float(x)) for x in values)


def _write_urdf_with_payload(source: Path | str, parent_link: str, payload: dict[str, Any], out: Path) -> Path:
    """The robot's URDF with the payload as an extra link fixed to `parent_link` at its origin: the reference."""
    root = _urdf_tree(source)
    body = etree.SubElement(root, "link", name="test_payload_link")
    inertial = etree.SubElement(body, "inertial")
    etree.SubElement(inertial, "origin", xyz=_numbers(payload["com"]), rpy="0 0 0")
    etree.SubElement(inertial, "mass", value=repr(float(payload["mass"])))
    ixx, iyy, izz, ixy, ixz, iyz = (repr(float(x)) for x in payload["inertia"])
    etree.SubElement(inertial, "inertia", ixx=ixx, iyy=iyy, izz=izz, ixy=ixy, ixz=ixz, iyz=iyz)
    fixed = etree.SubElement(root, "joint", name="test_payload_joint", type="fixed")
    etree.SubElement(fixed, "parent", link=parent_link)
    etree.SubElement(fixed, "child", link="test_payload_link")
    etree.SubElement(fixed, "origin", xyz="0 0 0", rpy="0 0 0")
    out.write_bytes(etree.tostring(root, xml_declaration=True, encoding="utf-8"))
    return out


def _mimic_map(urdf_path: Path | str, full: pin.Model, reduced: pin.Model) -> tuple[np.ndarray, np.ndarray]:
    """(G, offset) read from the URDF's <mimic> elements with lxml: q_full = G q_reduced + offset, v_full = G v.

    Only for robots whose joints are all 1-coordinate (revolute, prismatic), as the ones tested here.
    """
    root = _urdf_tree(urdf_path)
    followers = {}
    for element in root.iter("joint"):
        mimic = element.find("mimic")
        if mimic is not None:
            followers[element.get("name")] = (
                mimic.get("joint"),
                float(mimic.get("multiplier", "1")),
                float(mimic.get("offset", "0")),
            )
    assert followers, "the URDF declares no <mimic>"
    G, offset = np.zeros((full.nv, reduced.nv)), np.zeros(full.nq)
    for jid in range(1, full.njoints):
        name = full.names[jid]
        row = full.joints[jid].idx_v
        assert full.joints[jid].nq == full.joints[jid].nv == 1
        if name in followers:
            leader, multiplier, shift = followers[name]
            G[row, reduced.joints[reduced.getJointId(leader)].idx_v] = multiplier
            offset[row] = shift
        else:
            G[row, reduced.joints[reduced.getJointId(name)].idx_v] = 1.0
    return G, offset


def _energy_error_ratio(system: ms.Robot, q0: np.ndarray, v0: np.ndarray, dt: float, duration: float) -> float:
    """max |energy_error| at dt over the same at dt/2 with RK4: ~2⁴ = 16 when the energies are the exact
    invariant of the forward dynamics, ~1 when they are not (the error then stops shrinking with dt)."""
    errors = [
        float(np.abs(ms.simulate(system, q0, v0, duration=duration, dt=h, progress=False).energy_error).max())
        for h in (dt, dt / 2)
    ]
    return errors[0] / errors[1]


def _scene_error(message: str) -> Any:
    return pytest.raises(SceneError, match="^" + re.escape(message) + "$")


# ---- locked joints -------------------------------------------------------------------------------------
LOCK_CASES = {
    "ur5-two-joints": ("ur5", {"elbow_joint": 0.7, "wrist_2_joint": -1.1}),
    "panda-fingers": ("panda", {"panda_finger_joint1": 0.02, "panda_finger_joint2": 0.013}),
    "solo12-floating-knees": ("solo12", {"FL_KFE": -1.2, "HR_KFE": 0.9}),
    "double-pendulum-continuous": ("double_pendulum_continuous", {"joint1": 4.0}),
}


@pytest.mark.parametrize("case", LOCK_CASES, ids=list(LOCK_CASES))
def test_locked_joints_keep_the_full_dynamics_of_the_kept_dofs(robot: Callable[..., ms.Robot], case: str) -> None:
    """M, C v + g, g, damping and forward dynamics of the reduced model equal the full model's rows and columns of
    the kept dofs at the lock configuration, with v = 0 on the locked joints (the reduced model is exact, not an
    approximation); nq/nv shrink by the locked joints' sizes, the dof order is kept. The continuous case locks
    by angle, so its full configuration carries (cos 4, sin 4)."""
    name, lock = LOCK_CASES[case]
    full = robot(name)
    scene = make_scene(robot={"source": name}, lock=lock)
    rng = np.random.default_rng(7)
    locked_nq = sum(full.model.joints[full.model.getJointId(j)].nq for j in lock)
    assert (scene.full_nq, scene.full_nv) == (full.nq, full.nv)
    assert (scene.nq, scene.nv) == (full.nq - locked_nq, full.nv - len(lock))
    assert scene.dof_names == [d for d in full.dof_names if d not in lock]
    for _ in range(3):
        q_full, v_full, kept_q, kept_v = _locked_full_state(full, lock, rng)
        q, v = q_full[kept_q], v_full[kept_v]
        M_full, nle_full, g_full = _terms(full.model, q_full, v_full)
        block = np.ix_(kept_v, kept_v)
        _close(scene.mass_matrix(q), M_full[block], "M")
        _close(scene.nonlinear_effects(q, v), nle_full[kept_v], "C v + g")
        _close(scene.gravity(q), g_full[kept_v], "g")
        _close(scene.damping, full.damping[kept_v], "damping")
        tau = rng.normal(size=scene.nv)
        if scene.floating_base:
            tau[:6] = 0.0
        expected = np.linalg.solve(M_full[block], tau - nle_full[kept_v] - full.damping[kept_v] * v)
        _close(scene.forward_dynamics(q, v, tau), expected, "forward dynamics")


def test_lock_configuration_holds_the_lock_values(robot: Callable[..., ms.Robot]) -> None:
    """The full configuration the joints are locked in: the lock values ((cos, sin) for a continuous joint),
    the neutral configuration elsewhere."""
    full = robot("double_pendulum_continuous")
    scene = make_scene(robot={"source": "double_pendulum_continuous"}, lock={"joint1": -2.5})
    expected = full.neutral()
    expected[_joint_slices(full.model, "joint1")[0]] = [math.cos(-2.5), math.sin(-2.5)]
    _close(scene.lock_configuration, expected)


@pytest.mark.parametrize(
    ("source", "lock", "key"),
    [
        ("ur5", {"shoulder_pan_joint": 7.0}, "shoulder_pan_joint"),
        ("panda", {"panda_finger_joint1": -0.01}, "panda_finger_joint1"),
    ],
)
def test_lock_outside_the_limits_is_refused(
    robot: Callable[..., ms.Robot], source: str, lock: dict[str, float], key: str
) -> None:
    """A lock value outside the URDF's limits: one line with the value and the limits."""
    full = robot(source)
    i = _joint_slices(full.model, key)[0].start
    lo, hi = full.lower_limit[i], full.upper_limit[i]
    assert not lo <= lock[key] <= hi  # the case is what it claims
    message = f"<scene>: lock.{key}: {lock[key]:g} is outside the joint's limits [{lo:g}, {hi:g}]"
    with _scene_error(message):
        make_scene(robot={"source": source}, lock=lock)


def test_locking_every_joint_is_refused() -> None:
    with _scene_error("<scene>: lock: every joint is locked: nothing is left to simulate"):
        make_scene(robot={"source": "double_pendulum"}, lock={"joint1": 3.0, "joint2": 0.0})


def test_locking_the_floating_base_is_refused(robot: Callable[..., ms.Robot]) -> None:
    root = robot("solo12").joint_names[0]  # the free-flyer Pinocchio adds
    message = f"<scene>: lock.{root}: '{root}' is the floating base: it cannot be locked or given joint settings"
    with _scene_error(message):
        make_scene(robot={"source": "solo12"}, lock={root: 0.0})


# ---- base pose -----------------------------------------------------------------------------------------
def test_base_pose_rotates_gravity_and_moves_every_frame(robot: Callable[..., ms.Robot]) -> None:
    """ur5 welded at p with roll-pitch-yaw R: in the base frame the world's gravity reads Rᵀ g, so g(q) equals the
    unposed robot's with gravity Rᵀ g; M is unchanged; every frame (those welded to the world too) sits at
    (R, p) times its unposed placement; V(q) = V_unposed,Rᵀg(q) − m gᵀ p with m the moving bodies' mass."""
    position, rpy = np.array([0.3, -0.2, 1.5]), (0.4, -0.7, 1.2)
    full = robot("ur5")
    scene = make_scene(robot={"source": "ur5", "position": position.tolist(), "rpy": list(rpy)})
    R = _rpy_matrix(*rpy)
    pose = pin.SE3(R, position)
    rotated = full.model.copy()
    rotated.gravity.linear = R.T @ G0
    moving_mass = sum(full.model.inertias[j].mass for j in range(1, full.model.njoints))
    rng = np.random.default_rng(3)
    for _ in range(3):
        q, v = full.random_configuration(rng), rng.normal(size=full.nv)
        M, nle, g = _terms(rotated, q, v)
        _close(scene.gravity(q), g, "g")
        _close(scene.mass_matrix(q), M, "M")
        _close(scene.nonlinear_effects(q, v), nle, "C v + g")
        data = rotated.createData()
        potential = pin.computePotentialEnergy(rotated, data, q) - moving_mass * float(G0 @ position)
        _close(scene.potential_energy(q), potential, "V")
        reference, posed = full.model.createData(), scene.model.createData()
        pin.framesForwardKinematics(full.model, reference, q)
        pin.framesForwardKinematics(scene.model, posed, q)
        names = [f.name for f in full.model.frames]
        assert [f.name for f in scene.model.frames] == names
        for fid in range(1, len(names)):  # 0 is the universe itself
            _close(posed.oMf[fid].homogeneous, (pose * reference.oMf[fid]).homogeneous, names[fid])


@pytest.mark.parametrize(
    ("tables", "message"),
    [
        (
            {"source": "solo12", "position": [0.0, 0.0, 1.0]},
            "<scene>: robot.position: only for a fixed base, and 'solo12' is floating by default "
            '(add base = "fixed")',
        ),
        (
            {"source": "ur5", "base": "floating", "rpy": [0.0, 0.0, 1.0]},
            '<scene>: robot.rpy: only for a fixed base, not with base = "floating"',
        ),
    ],
)
def test_a_floating_base_takes_no_pose(tables: dict[str, Any], message: str) -> None:
    with _scene_error(message):
        make_scene(robot=tables)


# ---- gravity -------------------------------------------------------------------------------------------
def test_zero_gravity_means_no_gravity_torque_and_constant_potential(robot: Callable[..., ms.Robot]) -> None:
    """gravity = [0, 0, 0]: g(q) = 0 at any q, and V stays constant (zero) along a free motion."""
    full = robot("ur5")
    scene = make_scene(robot={"source": "ur5"}, gravity=[0.0, 0.0, 0.0])
    rng = np.random.default_rng(5)
    for _ in range(3):
        assert np.all(scene.gravity(full.random_configuration(rng)) == 0.0)
    q0, v0 = full.random_configuration(rng), rng.normal(size=full.nv)
    traj = ms.simulate(scene, q0, v0, duration=0.05, dt=1e-3, progress=False)
    assert np.ptp(traj.q, axis=0).max() > 1e-3  # it does move
    assert np.all(traj.potential_energy == traj.potential_energy[0])


def test_any_gravity_vector_acts_through_the_centre_of_mass(robot: Callable[..., ms.Robot]) -> None:
    """g(q) = −m J_comᵀ γ and V(q1) − V(q2) = −m γᵀ (c(q1) − c(q2)) for a gravity γ in any direction, with m, c and
    J_com from Pinocchio's centre-of-mass algorithms on the unmodified model (not RNEA)."""
    gamma = np.array([1.2, -3.4, -5.6])
    full = robot("panda")
    scene = make_scene(robot={"source": "panda"}, gravity=gamma.tolist())
    data = full.model.createData()
    rng = np.random.default_rng(11)
    qs = [full.random_configuration(rng) for _ in range(3)]
    coms = []
    for q in qs:
        jacobian = pin.jacobianCenterOfMass(full.model, data, q, False)
        mass = data.mass[0]
        coms.append(data.com[0].copy())
        _close(scene.gravity(q), -mass * jacobian.T @ gamma, "g")
    for (q1, c1), (q2, c2) in [((qs[0], coms[0]), (qs[1], coms[1])), ((qs[1], coms[1]), (qs[2], coms[2]))]:
        _close(scene.potential_energy(q1) - scene.potential_energy(q2), -data.mass[0] * gamma @ (c1 - c2), "ΔV")


# ---- payloads ------------------------------------------------------------------------------------------
PAYLOAD = {"mass": 1.3, "com": [0.02, -0.01, 0.12], "inertia": [4e-3, 5e-3, 3e-3, 2e-4, -1e-4, 3e-4]}


@pytest.mark.parametrize("frame", ["panda_hand", "panda_link4"])
def test_payload_equals_an_extra_link_in_the_urdf(robot: Callable[..., ms.Robot], tmp_path: Path, frame: str) -> None:
    """A payload on a link's frame gives the same M(q) and g(q) as the URDF with the payload written as an extra
    link fixed to that link (Pinocchio's parser merges it): panda_hand sits behind a fixed joint with a rotated
    placement, panda_link4 is a joint's own body. The total mass grows by the payload's mass."""
    full = robot("panda")
    scene = make_scene(robot={"source": "panda"}, payload=[{"frame": frame, **PAYLOAD}])
    reference = ms.load_robot(
        _write_urdf_with_payload(full.source["urdf_path"], frame, PAYLOAD, tmp_path / "panda_payload.urdf")
    )
    assert reference.nv == scene.nv == full.nv
    rng = np.random.default_rng(13)
    for _ in range(3):
        q, v = full.random_configuration(rng), rng.normal(size=full.nv)
        M, nle, g = _terms(reference.model, q, v)
        _close(scene.mass_matrix(q), M, "M")
        _close(scene.gravity(q), g, "g")
        _close(scene.nonlinear_effects(q, v), nle, "C v + g")
        assert np.abs(scene.mass_matrix(q) - full.mass_matrix(q)).max() > 1e-3  # the payload matters here
    assert scene.total_mass == pytest.approx(full.total_mass + PAYLOAD["mass"], rel=1e-14)


def test_payload_on_a_frame_welded_to_the_world_is_refused() -> None:
    full = ms.load_robot("ur5")
    moving = ", ".join(f.name for f in full.model.frames if f.parentJoint != 0)
    message = f"<scene>: payload[0].frame: 'base_link' is welded to the world: nothing there moves (valid: {moving})"
    with _scene_error(message):
        make_scene(robot={"source": "ur5"}, payload=[{"frame": "base_link", "mass": 1.0}])


# ---- armature ------------------------------------------------------------------------------------------
def test_armature_adds_to_the_mass_matrix_diagonal_and_the_kinetic_energy(robot: Callable[..., ms.Robot]) -> None:
    """M_scene = CRBA(robot) + diag(A); T = ½ vᵀ (M + A) v, through the public method and the one simulate records;
    forward dynamics solve (M + A) a = τ − C v − g; and the energy error of RK4 shrinks at its order, which it
    would not if T and the dynamics disagreed about A."""
    full = robot("ur5")
    armature = {"shoulder_pan_joint": 0.3, "elbow_joint": 0.2, "wrist_3_joint": 0.05}
    scene = make_scene(robot={"source": "ur5"}, joints={k: {"armature": a} for k, a in armature.items()})
    A = np.diag([armature.get(d, 0.0) for d in full.dof_names])
    rng = np.random.default_rng(17)
    for _ in range(3):
        q, v, tau = full.random_configuration(rng), rng.normal(size=full.nv), rng.normal(size=full.nv)
        M, nle, _ = _terms(full.model, q, v)
        _close(scene.mass_matrix(q), M + A, "M")
        kinetic = 0.5 * v @ (M + A) @ v
        _close(scene.kinetic_energy(q, v), kinetic, "T")
        _close(scene.unchecked_energies(q, v)[0], kinetic, "T (recorded)")
        _close(scene.forward_dynamics(q, v, tau), np.linalg.solve(M + A, tau - nle), "forward dynamics")
    q0 = np.array([0.0, -1.2, 1.5, -1.0, -1.57, 0.0])
    assert _energy_error_ratio(scene, q0, np.full(6, 1.5), dt=8e-3, duration=0.4) > 8.0


# ---- mimic joints --------------------------------------------------------------------------------------
MIMIC_URDF = urdf(
    link("base"),
    link("l1"),
    link("l2", mass=0.7, com="0.1 0 -0.4"),
    link("l3", mass=0.5),
    joint("j1", "base", "l1"),
    joint("j2", "l1", "l2", xyz="0 0 -1", axis="1 0 0").replace(
        "</joint>", '<mimic joint="j1" multiplier="2.0" offset="0.1"/></joint>'
    ),
    joint("j3", "l2", "l3", xyz="0 0 -1"),
    name="mimic_chain",
)


def _mimic_case(name: str, write_urdf: Callable[..., Path]) -> tuple[ms.Robot, Scene, str]:
    """(full robot without mimic, mimic scene, URDF path) for panda or a chain whose middle joint follows the
    first with multiplier 2 and offset 0.1 (panda's fingers have multiplier 1, offset 0)."""
    source = "panda" if name == "panda" else str(write_urdf(MIMIC_URDF, "mimic_chain.urdf"))
    full = ms.load_robot(source, damping=False)
    # Without URDF damping: the follower's damper is the subject of its own test.
    scene = make_scene(robot={"source": source, "mimic": True, "damping": False})
    return full, scene, full.source["urdf_path"]


MIMIC_CRBA_BUG = (
    "bug: pin 4.1's crba on a model whose mimic joint has child joints accumulates into Data.Fcrb across calls: "
    "every call on the same Data adds the leader/grandchild coupling again (M[j1, j3] grows 1x, 2x, 3x); Scene "
    "reuses self.data in mass_matrix, mimic.crba_forward_dynamics and mimic.energies"
)


@pytest.mark.parametrize("name", ["panda", "chain"])
def test_mimic_scene_is_the_full_robot_restricted_to_the_mimic_map(write_urdf: Callable[..., Path], name: str) -> None:
    """With G and the offset read from the URDF's <mimic> (q_full = G q + offset, v_full = G v, G constant):
    M = Gᵀ M_full G, C v + g = Gᵀ (C v + g)_full, g = Gᵀ g_full, (Gᵀ M_full G) a = τ − Gᵀ (C v + g)_full, and T, V
    (as simulate records them) equal the full robot's at the consistent full state, at several states in a row."""
    full, scene, path = _mimic_case(name, write_urdf)
    assert (scene.nq, scene.nv) == (full.nq - 1, full.nv - 1)
    G, offset = _mimic_map(path, full.model, scene.model)
    rng = np.random.default_rng(19)
    for _ in range(3):
        q, v = scene.random_configuration(rng), rng.normal(size=scene.nv)
        q_full, v_full = G @ q + offset, G @ v
        M, nle, g = _terms(full.model, q_full, v_full)
        _close(scene.mass_matrix(q), G.T @ M @ G, "M")
        _close(scene.nonlinear_effects(q, v), G.T @ nle, "C v + g")
        _close(scene.gravity(q), G.T @ g, "g")
        tau = rng.normal(size=scene.nv)
        _close(scene.forward_dynamics(q, v, tau), np.linalg.solve(G.T @ M @ G, tau - G.T @ nle), "forward dynamics")
        kinetic, potential = scene.unchecked_energies(q, v)
        _close(kinetic, full.kinetic_energy(q_full, v_full), "T")
        _close(potential, full.potential_energy(q_full), "V")


def test_mimic_scene_public_energies(write_urdf: Callable[..., Path]) -> None:
    """The public energy methods of a mimic scene equal the full robot's at the consistent full state."""
    full, scene, path = _mimic_case("panda", write_urdf)
    G, offset = _mimic_map(path, full.model, scene.model)
    rng = np.random.default_rng(23)
    q, v = scene.random_configuration(rng), rng.normal(size=scene.nv)
    _close(scene.kinetic_energy(q, v), full.kinetic_energy(G @ q + offset, G @ v), "T")
    _close(scene.potential_energy(q), full.potential_energy(G @ q + offset), "V")


def test_mimic_scene_conserves_energy_at_rk4_order() -> None:
    """Undamped mimic panda: the CRBA forward dynamics and the mimic energies belong together (RK4's energy error
    shrinks ~16× when dt halves)."""
    scene = make_scene(robot={"source": "panda", "mimic": True, "damping": False})
    q0 = np.array([0.0, -0.3, 0.0, -2.0, 0.0, 1.7, 0.8, 0.02])
    v0 = np.array([1.0, -0.5, 0.8, 0.5, -1.0, 0.7, 1.5, 0.05])
    assert _energy_error_ratio(scene, q0, v0, dt=8e-3, duration=0.4) > 8.0


def test_mimic_scene_damping_includes_the_followers(robot: Callable[..., ms.Robot]) -> None:
    """With URDF damping on: the scene's forward dynamics equal the full robot's restricted to the mimic map,
    (Gᵀ M G) a = τ − Gᵀ (C v + g)_full − Gᵀ D_full G v."""
    full = robot("panda")
    scene = make_scene(robot={"source": "panda", "mimic": True})
    G, offset = _mimic_map(full.source["urdf_path"], full.model, scene.model)
    rng = np.random.default_rng(29)
    q, v, tau = scene.random_configuration(rng), rng.normal(size=scene.nv), rng.normal(size=scene.nv)
    M, nle, _ = _terms(full.model, G @ q + offset, G @ v)
    expected = np.linalg.solve(G.T @ M @ G, tau - G.T @ nle - G.T @ (full.damping * (G @ v)))
    _close(scene.forward_dynamics(q, v, tau), expected)


def test_mimic_scene_spring_on_a_joint_after_the_mimic_joint(write_urdf: Callable[..., Path]) -> None:
    """A spring on j3, after the mimic joint j2: its stored energy ½ k (q3 − rest)² adds to the full V."""
    path = str(write_urdf(MIMIC_URDF, "mimic_chain.urdf"))
    full = ms.load_robot(path)
    scene = make_scene(robot={"source": path, "mimic": True}, joints={"j3": {"stiffness": 5.0, "rest": 0.2}})
    G, offset = _mimic_map(path, full.model, scene.model)
    q = np.array([0.3, -0.4])
    _close(scene.unchecked_energies(q, np.zeros(2))[1], full.potential_energy(G @ q + offset) + 0.5 * 5.0 * 0.6**2)


def test_locking_a_mimic_leader_is_a_scene_error() -> None:
    """Locks and mimic joints are not combined (yet): the user gets a SceneError naming the key."""
    with pytest.raises(SceneError, match=re.escape("<scene>: lock.panda_finger_joint1: ")):
        make_scene(robot={"source": "panda", "mimic": True}, lock={"panda_finger_joint1": 0.02})


@pytest.mark.parametrize("integrator", sorted(n for n, m in INTEGRATORS.items() if m.implicit))
def test_implicit_integrators_refuse_a_mimic_scene(integrator: str) -> None:
    """Implicit methods need ABA derivatives, which mimic joints lack: the message lists the methods that can."""
    scene = make_scene(robot={"source": "panda", "mimic": True})
    able = ", ".join(sorted(n for n, m in INTEGRATORS.items() if not m.implicit))
    message = (
        f"integrator '{integrator}' needs the dynamics' analytic derivatives, which scene '{scene.name}' does not "
        f"provide (it honours mimic joints, which Pinocchio's ABA derivatives do not support); use one of: {able}"
    )
    with pytest.raises(InvalidArgumentError, match="^" + re.escape(message) + "$"):
        ms.simulate(scene, scene.q0, scene.v0, duration=0.01, dt=1e-3, integrator=integrator, progress=False)


# ---- damping and friction overrides --------------------------------------------------------------------
def _rough_chain(write_urdf: Callable[..., Path]) -> str:
    """Two revolute joints, each with URDF damping 0.1 and Coulomb friction 0.2."""
    rough = '<dynamics damping="0.1" friction="0.2"/>'
    text = urdf(
        link("base"),
        link("l1"),
        link("l2", mass=0.6),
        joint("j1", "base", "l1", damping=0.1),
        joint("j2", "l1", "l2", xyz="0 0 -1", damping=0.1),
        name="rough_chain",
    ).replace('<dynamics damping="0.1"/>', rough)
    return str(write_urdf(text, "rough_chain.urdf"))


@pytest.mark.parametrize("urdf_damping", [True, False])
def test_joint_overrides_replace_urdf_damping_and_friction(write_urdf: Callable[..., Path], urdf_damping: bool) -> None:
    """joints.j1 overrides replace the URDF's damping and friction on j1; j2 keeps the URDF's, unless
    robot.damping = false drops them (the explicit overrides stay). Checked on the forward dynamics:
    M a = τ − C v − g − D v − F tanh(v / v_s), with M, C v + g from the robot loaded without damping."""
    path = _rough_chain(write_urdf)
    bare = ms.load_robot(path, damping=False)
    scene = make_scene(
        robot={"source": path, "damping": urdf_damping},
        joints={"j1": {"damping": 0.7, "friction": 0.4}},
        friction_velocity=0.05,
    )
    kept = 1.0 if urdf_damping else 0.0
    D, F = np.array([0.7, 0.1 * kept]), np.array([0.4, 0.2 * kept])
    _close(scene.damping, D, "damping")
    rng = np.random.default_rng(31)
    for _ in range(3):
        # Velocities of the order of v_s, where tanh is neither linear nor saturated: v_s matters.
        q, v, tau = bare.random_configuration(rng), rng.normal(scale=0.05, size=2), rng.normal(size=2)
        M, nle, _ = _terms(bare.model, q, v)
        expected = np.linalg.solve(M, tau - nle - D * v - F * np.tanh(v / 0.05))
        _close(scene.forward_dynamics(q, v, tau), expected, "forward dynamics")


# ---- a scene declaring nothing but the robot -----------------------------------------------------------
def _urdf_declares_damping(path: str) -> bool:
    return any(float(d.get("damping", "0")) > 0 for d in _urdf_tree(path).iter("dynamics"))


@pytest.mark.parametrize("name", ["ur5", "double_pendulum"])
def test_a_scene_of_only_the_robot_steps_bitwise_like_the_robot(robot: Callable[..., ms.Robot], name: str) -> None:
    """make_scene(robot=...) models nothing more: no elements, no constraints, nothing recorded, a ledger of joint
    torques (and damping exactly when the URDF declares it), and RK4 runs bitwise equal to the plain robot's."""
    full = robot(name)
    scene = make_scene(robot={"source": name})
    assert scene.elements is None and scene.constraints is None
    assert scene.record_fields == ()
    damped = _urdf_declares_damping(full.source["urdf_path"])
    expected = [("joint_torques", "work")] + ([("joint_damping", "dissipated")] if damped else [])
    assert scene.ledger_elements == expected
    assert damped == (name == "double_pendulum")  # both branches are exercised
    rng = np.random.default_rng(37)
    q0, v0 = full.random_configuration(rng), rng.normal(size=full.nv)
    runs = [ms.simulate(system, q0, v0, duration=0.05, dt=1e-3, progress=False) for system in (full, scene)]
    for field in ("t", "q", "v", "kinetic_energy", "potential_energy", "work", "dissipated", "energy_error"):
        assert np.array_equal(getattr(runs[0], field), getattr(runs[1], field)), field
    assert runs[0].ledger.keys() == runs[1].ledger.keys()


# ---- semantic errors -----------------------------------------------------------------------------------
# Each case: (the scene's tables besides robot = ur5, the message after "<scene>: "), built from ur5's joint and
# frame lists as the catalog robot has them (a joint list without elbow_joint after it is locked).
SEMANTIC_CASES: dict[str, Callable[[list[str], list[str]], tuple[dict[str, Any], str]]] = {
    "joints-unknown-joint": lambda joints, frames: (
        {"joints": {"elbo": {"damping": 1.0}}},
        f"joints.elbo: unknown joint 'elbo' (valid: {', '.join(joints)})",
    ),
    "lock-unknown-joint": lambda joints, frames: (
        {"lock": {"elbo": 1.0}},
        f"lock.elbo: unknown joint 'elbo' (valid: {', '.join(joints)})",
    ),
    "initial-q-unknown-joint": lambda joints, frames: (
        {"initial": {"q": {"elbo": 0.5}}},
        f"initial.q.elbo: unknown joint 'elbo' (valid: {', '.join(joints)})",
    ),
    "initial-q-names-a-locked-joint": lambda joints, frames: (
        {"lock": {"elbow_joint": 1.0}, "initial": {"q": {"elbow_joint": 0.5}}},
        "initial.q.elbow_joint: unknown joint 'elbow_joint' "
        f"(valid: {', '.join(j for j in joints if j != 'elbow_joint')})",
    ),
    "force-unknown-frame": lambda joints, frames: (
        {"force": [{"frame": "tool9", "force": [1.0, 0.0, 0.0]}]},
        "force[0].frame: unknown frame 'tool9' (did you mean 'tool0'?)",
    ),
    "payload-unknown-frame": lambda joints, frames: (
        {"payload": [{"frame": "tool9", "mass": 1.0}]},
        "payload[0].frame: unknown frame 'tool9' (did you mean 'tool0'?)",
    ),
    "constraint-unknown-frame": lambda joints, frames: (
        {"constraint": [{"type": "point", "frames": ["zz9"]}]},
        f"constraint[0].frames: unknown frame 'zz9' (valid: {', '.join(frames[0])})",
    ),
    "initial-q-length-after-locking": lambda joints, frames: (
        {"lock": {"elbow_joint": 1.0}, "initial": {"q": [0.0] * len(joints)}},
        f"initial.q: has {len(joints)} entries, the scene's model needs {len(joints) - 1} after locking 1 joint(s)",
    ),
    "initial-v-length": lambda joints, frames: (
        {"initial": {"v": [0.0] * (len(joints) + 1)}},
        f"initial.v: has {len(joints) + 1} entries, the scene's model needs {len(joints)}",
    ),
    "rest-without-stiffness": lambda joints, frames: (
        {"joints": {"elbow_joint": {"rest": 0.3}}},
        "joints.elbow_joint.rest: a rest position needs a spring: give stiffness > 0",
    ),
    "rest-with-zero-stiffness": lambda joints, frames: (
        {"joints": {"elbow_joint": {"rest": 0.3, "stiffness": 0.0}}},
        "joints.elbow_joint.rest: a rest position needs a spring: give stiffness > 0",
    ),
    "locked-and-overridden": lambda joints, frames: (
        {"lock": {"elbow_joint": 1.0}, "joints": {"elbow_joint": {"damping": 0.5}}},
        "joints.elbow_joint: the joint is locked (lock.elbow_joint); a locked joint takes no overrides",
    ),
}


@pytest.mark.parametrize("case", SEMANTIC_CASES, ids=list(SEMANTIC_CASES))
def test_semantic_errors_are_one_line_scene_errors(robot: Callable[..., ms.Robot], case: str) -> None:
    """Names the model does not have, sizes that do not fit the reduced model, inconsistent joint settings."""
    full = robot("ur5")
    frames = [f.name for f in full.model.frames if f.name != "universe"]
    moving = [f.name for f in full.model.frames if f.parentJoint != 0]  # forces and payloads need a moving body
    tables, message = SEMANTIC_CASES[case](full.joint_names, (frames, moving))
    with _scene_error("<scene>: " + message):
        make_scene(robot={"source": "ur5"}, **tables)


# ---- describe() ----------------------------------------------------------------------------------------
def _line(text: str, label: str) -> str:
    """The one line of describe()'s text that carries `label`."""
    lines = [line for line in text.splitlines() if label in line]
    assert len(lines) == 1, f"{label!r} in {text!r}"
    return lines[0]


def test_describe_lists_what_the_scene_modelled(robot: Callable[..., ms.Robot]) -> None:
    """Sizes full → reduced (computed from the catalog robot and the lock table), locked joints with their values,
    payloads, armature, gravity, every force element and every constraint with its rows (point: 3)."""
    full = robot("ur5")
    tables: dict[str, Any] = {
        "robot": {"source": "ur5"},
        "gravity": [0.0, 0.0, -3.7],
        "lock": {"wrist_3_joint": 0.3},
        "joints": {"elbow_joint": {"stiffness": 3.0, "friction": 0.2, "armature": 0.05}},
        "payload": [{"frame": "wrist_2_link", "mass": 0.5}],
        "force": [{"name": "push", "frame": "tool0", "force": [1.0, 0.0, 0.0]}],
        "constraint": [{"name": "pin", "type": "point", "frames": ["tool0"]}],
    }
    text = make_scene(**tables).describe()
    locked = _line(text, "locked:")
    assert "wrist_3_joint = 0.3" in locked
    assert f"{full.nq}/{full.nv} -> {full.nq - 1}/{full.nv - 1}" in locked
    assert "0.5 kg on wrist_2_link" in _line(text, "payloads:")
    assert "elbow_joint 0.05" in _line(text, "armature")
    assert "-3.7" in _line(text, "gravity")
    elements = _line(text, "force elements:")
    for name in ("force:push", "friction:elbow_joint", "spring:elbow_joint"):
        assert name in elements
    assert "pin (3 rows)" in _line(text, "constraints:")


def test_describe_of_a_bare_scene_says_nothing_was_added(robot: Callable[..., ms.Robot]) -> None:
    full = robot("ur5")
    text = make_scene(robot={"source": "ur5"}).describe()
    assert f"nq/nv {full.nq}/{full.nv} (nothing locked)" in text
    assert "force elements: none" in _line(text, "force elements:")
    assert "constraints: none" in _line(text, "constraints:")
    assert "payloads" not in text and "armature" not in text


# ---- shipped scenes that only modify the model ---------------------------------------------------------
@pytest.fixture(scope="module")
def talos_scene() -> Scene:
    """talos_upper_body, built once per module (talos is the largest catalog model)."""
    return load_scene("talos_upper_body")


def _shipped_tables(name: str) -> dict[str, Any]:
    """The shipped scene file's tables, read with tomllib (not through the scene parser)."""
    return tomllib.loads(shipped_scenes()[name].read_text())


@pytest.mark.parametrize("name", ["panda_payload", "talos_upper_body"])
def test_shipped_scene_maps_its_configuration_to_the_full_robot(
    robot: Callable[..., ms.Robot], request: pytest.FixtureRequest, name: str
) -> None:
    """full_configuration(q) puts the kept joints' entries where the full robot has them and the lock values (as
    the file writes them) in the locked joints; the reduced model's M and g are the full model's kept rows there
    (a fixed base's position does not enter them); the [initial] table lands on the named joints."""
    tables = _shipped_tables(name)
    scene = request.getfixturevalue("talos_scene") if name == "talos_upper_body" else load_scene(name)
    full = robot(tables["robot"]["source"], False)
    lock = tables["lock"]
    assert (scene.full_nq, scene.full_nv) == (full.nq, full.nv)
    assert (scene.nq, scene.nv) == (full.nq - len(lock), full.nv - len(lock))
    rng = np.random.default_rng(41)
    for _ in range(2):
        q_full, v_full, kept_q, kept_v = _locked_full_state(full, lock, rng)
        q = q_full[kept_q]
        assert np.array_equal(scene.full_configuration(q), q_full)
        if not tables.get("payload") and not tables.get("joints"):  # panda_payload's model: the next test
            M, _, g = _terms(full.model, q_full, v_full)
            _close(scene.mass_matrix(q), M[np.ix_(kept_v, kept_v)], "M")
            _close(scene.gravity(q), g[kept_v], "g")
    initial = tables["initial"]["q"]
    start = scene.full_configuration(scene.q0)
    if isinstance(initial, dict):
        for joint_name, value in initial.items():
            assert start[_joint_slices(full.model, joint_name)[0].start] == value
    else:
        np.testing.assert_array_equal(scene.q0, initial)


def test_panda_payload_scene_equals_its_urdf_with_payload_armature_and_locks(
    robot: Callable[..., ms.Robot], tmp_path: Path
) -> None:
    """The shipped panda_payload: M = (URDF with the payload link)'s kept rows at the lock configuration +
    diag(armature), g the same rows; total mass + 2 kg (the fingers stay moving bodies, merged into the hand)."""
    tables = _shipped_tables("panda_payload")
    scene = load_scene("panda_payload")
    full = robot("panda", False)
    (payload,) = tables["payload"]
    reference = ms.load_robot(
        _write_urdf_with_payload(full.source["urdf_path"], payload["frame"], payload, tmp_path / "panda_payload.urdf")
    )
    lock = tables["lock"]
    armature = np.diag([tables["joints"][d]["armature"] for d in scene.dof_names])
    rng = np.random.default_rng(43)
    for _ in range(3):
        q_full, v_full, kept_q, kept_v = _locked_full_state(reference, lock, rng)
        q, v = q_full[kept_q], v_full[kept_v]
        M, nle, g = _terms(reference.model, q_full, v_full)
        _close(scene.mass_matrix(q), M[np.ix_(kept_v, kept_v)] + armature, "M")
        _close(scene.nonlinear_effects(q, v), nle[kept_v], "C v + g")
        _close(scene.gravity(q), g[kept_v], "g")
    assert scene.total_mass == pytest.approx(full.total_mass + payload["mass"], rel=1e-14)
