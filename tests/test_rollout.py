"""Batched rollouts against looped simulate(): the same samples, statuses and messages; progress bars (the Ray
backend: tests/test_determinism.py)."""

from __future__ import annotations

import importlib
import re
from typing import Any

import numpy as np
import pinocchio as pin
import pytest
from conftest import ctrl_c_at, joint, link, urdf

import multibody_sim as ms
from multibody_sim.integrators.explicit_rk import ExplicitRungeKutta
from multibody_sim.integrators.tableau import ButcherTableau

rollout_module = importlib.import_module("multibody_sim.rollout")  # the module (the package exports the function)

FIXED_STEP_EXPLICIT = sorted(name for name, m in ms.INTEGRATORS.items() if not m.adaptive and not m.implicit)
ARRAYS = (
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
)
COUNTS = ("steps", "rejected_steps", "evaluations", "controller_calls", "saturated_controls", "saturated_dofs")


def looped(system: ms.Robot, Q0: np.ndarray, V0: np.ndarray, controllers: list[Any] | None = None, **kw: Any):
    """(trajectory, message) per element from simulate(), the early stops' partial trajectories included."""
    out = []
    for b in range(len(Q0)):
        controller = controllers[b] if controllers is not None else None
        try:
            out.append((ms.simulate(system, Q0[b], V0[b], controller=controller, **kw), ""))
        except ms.SimulationError as exc:
            out.append((exc.trajectory, str(exc)))
    return out


def assert_same(batch: ms.BatchTrajectory, reference: list[tuple[ms.Trajectory, str]]) -> None:
    """Every element bit for bit as simulate() returned it: arrays, ledger, status, message, counts, limits."""
    assert len(batch) == len(reference)
    for b, (traj, message) in enumerate(reference):
        element = batch.element(b)
        assert element.status == traj.status, b
        assert batch.messages[b] == message, b
        assert batch.n_samples[b] == len(traj)
        for name in ARRAYS:
            np.testing.assert_array_equal(getattr(element, name), getattr(traj, name), err_msg=f"{name}[{b}]")
        assert element.ledger.keys() == traj.ledger.keys()
        for name, entry in traj.ledger.items():
            np.testing.assert_array_equal(element.ledger[name].energy, entry.energy, err_msg=f"ledger {name}[{b}]")
        for name in COUNTS:
            assert element.stats[name] == traj.stats[name], (name, b)
        assert element.limit_violations == traj.limit_violations, b
    # The padding: every array finite, each element's rows past its samples repeat its last one.
    for name in ARRAYS:
        assert np.all(np.isfinite(getattr(batch, name))), name
    for b in np.flatnonzero((batch.n_samples < batch.t.shape[1]) & (batch.n_samples > 0)):
        n = batch.n_samples[b]
        assert np.all(batch.q[b, n:] == batch.q[b, n - 1]) and np.all(batch.t[b, n:] == batch.t[b, n - 1])
    assert np.array_equal(batch.mask.sum(axis=1), batch.n_samples)


@pytest.fixture(params=["default", "row"])
def kernel(request: pytest.FixtureRequest, monkeypatch: pytest.MonkeyPatch) -> str:
    """The kernel runs take: "default" (the native one where it runs, as driver.choose_kernel picks) or "row" (the
    row kernel forced with MULTIBODY_SIM_NATIVE=0, as every run without the compiled extension)."""
    if request.param == "row":
        monkeypatch.setenv("MULTIBODY_SIM_NATIVE", "0")
    return str(request.param)


def assert_kernel(batch: ms.BatchTrajectory, kernel: str) -> None:
    """With the row kernel forced, the batch says it ran on it."""
    if kernel == "row":
        assert batch.metadata["kernel"] == "python (row)"
        assert batch.metadata["why_not_native"] == "MULTIBODY_SIM_NATIVE=0"


