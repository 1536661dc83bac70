"""Contact scenes on the native kernel (src/native/contact.cpp) against the Python kernel, their specification
(integrators/timestepping.py, scenes/contact.py): the same samples, energies, ledger flows, solver stats and
contact records bit for bit for simulate(), Stepper and rollout() on every shipped contact scene and on the shapes
and solvers the shipped scenes do not cover; a contact constant perturbed on one side breaks the agreement; solver
failures, Ctrl-C and the scenes that stay on Python behave as on the Python kernel."""

from __future__ import annotations

import dataclasses
import gc
import os
import signal
import threading
from pathlib import Path

import numpy as np
import pytest
from conftest import FIELDS, assert_same_run, assert_same_stepper, both, needs_native, on_kernel

import multibody_sim as ms
from multibody_sim.controllers import PDGravity
from multibody_sim.integrators import INTEGRATORS
from multibody_sim.integrators.timestepping import TimeStepping
from multibody_sim.kernels import native as native_core
from multibody_sim.kernels.native import BUDGET_SECONDS, next_budget, why_not_native
from multibody_sim.scenes import contact as contact_module
from multibody_sim.scenes import make_scene

pytestmark = needs_native

SCENES = sorted(p.stem for p in (Path(__file__).parents[1] / "models" / "scenes").glob("*.toml"))
CONTACT_SCENES = [name for name in SCENES if ms.load_scene(name).contact is not None]
STATS = ("steps", "rejected_steps", "evaluations", "solver_steps", "solver_unconverged", "solver_iterations",
         "controller_calls", "saturated_controls", "saturated_dofs")  # fmt: skip
TIMESTEPPING = INTEGRATORS["timestepping"]


def assert_same_contacts(a, b) -> None:
    assert (a is None) == (b is None)
    if a is not None:
        assert a.bodies == b.bodies
        for part in ("sample", "pair", "point", "normal", "impulse"):
            np.testing.assert_array_equal(getattr(a, part), getattr(b, part), err_msg=part)


def assert_same(a, b) -> None:
    """Every sample, ledger flow, count, solver count, contact record and the status equal bit for bit."""
    assert a.metadata["kernel"] == "native" and b.metadata["kernel"] != "native"
    assert_same_run(a, b, STATS)
    assert_same_contacts(a.contacts, b.contacts)


def simulate(scene, duration: float, **options):
    """simulate() of the scene from its initial state with timestepping at 1 ms."""
    return ms.simulate(
        scene, scene.q0, scene.v0, duration=duration, dt=1e-3, integrator="timestepping", progress=False, **options
    )


def scene_run(scene, steps: int = 300, **options):
    """simulate() of the scene's own settings (controller included) for `steps` steps."""
    settings = {**scene.simulation_settings(), **options}
    settings["duration"] = steps * settings["dt"]
    q0, v0 = settings.pop("q0"), settings.pop("v0")
    return lambda: ms.simulate(scene, q0, v0, progress=False, **settings)


# ---- every shipped contact scene ---------------------------------------------------------------------------------
def test_the_shipped_contact_scenes_are_the_ones_issue_16_names():
    assert set(CONTACT_SCENES) >= {"sliding_box", "bouncing_ball", "box_stack", "solo12_standing", "go2_standing",
                                   "talos_standing", "panda_push", "panda_limits"}  # fmt: skip


@pytest.mark.parametrize("name", CONTACT_SCENES)
def test_every_shipped_contact_scene_runs_natively_bit_for_bit(name, monkeypatch):
    scene = ms.load_scene(name)
    assert why_not_native(scene, TIMESTEPPING) is None
    native_run, python_run = both(scene_run(scene, 600), monkeypatch)  # the ball lands at 0.45 s
    assert_same(native_run, python_run)
    assert python_run.stats["solver_steps"] > 0  # the contact problem is exercised
    assert "\nkernel: native\n" in native_run.summary()
    # Still exact, on both kernels (they are equal above): the contact dissipates on every step (complementarity,
    # the penetration correction and restitution included), and the ledger closes to 1e-9 of the run's energy scale.
    ledger = python_run.ledger
    assert np.diff(ledger["contact"].energy).min() >= 0.0
    scale = np.abs(python_run.kinetic_energy).max() + np.abs(python_run.potential_energy).max()
    scale = max(scale, *(np.abs(entry.energy).max() for entry in ledger.values()))
    assert python_run.max_abs_energy_error <= 1e-9 * scale


