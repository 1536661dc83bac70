"""One stepping core: simulate(), Stepper and rollout() drive the same loop, so they agree bit for bit, for every
integrator, on a fixed arm, a floating robot and a scene with springs, damping and a wrench; the integrator contract
(solver state, status) and its adapter for subclasses written against the first contract; runs that end by user
code keep their samples."""

from __future__ import annotations

import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import multibody_sim as ms
from multibody_sim.integrators import Integrator

DT = 1e-3
STEPS = 40  # 8 control intervals of 5 dt
CONTROL = 5 * DT
ADAPTIVE = {"rtol": 1e-7, "atol": 1e-9}
SYSTEMS = ("arm", "floating", "scene")


def exact(message: str) -> str:
    return f"^{re.escape(message)}$"


@pytest.fixture(scope="module")
def systems() -> dict[str, ms.Robot]:
    """A damped arm with effort limits, a floating base, and a fixed-base scene with springs, damping, friction and
    a time-dependent wrench (its own ledger elements, potentials and a frame Jacobian per evaluation)."""
    scene = ms.make_scene(
        robot={"source": "ur5"},
        joints={
            "shoulder_lift_joint": {"stiffness": 30.0, "rest": -1.0, "damping": 0.5},
            "elbow_joint": {"stiffness": 10.0, "rest": 1.2, "friction": 0.2},
            "wrist_1_joint": {"damping": 0.2},
        },
        force=[{"name": "push", "frame": "tool0", "force": [5.0, 0.0, -3.0], "shape": "ramp", "ramp_time": 0.02}],
        friction_velocity=0.05,
    )
    return {"arm": ms.load_robot("panda"), "floating": ms.load_robot("solo12"), "scene": scene}


def start(system: ms.Robot, seed: int = 3) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    return system.random_configuration(rng), 0.3 * rng.normal(size=system.nv)


