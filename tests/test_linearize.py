"""linearize(): Jacobians of one integrator step, against finite differences of the step, closed-form stability
functions, and an LQR design that must stabilise the upright double pendulum."""

from __future__ import annotations

import math
import re
import sys

import numpy as np
import pinocchio as pin
import pytest
import scipy.linalg

import multibody_sim as ms
from multibody_sim.integrators.implicit import ImplicitEuler
from multibody_sim.state import ConfigurationSpace

# Every registry method but the variational integrator, which linearize refuses (tested below): a new method is
# checked against finite differences for free.
METHODS = sorted(name for name in ms.INTEGRATORS if name != "variational")
# Central differences with a step of 1e-4 in the tangent space: truncation ε²/6·|Φ'''| ≈ 1e-9 of the Jacobian's
# size on these states, round-off 1e-16/ε ≈ 1e-12; a missed term of the chain rule shows at 1e-4 to 1e-2.
EPS = 1e-4
TOLERANCE = 1e-6


def exact(message: str) -> str:
    return f"^{re.escape(message)}$"


def finite_differences(
    robot: ms.Robot, method: str, q: np.ndarray, v: np.ndarray, tau: np.ndarray, dt: float
) -> tuple[np.ndarray, np.ndarray]:
    """Central differences of the integrator's own step, perturbed and compared in the tangent space."""
    step = ms.get_integrator(method).step
    nv = robot.nv
    q1, v1, _ = step(robot, q, v, tau, dt)
    columns = []
    for k in range(3 * nv):
        sides = []
        for sign in (1.0, -1.0):
            e = np.zeros(3 * nv)
            e[k] = sign * EPS
            qk, vk, _ = step(robot, robot.integrate(q, e[:nv]), v + e[nv : 2 * nv], tau + e[2 * nv :], dt)
            sides.append(np.concatenate((robot.difference(q1, qk), vk - v1)))
        columns.append((sides[0] - sides[1]) / (2.0 * EPS))
    jacobian = np.array(columns).T
    return jacobian[:, : 2 * nv], jacobian[:, 2 * nv :]


def planar_robot() -> ms.Robot:
    """A puck on a planar joint (SE(2)) carrying a damped pendulum, built directly in Pinocchio."""
    model = pin.Model()
    puck = model.addJoint(0, pin.JointModelPlanar(), pin.SE3.Identity(), "slide")
    model.appendBodyToJoint(puck, pin.Inertia(1.0, np.array([0.1, 0.05, 0.0]), np.diag([0.01] * 3)), pin.SE3.Identity())
    hinge = model.addJoint(puck, pin.JointModelRX(), pin.SE3(np.eye(3), np.array([0.2, 0.0, 0.0])), "hinge")
    model.appendBodyToJoint(
        hinge, pin.Inertia(1.0, np.array([0.0, 0.0, -0.3]), np.diag([0.01] * 3)), pin.SE3.Identity()
    )
    model.damping[3] = 0.3
    return ms.Robot(model, name="planar", floating_base=False)


def ball_robot() -> ms.Robot:
    """A spherical joint (SO(3)) with an elbow below it, built directly in Pinocchio (URDF has no ball joint)."""
    model = pin.Model()
    ball = model.addJoint(0, pin.JointModelSpherical(), pin.SE3.Identity(), "ball")
    model.appendBodyToJoint(
        ball, pin.Inertia(2.0, np.array([0.1, 0.0, -0.4]), np.diag([0.02, 0.03, 0.04])), pin.SE3.Identity()
    )
    elbow = model.addJoint(ball, pin.JointModelRY(), pin.SE3(np.eye(3), np.array([0.0, 0.0, -0.5])), "elbow")
    model.appendBodyToJoint(
        elbow, pin.Inertia(1.0, np.array([0.0, 0.0, -0.3]), np.diag([0.01] * 3)), pin.SE3.Identity()
    )
    return ms.Robot(model, name="ball", floating_base=False)


