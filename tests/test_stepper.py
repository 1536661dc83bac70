"""The stepper: simulate()'s arithmetic one step at a time, settable state, the ledger, and early stops."""

from __future__ import annotations

import re

import numpy as np
import pytest

import multibody_sim as ms
from multibody_sim.integrators.implicit import ImplicitEuler
from multibody_sim.monitor import BLOWUP_FACTOR, Monitor
from multibody_sim.recording import SampleStore

DT = 2.0**-10  # a power of two: k·dt is exact, so every step of simulate() is exactly dt long
N_STEPS = 40
ADAPTIVE = {"rtol": 1e-6, "atol": 1e-8}


def exact(message: str) -> str:
    return f"^{re.escape(message)}$"


def options(name: str) -> dict[str, float]:
    return ADAPTIVE if ms.INTEGRATORS[name].adaptive else {}


def tracking(robot: ms.Robot, gain: float):
    """A time-varying PD controller; on the panda its gains saturate some joints at their effort limits."""
    rng = np.random.default_rng(7)
    target = robot.random_configuration(rng)
    actuated = np.arange(robot.nv) >= (6 if robot.floating_base else 0)

    def controller(t, q, v):
        error = robot.space.difference(q, target) * (1.0 + 0.5 * np.sin(20.0 * t))
        return np.where(actuated, gain * error - 0.1 * gain**0.5 * v, 0.0)

    return controller


def start(robot: ms.Robot) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(3)
    v0 = 0.3 * rng.normal(size=robot.nv)
    return robot.random_configuration(rng), v0


def run_both(robot: ms.Robot, name: str, gain: float) -> tuple[ms.Trajectory, dict[str, np.ndarray], ms.Stepper]:
    q0, v0 = start(robot)
    controller = tracking(robot, gain)
    extra = {"control_dt": DT, "output_dt": DT} if ms.INTEGRATORS[name].adaptive else {}
    traj = ms.simulate(
        robot, q0, v0, duration=N_STEPS * DT, dt=DT, integrator=name, controller=controller, **options(name), **extra
    )
    stepper = ms.Stepper(robot, dt=DT, integrator=name, q0=q0, v0=v0, **options(name))
    rows: dict[str, list] = {key: [] for key in ("t", "q", "v", "tau", "work", "dissipated", "kinetic_energy")}
    for _ in range(N_STEPS + 1):
        rows["t"].append(stepper.t)
        rows["q"].append(stepper.q)
        rows["v"].append(stepper.v)
        rows["work"].append(stepper.work)
        rows["dissipated"].append(stepper.dissipated)
        rows["kinetic_energy"].append(stepper.kinetic_energy)
        if len(rows["t"]) <= N_STEPS:
            stepper.step(controller(stepper.t, stepper.q, stepper.v))
            rows["tau"].append(stepper.tau)
    rows["tau"].append(rows["tau"][-1])  # simulate's last row repeats the torque
    return traj, {key: np.array(values) for key, values in rows.items()}, stepper


# ---- the same arithmetic as simulate() ------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(ms.INTEGRATORS))
def test_n_steps_with_a_controller_equal_simulates_samples_bitwise(robot, name):
    # The panda is a damped arm with effort limits that this controller's gains exceed: the saturation, the ledger
    # (work and damping) and the energies must all agree bit for bit. Adaptive methods are compared with
    # simulate(control_dt = output_dt = dt), which lands its error-controlled steps on the same instants.
    panda = robot("panda")
    traj, rows, stepper = run_both(panda, name, gain=400.0)
    assert len(traj) == N_STEPS + 1
    for field in ("t", "q", "v", "tau", "work", "dissipated", "kinetic_energy"):
        np.testing.assert_array_equal(rows[field], getattr(traj, field), err_msg=field)
    assert stepper.stats["saturated_controls"] == traj.stats["saturated_controls"] > 0
    assert stepper.stats["saturated_dofs"] == traj.stats["saturated_dofs"]
    assert stepper.stats["steps"] == traj.stats["steps"]
    assert stepper.stats["rejected_steps"] == traj.stats["rejected_steps"]
    assert stepper.ledger == {name: entry.energy[-1] for name, entry in traj.ledger.items()}
    assert stepper.energy_error == traj.energy_error[-1]
    assert stepper.total_energy == traj.total_energy[-1]


