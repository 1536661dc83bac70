"""The energy ledger: Euler's outward spiral, symplectic boundedness, energy-error orders, and the ledger balance."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
import pytest
from scipy.integrate import cumulative_simpson
from scipy.spatial.transform import Rotation

import multibody_sim as ms

# The shipped pendulum (models/pendulum/pendulum.urdf): a 1 kg bob 1 m below the hinge with its own inertia
# 0.001 kg m² about the hinge axis, so I = m l² + 0.001; potential m g z with the bob at z = -l cos θ.
G = 9.81  # Pinocchio's default gravity [m/s²]
PENDULUM_MASS, PENDULUM_LENGTH = 1.0, 1.0
PENDULUM_INERTIA = PENDULUM_MASS * PENDULUM_LENGTH**2 + 0.001
PENDULUM_OMEGA2 = PENDULUM_MASS * G * PENDULUM_LENGTH / PENDULUM_INERTIA  # small-angle ω² [1/s²]
PENDULUM_BOTTOM_ENERGY = -PENDULUM_MASS * G * PENDULUM_LENGTH  # H at rest, hanging [J]
# example-robot-data's double pendulum declares <dynamics damping="0.05"/> on both joints (FIELD_NOTES).
DOUBLE_PENDULUM_DAMPING = np.array([0.05, 0.05])
# Hanging-ish with both links swinging hard: non-trivial, non-chaotic over 1-2 s.
DOUBLE_PENDULUM_Q0 = np.array([np.pi - 1.5, 0.5])
DOUBLE_PENDULUM_V0 = np.array([2.0, 1.0])


def _slope(dts: list[float], errors: list[float]) -> float:
    """Least-squares slope of log(error) against log(dt): the observed order."""
    return float(np.polyfit(np.log(dts), np.log(errors), 1)[0])


def _fixed_step(name: str) -> ms.Integrator:
    method = ms.INTEGRATORS[name]
    if method.adaptive:
        pytest.skip("adaptive: dt is only the first trial step, so nothing here depends on it")
    return method


def _sinusoidal_torque(t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Open-loop torques of ~half the links' gravity torque: they put O(1) J in and take some out."""
    return np.array([0.5 * np.sin(3.0 * t), 0.3 * np.cos(2.0 * t)])


# ---- explicit Euler: the outward spiral ------------------------------------------------------------------
def test_explicit_euler_gains_energy_at_the_linearised_rate(robot: Callable[..., ms.Robot]) -> None:
    """For θ'' = -ω²θ, Euler's step matrix has eigenvalues 1 ± iωdt, so H - H_min grows by |1 + iωdt|² a step.

    Indeed ω²θ² + θ'² is multiplied by exactly 1 + ω²dt² by [[1, dt], [-ω²dt, 1]]. At 0.02 rad the
    pendulum's nonlinearity changes the per-step gain by O(θ²) ~ 1e-3 relative.
    """
    pendulum = robot("pendulum")
    assert np.allclose(pendulum.model.gravity.linear, [0.0, 0.0, -G])  # the premise of the constants above
    dt, duration = 0.01, 20.0  # ten periods; the energy grows ~7-fold, the amplitude to ~0.05 rad
    traj = ms.simulate(pendulum, [0.02], [0.0], duration=duration, dt=dt, integrator="euler")
    excess = traj.total_energy - PENDULUM_BOTTOM_ENERGY
    gain = 1.0 + PENDULUM_OMEGA2 * dt**2
    assert np.all(np.diff(traj.total_energy) > 0.0)  # monotone: every single step gains energy
    per_step = np.diff(excess) / excess[:-1] / (gain - 1.0)
    assert np.all(np.abs(per_step - 1.0) < 5e-3), (per_step.min(), per_step.max())
    n_steps = len(traj) - 1
    np.testing.assert_allclose(np.log(excess[-1] / excess[0]), n_steps * np.log(gain), rtol=1e-3)
    assert excess[-1] / excess[0] > 5.0  # the spiral is no round-off effect


