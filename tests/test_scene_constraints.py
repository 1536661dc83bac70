"""Holonomic constraints (scenes/constraints.py) against independent oracles.

Oracles: SymPy's LagrangesMethod with holonomic constraints (the four-bar, built from the URDF's numbers parsed
here), static equilibrium against Pinocchio's generalized gravity, reduced models (pin.buildReducedModel + ABA)
for welds and folded pendulums, the analytic critically damped Baumgarte decay, frame kinematics, energy
conservation at RK4's order, and Richardson estimates of RK4's global error for the drift bound.
"""

from __future__ import annotations

import pickle
import re
from collections.abc import Callable
from typing import Any

import numpy as np
import pinocchio as pin
import pytest
import sympy as sp
from conftest import joint, link, urdf
from lxml import etree
from sympy.physics.mechanics import (
    LagrangesMethod,
    Lagrangian,
    Point,
    ReferenceFrame,
    RigidBody,
    dynamicsymbols,
    inertia,
)

from multibody_sim.catalog import CATALOG, catalog_urdf
from multibody_sim.exceptions import InvalidArgumentError
from multibody_sim.scenes.constraints import DEFAULT_STABILIZATION, Constraints
from multibody_sim.scenes.spec import ConstraintSpec

LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
FOUR_BAR_URDF = catalog_urdf(CATALOG["four_bar"])[0]
LOOP = ConstraintSpec("loop", "loop", ("coupler_tip", "rocker_tip"))


# ---- the four-bar: geometry from the URDF text, closed-form assembly ---------------------------------
def _urdf_tree() -> tuple[dict[str, etree._Element], dict[str, etree._Element]]:
    root = etree.parse(str(FOUR_BAR_URDF)).getroot()
    return {e.get("name"): e for e in root.findall("link")}, {e.get("name"): e for e in root.findall("joint")}


def _numbers(text: str) -> np.ndarray:
    return np.array([float(x) for x in text.split()])


def _four_bar_lengths() -> tuple[float, float, float, float]:
    """(crank a, coupler b, rocker c, ground d) [m]: the in-plane (y) offsets of the URDF's joints."""
    _, joints = _urdf_tree()
    y = {name: _numbers(j.find("origin").get("xyz"))[1] for name, j in joints.items()}
    return y["coupler_joint"], y["coupler_tip_joint"], y["rocker_tip_joint"], y["rocker_joint"]


