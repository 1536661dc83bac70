"""The Robot API boundary: argument checks, names and sizes, random configurations, damping and limits.

Expected sizes, names, limits and damping are read from the URDF text here (lxml), not from the package.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
from conftest import joint, link, urdf
from lxml import etree

import multibody_sim as ms
from multibody_sim.catalog import catalog_urdf

MOVABLE = ("revolute", "continuous", "prismatic")


@dataclass(frozen=True)
class UrdfJoint:
    """One <joint> as the URDF text states it."""

    name: str
    type: str
    parent: str
    child: str
    lower: float | None  # None where the URDF gives no <limit lower>
    upper: float | None
    effort: float | None
    damping: float


def _urdf_joints(name: str) -> list[UrdfJoint]:
    path, _ = catalog_urdf(ms.CATALOG[name])
    joints = []
    for element in etree.parse(str(path)).getroot().findall("joint"):
        limit, dynamics = element.find("limit"), element.find("dynamics")

        def attribute(el: etree._Element | None, key: str) -> float | None:
            return float(el.get(key)) if el is not None and el.get(key) is not None else None

        joints.append(
            UrdfJoint(
                name=element.get("name"),
                type=element.get("type"),
                parent=element.find("parent").get("link"),
                child=element.find("child").get("link"),
                lower=attribute(limit, "lower"),
                upper=attribute(limit, "upper"),
                effort=attribute(limit, "effort"),
                damping=attribute(dynamics, "damping") or 0.0,
            )
        )
    return joints


def _movable(name: str) -> dict[str, UrdfJoint]:
    return {j.name: j for j in _urdf_joints(name) if j.type in MOVABLE}


def _raises(robot_call: Callable[[], object], message: str) -> None:
    """The call raises InvalidArgumentError, which is also a ValueError, with exactly this message."""
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$") as info:
        robot_call()
    assert isinstance(info.value, ms.InvalidArgumentError)
    assert isinstance(info.value, ms.MultibodySimError)


# ---- argument checks ---------------------------------------------------------------------------------------
def test_wrong_shapes_name_the_argument(robot: Callable[..., ms.Robot]) -> None:
    ur5 = robot("ur5")
    q, v = ur5.neutral(), np.zeros(6)
    _raises(lambda: ur5.mass_matrix(np.zeros(5)), "q must have shape (6,), got (5,)")
    _raises(lambda: ur5.gravity(np.zeros((1, 6))), "q must have shape (6,), got (1, 6)")
    _raises(lambda: ur5.gravity(0.0), "q must have shape (6,), got ()")
    _raises(lambda: ur5.coriolis_matrix(q, np.zeros(7)), "v must have shape (6,), got (7,)")
    _raises(lambda: ur5.forward_dynamics(q, v, np.zeros(3)), "tau must have shape (6,), got (3,)")
    _raises(lambda: ur5.inverse_dynamics(q, v, np.zeros(9)), "a must have shape (6,), got (9,)")
    _raises(lambda: ur5.integrate(q, np.zeros(4)), "dv must have shape (6,), got (4,)")
    _raises(lambda: ur5.difference(q, np.zeros(2)), "q1 must have shape (6,), got (2,)")
    _raises(lambda: ur5.difference(np.zeros(2), q), "q0 must have shape (6,), got (2,)")
    _raises(lambda: ur5.kinetic_energy(q, []), "v must have shape (6,), got (0,)")


def test_floating_base_shapes_are_nq_and_nv(robot: Callable[..., ms.Robot]) -> None:
    solo = robot("solo12")  # nq = 19 (position + quaternion), nv = 18
    q = solo.neutral()
    _raises(lambda: solo.mass_matrix(q[:18]), "q must have shape (19,), got (18,)")
    _raises(lambda: solo.coriolis_matrix(q, np.zeros(19)), "v must have shape (18,), got (19,)")
    _raises(lambda: solo.forward_dynamics(q, np.zeros(18), np.zeros(12)), "tau must have shape (18,), got (12,)")


def test_non_numbers_are_refused(robot: Callable[..., ms.Robot]) -> None:
    ur5 = robot("ur5")
    _raises(lambda: ur5.gravity("zero"), "q must be an array of 6 real numbers, got str")
    _raises(
        lambda: ur5.gravity([1.0, [2.0, 3.0], 4.0, 5.0, 6.0, 7.0]),
        "q must be an array of 6 real numbers, got list",
    )
    _raises(lambda: ur5.kinetic_energy(ur5.neutral(), {"a": 1}), "v must be an array of 6 real numbers, got dict")
    _raises(lambda: ur5.gravity(["0.1"] * 6), "q must be an array of 6 real numbers, got list")
    _raises(lambda: ur5.gravity(np.full(6, 0.1 + 2j)), "q must be an array of 6 real numbers, got dtype complex128")


def test_non_finite_entries_are_listed(robot: Callable[..., ms.Robot]) -> None:
    ur5 = robot("ur5")
    q, v = ur5.neutral(), np.zeros(6)
    _raises(
        lambda: ur5.mass_matrix([0, 0, np.nan, 0, 0, 0]),
        "q must be finite, got non-finite entries at indices [2]",
    )
    _raises(
        lambda: ur5.coriolis_matrix(q, [np.inf, 0, 0, 0, 0, -np.inf]),
        "v must be finite, got non-finite entries at indices [0, 5]",
    )
    _raises(
        lambda: ur5.forward_dynamics(q, v, [0, 0, 0, 0, np.nan, 0]),
        "tau must be finite, got non-finite entries at indices [4]",
    )
    solo = robot("solo12")
    q = solo.neutral()
    q[6] = np.nan  # the quaternion's w: finiteness is checked before normalization
    _raises(lambda: solo.gravity(q), "q must be finite, got non-finite entries at indices [6]")


@pytest.mark.parametrize("norm", [0.0, 0.5, 1.0 + 1e-4, 2.0])
def test_non_unit_quaternion_is_refused(robot: Callable[..., ms.Robot], norm: float) -> None:
    solo = robot("solo12")
    q = solo.random_configuration(0)
    q[3:7] *= norm
    message = "q is not a valid configuration: its quaternion / (cos, sin) entries must have unit norm"
    _raises(lambda: solo.mass_matrix(q), message)
    _raises(lambda: solo.integrate(q, np.zeros(18)), message)
    _raises(lambda: solo.difference(solo.neutral(), q), message.replace("q ", "q1 ", 1))


def test_non_unit_cos_sin_pair_is_refused(robot: Callable[..., ms.Robot]) -> None:
    pendulum = robot("double_pendulum_continuous")  # q = (cos q1, sin q1, cos q2, sin q2)
    _raises(
        lambda: pendulum.gravity([1.0, 0.0, 2.0, 0.0]),
        "q is not a valid configuration: its quaternion / (cos, sin) entries must have unit norm",
    )
    assert pendulum.gravity([0.0, 1.0, math.cos(0.3), math.sin(0.3)]).shape == (2,)


def test_unit_quaternion_within_round_off_is_accepted(robot: Callable[..., ms.Robot]) -> None:
    solo = robot("solo12")
    q = solo.random_configuration(1)
    q[3:7] *= 1.0 + 1e-10  # what integrating a quaternion in float64 leaves behind
    assert solo.mass_matrix(q).shape == (18, 18)


def test_floating_base_torque_must_be_zero(robot: Callable[..., ms.Robot]) -> None:
    solo = robot("solo12")
    q, v = solo.neutral(), np.zeros(18)
    tau = np.zeros(18)
    tau[2] = 3.5
    _raises(
        lambda: solo.forward_dynamics(q, v, tau),
        "tau[0:6] acts on the unactuated floating base and must be zero, got [0.0, 0.0, 3.5, 0.0, 0.0, 0.0]",
    )
    tau[2], tau[6:] = 0.0, 1.0  # joint torques are fine
    assert np.all(np.isfinite(solo.forward_dynamics(q, v, tau)))


def test_fixed_base_accepts_any_finite_torque_and_plain_sequences(robot: Callable[..., ms.Robot]) -> None:
    ur5 = robot("ur5")
    a_list = ur5.forward_dynamics([0, 0.1, 0.2, 0, 0, 0], (1, 2, 3, 4, 5, 6), [10.0] * 6)
    a_array = ur5.forward_dynamics(np.array([0, 0.1, 0.2, 0, 0, 0]), np.arange(1.0, 7.0), np.full(6, 10.0))
    np.testing.assert_array_equal(a_list, a_array)


# ---- sizes and names ---------------------------------------------------------------------------------------
SIZED_ROBOTS = [
    ("pendulum", False),
    ("double_pendulum", False),
    ("double_pendulum_continuous", False),
    ("ur5", False),
    ("ur5", True),
    ("panda", False),
    ("z1", False),
    ("solo12", True),
    ("solo12", False),
    ("talos", True),
    ("free_body", True),
]


@pytest.mark.parametrize(("name", "floating_base"), SIZED_ROBOTS)
def test_sizes_follow_the_urdf_joint_types(robot: Callable[..., ms.Robot], name: str, floating_base: bool) -> None:
    """nv = one per revolute/continuous/prismatic joint (+6 for a free-flyer); nq adds one per continuous
    joint (stored as cos, sin) and one for the free-flyer's quaternion. Panda's <mimic> finger counts."""
    joints = _urdf_joints(name)
    count = {kind: sum(j.type == kind for j in joints) for kind in MOVABLE}
    nv = count["revolute"] + count["prismatic"] + count["continuous"] + (6 if floating_base else 0)
    nq = nv + count["continuous"] + (1 if floating_base else 0)
    r = robot(name, floating_base=floating_base)
    assert (r.nq, r.nv, r.floating_base) == (nq, nv, floating_base)
    assert r.model.nq == nq and r.model.nv == nv
    assert len(r.dof_names) == nv and len(set(r.dof_names)) == nv
    assert len(r.joint_names) == len(_movable(name)) + (1 if floating_base else 0)
    assert r.neutral().shape == (nq,)


def test_catalog_bases(robot: Callable[..., ms.Robot]) -> None:
    """The natural base: arms and pendulums are welded, legged robots, humanoids and the free body float."""
    assert not any(robot(n).floating_base for n in ("pendulum", "double_pendulum", "ur5", "panda", "z1"))
    assert all(robot(n).floating_base for n in ("solo12", "talos", "free_body"))


@pytest.mark.parametrize(("name", "floating_base"), SIZED_ROBOTS)
def test_joint_and_dof_names(robot: Callable[..., ms.Robot], name: str, floating_base: bool) -> None:
    r = robot(name, floating_base=floating_base)
    urdf_joints = _movable(name)
    names = r.joint_names
    if floating_base:
        root = names[0]
        assert root not in urdf_joints  # the free-flyer Pinocchio adds, first
        assert r.dof_names[:6] == [f"{root}.{c}" for c in ("vx", "vy", "vz", "wx", "wy", "wz")]
        names = names[1:]
    assert sorted(names) == sorted(urdf_joints)
    # Every joint here has one velocity, so the remaining dof names are the joint names in order.
    assert r.dof_names[6 if floating_base else 0 :] == names
    # Pinocchio's order is a depth-first walk of the tree: a joint comes after the movable joints above it.
    by_child = {j.child: j for j in _urdf_joints(name)}
    position = {n: i for i, n in enumerate(names)}
    for joint_name in names:
        above = by_child.get(urdf_joints[joint_name].parent)
        while above is not None and above.type not in MOVABLE:
            above = by_child.get(above.parent)
        if above is not None:
            assert position[above.name] < position[joint_name]


@pytest.mark.parametrize("name", ["ur5", "panda", "z1", "double_pendulum"])
def test_serial_chain_names_are_in_urdf_order(robot: Callable[..., ms.Robot], name: str) -> None:
    """Along a serial chain the depth-first order is the chain's order from the base; where the chain forks
    (panda's hand carries two fingers) only the set of the remaining joints is fixed."""
    joints = _urdf_joints(name)
    by_parent: dict[str, list[UrdfJoint]] = {}
    for j in joints:
        by_parent.setdefault(j.parent, []).append(j)
    (link_name,) = {j.parent for j in joints} - {j.child for j in joints}
    chain: list[str] = []
    while len(by_parent.get(link_name, [])) == 1:
        (j,) = by_parent[link_name]
        chain += [j.name] if j.type in MOVABLE else []
        link_name = j.child
    names = robot(name).joint_names
    assert names[: len(chain)] == chain
    assert sorted(names[len(chain) :]) == sorted(set(_movable(name)) - set(chain))


# ---- random configurations ---------------------------------------------------------------------------------
RANDOM_ROBOTS = [
    "ur5",
    "panda",
    "z1",
    "double_pendulum",
    "double_pendulum_continuous",
    "solo12",
    "talos",
    "free_body",
]


def _coordinate_kinds(r: ms.Robot) -> dict[str, list[int]]:
    """Configuration indices by kind, from the joint sizes (nq, nv) Pinocchio reports."""
    kinds: dict[str, list[int]] = {"scalar": [], "cos_sin": [], "base_position": [], "quaternion": []}
    for j in r.model.joints[1:]:
        i = j.idx_q
        if (j.nq, j.nv) == (1, 1):
            kinds["scalar"].append(i)
        elif (j.nq, j.nv) == (2, 1):
            kinds["cos_sin"].append(i)
        elif (j.nq, j.nv) == (7, 6):
            kinds["base_position"] += [i, i + 1, i + 2]
            kinds["quaternion"].append(i + 3)
        else:
            raise AssertionError(f"unexpected joint {j.shortname()} in a catalog robot")
    return kinds


@pytest.mark.parametrize("name", RANDOM_ROBOTS)
def test_random_configuration_respects_limits_and_manifold(robot: Callable[..., ms.Robot], name: str) -> None:
    r = robot(name)
    urdf_joints = _movable(name)
    rng = np.random.default_rng(20)
    Q = np.array([r.random_configuration(rng) for _ in range(300)])
    kinds = _coordinate_kinds(r)
    for jid in range(1, r.model.njoints):
        j, joint_name = r.model.joints[jid], r.model.names[jid]
        if (j.nq, j.nv) != (1, 1):
            continue
        values = Q[:, j.idx_q]
        spec = urdf_joints[joint_name]
        limited = spec.type != "continuous" and spec.lower is not None and spec.lower < spec.upper
        lo, hi = (spec.lower, spec.upper) if limited else (-math.pi, math.pi)
        assert lo <= values.min() and values.max() <= hi, joint_name
        # Uniform over the range: 300 samples leave a gap above 10 % at either end with probability < 1e-13.
        assert values.min() < lo + 0.1 * (hi - lo) and values.max() > hi - 0.1 * (hi - lo), joint_name
    for i in kinds["cos_sin"]:
        np.testing.assert_allclose(np.hypot(Q[:, i], Q[:, i + 1]), 1.0, rtol=0, atol=1e-15)
    for i in kinds["quaternion"]:
        np.testing.assert_allclose(np.linalg.norm(Q[:, i : i + 4], axis=1), 1.0, rtol=0, atol=1e-15)
    if kinds["base_position"]:
        base = Q[:, kinds["base_position"]]
        assert np.all(np.abs(base) <= 1.0) and base.min() < -0.9 and base.max() > 0.9
    for q in Q[:5]:
        r.check_q(q)  # valid configurations for every dynamics call


def test_double_pendulum_zero_limits_mean_full_turns(robot: Callable[..., ms.Robot]) -> None:
    """Its URDF declares lower = upper = 0 (no limit), so samples span (−π, π) rather than sitting at 0."""
    assert {(j.lower, j.upper) for j in _movable("double_pendulum").values()} == {(0.0, 0.0)}
    pendulum = robot("double_pendulum")
    Q = np.array([pendulum.random_configuration(seed) for seed in range(100)])
    assert np.all(np.abs(Q) <= math.pi)
    assert Q.min() < -2.5 and Q.max() > 2.5  # uniform: P(max < 2.5) = (0.898)^100 ≈ 2e-5


def test_random_quaternion_is_uniform_on_the_sphere(robot: Callable[..., ms.Robot]) -> None:
    """Uniform on S³: E[q qᵀ] = I/4 (each entry of q² has standard deviation 1/4, so 1/(4√N) for the mean)."""
    body = robot("free_body")
    rng = np.random.default_rng(21)
    quaternions = np.array([body.random_configuration(rng)[3:7] for _ in range(4000)])
    second_moment = quaternions.T @ quaternions / len(quaternions)
    np.testing.assert_allclose(second_moment, np.eye(4) / 4, rtol=0, atol=6 / (4 * math.sqrt(4000)))
    assert np.abs(quaternions.mean(axis=0)).max() < 6 * 0.5 / math.sqrt(4000)  # both signs of each entry


def test_random_configuration_is_reproducible(robot: Callable[..., ms.Robot]) -> None:
    talos = robot("talos")
    np.testing.assert_array_equal(talos.random_configuration(7), talos.random_configuration(7))
    np.testing.assert_array_equal(
        talos.random_configuration(np.random.default_rng(7)),
        talos.random_configuration(np.random.default_rng(7)),
    )
    assert not np.array_equal(talos.random_configuration(7), talos.random_configuration(8))
    rng = np.random.default_rng(7)
    first, second = talos.random_configuration(rng), talos.random_configuration(rng)
    assert not np.array_equal(first, second)  # a generator advances between calls


# ---- damping -----------------------------------------------------------------------------------------------
def _urdf_damping(r: ms.Robot, name: str) -> np.ndarray:
    """The URDF's <dynamics damping> in r's velocity order (0 for the free-flyer's six)."""
    joints = _movable(name)
    return np.array([joints[d].damping if d in joints else 0.0 for d in r.dof_names])


def test_double_pendulum_damping_is_read_or_ignored(robot: Callable[..., ms.Robot]) -> None:
    assert [j.damping for j in _movable("double_pendulum").values()] == [0.05, 0.05]
    np.testing.assert_array_equal(robot("double_pendulum", damping=True).damping, [0.05, 0.05])
    np.testing.assert_array_equal(robot("double_pendulum", damping=False).damping, [0.0, 0.0])


@pytest.mark.parametrize(("name", "floating_base"), [("z1", False), ("panda", False), ("talos", True)])
def test_damping_matches_urdf(robot: Callable[..., ms.Robot], name: str, floating_base: bool) -> None:
    damped = robot(name, floating_base=floating_base, damping=True)
    expected = _urdf_damping(damped, name)
    assert np.count_nonzero(expected) > 0  # these URDFs do declare damping
    np.testing.assert_array_equal(damped.damping, expected)
    np.testing.assert_array_equal(robot(name, floating_base=floating_base, damping=False).damping, np.zeros(damped.nv))


@pytest.mark.parametrize(("name", "floating_base"), [("z1", False), ("talos", True), ("double_pendulum", False)])
def test_damping_acts_as_minus_d_v(robot: Callable[..., ms.Robot], name: str, floating_base: bool) -> None:
    """The damped robot under tau accelerates like the undamped one under tau − D v (D from the URDF)."""
    damped = robot(name, floating_base=floating_base, damping=True)
    free = robot(name, floating_base=floating_base, damping=False)
    D = _urdf_damping(damped, name)
    rng = np.random.default_rng(22)
    q, v = damped.random_configuration(rng), rng.normal(size=damped.nv)
    tau = rng.normal(size=damped.nv)
    tau[: 6 if floating_base else 0] = 0.0
    a = damped.forward_dynamics(q, v, tau)
    np.testing.assert_allclose(a, free.forward_dynamics(q, v, tau - D * v), rtol=1e-12, atol=1e-12 * np.abs(a).max())
    np.testing.assert_allclose(damped.inverse_dynamics(q, v, a), free.inverse_dynamics(q, v, a) + D * v, rtol=1e-12)
    # The energy ledger carries the dissipation only when damping is on: power v·(D v) ≥ 0.
    assert damped.ledger_elements == [("joint_torques", "work"), ("joint_damping", "dissipated")]
    assert free.ledger_elements == [("joint_torques", "work")]
    np.testing.assert_allclose(damped.ledger_power(q, v, tau), [tau @ v, v @ (D * v)], rtol=1e-14)


# ---- position and effort limits ----------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["ur5", "panda", "z1", "talos"])
def test_finite_position_limits_are_read(robot: Callable[..., ms.Robot], name: str) -> None:
    r = robot(name)
    joints = _movable(name)
    lower, upper = np.full(r.nq, -np.inf), np.full(r.nq, np.inf)
    for jid in range(1, r.model.njoints):
        j, spec = r.model.joints[jid], joints.get(r.model.names[jid])
        if spec is not None and spec.lower is not None and spec.lower < spec.upper:
            lower[j.idx_q], upper[j.idx_q] = spec.lower, spec.upper
    assert np.isfinite(lower).sum() == len(joints)  # every joint of these robots is limited
    np.testing.assert_array_equal(r.lower_limit, lower)
    np.testing.assert_array_equal(r.upper_limit, upper)


def test_z1_one_sided_zero_limits_are_real_ranges(robot: Callable[..., ms.Robot]) -> None:
    """A zero bound with a different other bound (z1's joint2: [0, 2.967]) is a limit; only lower = upper = 0
    means none."""
    z1 = robot("z1")
    i = z1.joint_names.index("joint2")
    assert (z1.lower_limit[i], z1.upper_limit[i]) == (0.0, _movable("z1")["joint2"].upper)


@pytest.mark.parametrize("name", ["double_pendulum", "double_pendulum_continuous", "free_body"])
def test_unlimited_coordinates_are_infinite(robot: Callable[..., ms.Robot], name: str) -> None:
    r = robot(name)
    assert np.all(r.lower_limit == -np.inf) and np.all(r.upper_limit == np.inf)


def test_base_coordinates_of_a_floating_robot_are_unlimited(robot: Callable[..., ms.Robot]) -> None:
    solo = robot("solo12")
    assert np.all(np.isinf(solo.lower_limit[:7])) and np.all(np.isinf(solo.upper_limit[:7]))
    assert np.all(np.isfinite(solo.lower_limit[7:]))


def test_limits_from_a_urdf_written_in_code(write_urdf: Callable[..., Path]) -> None:
    text = urdf(
        link("base"),
        link("a"),
        link("b"),
        link("c"),
        joint("limited", "base", "a", limits='lower="-1" upper="2" effort="7" velocity="1"'),
        joint("zeros", "a", "b", limits='lower="0" upper="0" effort="0" velocity="0"'),
        joint(
            "slider",
            "b",
            "c",
            kind="prismatic",
            axis="1 0 0",
            limits='lower="-0.1" upper="0.3" effort="5" velocity="1"',
        ),
    )
    r = ms.load_robot(write_urdf(text))
    assert r.joint_names == ["limited", "zeros", "slider"]
    np.testing.assert_array_equal(r.lower_limit, [-1.0, -np.inf, -0.1])
    np.testing.assert_array_equal(r.upper_limit, [2.0, np.inf, 0.3])
    np.testing.assert_array_equal(r.effort_limit, [7.0, np.inf, 5.0])  # effort 0 means "no limit" too
    np.testing.assert_array_equal(r.damping, [0.0, 0.0, 0.0])


def test_effort_limits_of_catalog_robots(robot: Callable[..., ms.Robot]) -> None:
    ur5 = robot("ur5")
    joints = _movable("ur5")
    np.testing.assert_array_equal(ur5.effort_limit, [joints[n].effort for n in ur5.joint_names])
    np.testing.assert_array_equal(robot("double_pendulum").effort_limit, [np.inf, np.inf])  # declared 0
    assert np.all(np.isinf(robot("solo12").effort_limit[:6]))  # nothing actuates the base


# ---- limit_excess ------------------------------------------------------------------------------------------
def test_limit_excess_on_crafted_configurations(robot: Callable[..., ms.Robot]) -> None:
    ur5 = robot("ur5")
    joints = _movable("ur5")
    elbow = ur5.joint_names.index("elbow_joint")
    pan = ur5.joint_names.index("shoulder_pan_joint")
    elbow_upper, pan_lower = joints["elbow_joint"].upper, joints["shoulder_pan_joint"].lower
    Q = np.zeros((4, 6))
    Q[1, elbow] = elbow_upper + 0.3  # above the upper limit
    Q[2, pan] = pan_lower - 0.2  # below the lower limit
    Q[3, elbow], Q[3, pan] = elbow_upper, pan_lower  # exactly on the limits: inside
    expected = np.zeros((4, 6))
    expected[1, elbow], expected[2, pan] = 0.3, 0.2
    np.testing.assert_allclose(ur5.limit_excess(Q), expected, rtol=0, atol=1e-15)


def test_limit_excess_of_panda_neutral_pose(robot: Callable[..., ms.Robot]) -> None:
    """Panda's joint4 range is [−3.0718, −0.0698]: the all-zero configuration is outside it by 0.0698."""
    panda = robot("panda")
    i = panda.joint_names.index("panda_joint4")
    excess = panda.limit_excess(np.zeros((1, panda.nq)))
    expected = np.zeros((1, panda.nq))
    expected[0, i] = -_movable("panda")["panda_joint4"].upper
    np.testing.assert_allclose(excess, expected, rtol=0, atol=1e-15)


def test_limit_excess_ignores_unlimited_coordinates(robot: Callable[..., ms.Robot]) -> None:
    pendulum = robot("double_pendulum")
    assert not pendulum.limit_excess(np.array([[50.0, -50.0], [1e6, 0.0]])).any()
    solo = robot("solo12")
    Q = np.tile(solo.random_configuration(3), (2, 1))
    Q[1, :3] = 1e3  # far away, and the quaternion's entries are not limits either
    first = _movable("solo12")[solo.joint_names[1]]  # q[7] is the first leg joint's angle
    Q[1, 7] = first.upper + 0.5
    excess = solo.limit_excess(Q)
    expected = np.zeros_like(Q)
    expected[1, 7] = 0.5
    np.testing.assert_allclose(excess, expected, rtol=0, atol=1e-12)


def test_limit_excess_of_one_configuration_has_its_shape(robot: Callable[..., ms.Robot]) -> None:
    ur5 = robot("ur5")
    assert ur5.limit_excess(np.zeros(6)).shape == (6,)


def test_limit_excess_ignores_round_off_at_a_limit(robot: Callable[..., ms.Robot]) -> None:
    """A coordinate a few ulps past its limit is round-off, not a violation; a real excess still is."""
    panda = robot("panda")
    finger = panda.joint_names.index("panda_finger_joint1")
    elbow = panda.joint_names.index("panda_joint4")
    lower, upper = panda.lower_limit, panda.upper_limit
    q = (lower + upper) / 2
    Q = np.tile(q, (6, 1))
    Q[0, finger] = -2.6e-19  # what a run resting on the finger's 0 m limit reports without the tolerance
    Q[1, finger] = np.nextafter(np.nextafter(lower[finger], -1.0), -1.0)  # two ulps below 0
    Q[2, elbow] = upper[elbow] + 2 * np.spacing(upper[elbow])  # two ulps above -0.0698 rad
    Q[3, elbow] = lower[elbow] - 4 * np.finfo(float).eps * abs(lower[elbow])  # a few ulps of a -3.07 rad limit
    Q[4, finger] = -1e-9  # a real excess, however small
    Q[5, elbow] = upper[elbow] + 1e-12
    excess = panda.limit_excess(Q)
    assert not excess[:4].any()
    assert excess[4, finger] == 1e-9 and np.count_nonzero(excess[4]) == 1
    assert excess[5, elbow] == pytest.approx(1e-12, rel=1e-3) and np.count_nonzero(excess[5]) == 1
    # The tolerance scales with the limit: 8 eps of max(|lower|, |upper|, 1).
    assert panda.limit_tolerance[finger] == 8 * np.finfo(float).eps
    assert panda.limit_tolerance[elbow] == 8 * np.finfo(float).eps * abs(lower[elbow])


def test_panda_resting_on_its_finger_limits_reports_no_violation(robot: Callable[..., ms.Robot]) -> None:
    """Held still at q = 0 (fingers closed on their 0 m limit), panda's fingers drift by round-off only."""
    panda = robot("panda")
    q = np.zeros(panda.nq)
    hold = ms.GravityCompensation(panda)
    traj = ms.simulate(panda, q, np.zeros(panda.nv), duration=0.05, dt=1e-3, controller=hold)
    fingers = [panda.joint_names.index(n) for n in ("panda_finger_joint1", "panda_finger_joint2")]
    drift = np.abs(traj.q[:, fingers]).max()
    assert 0 < drift < 1e-15  # the fingers do move, by round-off
    # Joint 4 at 0 is outside its range [-3.07, -0.07] rad on every sample: those are the only violations.
    assert traj.limit_violations.count == len(traj.t)
    assert traj.limit_violations.worst_joint == "panda_joint4"
