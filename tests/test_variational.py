"""The variational integrator against independent references.

Every expected value comes from outside the code under test: finite differences of Pinocchio's kinetic energy and
of the residual, a fine RK4 reference for convergence orders, conservation laws of the exact flow (energy, the
momentum of a symmetry) that RK4 only approaches, the symplectic form, and the closed-form trapezoidal recurrence
that the method must reduce to on a linear system.
"""

from __future__ import annotations

import math
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from conftest import joint, link, urdf

import multibody_sim as ms
from multibody_sim.integrators import INTEGRATORS, StepFailure
from multibody_sim.integrators.variational import VariationalIntegrator, evaluate

RobotFactory = Callable[..., ms.Robot]
METHOD = INTEGRATORS["variational"]


def _tangent_basis(robot: ms.Robot, q: np.ndarray, eps: float) -> list[tuple[np.ndarray, np.ndarray]]:
    """(q ⊕ eps e_i, q ⊕ -eps e_i) for every tangent direction e_i."""
    return [(robot.integrate(q, eps * e), robot.integrate(q, -eps * e)) for e in np.eye(robot.nv)]


def _kinetic_gradient_fd(robot: ms.Robot, q: np.ndarray, w: np.ndarray, eps: float = 1e-6) -> np.ndarray:
    """∂T/∂q at fixed velocity w by central differences of Pinocchio's kinetic energy, shape (nv,)."""
    return np.array(
        [
            (robot.kinetic_energy(a, w) - robot.kinetic_energy(b, w)) / (2 * eps)
            for a, b in _tangent_basis(robot, q, eps)
        ]
    )


def _kinetic_hessian_fd(robot: ms.Robot, q: np.ndarray, w: np.ndarray, eps: float = 1e-4) -> np.ndarray:
    """∂²T/∂q² at fixed w by central second differences of the kinetic energy, shape (nv, nv)."""
    basis = np.eye(robot.nv) * eps

    def kinetic(step: np.ndarray) -> float:
        return robot.kinetic_energy(robot.integrate(q, step), w)

    return np.array(
        [
            [(kinetic(a + b) - kinetic(a - b) - kinetic(b - a) + kinetic(-a - b)) / (4 * eps * eps) for b in basis]
            for a in basis
        ]
    )


