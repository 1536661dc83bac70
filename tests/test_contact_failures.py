"""A library's exception inside a contact step is data (issue 26 class 1): the row it happened in ends with status
"failed" and the library's message, its samples kept and `out` written, the other rows go on, in every entry point
(simulate, Stepper, rollout, BatchStepper, the gym vector env) and on both kernels.

On the Python kernel the exception comes from Pinocchio's Cholesky (wrapped to raise, for one row's state, the
error Pinocchio's ADMM used to raise: "L should be > m"); on the native kernel, from coal and Boost reading a mesh
hull's archive that was damaged on its way (the hulls are read when a pair first needs coal with one, inside the
step)."""

from __future__ import annotations


import numpy as np
import pinocchio as pin
import pytest
from conftest import needs_native

import multibody_sim as ms
from multibody_sim.kernels import native as native_kernel
from multibody_sim.scenes import make_scene

MESSAGE = "L should be > m"


def boxes() -> ms.Scene:
    return make_scene(ground={"friction": 0.8}, object=[{"name": "box", "shape": "box", "size": [0.2, 0.2, 0.1],
                      "mass": 1.0, "position": [0.0, 0.0, 0.05], "velocity": [1.0, 0.0, 0.0, 0.0, 0.0, 0.0]}])  # fmt: skip


@pytest.fixture
def python_library_error(monkeypatch):
    """The Python kernel, with Pinocchio's Cholesky raising for a box past x = 0.05 m (that row's state only)."""
    monkeypatch.setenv("MULTIBODY_SIM_NATIVE", "0")
    decompose = pin.cholesky.decompose

    def failing(model, data):
        if data.oMi[1].translation[0] > 0.05:
            raise ValueError(MESSAGE)
        return decompose(model, data)

    monkeypatch.setattr(pin.cholesky, "decompose", failing)


def test_simulate_ends_failed_with_the_library_message_keeps_its_samples_and_writes_out(python_library_error, tmp_path):
    scene = boxes()
    out = tmp_path / "run.npz"
    with pytest.raises(ms.SimulationError) as info:
        ms.simulate(scene, scene.q0, scene.v0, duration=0.3, dt=1e-3, integrator="timestepping", progress=False,
                    out=str(out))  # fmt: skip
    error = info.value
    assert error.status == "failed"
    assert f"ValueError raised in the contact step: {MESSAGE}" in str(error)
    traj = error.trajectory
    assert traj.metadata["kernel"].startswith("python") and len(traj) > 10 and traj.q[-1, 0] <= 0.05 + 1e-3
    assert ms.Trajectory.load(out).status == "failed" and len(ms.Trajectory.load(out)) == len(traj)


def test_rollout_and_batches_fail_that_row_alone(python_library_error):
    """The slow rows never pass x = 0.05 m: they complete; the fast one fails alone, in rollout, BatchStepper and the
    gym vector env (infos["failure"], infos["message"])."""
    scene = boxes()
    Q0, V0 = np.tile(scene.q0, (3, 1)), np.tile(scene.v0, (3, 1))
    V0[:, 0] = [0.05, 1.0, 0.02]
    batch = ms.rollout(scene, Q0, V0, duration=0.3, dt=1e-3, integrator="timestepping", progress=False)
    assert list(batch.status) == ["completed", "failed", "completed"]
    stepper = ms.BatchStepper(scene, Q0, V0, dt=1e-3, integrator="timestepping")
    failures = {}
    for _ in range(200):
        failures.update(stepper.step(np.zeros((3, scene.nv))).failures)
    assert list(failures) == [1] and failures[1][0] == "failed" and MESSAGE in failures[1][1]
    pytest.importorskip("gymnasium")
    from multibody_sim.gym import MultibodyVectorEnv

    env = MultibodyVectorEnv(scene, 3, reward=lambda q, v, tau: 0.0, dt=1e-3, method="timestepping",
                             initial_q=scene.q0, initial_v=V0[1], reset_noise_q=0.0, reset_noise_v=0.0)  # fmt: skip
    env.reset(seed=0)
    seen = []
    for _ in range(100):
        _, _, terminated, _, infos = env.step(np.zeros((3, scene.nv)))
        if "failure" in infos:
            seen += [(i, infos["failure"][i], infos["message"][i]) for i in np.flatnonzero(infos["_failure"])]
    assert seen and all(status == "failed" and MESSAGE in message for _, status, message in seen)


def test_the_single_gym_env_ends_the_episode_with_the_failure(python_library_error):
    pytest.importorskip("gymnasium")
    from multibody_sim.gym import MultibodyEnv

    scene = boxes()
    env = MultibodyEnv(scene, reward=lambda q, v, tau: 1.0, dt=1e-3, method="timestepping", failure_reward=-5.0,
                       reset_noise_q=0.0, reset_noise_v=0.0)  # fmt: skip
    env.reset(seed=0)
    for _ in range(200):
        _, reward, terminated, _, info = env.step(np.zeros(scene.nv))
        if terminated:
            break
    assert terminated and reward == -5.0
    assert info["failure"] == "failed" and f"ValueError raised in the contact step: {MESSAGE}" in info["message"]


def test_stepper_raises_failed_and_stays_where_it_was(python_library_error):
    scene = boxes()
    stepper = ms.Stepper(scene, dt=1e-3, integrator="timestepping", q0=scene.q0, v0=scene.v0)
    with pytest.raises(ms.SimulationError) as info:
        for _ in range(200):
            stepper.step(np.zeros(scene.nv))
    assert info.value.status == "failed" and MESSAGE in str(info.value)
    assert stepper.q[0] <= 0.05 + 1e-3  # the state before the failed step


