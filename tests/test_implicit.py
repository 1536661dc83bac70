"""Implicit integrators: orders, the analytic Newton Jacobian, stiffness, linear stability, Newton failures.

References, all independent of the implicit code: fine-step RK4 runs, central finite differences, the
stability functions of backward Euler and implicit midpoint on the linear test equation, the pendulum's
frequency from its URDF constants, and the methods' defining equations written out with the public API.
"""

from __future__ import annotations

import functools
import math
import re
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from conftest import joint, link, urdf

import multibody_sim as ms
from multibody_sim.integrators import StepFailure
from multibody_sim.integrators.implicit import ImplicitEuler, ImplicitMidpoint, residual, residual_jacobian
from multibody_sim.state import ConfigurationSpace

IMPLICIT = ["implicit_euler", "implicit_midpoint"]
ORDER = {"implicit_euler": 1, "implicit_midpoint": 2}
FRACTION = {"implicit_euler": 1.0, "implicit_midpoint": 0.5}  # the unknown velocity acts over s = FRACTION·h
RK4_STABILITY_BOUND = 2.785293563405282  # RK4's stability interval on the negative real axis is [-2.7853, 0]

# A heavy upper link swinging slowly, with a light tip (10 g) on a heavily damped elbow (100 N·m·s/rad): the
# tip's motion relative to the upper link decays at ~4e4 /s, the slowest mode at ~5e-4 /s.
STIFF_ARM = urdf(
    '<link name="base"/>',
    link("upper", mass=1.0, com="0 0 -0.5", inertia="0.01 0.01 0.01"),
    link("tip", mass=0.01, com="0 0 -0.5", inertia="1e-4 1e-4 1e-4"),
    joint("shoulder", "base", "upper", damping=0.05),
    joint("elbow", "upper", "tip", xyz="0 0 -1", damping=100.0),
    name="stiff_arm",
)


@pytest.fixture
def stiff_arm(write_urdf: Callable[..., Path]) -> ms.Robot:
    return ms.load_robot(write_urdf(STIFF_ARM, "stiff_arm.urdf"))


def state_error(system: ms.Robot, a: ms.Trajectory, b: ms.Trajectory) -> float:
    """‖(q_a ⊖ q_b, v_a - v_b)‖∞ at the final sample."""
    dq = system.space.difference(b.q[-1], a.q[-1])
    return float(max(np.max(np.abs(dq)), np.max(np.abs(a.v[-1] - b.v[-1]))))


def fitted_slope(steps: list[float], values: list[float]) -> float:
    return float(np.polyfit(np.log(steps), np.log(values), 1)[0])


def linearisation(system: ms.Robot, q: np.ndarray) -> np.ndarray:
    """The state matrix [[0, I], [da/dq, da/dv]] at (q, v = 0, tau = 0), shape (2 nv, 2 nv)."""
    nv = system.nv
    da_dq, da_dv, _ = system.unchecked_dynamics_derivatives(q, np.zeros(nv), np.zeros(nv))
    return np.block([[np.zeros((nv, nv)), np.eye(nv)], [da_dq, da_dv]])


# ---- registry and flags ----------------------------------------------------------------------------------
@pytest.mark.parametrize("name", IMPLICIT)
def test_registered_with_the_flags_the_methods_have(name):
    method = ms.INTEGRATORS[name]
    assert (method.order, method.implicit, method.a_stable, method.adaptive) == (ORDER[name], True, True, False)
    # Neither is symplectic for general M(q); implicit midpoint is for constant M only, and must say so.
    assert not method.symplectic
    if name == "implicit_midpoint":
        assert "symplectic only where M is constant" in method.notes


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"max_iterations": 0}, "max_iterations must be a positive integer, got 0"),
        ({"max_iterations": 2.5}, "max_iterations must be a positive integer, got 2.5"),
        ({"rtol": 0.0}, "rtol must be positive and finite, got 0.0"),
        ({"atol": math.inf}, "atol must be positive and finite, got inf"),
    ],
)
def test_newton_settings_are_checked(kwargs, message):
    with pytest.raises(ValueError, match=re.escape(message)):
        ImplicitEuler(**kwargs)


