"""The stepping loop: sampling, controller timing (zero-order hold), early stops, limit reports, metadata."""

from __future__ import annotations

import hashlib
import importlib.metadata
import json
import math
import re
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
import pytest
from conftest import joint, link, urdf
from scipy.integrate import solve_ivp, trapezoid
from scipy.special import ellipk

import multibody_sim as ms

# The pendulum written below: a 1 kg point-like bob (inertia 1e-3 kg·m² about its centre) 1 m below a hinge
# about y, so about the hinge I = 1e-3 + 1 · 1² kg·m² and the gravity torque is -m g l sin(q).
MASS, LENGTH, BOB_INERTIA, G = 1.0, 1.0, 1e-3, 9.81
I_HINGE = BOB_INERTIA + MASS * LENGTH**2
MGL = MASS * G * LENGTH
FIXED_STEP = sorted(name for name, method in ms.INTEGRATORS.items() if not method.adaptive)
# Explicit methods cost a fixed number of forward-dynamics evaluations per step; implicit ones vary.
EXPLICIT_FIXED_STEP = [name for name in FIXED_STEP if not ms.INTEGRATORS[name].implicit]


def pendulum_text(lower: float = -3.0, upper: float = 3.0) -> str:
    """URDF of the pendulum above, with its hinge limits [rad]."""
    limits = f'lower="{lower}" upper="{upper}" effort="50" velocity="50"'
    return urdf(
        '<link name="base"/>',
        link("bob", mass=MASS, com=f"0 0 {-LENGTH}", inertia=f"{BOB_INERTIA} {BOB_INERTIA} {BOB_INERTIA}"),
        joint("hinge", "base", "bob", limits=limits),
        name="pendulum",
    )


@pytest.fixture
def pendulum(write_urdf: Callable[..., Path]) -> ms.Robot:
    """The pendulum above, loaded fresh (tests may wrap its methods)."""
    robot = ms.load_robot(write_urdf(pendulum_text()))
    # The oracle below assumes Pinocchio's standard gravity; check it rather than trust it.
    np.testing.assert_array_equal(robot.model.gravity.linear, [0.0, 0.0, -G])
    return robot


def cure(dt: str) -> str:
    """The remedy every divergence message ends with (A-stable implicit methods are suggested if any)."""
    implicit = sorted(name for name, method in ms.INTEGRATORS.items() if method.implicit and method.a_stable)
    also = f", or an implicit integrator ({', '.join(implicit)})" if implicit else ""
    return f"try a smaller dt (now {dt} s){also}"


def exact(message: str) -> str:
    """A regex matching exactly `message` (pytest.raises searches, so anchor both ends)."""
    return f"^{re.escape(message)}$"


def pendulum_zoh_oracle(
    controller: Callable[..., np.ndarray], q0: float, v0: float, control_dt: float, n_control: int
) -> tuple[np.ndarray, np.ndarray]:
    """The exact zero-order-hold closed loop on the pendulum ODE I q'' = tau - m g l sin q, by SciPy.

    Returns:
        (states at the control instants, shape (n_control + 1, 2); torques held, shape (n_control,)).
    """
    y = np.array([q0, v0])
    states, torques = [y], []
    for j in range(n_control):
        tau = float(controller(j * control_dt, y[:1].copy(), y[1:].copy())[0])
        sol = solve_ivp(
            lambda _t, s, tau=tau: [s[1], (tau - MGL * math.sin(s[0])) / I_HINGE],
            (0.0, control_dt),
            y,
            method="DOP853",
            rtol=1e-12,
            atol=1e-13,
        )
        y = sol.y[:, -1]
        states.append(y)
        torques.append(tau)
    return np.array(states), np.array(torques)


