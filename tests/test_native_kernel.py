"""The native kernel (src/native/, kernels/native.py) against the Python kernel, its specification: the same
samples, counts, statuses and messages for simulate(), Stepper and rollout(), every explicit method, every robot of
the benchmark set; a perturbed stage coefficient breaks the agreement; Ctrl-C mid-run keeps every sample."""

from __future__ import annotations

import os
import signal
import threading
import time

import numpy as np
import pinocchio as pin
import pytest
from conftest import FIELDS, assert_same_run, needs_native, on_kernel

import multibody_sim as ms
from multibody_sim.driver import choose_kernel
from multibody_sim.integrators.explicit_rk import ExplicitRungeKutta
from multibody_sim.kernels.native import NativeKernel, why_not_native

pytestmark = needs_native

ROBOTS = ["double_pendulum", "ur5", "panda", "solo12", "talos"]
FIXED = ["euler", "semi_implicit_euler", "midpoint", "rk4"]
ADAPTIVE = ["bs32", "dp54", "dop853"]


def start(robot, seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A seeded (q0, v0) around the default pose and a torque beyond the effort limits on some joints (saturated)."""
    rng = np.random.default_rng(seed)
    q0 = pin.integrate(robot.model, robot.default_pose(), 0.3 * rng.normal(size=robot.nv))
    v0 = 0.5 * rng.normal(size=robot.nv)
    # Torques of the robot's weight scale, beyond the effort limits on some joints where those are of that scale
    tau = rng.normal(size=robot.nv) * np.minimum(robot.effort_limit, robot.total_mass)
    weakest = int(np.argmin(robot.effort_limit))
    if robot.effort_limit[weakest] <= 2.0 * robot.total_mass:  # saturated at the first control instants
        tau[weakest] = 1.5 * robot.effort_limit[weakest]
    if robot.floating_base:
        tau[:6] = 0.0
    return q0, v0, tau


def options(method: str) -> dict:
    return {"rtol": 1e-7, "atol": 1e-7} if method in ADAPTIVE else {}


def assert_same(a, b) -> None:
    """Every sample, count and status equal bit for bit."""
    assert_same_run(a, b)


# ---- simulate --------------------------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", FIXED + ADAPTIVE)
@pytest.mark.parametrize("name", ROBOTS)
def test_simulate_native_equals_python_bit_for_bit(robot, monkeypatch, name, method):
    system = robot(name)
    q0, v0, tau = start(system)
    duration = 0.01 if name == "talos" else 0.04
    control_dt = 0.004 if name != "talos" else 0.002

    def controller(t, q, v):
        return tau * np.cos(20.0 * t)  # a new torque at every control instant, saturated on some joints

    def run():
        return ms.simulate(
            system, q0, v0, duration=duration, dt=1e-3, integrator=method, controller=controller,
            control_dt=control_dt, **options(method),
        )  # fmt: skip

    fast, reference = on_kernel(True, run, monkeypatch), on_kernel(False, run, monkeypatch)
    assert fast.metadata["kernel"] == "native" and reference.metadata["kernel"] == "python (row)"
    assert_same(fast, reference)
    if name in ("ur5", "panda", "talos"):
        assert fast.stats["saturated_controls"] > 0  # the saturation path was exercised


@pytest.mark.parametrize("method", ADAPTIVE)
def test_dense_output_samples_agree(robot, monkeypatch, method):
    system = robot("solo12")
    q0, v0, _ = start(system, 1)

    def run():
        return ms.simulate(
            system, q0, v0, duration=0.05, dt=1e-3, integrator=method, output_dt=0.002, **options(method)
        )

    fast, reference = on_kernel(True, run, monkeypatch), on_kernel(False, run, monkeypatch)
    assert len(fast) == 26
    assert_same(fast, reference)


def test_a_perturbed_stage_coefficient_breaks_the_agreement(robot, monkeypatch):
    """The comparison above can fail: with one of RK4's stage coefficients moved by 1e-6 in the tableau handed to
    C++, the native run leaves the Python kernel's by far more than round-off."""
    system = robot("ur5")
    q0, v0, _ = start(system)

    def run():
        return ms.simulate(system, q0, v0, duration=0.05, dt=1e-3, integrator="rk4")

    reference = on_kernel(False, run, monkeypatch)
    assert_same(on_kernel(True, run, monkeypatch), reference)
    honest = ExplicitRungeKutta.native_data

    def perturbed(method):
        data = honest(method)
        a = list(data["a"])
        a[2 * 4 + 1] += 1e-6  # a[2][1] = 1/2: the third stage's weight on the second
        return {**data, "a": a}

    monkeypatch.setattr(ExplicitRungeKutta, "native_data", perturbed)
    fast = on_kernel(True, run, monkeypatch)
    assert fast.metadata["kernel"] == "native"
    gap = float(np.max(np.abs(fast.v - reference.v)) / np.max(np.abs(reference.v)))
    assert gap > 1e-12
    with pytest.raises(AssertionError):
        assert_same(fast, reference)


# ---- Stepper and rollout ---------------------------------------------------------------------------------------------
@pytest.mark.parametrize("method", ["rk4", "dp54"])
@pytest.mark.parametrize("name", ["panda", "solo12"])
def test_stepper_native_equals_python(robot, monkeypatch, name, method):
    system = robot(name)
    q0, v0, tau = start(system)

    def run():
        stepper = ms.Stepper(system, dt=1e-3, integrator=method, control_dt=0.004, q0=q0, v0=v0, **options(method))
        states = []
        for k in range(6):
            stepper.step(tau * np.cos(k))
            states.append((stepper.t, stepper.q.copy(), stepper.v.copy(), stepper.work, stepper.dissipated))
        return states, stepper.stats, stepper._core.kernel

    (fast, fast_stats, kernel), (reference, reference_stats, _) = (
        on_kernel(True, run, monkeypatch),
        on_kernel(False, run, monkeypatch),
    )
    assert isinstance(kernel, NativeKernel)
    for got, want in zip(fast, reference, strict=True):
        assert got[0] == want[0] and got[3:] == want[3:]
        np.testing.assert_array_equal(got[1], want[1])
        np.testing.assert_array_equal(got[2], want[2])
    assert fast_stats == reference_stats


@pytest.mark.parametrize("method", ["rk4", "semi_implicit_euler", "dop853"])
@pytest.mark.parametrize("name", ["ur5", "solo12"])
def test_rollout_on_two_threads_equals_pythons_simulate_per_element(robot, monkeypatch, name, method):
    """Rows split over 2 threads (each owns its rows to the end) give each element simulate()'s Python samples."""
    system = robot(name)
    B = 5
    starts = [start(system, seed) for seed in range(B)]
    Q0, V0 = np.array([s[0] for s in starts]), np.array([s[1] for s in starts])
    extra = {"control_dt": 0.005} if method in ADAPTIVE else {}
    n_control = 4 if method in ADAPTIVE else 20
    taus = np.array([[s[2] * np.cos(j) for j in range(n_control)] for s in starts])
    monkeypatch.setenv("MULTIBODY_SIM_NATIVE", "1")
    batch = ms.rollout(
        system, Q0, V0, duration=0.02, dt=1e-3, integrator=method, taus=taus, num_threads=2, **extra,
        **options(method),
    )  # fmt: skip
    assert batch.metadata["kernel"] == "native"
    monkeypatch.setenv("MULTIBODY_SIM_NATIVE", "0")
    for b in range(B):
        controller = _OpenLoop(taus[b], 0.005 if method in ADAPTIVE else 1e-3)
        alone = ms.simulate(
            system, Q0[b], V0[b], duration=0.02, dt=1e-3, integrator=method, controller=controller, **extra,
            **options(method),
        )  # fmt: skip
        element = batch.element(b)
        for field in FIELDS:
            np.testing.assert_array_equal(getattr(element, field), getattr(alone, field), err_msg=field)


class _OpenLoop:
    """taus[j] from control instant j on (what rollout's open-loop torques mean), as a controller."""

    def __init__(self, taus: np.ndarray, period: float):
        self.taus, self.period = taus, period

    def __call__(self, t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        return self.taus[min(int(round(t / self.period)), len(self.taus) - 1)]


def test_threads_do_not_change_a_batch(robot, monkeypatch):
    system = robot("panda")
    rng = np.random.default_rng(3)
    B = 7
    Q0 = np.array([system.random_configuration(rng) for _ in range(B)])
    V0 = rng.normal(size=(B, system.nv))
    monkeypatch.setenv("MULTIBODY_SIM_NATIVE", "1")
    runs = [ms.rollout(system, Q0, V0, duration=0.05, dt=1e-3, num_threads=n) for n in (1, 2, 3)]
    for other in runs[1:]:
        for field in FIELDS:
            np.testing.assert_array_equal(getattr(other, field), getattr(runs[0], field), err_msg=field)


# ---- early stops -------------------------------------------------------------------------------------------------
@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")
@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")
@pytest.mark.parametrize("method", ["euler", "rk4", "dp54"])
def test_early_stops_give_the_python_kernels_status_message_and_samples(robot, monkeypatch, method):
    system = robot("double_pendulum", damping=False)

    def controller(t, q, v):
        return np.array([0.0, 1e200 if t > 0.0095 else 0.0])

    def run():
        with pytest.raises(ms.SimulationError) as info:
            ms.simulate(system, [0.3, 0.1], [0.0, 0.0], duration=0.1, dt=1e-3, integrator=method,
                        controller=controller, **options(method))  # fmt: skip
        return info.value

    fast, reference = on_kernel(True, run, monkeypatch), on_kernel(False, run, monkeypatch)
    assert fast.status == reference.status and str(fast) == str(reference)
    assert fast.status == ("step_collapsed" if method == "dp54" else "diverged")
    assert len(reference.trajectory) >= (3 if method in ADAPTIVE else 10)
    assert_same(fast.trajectory, reference.trajectory)


@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")
@pytest.mark.filterwarnings("ignore:invalid value encountered:RuntimeWarning")
def test_a_row_that_diverges_in_a_batch_stops_alone(robot, monkeypatch):
    system = robot("double_pendulum", damping=False)
    B = 4
    Q0 = np.tile([0.3, 0.1], (B, 1))
    V0 = np.zeros((B, 2))
    taus = np.zeros((B, 30, 2))
    taus[2, 10:, 1] = 1e200  # element 2 (the second thread's first) diverges at its 11th step

    def run():
        return ms.rollout(system, Q0, V0, duration=0.03, dt=1e-3, integrator="rk4", taus=taus, num_threads=2)

    fast, reference = on_kernel(True, run, monkeypatch), on_kernel(False, run, monkeypatch)
    assert list(fast.status) == ["completed", "completed", "diverged", "completed"]
    assert list(fast.status) == list(reference.status) and fast.messages == reference.messages
    np.testing.assert_array_equal(fast.n_samples, reference.n_samples)
    for field in FIELDS:
        np.testing.assert_array_equal(getattr(fast, field), getattr(reference, field), err_msg=field)
    for name in ("steps", "rejected_steps", "evaluations"):
        np.testing.assert_array_equal(fast.stats[name], reference.stats[name], err_msg=name)


# ---- Ctrl-C ------------------------------------------------------------------------------------------------------
def test_ctrl_c_mid_run_keeps_every_sample(robot, monkeypatch):
    """A real SIGINT while the engine runs: the run stops within its budget with every sample, each one the
    uninterrupted run's."""
    system = robot("ur5")
    q0, v0, _ = start(system)
    monkeypatch.setenv("MULTIBODY_SIM_NATIVE", "1")
    timer = threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGINT))
    began = time.perf_counter()
    timer.start()
    try:
        with pytest.raises(ms.SimulationInterrupted) as info:
            ms.simulate(system, q0, v0, duration=1e4, dt=1e-3, output_dt=0.01)
    finally:
        timer.cancel()
    assert time.perf_counter() - began < 60.0  # honoured (the run itself would take minutes)
    traj = info.value.trajectory
    assert traj.status == "interrupted" and len(traj) > 10
    steps = traj.stats["steps"]
    assert str(info.value) == f"interrupted at t = {traj.t[-1]:.6g} s (step {steps}); {len(traj)} samples kept"
    whole = ms.simulate(system, q0, v0, duration=traj.t[-2], dt=1e-3, output_dt=0.01)
    n = len(whole)
    assert n == len(traj) - 1  # every sample on the grid up to the last one, which is the state where it stopped
    for field in FIELDS:
        np.testing.assert_array_equal(getattr(traj, field)[:n], getattr(whole, field), err_msg=field)
    np.testing.assert_array_equal(np.diff(traj.t[:n]), np.diff(whole.t))


