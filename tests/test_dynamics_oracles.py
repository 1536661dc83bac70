"""Physics oracles for Robot's dynamics: a SymPy Lagrangian, ABA against CRBA + RNEA, the skew symmetry of
Ṁ − 2C, energy identities and the exact (elliptic-integral) period of a pendulum.

Every expected value here comes from somewhere other than the code under test: equations of motion derived
symbolically from the URDF's own numbers, a different Pinocchio algorithm, finite differences or closed
forms.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest
import sympy as sp
from lxml import etree
from scipy.interpolate import CubicHermiteSpline
from scipy.special import ellipk
from sympy.physics import mechanics as me

import multibody_sim as ms
from multibody_sim.catalog import catalog_urdf

STANDARD_GRAVITY = 9.81  # [m/s²] Pinocchio's default, along world −z (checked against model.gravity below)

# Matching to 1e-10 of the quantity's size leaves ~1e5 of head room over float64 round-off (measured 1e-16 …
# 1e-15) while a wrong inertia, offset or sign changes the terms at the 1e-3 level or more.
ORACLE_RTOL = 1e-10


# ---- URDF reading (the oracle's own, independent of the package's loader) ----------------------------------
def _urdf_root(name: str) -> etree._Element:
    path, _ = catalog_urdf(ms.CATALOG[name])
    return etree.parse(str(path)).getroot()


def _floats(element: etree._Element | None, attribute: str, default: str) -> list[float]:
    text = element.get(attribute) if element is not None else None
    return [float(x) for x in (text if text is not None else default).split()]


def _chain(root: etree._Element) -> list[etree._Element]:
    """The joints of a serial chain from its root link outwards."""
    joints = root.findall("joint")
    children = {j.find("child").get("link") for j in joints}
    (link,) = {lk.get("name") for lk in root.findall("link")} - children
    chain = []
    while True:
        following = [j for j in joints if j.find("parent").get("link") == link]
        if not following:
            return chain
        (joint,) = following  # a serial chain: one joint leaves each link
        chain.append(joint)
        link = joint.find("child").get("link")


def _joint_damping(root: etree._Element) -> np.ndarray:
    """<dynamics damping> of each joint of the chain, 0 where absent [N·m·s/rad]."""
    return np.array([_floats(j.find("dynamics"), "damping", "0")[0] for j in _chain(root)])


# ---- SymPy oracle ------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class LagrangeOracle:
    """Numerical functions of the equations of motion M(q) q̈ + c(q, q̇) + g(q) = τ derived by SymPy."""

    mass_matrix: Callable[[np.ndarray], np.ndarray]
    coriolis: Callable[[np.ndarray, np.ndarray], np.ndarray]  # the velocity-product vector C(q, q̇) q̇
    gravity: Callable[[np.ndarray], np.ndarray]
    kinetic_energy: Callable[[np.ndarray, np.ndarray], float]
    potential_energy: Callable[[np.ndarray], float]


def _vector(components: list[float], frame: me.ReferenceFrame) -> me.Vector:
    return sum((sp.Float(c) * e for c, e in zip(components, (frame.x, frame.y, frame.z), strict=True)), me.Vector(0))


def _urdf_rpy_frame(name: str, parent: me.ReferenceFrame, rpy: list[float]) -> me.ReferenceFrame:
    """URDF's rpy is R = Rz(yaw) Ry(pitch) Rx(roll): body-fixed Z, Y, X rotations by (yaw, pitch, roll)."""
    frame = me.ReferenceFrame(name)
    frame.orient_body_fixed(parent, tuple(sp.Float(a) for a in reversed(rpy)), "ZYX")
    return frame


