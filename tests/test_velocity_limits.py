"""Actuator velocity limits as rows of the time-stepper's contact problem (scenes/contact.py, "Velocity limits"):
checked against closed forms (a rotor driven by a load far above its effort limit: held at exactly v_max, each
step's impulse the load's momentum over the step), a falling go2 whose feet hit the ground under random torques (no
joint sample past its limit), the energy ledger, the off switch, steps far from the limits (the same problem and
solves as without the rows), and the native kernel against the Python one bit for bit."""

from __future__ import annotations


import numpy as np
import pytest
from conftest import assert_same_run, both, needs_native, shipped

import multibody_sim as ms
from multibody_sim.exceptions import SceneError
from multibody_sim.integrators import INTEGRATORS
from multibody_sim.integrators.cone_solver import TOLERANCE
from multibody_sim.scenes import make_scene
from multibody_sim.scenes.contact import ContactModel

EFFORT, V_MAX, LOAD = 10.0, 3.0, 100.0  # the load is 10 times what the motor can hold
I_ROTOR = 1.0 + 0.001  # the pendulum's inertia about its hinge [kg·m²] (tests/test_actuators.py)
DT = 1e-3
STATS = ("steps", "evaluations", "solver_steps", "solver_unconverged", "solver_iterations")


def rotor(
    load: float = LOAD, velocity_limits: str = "enforce", solver: str = "admm", randomize: dict | None = None,
    **actuator: object,
) -> ms.Scene:
    """The shipped pendulum without gravity (a free rotor of inertia I_ROTOR) with a torque actuator (effort 10 N·m,
    velocity limit 3 rad/s, its overspeed brake by default) and a constant external torque `load` about its hinge;
    a ground far below makes it a contact scene (stepped by timestepping) that nothing touches."""
    table = {"joints": "hinge", "kind": "torque", "effort_limit": EFFORT, "velocity_limit": V_MAX, **actuator}
    force = [{"name": "load", "frame": "bob", "torque": [0.0, load, 0.0]}]
    return make_scene(
        robot={"source": "pendulum"},
        gravity=[0, 0, 0],
        actuator=[table],
        force=force,
        ground={"height": -10.0},
        contact={"velocity_limits": velocity_limits, "solver": solver},
        **({"randomize": randomize} if randomize else {}),
    )


def spin(scene: ms.Scene, duration: float = 0.2) -> ms.Trajectory:
    return scene.run(duration=duration, dt=DT, controller=lambda t, q, v: np.zeros(1), q0=[0.0], v0=[0.0])


def test_the_rows_follow_the_brakes_and_turn_off() -> None:
    assert rotor().contact.speed_limits[0][:2] == (1, V_MAX)
    assert "velocity limits: enforced" in rotor().describe()
    assert rotor(velocity_limits="brake").contact.speed_limits == []
    assert rotor(overspeed="none").contact.speed_limits == []  # no brake: the joint declares no enforcement
    with pytest.raises(SceneError, match=r"contact.velocity_limits: must be one of brake, enforce"):
        rotor(velocity_limits="hard")


def test_a_load_far_above_the_effort_limit_is_held_at_exactly_the_limit() -> None:
    """From rest the load (100 N·m against 10 N·m of brake) reaches v_max after I v_max / (load − ...) and the rows
    hold the rotor there to the solver's tolerance; without them the brake cannot, and the speed climbs on."""
    capped, braked = spin(rotor()), spin(rotor(velocity_limits="brake"))
    assert capped.status == braked.status == "completed"
    speed = capped.v[:, 0]
    scale = max(LOAD * DT / I_ROTOR + V_MAX, 9.81 * DT)  # the step's velocity scale bounds the residual
    assert speed.max() <= V_MAX + TOLERANCE * scale
    reached = int(np.argmax(speed >= V_MAX - 1e-12))
    assert 0 < reached < 40  # the load's 0.1 rad/s per step brings it there in about 30 steps
    np.testing.assert_allclose(speed[reached:], V_MAX, rtol=0, atol=TOLERANCE * scale)
    assert braked.v[-1, 0] > 5 * V_MAX  # the brake alone: 10 N·m against 100
    assert abs(capped.energy_error).max() <= 1e-9 * capped.ledger["force:load"].energy[-1]