def _random_state(robot: ms.Robot, seed: int, speed: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return robot.random_configuration(rng), rng.uniform(-speed, speed, robot.nv)


def _slope(dts: list[float], errors: list[float]) -> float:
    return float(np.polyfit(np.log(dts), np.log(errors), 1)[0])


# ---- the identities the residual is built on ------------------------------------------------------------
@pytest.mark.parametrize("name", ["ur5", "double_pendulum_continuous", "panda"])
def test_kinetic_energy_gradient_identities(robot: RobotFactory, name: str) -> None:
    """∂T/∂q(q, w) = C(q, w)ᵀ w = ½ K(q, w)ᵀ w with K = ∂(M w)/∂q, against finite differences of T."""
    r = robot(name)
    q, w = _random_state(r, seed=1)
    expected = _kinetic_gradient_fd(r, q, w)
    via_coriolis = r.coriolis_matrix(q, w).T @ w
    # K from RNEA derivatives: rnea(q, 0, w) = M(q) w + g(q).
    dtau_dq = pin.computeRNEADerivatives(r.model, r.data, q, np.zeros(r.nv), w)[0].copy()
    K = dtau_dq - pin.computeGeneralizedGravityDerivatives(r.model, r.data, q)
    via_rnea = 0.5 * K.T @ w
    size = np.abs(expected).max()
    # Central differences at 1e-6 are exact to ~1e-10 of the size (truncation 1e-12, round-off 1e-16/1e-6).
    assert np.abs(via_coriolis - expected).max() <= 1e-7 * size
    assert np.abs(via_rnea - expected).max() <= 1e-7 * size


@pytest.mark.parametrize(("name", "damping"), [("ur5", False), ("double_pendulum", True)])
def test_newton_jacobian_against_finite_differences(robot: RobotFactory, name: str, damping: bool) -> None:
    """Newton's Jacobian is dR/dw without exactly the -(h²/4) ∂²T/∂q² term, and that term is O(h²)."""
    r = robot(name, damping=damping)
    q, v = _random_state(r, seed=2, speed=2.0)
    tau = np.random.default_rng(3).uniform(-1.0, 1.0, r.nv)
    p = r.mass_matrix(q) @ v
    w = v + 0.1
    missing = []
    for h in (0.02, 0.01):

        def residual(x: np.ndarray, h: float = h) -> np.ndarray:
            return evaluate(r.model, r.data, r.damping, q, p, tau, h, x).residual

        eps = 1e-6
        J_fd = np.column_stack([(residual(w + eps * e) - residual(w - eps * e)) / (2 * eps) for e in np.eye(r.nv)])
        J = evaluate(r.model, r.data, r.damping, q, p, tau, h, w).jacobian
        q_mid = r.integrate(q, 0.5 * h * w)
        H_T = _kinetic_hessian_fd(r, q_mid, w)
        size = np.abs(J_fd).max()
        # FD of R is good to ~1e-9 of its size; the Hessian's FD error (~1e-7) is scaled down by h²/4.
        assert np.abs(J - h * h / 4 * H_T - J_fd).max() <= 1e-7 * size
        missing.append(np.abs(J - J_fd).max())
    # The dropped term scales as h²: halving h divides it by ~4 (not exactly: q̄ moves with h).
    assert missing[0] / missing[1] == pytest.approx(4.0, rel=0.1)


def _plain_newton_residuals(r: ms.Robot, q: np.ndarray, v: np.ndarray, h: float, n: int) -> np.ndarray:
    """Relative residuals of n iterations of Newton with the Hessian-free Jacobian alone (no secant help)."""
    tau = np.zeros(r.nv)
    p = r.mass_matrix(q) @ v
    w = v + 0.5 * h * r.forward_dynamics(q, v, tau)
    history = []
    for _ in range(n):
        ev = evaluate(r.model, r.data, r.damping, q, p, tau, h, w)
        history.append(np.abs(ev.residual).max() / ev.scale)
        w = w - np.linalg.solve(ev.jacobian, ev.residual)
    return np.array(history)


def test_plain_newton_contracts_at_order_h_squared(robot: RobotFactory) -> None:
    """With the Hessian term dropped, Newton converges linearly at a rate that falls as h² (the derivation)."""
    r = robot("ur5", damping=False)
    q, v = _random_state(r, seed=4)
    hs = [0.08, 0.04, 0.02]
    # The second contraction: past the initial guess's nonlinearity, still far above round-off (1e-16).
    rates = [float(np.divide(*_plain_newton_residuals(r, q, v, h, 3)[2:0:-1])) for h in hs]
    assert max(rates) < 1e-3  # several digits per iteration at ordinary steps
    assert _slope(hs, rates) == pytest.approx(2.0, abs=0.2)


def test_secant_correction_rescues_coarse_steps_and_solution_solves_the_equations(robot: RobotFactory) -> None:
    """At a coarse step where plain Newton crawls (rate > 0.5), the solver still converges fast, and the state
    it returns satisfies the discrete Euler–Lagrange equations to 1e-12 when re-checked from scratch."""
    r = robot("double_pendulum", damping=False)
    # The second link spins at 19 rad/s and turns ~1 rad per step of 0.05 s.
    q, v, h = np.array([3.3977, -0.5038]), np.array([-5.03, 18.98]), 0.05
    plain = _plain_newton_residuals(r, q, v, h, 10)
    assert plain[-1] / plain[-2] > 0.5
    method = VariationalIntegrator()
    q_next, v_next, _ = method.step(r, q, v, np.zeros(2), h)
    assert method.last_iterations <= 10
    assert method.last_evaluations == 3 + 3 * (method.last_iterations + 1)
    # Re-check: w from the returned configuration, momenta from the returned velocity.
    w = r.difference(q, q_next) / h
    ev = evaluate(r.model, r.data, r.damping, q, r.mass_matrix(q) @ v, np.zeros(2), h, w)
    assert np.abs(ev.residual).max() <= 2e-12 * ev.scale  # the tolerance plus round-off of difference()
    assert np.abs(r.mass_matrix(q_next) @ v_next - ev.momentum_next).max() <= 1e-12 * ev.scale


def test_newton_failure_raises_never_returns(robot: RobotFactory) -> None:
    """One Newton iteration cannot reach 1e-12: the step raises StepFailure and simulate stops with status."""
    r = robot("ur5")
    q, v = _random_state(r, seed=5)
    method = VariationalIntegrator(max_iterations=1)
    with pytest.raises(
        StepFailure, match=re.escape("Newton did not solve the discrete Euler–Lagrange equations: relative residual ")
    ) as failure:
        method.step(r, q, v, np.zeros(r.nv), 0.01)
    assert failure.value.status == "newton_failed"
    assert re.fullmatch(r".* > tolerance 1e-12 after 1 iteration\(s\)", str(failure.value))
    with pytest.raises(ms.SimulationError) as stop:
        ms.simulate(r, q, v, duration=0.1, dt=0.01, integrator=method)
    assert stop.value.status == "newton_failed"
    assert stop.value.trajectory is not None
    np.testing.assert_array_equal(stop.value.trajectory.q, [q])  # only the initial state: nothing unconverged


# ---- order, energy, momentum, symplecticity -------------------------------------------------------------
@pytest.mark.parametrize("name", ["ur5", "double_pendulum_continuous"])
def test_convergence_order(robot: RobotFactory, name: str) -> None:
    """The final-state error against a fine RK4 reference falls at the declared order (2)."""
    r = robot(name, damping=False)
    q0, v0 = _random_state(r, seed=11)
    duration = 0.5
    # RK4 at 2^-12 s is ~1e-12 accurate here: far below the smallest error fitted (~4e-4).
    ref = ms.simulate(r, q0, v0, duration=duration, dt=2.0**-12, integrator="rk4", output_dt=duration)
    dts = [2.0**-k for k in range(5, 10)]
    errors = []
    for dt in dts:
        traj = ms.simulate(r, q0, v0, duration=duration, dt=dt, integrator="variational", output_dt=duration)
        errors.append(max(np.abs(r.difference(ref.q[-1], traj.q[-1])).max(), np.abs(traj.v[-1] - ref.v[-1]).max()))
    assert _slope(dts, errors) == pytest.approx(METHOD.order, abs=0.1)


def test_energy_bounded_over_a_long_run_where_rk4_drifts(robot: RobotFactory) -> None:
    """Undamped double pendulum, 2e4 coarse steps: RK4's energy error grows secularly, the variational one
    oscillates with an amplitude that does not grow (backward error analysis of symplectic methods)."""
    r = robot("double_pendulum", damping=False)
    q0, v0 = np.array([math.pi - 1.0, 0.5]), np.zeros(2)
    dt, steps = 0.01, 20_000
    amplitude = {}
    for integrator in ("rk4", "variational"):
        error = ms.simulate(r, q0, v0, duration=steps * dt, dt=dt, integrator=integrator, output_dt=5 * dt).energy_error
        tenth = len(error) // 10
        amplitude[integrator] = np.abs(error[:tenth]).max(), np.abs(error[-tenth:]).max()
    rk4_first, rk4_last = amplitude["rk4"]
    vi_first, vi_last = amplitude["variational"]
    assert rk4_last > 5 * rk4_first  # a linear drift makes this ~10
    assert vi_last < 1.5 * vi_first  # bounded: no trend between the first and the last tenth
    assert max(vi_first, vi_last) < rk4_last


def test_symmetry_momentum_conserved_to_solver_tolerance(robot: RobotFactory) -> None:
    """ur5's shoulder pan axis is vertical and gravity is vertical, so p_0 = (M(q) v)_0 is a constant of the
    motion. RK4's drift in it falls at order 4 (so the exact flow conserves it); the variational integrator
    keeps it to the Newton tolerance per step (discrete Noether)."""
    r = robot("ur5", damping=False)
    q0, v0 = _random_state(r, seed=7)
    # The symmetry, checked on Pinocchio's own terms: M and V do not depend on q_0, and g_0 = 0.
    shifted = q0.copy()
    shifted[0] += 0.7
    np.testing.assert_allclose(r.mass_matrix(shifted), r.mass_matrix(q0), rtol=0, atol=1e-12)
    assert r.potential_energy(shifted) == pytest.approx(r.potential_energy(q0), abs=1e-12)
    assert abs(r.gravity(q0)[0]) < 1e-12

    def drift(dt: float, integrator: str | ms.Integrator, steps: int) -> float:
        traj = ms.simulate(r, q0, v0, duration=steps * dt, dt=dt, integrator=integrator, output_dt=10 * dt)
        p0 = np.array([(r.mass_matrix(q) @ v)[0] for q, v in zip(traj.q, traj.v, strict=True)])
        return float(np.abs(p0 - p0[0]).max() / np.abs(r.mass_matrix(q0) @ v0).max())

    rk4_coarse, rk4_fine = drift(0.01, "rk4", 2000), drift(0.005, "rk4", 4000)
    assert rk4_coarse / rk4_fine == pytest.approx(16.0, rel=0.3)
    steps = 2000
    default = drift(0.01, "variational", steps)
    # 50x tighter than the default: 1e-14 is at the residual's round-off floor (Newton stalled at 1.46e-14 on this
    # machine's BLAS), where a step fails instead of converging.
    tighter = drift(0.01, VariationalIntegrator(tolerance=2e-14), steps)
    # Each step keeps p_0 to its residual, at most 1e-12 of that step's largest term, so even a worst-case
    # linear accumulation stays below steps * 1e-12 of |p|; measured 1.6e-11, against RK4's 5.8e-4.
    assert default <= steps * 1e-12
    assert default <= 1e-6 * rk4_coarse
    # The drift is the solver's and nothing else: a 50x tighter tolerance removes most of it (measured: 97 %).
    assert tighter <= default / 10


@pytest.mark.parametrize(
    ("integrator", "symplectic"), [("variational", True), ("semi_implicit_euler", False), ("rk4", False)]
)
def test_step_map_is_symplectic_in_position_momentum(robot: RobotFactory, integrator: str, symplectic: bool) -> None:
    """The one-step map (q, p) -> (q', p'), p = M(q) v, preserves the canonical form: Φᵀ Ω Φ = Ω with Φ its
    finite-difference Jacobian. Controls: RK4 and velocity-form semi-implicit Euler (M depends on q here) are
    not symplectic, and the same harness must see it."""
    r = robot("double_pendulum", damping=False)
    method, n, h = INTEGRATORS[integrator], 2, 0.05
    q, v = np.array([math.pi - 1.0, 0.8]), np.array([1.0, -2.0])
    tau = np.zeros(n)

    def flow(dq: np.ndarray, dp: np.ndarray) -> np.ndarray:
        qa = r.integrate(q, dq)
        pa = r.mass_matrix(q) @ v + dp
        qb, vb, _ = method.step(r, qa, np.linalg.solve(r.mass_matrix(qa), pa), tau, h)
        return np.concatenate([r.difference(q, qb), r.mass_matrix(qb) @ vb])

    eps = 1e-6
    Phi = np.column_stack(
        [(flow(eps * e[:n], eps * e[n:]) - flow(-eps * e[:n], -eps * e[n:])) / (2 * eps) for e in np.eye(2 * n)]
    )
    Omega = np.block([[np.zeros((n, n)), np.eye(n)], [-np.eye(n), np.zeros((n, n))]])
    defect = np.abs(Phi.T @ Omega @ Phi - Omega).max()
    assert method.symplectic == symplectic
    if symplectic:
        # FD truncation ~eps² times third derivatives (measured 4e-9) plus solver noise 1e-12 / eps at worst.
        assert defect < 1e-7
    else:
        assert defect > 1e-3  # measured 4.5e-2 (RK4) and 0.7 (semi-implicit Euler) at this step


# ---- forcing and the ledger -----------------------------------------------------------------------------
def test_ledger_energy_error_converges_at_order_two(robot: RobotFactory) -> None:
    """With joint damping and time-varying torques, H - H0 - work + dissipated -> 0 at order 2."""
    r = robot("double_pendulum", damping=True)
    assert [name for name, _ in r.ledger_elements] == ["joint_torques", "joint_damping"]
    q0, v0 = np.array([math.pi - 1.2, 0.8]), np.array([0.5, -1.0])

    def controller(t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        return np.array([0.2 * math.sin(3 * t), 0.1 * math.cos(5 * t)])

    dts = [2.0**-k for k in range(5, 9)]
    errors, dissipated = [], []
    for dt in dts:
        traj = ms.simulate(r, q0, v0, duration=2.0, dt=dt, integrator="variational", controller=controller)
        errors.append(np.abs(traj.energy_error).max())
        dissipated.append(traj.dissipated[-1])
    assert _slope(dts, errors) == pytest.approx(2.0, abs=0.1)
    assert min(dissipated) > 0.1  # the damper really took energy out (~0.7 J), so the check is not vacuous


def _slider_urdf(mass: float, damping: float) -> str:
    """A body on a vertical prismatic joint: M constant, V = m g z linear, so L is quadratic."""
    limits = 'lower="-1e4" upper="1e4" effort="100" velocity="100"'
    return urdf(
        link("base"),
        link("slider", mass=mass, com="0 0 0"),
        joint("slide", "base", "slider", kind="prismatic", axis="0 0 1", limits=limits, damping=damping),
    )


def test_linear_system_is_the_trapezoidal_rule_a_stable_not_l_stable(write_urdf: Callable[..., Path]) -> None:
    """On a linear system the method is the trapezoidal rule: it must match that closed-form recurrence, stay
    stable at h·d/m = 50 where RK4 explodes, flip the sign of the stiff mode each step (not L-stable), and
    close the energy ledger exactly (the trapezoidal energy identity: ΔH = h tau w - h d w²)."""
    m, d, g, force, h = 2.0, 200.0, 9.81, 5.0, 0.5
    r = ms.load_robot(write_urdf(_slider_urdf(m, d)))
    assert METHOD.a_stable
    steps = 40
    traj = ms.simulate(
        r,
        [0.0],
        [3.0],
        duration=steps * h,
        dt=h,
        integrator="variational",
        controller=lambda t, q, v: np.array([force]),
    )
    # Closed form: v' = (force/m - g) - (d/m) v, trapezoidal in v, then z by the average velocity.
    lam = d / m
    z, v = [0.0], [3.0]
    for _ in range(steps):
        v_next = ((1 - h * lam / 2) * v[-1] + h * (force / m - g)) / (1 + h * lam / 2)
        z.append(z[-1] + h * (v[-1] + v_next) / 2)
        v.append(v_next)
    np.testing.assert_allclose(traj.v[:, 0], v, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(traj.q[:, 0], z, rtol=1e-12, atol=1e-12)
    settle = (force / m - g) / lam  # the terminal velocity
    transient = traj.v[:, 0] - settle
    assert np.all(np.sign(transient[1:6]) == -np.sign(transient[:5]))  # amplification (1-25)/(1+25) < 0
    assert np.all(np.abs(transient[1:]) <= np.abs(transient[:-1]) * (1 + 1e-12))
    scale = np.abs(traj.total_energy).max()
    assert np.abs(traj.energy_error).max() <= 1e-12 * scale
    # (The overflow on the way to inf is the point here, not a warning to show.)
    with pytest.raises(ms.SimulationError) as rk4, np.errstate(over="ignore", invalid="ignore"):
        ms.simulate(r, [0.0], [3.0], duration=steps * h, dt=h, integrator="rk4")
    assert rk4.value.status == "diverged"


# ---- refusals -----------------------------------------------------------------------------------------------
def test_refuses_floating_bases(robot: RobotFactory) -> None:
    r = robot("solo12")
    message = (
        "integrator 'variational' does not support floating bases yet (robot 'solo12' has one); "
        "use rk4, dp54 or another explicit integrator"
    )
    with pytest.raises(ms.InvalidArgumentError, match=f"^{re.escape(message)}$"):
        METHOD.check_system(r)
    with pytest.raises(ms.InvalidArgumentError, match=f"^{re.escape(message)}$"):
        ms.simulate(r, r.neutral(), np.zeros(r.nv), duration=0.1, dt=0.01, integrator="variational")
    with pytest.raises(ms.InvalidArgumentError, match=f"^{re.escape(message)}$"):  # even if the hook is skipped
        METHOD.step(r, r.neutral(), np.zeros(r.nv), np.zeros(r.nv), 0.01)


def test_refuses_curved_joints_on_a_fixed_base(write_urdf: Callable[..., Path]) -> None:
    text = urdf(link("base"), link("puck", com="0 0 0"), joint("slide", "base", "puck", kind="planar", axis="0 0 1"))
    r = ms.load_robot(write_urdf(text))
    message = (
        "integrator 'variational' supports only revolute, prismatic and continuous joints yet (robot "
        "'robot' has the planar joint 'slide'); use rk4, dp54 or another explicit integrator"
    )
    with pytest.raises(ms.InvalidArgumentError, match=f"^{re.escape(message)}$"):
        METHOD.check_system(r)