@pytest.mark.parametrize("name", sorted(ms.INTEGRATORS))
def test_a_floating_base_steps_like_simulate_or_is_refused_alike(robot, name):
    # On a free-flyer the stages live in the local chart: the stepper must not take another road. Methods that
    # do not support floating bases refuse the stepper with simulate()'s message.
    solo = robot("solo12")
    try:
        traj, rows, _ = run_both(solo, name, gain=5.0)
    except ms.InvalidArgumentError as refused:
        q0, v0 = start(solo)
        with pytest.raises(ms.InvalidArgumentError, match=exact(str(refused))):
            ms.Stepper(solo, dt=DT, integrator=name, q0=q0, v0=v0, **options(name))
        with pytest.raises(ms.InvalidArgumentError):
            ms.simulate(solo, q0, v0, duration=DT, dt=DT, integrator=name, **options(name))
        return
    for field in ("t", "q", "v", "tau", "work"):
        np.testing.assert_array_equal(rows[field], getattr(traj, field), err_msg=field)


@pytest.mark.parametrize("name", ["rk4", "implicit_midpoint", "dp54"])
def test_advance_to_lands_like_simulates_duration_with_a_short_last_step(robot, name):
    # dt = 1 ms and 0.0505 s: 50 steps of dt then one of 0.5 ms, with the controller called at k·dt as simulate()
    # does, in two calls: one that stays on the grid (0.02 s = 20 steps) and one that ends off it.
    panda = robot("panda")
    q0, v0 = start(panda)
    controller = tracking(panda, gain=20.0)
    extra = {"control_dt": 1e-3, "output_dt": 1e-3} if ms.INTEGRATORS[name].adaptive else {}
    traj = ms.simulate(
        panda, q0, v0, duration=0.0505, dt=1e-3, integrator=name, controller=controller, **options(name), **extra
    )
    stepper = ms.Stepper(panda, dt=1e-3, integrator=name, q0=q0, v0=v0, **options(name))
    middle = stepper.advance_to(0.02, controller)
    assert middle.t == traj.t[20] == 0.02
    np.testing.assert_array_equal(middle.q, traj.q[20])
    end = stepper.advance_to(0.0505, controller)
    assert end.t == traj.t[-1] == 0.0505
    np.testing.assert_array_equal(end.q, traj.q[-1])
    np.testing.assert_array_equal(end.v, traj.v[-1])
    assert stepper.work == traj.work[-1]
    assert stepper.stats["controller_calls"] == traj.stats["controller_calls"] == 51


def test_an_adaptive_stepper_reuses_its_last_stage_only_under_the_same_torque(robot):
    # With the torque unchanged, dp54's last stage (first same as last) starts the next step: one evaluation
    # fewer per step, and the same bits as simulate(), which recomputes it after every controller call.
    dp = robot("double_pendulum")
    tau = np.array([0.3, -0.2])
    traj = ms.simulate(
        dp, [0.5, 0.2], [0.0, 0.0], duration=N_STEPS * DT, dt=DT, integrator="dp54",
        controller=lambda t, q, v: tau, control_dt=DT, output_dt=DT, **ADAPTIVE,
    )  # fmt: skip
    stepper = ms.Stepper(dp, dt=DT, integrator="dp54", q0=[0.5, 0.2], **ADAPTIVE)
    stepper.step(tau)
    for _ in range(N_STEPS - 1):
        stepper.step()  # None: the previous torque, held
    np.testing.assert_array_equal(stepper.q, traj.q[-1])
    np.testing.assert_array_equal(stepper.v, traj.v[-1])
    assert stepper.stats["evaluations"] == traj.stats["evaluations"] - (N_STEPS - 1)


def test_step_without_a_torque_holds_the_previous_one(robot):
    dp = robot("double_pendulum")
    held, given = ms.Stepper(dp, dt=1e-3, q0=[0.4, 0.1]), ms.Stepper(dp, dt=1e-3, q0=[0.4, 0.1])
    tau = np.array([0.2, 0.1])
    held.step(tau)
    given.step(tau)
    for _ in range(5):
        held.step()
        given.step(tau)
    np.testing.assert_array_equal(held.q, given.q)
    np.testing.assert_array_equal(held.tau, tau)
    assert ms.Stepper(dp, dt=1e-3).tau.tolist() == [0.0, 0.0]  # zero before the first torque