def feedback(t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """A state-feedback law with a time-varying offset, so holding it matters."""
    return np.array([0.5 * math.cos(2.0 * t) - 4.0 * q[0] - 1.0 * v[0]])


# ---- sampling ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("integrator", FIXED_STEP)
def test_fixed_step_sampling_ends_exactly_at_duration_with_a_short_last_step(pendulum, integrator):
    traj = ms.simulate(pendulum, [0.3], [0.0], duration=0.105, dt=0.01, integrator=integrator)
    # 0.105 s in steps of 0.01 s: ten full steps and a last one of 0.005 s.
    assert traj.t[0] == 0.0
    assert traj.t[-1] == 0.105
    steps = np.diff(traj.t)
    assert len(steps) == 11
    np.testing.assert_allclose(steps[:-1], 0.01, rtol=1e-12)
    assert steps[-1] == pytest.approx(0.005, rel=1e-12)
    assert traj.stats["steps"] == 11
    assert traj.stats["rejected_steps"] == 0
    assert traj.status == "completed"
    assert all(len(getattr(traj, name)) == 12 for name in ("q", "v", "tau", "total_energy", "energy_error"))


@pytest.mark.parametrize("integrator", EXPLICIT_FIXED_STEP)
def test_evaluations_are_steps_times_the_methods_stage_count(pendulum, integrator):
    calls = 0
    forward_dynamics = pendulum.unchecked_forward_dynamics

    def counting(q, v, tau, t=0.0):  # count the dynamics evaluations independently of the stats
        nonlocal calls
        calls += 1
        return forward_dynamics(q, v, tau, t)

    pendulum.unchecked_forward_dynamics = counting
    traj = ms.simulate(pendulum, [0.3], [0.0], duration=0.105, dt=0.01, integrator=integrator)
    assert traj.stats["evaluations"] == 11 * ms.INTEGRATORS[integrator].evaluations_per_step == calls


def test_a_duration_that_is_a_multiple_of_dt_takes_no_extra_sliver_step(pendulum):
    # 1.0 / 0.1 is 10.000000000000002 in floating point: still ten steps of 0.1 s.
    traj = ms.simulate(pendulum, [0.3], [0.0], duration=1.0, dt=0.1)
    assert traj.stats["steps"] == 10
    assert traj.t[-1] == 1.0
    np.testing.assert_allclose(np.diff(traj.t), 0.1, rtol=1e-12)


def test_a_duration_shorter_than_dt_is_one_short_step(pendulum):
    traj = ms.simulate(pendulum, [0.3], [0.0], duration=0.004, dt=0.01)
    np.testing.assert_array_equal(traj.t, [0.0, 0.004])
    assert traj.stats["steps"] == 1


@pytest.mark.parametrize(
    ("duration", "output_dt", "expected"),
    [
        (0.105, 0.03, [0.0, 0.03, 0.06, 0.09, 0.105]),  # multiples of output_dt, then the final time
        (0.1, 0.05, [0.0, 0.05, 0.1]),  # the final time is a multiple: not sampled twice
        (0.1, 0.01, np.arange(11) * 0.01),
    ],
)
def test_output_dt_decimates_to_its_multiples_plus_the_final_time(pendulum, duration, output_dt, expected):
    every = ms.simulate(pendulum, [0.3], [0.0], duration=duration, dt=0.01)
    traj = ms.simulate(pendulum, [0.3], [0.0], duration=duration, dt=0.01, output_dt=output_dt)
    np.testing.assert_allclose(traj.t, expected, rtol=1e-12, atol=0)
    assert traj.t[-1] == duration
    assert traj.stats["steps"] == every.stats["steps"]  # decimation changes the output, not the stepping
    # Decimated samples are the same states as the undecimated run's at those times.
    rows = [int(np.argmin(np.abs(every.t - t))) for t in traj.t]
    np.testing.assert_array_equal(traj.q, every.q[rows])
    np.testing.assert_array_equal(traj.v, every.v[rows])


@pytest.mark.parametrize("option", ["output_dt", "control_dt"])
@pytest.mark.parametrize("period", [0.015, 0.005, 0.025])
def test_periods_that_are_not_multiples_of_dt_are_refused(pendulum, option, period):
    with pytest.raises(
        ms.InvalidArgumentError, match=exact(f"{option} must be a whole multiple of dt = 0.01 s, got {period:g} s")
    ):
        ms.simulate(pendulum, [0.3], [0.0], duration=0.1, dt=0.01, **{option: period})


def test_unknown_and_adaptive_only_options_are_refused_on_fixed_step_methods(pendulum):
    with pytest.raises(
        ms.InvalidArgumentError, match=exact("unknown option 'out_dt' (valid for 'rk4': control_dt, output_dt)")
    ):
        ms.simulate(pendulum, [0.3], [0.0], duration=0.1, dt=0.01, out_dt=0.02)
    adaptive = sorted(name for name, method in ms.INTEGRATORS.items() if method.adaptive)
    where = f" (it applies to the adaptive integrators: {', '.join(adaptive)})" if adaptive else ""
    for option in ("rtol", "atol", "max_step"):
        with pytest.raises(
            ms.InvalidArgumentError,
            match=exact(f"option '{option}' does not apply to the fixed-step integrator 'rk4'{where}"),
        ):
            ms.simulate(pendulum, [0.3], [0.0], duration=0.1, dt=0.01, **{option: 1e-6})


# Numbers only: a numeric string or a bool (True would be 1 s) is a mistake, not a duration.
BAD_PERIODS = [
    (0, "0"),
    (0.0, "0.0"),
    (-0.5, "-0.5"),
    (float("nan"), "nan"),
    (float("inf"), "inf"),
    ("fast", "'fast'"),
    ("0.5", "'0.5'"),
    (True, "True"),
]


@pytest.mark.parametrize(
    ("name", "value", "shown"),
    [(name, value, shown) for name in ("duration", "dt", "output_dt", "control_dt") for value, shown in BAD_PERIODS]
    # None is the documented default of output_dt and control_dt, but no default for duration and dt.
    + [("duration", None, "None"), ("dt", None, "None")],
)
def test_bad_durations_and_steps_are_refused(pendulum, name, value, shown):
    kwargs: dict[str, Any] = {"duration": 0.1, "dt": 0.01, name: value}
    with pytest.raises(
        ms.InvalidArgumentError, match=exact(f"{name} must be a positive number of seconds, got {shown}")
    ):
        ms.simulate(pendulum, [0.3], [0.0], **kwargs)


def test_a_controller_that_is_not_callable_is_refused(pendulum):
    with pytest.raises(
        ms.InvalidArgumentError, match=exact("controller must be callable as controller(t, q, v), got ndarray")
    ):
        ms.simulate(pendulum, [0.3], [0.0], duration=0.1, dt=0.01, controller=np.zeros(1))


# ---- controller timing ---------------------------------------------------------------------------------
@pytest.mark.parametrize("integrator", FIXED_STEP)
def test_controller_is_called_once_per_step_at_the_accepted_states(pendulum, integrator):
    seen: list[tuple[float, np.ndarray, np.ndarray]] = []

    def controller(t, q, v):
        seen.append((t, q, v))  # keep the very arrays: the loop must not reuse them for later states
        return np.array([0.2 * math.sin(5.0 * t)])

    traj = ms.simulate(pendulum, [0.3], [0.1], duration=0.105, dt=0.01, integrator=integrator, controller=controller)
    # Once per step, at each step's start (never at the final time, where no step follows).
    assert [t for t, _, _ in seen] == pytest.approx(list(traj.t[:-1]), rel=0, abs=1e-15)
    assert traj.stats["controller_calls"] == len(seen) == 11
    # The states it saw are the accepted ones the trajectory records, not intermediate stages.
    np.testing.assert_array_equal(np.array([q for _, q, _ in seen]), traj.q[:-1])
    np.testing.assert_array_equal(np.array([v for _, _, v in seen]), traj.v[:-1])


def test_control_dt_holds_the_torque_between_controller_calls(pendulum):
    seen: list[float] = []

    def controller(t, q, v):
        seen.append(t)
        return np.array([1.0 + t])  # a different torque at every call

    traj = ms.simulate(pendulum, [0.3], [0.0], duration=0.3, dt=0.01, control_dt=0.05, controller=controller)
    np.testing.assert_allclose(seen, 0.05 * np.arange(6), rtol=0, atol=1e-15)
    assert traj.stats["controller_calls"] == 6
    assert len(traj) == 31
    # Row k holds the torque applied over [t_k, t_k+1): the latest call at or before t_k; the last row repeats.
    held = 1.0 + 0.05 * np.floor(np.arange(30) / 5 + 1e-9)
    np.testing.assert_allclose(traj.tau[:-1, 0], held, rtol=1e-15)
    assert traj.tau[-1, 0] == traj.tau[-2, 0]


def test_tau_row_k_is_the_torque_that_moved_the_state_from_sample_k_to_k_plus_1(pendulum):
    traj = ms.simulate(pendulum, [0.3], [0.0], duration=0.2, dt=0.02, controller=feedback)
    for k in range(len(traj) - 1):
        # One independent step of the same length from sample k under the constant torque tau[k].
        step = ms.simulate(
            pendulum,
            traj.q[k],
            traj.v[k],
            duration=traj.t[k + 1] - traj.t[k],
            dt=0.02,
            controller=lambda t, q, v, tau=traj.tau[k]: tau,
        )
        np.testing.assert_allclose(step.q[-1], traj.q[k + 1], rtol=0, atol=1e-14)
        np.testing.assert_allclose(step.v[-1], traj.v[k + 1], rtol=0, atol=1e-14)


def test_control_dt_equals_hand_chained_constant_torque_segments(pendulum):
    dt, control_dt, n_control = 0.01, 0.05, 12
    traj = ms.simulate(
        pendulum, [0.4], [0.0], duration=control_dt * n_control, dt=dt, control_dt=control_dt, controller=feedback
    )
    q, v = np.array([0.4]), np.array([0.0])
    for j in range(n_control):
        tau = feedback(j * control_dt, q, v)
        segment = ms.simulate(pendulum, q, v, duration=control_dt, dt=dt, controller=lambda t, q, v, tau=tau: tau)
        q, v = segment.q[-1], segment.v[-1]
        row = 5 * (j + 1)
        # The segments' last steps may be dt ± one ulp: agreement to round-off, not bit for bit.
        np.testing.assert_allclose(traj.q[row], q, rtol=0, atol=1e-13)
        np.testing.assert_allclose(traj.v[row], v, rtol=0, atol=1e-13)
        np.testing.assert_allclose(traj.tau[row - 5], tau, rtol=0, atol=1e-12)


def test_zero_order_hold_matches_the_exact_sampled_data_closed_loop(pendulum):
    dt, control_dt, n_control = 0.01, 0.05, 20
    oracle, torques = pendulum_zoh_oracle(feedback, 0.4, 0.0, control_dt, n_control)
    traj = ms.simulate(
        pendulum, [0.4], [0.0], duration=control_dt * n_control, dt=dt, control_dt=control_dt, controller=feedback
    )
    rows = 5 * np.arange(n_control + 1)
    state_error = np.max(np.abs(np.column_stack([traj.q[rows, 0], traj.v[rows, 0]]) - oracle))
    # RK4 at omega·dt ~ 0.04: global error ~ 1e-8 here; 1e-6 leaves room yet is far below the gap below.
    assert state_error < 1e-6
    np.testing.assert_allclose(traj.tau[rows[:-1], 0], torques, rtol=0, atol=1e-5)
    # The oracle discriminates: calling the controller every step (no hold) lands far from it.
    unheld = ms.simulate(pendulum, [0.4], [0.0], duration=control_dt * n_control, dt=dt, controller=feedback)
    assert np.max(np.abs(np.column_stack([unheld.q[rows, 0], unheld.v[rows, 0]]) - oracle)) > 1e3 * state_error


def test_the_controller_sees_read_only_state_and_the_callers_arrays_stay_untouched(pendulum):
    refused = []

    def meddler(t, q, v):
        for array in (q, v):
            try:
                array[0] = 99.0
            except ValueError as exc:
                refused.append(str(exc))
        return np.zeros(1)

    q0, v0 = np.array([0.3]), np.array([0.1])
    traj = ms.simulate(pendulum, q0, v0, duration=0.05, dt=0.01, controller=meddler)
    assert refused == ["assignment destination is read-only"] * 10
    reference = ms.simulate(pendulum, q0, v0, duration=0.05, dt=0.01, controller=lambda t, q, v: np.zeros(1))
    np.testing.assert_array_equal(traj.q, reference.q)
    # The caller's own arrays are neither changed nor frozen.
    np.testing.assert_array_equal(q0, [0.3])
    q0[0] = 0.2
    v0[0] = 0.0


@pytest.mark.parametrize(
    ("output", "reason"),
    [
        (np.zeros(2), "must have shape (1,), got (2,)"),
        (np.zeros((1, 1)), "must have shape (1,), got (1, 1)"),
        (np.array([np.nan]), "must be finite, got non-finite entries at indices [0]"),
        (np.array([np.inf]), "must be finite, got non-finite entries at indices [0]"),
    ],
)
def test_bad_controller_output_names_the_time(pendulum, output, reason):
    def controller(t, q, v):
        return output if t > 0.045 else np.zeros(1)  # fine until the sixth call, at t = 0.05 s

    with pytest.raises(ms.InvalidArgumentError, match=exact(f"controller output at t = 0.05 s: tau {reason}")):
        ms.simulate(pendulum, [0.3], [0.0], duration=0.1, dt=0.01, controller=controller)


def test_controller_output_that_is_not_numbers_names_the_time(pendulum):
    with pytest.raises(
        ms.InvalidArgumentError,
        match=exact("controller output at t = 0 s: tau must be an array of 1 real numbers, got str"),
    ):
        ms.simulate(pendulum, [0.3], [0.0], duration=0.1, dt=0.01, controller=lambda t, q, v: "push")


def test_controller_torque_on_an_unactuated_floating_base_is_refused(robot):
    solo = robot("solo12")

    def controller(t, q, v):
        tau = np.zeros(solo.nv)
        tau[2] = 1.0 if t > 0.045 else 0.0  # a vertical force on the base from t = 0.05 s
        tau[6:] = 0.1  # joint torques are fine
        return tau

    with pytest.raises(ms.InvalidArgumentError) as info:
        ms.simulate(solo, solo.neutral(), np.zeros(solo.nv), duration=0.1, dt=0.01, controller=controller)
    message = str(info.value)
    assert message.startswith("controller output at t = 0.05 s")
    assert message.endswith("acts on the unactuated floating base and must be zero, got [0.0, 0.0, 1.0, 0.0, 0.0, 0.0]")


def test_joint_torques_on_a_floating_robot_are_accepted(robot):
    solo = robot("solo12")
    tau = np.r_[np.zeros(6), np.full(12, 0.1)]
    traj = ms.simulate(solo, solo.neutral(), np.zeros(solo.nv), duration=0.02, dt=0.01, controller=lambda t, q, v: tau)
    np.testing.assert_array_equal(traj.tau, np.tile(tau, (3, 1)))


# ---- early stops ---------------------------------------------------------------------------------------
def check_partial(traj: ms.Trajectory, duration: float, status: str) -> None:
    """What every early stop must hand back: finite samples only, increasing times, before the end."""
    assert traj.status == status
    assert len(traj) >= 1 and traj.t[0] == 0.0
    assert np.all(np.diff(traj.t) > 0)
    assert traj.t[-1] < duration
    for name in (
        "t",
        "q",
        "v",
        "tau",
        "kinetic_energy",
        "potential_energy",
        "total_energy",
        "work",
        "dissipated",
        "energy_error",
    ):
        array = getattr(traj, name)
        assert len(array) == len(traj), name
        assert np.all(np.isfinite(array)), name


def test_energy_blow_up_stops_the_run_with_the_finite_samples(robot):
    # Explicit Euler at 0.2 s on a fast double pendulum gains energy geometrically within a few steps.
    dp = robot("double_pendulum", damping=False)
    with pytest.raises(ms.SimulationError) as info:
        ms.simulate(dp, [1.0, 0.3], [10.0, -10.0], duration=50.0, dt=0.2, integrator="euler")
    error = info.value
    assert isinstance(error, RuntimeError) and isinstance(error, ms.MultibodySimError)
    assert error.status == "diverged"
    traj = error.trajectory
    check_partial(traj, 50.0, "diverged")
    np.testing.assert_allclose(traj.t, 0.2 * np.arange(len(traj)), rtol=1e-12)
    assert traj.stats["steps"] == len(traj) - 1
    # The blow-up criterion, recomputed from the samples: the energy error first exceeds 1000 times the
    # run's energy scale (initial |T| + |V|, the work of lifting the robot by 1 m, and the work put in; not the
    # dissipation, which a diverging damped mode would inflate without bound).
    # Bodies welded to the world never move: they count neither in V nor in the robot's mass here.
    mass = sum(inertia.mass for inertia in dp.model.inertias[1:])
    scale = traj.kinetic_energy[0] + abs(traj.potential_energy[0]) + mass * G
    scales = scale + np.abs(traj.work)
    beyond = np.abs(traj.energy_error) > 1e3 * scales
    assert beyond[-1] and not beyond[:-1].any()
    fastest = int(np.argmax(np.abs(traj.v[-1])))
    assert error.args[0] == (
        f"diverged at t = {traj.t[-1]:.6g} s (step {len(traj) - 1}): the energy error "
        f"{traj.energy_error[-1]:.3g} J exceeds 1000 times the run's energy scale ({scales[-1]:.3g} J), "
        f"fastest in '{dp.dof_names[fastest]}' ({traj.v[-1][fastest]:.3g}); {cure('0.2')}"
    )


def test_energy_put_in_by_torques_is_not_mistaken_for_a_blow_up(pendulum):
    # An exponentially growing torque spins the pendulum up to ~380 rad/s: H grows far beyond 1000 times the
    # run's initial energy scale (|V(0)| + m g · 1 m ~ 20 J), all of it paid for by the torque's work, so the
    # ledger balances and the run must complete.
    unlimited = ms.load_robot("pendulum")
    unlimited.effort_limit[:] = np.inf  # a motor without a torque limit: nothing saturates
    traj = ms.simulate(unlimited, [0.0], [0.0], duration=3.0, dt=0.002, controller=lambda t, q, v: [20.0 * math.exp(t)])
    assert traj.status == "completed"
    gained = traj.total_energy[-1] - traj.total_energy[0]
    assert gained > 1e3 * (abs(traj.potential_energy[0]) + MASS * G)
    # The work, cross-checked by the trapezoid rule on the samples (O(dt) since the torque is held: ~1e-3).
    assert traj.work[-1] == pytest.approx(trapezoid(traj.tau[:, 0] * traj.v[:, 0], traj.t), rel=1e-2)
    assert abs(traj.energy_error[-1]) < 1e-6 * gained


def rk4_step_by_hand(model: pin.Model, q: np.ndarray, v: np.ndarray, tau: np.ndarray, h: float):
    """Classical RK4 on (q, v) for revolute joints (q' = v), with Pinocchio's ABA: an independent step."""
    data = model.createData()
    with np.errstate(all="ignore"):  # this step is meant to overflow
        k1q, k1v = v, pin.aba(model, data, q, v, tau)
        k2q, k2v = v + h / 2 * k1v, pin.aba(model, data, q + h / 2 * k1q, v + h / 2 * k1v, tau)
        k3q, k3v = v + h / 2 * k2v, pin.aba(model, data, q + h / 2 * k2q, v + h / 2 * k2v, tau)
        k4q, k4v = v + h * k3v, pin.aba(model, data, q + h * k3q, v + h * k3v, tau)
        return q + h / 6 * (k1q + 2 * k2q + 2 * k3q + k4q), v + h / 6 * (k1v + 2 * k2v + 2 * k3v + k4v)


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")
@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")
def test_a_non_finite_state_stops_the_run_naming_time_dof_and_cure(robot):
    dp = robot("double_pendulum", damping=False)

    def kick(t, q, v):  # finite, so it passes the output check, but the next step overflows to NaN
        return np.array([0.0, 1e200 if t > 0.295 else 0.0])

    with pytest.raises(ms.SimulationError) as info:
        ms.simulate(dp, [np.pi - 0.2, 0.1], [0.0, 0.0], duration=1.0, dt=0.01, controller=kick)
    error = info.value
    traj = error.trajectory
    check_partial(traj, 1.0, "diverged")
    assert traj.t[-1] == pytest.approx(0.3, abs=1e-12)  # the last finite state is the one the kick hit
    assert traj.tau[-1, 1] == 1e200  # the evidence: the torque applied from that state
    q_next, v_next = rk4_step_by_hand(dp.model, traj.q[-1], traj.v[-1], traj.tau[-1], 0.01)
    bad = ~(np.isfinite(q_next) & np.isfinite(v_next))
    assert bad.any()  # truly non-finite, not merely large
    first_bad = dp.dof_names[int(np.argmax(bad))]
    # The message names the step's end, where the state stopped being finite.
    assert error.args[0] == (
        f"diverged at t = 0.31 s (step 31): the state became non-finite in '{first_bad}'; {cure('0.01')}"
    )


def overflowing_euler_run(dp: ms.Robot) -> ms.SimulationError:
    """Explicit Euler with a huge torque from t = 0.3 s: the next velocity is ~1e201, finite but its square
    (hence the kinetic energy) overflows."""
    with pytest.raises(ms.SimulationError) as info:
        ms.simulate(
            dp,
            [np.pi - 0.2, 0.1],
            [0.0, 0.0],
            duration=1.0,
            dt=0.01,
            integrator="euler",
            controller=lambda t, q, v: np.array([0.0, 1e200 if t > 0.295 else 0.0]),
        )
    return info.value


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")
@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")
def test_a_message_saying_non_finite_is_true(robot):
    # A cheap check on |x|^2 alone once called such a huge but finite state "non-finite", naming a random dof.
    dp = robot("double_pendulum", damping=False)
    error = overflowing_euler_run(dp)
    traj, message = error.trajectory, str(error)
    assert error.status == "diverged"
    named = re.search(r"became non-finite in '([^']+)'", message)
    if named:  # the claim must hold for an explicit Euler step from the last finite sample
        data = dp.model.createData()
        q, v, tau = traj.q[-1], traj.v[-1], traj.tau[-1]
        with np.errstate(all="ignore"):
            v_next = v + 0.01 * pin.aba(dp.model, data, q, v, tau)
            q_next = q + 0.01 * v
        dof = dp.dof_names.index(named.group(1))
        assert not (np.isfinite(q_next[dof]) and np.isfinite(v_next[dof])), message
    else:  # stopped by the energy check: it names the fastest dof of the last sample
        fastest = dp.dof_names[int(np.argmax(np.abs(traj.v[-1])))]
        assert f"fastest in '{fastest}'" in message


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")
@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")
def test_a_state_whose_energy_overflows_leaves_only_finite_samples(robot):
    error = overflowing_euler_run(robot("double_pendulum", damping=False))
    assert "nan" not in str(error)
    check_partial(error.trajectory, 1.0, "diverged")


def test_ctrl_c_in_the_controller_keeps_every_sample_so_far(pendulum):
    def controller(t, q, v):
        if t > 0.495:
            raise KeyboardInterrupt
        return feedback(t, q, v)

    with pytest.raises(ms.SimulationInterrupted) as info:
        ms.simulate(pendulum, [0.3], [0.0], duration=1.0, dt=0.01, controller=controller)
    error = info.value
    assert isinstance(error, KeyboardInterrupt)
    assert error.status == "interrupted"
    assert str(error) == "interrupted at t = 0.5 s (step 50); 51 samples kept"
    traj = error.trajectory
    check_partial(traj, 1.0, "interrupted")
    # Every state up to the interruption, identical to an uninterrupted run's.
    full = ms.simulate(pendulum, [0.3], [0.0], duration=1.0, dt=0.01, controller=feedback)
    assert len(traj) == 51
    np.testing.assert_array_equal(traj.t, full.t[:51])
    np.testing.assert_array_equal(traj.q, full.q[:51])
    np.testing.assert_array_equal(traj.v, full.v[:51])
    np.testing.assert_array_equal(traj.tau[:50], full.tau[:50])
    np.testing.assert_array_equal(traj.tau[-1], traj.tau[-2])  # no torque was computed at t = 0.5 s
    np.testing.assert_array_equal(traj.energy_error, full.energy_error[:51])
    assert traj.stats["steps"] == 50


# ---- position limits -----------------------------------------------------------------------------------
def test_limit_violations_of_a_swing_beyond_tight_limits(write_urdf):
    limit, amplitude, dt, duration = 0.1, 0.5, 0.01, 2.5
    tight = ms.load_robot(write_urdf(pendulum_text(-limit, limit)))
    # Start at the bottom with the speed that, by energy conservation, swings up to ±amplitude: the worst
    # excess then falls between samples, not on the initial one.
    v0 = math.sqrt(2.0 * MGL * (1.0 - math.cos(amplitude)) / I_HINGE)
    traj = ms.simulate(tight, [0.0], [v0], duration=duration, dt=dt)
    violations = traj.limit_violations
    assert violations.worst_joint == "hinge"
    # The worst sample lies within dt/2 of a turning point, at an odd multiple of a quarter of the exact
    # period (complete elliptic integral of the first kind) ...
    period = 4.0 * math.sqrt(I_HINGE / MGL) * ellipk(math.sin(amplitude / 2) ** 2)
    quarters = violations.worst_time / (period / 4)
    assert abs(quarters - round(quarters)) * period / 4 <= dt / 2 and round(quarters) % 2 == 1
    # ... so it falls short of amplitude - limit by at most (1/2) q'' (dt/2)^2, q'' = m g l sin(amplitude) / I.
    shortfall = 0.5 * MGL * math.sin(amplitude) / I_HINGE * (dt / 2) ** 2
    assert amplitude - limit - shortfall - 1e-8 <= violations.worst_excess <= amplitude - limit + 1e-8
    # Count: the samples where the exact swing is outside ±limit (SciPy at tight tolerance as the oracle).
    exact_swing = solve_ivp(
        lambda _t, s: [s[1], -MGL * math.sin(s[0]) / I_HINGE],
        (0.0, duration),
        [0.0, v0],
        method="DOP853",
        t_eval=traj.t,
        rtol=1e-12,
        atol=1e-13,
    ).y[0]
    outside = int(np.sum(np.abs(exact_swing) > limit))
    assert 0 < outside < len(traj)
    assert abs(violations.count - outside) <= 1  # only a sample within RK4's ~1e-8 of a limit could differ
    assert violations.samples == violations.count  # one joint
    assert violations.describe() == (
        f"{violations.count} position-limit violations in {violations.count} samples; worst: 'hinge' "
        f"{violations.worst_excess:.3g} outside its limit at t = {violations.worst_time:.6g} s"
    )


def test_zero_limits_mean_no_limit(robot):
    # example-robot-data's double pendulum declares limits of 0: hanging at q ~ [pi, 0] breaks no limit.
    dp = robot("double_pendulum")
    traj = ms.simulate(dp, [np.pi - 0.5, 0.3], [0.0, 1.0], duration=0.5, dt=0.01)
    assert np.max(np.abs(traj.q)) > 2.0
    assert traj.limit_violations == ms.LimitViolations()
    assert traj.limit_violations.describe() == "no position-limit violations"


# ---- metadata and ownership ---------------------------------------------------------------------------
def test_metadata_records_versions_load_arguments_urdf_hash_and_options(tmp_path, write_urdf):
    path = write_urdf(pendulum_text(), name="swing.urdf")
    robot = ms.load_robot(path, floating_base=False, damping=False, package_dirs=[tmp_path])
    traj = ms.simulate(
        robot, [0.3], [0.0], duration=0.1, dt=0.01, integrator="midpoint", output_dt=0.02, controller=feedback
    )
    meta = traj.metadata
    json.dumps(meta)  # plain JSON, so it can travel in a trajectory file
    for dist in ("multibody-sim", "pin", "numpy"):
        assert meta["versions"][dist] == importlib.metadata.version(dist)
    described = meta["robot"]
    arguments = described["load_robot"]
    assert arguments == {"source": str(path), "floating_base": False, "damping": False, "package_dirs": [str(tmp_path)]}
    assert described["floating_base"] is False
    assert described["damping"] is False
    assert described["urdf_sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    assert Path(described["urdf_path"]) == path.resolve()
    assert (described["nq"], described["nv"], described["dof_names"]) == (1, 1, ["hinge"])
    assert meta["integrator"] == "midpoint"
    assert meta["options"] == {"dt": 0.01, "duration": 0.1, "output_dt": 0.02}
    assert meta["controller"] == "feedback"
    # The recorded arguments reproduce the run.
    again = ms.simulate(
        ms.load_robot(**arguments),
        [0.3],
        [0.0],
        duration=0.1,
        dt=0.01,
        integrator="midpoint",
        output_dt=0.02,
        controller=feedback,
    )
    np.testing.assert_array_equal(again.q, traj.q)


def test_metadata_records_the_resolved_base_and_the_arguments_of_a_catalog_robot(robot):
    solo = robot("solo12")
    traj = ms.simulate(solo, solo.neutral(), np.zeros(solo.nv), duration=0.01, dt=0.01)
    described = traj.metadata["robot"]
    assert described["floating_base"] is True  # what was simulated ...
    assert described["load_robot"]["floating_base"] is None  # ... and what was asked: the natural base
    assert (described["nq"], described["nv"]) == (19, 18)
    again = ms.load_robot(**described["load_robot"])
    assert (again.nq, again.nv, again.floating_base) == (19, 18, True)


def test_returned_arrays_are_not_aliased_to_the_loop_state(pendulum):
    def run() -> ms.Trajectory:
        return ms.simulate(pendulum, [0.3], [0.1], duration=0.1, dt=0.01, controller=feedback)

    first = run()
    kept = {name: getattr(first, name).copy() for name in ("t", "q", "v", "tau", "total_energy", "work")}
    for name in kept:
        getattr(first, name)[...] = np.nan  # scribble over everything the caller was given
    first.ledger["joint_torques"].energy[...] = np.nan
    second = run()
    for name, array in kept.items():
        np.testing.assert_array_equal(getattr(second, name), array)
    assert np.all(np.isfinite(second.ledger["joint_torques"].energy))