# ---- semi-implicit Euler: bounded on a separable Hamiltonian ---------------------------------------------
def test_semi_implicit_euler_energy_stays_bounded_while_explicit_euler_drifts(
    robot: Callable[..., ms.Robot],
) -> None:
    """1e5 steps on the nonlinear pendulum (M constant, so the velocity form is symplectic).

    Backward error analysis: this method (kick with q_n, then drift with v_{n+1}) exactly follows, up to
    O(dt²), the modified Hamiltonian H̃ = H - (dt/2) θ' V'(θ) (Hairer, Lubich & Wanner, GNI IX.3). So
    H_n - H_0 = (dt/2) (θ'_n V'(θ_n) - θ'_0 V'(θ_0)) + O(dt²): bounded, oscillating, no secular growth.
    """
    pendulum = robot("pendulum")
    dt, duration = 1e-3, 100.0  # 1e5 steps, ~50 periods at 1 rad amplitude
    options = {"duration": duration, "dt": dt, "output_dt": 1e-2}
    semi = ms.simulate(pendulum, [1.0], [0.0], integrator="semi_implicit_euler", **options)
    tenth = len(semi) // 10
    first, last = np.abs(semi.energy_error[:tenth]).max(), np.abs(semi.energy_error[-tenth:]).max()
    assert last < 1.02 * first, (first, last)
    predicted = 0.5 * dt * semi.v[:, 0] * PENDULUM_MASS * G * PENDULUM_LENGTH * np.sin(semi.q[:, 0])
    # The O(dt²) remainder is ~ω dt ~ 3e-3 of the O(dt) term.
    assert np.abs(semi.energy_error - predicted).max() < 1e-2 * np.abs(predicted).max()

    explicit = ms.simulate(pendulum, [1.0], [0.0], integrator="euler", **options)
    first_e, last_e = np.abs(explicit.energy_error[:tenth]).max(), np.abs(explicit.energy_error[-tenth:]).max()
    assert last_e > 5.0 * first_e and last_e > 100.0 * last, (first_e, last_e, last)


# ---- energy-error convergence ----------------------------------------------------------------------------
ENERGY_LADDER = (8, 9, 10, 11)  # dt = 2^-k s; from dt = 2^-7 s down the sequences are asymptotic (midpoint
# slopes 2.3, 2.0, 2.0; rk4 3.8, 3.9, 4.0) and rk4 at 2^-11 s is still 100x above round-off.
ENERGY_FLOOR = 1e-12  # [J]: the energies here are O(1) J; 4000 steps of round-off sit near 1e-13 J


def _energy_error_slope(
    system: ms.Robot, method: ms.Integrator, duration: float, **kwargs: object
) -> tuple[float | None, list[float]]:
    """(slope, errors): observed order of max |energy_error| over the run, against dt over ENERGY_LADDER."""
    dts, errors = [], []
    for k in ENERGY_LADDER:
        dt = 2.0**-k
        traj = ms.simulate(system, DOUBLE_PENDULUM_Q0, DOUBLE_PENDULUM_V0, duration=duration, dt=dt,
                           integrator=method, **kwargs)  # fmt: skip
        dts.append(dt)
        errors.append(traj.max_abs_energy_error)
    kept = [(dt, e) for dt, e in zip(dts, errors, strict=True) if e > ENERGY_FLOOR]
    if len(kept) < 3:
        return None, errors
    return _slope(*zip(*kept, strict=True)), errors


@pytest.mark.parametrize("name", sorted(ms.INTEGRATORS))
def test_energy_error_shrinks_at_least_at_the_method_order(robot: Callable[..., ms.Robot], name: str) -> None:
    """H is Lipschitz on bounded sets, so an order-p method's energy error is O(dt^p) (or better).

    On the conservative double pendulum the ledger is empty, so energy_error is H - H(0).
    """
    method = _fixed_step(name)
    pendulum = robot("double_pendulum", damping=False)
    try:
        method.check_system(pendulum)
    except ms.InvalidArgumentError as exc:
        pytest.skip(f"{name} refuses the double pendulum: {exc}")
    slope, errors = _energy_error_slope(pendulum, method, 1.0, output_dt=2.0**-7)
    if slope is None:  # an energy-preserving method sits at round-off on every rung
        assert max(errors) < 100 * ENERGY_FLOOR, errors
        return
    assert slope > method.order - 0.3, f"{name}: energy-error order {slope:.2f}; errors {errors}"