# ---- state: get, set, reset ----------------------------------------------------------------------------------
def test_reset_reproduces_the_same_run_bit_for_bit(robot):
    # Nothing survives a reset: the adaptive step size, the ledger, the stats, the torque.
    dp = robot("double_pendulum")
    stepper = ms.Stepper(dp, dt=0.01, integrator="dp54", q0=[1.0, -0.5], v0=[0.0, 2.0], **ADAPTIVE)

    def run():
        for k in range(30):
            stepper.step([0.1 * np.sin(k), 0.0])
        return stepper.q, stepper.v, stepper.work, stepper.dissipated, dict(stepper.stats)

    first = run()
    state = stepper.reset()
    assert state.t == 0.0 and state.q.tolist() == [1.0, -0.5] and state.v.tolist() == [0.0, 2.0]
    assert stepper.work == stepper.dissipated == 0.0 and stepper.stats["steps"] == 0
    second = run()
    for a, b in zip(first, second, strict=True):
        np.testing.assert_array_equal(a, b)


def test_reset_to_a_given_state_and_time(robot):
    dp = robot("double_pendulum")
    stepper = ms.Stepper(dp, dt=0.01)
    stepper.step([1.0, 1.0])
    state = stepper.reset(q=[0.1, 0.2], v=[0.3, 0.4], t=2.5)
    assert (state.t, state.q.tolist(), state.v.tolist()) == (2.5, [0.1, 0.2], [0.3, 0.4])
    np.testing.assert_array_equal(stepper.tau, [0.0, 0.0])
    stepper.step()
    assert stepper.t == 2.5 + 0.01


def test_time_is_counted_in_steps_not_summed(robot):
    # 1000 steps of 0.001 s: a running sum drifts off 1.0; k·dt does not.
    stepper = ms.Stepper(robot("pendulum"), dt=0.001, integrator="euler")
    for _ in range(1000):
        stepper.step()
    assert stepper.t == 1000 * 0.001 == 1.0
    stepper.t = 5.0
    stepper.step()
    assert stepper.t == 5.001


def test_setting_the_state_checks_it_like_the_robot_does(robot):
    solo = robot("solo12")
    stepper = ms.Stepper(solo, dt=1e-3)
    with pytest.raises(ms.InvalidArgumentError, match=exact("q must have shape (19,), got (18,)")):
        stepper.q = np.zeros(18)
    bad = solo.neutral()
    bad[3:7] = [0.0, 0.0, 0.0, 2.0]
    with pytest.raises(
        ms.InvalidArgumentError,
        match=exact("q is not a valid configuration: its quaternion / (cos, sin) entries must have unit norm"),
    ):
        stepper.q = bad
    with pytest.raises(ms.InvalidArgumentError, match=exact("v must be finite, got non-finite entries at indices [2]")):
        stepper.v = [0.0, 0.0, np.nan] + [0.0] * 15
    with pytest.raises(ms.InvalidArgumentError, match=exact("t must be a finite number of seconds, got inf")):
        stepper.t = np.inf
    with pytest.raises(ms.InvalidArgumentError, match=exact("q0 must have shape (19,), got (3,)")):
        ms.Stepper(solo, dt=1e-3, q0=[0.0, 0.0, 0.0])
    # The state handed out is read-only: editing it in place would bypass these checks.
    with pytest.raises(ValueError, match="read-only"):
        stepper.q[0] = 1.0


def test_a_hand_set_state_moves_the_energy_reference_not_the_error(robot):
    # Setting v adds kinetic energy that no ledger element paid for: energy_error must stay a check on the
    # integration (unchanged by the jump, then small under RK4), while total_energy jumps.
    dp = robot("double_pendulum")
    stepper = ms.Stepper(dp, dt=1e-3, q0=[2.0, 0.5])
    for _ in range(100):
        stepper.step()
    before, energy = stepper.energy_error, stepper.total_energy
    stepper.v = [10.0, 10.0]
    assert stepper.total_energy - energy > 1.0  # 1.66 J
    assert stepper.energy_error == pytest.approx(before, abs=1e-12)
    for _ in range(300):
        stepper.step()
    # RK4 at 1 ms over 0.3 s of fast swinging: its consistency error is O(dt⁴), ~5e-8 J here, a millionth of the
    # jump that a stepper blind to hand-set states would report as error.
    assert abs(stepper.energy_error) < 1e-6
    assert stepper.dissipated > 0.0  # the joints' damping took energy out, and the ledger saw it