def four_bar_state(theta1: float, omega1: float = 0.0, branch: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """Closed-form consistent (q, v) for crank angle theta1 and crank rate omega1 (models/four_bar/README.md).

    branch +1: coupler and rocker meet below the ground line; -1: above it.
    """
    a, b, c, d = _four_bar_lengths()
    e = lambda angle: np.array([np.cos(angle), np.sin(angle)])  # noqa: E731
    crank_pin = a * e(theta1)
    r = np.array([d, 0.0]) - crank_pin
    rho = np.linalg.norm(r)
    alpha = np.arccos((b**2 + rho**2 - c**2) / (2 * b * rho))
    phi = np.arctan2(r[1], r[0]) - branch * alpha
    tip = crank_pin + b * e(phi)
    theta3 = np.arctan2(tip[1], tip[0] - d)
    phi_dot = -a * omega1 * np.sin(theta3 - theta1) / (b * np.sin(theta3 - phi))
    theta3_dot = a * omega1 * np.sin(phi - theta1) / (c * np.sin(phi - theta3))
    theta2 = np.angle(np.exp(1j * (phi - theta1)))
    return np.array([theta1, theta2, theta3]), np.array([omega1, phi_dot - omega1, theta3_dot])


def _frame_gap(model: pin.Model, q: np.ndarray, v: np.ndarray, f1: str, f2: str) -> tuple[np.ndarray, np.ndarray]:
    """World position and velocity of frame f1's origin minus frame f2's, from Pinocchio's frame kinematics."""
    data = model.createData()
    pin.forwardKinematics(model, data, q, v)
    pin.updateFramePlacements(model, data)
    i, j = model.getFrameId(f1), model.getFrameId(f2)
    gap = data.oMf[i].translation - data.oMf[j].translation
    rate = pin.getFrameVelocity(model, data, i, LWA).linear - pin.getFrameVelocity(model, data, j, LWA).linear
    return gap, rate


def _point_jacobian(model: pin.Model, q: np.ndarray, frame: str) -> np.ndarray:
    data = model.createData()
    pin.computeJointJacobians(model, data, q)
    pin.updateFramePlacements(model, data)
    return pin.getFrameJacobian(model, data, model.getFrameId(frame), LWA)


def _mass_matrix_and_bias(model: pin.Model, q: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    data = model.createData()
    M = pin.crba(model, data, q)
    return np.triu(M) + np.triu(M, 1).T, pin.nonLinearEffects(model, data, q, v).copy()


def rk4(
    constraints: Constraints,
    q: np.ndarray,
    v: np.ndarray,
    dt: float,
    steps: int,
    each: Callable[[np.ndarray, np.ndarray], None] | None = None,
) -> tuple[np.ndarray, np.ndarray]:
    """Classical RK4 on the constrained dynamics (no torques); each(q, v) sees every state, the first included."""
    model = constraints.model
    tau = np.zeros(model.nv)

    def f(q: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        return v, constraints.forward_dynamics(q, v, tau)

    for _ in range(steps):
        if each is not None:
            each(q, v)
        k1 = f(q, v)
        k2 = f(pin.integrate(model, q, 0.5 * dt * k1[0]), v + 0.5 * dt * k1[1])
        k3 = f(pin.integrate(model, q, 0.5 * dt * k2[0]), v + 0.5 * dt * k2[1])
        k4 = f(pin.integrate(model, q, dt * k3[0]), v + dt * k3[1])
        q = pin.integrate(model, q, dt / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0]))
        v = v + dt / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
    if each is not None:
        each(q, v)
    return q, v


@pytest.fixture(scope="module")
def four_bar(robot: Callable[..., Any]) -> pin.Model:
    return robot("four_bar").model


# ---- the shipped model and its closed form ------------------------------------------------------------
@pytest.mark.parametrize("branch", [1, -1])
def test_closed_form_state_closes_the_loop(four_bar: pin.Model, branch: int) -> None:
    """README's formulas give states where Pinocchio puts coupler_tip on rocker_tip, at equal velocities."""
    for theta1 in np.linspace(0.0, 2 * np.pi, 9):
        q, v = four_bar_state(theta1, omega1=3.0, branch=branch)
        gap, rate = _frame_gap(four_bar, q, v, "coupler_tip", "rocker_tip")
        assert np.abs(gap).max() < 1e-14 and np.abs(rate).max() < 1e-13
        coupler = _frame_gap(four_bar, q, v, "coupler_tip", "universe")[0]
        assert np.sign(coupler[2]) == -branch  # branch +1 meets below the ground line


def test_four_bar_is_a_grashof_crank_rocker_with_a_good_transmission_angle() -> None:
    a, b, c, d = _four_bar_lengths()
    lengths = sorted([a, b, c, d])
    assert lengths[0] + lengths[3] < lengths[1] + lengths[2] and lengths[0] == a  # the crank turns fully
    # transmission angle at the extremes of the crank-pin-to-rocker-pivot distance (d - a, d + a)
    mu = [np.degrees(np.arccos((b**2 + c**2 - rho**2) / (2 * b * c))) for rho in (d - a, d + a)]
    assert min(mu) > 40 and max(mu) < 140  # far from the singular 0 and 180 degrees
    assert (round(min(mu)), round(max(mu))) == (54, 100)  # as README.md states


# ---- SymPy: Lagrange's equations of the first kind ------------------------------------------------------
@pytest.fixture(scope="module")
def sympy_four_bar() -> Callable[[np.ndarray, np.ndarray, np.ndarray], tuple[np.ndarray, ...]]:
    """(q, v, tau) -> (accelerations, generalized constraint force, loop Jacobian rows y, z) from SymPy.

    Built from the URDF's joint origins, axes and inertial data parsed here, with SymPy's own kinematics.
    """
    links, joints = _urdf_tree()
    q = dynamicsymbols("q1:4")
    qd = [x.diff() for x in q]
    tau = sp.symbols("tau1:4")
    world = ReferenceFrame("N")
    origin = Point("O")
    origin.set_vel(world, 0)
    places = {"ground": (world, origin)}
    bodies, forces = [], []

    def attach(name: str) -> tuple[etree._Element, str, str]:
        element = joints[name]
        parent, child = element.find("parent").get("link"), element.find("child").get("link")
        frame, point = places[parent]
        xyz = _numbers(element.find("origin").get("xyz"))
        assert not np.any(_numbers(element.find("origin").get("rpy", "0 0 0")))  # kept simple: no rotations
        places[child] = (frame, point.locatenew(f"{child}_o", xyz[0] * frame.x + xyz[1] * frame.y + xyz[2] * frame.z))
        return element, parent, child

    for i, name in enumerate(["crank_joint", "coupler_joint", "rocker_joint"]):
        element, parent, child = attach(name)
        parent_frame, point = places[child]
        ax = _numbers(element.find("axis").get("xyz"))
        axis = ax[0] * parent_frame.x + ax[1] * parent_frame.y + ax[2] * parent_frame.z
        frame = parent_frame.orientnew(child, "Axis", (q[i], axis))
        places[child] = (frame, point)
        inertial = links[child].find("inertial")
        mass = float(inertial.find("mass").get("value"))
        com = _numbers(inertial.find("origin").get("xyz"))
        assert not np.any(_numbers(inertial.find("origin").get("rpy", "0 0 0")))
        k = {key: float(value) for key, value in inertial.find("inertia").attrib.items()}
        centre = point.locatenew(f"{child}_c", com[0] * frame.x + com[1] * frame.y + com[2] * frame.z)
        centre.set_vel(world, centre.pos_from(origin).dt(world))
        dyadic = inertia(frame, k["ixx"], k["iyy"], k["izz"], k["ixy"], k["iyz"], k["ixz"])
        body = RigidBody(child, centre, frame, mass, (dyadic, centre))
        body.potential_energy = mass * 9.81 * (centre.pos_from(origin) & world.z)
        bodies.append(body)
        forces.append((frame, tau[i] * axis))  # the joint torque on the child, its reaction on the parent
        if parent != "ground":
            forces.append((parent_frame, -tau[i] * axis))
    attach("coupler_tip_joint")
    attach("rocker_tip_joint")
    gap = places["coupler_tip"][1].pos_from(origin) - places["rocker_tip"][1].pos_from(origin)
    closure = [gap & world.y, gap & world.z]  # the loop's two independent (in-plane) rows
    method = LagrangesMethod(Lagrangian(world, *bodies), q, forcelist=forces, frame=world, hol_coneqs=closure)
    method.form_lagranges_equations()
    n = len(q)
    system = sp.lambdify([q, qd, tau], method.mass_matrix_full, "numpy")
    rhs = sp.lambdify([q, qd, tau], method.forcing_full, "numpy")
    mass = sp.lambdify([q], method.mass_matrix[:, :n], "numpy")  # M(q) without the multipliers' columns
    forcing = sp.lambdify([q, qd, tau], method.forcing, "numpy")  # tau - C v - g
    jacobian = sp.lambdify([q], sp.Matrix(closure).jacobian(q), "numpy")

    def solve(qv: np.ndarray, vv: np.ndarray, tv: np.ndarray) -> tuple[np.ndarray, ...]:
        accelerations = np.linalg.solve(system(qv, vv, tv), np.ravel(rhs(qv, vv, tv)))[n : 2 * n]
        constraint_force = mass(qv) @ accelerations - np.ravel(forcing(qv, vv, tv))  # M a + h - tau
        return accelerations, constraint_force, np.asarray(jacobian(qv), dtype=float)

    return solve


def test_four_bar_matches_sympy_lagranges_method(four_bar: pin.Model, sympy_four_bar: Callable) -> None:
    """Accelerations and the loop force equal SymPy's at consistent states, with torques and motion."""
    assert np.allclose(four_bar.gravity.linear, [0.0, 0.0, -9.81])  # the value the SymPy model uses
    rng = np.random.default_rng(4)
    constraints = Constraints(four_bar, [LOOP], four_bar_state(0.0)[0])
    for theta1, branch in [(0.3, 1), (1.7, 1), (3.5, 1), (5.0, 1), (0.8, -1), (4.2, -1)]:
        q, v = four_bar_state(theta1, rng.uniform(-6, 6), branch)
        tau = rng.uniform(-1, 1, 3)
        expected, constraint_force, jacobian = sympy_four_bar(q, v, tau)
        a = constraints.forward_dynamics(q, v, tau)
        assert np.allclose(a, expected, rtol=1e-9, atol=1e-9 * np.abs(expected).max())
        # The same physical force: SymPy's generalized constraint force is Jᵀ F for the force F on the coupler at
        # its tip (J the in-plane rows of d(coupler_tip - rocker_tip)/dq); ours is F in world axes.
        force = np.linalg.lstsq(jacobian.T, constraint_force, rcond=None)[0]
        lam = constraints.multipliers()
        scale = np.abs(force).max()
        assert abs(lam[0]) < 1e-9 * scale  # the out-of-plane (redundant) row carries nothing
        assert np.allclose(lam[1:], force, rtol=1e-8, atol=1e-9 * scale)


# ---- weld -------------------------------------------------------------------------------------------------
def test_weld_holds_ur5_at_rest_with_the_static_wrench(robot: Callable) -> None:
    """ur5 with tool0 welded where it is: no motion, and Jᵀ λ is exactly the generalized gravity g(q)."""
    model = robot("ur5", damping=False).model
    rng = np.random.default_rng(7)
    for _ in range(3):
        q = robot("ur5").random_configuration(rng)
        constraints = Constraints(model, [ConstraintSpec("hold", "weld", ("tool0", "universe"))], q)
        a = constraints.forward_dynamics(q, np.zeros(6), np.zeros(6))
        assert np.abs(a).max() < 1e-10
        wrench = constraints.multipliers()
        gravity = pin.computeGeneralizedGravity(model, model.createData(), q)
        # λ is the wrench on tool0's body at tool0's origin in world axes: it maps through tool0's Jacobian
        assert np.allclose(_point_jacobian(model, q, "tool0").T @ wrench, gravity, rtol=1e-10, atol=1e-10)
        q_end, v_end = rk4(constraints, q, np.zeros(6), 1e-2, 20)
        assert np.abs(q_end - q).max() < 1e-12 and np.abs(v_end).max() < 1e-11


def test_weld_between_links_moves_like_the_reduced_model(robot: Callable) -> None:
    """tool0 welded to the upper arm locks elbow and wrists (6 rows, rank 4: two redundant rows); the shoulder
    moves as in a model with those joints removed by pin.buildReducedModel."""
    model = robot("ur5", damping=False).model
    rng = np.random.default_rng(8)
    q = robot("ur5").random_configuration(rng)
    constraints = Constraints(model, [ConstraintSpec("arm", "weld", ("tool0", "upper_arm_link"))], q)
    locked = [model.getJointId(n) for n in ("elbow_joint", "wrist_1_joint", "wrist_2_joint", "wrist_3_joint")]
    reduced = pin.buildReducedModel(model, locked, q)
    v = np.zeros(6)
    v[:2] = rng.uniform(-1, 1, 2)
    tau = np.zeros(6)
    tau[:2] = rng.uniform(-5, 5, 2)
    a = constraints.forward_dynamics(q, v, tau)
    expected = pin.aba(reduced, reduced.createData(), q[:2], v[:2], tau[:2])
    assert np.allclose(a[:2], expected, rtol=1e-9, atol=1e-9)
    assert np.abs(a[2:]).max() < 1e-9 * np.abs(expected).max()
    M, h = _mass_matrix_and_bias(model, q, v)
    J = _point_jacobian(model, q, "tool0") - _body_jacobian_at(model, q, "upper_arm_link", "tool0")
    lam = constraints.multipliers()
    assert np.allclose(J.T @ lam, M @ a + h - tau, atol=1e-9 * np.abs(h).max())
    # the minimum-norm multipliers: nothing along the two directions Jᵀ maps to zero
    _, sigma, rows = np.linalg.svd(J.T)
    assert np.sum(sigma > 1e-9 * sigma[0]) == 4
    null = rows[4:]
    assert np.abs(null @ lam).max() < 1e-6 * np.abs(lam).max()  # the documented tolerance along null(Jᵀ)


def _body_jacobian_at(model: pin.Model, q: np.ndarray, body_frame: str, point_frame: str) -> np.ndarray:
    """World-aligned Jacobian of the point of body_frame's body that is at point_frame's origin."""
    data = model.createData()
    pin.computeJointJacobians(model, data, q)
    pin.updateFramePlacements(model, data)
    jid = model.frames[model.getFrameId(body_frame)].parentJoint
    placement = data.oMi[jid].actInv(data.oMf[model.getFrameId(point_frame)])
    return pin.getFrameJacobian(model, data, jid, placement, LWA)


# ---- point ------------------------------------------------------------------------------------------------
def test_point_holds_the_pendulum_bob(robot: Callable) -> None:
    """The bob pinned where it is: the pendulum stays at rest under gravity and Jᵀ λ = g(q)."""
    model = pin.Model(robot("pendulum").model)
    hinge = model.getJointId("hinge")
    model.addFrame(pin.Frame("bob_centre", hinge, pin.SE3(np.eye(3), np.array([0.0, 0.0, -1.0])), pin.OP_FRAME))
    q = np.array([1.0])
    constraints = Constraints(model, [ConstraintSpec("pin", "point", ("bob_centre",))], q)
    q_end, v_end = rk4(constraints, q, np.zeros(1), 1e-3, 1000)
    assert abs(q_end[0] - q[0]) < 1e-12 and abs(v_end[0]) < 1e-12
    constraints.forward_dynamics(q, np.zeros(1), np.zeros(1))
    gravity = pin.computeGeneralizedGravity(model, model.createData(), q)
    assert np.allclose(_point_jacobian(model, q, "bob_centre")[:3].T @ constraints.multipliers(), gravity, rtol=1e-12)
    assert abs(gravity[0]) > 5.0  # a real load: 1 kg at 1 m, 1 rad from hanging


def _folded_double_pendulum() -> pin.Model:
    """Two equal 1 m links (1 kg each, centre of mass mid-link) on parallel hinges, with a massless tip frame."""
    text = urdf(
        '<link name="base"/>',
        link("upper", com="0 0 -0.5", inertia="0.02 0.02 0.001"),
        link("lower", com="0 0 -0.5", inertia="0.02 0.02 0.001"),
        '<link name="tip"/>',
        joint("shoulder", "base", "upper", limits='lower="0" upper="0" effort="10" velocity="10"'),
        joint("elbow", "upper", "lower", xyz="0 0 -1", limits='lower="0" upper="0" effort="10" velocity="10"'),
        joint("tip_joint", "lower", "tip", kind="fixed", xyz="0 0 -1"),
    )
    return pin.buildModelFromXML(text)


def test_point_folded_double_pendulum_swings_as_one_body() -> None:
    """Folded (elbow at π) with the tip pinned at the shoulder, the chain keeps one degree of freedom: it swings
    as a rigid body about the shoulder. The constraint Jacobian has rank 1 of 3 rows there (redundant rows).

    Oracle: RK4 on the model with the elbow locked at π (pin.buildReducedModel), same steps. Drift bound: the exact
    motion has none, so the drift is at most L ‖q_rk4 - q_exact‖ with L = 3 m (|∂tip/∂q| ≤ l₁ + 2 l₂ in the ∞
    norm); RK4's global error is estimated by Richardson from the 2 ms run, ‖q_1ms - q_2ms‖ / 15, and a floor of
    1e-12 m covers round-off (2000 steps of ~1e-16 relative each on 1 m).
    """
    model = _folded_double_pendulum()
    q0 = np.array([1.0, np.pi])
    constraints = Constraints(model, [ConstraintSpec("fold", "point", ("tip",), position=(0.0, 0.0, 0.0))], q0)
    reduced = pin.buildReducedModel(model, [model.getJointId("elbow")], q0)
    reduced_data = reduced.createData()
    runs = {}
    for dt in (1e-3, 2e-3):
        states: list[tuple[np.ndarray, np.ndarray]] = []
        drifts: list[float] = []

        def record(q: np.ndarray, v: np.ndarray, states: list = states, drifts: list = drifts) -> None:
            states.append((q.copy(), v.copy()))
            drifts.append(constraints.drift(q, v)[0][0])

        rk4(constraints, q0, np.zeros(2), dt, round(2.0 / dt), record)
        runs[dt] = (states, drifts)
    states, drifts = runs[1e-3]
    coarse = runs[2e-3][0]
    richardson = max(np.abs(states[2 * k][0] - coarse[k][0]).max() for k in range(len(coarse))) / 15
    assert max(drifts) <= 3.0 * richardson + 1e-12
    assert max(abs(q[1] - np.pi) for q, _ in states) <= 3.0 * richardson + 1e-12
    # the shoulder follows the one-body pendulum
    theta, omega = q0[:1], np.zeros(1)
    dt = 1e-3
    for k in range(1, len(states)):
        f = lambda th, om: (om, pin.aba(reduced, reduced_data, th, om, np.zeros(1)))  # noqa: E731
        k1 = f(theta, omega)
        k2 = f(theta + dt / 2 * k1[0], omega + dt / 2 * k1[1])
        k3 = f(theta + dt / 2 * k2[0], omega + dt / 2 * k2[1])
        k4 = f(theta + dt * k3[0], omega + dt * k3[1])
        theta = theta + dt / 6 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
        omega = omega + dt / 6 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
        assert abs(states[k][0][0] - theta[0]) < 1e-9, k
    assert np.ptp([q[0] for q, _ in states]) > 1.5  # it really swung (from 1 rad to about -1 rad)


# ---- energy and power ---------------------------------------------------------------------------------------
def test_four_bar_conserves_energy_at_rk4_order(four_bar: pin.Model) -> None:
    """Undamped, unforced, swinging under gravity: the error in H = T + V falls as dt⁴ over a ladder of steps
    (RK4's order) and is a part per million of the kinetic energy at 1 ms. The constraint's power is exactly zero
    on the manifold; the numerical state leaves it by RK4's error only, so the power falls at the same order."""
    q0, v0 = four_bar_state(0.5, omega1=8.0)
    constraints = Constraints(four_bar, [LOOP], q0)
    data = four_bar.createData()

    def energies(q: np.ndarray, v: np.ndarray) -> tuple[float, float]:
        pin.forwardKinematics(four_bar, data, q, v)
        return pin.computeKineticEnergy(four_bar, data), pin.computePotentialEnergy(four_bar, data)

    kinetic0, potential0 = energies(q0, v0)
    steps = np.array([8e-3, 4e-3, 2e-3, 1e-3])
    energy_errors, power_peaks = [], []
    power = np.empty(1)
    for dt in steps:
        worst = [0.0, 0.0]

        def track(q: np.ndarray, v: np.ndarray, worst: list = worst) -> None:
            worst[0] = max(worst[0], abs(sum(energies(q, v)) - kinetic0 - potential0))
            constraints.forward_dynamics(q, v, np.zeros(3))
            worst[1] = max(worst[1], abs(constraints.powers(v, power)[0]))

        q_end, _ = rk4(constraints, q0, v0, dt, round(1.0 / dt), track)
        energy_errors.append(worst[0])
        power_peaks.append(worst[1])
    energy_slope = np.polyfit(np.log(steps), np.log(energy_errors), 1)[0]
    power_slope = np.polyfit(np.log(steps), np.log(power_peaks), 1)[0]
    assert 3.5 < energy_slope < 4.7, (energy_errors, energy_slope)
    assert 3.5 < power_slope < 4.7, (power_peaks, power_slope)
    assert energy_errors[-1] < 2e-6 * kinetic0
    assert abs(q_end[0] - q0[0]) > 0.3  # it swung


def test_power_of_the_constraint_forces_off_the_manifold(robot: Callable) -> None:
    """Off the manifold (Baumgarte at work) each constraint's power is λ_k·(J_k v), J_k from frame Jacobians, and
    their sum is vᵀ(M a + h - tau) computed from CRBA and the nonlinear effects."""
    model = robot("ur5", damping=False).model
    rng = np.random.default_rng(11)
    q_ref = robot("ur5").random_configuration(rng)
    specs = [ConstraintSpec("tool", "point", ("tool0",)), ConstraintSpec("elbow", "point", ("forearm_link",))]
    constraints = Constraints(model, specs, q_ref)
    q, v, tau = q_ref + rng.normal(0, 0.05, 6), rng.normal(0, 1, 6), rng.normal(0, 3, 6)
    a = constraints.forward_dynamics(q, v, tau)
    lam = constraints.multipliers()
    powers = constraints.powers(v, np.empty(2))
    for k, frame in enumerate(["tool0", "forearm_link"]):
        J = _point_jacobian(model, q, frame)[:3]
        assert powers[k] == pytest.approx(lam[3 * k : 3 * k + 3] @ (J @ v), rel=1e-10)
    M, h = _mass_matrix_and_bias(model, q, v)
    total = v @ (M @ a + h - tau)
    assert powers.sum() == pytest.approx(total, rel=1e-9)
    assert abs(total) > 1e-2  # off the manifold the Baumgarte forces do work


# ---- Baumgarte stabilization and drift -------------------------------------------------------------------
def test_baumgarte_decay_is_critically_damped(robot: Callable) -> None:
    """A point constraint's error obeys e'' + Kd e' + Kp e = 0: from rest off the anchor, with the default gains
    (ω = 10 /s), |e(t)| = |e(0)| (1 + ω t) exp(-ω t)."""
    model = robot("ur5", damping=False).model
    rng = np.random.default_rng(5)
    q_ref = robot("ur5").random_configuration(rng)
    constraints = Constraints(model, [ConstraintSpec("tool", "point", ("tool0",))], q_ref)
    kp, kd = DEFAULT_STABILIZATION
    omega = np.sqrt(kp)
    assert kd == pytest.approx(2 * omega)  # critically damped
    q0 = q_ref + rng.normal(0, 1e-3, 6)
    e0 = constraints.drift(q0, np.zeros(6))[0][0]
    seen: list[float] = []
    rk4(constraints, q0, np.zeros(6), 1e-3, 600, lambda q, v: seen.append(constraints.drift(q, v)[0][0]))
    for k in (100, 300, 600):
        t = k * 1e-3
        assert seen[k] == pytest.approx(e0 * (1 + omega * t) * np.exp(-omega * t), rel=1e-5)


def test_drift_matches_frame_kinematics(four_bar: pin.Model, robot: Callable) -> None:
    """drift() is the distance and relative speed of the two frames (Pinocchio's frame kinematics), and a weld's
    is the larger of its translation [m] and rotation angle [rad]."""
    q, v = four_bar_state(1.2, omega1=2.0)
    constraints = Constraints(four_bar, [LOOP], q)
    position, velocity = constraints.drift(q, v)
    assert position[0] < 1e-15 and velocity[0] < 1e-14
    rng = np.random.default_rng(2)
    q_off, v_off = q + rng.normal(0, 1e-2, 3), v + rng.normal(0, 1e-1, 3)
    gap, rate = _frame_gap(four_bar, q_off, v_off, "coupler_tip", "rocker_tip")
    position, velocity = constraints.drift(q_off, v_off)
    assert position[0] == pytest.approx(np.linalg.norm(gap), rel=1e-12)
    assert velocity[0] == pytest.approx(np.linalg.norm(rate), rel=1e-12)

    model = robot("ur5", damping=False).model
    q_ref = robot("ur5").random_configuration(rng)
    weld = Constraints(model, [ConstraintSpec("hold", "weld", ("tool0", "universe"))], q_ref)
    for dq in (np.array([0.0, 0, 0, 0, 0, 0.02]), np.array([0.05, -0.03, 0.02, 0, 0, 0])):
        data = model.createData()
        pin.framesForwardKinematics(model, data, q_ref)
        before = data.oMf[model.getFrameId("tool0")].copy()
        pin.framesForwardKinematics(model, data, q_ref + dq)
        after = data.oMf[model.getFrameId("tool0")]
        translation = np.linalg.norm(after.translation - before.translation)
        angle = np.arccos(np.clip((np.trace(before.rotation.T @ after.rotation) - 1) / 2, -1, 1))
        assert weld.drift(q_ref + dq, np.zeros(6))[0][0] == pytest.approx(max(translation, angle), rel=1e-9)


# ---- redundant rows -----------------------------------------------------------------------------------------
def test_redundant_rows_do_not_blow_up(four_bar: pin.Model) -> None:
    """The planar loop's zero row, the same loop declared twice, and an out-of-plane offset no motion can close
    all give the accelerations of the plain loop and bounded multipliers."""
    q, v = four_bar_state(2.2, omega1=4.0)
    tau = np.array([0.2, -0.1, 0.05])
    single = Constraints(four_bar, [LOOP], q)
    a = single.forward_dynamics(q, v, tau)
    lam = single.multipliers()
    assert lam[0] == 0.0 and np.all(np.isfinite(lam))
    scale = np.abs(lam).max()

    twice = Constraints(four_bar, [LOOP, ConstraintSpec("again", "loop", LOOP.frames)], q)
    assert np.allclose(twice.forward_dynamics(q, v, tau), a, rtol=1e-9)
    both = twice.multipliers()
    # the minimum-norm split of one force between two identical constraints: half each (to the documented 1e-6
    # along null(Jᵀ), here the difference of the two)
    assert np.allclose(both[:3] + both[3:], lam, atol=1e-9 * scale)
    assert np.allclose(both[:3], lam / 2, atol=1e-6 * scale) and np.allclose(both[3:], lam / 2, atol=1e-6 * scale)

    # rocker_tip moved 1 mm along the joint axes: the gap's x row cannot close, and Baumgarte keeps asking
    offset = pin.Model(four_bar)
    tip = four_bar.frames[four_bar.getFrameId("rocker_tip")]
    shifted = pin.SE3(tip.placement.rotation, tip.placement.translation + np.array([1e-3, 0.0, 0.0]))
    offset.addFrame(pin.Frame("rocker_tip_x", tip.parentJoint, shifted, pin.OP_FRAME))
    skewed = Constraints(offset, [ConstraintSpec("skew", "loop", ("coupler_tip", "rocker_tip_x"))], q)
    assert np.allclose(skewed.forward_dynamics(q, v, tau), a, rtol=1e-9)
    assert np.allclose(skewed.multipliers(), lam, atol=1e-9 * scale)
    assert skewed.fallbacks == 1
    assert skewed.drift(q, v)[0][0] == pytest.approx(1e-3, rel=1e-12)


# ---- bad declarations ----------------------------------------------------------------------------------------
def test_bad_declarations_raise_with_the_valid_options(four_bar: pin.Model) -> None:
    q = four_bar_state(0.0)[0]
    valid = ", ".join(sorted({f.name for f in four_bar.frames}))
    assert "coupler_tip" in valid and "universe" in valid
    cases = [
        (
            ConstraintSpec("loop", "loop", ("coupler_tip", "zzz")),
            f"constraint 'loop': unknown frame 'zzz' (valid: {valid})",
        ),
        (
            ConstraintSpec("loop", "loop", ("coupler_tip", "rocker_top")),
            "constraint 'loop': unknown frame 'rocker_top' (did you mean 'rocker_tip' or 'rocker' or 'rocker_joint'?)",
        ),
        (
            ConstraintSpec("loop", "hinge", LOOP.frames),
            "constraint 'loop': type must be one of loop, point, weld, got 'hinge'",
        ),
        (
            ConstraintSpec("p", "point", LOOP.frames),
            "constraint 'p': a point constraint takes one frame, got ['coupler_tip', 'rocker_tip']",
        ),
        (
            ConstraintSpec("w", "weld", ("coupler_tip", "coupler_tip")),
            "constraint 'w': a weld constraint takes two distinct frames, got ['coupler_tip', 'coupler_tip']",
        ),
        (
            ConstraintSpec("same", "loop", ("coupler", "coupler_tip")),
            "constraint 'same': frames 'coupler' and 'coupler_tip' are fixed to one rigid body "
            "(joint 'coupler_joint'): the constraint could not act",
        ),
        (
            ConstraintSpec("g", "point", ("ground",)),
            "constraint 'g': frame 'ground' is fixed to the world: the constraint could not act",
        ),
        (
            ConstraintSpec("loop", "loop", LOOP.frames, position=(0.0, 0.0, 0.0)),
            "constraint 'loop': position applies to point constraints only",
        ),
        (
            ConstraintSpec("p", "point", ("coupler_tip",), position=(0.0, np.inf, 0.0)),
            "constraint 'p': position must be 3 finite numbers [m], got (0.0, inf, 0.0)",
        ),
        (
            ConstraintSpec("loop", "loop", LOOP.frames, stabilization=(100.0, -1.0)),
            "constraint 'loop': stabilization must be two finite gains (Kp, Kd) >= 0, got [100.0, -1.0]",
        ),
    ]
    for spec, message in cases:
        with pytest.raises(InvalidArgumentError, match=re.escape(message) + "$"):
            Constraints(four_bar, [spec], q)
    with pytest.raises(InvalidArgumentError, match=re.escape("constraint 'loop' is declared twice")):
        Constraints(four_bar, [LOOP, LOOP], q)
    with pytest.raises(InvalidArgumentError, match=re.escape("q_ref must be a finite array of shape (3,), got (2,)")):
        Constraints(four_bar, [LOOP], q[:2])


def test_names_rows_ledger_and_gains(four_bar: pin.Model) -> None:
    q = four_bar_state(0.0)[0]
    constraints = Constraints(
        four_bar,
        [LOOP, ConstraintSpec("crank_pin", "point", ("coupler",), stabilization=(400.0, 40.0))],
        q,
    )
    assert constraints.names == ["loop", "crank_pin"]
    assert constraints.rows == [3, 3] and constraints.n_rows == 6
    assert constraints.ledger == [("constraint:loop", "work"), ("constraint:crank_pin", "work")]
    assert constraints.stabilization == [DEFAULT_STABILIZATION, (400.0, 40.0)]
    assert np.array_equal(constraints.multipliers(), np.zeros(6))


def test_constraints_survive_pickling(four_bar: pin.Model) -> None:
    """Scenes travel to worker processes: a round trip rebuilds the same constraints (Pinocchio's constraint
    objects do not pickle themselves)."""
    q, v = four_bar_state(0.7, omega1=2.0)
    specs = [LOOP, ConstraintSpec("anchor", "point", ("coupler",), position=(0.0, 0.05, 0.09), stabilization=(4, 4))]
    constraints = Constraints(four_bar, specs, q)
    copy = pickle.loads(pickle.dumps(constraints))
    assert copy.names == constraints.names and copy.stabilization == constraints.stabilization
    assert np.array_equal(copy.forward_dynamics(q, v, np.ones(3)), constraints.forward_dynamics(q, v, np.ones(3)))
    assert np.array_equal(copy.multipliers(), constraints.multipliers())