# ---- the native kernel ----------------------------------------------------------------------------------------------


def box_on_solo12() -> ms.Scene:
    """solo12 on its URDF meshes, a box resting on its base (a hull against a box: coal's pair) and its base hull
    against the ground."""
    box = {"name": "box", "shape": "box", "size": [0.1, 0.1, 0.05], "mass": 0.2, "position": [0.0, 0.0, 0.5]}
    return make_scene(robot={"source": "solo12"}, ground={"friction": 0.8}, object=[box],
                      contact={"pairs": [["ground", "base_link"], ["box", "base_link"]]})  # fmt: skip


def base_top(scene: ms.Scene, q: np.ndarray) -> float:
    """The height of the base hull's highest vertex at q [m]."""
    model, data = scene.model, scene.model.createData()
    pin.forwardKinematics(model, data, q)
    (k,) = [k for k, g in enumerate(scene.contact.geometries) if g.body == "base_link" and g.kind == "mesh"]
    geometry, vertices = scene.contact.geometries[k], scene.contact.shapes[k].vertices
    placement = data.oMi[geometry.joint] * geometry.placement
    return float((vertices @ placement.rotation.T + placement.translation)[:, 2].max())


@pytest.fixture
def damaged_archive(monkeypatch):
    """The native kernel, with each mesh hull's archive cut short on its way to the engine."""
    monkeypatch.setenv("MULTIBODY_SIM_NATIVE", "1")
    contact_data = native_kernel.contact_data

    def damaged(scene, method):
        data = contact_data(scene, method)
        for shape in data["shapes"]:
            if shape["kind"] == "mesh":
                shape["archive"] = shape["archive"][:40].copy()
        return data

    monkeypatch.setattr(native_kernel, "contact_data", damaged)


@needs_native
def test_a_library_exception_in_the_native_step_fails_that_row_alone(damaged_archive, tmp_path):
    """Row 0's box rests on the base (its pair needs coal and the damaged hull): it fails with Boost's message; row
    1's box is 0.7 m above it (its pair's bounding spheres apart: the hulls are never read) and completes. The same in
    simulate() (out written), Stepper and BatchStepper."""
    scene = box_on_solo12()
    q_on = scene.q0.copy()
    q_on[scene.nq - 7 + 2] = base_top(scene, scene.q0) + 0.025 + 0.002  # the box's bottom 2 mm above the base hull
    q_far = scene.q0.copy()
    q_far[scene.nq - 7 + 2] = 1.0
    Q0 = np.array([q_on, q_far])
    V0 = np.zeros((2, scene.nv))
    batch = ms.rollout(scene, Q0, V0, duration=0.05, dt=1e-3, integrator="timestepping", progress=False)
    assert batch.metadata["kernel"] == "native"
    assert list(batch.status) == ["failed", "completed"]
    out = tmp_path / "run.npz"
    with pytest.raises(ms.SimulationError) as info:
        ms.simulate(scene, q_on, V0[0], duration=0.05, dt=1e-3, integrator="timestepping", progress=False,
                    out=str(out))  # fmt: skip
    error = info.value
    assert error.status == "failed" and "RuntimeError raised in the contact step" in str(error)
    assert error.trajectory.metadata["kernel"] == "native" and len(error.trajectory) >= 1
    assert ms.Trajectory.load(out).status == "failed"
    stepper = ms.Stepper(scene, dt=1e-3, integrator="timestepping", q0=q_on, v0=V0[0])
    with pytest.raises(ms.SimulationError) as info:
        stepper.step(np.zeros(scene.nv))
    assert info.value.status == "failed"
    batch_stepper = ms.BatchStepper(scene, Q0, V0, dt=1e-3, integrator="timestepping")
    failures = batch_stepper.step(np.zeros((2, scene.nv))).failures
    assert list(failures) == [0] and failures[0][0] == "failed"


@needs_native
def test_the_gym_envs_carry_a_native_library_exception_as_the_rows_failure(damaged_archive):
    """The single env ends its episode with info["failure"] and info["message"]; the vector env fails row 0 alone."""
    pytest.importorskip("gymnasium")
    from multibody_sim.gym import MultibodyEnv, MultibodyVectorEnv

    scene = box_on_solo12()
    q_on = scene.q0.copy()
    q_on[scene.nq - 7 + 2] = base_top(scene, scene.q0) + 0.025 + 0.002
    q_far = scene.q0.copy()
    q_far[scene.nq - 7 + 2] = 1.0
    env = MultibodyEnv(scene, reward=lambda q, v, tau: 1.0, dt=1e-3, method="timestepping", initial_q=q_on,
                       reset_noise_q=0.0, reset_noise_v=0.0)  # fmt: skip
    env.reset(seed=0)
    _, reward, terminated, _, info = env.step(np.zeros(scene.nv))
    assert terminated and reward == 0.0 and info["failure"] == "failed"
    assert "RuntimeError raised in the contact step" in info["message"]
    vector = MultibodyVectorEnv(scene, 2, reward=lambda q, v, tau: 1.0, dt=1e-3, method="timestepping",
                                reset_noise_q=0.0, reset_noise_v=0.0)  # fmt: skip
    vector.reset(seed=0, options={"q": np.array([q_on, q_far]), "v": np.zeros((2, scene.nv))})
    _, rewards, terminated, _, infos = vector.step(np.zeros((2, scene.nv)))
    assert list(terminated) == [True, False] and list(rewards) == [0.0, 1.0]
    assert list(infos["_failure"]) == [True, False] and infos["failure"][0] == "failed"
    assert "RuntimeError raised in the contact step" in infos["message"][0]