# ---- observed order against a fine RK4 reference -------------------------------------------------------
ORDER_CASES = {
    # (robot, floating_base, seed, torque on the actuated joints [N·m]); panda is damped, solo12 and
    # free_body are floating bases (free_body has no actuated joint: pure SE(3) motion in gravity).
    "panda": ("panda", None, 1, 0.05),
    "solo12": ("solo12", None, 1, 0.05),
    "free_body": ("free_body", None, 2, 0.0),
}
ORDER_STEPS = [2.0**-k for k in range(7, 12)]
ORDER_HORIZON = 0.25


@functools.cache
def _order_problem(case: str) -> tuple[ms.Robot, np.ndarray, np.ndarray, np.ndarray, ms.Trajectory]:
    name, floating_base, seed, torque = ORDER_CASES[case]
    system = ms.load_robot(name, floating_base=floating_base)
    rng = np.random.default_rng(seed)
    q0 = system.random_configuration(rng)
    v0 = 0.2 * rng.normal(size=system.nv)
    tau = np.zeros(system.nv)
    tau[6 if system.floating_base else 0 :] = torque
    reference = ms.simulate(
        system, q0, v0, duration=ORDER_HORIZON, dt=2.0**-13, integrator="rk4", controller=lambda t, q, v: tau
    )
    return system, q0, v0, tau, reference


@pytest.mark.parametrize("case", sorted(ORDER_CASES))
@pytest.mark.parametrize("name", IMPLICIT)
def test_observed_order(case, name):
    system, q0, v0, tau, reference = _order_problem(case)
    errors = [
        state_error(
            system,
            ms.simulate(system, q0, v0, duration=ORDER_HORIZON, dt=dt, integrator=name, controller=lambda t, q, v: tau),
            reference,
        )
        for dt in ORDER_STEPS
    ]
    # The reference's own error (RK4 at 2^-13 s against 2^-14 s: 1e-13 to 1.3e-11) is 100x below every point.
    assert min(errors) > 100 * 1.3e-11
    assert fitted_slope(ORDER_STEPS, errors) == pytest.approx(ORDER[name], abs=0.12)


@pytest.mark.parametrize("name", IMPLICIT)
@pytest.mark.parametrize("case", ["panda", "stiff_arm"])
def test_energy_error_of_a_damped_torqued_run_converges_at_the_methods_order(name, case, stiff_arm):
    """The ledger (work in, damping out) is integrated with the method's own quadrature, so H - H0 - W + D
    vanishes at the method's order; a ledger quadrature of a lower order would cap the slope."""
    if case == "panda":
        system = ms.load_robot("panda")
        q0 = system.random_configuration(np.random.default_rng(3))
        tau = np.full(system.nv, 0.5)
    else:
        # The elbow torque makes the tip creep against the heavy elbow damping, which then dissipates.
        system, q0, tau = stiff_arm, np.array([0.5, 0.0]), np.array([2.0, 1.0])
    steps = [2.0**-k for k in range(6, 10)]
    errors = []
    for dt in steps:
        run = ms.simulate(
            system, q0, np.zeros(system.nv), duration=0.25, dt=dt, integrator=name, controller=lambda t, q, v: tau
        )
        assert abs(run.work[-1]) > 1e-3 and run.dissipated[-1] > 1e-3  # both ledger columns are exercised
        errors.append(run.max_abs_energy_error)
    assert fitted_slope(steps, errors) == pytest.approx(ORDER[name], abs=0.15)


# ---- the returned state solves the method's equations ----------------------------------------------------
@pytest.mark.parametrize("name", IMPLICIT)
@pytest.mark.parametrize("robot_name", ["panda", "solo12"])
def test_a_step_satisfies_the_defining_equations(name, robot_name, robot):
    """Written out with the public Robot API, independently of the residual the Newton solver uses."""
    system = robot(robot_name)
    rng = np.random.default_rng(7)
    q, v = system.random_configuration(rng), rng.normal(size=system.nv)
    tau = np.zeros(system.nv)
    tau[6 if system.floating_base else 0 :] = rng.normal(size=system.nv - (6 if system.floating_base else 0))
    h = 0.01
    q_next, v_next, flows = ms.INTEGRATORS[name].step(system, q, v, tau, h)
    if name == "implicit_euler":
        x, q_eval, v_eval = v_next, q_next, v_next
        defect = v_next - v - h * system.forward_dynamics(q_next, v_next, tau)
    else:
        x = 0.5 * (v + v_next)
        q_eval, v_eval = system.integrate(q, 0.5 * h * x), x
        defect = x - v - 0.5 * h * system.forward_dynamics(q_eval, x, tau)
    assert np.max(np.abs(system.difference(system.integrate(q, h * x), q_next))) < 1e-14
    # Newton's tolerance is 1e-10 (relative + absolute) in x; the defect is that times ‖dR/dx‖ at most.
    assert np.max(np.abs(defect)) < 1e-9
    # The ledger: joint-torque work tau·v and damping v·D·v, taken where the method takes its velocity.
    expected = h * np.array([tau @ v_eval] + ([v_eval @ (system.damping * v_eval)] if system.damping.any() else []))
    np.testing.assert_allclose(flows, expected, rtol=1e-13, atol=1e-15)
    assert system.space.is_normalized(q_eval)


