"""Adaptive methods: coefficients, error control, dense output, step collapse, control instants."""

from __future__ import annotations

import re

import numpy as np
import pytest
import scipy.integrate

import multibody_sim as ms
from multibody_sim.integrators.tableau import BOGACKI_SHAMPINE_32, DORMAND_PRINCE_54
from multibody_sim.step_control import PIController

ADAPTIVE = [name for name, method in ms.INTEGRATORS.items() if method.adaptive]


def slope(x: np.ndarray, y: np.ndarray) -> float:
    return float(np.polyfit(np.log(x), np.log(y), 1)[0])


@pytest.mark.parametrize(
    ("tableau", "reference"),
    [(BOGACKI_SHAMPINE_32, scipy.integrate.RK23), (DORMAND_PRINCE_54, scipy.integrate.RK45)],
)
def test_tableaux_match_scipy(tableau, reference) -> None:
    # scipy's published coefficients are an independent transcription of the same papers.
    s = reference.n_stages
    a = np.array(tableau.a)
    assert np.allclose(a[:s, : reference.A.shape[1]], reference.A, atol=1e-15)
    assert np.allclose(tableau.b[:s], reference.B, atol=1e-15)
    assert np.allclose(tableau.c[:s], reference.C, atol=1e-15)
    # scipy's E is (b_hat - b) with the FSAL stage appended.
    assert np.allclose(np.array(tableau.b_hat) - np.array(tableau.b), reference.E, atol=1e-15)
    assert tableau.order == reference.order


def test_adaptive_methods_are_registered() -> None:
    assert set(ADAPTIVE) >= {"bs32", "dp54"}


@pytest.mark.parametrize("name", ADAPTIVE)
def test_global_error_follows_the_tolerance(name: str, robot) -> None:
    pendulum = robot("double_pendulum", damping=False)
    q0, v0 = np.array([2.0, 0.5]), np.zeros(2)
    reference = ms.simulate(pendulum, q0, v0, duration=1.0, dt=2e-4, integrator="rk4", output_dt=0.02)
    tolerances = np.array([1e-5, 1e-7, 1e-9])
    errors = []
    for tol in tolerances:
        traj = ms.simulate(pendulum, q0, v0, duration=1.0, dt=1e-3, integrator=name, rtol=tol, atol=tol, output_dt=0.02)
        np.testing.assert_allclose(traj.t, reference.t, atol=1e-12)
        errors.append(np.abs(traj.q - reference.q).max())
        assert errors[-1] < 100 * tol
    # Tolerance proportionality: the error scales like the tolerance (a slope near 1), for every sample,
    # including the dense-output ones between steps.
    assert 0.7 < slope(tolerances, np.array(errors)) < 1.3


@pytest.mark.parametrize("name", ADAPTIVE)
@pytest.mark.parametrize(
    ("robot_name", "steps"),
    # Ladders in each model's asymptotic range: the double pendulum's light links move fast.
    [("double_pendulum", [0.02, 0.01, 0.005, 0.0025]), ("free_body", [0.16, 0.08, 0.04, 0.02])],
)
def test_dense_output_and_error_estimate_orders(name: str, robot_name: str, steps: list[float], robot) -> None:
    """One trial step from a fixed state: the interpolant's error at θ = 0.4 shrinks like h^(p*+1) with p* its
    order (7 for dop853, 4 for dp54, 3 for bs32), and the error estimate like h^(embedded order + 1)."""
    method = ms.INTEGRATORS[name]
    if name == "dop853":  # 8th order reaches round-off sooner: coarser ladders, above it
        steps = {"double_pendulum": [0.08, 0.04, 0.02, 0.01], "free_body": [0.64, 0.32, 0.16]}[robot_name]
    system = robot(robot_name, damping=False)
    rng = np.random.default_rng(3)
    q = system.random_configuration(rng)
    v = rng.uniform(-2.0, 2.0, system.nv)
    tau = np.zeros(system.nv)
    dense_errors, estimates = [], []
    for h in steps:
        attempt = method.attempt(system, q, v, tau, h, rtol=1.0, atol=1.0)
        q_dense, v_dense, _ = method.dense_output(system, q, v, attempt, h, 0.4)
        exact = ms.simulate(system, q, v, duration=0.4 * h, dt=0.4 * h / 400, integrator="rk4")
        dense_errors.append(
            max(np.abs(system.difference(exact.q[-1], q_dense)).max(), np.abs(exact.v[-1] - v_dense).max())
        )
        estimates.append(attempt.error)
    dense_order = {"dop853": 7, "dp54": 4, "bs32": 3}[name]
    assert slope(np.array(steps), np.array(dense_errors)) == pytest.approx(dense_order + 1, abs=0.5)
    assert slope(np.array(steps), np.array(estimates)) == pytest.approx(method.embedded_order + 1, abs=0.5)