# ---- which kernel runs, and why not ----------------------------------------------------------------------------
def test_why_a_run_is_not_native(robot, monkeypatch):
    system = robot("ur5")
    assert why_not_native(system, ms.INTEGRATORS["rk4"]) is None
    assert why_not_native(system, ms.INTEGRATORS["implicit_euler"]) == (
        "integrator 'implicit_euler' is not an explicit method of the registry"
    )
    assert "\nkernel: native\n" in ms.simulate(system, system.neutral(), np.zeros(6), duration=0.01, dt=1e-3).summary()
    monkeypatch.setenv("MULTIBODY_SIM_NATIVE", "0")
    assert why_not_native(system, ms.INTEGRATORS["rk4"]) == "MULTIBODY_SIM_NATIVE=0"
    traj = ms.simulate(system, system.neutral(), np.zeros(6), duration=0.01, dt=1e-3)
    assert traj.metadata["why_not_native"] == "MULTIBODY_SIM_NATIVE=0"
    assert "\nkernel: python (row) (not native: MULTIBODY_SIM_NATIVE=0)\n" in traj.summary()
    monkeypatch.delenv("MULTIBODY_SIM_NATIVE")
    wrapped = ms.load_robot("ur5")
    wrapped.unchecked_forward_dynamics = wrapped.unchecked_forward_dynamics
    assert why_not_native(wrapped, ms.INTEGRATORS["rk4"]) == (
        "the system's unchecked_forward_dynamics replaced in Python"
    )
    Q0, V0 = system.neutral()[None, :], np.zeros((1, system.nv))
    assert isinstance(choose_kernel(system, ms.INTEGRATORS["rk4"], Q0, V0), NativeKernel)
    assert not isinstance(choose_kernel(wrapped, ms.INTEGRATORS["rk4"], Q0, V0), NativeKernel)