def extra_scenes() -> dict:
    """What the shipped scenes leave out: PGS, a cylinder standing on its face (a patch of more than
    MAX_PATCH_POINTS points), a sphere bouncing on a box (a pair between two objects), restitution on a box, a
    penetration pushed out, a force element beside the contact."""
    can = {"name": "can", "shape": "cylinder", "radius": 0.1, "length": 0.2, "mass": 1.0,
           "position": [0.0, 0.0, 0.1], "velocity": [0.5, 0.0, 0.0, 0.0, 0.0, 2.0]}  # fmt: skip
    table = {"name": "table", "shape": "box", "size": [0.6, 0.6, 0.1], "mass": 5.0, "position": [0.0, 0.0, 0.05]}
    ball = {"name": "ball", "shape": "sphere", "radius": 0.05, "mass": 0.2, "position": [0.05, 0.0, 0.2],
            "velocity": [0.3, 0.0, 0.0, 0.0, 0.0, 0.0]}  # fmt: skip
    box = {"name": "box", "shape": "box", "size": [0.2, 0.1, 0.1], "mass": 1.0, "position": [0.0, 0.0, 0.3],
           "rpy": [0.2, 0.1, 0.0]}  # fmt: skip
    push = {"name": "push", "frame": "box", "force": [8.0, 0.0, 0.0], "reference": "world", "shape": "ramp",
            "ramp_time": 0.2}  # fmt: skip
    sliding = {"name": "box", "shape": "box", "size": [0.2, 0.2, 0.1], "mass": 1.0, "position": [0.0, 0.0, 0.05],
               "velocity": [1.0, 0.5, 0.0, 0.0, 0.0, 1.0]}  # fmt: skip
    return {
        "pgs": make_scene(ground={"friction": 0.8}, contact={"solver": "pgs"}, object=[sliding]),
        "cylinder": make_scene(ground={"friction": 0.5}, object=[can]),
        "ball on a table": make_scene(
            ground={"friction": 0.6, "restitution": 0.3},
            contact={"pairs": "all", "body_restitution": 0.5},
            object=[table, ball],
        ),
        "tilted box bouncing": make_scene(ground={"friction": 0.4, "restitution": 0.6}, object=[box]),
        "sunk box": make_scene(ground={"friction": 0.8}, object=[dict(sliding, position=[0.0, 0.0, 0.048])]),
        "pushed box": make_scene(ground={"friction": 0.5}, object=[dict(sliding, velocity=[0.0] * 6)], force=[push]),
    }


@pytest.mark.parametrize("label", ["pgs", "cylinder", "ball on a table", "tilted box bouncing", "pushed box"])
def test_shapes_pairs_and_solvers_beyond_the_shipped_scenes(label, monkeypatch):
    scene = extra_scenes()[label]
    assert why_not_native(scene, TIMESTEPPING) is None
    run = lambda: simulate(scene, 0.4)  # noqa: E731
    native_run, python_run = both(run, monkeypatch)
    assert_same(native_run, python_run)
    assert python_run.stats["solver_steps"] > 0
    if label == "cylinder":  # a patch of more points than the cap: the extreme ones were chosen
        per_sample = np.bincount(python_run.contacts.sample)
        assert per_sample.max() == contact_module.MAX_PATCH_POINTS
    if label in ("ball on a table", "tilted box bouncing"):
        assert python_run.ledger["restitution"].energy[-1] > 0.0  # a bounce happened
    if label == "pushed box":  # a force element with its ledger flow beside the contact's
        assert python_run.ledger["force:push"].energy[-1] > 0.0


CAPSULE_MJCF = """<mujoco model="capsule"><worldbody><body name="rod" pos="0 0 0.1"><freejoint name="root"/>
<geom name="rod" type="capsule" size="0.03 0.1" mass="1.0" euler="0 1.4 0"/></body></worldbody></mujoco>"""