# ---- the analytic Newton Jacobian against finite differences ------------------------------------------
def _finite_difference_jacobian(system, q, v, tau, s, x, eps=1e-4):
    columns = []
    for j in range(system.nv):
        step = np.zeros(system.nv)
        step[j] = eps
        plus, _ = residual(system, q, v, tau, s, x + step)
        minus, _ = residual(system, q, v, tau, s, x - step)
        columns.append((plus - minus) / (2 * eps))
    return np.column_stack(columns)


@pytest.mark.parametrize("model", ["panda", "stiff_arm", "solo12", "free_body"])
def test_newton_jacobian_matches_finite_differences(model, robot, stiff_arm):
    system = stiff_arm if model == "stiff_arm" else robot(model)
    rng = np.random.default_rng(11)
    q, v, x = system.random_configuration(rng), rng.normal(size=system.nv), 2.0 * rng.normal(size=system.nv)
    tau = np.zeros(system.nv)
    # Small torques: solo12's light legs turn N·m into 1e3 rad/s², whose round-off would swamp the differences.
    tau[6 if system.floating_base else 0 :] = 0.1 * rng.normal(size=system.nv - (6 if system.floating_base else 0))
    s = 0.05  # a coarse step, so that the chart and q-dependence terms are far above the differencing error
    R, q_x = residual(system, q, v, tau, s, x)
    analytic = residual_jacobian(system, q, tau, s, x, q_x)
    numeric = _finite_difference_jacobian(system, q, v, tau, s, x)
    scale = np.max(np.abs(numeric))
    # Central differences at eps = 1e-4: truncation ~eps² |R'''| and round-off ~1e-16 |s a| / eps, both
    # well below 1e-7 of the Jacobian's scale here (measured: 4e-9 at worst, on solo12).
    assert np.max(np.abs(analytic - numeric)) < 1e-7 * scale
    if system.floating_base:
        # The dIntegrate chain factor matters: leaving it out is visible 100x above the tolerance.
        da_dq, da_dv, _ = system.unchecked_dynamics_derivatives(q_x, x, tau)
        naive = np.eye(system.nv) - s * (s * da_dq + da_dv)
        assert np.max(np.abs(naive - numeric)) > 100 * 1e-7 * scale


# ---- stiffness: a light link on a heavily damped joint --------------------------------------------------
def test_stiff_arm_has_a_stiffness_ratio_above_1e4(stiff_arm):
    eigenvalues = np.linalg.eigvals(linearisation(stiff_arm, np.zeros(2)))
    decay = np.abs(eigenvalues.real)
    assert np.all(eigenvalues.real < 0.0)  # the hanging equilibrium is asymptotically stable
    assert decay.max() / decay.min() >= 1e4
    # The fast mode is the elbow damping acting on the tip through the inverse mass matrix: rate ≈ d2 (M^-1)_22
    # = d2 M11 / det M, with the two-link M at q = 0 from the URDF's constants (gravity and the shoulder's
    # damping shift it by ~1e-5).
    m1, c1, i1, m2, l1, c2, i2 = 1.0, 0.5, 0.01, 0.01, 1.0, 0.5, 1e-4
    M11 = i1 + m1 * c1**2 + i2 + m2 * (l1**2 + c2**2 + 2 * l1 * c2)
    M12 = i2 + m2 * (c2**2 + l1 * c2)
    M22 = i2 + m2 * c2**2
    assert decay.max() == pytest.approx(100.0 * M11 / (M11 * M22 - M12**2), rel=1e-3)