@pytest.mark.parametrize(("name", "order"), [("rk4", 4), ("midpoint", 2)])
def test_energy_error_order_of_explicit_runge_kutta(robot: Callable[..., ms.Robot], name: str, order: int) -> None:
    """RK methods do not preserve energy: their energy error is exactly of their order, not better."""
    pendulum = robot("double_pendulum", damping=False)
    slope, errors = _energy_error_slope(pendulum, ms.INTEGRATORS[name], 1.0, output_dt=2.0**-7)
    assert slope is not None and abs(slope - order) < 0.3, f"{name}: {slope}, {errors}"


# ---- the ledger with damping and torques -----------------------------------------------------------------
def test_ledger_balances_with_damping_and_torques(robot: Callable[..., ms.Robot]) -> None:
    """Damped double pendulum driven by torques: energy_error is at RK4's accuracy (order 4) while work and
    dissipation are O(1) J, and the ledger's dissipation matches an independent quadrature of vᵀDv."""
    pendulum = robot("double_pendulum", damping=True)
    np.testing.assert_array_equal(pendulum.damping, DOUBLE_PENDULUM_DAMPING)
    assert [kind for _, kind in pendulum.ledger_elements] == ["work", "dissipated"]
    slope, errors = _energy_error_slope(pendulum, ms.INTEGRATORS["rk4"], 2.0, controller=_sinusoidal_torque)
    assert slope is not None and abs(slope - 4) < 0.3, (slope, errors)

    traj = ms.simulate(pendulum, DOUBLE_PENDULUM_Q0, DOUBLE_PENDULUM_V0, duration=2.0, dt=2.0**-11,
                       controller=_sinusoidal_torque)  # fmt: skip
    work, dissipated = traj.work[-1], traj.dissipated[-1]
    assert abs(work) > 0.3 and dissipated > 0.3  # the balance is between sizeable flows ...
    assert traj.max_abs_energy_error < 1e-8 * (abs(work) + dissipated)  # ... and closes to RK4 accuracy
    assert np.all(np.diff(traj.dissipated) >= 0.0)  # vᵀDv ≥ 0: dampers only take energy out

    # Simpson on the samples of vᵀDv; its error is O(dt²) here (the held torque puts kinks in v at every
    # step): ~2e-6 J at dt = 2^-11 s, against 1.3 J dissipated.
    power = np.sum(DOUBLE_PENDULUM_DAMPING * traj.v**2, axis=1)
    np.testing.assert_allclose(traj.dissipated, cumulative_simpson(power, x=traj.t, initial=0.0),
                               rtol=0.0, atol=1e-5 * dissipated)  # fmt: skip
    # Work of the held torque by per-step trapezoids of τ_k·v: also O(dt²).
    steps = np.sum(traj.tau[:-1] * 0.5 * (traj.v[:-1] + traj.v[1:]), axis=1) * np.diff(traj.t)
    np.testing.assert_allclose(traj.work[1:], np.cumsum(steps), rtol=0.0, atol=1e-5 * abs(work))


@pytest.mark.parametrize("name", sorted(ms.INTEGRATORS))
def test_work_of_a_held_torque_is_torque_times_displacement(robot: Callable[..., ms.Robot], name: str) -> None:
    """On revolute joints q' = v, so ∫ τ_k·v dt over a step with τ_k held is exactly τ_k·(q_{k+1} - q_k).

    Every method whose ledger uses the same quadrature as its configuration update meets this to round-off,
    whatever its accuracy: it catches a wrong torque sample, weights or sign in the ledger.
    """
    method = _fixed_step(name)
    pendulum = robot("double_pendulum", damping=True)
    try:
        method.check_system(pendulum)
    except ms.InvalidArgumentError as exc:
        pytest.skip(f"{name} refuses the damped double pendulum: {exc}")
    traj = ms.simulate(pendulum, DOUBLE_PENDULUM_Q0, DOUBLE_PENDULUM_V0, duration=1.0, dt=2.0**-9,
                       integrator=method, controller=_sinusoidal_torque)  # fmt: skip
    displacement_work = np.cumsum(np.sum(traj.tau[:-1] * np.diff(traj.q, axis=0), axis=1))
    assert abs(traj.work[-1]) > 0.1
    np.testing.assert_allclose(traj.work[1:], displacement_work, rtol=0.0, atol=1e-12)
    assert traj.work[0] == 0.0 and traj.dissipated[0] == 0.0