def test_urdf_meshes_and_capsules_run_natively_bit_for_bit(monkeypatch, tmp_path):
    """solo12 released onto the ground on its URDF mesh hulls (their vertices against the ground; coal's archive of
    each hull crosses for the pairs coal computes) and an MJCF capsule landing on its side."""
    path = tmp_path / "capsule.xml"
    path.write_text(CAPSULE_MJCF)
    for scene, steps in ((make_scene(robot={"source": "solo12"}, ground={"friction": 0.8}), 150),
                         (make_scene(robot={"source": str(path)}, ground={"friction": 0.8}), 300)):  # fmt: skip
        kinds = {g.kind for g in scene.contact.geometries}
        assert kinds & {"mesh", "capsule"} and why_not_native(scene, TIMESTEPPING) is None
        native_run, python_run = both(lambda s=scene, n=steps: simulate(s, n * 1e-3), monkeypatch)  # noqa: B023
        assert_same(native_run, python_run)
        assert python_run.stats["solver_steps"] > 0


# ---- Stepper and rollout ------------------------------------------------------------------------------------------
def test_stepper_on_a_contact_scene(monkeypatch):
    """Stepper with a controller at control instants (jumps keep the warm start) and a state set by hand (a jump
    that restarts the solver state), as on the Python kernel."""
    scene = ms.load_scene("solo12_standing")

    def run():
        stepper = ms.Stepper(scene, dt=1e-3, integrator="timestepping", q0=scene.q0, v0=scene.v0, control_dt=4e-3)
        controller = scene.make_controller()
        stepper.advance_to(0.1, controller)
        stepper.v = 0.5 * stepper.v
        stepper.advance_to(0.2, controller)
        return stepper

    a, b = both(run, monkeypatch)
    assert_same_stepper(a, b)
    assert b.stats["evaluations"] > b.stats["steps"]  # contact steps (two evaluations each) were taken


