"""The kernels package: every kernel implements every member of its protocol, and without the compiled extension
(MULTIBODY_SIM_NATIVE=0) batches run the row kernel and give simulate()'s and Stepper's results bit for bit: rollout
(tests/test_rollout.py's `kernel` fixture), BatchStepper and the gym vector environment, on a floating base too. A
row's stop carries its step number as data, which BatchStepper recounts from the row's reset."""

from __future__ import annotations

import inspect
from typing import Any

import numpy as np
import pytest

import multibody_sim as ms
from multibody_sim.kernels.base import Kernel, StepKernel
from multibody_sim.kernels.native import NativeKernel
from multibody_sim.kernels.row import RowKernel, RowState


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