def lagrange_oracle(root: etree._Element, *, rotational_inertia: bool = True) -> LagrangeOracle:
    """Equations of motion of a serial chain of revolute joints from the URDF's numbers, by LagrangesMethod.

    Each link is a rigid body with the URDF's mass, centre of mass and full 3×3 inertia tensor (about the
    centre of mass, in the inertial frame); rotational_inertia=False keeps only point masses, to show that
    the comparison can tell the difference. The root link is welded to the world at the origin.
    """
    chain = _chain(root)
    links = {lk.get("name"): lk for lk in root.findall("link")}
    world, origin = me.ReferenceFrame("N"), me.Point("O")
    origin.set_vel(world, 0)
    angles = me.dynamicsymbols(f"q1:{len(chain) + 1}")
    frame, point, bodies = world, origin, []
    for k, (joint, angle) in enumerate(zip(chain, angles, strict=True)):
        assert joint.get("type") in ("revolute", "continuous"), "this oracle handles hinges only"
        placement = joint.find("origin")
        joint_point = point.locatenew(f"P{k}", _vector(_floats(placement, "xyz", "0 0 0"), frame))
        joint_frame = _urdf_rpy_frame(f"J{k}", frame, _floats(placement, "rpy", "0 0 0"))
        link_frame = me.ReferenceFrame(f"L{k}")
        link_frame.orient_axis(joint_frame, _vector(_floats(joint.find("axis"), "xyz", "1 0 0"), joint_frame), angle)

        inertial = links[joint.find("child").get("link")].find("inertial")
        mass = float(inertial.find("mass").get("value"))
        com_placement = inertial.find("origin")
        com = joint_point.locatenew(f"G{k}", _vector(_floats(com_placement, "xyz", "0 0 0"), link_frame))
        com.set_vel(world, com.pos_from(origin).dt(world))
        inertial_frame = _urdf_rpy_frame(f"I{k}", link_frame, _floats(com_placement, "rpy", "0 0 0"))
        element = inertial.find("inertia")
        ixx, iyy, izz, ixy, iyz, ixz = (float(element.get(a)) for a in ("ixx", "iyy", "izz", "ixy", "iyz", "ixz"))
        scale = 1.0 if rotational_inertia else 0.0
        # sympy's inertia() takes the tensor's entries, as URDF does (products of inertia with their sign).
        dyadic = scale * me.inertia(inertial_frame, ixx, iyy, izz, ixy, iyz, ixz)
        body = me.RigidBody(f"B{k}", com, link_frame, mass, (dyadic, com))
        body.potential_energy = mass * STANDARD_GRAVITY * com.pos_from(origin).dot(world.z)
        bodies.append(body)
        frame, point = link_frame, joint_point

    method = me.LagrangesMethod(me.Lagrangian(world, *bodies), angles)
    method.form_lagranges_equations()
    q = sp.symbols(f"q1:{len(chain) + 1}")
    v = sp.symbols(f"v1:{len(chain) + 1}")
    plain = {**{a.diff(): s for a, s in zip(angles, v, strict=True)}, **dict(zip(angles, q, strict=True))}
    forcing = method.forcing.subs(plain)  # M q̈ = forcing = −C q̇ − g (no applied forces)
    gravity = -forcing.subs(dict.fromkeys(v, 0))
    kinetic = sum(b.kinetic_energy(world) for b in bodies).subs(plain)
    potential = sum(b.potential_energy for b in bodies).subs(plain)
    mass_matrix = sp.lambdify([q], method.mass_matrix.subs(plain), cse=True)
    coriolis = sp.lambdify([q, v], -forcing - gravity, cse=True)
    gravity_f = sp.lambdify([q], gravity, cse=True)
    kinetic_f = sp.lambdify([q, v], kinetic, cse=True)
    potential_f = sp.lambdify([q], potential, cse=True)
    return LagrangeOracle(
        mass_matrix=lambda x: np.array(mass_matrix(x), dtype=float),
        coriolis=lambda x, y: np.array(coriolis(x, y), dtype=float).ravel(),
        gravity=lambda x: np.array(gravity_f(x), dtype=float).ravel(),
        kinetic_energy=lambda x, y: float(kinetic_f(x, y)),
        potential_energy=lambda x: float(potential_f(x)),
    )


@pytest.fixture(scope="module")
def double_pendulum_urdf() -> etree._Element:
    return _urdf_root("double_pendulum")


@pytest.fixture(scope="module")
def oracle(double_pendulum_urdf: etree._Element) -> LagrangeOracle:
    return lagrange_oracle(double_pendulum_urdf)


