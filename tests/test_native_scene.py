"""Scenes and built-in controllers on the native kernel (src/native/scene.cpp) against the Python kernel, their
specification: the same samples, ledger, records, counts and saturation for simulate(), Stepper and rollout() on
every shipped scene the native kernel renders and on the benchmark's scene variants; a perturbed element
coefficient breaks the agreement; the energy ledger closes as tightly; built-in controllers run without a call
into Python per control instant; the scenes that stay on Python say why."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from conftest import assert_same_run, assert_same_stepper, both, needs_native, on_kernel

import multibody_sim as ms
from multibody_sim.controllers import PD, GravityCompensation, PDGravity
from multibody_sim.integrators import INTEGRATORS
from multibody_sim.kernels import native as native_core
from multibody_sim.kernels.native import why_not_native
from multibody_sim.scenes.elements import ForceElements

pytestmark = needs_native

SCENES = sorted(p.stem for p in (Path(__file__).parents[1] / "models" / "scenes").glob("*.toml"))
RK4 = INTEGRATORS["rk4"]


def assert_same(a, b) -> None:
    """Every sample, ledger entry (springs' records included), count and status equal bit for bit."""
    assert a.metadata["kernel"] == "native" and b.metadata["kernel"] != "native"
    assert_same_run(a, b)


def scene_variants(robot_name: str = "ur5", frame: str = "tool0") -> dict:
    """scripts/bench_rollout.py's scene section: springs, damping and friction on every joint; with a ramped world
    force at `frame`; with a sine local wrench at `frame`."""
    robot = ms.load_robot(robot_name, damping=False)
    joints = {
        joint: {"stiffness": 2.0, "rest": 0.1, "damping": 0.05, "friction": 0.02}
        for joint in robot.model.names[1:]
        if robot.model.joints[robot.model.getJointId(joint)].nv == 1
    }
    push = {"name": "push", "frame": frame, "force": [5.0, 0.0, 0.0], "reference": "world", "shape": "ramp"}
    wrench = {"name": "wrench", "frame": frame, "force": [5.0, 0.0, 0.0], "torque": [0.0, 0.0, 0.2],
              "reference": "local", "shape": "sine", "frequency": 2.0}  # fmt: skip
    source = {"source": robot_name, "damping": False}
    return {
        "springs, damping, friction": ms.make_scene(robot=source, joints=joints),
        "+ a world force": ms.make_scene(robot=source, joints=joints, force=[{**push, "ramp_time": 0.1}]),
        "+ a local wrench": ms.make_scene(robot=source, joints=joints, force=[wrench]),
    }


def start(scene, seed: int = 0):
    """A seeded (q0, v0) near the scene's initial state."""
    rng = np.random.default_rng(seed)
    q0 = scene.space.integrate(scene.q0, 0.2 * rng.normal(size=scene.nv))
    return q0, scene.v0 + 0.5 * rng.normal(size=scene.nv)


# ---- every shipped scene -------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", SCENES)
def test_every_shipped_scene_runs_natively_bit_for_bit_or_says_why_not(name, monkeypatch):
    scene = ms.load_scene(name)
    reason = why_not_native(scene, RK4)
    if scene.contact is not None or scene.constraints is not None or scene.mimic:
        assert reason is not None and any(word in reason for word in ("contact", "constraints", "mimic"))
        return
    assert reason is None
    settings = {**scene.simulation_settings(), "duration": 0.2}
    if why_not_native(scene, INTEGRATORS[settings["integrator"]]) is not None:  # an implicit method: RK4 instead
        settings["integrator"] = "rk4"
        settings["dt"] = min(settings["dt"], 1e-3)
    q0, v0 = settings.pop("q0"), settings.pop("v0")
    native_run, python_run = both(lambda: ms.simulate(scene, q0, v0, progress=False, **settings), monkeypatch)
    assert_same(native_run, python_run)


@pytest.mark.parametrize("method", ["semi_implicit_euler", "midpoint", "rk4", "dp54", "dop853"])
@pytest.mark.parametrize("name", ["ur5_ceiling_push", "free_body_torqued", "spring_chain", "panda_payload"])
def test_scenes_agree_for_every_kind_of_method(name, method, monkeypatch):
    scene = ms.load_scene(name)
    options = {"rtol": 1e-8, "atol": 1e-8, "output_dt": 0.01} if INTEGRATORS[method].adaptive else {}
    native_run, python_run = both(
        lambda: ms.simulate(scene, *start(scene), duration=0.3, dt=1e-3, integrator=method, progress=False, **options),
        monkeypatch,
    )
    assert_same(native_run, python_run)


# ---- the benchmark's scene variants: simulate, Stepper, rollout on two threads ---------------------------------------
@pytest.mark.parametrize("label", ["springs, damping, friction", "+ a world force", "+ a local wrench"])
def test_bench_scene_variants_simulate_and_rollout(label, monkeypatch):
    scene = scene_variants()[label]
    assert why_not_native(scene, RK4) is None
    native_run, python_run = both(
        lambda: ms.simulate(scene, *start(scene), duration=0.3, dt=1e-3, progress=False), monkeypatch
    )
    assert_same(native_run, python_run)
    B = 5
    starts = [start(scene, seed) for seed in range(B)]
    Q0, V0 = np.array([q for q, _ in starts]), np.array([v for _, v in starts])
    batch = on_kernel(True, lambda: ms.rollout(scene, Q0, V0, duration=0.2, dt=1e-3, num_threads=2,
                                               progress=False), monkeypatch)  # fmt: skip
    for b in range(B):  # each element is the Python kernel's simulate() of its state
        one = on_kernel(False, lambda b=b: ms.simulate(scene, Q0[b], V0[b], duration=0.2, dt=1e-3, progress=False),
                        monkeypatch)  # fmt: skip
        for name in ("q", "v", "energy_error"):
            np.testing.assert_array_equal(getattr(batch, name)[b], getattr(one, name), err_msg=name)


def test_bench_scene_variants_stepper(monkeypatch):
    scene = scene_variants()["+ a local wrench"]

    def run():
        stepper = ms.Stepper(scene, dt=1e-3, q0=start(scene)[0], control_dt=5e-3)
        stepper.advance_to(0.2, PDGravity(scene, scene.q0, kp=300.0))
        return stepper

    a, b = both(run, monkeypatch)
    assert_same_stepper(a, b)


# ---- built-in controllers natively -------------------------------------------------------------------------------
def controllers(scene):
    q_ref = scene.space.integrate(scene.q0, np.full(scene.nv, 0.3))
    return {
        "pd": lambda: PD(scene, q_ref, kp=400.0),
        "gravity": lambda: GravityCompensation(scene),
        "pd_gravity": lambda: PDGravity(scene, q_ref, kp=3000.0, v_ref=np.full(scene.nv, 0.1)),  # saturates
    }


@pytest.mark.parametrize("kind", ["pd", "gravity", "pd_gravity"])
def test_builtin_controllers_run_natively_without_python_per_instant(kind, monkeypatch):
    scene = ms.load_scene("ur5_ceiling_push")
    make = controllers(scene)[kind]
    q0, v0 = start(scene)
    python_run = on_kernel(False, lambda: ms.simulate(scene, q0, v0, duration=0.3, dt=1e-3, controller=make(),
                                                      control_dt=2e-3, progress=False), monkeypatch)  # fmt: skip
    calls = []
    for cls in (PD, GravityCompensation, PDGravity):  # the native run never calls the Python controller
        monkeypatch.setattr(cls, "__call__", lambda self, t, q, v: calls.append(t) or np.zeros(scene.nv))
    native_run = on_kernel(True, lambda: ms.simulate(scene, q0, v0, duration=0.3, dt=1e-3, controller=make(),
                                                     control_dt=2e-3, progress=False), monkeypatch)  # fmt: skip
    assert calls == []
    assert_same(native_run, python_run)
    assert native_run.stats["controller_calls"] == 150
    if kind == "pd_gravity":
        assert native_run.stats["saturated_controls"] > 0  # saturation is exercised


@pytest.mark.parametrize("method", ["rk4", "bs32", "dp54"])
def test_builtin_controllers_at_adaptive_control_instants_and_every_step(method, monkeypatch):
    scene = ms.load_scene("ur5_ceiling_push")
    options = {"rtol": 1e-8, "atol": 1e-8} if INTEGRATORS[method].adaptive else {}
    for control_dt in (None, 0.01):
        if control_dt is None and not options:
            continue
        run = lambda control_dt=control_dt: ms.simulate(  # noqa: E731
            scene, *start(scene), duration=0.3, dt=1e-3, integrator=method, controller=controllers(scene)["pd"](),
            control_dt=control_dt, progress=False, **options)  # fmt: skip
        assert_same(*both(run, monkeypatch))


def test_rollout_controllers_per_row_taus_and_saturation_on_two_threads(monkeypatch):
    scene = ms.load_scene("ur5_ceiling_push")
    B = 4
    starts = [start(scene, seed) for seed in range(B)]
    Q0, V0 = np.array([q for q, _ in starts]), np.array([v for _, v in starts])
    make = controllers(scene)
    sweep = [make["pd"](), make["gravity"](), make["pd_gravity"](), PD(scene, scene.q0, kp=[10.0 * (i + 1) for i in
                                                                                             range(6)])]  # fmt: skip
    taus = np.random.default_rng(3).normal(size=(B, 100, scene.nv)) * 100.0  # beyond the effort limits at times
    for kwargs in ({"controller": sweep}, {"controller": make["pd_gravity"]()}, {"taus": taus}):
        run = lambda kwargs=kwargs: ms.rollout(scene, Q0, V0, duration=0.2, dt=1e-3, control_dt=2e-3,  # noqa: E731
                                              num_threads=2, progress=False, **kwargs)  # fmt: skip
        a, b = both(run, monkeypatch)
        for name in ("q", "v", "tau", "energy_error"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
        for key in ("controller_calls", "saturated_controls", "saturated_dofs"):
            np.testing.assert_array_equal(a.stats[key], b.stats[key], err_msg=key)
    assert np.asarray(a.stats["saturated_controls"]).sum() > 0


def test_a_python_controller_keeps_the_drivers_events(monkeypatch):
    scene = ms.load_scene("ur5_ceiling_push")
    pd = controllers(scene)["pd"]()
    seen = []

    def controller(t, q, v):
        seen.append(t)
        return pd(t, q, v)

    run = lambda: ms.simulate(scene, scene.q0, scene.v0, duration=0.1, dt=1e-3, controller=controller,  # noqa: E731
                              control_dt=5e-3, progress=False)  # fmt: skip
    a, b = both(run, monkeypatch)
    assert_same(a, b)
    assert len(seen) == 2 * 20


# ---- the test can fail: a perturbed coefficient --------------------------------------------------------------------
def nudged(term: dict, field: str) -> dict:
    """The term (a native term's fields) with its number `field` (or each number of its list) times 1 + 1e-9."""
    value = term[field]
    value = [x * (1 + 1e-9) for x in value] if isinstance(value, list) else value * (1 + 1e-9)
    return {**term, field: value}


# (the scene variant, the native data's list, the field nudged in its first term); viscous damping is the robot's
# (the kernel's own), not an element
PERTURBATIONS = {
    "spring": ("+ a world force", "springs", "minus_k"),
    "friction": ("+ a world force", "rough", "c"),
    "spring energy": ("+ a world force", "energies", "k"),
    "world force's ramp": ("+ a world force", "wrenches", "ramp_time"),
    "local wrench": ("+ a local wrench", "wrenches", "w6"),
    "local wrench's sine": ("+ a local wrench", "wrenches", "frequency"),
}


@pytest.mark.parametrize("what", sorted(PERTURBATIONS))
def test_a_perturbed_element_coefficient_breaks_the_agreement(what, monkeypatch):
    label, terms, field = PERTURBATIONS[what]
    scene = scene_variants()[label]
    q0, v0 = start(scene)
    run = lambda: ms.simulate(scene, q0, v0, duration=0.3, dt=1e-3, progress=False)  # noqa: E731
    python_run = on_kernel(False, run, monkeypatch)
    assert_same(on_kernel(True, run, monkeypatch), python_run)  # unperturbed: equal
    native_data = ForceElements.native_data

    def perturbed(self, load_model):
        data = native_data(self, load_model)
        data[terms][0] = nudged(data[terms][0], field)
        return data

    monkeypatch.setattr(ForceElements, "native_data", perturbed)
    with pytest.raises(AssertionError):
        assert_same(on_kernel(True, run, monkeypatch), python_run)


# ---- the energy ledger closes -------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["double_pendulum_spring_friction", "ur5_ceiling_push", "free_body_torqued"])
def test_the_energy_ledger_closes_as_on_the_python_kernel(name, monkeypatch):
    scene = ms.load_scene(name)
    run = lambda: ms.simulate(scene, scene.q0, scene.v0, duration=1.0, dt=1e-3, progress=False)  # noqa: E731
    a, b = both(run, monkeypatch)
    scale = np.abs(a.total_energy).max() + np.abs(a.work).max() + np.abs(a.dissipated).max() + 1.0
    assert np.abs(a.energy_error).max() <= 1e-5 * scale  # RK4 at 1 ms: the ledger closes
    assert np.abs(a.energy_error).max() <= np.abs(b.energy_error).max() * (1 + 1e-9) + 1e-15


# ---- what stays on Python -------------------------------------------------------------------------------------------
def test_why_a_scene_is_not_native(monkeypatch):
    def shape(t):
        return 0.5

    force = {"name": "f", "frame": "tool0", "force": [1.0, 0, 0], "shape": shape}
    callable_shape = ms.make_scene(robot={"source": "ur5"}, force=[force])
    assert why_not_native(callable_shape, RK4) == "force 'f' has a Python callable shape"
    run = lambda: ms.simulate(callable_shape, callable_shape.q0, callable_shape.v0, duration=0.05, dt=1e-3,  # noqa: E731
                              progress=False)  # fmt: skip
    traj = on_kernel(True, run, monkeypatch)
    assert traj.metadata["kernel"] != "native"
    assert traj.metadata["why_not_native"] == "force 'f' has a Python callable shape"
    assert "not an explicit method" in why_not_native(ms.load_scene("spring_chain"), INTEGRATORS["implicit_midpoint"])
    assert "constraints" in why_not_native(ms.load_scene("ur5_pinned_tool"), RK4)
    assert "mimic" in why_not_native(ms.load_scene("panda_mimic"), RK4)
    assert native_core._scene_reason(ms.load_scene("panda_payload")) is None


def test_a_native_controller_output_that_is_not_finite_fails_as_on_python(monkeypatch):
    robot = ms.load_robot("ur5")
    q0, v0 = robot.default_pose(), np.zeros(robot.nv)
    v0[2] = 1e300  # kd · v overflows: the output is not a torque

    def run():
        with pytest.raises(ms.ControllerOutputError) as caught:
            ms.simulate(robot, q0, v0, duration=0.01, dt=1e-3, controller=PD(robot, q0, kp=1.0, kd=1e10),
                        progress=False)  # fmt: skip
        return caught.value

    a, b = both(run, monkeypatch)
    assert str(a) == str(b) == "controller output at t = 0 s: tau must be finite, got non-finite entries at indices [2]"
    assert a.status == b.status == "failed"
    for name in ("t", "q", "v", "kinetic_energy", "potential_energy", "energy_error"):  # v² overflows: T is NaN
        np.testing.assert_array_equal(getattr(a.trajectory, name), getattr(b.trajectory, name), err_msg=name)
    assert a.trajectory.stats == {**b.trajectory.stats, "wall_time": a.trajectory.stats["wall_time"]}