def _rk4_run(system: ms.Robot, dt: float) -> ms.Trajectory:
    try:
        return ms.simulate(system, [0.5, 0.0], [0.0, 0.0], duration=0.05, dt=dt, integrator="rk4")
    except ms.SimulationError as failure:
        return failure.trajectory


def test_rk4_stability_limit_is_set_by_the_fast_mode(stiff_arm):
    """RK4 is stable while |h λ_fast| stays inside its real stability interval, and blows up just beyond."""
    fast = np.max(np.abs(np.linalg.eigvals(linearisation(stiff_arm, np.zeros(2))).real))
    limit = RK4_STABILITY_BOUND / fast
    stable, unstable = _rk4_run(stiff_arm, 0.9 * limit), _rk4_run(stiff_arm, 1.1 * limit)
    assert stable.status == "completed"
    # The stable run's elbow creeps at < 1e-3 rad/s; past the limit the fast mode grows by 1.5x a step until
    # the blow-up check stops the run (five orders of magnitude above the stable creep).
    assert np.max(np.abs(stable.v[:, 1])) < 1e-3
    assert np.max(np.abs(unstable.v[:, 1])) > 1e2


def test_rk4_just_past_its_stability_limit_is_reported_as_diverged(stiff_arm):
    fast = np.max(np.abs(np.linalg.eigvals(linearisation(stiff_arm, np.zeros(2))).real))
    assert _rk4_run(stiff_arm, 1.1 * RK4_STABILITY_BOUND / fast).status == "diverged"


def test_implicit_methods_are_stable_and_accurate_where_rk4_diverges(stiff_arm):
    fast = np.max(np.abs(np.linalg.eigvals(linearisation(stiff_arm, np.zeros(2))).real))
    q0, v0, horizon = np.array([0.5, 0.0]), np.zeros(2), 0.5
    # RK4 at 2^-15 s (|h λ| = 1.3, well inside its stability interval) is the reference.
    reference = ms.simulate(stiff_arm, q0, v0, duration=horizon, dt=2.0**-15, integrator="rk4")
    motion = max(np.ptp(reference.q[:, 0]), np.ptp(reference.v[:, 0]))
    steps = [2.0**-k for k in range(6, 10)]
    assert min(steps) > 10 * RK4_STABILITY_BOUND / fast  # every step is at least 10x past RK4's limit
    for dt in steps:
        with pytest.raises(ms.SimulationError) as failure:
            ms.simulate(stiff_arm, q0, v0, duration=horizon, dt=dt, integrator="rk4")
        assert failure.value.status == "diverged"
    for name, coarse_bound in [("implicit_euler", 0.2), ("implicit_midpoint", 0.005)]:
        errors = [
            state_error(stiff_arm, ms.simulate(stiff_arm, q0, v0, duration=horizon, dt=dt, integrator=name), reference)
            for dt in steps
        ]
        # Accurate: the classical order holds in the stiff regime (no order reduction), and even the coarsest
        # step tracks the swing (bounds: O(h) and O(h²) relative errors at h = 2^-6 s against a 1.5 s period).
        assert fitted_slope(steps, errors) == pytest.approx(ORDER[name], abs=0.12)
        assert errors[0] < coarse_bound * motion
        # Stable at far coarser steps too, up to a tenth of the horizon: finite, and with no torque the energy
        # error stays below the energy above rest (all that the damped swing could ever lose).
        coarse = ms.simulate(stiff_arm, q0, v0, duration=horizon, dt=horizon / 10, integrator=name)
        above_rest = reference.total_energy[0] - stiff_arm.potential_energy(np.zeros(2))
        assert np.all(np.abs(coarse.energy_error) < above_rest)