# ---- early stops -------------------------------------------------------------------------------------------
def test_divergence_raises_like_simulate_and_keeps_the_state_before(robot):
    # The README's example: explicit Euler at 50 ms on a fast double pendulum gains energy until the blow-up
    # check stops it. Same step, same message as simulate(); the stepper stays at the last good state.
    dp = robot("double_pendulum", damping=False)
    q0, v0 = [3.0, 0.0], [40.0, -40.0]
    with pytest.raises(ms.SimulationError) as by_simulate:
        ms.simulate(dp, q0, v0, duration=20.0, dt=0.05, integrator="euler")
    stepper = ms.Stepper(dp, dt=0.05, integrator="euler", q0=q0, v0=v0)
    with pytest.raises(ms.SimulationError) as by_stepper:
        stepper.advance_to(20.0)
    assert by_stepper.value.status == by_simulate.value.status == "diverged"
    assert str(by_stepper.value) == str(by_simulate.value)
    samples = by_simulate.value.trajectory
    # simulate() keeps the blown-up sample as evidence; the stepper refuses to enter it.
    assert stepper.t == samples.t[-2]
    np.testing.assert_array_equal(stepper.q, samples.q[-2])
    np.testing.assert_array_equal(by_stepper.value.trajectory.q, samples.q[-2:-1])
    assert by_stepper.value.trajectory.status == "diverged"


def test_the_one_sample_energy_check_never_passes_a_sample_the_full_check_flags(robot):
    # Stepper checks one sample per step; Monitor.surely_fine clears it in Python floats at half the bound before
    # NumPy's full check runs. It must never clear a sample the full check flags, and it must clear ordinary ones.
    dp = robot("double_pendulum")  # damped: the ledger has a work and a dissipated element
    monitor = Monitor(dp, 1)
    store = SampleStore(1, dp.nq, dp.nv, len(dp.ledger_elements), 0, 2)
    store.ENERGY[1, 0], store.FLOWS[1, 0] = (1.0, 0.0), 0.0  # a harmless second sample: the full check's range
    rng = np.random.default_rng(3)
    cleared = flagged = 0
    for _ in range(3000):
        scale = 10.0 ** rng.uniform(-3, 3)
        monitor.initial[0], monitor.scale[0] = rng.normal() * scale, scale
        work, dissipated = rng.normal() * scale, abs(rng.normal()) * scale
        bound = BLOWUP_FACTOR * (scale + abs(work))
        error = rng.choice([-1.0, 1.0]) * bound * 10.0 ** rng.uniform(-3, 0.5)  # up to 3x the bound
        if rng.uniform() < 0.2:
            dissipated = bound * 10.0 ** rng.uniform(-1, 0.5)
        kinetic = abs(rng.normal()) * scale
        potential = error + monitor.initial[0] + work - dissipated - kinetic
        if rng.uniform() < 0.05:
            potential = rng.choice([np.inf, -np.inf, np.nan])
        store.ENERGY[0, 0] = kinetic, potential
        store.FLOWS[0, 0] = work, dissipated
        problem = monitor.first_problem(store, 0, 0, 2)
        fine = monitor.surely_fine(store, 0, 0)
        if problem is not None and problem[0] == 0:
            flagged += 1
            assert not fine, (kinetic, potential, work, dissipated)
        cleared += fine
    assert flagged > 500 and cleared > 1000  # both sides were exercised


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")
@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")
def test_a_non_finite_step_raises_and_leaves_the_state_untouched(robot):
    dp = robot("double_pendulum", damping=False)
    stepper = ms.Stepper(dp, dt=0.01, q0=[np.pi - 0.2, 0.1], check_energy=False)
    stepper.step()
    q, v, t = stepper.q, stepper.v, stepper.t
    with pytest.raises(ms.SimulationError) as info:
        stepper.step([0.0, 1e200])
    assert info.value.status == "diverged"
    assert re.match(
        r"diverged at t = 0\.02 s \(step 2\): the state became non-finite in '\w+'; try a smaller dt", str(info.value)
    )
    assert stepper.t == t and stepper.q is q and stepper.v is v
    stepper.step([0.0, 0.0])  # and it carries on from there
    assert stepper.t == 0.02