# (robot, floating_base, dt, velocity scale): steps long enough that the stages move far from q, so every term of
# the chain rule (the chart map on the free-flyer, SE(2) and SO(3) groups above all) weighs in.
CASES = {
    "ur5 arm": ("ur5", None, 0.02, 1.0),
    "z1 damped arm": ("z1", None, 5e-4, 1.0),  # its damped gripper decays at 3425/s: explicit steps stable
    "continuous joints": ("double_pendulum_continuous", None, 0.02, 1.0),
    "solo12 floating base": ("solo12", True, 0.005, 3.0),
    "free body spinning": ("free_body", True, 0.05, 5.0),
    "planar joint": ("planar", None, 0.05, 4.0),
    "spherical joint": ("ball", None, 0.05, 4.0),
}


def case_robot(robot, name: str, floating: bool | None) -> ms.Robot:
    if name == "planar":
        return planar_robot()
    if name == "ball":
        return ball_robot()
    return robot(name, floating_base=floating)


@pytest.mark.parametrize("method", METHODS)
@pytest.mark.parametrize("case", list(CASES))
def test_jacobians_match_central_differences_of_the_step(robot, case, method):
    name, floating, dt, speed = CASES[case]
    system = case_robot(robot, name, floating)
    rng = np.random.default_rng(sorted(CASES).index(case))
    q = system.random_configuration(rng)
    v = speed * rng.normal(size=system.nv)
    tau = rng.normal(size=system.nv)
    if system.floating_base:
        tau[:6] = 0.0
    A, B = ms.linearize(system, q, v, tau, dt, integrator=method)
    A_fd, B_fd = finite_differences(system, method, q, v, tau, dt)
    assert A.shape == (2 * system.nv, 2 * system.nv) and B.shape == (2 * system.nv, system.nv)
    assert np.abs(A - A_fd).max() <= TOLERANCE * max(1.0, np.abs(A_fd).max())
    assert np.abs(B - B_fd).max() <= TOLERANCE * np.abs(B_fd).max()


def test_the_finite_difference_check_sees_the_chart_terms(robot, monkeypatch):
    # The test above can fail: without the derivative of the chart velocity J(ξ)⁻¹ v (a second-order effect of the
    # Lie group) a spinning free body's RK4 Jacobian is off by ~5e-3, over 1000 times the tolerance.
    body = robot("free_body")
    rng = np.random.default_rng(0)
    q, v, tau = body.random_configuration(rng), 5.0 * rng.normal(size=6), np.zeros(6)
    A_fd, _ = finite_differences(body, "rk4", q, v, tau, 0.05)
    monkeypatch.setattr(ConfigurationSpace, "add_chart_curvature", lambda *args: None)
    A, _ = ms.linearize(body, q, v, tau, 0.05, integrator="rk4")
    assert np.abs(A - A_fd).max() > 1e3 * TOLERANCE * max(1.0, np.abs(A_fd).max())


# ---- closed forms at an equilibrium ------------------------------------------------------------------------
def pendulum_stability_functions(hF: np.ndarray) -> dict[str, np.ndarray]:
    """Each method's step matrix on the linear system x' = F x: its stability function R(hF)."""
    eye = np.eye(len(hF))
    hF2 = hF @ hF
    return {
        "euler": eye + hF,
        "midpoint": eye + hF + hF2 / 2,
        "rk4": eye + hF + hF2 / 2 + hF2 @ hF / 6 + hF2 @ hF2 / 24,
        "implicit_euler": np.linalg.inv(eye - hF),
        "implicit_midpoint": np.linalg.solve(eye - hF / 2, eye + hF / 2),
    }


