"""Gymnasium environments (multibody_sim.gym): gymnasium's own checker, seeded reproducibility, action bounds read
from the URDF, and the vector environment against gymnasium's SyncVectorEnv over single environments (its
autoreset semantics are the reference), row for row and bit for bit."""

from __future__ import annotations

import warnings
import xml.etree.ElementTree as ET
from itertools import combinations
from typing import Any

import numpy as np
import pytest

import multibody_sim as ms

gymnasium = pytest.importorskip("gymnasium")
from gymnasium.utils.env_checker import check_env, data_equivalence, data_shares_objects  # noqa: E402
from gymnasium.vector import AutoresetMode, SyncVectorEnv  # noqa: E402

from multibody_sim.gym import MultibodyEnv, MultibodyVectorEnv  # noqa: E402

# What gymnasium's checker says of every environment here, and why that is right: (q, v) is unbounded, torques
# are in N·m (not normalised to [-1, 1]), a floating base's unactuated entries have zero width, and an environment
# made without gymnasium.make has no spec.
EXPECTED_WARNINGS = (
    "minimum value is -infinity",
    "maximum value is infinity",
    "normalized",
    "maximum and minimum values are equal",
    "not having a spec",
)


def reward(q: np.ndarray, v: np.ndarray, tau: np.ndarray) -> float:
    return -float(v @ v) - 1e-4 * float(tau @ tau)


def fell(q: np.ndarray, v: np.ndarray) -> bool:
    return bool(np.abs(v).max() > 2.0)


def settings(**extra: Any) -> dict[str, Any]:
    base = dict(reward=reward, terminated=fell, max_episode_steps=6, control_dt=0.01, dt=0.002, reset_noise_q=0.2)
    return {**base, **extra}


@pytest.fixture(scope="module")
def ur5() -> ms.Robot:
    return ms.load_robot("ur5")


@pytest.fixture(scope="module")
def solo12() -> ms.Robot:
    return ms.load_robot("solo12")