def test_the_impulse_is_the_momentum_the_load_gives_in_a_step() -> None:
    """At the limit each step's velocity-limit impulse is the load's h·load (closed form: I v⁺ = I v_max), whatever
    the brake's implicit share; the row's work, λ (v_max + v_free) / 2, is booked in the brake's ledger line."""
    scene = rotor()
    method = INTEGRATORS["timestepping"]
    q, v = np.zeros(1), np.array([V_MAX])
    state = method.init(scene, q, v)
    attempt = method.attempt(scene, q, v, np.zeros(1), DT, 0.0, state)
    scale = V_MAX + LOAD * DT / I_ROTOR  # the step's velocity scale: the solver's tolerance is relative to it
    assert attempt.v[0] == pytest.approx(V_MAX, abs=TOLERANCE * scale)
    impulse = attempt.state.impulses[("speed", 1, 1)][0]
    assert impulse == pytest.approx(LOAD * DT, abs=I_ROTOR * TOLERANCE * scale)
    problem, _ = attempt.state.active
    assert [s[2] for s in problem.speeds] == [1] and problem.points == []
    names = [name for name, _ in scene.ledger_elements]
    line = names.index("actuator_overspeed:hinge")
    v_free = V_MAX + LOAD * DT / (I_ROTOR + DT * EFFORT / (0.1 * V_MAX))  # the implicit brake's step
    assert attempt.flows[line] == pytest.approx(0.5 * impulse * (V_MAX + v_free), rel=1e-9)
    assert attempt.flows[names.index("contact")] == pytest.approx(0.0, abs=1e-15)


def test_a_joint_below_its_band_gets_no_row() -> None:
    """A speed below (1 − SPEED_BAND) v_max at the step's end: no row, nothing to solve."""
    scene = rotor(load=1.0)
    method = INTEGRATORS["timestepping"]
    q, v = np.zeros(1), np.array([0.5 * V_MAX])
    attempt = method.attempt(scene, q, v, np.zeros(1), DT, 0.0, method.init(scene, q, v))
    assert attempt.state.active is None and attempt.state.steps == 0


def falling_go2(velocity_limits: str, episodes: int = 4, scale: float = 1.0) -> ms.BatchTrajectory:
    """go2_standing with its catalog motors (velocity limits times `scale`) dropped from 0.2 m above its standing
    height under random torques within the effort limits (new every 2 ms), 0.4 s: the feet hit the ground."""
    tables = shipped("go2_standing", drop=("controller", "simulation"))
    tables["actuators"] = "catalog"
    tables["contact"] = {**tables.get("contact", {}), "velocity_limits": velocity_limits}
    if scale != 1.0:
        drawn = {"name": "velocity_limit", "joints": "*", "distribution": "uniform", "scale": [scale, scale]}
        tables["randomize"] = {"seed": 0, "parameter": [drawn]}
    scene = make_scene(**tables)
    n = 200
    taus = np.zeros((episodes, n, scene.nv))
    limit = scene.effort_limit[6:]
    for b in range(episodes):
        taus[b, :, 6:] = np.random.default_rng(b).uniform(-limit, limit, size=(n, len(limit)))
    Q0 = np.tile(scene.q0, (episodes, 1))
    Q0[:, 2] += 0.2
    V0 = np.zeros((episodes, scene.nv))
    return ms.rollout(scene, Q0, V0, duration=0.4, dt=DT, integrator="timestepping", taus=taus, control_dt=2e-3,
                      progress=False)  # fmt: skip


def test_a_falling_go2_keeps_every_joint_within_its_limit() -> None:
    capped = falling_go2("enforce")
    braked = falling_go2("brake")
    limits = np.array(make_scene(robot={"source": "go2"}).model.velocityLimit)[6:]
    assert (capped.status == "completed").all()
    ratio = np.abs(capped.v[:, :, 6:]).max(axis=(0, 1)) / limits
    assert ratio.max() <= 1.0 + 1e-6, ratio  # the solver's tolerance, relative to the step's velocity scale
    assert (np.abs(braked.v[:, :, 6:]).max(axis=(0, 1)) / limits).max() > 1.05  # the impacts do, without the rows
    for b in range(len(capped.status)):
        work = sum(np.abs(flow.energy[b]).max() for flow in capped.ledger.values())
        assert np.abs(capped.energy_error[b]).max() <= 1e-9 * work
    assert any(np.abs(capped.ledger[f"actuator_overspeed:{j}"].energy).max() > 0 for j in ("FL_calf_joint",
               "FR_calf_joint", "RL_calf_joint", "RR_calf_joint"))  # fmt: skip