# ---- the ledger on floating bases ------------------------------------------------------------------------
def test_ledger_balances_on_a_floating_quadruped_with_joint_control(robot: Callable[..., ms.Robot]) -> None:
    """solo12 tumbling in free fall while a PD controller drives its joints: ~137 J of potential energy turns
    into kinetic energy, the joints do O(0.1) J of work, and the balance closes at RK4's order."""
    solo = robot("solo12", floating_base=True)
    assert solo.ledger_elements == [("joint_torques", "work")]  # solo12's URDF declares no damping
    rng = np.random.default_rng(5)
    q0 = solo.random_configuration(rng)
    q0[7:] = rng.uniform(-1.0, 1.0, 12)
    v0 = rng.uniform(-1.0, 1.0, solo.nv)
    v0[3:6] *= 3.0
    target = q0[7:].copy()

    def pd(t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        tau = np.zeros(solo.nv)  # the base is unactuated
        # Gains kept soft for the light legs (joint inertias ~5e-4 kg m²): stiff ones would need tiny steps.
        tau[6:] = 1.0 * (target + 0.5 * np.sin(6.0 * t) - q[7:]) - 0.02 * v[6:]
        return tau

    dts, errors = [], []
    for k in (7, 8, 9, 10):
        traj = ms.simulate(solo, q0, v0, duration=1.0, dt=2.0**-k, controller=pd)
        dts.append(2.0**-k)
        errors.append(traj.max_abs_energy_error)
    slope = _slope(dts, errors)
    assert abs(slope - 4) < 0.3, (slope, errors)
    assert abs(traj.work[-1]) > 0.05 and traj.max_abs_energy_error < 1e-6 * abs(traj.work[-1])
    assert abs(traj.potential_energy[-1] - traj.potential_energy[0]) > 100.0  # it really fell
    np.testing.assert_array_equal(traj.dissipated, 0.0)
    # Joints are revolute: the held torque's work is τ·Δq on the joint coordinates (the base takes none).
    displacement_work = np.cumsum(np.sum(traj.tau[:-1, 6:] * np.diff(traj.q[:, 7:], axis=0), axis=1))
    np.testing.assert_allclose(traj.work[1:], displacement_work, rtol=0.0, atol=1e-12)


def test_free_body_falls_along_the_parabola_and_conserves_energy(robot: Callable[..., ms.Robot]) -> None:
    """A spinning box in free fall: its centre of mass (the body origin) follows z0 + ż0 t - g t²/2 whatever
    the tumbling, so V(t) is known in closed form; kinetic energy must rise by exactly what V loses."""
    box = robot("free_body")
    assert box.ledger_elements == [("joint_torques", "work")]
    rng = np.random.default_rng(1)
    q0 = box.random_configuration(rng)
    v0 = np.concatenate([rng.uniform(-1.0, 1.0, 3), 5.0 * rng.normal(size=3)])  # a fast tumble
    # v's linear part is in the body frame; scipy's quaternions are scalar-last like Pinocchio's.
    z_dot0 = (Rotation.from_quat(q0[3:7]).as_matrix() @ v0[:3])[2]
    mass = 2.0  # free_body.urdf
    dts, energy_errors, potential_errors = [], [], []
    for k in (5, 6, 7, 8):
        traj = ms.simulate(box, q0, v0, duration=1.0, dt=2.0**-k)
        z = q0[2] + z_dot0 * traj.t - 0.5 * G * traj.t**2
        dts.append(2.0**-k)
        energy_errors.append(traj.max_abs_energy_error)
        potential_errors.append(np.abs(traj.potential_energy - mass * G * z).max())
    assert abs(_slope(dts, energy_errors) - 4) < 0.3, energy_errors
    assert abs(_slope(dts, potential_errors) - 4) < 0.3, potential_errors
    drop = traj.potential_energy[0] - traj.potential_energy[-1]
    assert drop > 50.0
    np.testing.assert_allclose(traj.kinetic_energy[-1] - traj.kinetic_energy[0], drop, rtol=1e-9)
    np.testing.assert_array_equal(traj.work, 0.0)
