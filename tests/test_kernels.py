"""The kernels package: every kernel implements every member of its protocol, and without the compiled extension
(MULTIBODY_SIM_NATIVE=0) batches run the row kernel and give simulate()'s and Stepper's results bit for bit: rollout
(tests/test_rollout.py's `kernel` fixture), BatchStepper and the gym vector environment, on a floating base too. A
row's stop carries its step number as data, which BatchStepper recounts from the row's reset."""

from __future__ import annotations

import ast
import inspect
import re
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import needs_native

import multibody_sim as ms
from multibody_sim import native
from multibody_sim.controllers import PD, GravityCompensation, PDGravity
from multibody_sim.kernels import native as native_kernel
from multibody_sim.kernels.base import Kernel, StepKernel
from multibody_sim.kernels.native import NativeKernel
from multibody_sim.kernels.row import RowKernel, RowState
from multibody_sim.step_control import ConstantStep, PIController


def members(protocol: type) -> set[str]:
    """The names a protocol declares itself (not those of its bases)."""
    return {name for name in vars(protocol) if not name.startswith("_")}


@pytest.mark.parametrize(
    ("kernel", "protocols"),
    [(RowKernel, (Kernel, StepKernel)), (NativeKernel, (Kernel,))],
)
def test_every_kernel_implements_every_member_of_its_protocols(kernel: type, protocols: tuple[type, ...]) -> None:
    declared = set().union(*(members(p) for p in protocols))
    assert len(members(Kernel)) >= 12 and len(members(StepKernel)) == 6  # the protocols as written
    for name in sorted(declared):
        implementation = inspect.getattr_static(kernel, name, None)
        assert implementation is not None, f"{kernel.__name__} lacks {name}"
        function = implementation.fget if isinstance(implementation, property) else implementation
        source = inspect.getsource(function)
        assert "raise AssertionError" not in source and "NotImplementedError" not in source, (kernel.__name__, name)
    # A member no protocol declares is not part of the interface the core relies on: the kernel's own.
    assert "state_of" not in dir(kernel)


def test_the_row_kernels_loop_state_has_named_fields() -> None:
    dp = ms.load_robot("double_pendulum")
    kernel = RowKernel(dp, ms.INTEGRATORS["rk4"], np.zeros((2, 2)), np.ones((2, 2)))
    assert RowState._fields == ("q", "v", "flows", "solver", "t")
    assert isinstance(kernel.now, RowState) and kernel.now.t == 0.0 and len(kernel.now.q) == 2
    kernel.start_at(0.25)
    kernel.attempt(1e-3)
    kernel.accept(0.251)
    assert kernel.now.t == kernel.t == 0.251
    np.testing.assert_array_equal(kernel.now.v[1], kernel.states()[1][1])