def test_dop853_pays_at_tight_tolerances(robot) -> None:
    """The high-order pair earns its place: at rtol = atol = 1e-10 on ur5 it needs far fewer dynamics
    evaluations than dp54 for a comparable error (against a tighter dop853 reference)."""
    arm = robot("ur5", damping=False)
    q0, v0 = arm.random_configuration(1), np.zeros(6)
    reference = ms.simulate(
        arm, q0, v0, duration=1.0, dt=1e-3, integrator="dop853", rtol=1e-13, atol=1e-13, output_dt=0.05
    )
    runs = {
        name: ms.simulate(arm, q0, v0, duration=1.0, dt=1e-3, integrator=name, rtol=1e-10, atol=1e-10, output_dt=0.05)
        for name in ("dp54", "dop853")
    }
    errors = {name: np.abs(run.q - reference.q).max() for name, run in runs.items()}
    assert errors["dop853"] < 3 * errors["dp54"]  # a comparable error (both ~1e-10) ...
    assert runs["dop853"].stats["evaluations"] < 0.75 * runs["dp54"].stats["evaluations"]  # ... for far less work


def test_dop853_formula_is_high_order_at_fixed_steps(robot) -> None:
    """DOP853's propagating formula at fixed steps on ur5: the error falls by ~2^8 per halving of dt between
    2^-4 and 2^-7 s (above round-off, which it reaches by 2^-8 s); a wrong coefficient would show a low order."""
    arm = robot("ur5", damping=False)
    q0, v0 = arm.random_configuration(20240611), np.zeros(6)
    fixed = ms.ExplicitRungeKutta("dop853_fixed", ms.INTEGRATORS["dop853"].tableau, "dop853 without step control")
    reference = ms.simulate(arm, q0, v0, duration=0.5, dt=2.0**-12, integrator="rk4", output_dt=0.5)
    steps = [2.0**-k for k in range(4, 8)]
    errors = []
    for dt in steps:
        traj = ms.simulate(arm, q0, v0, duration=0.5, dt=dt, integrator=fixed, output_dt=0.5)
        errors.append(np.abs(arm.difference(reference.q[-1], traj.q[-1])).max())
    assert errors[-1] > 1e-12  # still above round-off and the reference's own error
    assert slope(np.array(steps), np.array(errors)) > 7.5


def test_fsal_reuses_the_last_stage(robot) -> None:
    pendulum = robot("double_pendulum", damping=False)
    traj = ms.simulate(pendulum, [2.0, 0.0], [0.0, 0.0], duration=1.0, dt=1e-3, integrator="dp54", rtol=1e-8, atol=1e-8)
    attempts = traj.stats["steps"] + traj.stats["rejected_steps"]
    # 7 stages on the first attempt, 6 new ones on every later attempt (the last stage of an accepted step,
    # or the first stage of a rejected one, is the next attempt's first).
    assert traj.stats["evaluations"] == 7 + 6 * (attempts - 1)


def test_without_output_dt_every_accepted_step_is_a_sample(robot) -> None:
    pendulum = robot("pendulum")
    traj = ms.simulate(pendulum, [1.0], [0.0], duration=2.0, dt=1e-2, integrator="dp54", rtol=1e-6, atol=1e-6)
    assert len(traj.t) == traj.stats["steps"] + 1
    assert traj.t[-1] == 2.0
    assert np.all(np.diff(traj.t) > 0)
    assert traj.max_abs_energy_error < 1e-5