def test_far_from_the_limits_the_step_is_the_same_as_without_the_rows() -> None:
    """A rotor at a third of its limit: the same problem sizes, solver counts and samples bit for bit as with
    velocity_limits = "brake" (the rows cost one comparison per joint there)."""
    runs = [
        rotor(load=0.0, velocity_limits=choice).run(
            duration=0.05, dt=DT, controller=lambda t, q, v: np.zeros(1), q0=[0.0], v0=[V_MAX / 3]
        )
        for choice in ("enforce", "brake")
    ]
    assert_same_run(*runs, STATS)


def test_go2_standing_far_from_its_limits_steps_as_without_the_rows() -> None:
    """go2_standing with its catalog motors held by its PD controller: every joint far below its limit, so the same
    problems, solver iterations and samples bit for bit with the rows on and off."""
    runs = []
    for choice in ("enforce", "brake"):
        tables = shipped("go2_standing", drop=("simulation",))
        tables["actuators"] = "catalog"
        tables["contact"] = {**tables.get("contact", {}), "velocity_limits": choice}
        scene = make_scene(**tables)
        runs.append(scene.run(duration=0.3, dt=DT))
    assert runs[0].stats["solver_steps"] == 300
    assert np.abs(runs[0].v[:, 6:]).max() < 0.5 * 15.7
    assert_same_run(*runs, STATS)


@needs_native
@pytest.mark.parametrize(("velocity_limits", "solver"), [("enforce", "admm"), ("brake", "admm"), ("enforce", "pgs")])
def test_the_native_kernel_renders_the_rows_bit_for_bit(velocity_limits, solver, monkeypatch) -> None:
    native_run, python_run = both(lambda: spin(rotor(velocity_limits=velocity_limits, solver=solver), 0.1), monkeypatch)
    assert native_run.metadata["kernel"] == "native" and python_run.metadata["kernel"] != "native"
    assert_same_run(native_run, python_run, STATS)


@needs_native
@pytest.mark.parametrize("scale", [1.0, 0.3])
def test_the_native_kernel_renders_a_falling_go2_bit_for_bit(scale, monkeypatch) -> None:
    """At 0.3 times its catalog velocity limits, most steps hold joints at their limits and tens of steps solve
    again with the rows the impacts need (counted on the Python side): the native kernel's re-solves too."""
    resolves = []
    speeding = ContactModel.speeding

    def counted(self, v, problem=None, band=0.0):
        added = speeding(self, v, problem, band)
        if problem is not None and added:
            resolves.append(len(added))
        return added

    monkeypatch.setattr(ContactModel, "speeding", counted)
    native_run, python_run = both(lambda: falling_go2("enforce", episodes=1, scale=scale), monkeypatch)
    assert len(resolves) >= (10 if scale < 1.0 else 1)
    for name in ("q", "v", "energy_error"):
        np.testing.assert_array_equal(getattr(native_run, name), getattr(python_run, name), err_msg=name)
    for name in native_run.ledger:
        np.testing.assert_array_equal(native_run.ledger[name].energy, python_run.ledger[name].energy, err_msg=name)


@needs_native
def test_rows_with_drawn_velocity_limits_hold_each_row_at_its_own(monkeypatch) -> None:
    """[randomize] draws each row's velocity limit: each row ends held at its own drawn limit, natively as on Python
    bit for bit (the engine's per-row contact scenes carry their limits)."""
    drawn = {"name": "velocity_limit", "joints": "hinge", "distribution": "uniform", "scale": [0.5, 1.5]}
    scene = rotor(randomize={"seed": 0, "parameter": [drawn]})

    def run():
        return ms.rollout(scene, np.zeros((4, 1)), np.zeros((4, 1)), duration=0.1, dt=DT, integrator="timestepping",
                          progress=False)  # fmt: skip

    native_run, python_run = both(run, monkeypatch)
    assert native_run.metadata["kernel"] == "native"
    limits = np.array([p["velocity_limit"]["hinge"] for p in native_run.metadata["parameters"]])
    assert len(set(limits.tolist())) == 4
    np.testing.assert_allclose(native_run.v[:, -1, 0], limits, rtol=0, atol=1e-8)
    np.testing.assert_array_equal(native_run.v, python_run.v)
    np.testing.assert_array_equal(native_run.energy_error, python_run.energy_error)