@pytest.fixture(params=["default", "row"])
def kernel(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """The kernel: "default" (the native one where it runs) or "row" (forced, as in a run without the extension)."""
    if request.param == "row":
        monkeypatch.setenv("MULTIBODY_SIM_NATIVE", "0")
    return str(request.param)


@pytest.mark.parametrize("name", ["ur5", "solo12"])
def test_a_batch_stepper_gives_simulates_samples_bit_for_bit(kernel: str, name: str) -> None:
    # Per-row torques held over control intervals of 2 dt: each row's states after every call are the samples of
    # simulate() with a controller returning the same torques at the control instants (solo12: a floating base,
    # whose chart map the retired batch kernel summed in another order).
    robot = ms.load_robot(name)
    rng = np.random.default_rng(4)
    B, intervals, dt = 3, 6, 1e-3
    Q0 = np.array([robot.random_configuration(rng) for _ in range(B)])
    V0 = rng.normal(scale=0.2, size=(B, robot.nv))
    taus = rng.normal(scale=2.0, size=(B, intervals, robot.nv))
    taus[:, :, robot.actuated.stop :] = 0.0
    taus[:, :, : robot.actuated.start] = 0.0
    stepper = ms.BatchStepper(robot, Q0, V0, dt=dt, control_dt=2 * dt, integrator="rk4")
    states = [stepper.step(taus[:, k]) for k in range(intervals)]
    for b in range(B):
        traj = ms.simulate(
            robot, Q0[b], V0[b], duration=intervals * 2 * dt, dt=dt, control_dt=2 * dt, output_dt=2 * dt,
            controller=lambda t, q, v, b=b: taus[b, round(t / (2 * dt))],
        )  # fmt: skip
        np.testing.assert_array_equal(np.array([s.q[b] for s in states]), traj.q[1:])
        np.testing.assert_array_equal(np.array([s.v[b] for s in states]), traj.v[1:])
        np.testing.assert_array_equal(np.array([s.tau[b] for s in states]), traj.tau[:-1])


def test_a_failed_rows_message_counts_steps_and_time_from_its_own_start(kernel: str) -> None:
    # Row 0 is thrown hard: explicit Euler at 50 ms blows up at its 12th step. Row 1 is reset after 5 intervals,
    # which rebuilds the stepping core (its clock restarts there): row 0's stop, counted by that core from 0, is
    # recounted from row 0's own start (RowStop.step, data, not a message parsed back) and reads as its Stepper's.
    pendulum = ms.load_robot("double_pendulum", damping=False)
    q0, v0 = np.array([3.0, 0.0]), np.array([40.0, -40.0])
    options: dict[str, Any] = dict(dt=0.05, integrator="euler", check_energy=False)
    alone = ms.Stepper(pendulum, q0=q0, v0=v0, **options)
    with pytest.raises(ms.SimulationError) as caught:
        for _ in range(40):
            alone.step(np.zeros(2))
    expected = str(caught.value)
    assert expected.startswith("diverged at t = 0.6 s (step 12): the state became non-finite in 'joint1'")
    batch = ms.BatchStepper(pendulum, np.array([q0, [3.0, 0.0]]), np.array([v0, [0.1, 0.0]]), **options)
    for _ in range(5):
        assert not batch.step(np.zeros((2, 2))).failures
    batch.reset(rows=[1])
    failures: dict[int, tuple[str, str]] = {}
    while not failures:
        failures = batch.step(np.zeros((2, 2))).failures
    assert failures == {0: ("diverged", expected)}


def test_the_vector_environment_on_a_floating_base_equals_single_environments(kernel: str) -> None:
    """Row for row and bit for bit, as gymnasium's SyncVectorEnv over MultibodyEnv copies, on solo12 (a floating
    base), through resets."""
    pytest.importorskip("gymnasium")
    from gymnasium.utils.env_checker import data_equivalence
    from gymnasium.vector import SyncVectorEnv

    from multibody_sim.gym import MultibodyEnv, MultibodyVectorEnv

    solo = ms.load_robot("solo12")
    n = 3
    kwargs: dict[str, Any] = dict(
        reward=lambda q, v, tau: -float(v @ v), max_episode_steps=4, control_dt=0.01, dt=0.002, reset_noise_v=0.5
    )
    vector = MultibodyVectorEnv(solo, n, **kwargs)
    reference = SyncVectorEnv([lambda: MultibodyEnv(solo, **kwargs) for _ in range(n)])
    assert data_equivalence(vector.reset(seed=5), reference.reset(seed=5), exact=True)
    vector.action_space.seed(1)
    for _ in range(9):  # two episodes of 4 steps each and a reset
        actions = vector.action_space.sample() * 0.02
        assert data_equivalence(vector.step(actions), reference.step(actions), exact=True)


# ---- the native boundary: named data -------------------------------------------------------------------------------
NATIVE_SOURCES = Path(__file__).resolve().parents[1] / "src" / "native"


@needs_native
def test_a_misnamed_missing_or_mistyped_field_fails_naming_it() -> None:
    module = native.module
    data = ms.INTEGRATORS["rk4"].native_data()
    fields = ", ".join(module.Method.fields)
    misnamed = {("stagse" if k == "stages" else k): v for k, v in data.items()}
    with pytest.raises(TypeError, match=rf"^Method has no field 'stagse' \(its fields: {fields}\)$"):
        module.Method(**misnamed)
    missing = {k: v for k, v in data.items() if k != "chart_terms"}
    with pytest.raises(TypeError, match=r"^Method is missing the field 'chart_terms'$"):
        module.Method(**missing)
    with pytest.raises(TypeError, match=r"^Method.stages: expected int, got str$"):
        module.Method(**{**data, "stages": "four"})
    with pytest.raises(ValueError, match=r"^Method.kind must be one of 'explicit_rk', .*'timestepping', got 'rk4'$"):
        module.Method(**{**data, "kind": "rk4"})
    with pytest.raises(ValueError, match=r"^Method.a must hold stages x stages entries$"):
        module.Method(**{**data, "a": data["a"][:-1]})
    # A nested struct of a kernel's data: a scene's term, and a field a contact model's constants lack.
    with pytest.raises(TypeError, match=r"^SpringTerm has no field 'k' \(its fields: dof, iq, rest, minus_k\)$"):
        module.SpringTerm(dof=0, iq=0, rest=0.0, k=1.0)
    scene = ms.load_scene("sliding_box")
    constants = native_kernel.contact_data(scene, ms.INTEGRATORS["timestepping"])["constants"]
    del constants["touching"]
    constants["solver"] = module.SolverSettings(**constants["solver"])
    with pytest.raises(TypeError, match=r"^ContactConstants is missing the field 'touching'$"):
        module.ContactConstants(**constants)


@needs_native
def test_every_exporter_fills_its_struct_exactly() -> None:
    # Each object the engine renders exports its own native_data(), whose names are the struct's fields: the
    # registry's native methods, both step-size controllers, a floating base's chart map, the built-in controllers,
    # a scene's elements and a contact scene's model.
    module = native.module
    rendered = [m for m in ms.INTEGRATORS.values() if type(m) in native_kernel.NATIVE_METHODS]
    assert {m.name for m in rendered} >= {"euler", "rk4", "dp54", "dop853", "semi_implicit_euler", "timestepping"}
    for method in rendered:
        data = method.native_data()
        assert set(data) <= set(module.Method.fields), method.name
        assert module.Method(**data).kind == data["kind"]
    solo = ms.load_robot("solo12")
    for control in (ConstantStep(1e-3), PIController(4, first_step=1e-3)):
        data = control.native_data()
        struct = module.ConstantStep if isinstance(control, ConstantStep) else module.PIController
        assert set(data) == set(struct.fields)
        struct(**data)
    chart = solo.space.native_data()
    assert [set(block) for block in chart["blocks"]] == [set(module.ChartBlock.fields)]
    assert module.ChartBlock(**chart["blocks"][0]).size == 6
    for controller in (
        PD(solo, solo.neutral(), kp=1.0),
        GravityCompensation(solo),
        PDGravity(solo, solo.neutral(), kp=1.0),
    ):
        data = controller.native_data(solo)
        assert set(data) == set(module.Policy.fields)
        module.Policy(**data)
        assert controller.native_data(ms.load_robot("solo12")) is None  # made for another robot
    scene = ms.load_scene("ur5_ceiling_push")
    elements = scene.elements.native_data(native.load_model)
    assert set(elements) == set(module.SceneForces.fields)
    contact = native_kernel.contact_data(ms.load_scene("sliding_box"), ms.INTEGRATORS["timestepping"])
    assert set(contact) == set(module.ContactScene.fields)
    assert set(contact["constants"]) == set(module.ContactConstants.fields)
    assert set(contact["constants"]["solver"]) == set(module.SolverSettings.fields)
    solver = module.SolverSettings(**contact["constants"]["solver"])
    assert module.ContactConstants(**{**contact["constants"], "solver": solver}).solver.tolerance == solver.tolerance


def test_the_kernel_module_reads_no_private_attribute_of_another_object() -> None:
    # kernels/native.py reads public data only (each object's native_data(), public attributes): every attribute it
    # names with a leading underscore is its own (self._...).
    tree = ast.parse(inspect.getsource(native_kernel))
    foreign = sorted(
        f"line {node.lineno}: .{node.attr}"
        for node in ast.walk(tree)
        if isinstance(node, ast.Attribute)
        and node.attr.startswith("_")
        and not node.attr.startswith("__")
        and not (isinstance(node.value, ast.Name) and node.value.id == "self")
    )
    assert foreign == []


def test_no_private_python_attribute_is_named_in_cpp() -> None:
    # C++ reads and writes Python objects through arguments and named structs only: no name with a leading
    # underscore in a string (an attribute's, "_previous_error"), nor any setattr at all.
    sources = sorted(NATIVE_SOURCES.glob("*.[ch]pp"))
    assert len(sources) >= 8
    for path in sources:
        text = path.read_text()
        assert "setattr" not in text, path.name
        assert re.findall(r'"_[A-Za-z]\w*"', text) == [], path.name


@needs_native
def test_no_binding_takes_more_than_8_arguments() -> None:
    # nanobind's signatures: every parameter, keyword-only ones included (as the house check counts them); `self`,
    # the bare `*` and **kwargs (the structs' field-by-field constructors) excluded.
    module = native.module
    counted = 0
    for name in dir(module):
        owner = getattr(module, name)
        functions = [owner] if callable(owner) and not isinstance(owner, type) else []
        if isinstance(owner, type):
            functions = [getattr(owner, attribute) for attribute in vars(owner) if not attribute.startswith("__")]
            functions.append(owner.__init__)
        for function in functions:
            for signature, *_ in getattr(function, "__nb_signature__", ()):
                params = signature[signature.index("(") + 1 : signature.rindex(")")]
                parts = [p.strip() for p in re.split(r",(?![^\[]*\])", params) if p.strip()]
                named = [p for p in parts if p != "*" and not p.startswith(("**", "self"))]
                counted += 1
                assert len(named) <= 8, (name, signature)
    assert counted > 40