def test_ctrl_c_in_a_batch_on_two_threads_keeps_every_sample(robot, monkeypatch):
    """SIGINT while two threads step their rows: every element keeps the same samples, each one simulate()'s."""
    system = robot("panda")
    rng = np.random.default_rng(5)
    B = 4
    Q0 = np.array([system.random_configuration(rng) for _ in range(B)])
    V0 = 0.1 * rng.normal(size=(B, system.nv))
    monkeypatch.setenv("MULTIBODY_SIM_NATIVE", "1")
    timer = threading.Timer(0.3, os.kill, (os.getpid(), signal.SIGINT))
    timer.start()
    try:
        with pytest.raises(ms.SimulationInterrupted) as info:
            ms.rollout(system, Q0, V0, duration=1e4, dt=1e-3, output_dt=0.01, num_threads=2, progress=False)
    finally:
        timer.cancel()
    batch = info.value.trajectory
    assert list(batch.status) == ["interrupted"] * B
    n = int(batch.n_samples[0])
    assert n > 10 and (batch.n_samples == n).all()
    for b in (0, B - 1):  # one row of each thread
        alone = ms.simulate(system, Q0[b], V0[b], duration=float(batch.t[b, n - 2]), dt=1e-3, output_dt=0.01)
        assert len(alone) == n - 1
        for field in FIELDS:
            np.testing.assert_array_equal(getattr(batch, field)[b, : n - 1], getattr(alone, field), err_msg=field)