def checked(env: Any) -> list[str]:
    """gymnasium's check_env on env; the warnings it gave that are not EXPECTED_WARNINGS."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        check_env(env)
    return [str(w.message) for w in caught if not any(e in str(w.message) for e in EXPECTED_WARNINGS)]


@pytest.mark.parametrize("system", ["ur5", "solo12", "scene:ur5_ceiling_push", "scene:double_pendulum_spring_friction"])
def test_gymnasium_env_checker_passes(system: str) -> None:
    loaded = ms.load_scene(system[6:]) if system.startswith("scene:") else ms.load_robot(system)
    assert checked(MultibodyEnv(loaded, **settings())) == []


def test_action_space_is_the_urdf_effort_limits(ur5: ms.Robot) -> None:
    efforts = _urdf_efforts(ur5.source["urdf_path"])
    env = MultibodyEnv(ur5, **settings())
    expected = np.array([efforts[name] for name in ur5.joint_names])
    np.testing.assert_array_equal(env.action_space.high, expected)
    np.testing.assert_array_equal(env.action_space.low, -expected)
    assert env.action_space.dtype == np.float64 and env.action_space.shape == (6,)
    assert env.observation_space.dtype == np.float64 and env.observation_space.shape == (12,)


def test_floating_base_entries_have_zero_width(solo12: ms.Robot) -> None:
    efforts = _urdf_efforts(solo12.source["urdf_path"])
    env = MultibodyEnv(solo12, **settings())
    space = env.action_space
    assert space.shape == (18,) and env.observation_space.shape == (19 + 18,)
    np.testing.assert_array_equal(space.low[:6], np.zeros(6))
    np.testing.assert_array_equal(space.high[:6], np.zeros(6))
    np.testing.assert_array_equal(space.high[6:], [efforts[name] for name in solo12.joint_names[1:]])
    space.seed(0)
    assert not space.sample()[:6].any()  # every action the space holds leaves the base alone


def _urdf_efforts(path: str) -> dict[str, float]:
    """Joint name -> <limit effort="..."> straight from the URDF file."""
    root = ET.parse(path).getroot()
    return {
        j.get("name"): float(j.find("limit").get("effort")) for j in root.iter("joint") if j.find("limit") is not None
    }


def test_reset_seed_reproduces_episodes(ur5: ms.Robot) -> None:
    env = MultibodyEnv(ur5, **settings(max_episode_steps=None, terminated=None))
    actions = np.random.default_rng(1).uniform(-20.0, 20.0, size=(8, 6))

    def episode(seed: int) -> list[Any]:
        out: list[Any] = [env.reset(seed=seed)]
        out += [env.step(a) for a in actions]
        return out

    first, again, other = episode(7), episode(7), episode(8)
    assert data_equivalence(first, again, exact=True)
    assert not np.array_equal(first[0][0], other[0][0])  # another seed, another start
    # The start is the default pose moved in the tangent space by at most reset_noise_q, at most reset_noise_v fast.
    obs = first[0][0]
    assert np.abs(ur5.difference(ur5.default_pose(), obs[:6])).max() <= 0.2
    assert 0 < np.abs(obs[6:]).max() <= 0.01


def test_reset_options_start_from_an_exact_state(ur5: ms.Robot) -> None:
    env = MultibodyEnv(ur5, **settings())
    q = ur5.default_pose() + 0.1
    obs, info = env.reset(seed=0, options={"q": q})
    np.testing.assert_array_equal(obs, np.concatenate((q, np.zeros(6))))
    assert info == {"t": 0.0}


def test_episode_follows_the_stepper(ur5: ms.Robot) -> None:
    """One environment step is one control interval of a Stepper with the action held; reward, termination and
    truncation come from the callables and the step count."""
    env = MultibodyEnv(ur5, **settings())
    obs, _ = env.reset(seed=3)
    stepper = ms.Stepper(ur5, dt=0.002, control_dt=0.01, q0=obs[:6], v0=obs[6:])
    action = np.linspace(-5.0, 5.0, 6)
    for k in range(6):
        obs, r, terminated, truncated, info = env.step(action)
        state = stepper.step(action)
        np.testing.assert_array_equal(obs, np.concatenate((state.q, state.v)))
        assert r == reward(state.q, state.v, action) and terminated == fell(state.q, state.v)
        assert truncated == (k == 5) and info == {"t": state.t}


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
@pytest.mark.parametrize(("name", "scale"), [("ur5", 1.0), ("solo12", 0.02)])
def test_vector_rows_equal_single_environments(name: str, scale: float, mode: AutoresetMode) -> None:
    """Row for row, MultibodyVectorEnv is gymnasium's SyncVectorEnv over MultibodyEnv copies (which seeds copy i
    with seed + i and autoresets as the mode says), through terminations and truncations: bit for bit on a fixed
    base; on a floating base the batch kernel's chart map rounds differently (rollout's contract), so states
    agree to round-off there and everything else exactly (actions of `scale` times the limits keep solo12 from
    blowing up, where round-off would grow without bound)."""
    robot = ms.load_robot(name)
    n = 5
    kwargs = settings(reset_noise_v=0.5)
    vector = MultibodyVectorEnv(robot, n, autoreset_mode=mode, **kwargs)
    reference = SyncVectorEnv([lambda: MultibodyEnv(robot, **kwargs) for _ in range(n)], autoreset_mode=mode)
    assert vector.metadata["autoreset_mode"] == mode
    assert data_equivalence(vector.reset(seed=11), reference.reset(seed=11), exact=True)
    vector.action_space.seed(2)
    ended = 0
    for _ in range(25):
        actions = vector.action_space.sample() * scale
        got, want = vector.step(actions), reference.step(actions)
        ended += int(np.sum(got[2] | got[3]))
        if robot.floating_base:
            np.testing.assert_allclose(got[0], want[0], rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(got[1], want[1], rtol=1e-12, atol=1e-12)
            got, want = got[2:4], want[2:4]  # terminations, truncations (infos hold final_obs in SAME_STEP)
        for a, b in zip(got, want, strict=True):
            assert data_equivalence(a, b, exact=True)
    assert ended > n  # episodes ended (terminated and truncated) and rows were reset, several times


def test_vector_scene_with_time_varying_forces_equals_single_environments() -> None:
    """A scene whose forces depend on time: each row keeps its own clock across resets."""
    scene = ms.load_scene("ur5_ceiling_push")
    n = 3
    kwargs = settings(max_episode_steps=4, control_dt=0.1, dt=0.01)
    vector = MultibodyVectorEnv(scene, n, **kwargs)
    reference = SyncVectorEnv([lambda: MultibodyEnv(scene, **kwargs) for _ in range(n)])
    assert data_equivalence(vector.reset(seed=0), reference.reset(seed=0), exact=True)
    vector.action_space.seed(0)
    for _ in range(9):
        actions = vector.action_space.sample()
        assert data_equivalence(vector.step(actions), reference.step(actions), exact=True)


def test_a_failed_row_ends_its_own_episode() -> None:
    """A row whose state diverges terminates with the reason in its info; the other rows go on, and the failed
    row starts a new episode at the next step (NEXT_STEP)."""
    pendulum = ms.load_robot("double_pendulum", damping=False)
    vector = MultibodyVectorEnv(
        pendulum, 3, reward=reward, control_dt=0.05, method="euler", failure_reward=-100.0, reset_noise_v=0.0
    )
    q = np.array([[3.0, 0.0], [3.0, 0.0], [3.0, 0.0]])
    v = np.array([[40.0, -40.0], [0.0, 0.0], [0.1, 0.0]])  # row 0 is thrown hard: euler at 50 ms blows up
    vector.reset(seed=0, options={"q": q, "v": v})
    failed_at = None
    for k in range(40):
        obs, rewards, terminated, truncated, infos = vector.step(np.zeros((3, 2)))
        assert np.isfinite(obs).all()
        if terminated[0]:
            failed_at = k
            break
        assert "_failure" not in infos or not infos["_failure"].any()
    assert failed_at is not None
    assert infos["_failure"].tolist() == [True, False, False] and infos["failure"][0] == "diverged"
    assert infos["message"][0].startswith("diverged at t = ") and rewards[0] == -100.0
    assert not terminated[1:].any() and not truncated.any()
    obs, rewards, terminated, _, infos = vector.step(np.zeros((3, 2)))
    assert infos["t"].tolist()[0] == 0.0 and rewards[0] == 0.0 and not terminated[0]  # reset, as NEXT_STEP does
    assert infos["t"][1] == pytest.approx((failed_at + 2) * 0.05)


def test_single_env_failure_terminates_with_the_reason() -> None:
    pendulum = ms.load_robot("double_pendulum", damping=False)
    env = MultibodyEnv(pendulum, reward=reward, control_dt=0.05, method="euler", failure_reward=-1.0)
    env.reset(options={"q": [3.0, 0.0], "v": [40.0, -40.0]})
    for _ in range(40):
        obs, r, terminated, truncated, info = env.step(np.zeros(2))
        if terminated:
            break
    assert terminated and info["failure"] == "diverged" and r == -1.0 and np.isfinite(obs).all()


# ---- the vector environment's counterparts of check_env's checks ---------------------------------------------------
@pytest.fixture(scope="module")
def vector(ur5: ms.Robot) -> MultibodyVectorEnv:
    return MultibodyVectorEnv(ur5, 4, **settings())


def test_vector_spaces_batch_the_single_spaces(vector: MultibodyVectorEnv) -> None:
    single_obs, single_action = vector.single_observation_space, vector.single_action_space
    assert vector.observation_space == gymnasium.vector.utils.batch_space(single_obs, 4)
    assert vector.action_space == gymnasium.vector.utils.batch_space(single_action, 4)
    assert vector.observation_space.shape == (4, 12) and vector.action_space.shape == (4, 6)


def test_vector_reset_is_seeded(vector: MultibodyVectorEnv) -> None:
    obs_1, info_1 = vector.reset(seed=123)
    obs_2, _ = vector.reset()
    obs_3, info_3 = vector.reset(seed=123)
    obs_4, _ = vector.reset()
    assert obs_1 in vector.observation_space and obs_2 in vector.observation_space
    assert data_equivalence((obs_1, info_1), (obs_3, info_3), exact=True)
    assert data_equivalence(obs_2, obs_4, exact=True)
    assert not np.array_equal(obs_1, obs_2) and not np.array_equal(obs_1[0], obs_1[1])
    assert not np.array_equal(vector.reset(seed=456)[0], obs_1)


def test_vector_step_is_deterministic_and_returns_fresh_data(vector: MultibodyVectorEnv) -> None:
    vector.action_space.seed(5)
    actions = [vector.action_space.sample() for _ in range(3)]
    runs = []
    for _ in range(2):
        calls = [vector.reset(seed=9)]
        calls += [vector.step(a) for a in actions]
        runs.append(calls)
    assert data_equivalence(runs[0], runs[1], exact=True)
    for (obs_1, *_, info_1), (obs_2, *_, info_2) in combinations(runs[0], 2):
        assert not data_shares_objects(obs_1, obs_2) and not data_shares_objects(info_1, info_2)
    obs, rewards, terminations, truncations, _ = runs[0][1]
    assert obs in vector.observation_space and obs.dtype == np.float64
    assert rewards.shape == (4,) and rewards.dtype == np.float64
    assert terminations.dtype == np.bool_ and truncations.dtype == np.bool_


def test_vector_partial_reset_and_disabled_autoreset(ur5: ms.Robot) -> None:
    vector = MultibodyVectorEnv(ur5, 3, autoreset_mode="Disabled", **settings(max_episode_steps=2))
    vector.reset(seed=1)
    zero = np.zeros((3, 6))
    vector.step(zero)
    _, _, _, truncated, _ = vector.step(zero)
    assert truncated.all()
    with pytest.raises(ms.InvalidArgumentError, match=r"^rows \[0, 1, 2\] ended their episodes: reset them first"):
        vector.step(zero)
    obs, infos = vector.reset(options={"reset_mask": np.array([True, False, True])})
    assert infos["_t"].tolist() == [True, False, True]
    with pytest.raises(ms.InvalidArgumentError, match=r"^rows \[1\] ended"):
        vector.step(zero)


# ---- bad input ----------------------------------------------------------------------------------------------------
def test_bad_arguments_say_what_is_wrong(ur5: ms.Robot) -> None:
    with pytest.raises(ms.InvalidArgumentError, match=r"^render_mode must be None, got 'human': the viewer is"):
        MultibodyEnv(ur5, **settings(), render_mode="human")
    with pytest.raises(ms.InvalidArgumentError, match=r"^reward is required: a callable reward\(q, v, tau\)"):
        MultibodyEnv(ur5, reward=None, control_dt=0.01)
    with pytest.raises(ms.InvalidArgumentError, match=r"^max_episode_steps must be a positive whole number, got 0$"):
        MultibodyEnv(ur5, **settings(max_episode_steps=0))
    with pytest.raises(
        ms.InvalidArgumentError, match=r"^reset_noise_q must be a number from 0 to 1e\+06 rad or m, got -1$"
    ):
        MultibodyEnv(ur5, **settings(reset_noise_q=-1))
    with pytest.raises(ms.InvalidArgumentError, match=r"^control_dt"):
        MultibodyEnv(ur5, **settings(control_dt=0.003))  # not a multiple of dt = 2 ms
    with pytest.raises(ms.InvalidArgumentError, match=r"^num_envs must be a positive whole number, got 0$"):
        MultibodyVectorEnv(ur5, 0, **settings())
    with pytest.raises(ms.InvalidArgumentError, match=r"^autoreset_mode must be one of 'NextStep'"):
        MultibodyVectorEnv(ur5, 2, autoreset_mode="sometimes", **settings())
    vector = MultibodyVectorEnv(ur5, 2, **settings())
    vector.reset(seed=0)
    with pytest.raises(ms.InvalidArgumentError, match=r"^actions must have shape \(2, 6\), got \(6,\)$"):
        vector.step(np.zeros(6))


def test_pushing_an_unactuated_base_is_refused(solo12: ms.Robot) -> None:
    env = MultibodyEnv(solo12, **settings())
    env.reset(seed=0)
    with pytest.raises(ms.InvalidArgumentError, match=r"acts on the unactuated floating base and must be zero"):
        env.step(np.ones(18))


# Actions the single environment refuses (strings, objects, complex numbers: NumPy would raise its own errors or
# silently drop the imaginary part), as one row and as the vector environment's batch.
NOT_TORQUES = {
    "string": ("abc", "abc", "str"),
    "objects": (np.array([object()] * 6), np.array([[object()] * 6] * 2), "dtype object"),
    "complex": (np.full(6, 1 + 1j), np.full((2, 6), 1 + 1j), "dtype complex128"),
    "a string among numbers": ([0, 0, 0, 0, 0, "x"], [[0, 0, 0, 0, 0, "x"]] * 2, "list"),
}


@pytest.mark.parametrize("kind", NOT_TORQUES)
def test_vector_env_refuses_what_the_single_env_refuses(ur5: ms.Robot, kind: str) -> None:
    single, batch, got = NOT_TORQUES[kind]
    env = MultibodyEnv(ur5, **settings())
    env.reset(seed=0)
    with pytest.raises(ms.InvalidArgumentError, match=rf"^tau must be an array of 6 real numbers, got {got}$"):
        env.step(single)
    vector = MultibodyVectorEnv(ur5, 2, **settings())
    vector.reset(seed=0)
    before = vector.stepper.q
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a complex action is refused, never truncated to its real part with a warning
        with pytest.raises(
            ms.InvalidArgumentError, match=rf"^actions must be an array of real numbers of shape \(2, 6\), got {got}$"
        ):
            vector.step(batch)
    np.testing.assert_array_equal(vector.stepper.q, before)  # nothing stepped


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"q": np.zeros((1, 6))}, r"options\['q'\] must have shape \(2, 6\), one row per reset row, got \(1, 6\)"),
        ({"q": np.zeros((3, 6))}, r"options\['q'\] must have shape \(2, 6\), one row per reset row, got \(3, 6\)"),
        ({"q": np.zeros(6)}, r"options\['q'\] must have shape \(2, 6\), one row per reset row, got \(6,\)"),
        (
            {"q": np.zeros((2, 6)), "v": np.zeros((1, 6))},
            r"options\['v'\] must have shape \(2, 6\), one row per reset row, got \(1, 6\)",
        ),
        (
            {"q": [["a"] * 6] * 2},
            r"options\['q'\] must be an array of real numbers of shape \(2, 6\), one row per reset row, got list",
        ),
        ({"q": np.full((2, 6), np.nan)}, r"options\['q'\]\[0\] must be finite, got non-finite entries at"),
    ],
)
def test_vector_reset_options_need_one_state_per_reset_row(ur5: ms.Robot, options: dict, message: str) -> None:
    vector = MultibodyVectorEnv(ur5, 2, **settings())
    vector.reset(seed=0)
    with pytest.raises(ms.InvalidArgumentError, match=f"^{message}"):
        vector.reset(options=options)
    # With a mask, one row is reset: one state.
    mask = np.array([False, True])
    vector.reset(options={"reset_mask": mask, "q": ur5.default_pose()[None]})
    with pytest.raises(ms.InvalidArgumentError, match=r"^options\['q'\] must have shape \(1, 6\), one row per reset"):
        vector.reset(options={"reset_mask": mask, "q": np.zeros((2, 6))})


# ---- the integrator and steps, as Scene.run() chooses them (issue 27) -------------------------------------------
def test_contact_scene_runs_in_a_vector_env_with_no_method_argument() -> None:
    """go2_standing in a MultibodyVectorEnv with nothing but a reward: timestepping at the scene's dt, as
    Scene.run(); a row started at the scene's state with zero torque is simulate()'s run of the scene, sample for
    sample."""
    scene = ms.load_scene("go2_standing")
    declared = scene.simulation_settings(controller=False)
    envs = MultibodyVectorEnv(scene, 2, reward=lambda q, v, tau: 0.0)
    assert (envs.stepper.integrator.name, envs.task.dt, envs.task.control_dt) == ("timestepping", declared["dt"], 1e-3)
    np.testing.assert_array_equal(envs.task.initial_q, scene.q0)
    obs, _ = envs.reset(seed=0, options={"q": np.tile(scene.q0, (2, 1))})
    rows = [obs]
    for _ in range(5):
        obs, _, terminated, _, infos = envs.step(np.zeros((2, scene.nv)))
        assert not terminated.any(), infos
        rows.append(obs)
    run = ms.simulate(scene, scene.q0, scene.v0, duration=5e-3, dt=1e-3, integrator="timestepping")
    for b in range(2):
        np.testing.assert_array_equal(np.array([r[b] for r in rows]), np.hstack((run.q, run.v)))


def test_scene_method_and_steps_are_the_scenes_own() -> None:
    scene = ms.load_scene("spring_chain")  # [simulation] integrator = "implicit_midpoint", dt = 2e-3
    env = MultibodyEnv(scene, reward=reward)
    assert (env.stepper.integrator.name, env.stepper.dt, env.stepper.control_dt) == ("implicit_midpoint", 2e-3, 2e-3)
    np.testing.assert_array_equal(env.task.initial_q, scene.q0)
    env = MultibodyEnv(scene, reward=reward, control_dt=0.01)  # a longer control interval over the scene's steps
    assert (env.stepper.dt, env.stepper.control_dt) == (2e-3, 0.01)
    env = MultibodyEnv(scene, reward=reward, method="rk4", dt=1e-3)  # what is given wins
    assert (env.stepper.integrator.name, env.stepper.dt, env.stepper.control_dt) == ("rk4", 1e-3, 1e-3)


def test_robot_steps_default_to_the_control_interval(ur5: ms.Robot) -> None:
    env = MultibodyEnv(ur5, reward=reward, control_dt=0.01)
    assert (env.stepper.integrator.name, env.stepper.dt, env.stepper.control_dt) == ("rk4", 0.01, 0.01)
    env = MultibodyEnv(ur5, reward=reward)
    assert (env.stepper.dt, env.stepper.control_dt) == (1e-3, 1e-3)


def test_seeds_options_noise_and_sizes_are_refused_in_one_line(ur5: ms.Robot) -> None:
    """What gymnasium or NumPy would refuse in their own words (or NumPy could not draw) is refused in ours, by both
    environments alike, and before any row changes."""
    env = MultibodyEnv(ur5, **settings())
    vector = MultibodyVectorEnv(ur5, 2, **settings())
    for e in (env, vector):
        with pytest.raises(ms.InvalidArgumentError, match=r"^seed must be None or a whole number >= 0, got -1$"):
            e.reset(seed=-1)
        with pytest.raises(ms.InvalidArgumentError, match=r"^options must be a dict \(keys 'q', 'v', 'reset_mask'\), "):
            e.reset(options="q")
    with pytest.raises(ms.InvalidArgumentError, match=r"^seed must be None or a whole number >= 0, got 1\.5$"):
        env.reset(seed=1.5)
    with pytest.raises(ms.InvalidArgumentError, match=r"^seed\[1\] must be None or a whole number >= 0, got 'x'$"):
        vector.reset(seed=[0, "x"])
    with pytest.raises(ms.InvalidArgumentError, match=r"^seed must be None, a whole number >= 0 or a list of one per"):
        vector.reset(seed=[0])
    obs, _ = vector.reset(seed=3)
    with pytest.raises(ms.InvalidArgumentError, match=r"^options\['q'\]\[1\] must be finite"):
        vector.reset(seed=5, options={"q": [ur5.default_pose(), np.full(6, np.nan)]})
    np.testing.assert_array_equal(vector._observations(), obs)  # refused: nothing reset, no generator reseeded
    np.testing.assert_array_equal(vector.reset(seed=3)[0], obs)
    with pytest.raises(ms.InvalidArgumentError, match=r"^reset_noise_v must be a number from 0 to 1e\+06 rad/s or m/s"):
        MultibodyEnv(ur5, **settings(reset_noise_v=1e308))  # NumPy's uniform draw would overflow
    with pytest.raises(ms.InvalidArgumentError, match=r"^4611686018427387904 environments would keep their states"):
        MultibodyVectorEnv(ur5, 2**62, **settings())