def test_control_instants_are_landed_on(robot) -> None:
    pendulum = robot("pendulum")
    calls: list[float] = []

    def torque(t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        calls.append(t)
        return np.array([0.5 if int(round(t / 0.05)) % 2 == 0 else -0.5])

    traj = ms.simulate(
        pendulum,
        [0.3],
        [0.0],
        duration=1.0,
        dt=0.2,
        integrator="dp54",
        rtol=1e-9,
        atol=1e-9,
        control_dt=0.05,
        output_dt=0.01,
        controller=torque,
    )
    np.testing.assert_allclose(calls, np.arange(20) * 0.05, atol=1e-12)
    np.testing.assert_allclose(traj.t, np.arange(101) * 0.01, atol=1e-12)
    # Torque rows: the value in force from each sample on.
    expected = np.array([0.5 if int(np.floor(t / 0.05 + 1e-9)) % 2 == 0 else -0.5 for t in traj.t[:-1]])
    np.testing.assert_allclose(traj.tau[:-1, 0], expected)
    # The square wave does work; the ledger still balances at the tolerance.
    assert np.abs(traj.work).max() > 5e-3
    assert traj.max_abs_energy_error < 1e-7
    # The same chain of constant-torque segments, integrated separately by rk4 at a fine step, agrees.
    q, v = np.array([0.3]), np.array([0.0])
    for k in range(20):
        seg = ms.simulate(
            pendulum,
            q,
            v,
            duration=0.05,
            dt=0.05 / 200,
            integrator="rk4",
            controller=lambda t, q, v, k=k: np.array([0.5 if k % 2 == 0 else -0.5]),
        )
        q, v = seg.q[-1], seg.v[-1]
    assert np.abs(traj.q[-1] - q).max() < 1e-7


def test_floating_body_conserves_energy_and_momentum() -> None:
    body = ms.load_robot("free_body")
    body.model.gravity.linear = np.zeros(3)  # a free body in space: pure rotation, energy all kinetic
    q0 = body.neutral()
    v0 = np.array([0.0, 0.0, 0.0, 0.05, 6.0, 0.05])  # spin near the intermediate axis: it tumbles
    traj = ms.simulate(body, q0, v0, duration=5.0, dt=1e-3, integrator="dp54", rtol=1e-9, atol=1e-9, output_dt=0.05)
    assert traj.max_abs_energy_error < 1e-6 * traj.total_energy[0]
    # World-frame angular momentum R(q) I ω is conserved by the exact flow (gravity acts at the centre of mass).
    inertia = body.model.inertias[1].inertia
    rotations = [ms_rotation(q) for q in traj.q]
    momenta = np.array([R @ inertia @ v[3:] for R, v in zip(rotations, traj.v, strict=True)])
    assert np.abs(momenta - momenta[0]).max() < 1e-6 * np.linalg.norm(momenta[0])
    # ... and it tumbles: the body-frame spin about y reverses.
    assert traj.v[:, 4].min() < -0.5 * v0[4]


def ms_rotation(q: np.ndarray) -> np.ndarray:
    x, y, z, w = q[3:7]
    return np.array(
        [
            [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
            [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
            [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
        ]
    )


class _BlowUp(ms.Robot):
    """A pendulum with an extra force that sends it to infinity in finite time (t* = 1/(2 v0))."""

    def unchecked_forward_dynamics(self, q, v, tau, t=0.0):
        return np.array([2.0 * v[0] ** 3])  # v' = 2 v³  ⇒  v = v0 / sqrt(1 - 4 v0² t)


def test_step_collapse_stops_cleanly(robot) -> None:
    base = robot("pendulum")
    blow_up = _BlowUp(base.model, name="blow_up", floating_base=False)
    with pytest.raises(ms.SimulationError) as caught:
        ms.simulate(
            blow_up, [0.0], [1.0], duration=1.0, dt=1e-3, integrator="dp54", rtol=1e-8, atol=1e-8, output_dt=1.0
        )
    error = caught.value
    assert error.status == "step_collapsed"
    assert re.match(
        r"step_collapsed at t = 0\.2[45]\d* s \(step \d+\): the step fell to .* s, below the 1e-12 s "
        r"minimum",
        str(error),
    ), str(error)
    traj = error.trajectory
    assert np.all(np.isfinite(traj.q)) and np.all(np.isfinite(traj.v))
    assert traj.t[-1] == pytest.approx(0.25, abs=1e-3)  # the singularity at t* = 1/4 s


def test_adaptive_methods_need_tolerances(robot) -> None:
    pendulum = robot("pendulum")
    with pytest.raises(
        ms.InvalidArgumentError,
        match=re.escape(
            "integrator 'dp54' is adaptive: pass rtol and atol (error tolerances; e.g. rtol=1e-6, atol=1e-8)"
        ),
    ):
        ms.simulate(pendulum, [0.1], [0.0], duration=1.0, dt=1e-3, integrator="dp54")
    with pytest.raises(ms.InvalidArgumentError, match=re.escape("integrator 'bs32' is adaptive: pass atol")):
        ms.simulate(pendulum, [0.1], [0.0], duration=1.0, dt=1e-3, integrator="bs32", rtol=1e-6)
    with pytest.raises(ms.InvalidArgumentError, match=re.escape("rtol must be a positive number of units, got -1.0")):
        ms.simulate(pendulum, [0.1], [0.0], duration=1.0, dt=1e-3, integrator="bs32", rtol=-1.0, atol=1e-6)


def test_max_step_is_respected(robot) -> None:
    pendulum = robot("pendulum")
    traj = ms.simulate(
        pendulum, [0.1], [0.0], duration=2.0, dt=1e-3, integrator="dp54", rtol=1e-4, atol=1e-4, max_step=0.01
    )
    assert np.diff(traj.t).max() <= 0.01 + 1e-12


def test_pi_controller_rules() -> None:
    control = PIController(error_order=4, max_step=0.5)
    accepted, h = control.next_step(0.1, 0.01)
    assert accepted and 0.1 < h <= 0.5
    accepted, h_rejected = control.next_step(0.1, 4.0)
    assert not accepted and 0.02 <= h_rejected < 0.1
    accepted, h_after = control.next_step(0.05, 1e-6)
    assert accepted and h_after == pytest.approx(0.05)  # no growth right after a rejection
    accepted, h_inf = control.next_step(0.05, float("inf"))
    assert not accepted and h_inf == pytest.approx(0.01)
    control.next_step(0.01, 0.5)  # an acceptance clears the no-growth rule
    accepted, h_big = control.next_step(0.4, 1e-9)
    assert accepted and h_big == 0.5  # capped at max_step