def test_a_newton_failure_raises_newton_failed_like_simulate(robot):
    dp = robot("double_pendulum")
    one_iteration = ImplicitEuler(max_iterations=1)
    with pytest.raises(ms.SimulationError) as by_simulate:
        ms.simulate(dp, [1.0, 0.5], [3.0, -3.0], duration=0.1, dt=0.05, integrator=one_iteration)
    stepper = ms.Stepper(dp, dt=0.05, integrator=one_iteration, q0=[1.0, 0.5], v0=[3.0, -3.0])
    with pytest.raises(ms.SimulationError) as by_stepper:
        stepper.step()
    assert by_stepper.value.status == "newton_failed"
    assert str(by_stepper.value) == str(by_simulate.value)
    assert stepper.t == 0.0 and stepper.q.tolist() == [1.0, 0.5]


# ---- arguments ------------------------------------------------------------------------------------------------
def test_options_are_checked_like_simulates(robot):
    dp = robot("double_pendulum")
    with pytest.raises(
        ms.InvalidArgumentError,
        match=exact("integrator 'dp54' is adaptive: pass rtol and atol (error tolerances; e.g. rtol=1e-6, atol=1e-8)"),
    ):
        ms.Stepper(dp, dt=1e-3, integrator="dp54")
    adaptive = ", ".join(sorted(n for n, m in ms.INTEGRATORS.items() if m.adaptive))
    with pytest.raises(
        ms.InvalidArgumentError,
        match=exact(
            f"option 'rtol' does not apply to the fixed-step integrator 'rk4' (it applies to the adaptive "
            f"integrators: {adaptive})"
        ),
    ):
        ms.Stepper(dp, dt=1e-3, rtol=1e-6)
    with pytest.raises(ms.InvalidArgumentError, match=exact("unknown option 'output_dt' (valid for 'rk4': none)")):
        ms.Stepper(dp, dt=1e-3, output_dt=1e-3)
    with pytest.raises(ms.InvalidArgumentError, match=exact("dt must be a positive number of seconds, got 0")):
        ms.Stepper(dp, dt=0)
    with pytest.raises(ms.UnknownIntegratorError, match="did you mean rk4"):
        ms.Stepper(dp, dt=1e-3, integrator="rk5")


def test_torques_and_targets_are_checked(robot):
    dp, solo = robot("double_pendulum"), robot("solo12")
    stepper = ms.Stepper(dp, dt=1e-3)
    with pytest.raises(ms.InvalidArgumentError, match=exact("tau must have shape (2,), got (3,)")):
        stepper.step([0.0, 0.0, 0.0])
    with pytest.raises(
        ms.InvalidArgumentError, match=exact("controller output at t = 0 s: tau must have shape (2,), got (1,)")
    ):
        stepper.advance_to(0.01, lambda t, q, v: np.zeros(1))
    with pytest.raises(
        ms.InvalidArgumentError, match=exact("controller must be callable as controller(t, q, v), got float")
    ):
        stepper.advance_to(0.01, 1.0)
    stepper.advance_to(0.01)
    with pytest.raises(
        ms.InvalidArgumentError,
        match=exact("t must not be before the current time 0.01 s, got 0.005 s"),
    ):
        stepper.advance_to(0.005)
    base_push = np.zeros(18)
    base_push[2] = 1.0
    with pytest.raises(
        ms.InvalidArgumentError,
        match=exact(
            "tau[0:6] acts on the unactuated floating base and must be zero, got [0.0, 0.0, 1.0, 0.0, 0.0, 0.0]"
        ),
    ):
        ms.Stepper(solo, dt=1e-3).step(base_push)
    assert stepper.advance_to(0.01).t == 0.01  # reaching the current time is a no-op