@pytest.mark.parametrize("name", IMPLICIT)
def test_one_step_on_the_linearised_stiff_arm_is_the_stability_function(name, stiff_arm):
    """Near equilibrium a step is x1 = R(hA) x0: backward Euler (I - hA)^-1, midpoint (I - hA/2)^-1 (I + hA/2).

    The fast mode shows L-stability apart from A-stability: backward Euler removes it in one step, implicit
    midpoint keeps it ringing with alternating sign (R(z) -> -1 as z -> -inf).
    """
    A = linearisation(stiff_arm, np.zeros(2))
    h = 2.0**-7  # |h λ_fast| ≈ 326
    x0 = 1e-5 * np.array([0.3, -0.2, 0.5, 1.0])  # small: quadratic terms are 1e-5 of the linear ones
    q1, v1, _ = ms.INTEGRATORS[name].step(stiff_arm, x0[:2], x0[2:], np.zeros(2), h)
    identity = np.eye(4)
    if name == "implicit_euler":
        expected = np.linalg.solve(identity - h * A, x0)
    else:
        expected = np.linalg.solve(identity - 0.5 * h * A, (identity + 0.5 * h * A) @ x0)
    np.testing.assert_allclose(np.concatenate([q1, v1]), expected, rtol=0, atol=1e-4 * np.max(np.abs(x0)))
    # Excite only the fast mode's velocity (elbow) from rest and look one step later.
    _, v_fast, _ = ms.INTEGRATORS[name].step(stiff_arm, np.zeros(2), np.array([0.0, 1e-5]), np.zeros(2), h)
    gain = v_fast[1] / 1e-5
    if name == "implicit_euler":
        assert abs(gain) < 0.01
    else:
        assert -1.0 < gain < -0.95


# ---- an undamped oscillator at large steps: artificial damping and phase error ----------------------------
# The catalog pendulum: 1 kg at l = 1 m on a hinge, bob inertia I_yy = 0.001 kg m², gravity 9.81 m/s².
PENDULUM_OMEGA = math.sqrt(1.0 * 9.81 * 1.0 / (1.0 * 1.0**2 + 0.001))


@pytest.mark.parametrize("omega_h", [0.5, 2.0])
@pytest.mark.parametrize("name", IMPLICIT)
def test_linear_oscillator_amplitude_and_phase(name, omega_h, robot):
    """On z' = iωz (z = ωθ - iθ'), backward Euler multiplies z by 1/(1 - iωh) per step: energy x 1/(1 + (ωh)²),
    phase atan(ωh); implicit midpoint by (1 + iωh/2)/(1 - iωh/2): energy kept, phase 2 atan(ωh/2)."""
    system = robot("pendulum", damping=False)
    omega = PENDULUM_OMEGA
    h, n = omega_h / omega, 8
    theta0 = 1e-3  # small: the pendulum's nonlinearity changes ω by θ²/16 ≈ 6e-8
    run = ms.simulate(system, [theta0], [0.0], duration=n * h, dt=h, integrator=name)
    assert len(run) == n + 1
    energy = run.total_energy - system.potential_energy(np.zeros(1))
    z = omega * run.q[:, 0] - 1j * run.v[:, 0]
    per_step_energy = (energy[-1] / energy[0]) ** (1 / n)
    per_step_phase = np.unwrap(np.angle(z))[-1] / n
    if name == "implicit_euler":
        assert per_step_energy == pytest.approx(1 / (1 + omega_h**2), rel=1e-5)
        assert per_step_phase == pytest.approx(math.atan(omega_h), rel=1e-5)
    else:
        assert per_step_energy == pytest.approx(1.0, rel=1e-5)
        numerical_frequency = per_step_phase / h
        assert numerical_frequency == pytest.approx(2 * math.atan(omega_h / 2) / h, rel=1e-5)
        assert abs(numerical_frequency - omega) > 0.01 * omega  # the phase error is real, not round-off


# ---- Newton failures: a clear status, the samples so far, never a wrong state ----------------------------
def test_newton_failure_mid_run_keeps_the_converged_samples(robot):
    """Hanging at rest the step is trivial (one iteration); a torque from t = 0.1 s needs more than the
    one iteration allowed, so the run stops there with every sample before it."""
    system = robot("pendulum")  # hanging straight down at q = 0: gravity's torque is exactly zero
    hanging = np.zeros(1)

    def kick(t, q, v):
        return np.ones(1) if t >= 0.1 - 1e-12 else np.zeros(1)

    with pytest.raises(ms.SimulationError) as failure:
        ms.simulate(
            system,
            hanging,
            np.zeros(1),
            duration=1.0,
            dt=0.02,
            integrator=ImplicitEuler(max_iterations=1),
            controller=kick,
        )
    error = failure.value
    assert error.status == "newton_failed"
    assert re.match(
        re.escape("newton_failed at t = 0.1 s (step 6): Newton did not converge in 1 iteration (last update norm "),
        str(error),
    )
    traj = error.trajectory
    assert traj.status == "newton_failed"
    np.testing.assert_allclose(traj.t, 0.02 * np.arange(6), atol=1e-15)
    assert np.all(np.isfinite(traj.q)) and np.all(np.isfinite(traj.v))
    np.testing.assert_allclose(traj.q, np.tile(hanging, (6, 1)), atol=1e-12)  # it rested, as it should