def random_states(system: ms.Robot, B: int, seed: int, v_scale: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    Q0 = np.array([system.random_configuration(rng) for _ in range(B)])
    return Q0, rng.normal(scale=v_scale, size=(B, system.nv))


@pytest.fixture
def wheel_arm(write_urdf) -> ms.Robot:
    """A continuous joint (q = (cos, sin): integrate is a rotation, not q + dv) on a damped revolute one."""
    wheel = joint("j_wheel", "base", "wheel", kind="continuous", damping=0.1)
    wheel = wheel.replace("<dynamics", '<limit effort="5" velocity="10"/><dynamics')
    text = urdf(
        link("base"),
        link("wheel", mass=1.0, com="0 0 -0.3"),
        link("arm", mass=0.5, com="0 0 -0.4"),
        wheel,
        joint("j_arm", "wheel", "arm", xyz="0 0 -0.6", damping=0.05),
    )
    return ms.load_robot(write_urdf(text))


# ---- the batched path reproduces simulate() ------------------------------------------------------------------------
@pytest.mark.parametrize("integrator", FIXED_STEP_EXPLICIT)
@pytest.mark.parametrize("case", ["double_pendulum", "ur5_pd", "solo12", "wheel_arm"])
def test_batch_equals_looped_simulate(robot, request, kernel: str, integrator: str, case: str) -> None:
    # Every configuration update a step takes: q + dv (double pendulum, ur5), Pinocchio's integrate on the
    # free-flyer (solo12) or the continuous joint, with the chart map (solo12, methods with more than one stage)
    # and without it; the damping ledger (double pendulum, wheel arm); saturation at effort limits (ur5's PD asks
    # for too much); a control period and an output period that differ, and a last step shortened to land on the
    # duration. On either kernel, a batch's rows are simulate()'s runs, bit for bit.
    controllers = None
    if case == "double_pendulum":
        system = robot("double_pendulum")  # damped (URDF 0.05), no limits
    elif case == "ur5_pd":
        system = robot("ur5")
        gains = [3000.0, 200.0, 1.0, 3000.0]  # the stiffest saturate at first; a parameter sweep per element
        controllers = [lambda t, q, v, k=k: k * (0.4 - q) - 0.05 * k * v for k in gains]
    elif case == "solo12":
        system = robot("solo12")
    else:
        system = request.getfixturevalue("wheel_arm")
    Q0, V0 = random_states(system, 4, seed=1, v_scale=0.1 if system.floating_base else 0.5)
    options = dict(duration=0.0305, dt=1e-3, integrator=integrator, output_dt=3e-3, control_dt=2e-3)
    batch = ms.rollout(system, Q0, V0, controller=controllers, **options)
    assert_same(batch, looped(system, Q0, V0, controllers, **options))
    assert_kernel(batch, kernel)
    assert np.all(batch.status == "completed")
    assert batch.t.shape == (4, 12) and batch.t[0, -1] == 0.0305  # 0, 3, ..., 30 ms and the end
    if case == "ur5_pd":
        assert batch.stats["saturated_controls"][0] > 0 and batch.stats["saturated_controls"][2] == 0


def test_tableaus_with_many_terms_or_inexact_products_are_bit_for_bit_too(robot, kernel: str) -> None:
    # Kutta's 3/8 rule (several terms per stage sum) and Ralston's method (one term, 2/3, whose product is not
    # exact): a tableau built here, not in the registry, runs on the row kernel; rollout and simulate agree on it.
    three_eighths = ButcherTableau(
        a=((0, 0, 0, 0), (1 / 3, 0, 0, 0), (-1 / 3, 1, 0, 0), (1, -1, 1, 0)),
        b=(1 / 8, 3 / 8, 3 / 8, 1 / 8),
        c=(0, 1 / 3, 2 / 3, 1),
        order=4,
    )
    ralston = ButcherTableau(a=((0, 0), (2 / 3, 0)), b=(1 / 4, 3 / 4), c=(0, 2 / 3), order=2)
    dp = robot("double_pendulum")
    Q0, V0 = random_states(dp, 3, seed=12)
    spring = lambda t, q, v: -q  # noqa: E731  (torques, so that the torque ledger goes through the stage sums)
    for tableau in (three_eighths, ralston):
        method = ExplicitRungeKutta("custom", tableau, "a tableau built in the test")
        options = dict(duration=0.02, dt=1e-3, integrator=method, output_dt=4e-3)
        assert_same(ms.rollout(dp, Q0, V0, controller=spring, **options), looped(dp, Q0, V0, [spring] * 3, **options))


def test_batched_controller_equals_per_state_controller_and_taus_equal_an_indexing_controller(robot) -> None:
    ur5 = robot("ur5")
    Q0, V0 = random_states(ur5, 3, seed=2)
    options = dict(duration=0.02, dt=1e-3, control_dt=2e-3)

    def pd(t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        return 300.0 * (0.2 - q) - 10.0 * v - t

    class BatchedPD:
        batched = True

        def __call__(self, t: float, Q: np.ndarray, V: np.ndarray) -> np.ndarray:
            assert not Q.flags.writeable and Q.shape == (3, ur5.nq)  # sees the state, cannot edit it
            return 300.0 * (0.2 - Q) - 10.0 * V - t

    reference = looped(ur5, Q0, V0, [pd] * 3, **options)
    assert_same(ms.rollout(ur5, Q0, V0, controller=pd, **options), reference)
    assert_same(ms.rollout(ur5, Q0, V0, controller=BatchedPD(), **options), reference)

    taus = np.random.default_rng(3).normal(scale=200.0, size=(3, 10, ur5.nv))  # 10 control instants in 20 ms
    indexing = [lambda t, q, v, b=b: taus[b, round(t / 2e-3)] for b in range(3)]
    batch = ms.rollout(ur5, Q0, V0, taus=taus, **options)
    assert_same(batch, looped(ur5, Q0, V0, indexing, **options))
    assert np.all(batch.stats["controller_calls"] == 10)
    # Open-loop torques saturate like controller outputs: some of these exceed ur5's limits.
    assert np.all(np.abs(batch.tau) <= ur5.effort_limit) and batch.stats["saturated_controls"].sum() > 0


def test_stateful_controller_gets_a_fresh_copy_per_element(robot) -> None:
    dp = robot("double_pendulum")

    class PI:
        """A PI controller: its integral is state that must not leak from one element into another."""

        def __init__(self) -> None:
            self.integral = np.zeros(2)

        def reset(self) -> None:
            self.integral = np.zeros(2)

        def __call__(self, t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
            error = np.array([np.pi, 0.0]) - q
            self.integral = self.integral + 1e-3 * error
            return 5.0 * error + 20.0 * self.integral - 0.5 * v

    Q0, V0 = random_states(dp, 3, seed=4)
    options = dict(duration=0.02, dt=1e-3)
    shared = PI()
    batch = ms.rollout(dp, Q0, V0, controller=shared, **options)
    assert_same(batch, looped(dp, Q0, V0, [PI() for _ in range(3)], **options))  # a new controller each
    assert np.all(shared.integral == 0.0)  # the caller's object was copied, not used


@pytest.mark.parametrize("name", ["panda", "solo12"])
def test_permutation_threads_and_batch_size_do_not_change_an_element(robot, name: str) -> None:
    # Elements are independent: the same arithmetic whatever their neighbours, order or thread count (on a
    # floating base too, where each row's chart map picks its own series or closed form by its own angle).
    system = robot(name)
    Q0, V0 = random_states(system, 5, seed=5)
    if system.floating_base:  # a base spinning ~1 rad per step: the closed forms, next to rows using the series
        V0[1, 3:6] = [900.0, 0.0, 900.0]
    options = dict(duration=0.01, dt=1e-3)
    whole = ms.rollout(system, Q0, V0, **options)
    order = np.array([3, 0, 4, 1, 2])
    permuted = ms.rollout(system, Q0[order], V0[order], num_threads=2, **options)
    alone = ms.rollout(system, Q0[2:3], V0[2:3], **options)
    for field in ARRAYS:
        np.testing.assert_array_equal(getattr(permuted, field), getattr(whole, field)[order])
        np.testing.assert_array_equal(getattr(alone, field)[0], getattr(whole, field)[2])


# ---- every joint kind over a batch ---------------------------------------------------------------------------------
JOINT_MODELS = {
    "free_flyer": pin.JointModelFreeFlyer,
    "spherical": pin.JointModelSpherical,
    "planar": pin.JointModelPlanar,
    "continuous": pin.JointModelRUBY,
    "prismatic": pin.JointModelPZ,
    "revolute": pin.JointModelRX,
}


def chain(*kinds: str) -> ms.Robot:
    """A chain of the given joint kinds built in code (URDF has no spherical joint), one 1 kg body on each."""
    model = pin.Model()
    parent = 0
    for i, kind in enumerate(kinds):
        placement = pin.SE3(np.eye(3), np.array([0.0, 0.1, -0.3 if i else 0.0]))
        parent = model.addJoint(parent, JOINT_MODELS[kind](), placement, f"{kind}_{i}")
        inertia = pin.Inertia(1.0, np.array([0.05, 0.02, -0.2]), np.diag([0.02, 0.03, 0.01]))
        model.appendBodyToJoint(parent, inertia, pin.SE3.Identity())
    return ms.Robot(model, name="chain", floating_base=False)


def test_every_joint_kind_in_a_batch_follows_simulate(kernel: str) -> None:
    # Free-flyer, spherical, planar (the chart map), continuous, prismatic and revolute joints, with the curved
    # joints first and interleaved with the others: on either kernel each row of a batch is simulate()'s run.
    options = dict(duration=0.02, dt=1e-3, output_dt=5e-3)
    mixed = chain("free_flyer", "spherical", "planar", "continuous", "prismatic", "revolute")
    interleaved = chain("revolute", "spherical", "prismatic", "free_flyer", "continuous")
    for system, seed in ((mixed, 15), (interleaved, 17)):
        Q0, V0 = random_states(system, 3, seed=seed, v_scale=0.1)
        for integrator in ("rk4", "midpoint", "euler"):
            batch = ms.rollout(system, Q0, V0, integrator=integrator, **options)
            assert_same(batch, looped(system, Q0, V0, integrator=integrator, **options))
            assert_kernel(batch, kernel)


# ---- early stops: one element's fate does not spoil the others ----------------------------------------------------
def test_diverging_elements_stop_with_simulates_status_and_message_and_the_rest_complete(robot, kernel: str) -> None:
    dp = robot("double_pendulum")
    Q0 = np.array([[3.0, 0.0], [0.1, 0.2], [3.0, 0.1], [1.0, 1.0], [1.0, 1.0]])
    # Element 1 spins so fast that explicit Euler's energy error explodes; element 3's kinetic energy
    # overflows at t = 0 already (no sample at all), as simulate() reports it; element 4's energy is finite,
    # but its accelerations (~ v²) overflow within a step: the state itself becomes non-finite.
    V0 = np.array([[0.0, 0.0], [1e3, -1e3], [0.0, 0.0], [1e200, 0.0], [0.0, 1e100]])
    for integrator, output_dt in [("euler", 0.1), ("rk4", 0.1), ("rk4", 0.02)]:
        options = dict(duration=1.0, dt=0.02, integrator=integrator, output_dt=output_dt)
        batch = ms.rollout(dp, Q0, V0, **options)
        assert_same(batch, looped(dp, Q0, V0, **options))
        assert batch.status.tolist() == ["completed", "diverged", "completed", "diverged", "diverged"]
        assert batch.n_samples[3] == 0 and np.all(batch.q[3] == Q0[3]) and np.all(batch.kinetic_energy[3] == 0)
        assert "the energy became non-finite" in batch.messages[3]
        assert "the state became non-finite" in batch.messages[4]
        assert batch.completed.tolist() == [True, False, True, False, False]


def test_adaptive_and_implicit_methods_run_element_by_element_through_simulate(robot) -> None:
    dp = robot("double_pendulum")
    Q0, V0 = random_states(dp, 3, seed=6)
    taus = np.random.default_rng(7).normal(size=(3, 5, 2))
    for options in (
        dict(integrator="dp54", rtol=1e-6, atol=1e-8, control_dt=0.01, output_dt=0.01),
        dict(integrator="implicit_euler", control_dt=0.01),
    ):
        batch = ms.rollout(dp, Q0, V0, duration=0.05, dt=5e-3, taus=taus, **options)
        period = options["control_dt"]
        indexing = [lambda t, q, v, b=b, period=period: taus[b, round(t / period)] for b in range(3)]
        assert_same(batch, looped(dp, Q0, V0, indexing, duration=0.05, dt=5e-3, **options))


def test_ctrl_c_keeps_every_element_so_far(robot) -> None:
    ur5 = robot("ur5")
    Q0, V0 = random_states(ur5, 3, seed=8)
    interrupting = ctrl_c_at(0.0095, 6)
    with pytest.raises(ms.SimulationInterrupted) as caught:
        ms.rollout(ur5, Q0, V0, duration=0.05, dt=1e-3, output_dt=4e-3, controller=interrupting)
    batch = caught.value.trajectory
    assert isinstance(batch, ms.BatchTrajectory) and np.all(batch.status == "interrupted")
    for b in range(3):
        with pytest.raises(ms.SimulationInterrupted) as single:
            ms.simulate(ur5, Q0[b], V0[b], duration=0.05, dt=1e-3, output_dt=4e-3, controller=interrupting)
        traj = single.value.trajectory
        for name in ARRAYS:  # samples at 0, 4, 8 ms and the state at 10 ms when Ctrl-C came
            np.testing.assert_array_equal(getattr(batch.element(b), name), getattr(traj, name))


def test_scene_records_are_kept_per_element_also_on_ctrl_c() -> None:
    # Each element keeps what simulate() records besides the state, its springs' potentials (ledger) and its
    # constraints' forces and drift, and so does a batch that a Ctrl-C cut short. Scenes step all their elements
    # together (the spring chain in the native kernel where it runs, the four-bar's constraint in the row kernel),
    # so a Ctrl-C interrupts every element at the same instant, each with simulate()'s samples up to it.
    four_bar, springs = ms.load_scene("four_bar"), ms.load_scene("spring_chain")
    for scene in (four_bar, springs):
        Q0 = np.array([scene.q0] * 3)
        V0 = np.array([scene.v0 + 0.1 * k for k in range(3)])
        batch = ms.rollout(scene, Q0, V0, duration=0.02, dt=1e-3, output_dt=5e-3)
        for b in range(3):
            alone = ms.simulate(scene, Q0[b], V0[b], duration=0.02, dt=1e-3, output_dt=5e-3)
            element = batch.element(b)
            assert set(element.ledger) == set(alone.ledger) and set(element.constraints) == set(alone.constraints)
            for name, entry in alone.ledger.items():
                np.testing.assert_array_equal(element.ledger[name].energy, entry.energy)
            for name, record in alone.constraints.items():
                for part in ("force", "drift", "velocity_drift"):
                    np.testing.assert_array_equal(getattr(element.constraints[name], part), getattr(record, part))
        if scene is four_bar:  # one loop-closure constraint of 3 rows: force (B, N, 3), drift (B, N)
            assert batch.constraints["loop"].force.shape == (*batch.t.shape, 3)
            assert batch.constraints["loop"].drift.shape == batch.t.shape
        else:  # springs only: their potentials in the ledger, no constraint
            assert not batch.constraints and any(entry.kind == "potential" for entry in batch.ledger.values())

    for scene in (four_bar, springs):
        interrupting = ctrl_c_at(0.0095, scene.nv)
        Q0, V0 = np.array([scene.q0] * 3), np.array([scene.v0] * 3)
        with pytest.raises(ms.SimulationInterrupted) as caught:
            ms.rollout(scene, Q0, V0, duration=0.05, dt=1e-3, controller=interrupting)
        batch = caught.value.trajectory
        # samples at 0, 1, ..., 9 ms, and the state at 10 ms, where the controller was interrupted
        assert batch.status.tolist() == ["interrupted"] * 3 and batch.n_samples.tolist() == [11, 11, 11]
        before = ms.simulate(scene, Q0[1], V0[1], duration=0.01, dt=1e-3)  # the same steps, the same records
        cut = batch.element(1)
        for name, entry in before.ledger.items():
            np.testing.assert_array_equal(cut.ledger[name].energy, entry.energy)
        for name, record in before.constraints.items():
            np.testing.assert_array_equal(cut.constraints[name].drift, record.drift)


def test_batches_joined_along_the_batch_axis_keep_constraint_records() -> None:
    # Ray's chunks are joined by rollout._concatenate: constraint records included, padded like the samples.
    scene = ms.load_scene("four_bar")
    Q0, V0 = np.array([scene.q0] * 3), np.array([scene.v0 + 0.1 * k for k in range(3)])
    whole = ms.rollout(scene, Q0, V0, duration=0.02, dt=1e-3, output_dt=5e-3)
    parts = [ms.rollout(scene, Q0[rows], V0[rows], duration=0.02, dt=1e-3, output_dt=5e-3) for rows in ([0], [1, 2])]
    joined = rollout_module._concatenate(parts)
    for part in ("force", "drift", "velocity_drift"):
        np.testing.assert_array_equal(
            getattr(joined.constraints["loop"], part), getattr(whole.constraints["loop"], part)
        )


# ---- physics, independently of simulate() --------------------------------------------------------------------------
def test_limit_reports_of_a_batch_follow_the_definition_sample_by_sample(robot) -> None:
    """Each element's position-limit report against the definition applied to its samples one by one: excess =
    max(lower - q, 0) + max(q - upper, 0), counted beyond 8 machine epsilons times max(|lower|, |upper|, 1)."""
    ur5 = robot("ur5", damping=False)  # one coordinate per joint: coordinate j is joint_names[j]
    Q0, V0 = random_states(ur5, 24, seed=5, v_scale=2.0)
    batch = ms.rollout(ur5, Q0, V0, duration=0.3, dt=1e-3, progress=False)
    lower, upper = ur5.lower_limit, ur5.upper_limit
    tolerance = 8 * np.finfo(float).eps * np.maximum(np.maximum(np.abs(lower), np.abs(upper)), 1.0)
    violating = 0
    for b in range(len(batch)):
        count = samples = 0
        worst = (0.0, None, None)
        for i in range(batch.n_samples[b]):
            inside = True
            for j, q in enumerate(batch.q[b, i]):
                excess = max(lower[j] - q, 0.0) + max(q - upper[j], 0.0)
                if excess > tolerance[j]:
                    count += 1
                    inside = False
                    if excess > worst[0]:
                        worst = (excess, ur5.joint_names[j], batch.t[b, i])
            samples += not inside
        report = batch.limit_violations[b]
        assert (report.count, report.samples) == (count, samples), b
        assert (report.worst_excess, report.worst_joint, report.worst_time) == worst, b
        violating += count > 0
    assert 0 < violating < len(batch)  # both kinds of element


def test_small_swings_of_a_batch_follow_the_linearised_pendulum(robot) -> None:
    # Small swings about the hanging equilibrium obey M x'' + K x = 0 with M from CRBA and K the gravity
    # Jacobian (central differences): the batch must follow the normal modes, up to the nonlinearity, which
    # shrinks with the square of the amplitude. The URDF's centres of mass are slightly off axis, so the
    # equilibrium is found by Newton on g(q) = 0 near [pi, 0] first.
    dp = robot("double_pendulum", damping=False)
    eps = 1e-6

    def stiffness(q: np.ndarray) -> np.ndarray:
        return np.column_stack([(dp.gravity(q + eps * e) - dp.gravity(q - eps * e)) / (2 * eps) for e in np.eye(2)])

    rest = np.array([np.pi, 0.0])
    for _ in range(5):
        rest = rest - np.linalg.solve(stiffness(rest), dp.gravity(rest))
    assert np.max(np.abs(dp.gravity(rest))) < 1e-12
    w2, modes = np.linalg.eig(np.linalg.solve(dp.mass_matrix(rest), stiffness(rest)))
    rng = np.random.default_rng(9)
    directions = rng.normal(size=(4, 2))
    X0 = np.concatenate([1e-3 * directions, 1e-4 * directions])  # the same swings at two amplitudes
    batch = ms.rollout(dp, rest + X0, np.zeros((8, 2)), duration=1.0, dt=1e-3, output_dt=0.01)
    c = np.linalg.solve(modes, X0.T)  # modal amplitudes, (2, B)
    linear = np.einsum("im,mb,tm->bti", modes, c, np.cos(np.outer(batch.t[0], np.sqrt(w2))))
    error = np.abs(batch.q - rest - linear).max(axis=(1, 2))
    big, small = error[:4].max() / 1e-3, error[4:].max() / 1e-4  # relative to the amplitude
    # Relative error ~ amplitude (quadratic terms): 1e-4 of it at 1e-4 leaves a 10x margin; RK4's own error,
    # ~(w dt)^4 w t ~ 1e-6, is below both. Ten times the amplitude, ten times the relative error.
    assert small < 1e-5
    assert 30 < big / small < 300
    assert np.all(np.abs(batch.energy_error) < 1e-12 * np.abs(batch.total_energy).max())


# ---- boundaries ----------------------------------------------------------------------------------------------------
def test_bad_arguments_are_refused_with_messages_that_name_them(robot) -> None:
    dp, solo = robot("double_pendulum"), robot("solo12")
    Q0, V0 = np.zeros((2, 2)), np.zeros((2, 2))
    run = dict(duration=0.01, dt=1e-3)

    def refused(message: str, system: ms.Robot = dp, q: Any = Q0, v: Any = V0, **kw: Any) -> None:
        with pytest.raises(ms.InvalidArgumentError, match=re.escape(message) + "$"):
            ms.rollout(system, q, v, **{**run, **kw})

    refused("q0s must have shape (B, 2), got (2,)", q=np.zeros(2))
    refused("v0s must have shape (B, 2), got (2, 3)", v=np.zeros((2, 3)))
    refused("q0s and v0s must hold as many states, got 2 and 3", v=np.zeros((3, 2)))
    refused("q0s must hold at least one state, got an empty batch", q=np.zeros((0, 2)), v=np.zeros((0, 2)))
    refused("v0s must be finite, got non-finite entries in rows [1]", v=[[0, 0], [0, np.nan]])
    bad_quaternion = np.array([solo.neutral(), solo.neutral()])
    bad_quaternion[1, 3:7] = [1.0, 1.0, 0.0, 0.0]
    refused(
        "q0s[1] is not a valid configuration: its quaternion / (cos, sin) entries must have unit norm",
        system=solo,
        q=bad_quaternion,
        v=np.zeros((2, solo.nv)),
    )
    refused("controller and taus are exclusive: pass one of them", controller=lambda t, q, v: q, taus=np.zeros(1))
    refused("taus must have shape (2, 10, 2) (elements, control instants, nv), got (2, 9, 2)", taus=np.zeros((2, 9, 2)))
    refused(
        "taus must have shape (2, 5, 2) (elements, control instants, nv), got (2, 10, 2)",
        taus=np.zeros((2, 10, 2)),
        control_dt=2e-3,
    )
    refused(
        "taus with the adaptive integrator 'dp54' need control_dt (the period of the torque sequence)",
        taus=np.zeros((2, 10, 2)),
        integrator="dp54",
        rtol=1e-6,
        atol=1e-8,
    )
    taus = np.zeros((2, 10, solo.nv))
    taus[0, 0, 2] = 1.0
    refused(
        "taus[:, :, 0:6] act on the unactuated floating base and must be zero",
        system=solo,
        q=[solo.neutral()] * 2,
        v=np.zeros((2, solo.nv)),
        taus=taus,
    )
    refused("controller as a sequence must hold one controller per element (2), got 1", controller=[lambda t, q, v: q])
    refused("backend must be one of local, ray, got 'dask'", backend="dask")
    refused("num_threads must be a positive whole number, got 0", num_threads=0)
    refused("chunk_size must be a positive whole number of elements, got 2.5", chunk_size=2.5)
    adaptive = ", ".join(sorted(name for name, m in ms.INTEGRATORS.items() if m.adaptive))
    refused(
        f"option 'rtol' does not apply to the fixed-step integrator 'rk4' (it applies to the adaptive integrators: "
        f"{adaptive})",
        rtol=1e-6,
    )

    class Wrong:
        batched = True

        def __call__(self, t: float, Q: np.ndarray, V: np.ndarray) -> np.ndarray:
            return np.zeros(2)

    # A controller output that is not a torque stops its element (status "failed", the message that used to stop
    # the whole rollout) and spares the others.
    def failed(messages: list[str], controller: Any) -> None:
        batch = ms.rollout(dp, Q0, V0, duration=0.01, dt=1e-3, controller=controller)
        assert batch.messages == messages
        assert batch.status.tolist() == ["failed" if m else "completed" for m in messages]
        assert batch.n_samples.tolist() == [1 if m else 11 for m in messages]  # the state at t = 0 is kept

    failed(["batched controller output at t = 0 s must have shape (2, 2), got (2,)"] * 2, Wrong())

    class Diverging:
        batched = True

        def __call__(self, t: float, Q: np.ndarray, V: np.ndarray) -> np.ndarray:
            return np.array([[0.0, 0.0], [np.nan, 0.0]])[: len(Q)]

    failed(
        [
            "",
            "batched controller output at t = 0 s, element 1: "
            "tau must be finite, got non-finite entries at indices [0]",
        ],
        Diverging(),
    )
    failed(["controller output at t = 0 s: tau must have shape (2,), got (3,)"] * 2, lambda t, q, v: np.zeros(3))


# ---- progress bars -------------------------------------------------------------------------------------------------
def test_progress_bar_only_when_asked_or_on_a_terminal(robot, capsys) -> None:
    dp = robot("double_pendulum")
    Q0, V0 = random_states(dp, 2, seed=10)
    ms.rollout(dp, Q0, V0, duration=0.05, dt=1e-3)  # captured output is not a terminal: silent
    assert capsys.readouterr().err == ""
    ms.rollout(dp, Q0, V0, duration=0.05, dt=1e-3, progress=True)
    err = capsys.readouterr().err
    assert "rollout" in err and "100/100" in err  # 2 elements × 50 steps, all done
    ms.rollout(dp, Q0, V0, duration=0.05, dt=1e-3, progress=False)
    assert capsys.readouterr().err == ""


def test_a_batch_that_cannot_fit_in_memory_is_refused_before_it_is_allocated() -> None:
    """B x samples x width checked against usable_memory() (free memory, ulimit -v, the cgroup's limit) up front:
    10^5 elements of 10^5 samples are ~1.3 TB."""
    pendulum = ms.load_robot("pendulum")
    B = 100_000
    with pytest.raises(
        ms.InvalidArgumentError,
        match=r"^this rollout would keep 1e\+05 samples of each of its 100000 elements \([0-9.e+]+ GiB\) in memory, "
        r"more than the [0-9.]+ GiB available \(.+\): sample less often \(output_dt\) or run the batch in smaller "
        r"parts$",
    ):
        ms.rollout(pendulum, np.zeros((B, 1)), np.zeros((B, 1)), duration=100.0, dt=1e-3)


def test_ledger_sums_are_numpys_masked_column_sums_bit_for_bit() -> None:
    """recording.ledger_sums (work and dissipated of the trajectories, without copies of the columns) against NumPy's
    own masked sums, flows[..., mask].sum(-1), bit for bit (a NaN where NumPy's is NaN, whatever its sign and
    payload): every layout the store gives (batch-major rows, one row, sample-major views), one sample, one or no
    column, signed zeros, overflow, infinities and NaNs. With the extension built, contiguous flows of several rows
    and columns go through its one-pass ledger_sums."""
    from multibody_sim import native, recording
    from multibody_sim.recording import ledger_sums

    assert (recording._summer() is not None) == (native.available and hasattr(native.module, "ledger_sums"))

    rng = np.random.default_rng(11)
    for trial in range(400):
        m, B, capacity = int(rng.integers(1, 45)), int(rng.integers(1, 4)), int(rng.integers(1, 600))
        N = int(rng.integers(0, capacity + 1))
        store = rng.standard_normal((B, capacity, m)) * 10.0 ** rng.integers(-3, 300, size=(B, capacity, m))
        if trial % 3 == 0:
            special = rng.random(store.shape) < 0.1
            store[special] = rng.choice([np.inf, -np.inf, np.nan, -0.0, 0.0], size=int(special.sum()))
        is_work = rng.random(m) < rng.random()
        sample_major = np.swapaxes(store, 0, 1)
        for flows in (store[:, :N], store[0, :N], sample_major[:N], sample_major[:N, B - 1], store[:, N - 1 : N]):
            with np.errstate(over="ignore", invalid="ignore"):
                sums = ledger_sums(flows, is_work)
                wanted = flows[..., is_work].sum(-1), flows[..., ~is_work].sum(-1)
            for got, want in zip(sums, wanted, strict=True):
                assert got.shape == want.shape and got.dtype == want.dtype
                nan = np.isnan(want)
                np.testing.assert_array_equal(np.isnan(got), nan)
                np.testing.assert_array_equal(got[~nan].view(np.int64), want[~nan].view(np.int64))


def test_limit_reports_extremes_are_numpys_min_and_max() -> None:
    """recording._extremes (the lowest and highest value of each coordinate over each row's samples, folded into long
    rows first) against Q.min(axis=1) and Q.max(axis=1): any number of samples (none to many, a multiple of the fold
    or not) and coordinates, contiguous or not, zeros of both signs."""
    from multibody_sim.recording import _extremes

    rng = np.random.default_rng(12)
    for _ in range(300):
        B, N, nq = int(rng.integers(1, 4)), int(rng.integers(1, 400)), int(rng.integers(1, 80))
        Q = rng.standard_normal((B, N + 3, nq)) * 10.0 ** rng.integers(-3, 5)
        Q[rng.random(Q.shape) < 0.05] = rng.choice([0.0, -0.0])
        for view in (Q[:, :N], np.ascontiguousarray(Q[:, :N])):
            low, high = _extremes(view)
            np.testing.assert_array_equal(low, view.min(axis=1))
            np.testing.assert_array_equal(high, view.max(axis=1))