def tracking(system: ms.Robot) -> Any:
    """A time-varying PD controller (on the panda its gains saturate some joints); zero on a floating base's 6
    unactuated entries, and gentle on solo12's light legs (explicit Euler at 1 ms stays stable)."""
    target = system.random_configuration(np.random.default_rng(7))
    actuated = np.arange(system.nv) >= (6 if system.floating_base else 0)
    kp, kd = (2.0, 0.05) if system.floating_base else (300.0, 2.0)

    def controller(t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        error = system.space.difference(q, target) * (1.0 + 0.5 * np.sin(20.0 * t))
        return np.where(actuated, kp * error - kd * v, 0.0)

    return controller


def refused(system: ms.Robot, name: str) -> str | None:
    try:
        ms.INTEGRATORS[name].check_system(system)
    except ms.InvalidArgumentError as exc:
        return str(exc)
    return None


@pytest.mark.parametrize("case", SYSTEMS)
@pytest.mark.parametrize("name", sorted(ms.INTEGRATORS))
@pytest.mark.parametrize("controlled", [False, True], ids=["free", "controlled"])
def test_stepper_and_rollout_give_simulates_samples_at_every_control_instant(systems, case, name, controlled) -> None:
    system = systems[case]
    why = refused(system, name)
    if why:
        pytest.skip(why)
    method = ms.INTEGRATORS[name]
    q0, v0 = start(system)
    options = dict(ADAPTIVE) if method.adaptive else {}
    controller = tracking(system) if controlled else None
    traj = ms.simulate(
        system, q0, v0, duration=STEPS * DT, dt=DT, integrator=name, controller=controller,
        control_dt=CONTROL, output_dt=CONTROL, **options,
    )  # fmt: skip
    assert traj.t.tolist() == [k * CONTROL if k < 8 else STEPS * DT for k in range(9)]
    stepper = ms.Stepper(system, dt=DT, integrator=name, control_dt=CONTROL, q0=q0, v0=v0, **options)
    for k in range(len(traj)):
        assert stepper.t == traj.t[k]
        np.testing.assert_array_equal(stepper.q, traj.q[k])
        np.testing.assert_array_equal(stepper.v, traj.v[k])
        assert stepper.work == traj.work[k] and stepper.dissipated == traj.dissipated[k]
        if k < len(traj) - 1:
            tau = controller(stepper.t, stepper.q, stepper.v) if controlled else None
            stepper.step(tau)
            np.testing.assert_array_equal(stepper.tau, traj.tau[k])
    if controlled and system.floating_base:
        assert not traj.tau[:, :6].any()  # the controller leaves the base alone
    for counter in ("steps", "rejected_steps", "evaluations", "saturated_controls"):
        assert stepper.stats[counter] == traj.stats[counter], counter
    # rollout: the same samples for every element, bit for bit
    Q0 = np.array([q0, start(system, 11)[0], q0])
    V0 = np.array([v0, start(system, 11)[1], -v0])
    batch = ms.rollout(
        system, Q0, V0, duration=STEPS * DT, dt=DT, integrator=name, controller=controller,
        control_dt=CONTROL, output_dt=CONTROL, **options,
    )  # fmt: skip
    first = batch.element(0)
    assert first.status == traj.status == "completed"
    for field in ("t", "q", "v", "tau", "kinetic_energy", "potential_energy", "work", "dissipated", "energy_error"):
        np.testing.assert_array_equal(getattr(first, field), getattr(traj, field), err_msg=field)
    for name_, entry in traj.ledger.items():
        np.testing.assert_array_equal(first.ledger[name_].energy, entry.energy, err_msg=name_)


def test_a_scene_with_springs_friction_and_a_wrench_batches(systems, monkeypatch) -> None:
    """Without the native kernel a batch of a scene runs the row kernel over its rows: the metadata names the kernel.
    (The native kernel takes scenes where it is built: tests/test_native_scene.py; here the Python kernel.)"""
    monkeypatch.setenv("MULTIBODY_SIM_NATIVE", "0")
    scene = systems["scene"]
    Q0 = np.array([start(scene, s)[0] for s in range(4)])
    batch = ms.rollout(scene, Q0, np.zeros((4, scene.nv)), duration=0.01, dt=DT)
    assert batch.metadata["kernel"] == "python (row)"
    alone = ms.simulate(scene, Q0[2], np.zeros(scene.nv), duration=0.01, dt=DT)
    assert alone.metadata["kernel"] == "python (row)"
    np.testing.assert_array_equal(batch.element(2).q, alone.q)
    for name, entry in alone.ledger.items():  # springs' potentials, damping, friction, the wrench's work
        np.testing.assert_array_equal(batch.element(2).ledger[name].energy, entry.energy)


# ---- the integrator contract -------------------------------------------------------------------------------------
class OldStyleEuler(Integrator):
    """An integrator written against the first contract: step() only."""

    name = "old_style_euler"
    order = 1
    description = "forward Euler through step()"
    evaluations_per_step = 1

    def step(self, system, q, v, tau, dt, t=0.0):
        a = system.unchecked_forward_dynamics(q, v, tau, t)
        return system.space.integrate(q, dt * v), v + dt * a, dt * system.ledger_power(q, v, tau, None, t)


def test_a_subclass_of_the_first_contract_keeps_working_through_the_adapter() -> None:
    # Its step() equals euler's: the same trajectory through simulate, Stepper and rollout.
    dp = ms.load_robot("double_pendulum")
    q0, v0 = np.array([1.0, 0.5]), np.array([0.0, 0.3])
    old = ms.simulate(dp, q0, v0, duration=0.05, dt=DT, integrator=OldStyleEuler())
    euler = ms.simulate(dp, q0, v0, duration=0.05, dt=DT, integrator="euler")
    np.testing.assert_array_equal(old.q, euler.q)
    np.testing.assert_array_equal(old.work, euler.work)
    stepper = ms.Stepper(dp, dt=DT, integrator=OldStyleEuler(), q0=q0, v0=v0)
    stepper.advance_to(0.05)
    np.testing.assert_array_equal(stepper.q, old.q[-1])
    batch = ms.rollout(dp, np.array([q0, q0]), np.array([v0, v0]), duration=0.05, dt=DT, integrator=OldStyleEuler())
    np.testing.assert_array_equal(batch.element(1).q, old.q)


def test_a_subclass_that_implements_no_step_is_refused_with_what_to_implement() -> None:
    class Empty(Integrator):
        name = "empty"
        order = 1
        description = "nothing"
        evaluations_per_step = 1

    message = (
        "integrator test_a_subclass_that_implements_no_step_is_refused_with_what_to_implement.<locals>.Empty "
        "implements neither attempt(system, q, v, tau, h, t, state) -> Attempt (the contract) nor "
        "step(system, q, v, tau, dt, t) -> (q, v, flows) (the first contract, still accepted for fixed-step "
        "methods): implement one of them"
    )
    dp = ms.load_robot("double_pendulum")
    for call in (
        lambda: ms.simulate(dp, [0.0, 0.0], [0.0, 0.0], duration=0.01, dt=DT, integrator=Empty()),
        lambda: ms.Stepper(dp, dt=DT, integrator=Empty()),
        lambda: ms.rollout(dp, np.zeros((2, 2)), np.zeros((2, 2)), duration=0.01, dt=DT, integrator=Empty()),
    ):
        with pytest.raises(ms.InvalidArgumentError, match=exact(message)):
            call()


def test_a_failed_step_is_a_status_not_an_exception() -> None:
    # Newton cannot converge in one iteration on a stiff step: attempt() says so, step() raises it.
    arm = ms.load_robot("stiff_arm")
    method = ms.integrators.implicit.ImplicitEuler(max_iterations=1)
    q, v = arm.random_configuration(0), np.array([3.0, -2.0])
    result = method.attempt(arm, q, v, np.zeros(arm.nv), 0.05)
    assert result.status == "newton_failed" and result.q is None and result.evaluations == 1
    assert result.message.startswith("Newton did not converge in 1 iteration")
    with pytest.raises(ms.integrators.StepFailure, match="Newton did not converge in 1 iteration"):
        method.step(arm, q, v, np.zeros(arm.nv), 0.05)


def test_adaptive_solver_state_carries_the_fsal_stage() -> None:
    dp = ms.load_robot("double_pendulum")
    method = ms.INTEGRATORS["dp54"]
    q, v, tau = np.array([1.0, 0.2]), np.array([0.1, 0.0]), np.zeros(2)
    loose = {"rtol": 1e-3, "atol": 1e-3}
    first = method.attempt(dp, q, v, tau, 0.002, 0.0, method.init(dp, q, v), **loose)
    assert first.evaluations == 7 and first.error is not None and first.error <= 1.0
    reused = method.attempt(dp, first.q, first.v, tau, 0.002, 0.002, first.state, **loose)
    fresh = method.attempt(dp, first.q, first.v, tau, 0.002, 0.002, method.init(dp, first.q, first.v), **loose)
    assert (reused.evaluations, fresh.evaluations) == (6, 7)  # the last stage was the next step's first
    np.testing.assert_array_equal(reused.q, fresh.q)


# ---- runs ended by user code keep their samples ------------------------------------------------------------------
class Boom(RuntimeError):
    pass


def test_a_controller_that_raises_stops_the_run_with_its_samples_and_the_cause(tmp_path: Path) -> None:
    dp = ms.load_robot("double_pendulum")

    def controller(t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        if t >= 0.01:
            raise Boom("sensor lost")
        return np.zeros(2)

    out = tmp_path / "run.npz"
    with pytest.raises(ms.SimulationError) as caught:
        ms.simulate(dp, [1.0, 0.0], [0.0, 0.0], duration=0.1, dt=DT, controller=controller, out=out)
    error = caught.value
    assert error.status == "failed" and isinstance(error.__cause__, Boom)
    assert str(error) == "failed at t = 0.01 s: the controller raised Boom: sensor lost"
    assert error.trajectory.t[-1] == pytest.approx(0.01) and len(error.trajectory) == 11
    saved = ms.Trajectory.load(out)
    assert saved.status == "failed" and np.array_equal(saved.q, error.trajectory.q)


def test_a_controller_output_that_is_not_a_torque_keeps_its_message_and_both_error_kinds() -> None:
    dp = ms.load_robot("double_pendulum")
    with pytest.raises(ms.SimulationError) as caught:
        ms.simulate(dp, [1.0, 0.0], [0.0, 0.0], duration=0.1, dt=DT, controller=lambda t, q, v: np.zeros(3))
    error = caught.value
    assert isinstance(error, ms.InvalidArgumentError) and isinstance(error, ms.ControllerOutputError)
    assert str(error) == "controller output at t = 0 s: tau must have shape (2,), got (3,)"
    assert error.status == "failed" and len(error.trajectory) == 1


def test_an_on_sample_callback_that_raises_keeps_the_samples_it_saw(tmp_path: Path) -> None:
    dp = ms.load_robot("double_pendulum")
    seen: list[float] = []

    def on_sample(t: float, q: np.ndarray, v: np.ndarray) -> None:
        seen.append(t)
        if len(seen) == 5:
            raise Boom("viewer closed")

    with pytest.raises(ms.SimulationError) as caught:
        ms.simulate(dp, [1.0, 0.0], [0.0, 0.0], duration=0.1, dt=DT, on_sample=on_sample, out=tmp_path / "r.npz")
    assert caught.value.status == "failed" and isinstance(caught.value.__cause__, Boom)
    assert caught.value.trajectory.t.tolist() == seen
    assert ms.Trajectory.load(tmp_path / "r.npz").t.tolist() == seen


def test_a_scene_force_that_raises_fails_the_run_and_in_a_batch_every_element() -> None:
    def shape(t: float) -> float:
        if t > 0.005:
            raise Boom("force table ended")
        return 1.0

    scene = ms.make_scene(
        robot={"source": "double_pendulum"}, force=[{"frame": "link2", "force": [1, 0, 0], "shape": shape}]
    )
    with pytest.raises(ms.SimulationError) as caught:
        ms.simulate(scene, [1.0, 0.0], [0.0, 0.0], duration=0.02, dt=DT)
    assert caught.value.status == "failed" and isinstance(caught.value.__cause__, Boom)
    assert "Boom raised in the dynamics: force table ended" in str(caught.value)
    assert caught.value.trajectory.t[-1] == pytest.approx(0.005)
    batch = ms.rollout(scene, np.array([[1.0, 0.0]] * 3), np.zeros((3, 2)), duration=0.02, dt=DT)
    assert batch.status.tolist() == ["failed"] * 3 and batch.n_samples.tolist() == [len(caught.value.trajectory)] * 3


def test_in_a_rollout_a_failing_element_fails_alone() -> None:
    dp = ms.load_robot("double_pendulum")

    def picky(t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        if q[0] > 0.5 and t > 0.0:
            raise Boom("out of range")
        return -0.1 * v

    Q0 = np.array([[0.0, 0.0], [1.0, 0.0], [0.2, 0.0]])
    batch = ms.rollout(dp, Q0, np.zeros((3, 2)), duration=0.02, dt=DT, controller=picky)
    assert batch.status.tolist() == ["completed", "failed", "completed"]
    assert batch.messages[1] == "failed at t = 0.001 s: the controller raised Boom: out of range"
    assert batch.n_samples.tolist() == [21, 2, 21]
    reference = ms.simulate(dp, Q0[2], [0.0, 0.0], duration=0.02, dt=DT, controller=picky)
    np.testing.assert_array_equal(batch.element(2).q, reference.q)