def _double_pendulum_states(n: int, seed: int) -> list[tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """(q, v, tau): the upright and hanging poses, then random angles, rates ~3 rad/s, torques ~0.5 N·m."""
    rng = np.random.default_rng(seed)
    poses = [np.zeros(2), np.array([np.pi, 0.0])] + [rng.uniform(-np.pi, np.pi, 2) for _ in range(n)]
    return [(q, rng.normal(0.0, 3.0, 2), rng.normal(0.0, 0.5, 2)) for q in poses]


def _assert_close(actual: np.ndarray, expected: np.ndarray, what: str, rtol: float = ORACLE_RTOL) -> None:
    """actual == expected to rtol of expected's largest entry (an entry can be 0: g at the upright pose)."""
    scale = float(np.max(np.abs(expected)))
    np.testing.assert_allclose(actual, expected, rtol=0, atol=rtol * scale, err_msg=what)


# ---- double pendulum against SymPy -------------------------------------------------------------------------
def test_gravity_points_down_world_z(robot: Callable[..., ms.Robot]) -> None:
    for name in ("double_pendulum", "pendulum", "solo12"):
        gravity = robot(name).model.gravity
        np.testing.assert_array_equal(gravity.linear, [0.0, 0.0, -STANDARD_GRAVITY])
        np.testing.assert_array_equal(gravity.angular, [0.0, 0.0, 0.0])


def test_double_pendulum_terms_match_sympy_lagrangian(robot: Callable[..., ms.Robot], oracle: LagrangeOracle) -> None:
    pendulum = robot("double_pendulum", damping=False)
    for q, v, _ in _double_pendulum_states(6, seed=1):
        M = oracle.mass_matrix(q)
        _assert_close(pendulum.mass_matrix(q), M, f"M at q={q}")
        _assert_close(pendulum.gravity(q), oracle.gravity(q), f"g at q={q}")
        _assert_close(pendulum.coriolis_matrix(q, v) @ v, oracle.coriolis(q, v), f"C v at q={q}, v={v}")
        _assert_close(pendulum.nonlinear_effects(q, v), oracle.coriolis(q, v) + oracle.gravity(q), f"C v + g at q={q}")
        assert pendulum.kinetic_energy(q, v) == pytest.approx(oracle.kinetic_energy(q, v), rel=ORACLE_RTOL)
        # Both measure height from world z = 0 where the base link is welded: no constant offset expected.
        assert pendulum.potential_energy(q) == pytest.approx(oracle.potential_energy(q), rel=ORACLE_RTOL)


def test_double_pendulum_gravity_is_not_trivially_small(oracle: LagrangeOracle) -> None:
    """The gravity comparison scales its tolerance with g: make sure g is not ~0 at the random states."""
    for q, _, _ in _double_pendulum_states(6, seed=1)[2:]:
        assert np.max(np.abs(oracle.gravity(q))) > 1e-3  # N·m; the links weigh ~0.3 kg at ~0.1 m


def test_double_pendulum_upright_at_zero_hanging_at_pi(robot: Callable[..., ms.Robot], oracle: LagrangeOracle) -> None:
    """q = 0 is upright (the potential maximum), [π, 0] hangs (the minimum): the catalog's documented pose."""
    pendulum = robot("double_pendulum")
    upright, hanging = np.zeros(2), np.array([np.pi, 0.0])
    drop = oracle.potential_energy(upright) - oracle.potential_energy(hanging)
    assert drop > 0.1  # J: ~0.6 kg falling ~0.2 m on average
    assert pendulum.potential_energy(upright) - pendulum.potential_energy(hanging) == pytest.approx(drop, rel=1e-12)


def test_rotational_inertia_is_visible_to_the_comparison(
    robot: Callable[..., ms.Robot], double_pendulum_urdf: etree._Element
) -> None:
    """A point-mass model of the same URDF misses the mass matrix by far more than the tolerance."""
    point_masses = lagrange_oracle(double_pendulum_urdf, rotational_inertia=False)
    pendulum = robot("double_pendulum")
    q = np.array([0.4, -1.1])
    M, M_points = pendulum.mass_matrix(q), point_masses.mass_matrix(q)
    assert np.max(np.abs(M - M_points)) > 1e6 * ORACLE_RTOL * np.max(np.abs(M))


def test_double_pendulum_forward_dynamics_without_damping(
    robot: Callable[..., ms.Robot], oracle: LagrangeOracle
) -> None:
    pendulum = robot("double_pendulum", damping=False)
    np.testing.assert_array_equal(pendulum.damping, [0.0, 0.0])
    for q, v, tau in _double_pendulum_states(4, seed=2):
        expected = np.linalg.solve(oracle.mass_matrix(q), tau - oracle.coriolis(q, v) - oracle.gravity(q))
        _assert_close(pendulum.forward_dynamics(q, v, tau), expected, f"a at q={q}, v={v}, tau={tau}")


def test_double_pendulum_forward_dynamics_with_urdf_damping(
    robot: Callable[..., ms.Robot], oracle: LagrangeOracle, double_pendulum_urdf: etree._Element
) -> None:
    D = _joint_damping(double_pendulum_urdf)
    np.testing.assert_array_equal(D, [0.05, 0.05])  # what the file says; the oracle reads it, not the package
    pendulum = robot("double_pendulum", damping=True)
    for q, v, tau in _double_pendulum_states(4, seed=3):
        M = oracle.mass_matrix(q)
        expected = np.linalg.solve(M, tau - D * v - oracle.coriolis(q, v) - oracle.gravity(q))
        _assert_close(pendulum.forward_dynamics(q, v, tau), expected, f"a at q={q}, v={v}, tau={tau}")
        # The damping term is large enough that ignoring it would fail the comparison above.
        assert np.max(np.abs(np.linalg.solve(M, D * v))) > 1e6 * ORACLE_RTOL * np.max(np.abs(expected))


# ---- ABA against CRBA + RNEA on catalog robots -------------------------------------------------------------
DYNAMICS_ROBOTS = [
    ("ur5", None),
    ("panda", None),
    ("double_pendulum_continuous", None),
    ("solo12", None),
    ("talos", None),
    ("free_body", None),
    ("panda", True),  # an arm on a free-flyer
    ("solo12", False),  # a legged robot welded to the world
]


def _random_state(robot: ms.Robot, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(q, v, tau): a random configuration, v ~ N(0, 1) and tau ~ N(0, 5²), zero on a floating base."""
    q = robot.random_configuration(rng)
    v = rng.normal(size=robot.nv)
    tau = rng.normal(0.0, 5.0, robot.nv)
    if robot.floating_base:
        tau[:6] = 0.0
    return q, v, tau


@pytest.mark.parametrize(("name", "floating_base"), DYNAMICS_ROBOTS)
def test_forward_dynamics_is_crba_rnea_solve(
    robot: Callable[..., ms.Robot], name: str, floating_base: bool | None
) -> None:
    """ABA's v̇ solves M v̇ = τ − D v − (C v + g) with M from CRBA and C v + g from RNEA."""
    r = robot(name, floating_base=floating_base)
    rng = np.random.default_rng(10)
    for _ in range(5):
        q, v, tau = _random_state(r, rng)
        a = r.forward_dynamics(q, v, tau)
        M = r.mass_matrix(q)
        rhs = tau - r.damping * v - r.nonlinear_effects(q, v)
        # Backward error: the residual of M a = rhs against the sizes involved (measured ≤ 5e-16).
        residual = np.linalg.norm(M @ a - rhs)
        assert residual <= 1e-12 * (np.linalg.norm(M, 2) * np.linalg.norm(a) + np.linalg.norm(rhs))
        # Forward error is bounded by cond(M) times the backward error (talos: cond ~1e5).
        expected = np.linalg.solve(M, rhs)
        assert np.linalg.norm(a - expected) <= 1e-13 * np.linalg.cond(M) * np.linalg.norm(expected)


@pytest.mark.parametrize(("name", "floating_base"), DYNAMICS_ROBOTS)
def test_inverse_dynamics_inverts_forward_dynamics(
    robot: Callable[..., ms.Robot], name: str, floating_base: bool | None
) -> None:
    """RNEA(q, v, ABA(q, v, τ)) + D v = τ, including zero wrench on a floating base."""
    r = robot(name, floating_base=floating_base)
    rng = np.random.default_rng(11)
    for _ in range(5):
        q, v, tau = _random_state(r, rng)
        a = r.forward_dynamics(q, v, tau)
        scale = np.linalg.norm(r.mass_matrix(q), 2) * np.linalg.norm(a) + np.linalg.norm(tau)
        assert np.linalg.norm(r.inverse_dynamics(q, v, a) - tau) <= 1e-12 * scale


# ---- Ṁ − 2C is skew-symmetric ------------------------------------------------------------------------------
@pytest.mark.parametrize(("name", "floating_base"), [("panda", None), ("solo12", None), ("talos", None)])
def test_mass_matrix_rate_minus_twice_coriolis_is_skew(
    robot: Callable[..., ms.Robot], name: str, floating_base: bool | None
) -> None:
    r = robot(name, floating_base=floating_base)
    rng = np.random.default_rng(12)
    eps = 1e-6  # central differences: truncation ~eps² ≈ 1e-12, round-off ~1e-16/eps ≈ 1e-10 of |M|·|v|
    for _ in range(3):
        q, v, _ = _random_state(r, rng)
        # Along the manifold: q(±eps) = q ⊕ (±eps v) is the motion with velocity v to first order.
        M_dot = (r.mass_matrix(r.integrate(q, eps * v)) - r.mass_matrix(r.integrate(q, -eps * v))) / (2 * eps)
        C = r.coriolis_matrix(q, v)
        S = M_dot - 2 * C
        scale = np.linalg.norm(r.mass_matrix(q)) * np.linalg.norm(v)
        assert np.linalg.norm(S + S.T) <= 1e-7 * scale
        # Not vacuous: Ṁ and the skew part of C are both of the order of |M|·|v| here.
        assert np.linalg.norm(M_dot) > 1e-3 * scale
        assert np.linalg.norm(C - C.T) > 1e-3 * scale
        # And C is the Coriolis matrix of the same dynamics: C v = RNEA(q, v, 0) − g.
        Cv = r.nonlinear_effects(q, v) - r.gravity(q)
        assert np.linalg.norm(C @ v - Cv) <= 1e-12 * scale * np.linalg.norm(v)


# ---- energies ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize(("name", "floating_base"), DYNAMICS_ROBOTS)
def test_kinetic_energy_is_half_v_m_v(robot: Callable[..., ms.Robot], name: str, floating_base: bool | None) -> None:
    r = robot(name, floating_base=floating_base)
    rng = np.random.default_rng(13)
    for _ in range(3):
        q, v, _ = _random_state(r, rng)
        assert r.kinetic_energy(q, v) == pytest.approx(0.5 * v @ r.mass_matrix(q) @ v, rel=1e-13)
        assert r.total_energy(q, v) == pytest.approx(r.kinetic_energy(q, v) + r.potential_energy(q), rel=1e-15)


def _potential_gradient(r: ms.Robot, q: np.ndarray, step: Callable[[np.ndarray, np.ndarray], np.ndarray]) -> np.ndarray:
    """Central differences of V along step(q, ±h eᵢ) for each velocity direction i."""
    h = 1e-5  # V ~ 10…1000 J: round-off ~1e-16 V/h ≈ 1e-11 V, truncation ~h² ≈ 1e-10 relative
    V = r.potential_energy
    return np.array([(V(step(q, h * e)) - V(step(q, -h * e))) / (2 * h) for e in np.eye(r.nv)])


def test_gravity_is_potential_gradient_on_fixed_arm(robot: Callable[..., ms.Robot]) -> None:
    """g(q) = ∂V/∂q; on an arm the coordinates are plain angles, so q + h eᵢ is a valid perturbation."""
    for name in ("ur5", "panda"):
        r = robot(name)
        rng = np.random.default_rng(14)
        for _ in range(3):
            q = r.random_configuration(rng)
            g = r.gravity(q)
            gradient = _potential_gradient(r, q, lambda x, dx: x + dx)
            assert np.linalg.norm(gradient - g) <= 1e-8 * np.linalg.norm(g)


def test_gravity_is_potential_gradient_on_floating_base(robot: Callable[..., ms.Robot]) -> None:
    """On a free-flyer, g is the derivative of V along q ⊕ h eᵢ (base-frame translation and rotation)."""
    for name in ("solo12", "free_body"):
        r = robot(name)
        rng = np.random.default_rng(15)
        for _ in range(3):
            q = r.random_configuration(rng)
            g = r.gravity(q)
            gradient = _potential_gradient(r, q, r.integrate)
            assert np.linalg.norm(gradient - g) <= 1e-8 * np.linalg.norm(g)
            # The base force is the weight expressed in the base frame: |g[0:3]| = m·9.81.
            assert np.linalg.norm(g[:3]) == pytest.approx(r.total_mass * STANDARD_GRAVITY, rel=1e-12)


# ---- simple pendulum period --------------------------------------------------------------------------------
@dataclass(frozen=True)
class PhysicalPendulum:
    mass: float  # [kg]
    arm: float  # distance from the hinge axis to the centre of mass [m]
    pivot_inertia: float  # moment of inertia about the hinge axis [kg·m²]

    def period(self, amplitude: float) -> float:
        """Exact period: T = 4 sqrt(I / (m g l)) K(k²), k = sin(θ0 / 2) (scipy's ellipk takes m = k²)."""
        return (
            4
            * math.sqrt(self.pivot_inertia / (self.mass * STANDARD_GRAVITY * self.arm))
            * float(ellipk(math.sin(amplitude / 2) ** 2))
        )

    @property
    def small_angle_period(self) -> float:
        return 2 * math.pi * math.sqrt(self.pivot_inertia / (self.mass * STANDARD_GRAVITY * self.arm))


def _pendulum_from_urdf(path: Path) -> PhysicalPendulum:
    """Mass, arm and pivot inertia of a one-hinge URDF, with the parallel-axis theorem."""
    root = etree.parse(str(path)).getroot()
    (joint,) = root.findall("joint")
    assert _floats(joint.find("origin"), "xyz", "0 0 0") == [0.0, 0.0, 0.0]
    axis = np.array(_floats(joint.find("axis"), "xyz", "1 0 0"))
    axis /= np.linalg.norm(axis)
    inertial = root.find(f"link[@name='{joint.find('child').get('link')}']/inertial")
    assert _floats(inertial.find("origin"), "rpy", "0 0 0") == [0.0, 0.0, 0.0]
    mass = float(inertial.find("mass").get("value"))
    com = np.array(_floats(inertial.find("origin"), "xyz", "0 0 0"))
    t = {a: float(inertial.find("inertia").get(a)) for a in ("ixx", "iyy", "izz", "ixy", "iyz", "ixz")}
    tensor = np.array([[t["ixx"], t["ixy"], t["ixz"]], [t["ixy"], t["iyy"], t["iyz"]], [t["ixz"], t["iyz"], t["izz"]]])
    arm = float(np.linalg.norm(com - (com @ axis) * axis))
    return PhysicalPendulum(mass=mass, arm=arm, pivot_inertia=float(axis @ tensor @ axis) + mass * arm**2)


def _measured_period(t: np.ndarray, q: np.ndarray, v: np.ndarray) -> tuple[float, float]:
    """Two period estimates from the zero crossings of q, interpolated by cubic Hermite with q and q̇ = v.

    Released from rest at θ0 > 0, q crosses zero at T/4, 3T/4, 5T/4: 4·t₁ and t₃ − t₁ both measure T.
    """
    crossings = CubicHermiteSpline(t, q, v).roots(extrapolate=False)
    assert len(crossings) >= 3, f"expected 3 zero crossings, found {crossings}"
    return 4 * crossings[0], crossings[2] - crossings[0]


@pytest.fixture(scope="module")
def pendulum_model() -> PhysicalPendulum:
    path, _ = catalog_urdf(ms.CATALOG["pendulum"])
    return _pendulum_from_urdf(path)


# RK4 at dt = 2 ms measured period errors of 1e-12 … 1.3e-11 (θ0 = 0.05 … 3 rad, error ∝ dt⁴: 2e-10 at 4 ms);
# 1e-9 leaves ~100× margin for other platforms and still rejects any model error above one part in 1e9.
PERIOD_RTOL = 1e-9


@pytest.mark.parametrize("amplitude", [0.05, 2.5, 3.0])
def test_pendulum_period_matches_elliptic_integral(
    robot: Callable[..., ms.Robot], pendulum_model: PhysicalPendulum, amplitude: float
) -> None:
    pendulum = robot("pendulum")
    assert pendulum.damping.tolist() == [0.0]  # the shipped pendulum is conservative
    exact = pendulum_model.period(amplitude)
    trajectory = ms.simulate(pendulum, [amplitude], [0.0], duration=1.3 * exact, dt=2e-3, integrator="rk4")
    quarter, full = _measured_period(trajectory.t, trajectory.q[:, 0], trajectory.v[:, 0])
    assert quarter == pytest.approx(exact, rel=PERIOD_RTOL)
    assert full == pytest.approx(exact, rel=PERIOD_RTOL)
    # A linearized (small-angle) model would be off by far more than the tolerance, even at 0.05 rad (1.6e-4).
    assert abs(full / pendulum_model.small_angle_period - 1) > 1e4 * PERIOD_RTOL


def test_pendulum_period_is_not_the_small_angle_period(pendulum_model: PhysicalPendulum) -> None:
    """The oracle itself is sensitive: amplitude lengthens the period far beyond the tolerance above."""
    T0 = pendulum_model.small_angle_period
    # Small amplitude: T/T0 = 1 + θ0²/16 + 11 θ0⁴/3072 + …: at 0.05 rad that is 1.5625e-4 ≫ 1e-9.
    assert pendulum_model.period(0.05) / T0 - 1 == pytest.approx(0.05**2 / 16 + 11 * 0.05**4 / 3072, rel=1e-4)
    assert pendulum_model.period(2.5) / T0 > 1.6
    assert pendulum_model.period(3.0) / T0 > 2.5
    # The bob's own rotational inertia (0.001 kg·m² about the hinge) moves T by 5e-4 relative: also visible.
    assert pendulum_model.pivot_inertia == pytest.approx(1.001, rel=1e-12)