@pytest.mark.parametrize("name", IMPLICIT)
def test_an_absurd_step_on_a_floating_base_fails_with_newton_failed(name, robot):
    system = robot("solo12")
    rng = np.random.default_rng(5)
    q0, v0 = system.random_configuration(rng), 3.0 * rng.normal(size=system.nv)
    with pytest.raises(ms.SimulationError) as failure:
        ms.simulate(system, q0, v0, duration=5.0, dt=1.0, integrator=name)
    assert failure.value.status == "newton_failed"
    assert str(failure.value).startswith("newton_failed at t = 0 s (step 1): Newton")
    traj = failure.value.trajectory
    assert len(traj) == 1 and np.all(np.isfinite(traj.q)) and np.all(np.isfinite(traj.v))


class LinearSlider:
    """A 1-DoF stub system with v' = c·v (or NaN), to reach the solver's singular and non-finite branches."""

    def __init__(self, c: float):
        model = pin.Model()
        model.addJoint(0, pin.JointModelPX(), pin.SE3.Identity(), "slider")
        self.space = ConfigurationSpace(model)
        self.nq = self.nv = 1
        self.c = c

    def unchecked_forward_dynamics(self, q, v, tau, t=0.0):
        return self.c * v

    def unchecked_dynamics_derivatives(self, q, v, tau, t=0.0):
        return np.zeros((1, 1)), np.full((1, 1), self.c), np.ones((1, 1))

    def ledger_power(self, q, v, tau, out=None, t=0.0):
        return np.array([tau @ v])


def test_a_singular_newton_jacobian_is_a_step_failure():
    """Backward Euler on v' = c v has the pole h c = 1 of R(z) = 1/(1 - z): dR/dx = 1 - h c = 0."""
    h, method = 0.25, ImplicitEuler()
    with pytest.raises(
        StepFailure,
        match=re.escape("Newton's Jacobian is singular at iteration 1 (pivots from 0 to 0, residual norm 1)"),
    ) as failure:
        method.step(LinearSlider(1 / h), np.zeros(1), np.ones(1), np.zeros(1), h)
    assert failure.value.status == "newton_failed"
    # A failed solve's cost is counted too: one residual, one Jacobian.
    assert (method.last_evaluations, method.last_jacobian_evaluations) == (1, 1)


def test_a_non_finite_residual_is_a_step_failure():
    with pytest.raises(StepFailure, match=re.escape("Newton's residual became non-finite at iteration 1")) as failure:
        ImplicitMidpoint().step(LinearSlider(math.nan), np.zeros(1), np.ones(1), np.zeros(1), 0.1)
    assert failure.value.status == "newton_failed"


# ---- honest counts --------------------------------------------------------------------------------------
class CountingSystem:
    """Forwards to a robot and counts forward-dynamics and derivative calls."""

    def __init__(self, system: ms.Robot):
        self._system = system
        self.space, self.nq, self.nv = system.space, system.nq, system.nv
        self.dynamics_calls = self.derivative_calls = 0

    def unchecked_forward_dynamics(self, q, v, tau, t=0.0):
        self.dynamics_calls += 1
        return self._system.unchecked_forward_dynamics(q, v, tau)

    def unchecked_dynamics_derivatives(self, q, v, tau, t=0.0):
        self.derivative_calls += 1
        return self._system.unchecked_dynamics_derivatives(q, v, tau)

    def ledger_power(self, q, v, tau, out=None, t=0.0):
        return self._system.ledger_power(q, v, tau)


@pytest.mark.parametrize("name", IMPLICIT)
@pytest.mark.parametrize("dt", [1e-3, 0.05])
def test_last_evaluations_counts_every_dynamics_call(name, dt, robot):
    counting = CountingSystem(robot("panda"))
    method = ms.INTEGRATORS[name]
    rng = np.random.default_rng(2)
    q, v = counting._system.random_configuration(rng), rng.normal(size=counting.nv)
    method.step(counting, q, v, np.zeros(counting.nv), dt)
    assert method.last_evaluations == counting.dynamics_calls == method.last_iterations
    assert method.last_jacobian_evaluations == counting.derivative_calls >= 1