@pytest.mark.parametrize(
    "method", ["euler", "midpoint", "rk4", "implicit_euler", "implicit_midpoint", "semi_implicit_euler"]
)
def test_at_the_pendulums_rest_the_jacobian_is_the_methods_stability_function(robot, method):
    # The catalog pendulum hanging at rest: a 1 kg bob (inertia 1e-3 kg·m²) 1 m below the hinge, so
    # x' = F x with F = [[0, 1], [-m g l / I, 0]], I = 1.001 kg·m², and the torque enters as (0, 1/I). At an
    # equilibrium every stage sits still, so one step's Jacobian is exactly the method's R(hF) (and, for B,
    # the same polynomial's (R(hF) - I) F⁻¹ G); semi-implicit Euler is [[1 - h²ω², h], [-hω², 1]] by hand.
    pendulum = robot("pendulum")
    inertia, mgl, h = 1.001, 9.81, 0.05
    F = np.array([[0.0, 1.0], [-mgl / inertia, 0.0]])
    G = np.array([[0.0], [1.0 / inertia]])
    if method == "semi_implicit_euler":
        w2 = mgl / inertia
        expected_A = np.array([[1.0 - h * h * w2, h], [-h * w2, 1.0]])
        expected_B = np.array([[h * h], [h]]) / inertia
    else:
        expected_A = pendulum_stability_functions(h * F)[method]
        expected_B = (expected_A - np.eye(2)) @ np.linalg.solve(F, G)
    A, B = ms.linearize(pendulum, [0.0], [0.0], [0.0], h, integrator=method)
    np.testing.assert_allclose(A, expected_A, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(B, expected_B, rtol=1e-12, atol=1e-14)


# ---- what LQR users need ---------------------------------------------------------------------------------------
@pytest.mark.parametrize("actuated", [[0, 1], [1]], ids=["both joints", "acrobot (elbow only)"])
def test_discrete_lqr_from_the_jacobians_holds_the_double_pendulum_upright(robot, actuated):
    # q = 0 is UPRIGHT for the catalog double pendulum (damped, 0.05 N·m·s/rad). Linearise one RK4 step of the
    # 10 ms control period about it (holding the tiny gravity torque its slightly off-axis links need there),
    # design a discrete LQR with SciPy's Riccati solver, and run the nonlinear robot at 1 ms under that
    # controller from a 0.1 rad perturbation.
    dp = robot("double_pendulum")
    control_dt = 0.01
    hold = dp.gravity(np.zeros(2))
    A, B = ms.linearize(dp, np.zeros(2), np.zeros(2), hold, control_dt, integrator="rk4")
    assert max(abs(np.linalg.eigvals(A))) > 1.02  # upright is unstable: a mode grows by 3 % per step
    Bu = B[:, actuated]
    Q, R = np.diag([10.0, 10.0, 1.0, 1.0]), 0.1 * np.eye(len(actuated))
    P = scipy.linalg.solve_discrete_are(A, Bu, Q, R)
    K = np.linalg.solve(R + Bu.T @ P @ Bu, Bu.T @ P @ A)
    rho = max(abs(np.linalg.eigvals(A - Bu @ K)))
    assert rho < 1.0

    def lqr(t, q, v):
        tau = np.zeros(2)
        tau[actuated] = hold[actuated] - K @ np.concatenate((q, v))
        return tau

    q0 = np.array([0.1, -0.1])
    closed = ms.simulate(dp, q0, [0.0, 0.0], duration=4.0, dt=1e-3, control_dt=control_dt, controller=lqr)
    opened = ms.simulate(dp, q0, [0.0, 0.0], duration=4.0, dt=1e-3)
    assert np.abs(opened.q[:, 0]).max() > math.pi / 2  # left alone, it falls
    distance = np.linalg.norm(np.hstack((closed.q, closed.v)), axis=1)
    assert np.abs(closed.q).max() < 1.0  # it never falls: the largest excursion stays below 1 rad
    if actuated == [0, 1]:
        # Fully actuated, the nonlinear closed loop converges at the rate the linear design predicts: ρ per
        # control period, i.e. ρ^100 per second, measured over 1..3 s (after the initial transient). The fine
        # 1 ms simulation and the nonlinearity shift it a little (0.5 % here).
        rate = (distance[3000] / distance[1000]) ** 0.5
        assert rate == pytest.approx(rho**100, rel=0.05)
        assert distance[-1] < 1e-4 * distance[0]  # ρ^400 ≈ 3e-6
    else:
        # With the shoulder unactuated the tiny gravity torque it needs upright (6e-6 N·m) is missing: the
        # closed loop settles at a nearby equilibrium instead, a fraction of a milliradian away.
        assert distance[-1] < 1e-2 * distance[0]
        assert np.abs(closed.v[-1]).max() < 1e-3


# ---- arguments and refusals ------------------------------------------------------------------------------------
def test_arguments_are_checked(robot):
    dp, solo = robot("double_pendulum"), robot("solo12")
    with pytest.raises(ms.InvalidArgumentError, match=exact("tau must have shape (2,), got (3,)")):
        ms.linearize(dp, [0.0, 0.0], [0.0, 0.0], [0.0, 0.0, 0.0], 0.01)
    with pytest.raises(ms.InvalidArgumentError, match=exact("dt must be a positive number of seconds, got -0.01")):
        ms.linearize(dp, [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], -0.01)
    push = np.zeros(18)
    push[0] = 1.0
    with pytest.raises(
        ms.InvalidArgumentError,
        match=exact(
            "tau[0:6] acts on the unactuated floating base and must be zero, got [1.0, 0.0, 0.0, 0.0, 0.0, 0.0]"
        ),
    ):
        ms.linearize(solo, solo.neutral(), np.zeros(18), push, 0.01)


def test_the_variational_integrator_is_refused_clearly(robot):
    with pytest.raises(
        ms.InvalidArgumentError,
        match=exact(
            "linearize does not support integrator 'variational' yet (supported: the explicit Runge–Kutta methods "
            "(euler, midpoint, rk4, bs32, dp54, dop853), semi_implicit_euler, implicit_euler and implicit_midpoint)"
        ),
    ):
        ms.linearize(robot("double_pendulum"), [0.0, 0.0], [0.0, 0.0], [0.0, 0.0], 0.01, integrator="variational")


def test_a_stage_turning_by_more_than_half_a_turn_is_linearized_like_any_other(robot, monkeypatch):
    # The step's chart map is its series truncated where the method's order allows: a polynomial in ξ, so even a
    # stage turning by 4 rad (a step far too long for accuracy) has a Jacobian, and linearize gives the step's.
    # So nonlinear a step needs smaller differences (the error falls as EPS²: 6e-3 at 1e-4, 6e-5 at 1e-5).
    monkeypatch.setattr(sys.modules[__name__], "EPS", 1e-5)
    body = robot("free_body")
    rng = np.random.default_rng(1)
    q, v = body.random_configuration(rng), np.array([0.3, -0.2, 0.1, 5.0, -3.0, 40.0])
    for method in ("midpoint", "rk4"):
        A, B = ms.linearize(body, q, v, np.zeros(6), 0.2, integrator=method)
        A_fd, B_fd = finite_differences(body, method, q, v, np.zeros(6), 0.2)
        assert np.abs(A - A_fd).max() <= TOLERANCE * max(1.0, np.abs(A_fd).max()), method
        assert np.abs(B - B_fd).max() <= TOLERANCE * np.abs(B_fd).max(), method


def test_a_newton_failure_is_a_simulation_error(robot):
    dp = robot("double_pendulum")
    with pytest.raises(ms.SimulationError, match=r"^linearize: Newton did not converge in 1 iteration") as info:
        ms.linearize(dp, [1.0, 0.5], [3.0, -3.0], [0.0, 0.0], 0.05, integrator=ImplicitEuler(max_iterations=1))
    assert info.value.status == "newton_failed"