@pytest.mark.parametrize("num_threads", [1, 2])
def test_rollout_of_a_contact_scene_on_threads(num_threads, monkeypatch):
    """Rows carry their own warm start and landings on any thread; each equals the Python kernel's rollout, whose
    rows take contact steps (two evaluations) at different times."""
    scene = ms.load_scene("bouncing_ball")
    B = 4
    Q0 = np.tile(scene.q0, (B, 1))
    Q0[:, 2] = [0.3, 0.5, 0.2, 0.4]  # the balls land at different steps
    V0 = np.tile(scene.v0, (B, 1))
    V0[:, 0] = [0.0, 0.2, -0.1, 0.3]
    run = lambda: ms.rollout(scene, Q0, V0, duration=0.6, dt=1e-3, integrator="timestepping",  # noqa: E731
                             num_threads=num_threads, progress=False)  # fmt: skip
    a, b = both(run, monkeypatch)
    for name in ("t", "q", "v", "energy_error", "kinetic_energy", "potential_energy"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    for key in ("steps", "evaluations"):  # evaluations: one per step, two with a contact problem
        np.testing.assert_array_equal(a.stats[key], b.stats[key], err_msg=key)
    for contacts_a, contacts_b in zip(a.contacts, b.contacts, strict=True):  # each element's, as simulate's
        assert_same_contacts(contacts_a, contacts_b)
    assert sum(len(c.sample) for c in b.contacts) > 0
    assert len(set(np.asarray(b.stats["evaluations"]).tolist())) > 1  # rows differ in their contact steps


def test_rollout_of_a_robot_contact_scene_with_its_controller_on_two_threads(monkeypatch):
    scene = ms.load_scene("solo12_standing")
    B = 3
    rng = np.random.default_rng(4)
    Q0 = np.array([scene.space.integrate(scene.q0, 0.02 * rng.normal(size=scene.nv)) for _ in range(B)])
    V0 = np.zeros((B, scene.nv))
    controller = PDGravity(scene, scene.q0, kp=20.0, kd=0.5)
    run = lambda: ms.rollout(scene, Q0, V0, duration=0.15, dt=1e-3, integrator="timestepping",  # noqa: E731
                             controller=controller, control_dt=2e-3, num_threads=2, progress=False)  # fmt: skip
    a, b = both(run, monkeypatch)
    for name in ("q", "v", "tau", "energy_error"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    for key in ("evaluations", "controller_calls"):
        np.testing.assert_array_equal(a.stats[key], b.stats[key], err_msg=key)


# ---- the test can fail: a contact constant perturbed on one side --------------------------------------------------
@pytest.mark.parametrize(
    "name, constant, label",
    [
        ("PENETRATION_CORRECTION", "reals", "sunk box"),  # the penetration correction's fraction
        ("PENETRATION_SLOP", "reals", "sunk box"),
        ("restitution", "restitution", "tilted box bouncing"),  # the restitution rule's coefficient
        ("friction", "friction", "pgs"),  # a pair's Coulomb coefficient, under PGS
        ("MAX_PATCH_POINTS", "ints", "cylinder"),
    ],
)
def test_a_contact_constant_perturbed_on_the_native_side_breaks_the_agreement(name, constant, label, monkeypatch):
    scene = extra_scenes()[label]
    run = lambda: simulate(scene, 0.4)  # noqa: E731
    native_run, python_run = both(run, monkeypatch)
    assert_same(native_run, python_run)  # unperturbed: equal
    contact_data = native_core.contact_data

    def perturbed(system, method):
        data = contact_data(system, method)
        if constant == "reals":
            data["constants"][name.lower()] *= 1 + 1e-9
        elif constant == "ints":
            data["constants"][name.lower()] -= 1
        else:
            data[constant] = [x * (1 + 1e-9) for x in data[constant]]
        return data

    monkeypatch.setattr(native_core, "contact_data", perturbed)
    broken = on_kernel(True, run, monkeypatch)
    differs = [field for field in FIELDS if not np.array_equal(getattr(broken, field), getattr(python_run, field))]
    assert differs, f"perturbing {name} changed nothing"


# ---- solver failures, Ctrl-C, refusals ----------------------------------------------------------------------------
def test_a_capped_solver_fails_the_run_natively_as_on_python(monkeypatch):
    bottom = {"name": "a", "shape": "box", "size": [0.3, 0.3, 0.1], "mass": 3.0, "position": [0, 0, 0.06],
              "rpy": [0.05, 0.02, 0.0]}  # fmt: skip
    top = {"name": "b", "shape": "box", "size": [0.2, 0.2, 0.1], "mass": 2.0, "position": [0, 0, 0.17],
           "rpy": [0.0, 0.05, 0.1]}  # fmt: skip
    scene = make_scene(ground={"friction": 0.8}, contact={"pairs": "all"}, object=[bottom, top])  # two tilted landings
    capped = TimeStepping(max_iterations=1)
    assert why_not_native(scene, capped) is None  # the cap is data for the engine

    def run():
        with pytest.raises(ms.SimulationError) as info:
            ms.simulate(scene, scene.q0, scene.v0, duration=0.05, dt=1e-3, integrator=capped, progress=False)
        return info.value

    a, b = both(run, monkeypatch)
    assert a.status == b.status == "solver_failed" and str(a) == str(b)
    assert_same(a.trajectory, b.trajectory)
    assert a.trajectory.stats["solver_unconverged"] > 0


def test_the_engine_budget_follows_the_rate_of_the_steps_taken():
    """The steps per engine call follow the steps a call actually took: a call that returned early at an event
    (one step in 10 µs) must not be read as a whole budget that fast (the next call would run ~200 000 box_stack
    steps, 20 s and more deaf to Ctrl-C, as a CI run once did); growth is at most 4x per call."""
    assert next_budget(64, 1, 1e-5) == 256  # the rate says 3000 steps; growth is held to 4x
    assert next_budget(64, 64, BUDGET_SECONDS) == 64  # on target: unchanged
    assert next_budget(1000, 1000, 2 * BUDGET_SECONDS) == 500  # too slow: halved
    assert next_budget(1 << 20, 1 << 20, 1e-3) == 1 << 20  # capped
    assert next_budget(64, 1, 10.0) == 16  # floored


def test_ctrl_c_mid_contact_run_keeps_every_sample(monkeypatch):
    """A real SIGINT while the engine steps a contact scene: every sample kept is the uninterrupted run's, with its
    contacts."""
    scene = ms.load_scene("box_stack")
    monkeypatch.setenv("MULTIBODY_SIM_NATIVE", "1")
    # Python's own Ctrl-C, and no gc callbacks meanwhile: Hypothesis (tests/test_fuzz.py) leaves one installed, and
    # a KeyboardInterrupt raised while it runs is lost ("Exception ignored in ... gc_callback"): in a full run the
    # interrupt was swallowed and the run went on for its 1e4 s
    previous = signal.signal(signal.SIGINT, signal.default_int_handler)
    callbacks = gc.callbacks[:]
    gc.callbacks.clear()
    timer = threading.Timer(0.5, os.kill, (os.getpid(), signal.SIGINT))
    timer.start()
    try:
        with pytest.raises(ms.SimulationInterrupted) as info:
            simulate(scene, 1e4, output_dt=0.01)
    finally:
        timer.cancel()
        gc.callbacks.extend(callbacks)
        signal.signal(signal.SIGINT, previous)
    traj = info.value.trajectory
    assert traj.status == "interrupted" and len(traj) > 5
    assert traj.metadata["kernel"] == "native"
    whole = simulate(scene, traj.t[-2], output_dt=0.01)
    n = len(whole)
    assert n == len(traj) - 1
    for field in FIELDS:
        np.testing.assert_array_equal(getattr(traj, field)[:n], getattr(whole, field), err_msg=field)
    kept = traj.contacts.sample < n
    for part in ("sample", "pair", "point", "normal", "impulse"):
        np.testing.assert_array_equal(getattr(traj.contacts, part)[kept], getattr(whole.contacts, part))
    assert traj.stats["solver_steps"] == traj.stats["steps"] > 0


def test_shapes_the_engine_does_not_render_stay_on_python_and_say_so():
    scene = ms.load_scene("sliding_box")
    model = scene.contact
    model.geometries[1] = dataclasses.replace(model.geometries[1], kind="ellipsoid")
    reason = why_not_native(scene, TIMESTEPPING)
    assert reason == (
        "the scene's collision geometry has ellipsoid shapes (the native kernel renders halfspace, box, sphere, "
        "cylinder, capsule, mesh)"
    )
    assert why_not_native(ms.load_scene("sliding_box"), INTEGRATORS["rk4"]) == (
        "the scene has contact, which only the timestepping integrator steps"
    )
    assert why_not_native(ms.load_robot("ur5"), TIMESTEPPING) == (
        "integrator 'timestepping' runs natively on contact scenes only"
    )


def test_batch_stepper_on_a_contact_scene_with_a_row_reset(monkeypatch):
    """gym's BatchStepper on two threads: rows step one control interval per call, a reset row restarts its
    solver state, as on the Python kernel."""
    scene = ms.load_scene("bouncing_ball")
    B = 3
    Q0 = np.tile(scene.q0, (B, 1))
    Q0[:, 2] = [0.2, 0.3, 0.25]

    def run():
        batch = ms.BatchStepper(scene, Q0, np.zeros((B, scene.nv)), dt=1e-3, integrator="timestepping",
                                num_threads=2)  # fmt: skip
        for _ in range(300):
            batch.step(np.zeros((B, scene.nv)))
        batch.reset(rows=[1], q=Q0[1:2], v=np.ones((1, scene.nv)))
        for _ in range(200):
            batch.step(np.zeros((B, scene.nv)))
        return batch.q.copy(), batch.v.copy()

    (qa, va), (qb, vb) = both(run, monkeypatch)
    np.testing.assert_array_equal(qa, qb)
    np.testing.assert_array_equal(va, vb)


def test_stepper_restores_the_solver_state_after_a_diverged_interval(monkeypatch):
    """A Stepper interval that diverges is undone (the state, the warm start, the counts) on either kernel alike,
    and the run goes on from there."""
    scene = ms.load_scene("solo12_standing")

    def run():
        stepper = ms.Stepper(scene, dt=1e-3, integrator="timestepping", q0=scene.q0, v0=scene.v0)
        controller = scene.make_controller()
        stepper.advance_to(0.05, controller)
        v = stepper.v
        stepper.v = np.full(scene.nv, 1e300)  # a jump to a state whose energy overflows
        with pytest.raises(ms.SimulationError) as info:
            stepper.step(controller(stepper.t, stepper.q, stepper.v))
        assert info.value.status == "diverged"
        stepper.v = v
        stepper.advance_to(0.1, controller)
        return stepper

    a, b = both(run, monkeypatch)
    assert_same_stepper(a, b, energy_error=False)  # NaN on both: the jump to 1e300 overflowed the reference
