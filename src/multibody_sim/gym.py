"""Gymnasium environments over any robot or scene: MultibodyEnv steps one Stepper, MultibodyVectorEnv steps B rows
on the batched stepping core (BatchStepper). Needs gymnasium (`pip install 'multibody-sim[gym]'`).

An environment step is one control interval (``control_dt``) with the action held as the joint torque; the
observation is the state (q, v), or with ``observation="sensors"`` (or a list of sensor names) the readings of a
scene's sensors (multibody_sim.sensors: noise, bias, rate and latency as declared), concatenated in the order
declared (named). Episodes start from a seeded distribution around the robot's default pose (a
scene's own initial state, q0 and v0, in its place):

    q0 = default_pose() ⊕ δq,  δq ~ U(-reset_noise_q, reset_noise_q)^nv  (in the tangent space: robot.integrate)
    v0 = δv,                   δv ~ U(-reset_noise_v, reset_noise_v)^nv

drawn in that order from the environment's generator (``np_random``, seeded by ``reset(seed=...)``), around
``initial_q`` / ``initial_v`` when given instead of the default pose and rest; ``reset(options={"q": q, "v": v})``
starts from an exact state instead.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from .exceptions import InvalidArgumentError, MissingDependencyError, SimulationError
from .integrators import Integrator
from .recording import sample_bytes
from .robot import Robot, real_array
from .safety import check_allocation
from .scenes import Scene, randomized_scene
from .stepper import BatchStepper, Stepper
from .torques import command_bounds
from .validation import check_callable, in_range, is_number, positive_number

try:
    import gymnasium
    from gymnasium import spaces
    from gymnasium.utils import seeding
    from gymnasium.vector import AutoresetMode, VectorEnv
    from gymnasium.vector.utils import batch_space
except ImportError:  # pragma: no cover - exercised without the extra only
    raise MissingDependencyError(
        "multibody_sim.gym needs the 'gymnasium' package, which is not installed (pip install 'multibody-sim[gym]')"
    ) from None

# The widest start distribution [rad, m; rad/s, m/s]: beyond it the draw means nothing (angles wrap; a base a thousand
# kilometres away) and its range, 2 x the noise, overflows near 1e308.
MAX_RESET_NOISE = 1e6
# A vector environment holds about this many copies of a row's sample: its spaces' bounds, the starts, the stepper's
# states, torques and ledger, the step's store and the observations returned.
ROW_COPIES = 8
Reward = Callable[[np.ndarray, np.ndarray, np.ndarray], float]
Termination = Callable[[np.ndarray, np.ndarray], bool]


@dataclass(frozen=True)
class _Task:
    """What both environments share, checked: the system, the callables, the timing and the start distribution."""

    system: Robot
    reward: Reward
    terminated: Termination | None
    max_episode_steps: int | None
    control_dt: float
    dt: float
    method: str | Integrator
    options: dict[str, Any]
    initial_q: np.ndarray
    initial_v: np.ndarray
    reset_noise_q: float
    reset_noise_v: float
    failure_reward: float
    sensors: tuple[str, ...] | None  # the observed sensors, or None: the state (q, v)
    randomizer: Any = None  # randomised physics: what each episode's scene parameters are drawn from

    @classmethod
    def check(
        cls,
        system: Robot,
        reward: Any,
        terminated: Any,
        max_episode_steps: Any,
        control_dt: Any,
        dt: Any,
        method: str | Integrator | None,
        options: dict[str, Any],
        initial_q: Any,
        initial_v: Any,
        reset_noise_q: Any,
        reset_noise_v: Any,
        failure_reward: Any,
        observation: Any = "state",
        randomize: Any = None,
    ) -> _Task:
        if not isinstance(system, Robot):
            raise InvalidArgumentError(
                f"system must be a Robot or a Scene (load_robot, load_scene), got {type(system).__name__}"
            )
        system, randomizer = randomized_scene(system, randomize, "randomize")
        if reward is None:
            raise InvalidArgumentError("reward is required: a callable reward(q, v, tau) -> float")
        check_callable(reward, "reward", "reward(q, v, tau)")
        check_callable(terminated, "terminated", "terminated(q, v)")
        if max_episode_steps is not None and (
            isinstance(max_episode_steps, bool) or not isinstance(max_episode_steps, (int, np.integer))
            or max_episode_steps < 1
        ):  # fmt: skip
            raise InvalidArgumentError(f"max_episode_steps must be a positive whole number, got {max_episode_steps!r}")
        method, dt, control_dt, options = _timing(system, method, dt, control_dt, options)
        noise_q = in_range(reset_noise_q, "reset_noise_q", 0.0, MAX_RESET_NOISE, "rad or m")
        noise_v = in_range(reset_noise_v, "reset_noise_v", 0.0, MAX_RESET_NOISE, "rad/s or m/s")
        failure = float(failure_reward) if is_number(failure_reward) else math.nan
        if not math.isfinite(failure):
            raise InvalidArgumentError(f"failure_reward must be a finite number, got {failure_reward!r}")
        if isinstance(system, Scene):  # the scene's own start ([initial], objects where it puts them)
            q_centre, v_centre = system.q0, system.v0
        else:
            q_centre, v_centre = system.default_pose(), np.zeros(system.nv)
        q = q_centre if initial_q is None else system.check_q(initial_q, "initial_q")
        v = v_centre if initial_v is None else system.check_v(initial_v, "initial_v")
        return cls(
            system,
            reward,
            terminated,
            None if max_episode_steps is None else int(max_episode_steps),
            control_dt,
            dt,
            method,
            dict(options),
            q,
            v,
            noise_q,
            noise_v,
            failure,
            _observed_sensors(system, observation),
            randomizer,
        )

    # ---- spaces ----------------------------------------------------------------------------------------------------
    def observation_space(self) -> spaces.Box:
        """(q, v), float64, shape (nq + nv,), or the observed sensors' readings (their components); unbounded."""
        if self.sensors is None:
            n = self.system.nq + self.system.nv
        else:
            sensors = self.system.sensors  # type: ignore[attr-defined]
            n = sum(sensors.placed[sensors.names.index(name)].width for name in self.sensors)
        return spaces.Box(-np.inf, np.inf, shape=(n,), dtype=np.float64)

    def observe(self, q: np.ndarray, v: np.ndarray, readings: dict[str, np.ndarray]) -> np.ndarray:
        """The observation of a state (q, v) and its readings (one row: arrays (components,); many: (n, ...))."""
        if self.sensors is None:
            return np.concatenate((q, v), axis=-1)
        return np.concatenate([readings[name] for name in self.sensors], axis=-1)

    def action_space(self) -> spaces.Box:
        """Joint torques, float64, shape (nv,), within ± the effort limits (±inf where the URDF gives none), of width
        zero on the unactuated entries (a floating base's 6); with a scene's actuators, their commands within their
        bounds (torques.command_bounds: a position servo's target within its joint's range)."""
        low, high = command_bounds(self.system)
        if self.system.floating_base:
            low[:6] = high[:6] = 0.0
        return spaces.Box(low, high, dtype=np.float64)

    # ---- episodes --------------------------------------------------------------------------------------------------
    def initial_state(
        self, rng: np.random.Generator, options: dict[str, Any] | None, row: str = ""
    ) -> tuple[np.ndarray, np.ndarray]:
        """An episode's start: options' exact "q" (and "v", default zero), else a draw (see the module docstring).
        `row` follows the option names in messages ("[2]": the vector environment's third reset row)."""
        system = self.system
        if options and "q" in options:
            q = system.check_q(options["q"], f"options['q']{row}")
            v = system.check_v(options.get("v", np.zeros(system.nv)), f"options['v']{row}")
            return q, v
        if options and "v" in options:
            raise InvalidArgumentError("options['v'] needs options['q'] too (the state to start from)")
        dq = rng.uniform(-self.reset_noise_q, self.reset_noise_q, size=system.nv)
        dv = rng.uniform(-self.reset_noise_v, self.reset_noise_v, size=system.nv)
        return system.space.integrate(self.initial_q, dq), self.initial_v + dv

    def parameters(self, rng: np.random.Generator) -> tuple[Any, dict[str, Any]]:
        """An episode's scene (its parameters drawn from `rng`, after its start: randomised physics) and the reset
        info's part: {"parameters": the values} (nothing drawn: the system itself and {})."""
        if self.randomizer is None:
            return self.system, {}
        values = self.randomizer.draw(rng)
        return self.system.with_parameters(values), {"parameters": values}  # type: ignore[attr-defined]

    def outcome(self, q: np.ndarray, v: np.ndarray, tau: np.ndarray) -> tuple[float, bool]:
        """(reward, terminated) of a step that ended at (q, v) with tau applied."""
        reward = float(self.reward(q, v, tau))
        terminated = bool(self.terminated(q, v)) if self.terminated is not None else False
        return reward, terminated


def _timing(
    system: Robot, method: str | Integrator | None, dt: Any, control_dt: Any, options: dict[str, Any]
) -> tuple[str | Integrator, float, float, dict[str, Any]]:
    """(method, dt, control_dt, options) with the defaults Scene.run() takes: a scene's [simulation] integrator,
    dt and control_dt (timestepping for a contact scene, rk4 otherwise; dt 1 ms), and its rtol, atol and max_step
    when its own method runs; for a robot rk4, dt = control_dt (1 ms when neither is given). control_dt defaults
    to dt."""
    control_dt = None if control_dt is None else positive_number(control_dt, "control_dt")
    dt = None if dt is None else positive_number(dt, "dt")
    declared: dict[str, Any] = {}
    if isinstance(system, Scene):
        declared = system.simulation_settings(controller=False)
    elif control_dt is not None:
        declared["dt"] = control_dt
    if method is None:
        method = declared.get("integrator", "rk4")
        adaptive: dict[str, Any] = {k: declared[k] for k in ("rtol", "atol", "max_step") if k in declared}
        options = {**adaptive, **options}
    dt = float(declared.get("dt", 1e-3)) if dt is None else dt
    control_dt = float(declared.get("control_dt", dt)) if control_dt is None else control_dt
    return method, dt, control_dt, options


def _check_seed(seed: Any, name: str = "seed") -> int | None:
    """A reset's seed: None or a whole number >= 0 (what numpy's SeedSequence takes), else InvalidArgumentError."""
    if seed is None:
        return None
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise InvalidArgumentError(f"{name} must be None or a whole number >= 0, got {seed!r:.80}")
    return int(seed)


def _check_options(options: Any) -> dict[str, Any]:
    """A reset's options as a new dict (None: empty), else InvalidArgumentError."""
    if options is None:
        return {}
    if not isinstance(options, Mapping):
        raise InvalidArgumentError(f"options must be a dict (keys 'q', 'v', 'reset_mask'), got {_described(options)}")
    return dict(options)


def _described(value: Any) -> str:
    """A short one-line description of a value for a message: an array's shape and dtype, else its type."""
    if isinstance(value, np.ndarray):
        return f"an array of shape {value.shape} and dtype {value.dtype}"
    return type(value).__name__


def _observed_sensors(system: Robot, observation: Any) -> tuple[str, ...] | None:
    """The sensors an observation names ("sensors": all, in the order declared; a list: those), or None for
    "state"; else InvalidArgumentError."""
    if isinstance(observation, str) and observation == "state":
        return None
    sensors = getattr(system, "sensors", None)
    names = sensors.names if sensors is not None else []
    if isinstance(observation, str) and observation == "sensors":
        if not names:
            raise InvalidArgumentError(
                'observation="sensors" needs a scene with sensors ([[sensor]] tables); this system declares none'
            )
        return tuple(names)
    if isinstance(observation, (list, tuple)) and observation and all(isinstance(n, str) for n in observation):
        unknown = [n for n in observation if n not in names]
        if unknown or len(set(observation)) != len(observation):
            problem = f"unknown sensor '{unknown[0]}'" if unknown else "a sensor named twice"
            raise InvalidArgumentError(
                f"observation: {problem} (the system's sensors: {', '.join(names) if names else 'none'})"
            )
        return tuple(observation)
    raise InvalidArgumentError(
        f'observation must be "state", "sensors" or a list of sensor names, got {_described(observation)}'
    )


class MultibodyEnv(gymnasium.Env):
    """A Gymnasium environment over a robot or scene: one step holds the action as joint torque over one control
    interval of a Stepper (simulate()'s stepping core).

    Observation: ``np.concatenate((q, v))``, a float64 Box of shape (nq + nv,); with ``observation="sensors"``
    (or a list of sensor names) the sensors' readings concatenated, a Box of their components (the env's seeded
    reset also seeds the sensors' noise: each sensor's generator seeded with (its seed, the reset's seed)).
    Action: the joint torques, a float64 Box of shape (nv,) bounded by the URDF's effort limits (±inf where it
    gives none), of zero width on the unactuated entries (a floating base's 6); torques beyond the limits are
    saturated. Reward: ``reward(q, v, tau)`` at the
    state the step reached, with the torque applied. An episode terminates when ``terminated(q, v)`` says so, or
    when the step fails (the state diverged, Newton failed, ...): then ``info["failure"]`` names the status and
    ``info["message"]`` says why, the state stays where it was before the step and the reward is
    ``failure_reward``. It is truncated after ``max_episode_steps`` steps. ``info["t"]`` is the episode's time [s].

    Episodes start from a seeded distribution around the default pose (see the module docstring); ``reset(seed=s)``
    reproduces an episode exactly. Rendering: none (``render_mode`` None): the viewer is a meshcat page in a
    browser, not a frame source; record states and view them with ``multibody_sim.viz``.

    Args:
        system: a Robot or a Scene.
        reward: ``reward(q, v, tau) -> float``.
        terminated: ``terminated(q, v) -> bool``, or None (only failures terminate).
        max_episode_steps: truncate after this many steps, or None.
        control_dt: the environment's step [s] (the Stepper's control interval); default: a scene's [simulation]
            control_dt, else dt.
        dt: the integration step [s] (control_dt must be a multiple of it for fixed-step methods); default: a
            scene's [simulation] dt (1 ms when it gives none, as Scene.run()), for a robot control_dt (1 ms when
            neither is given).
        method: the integrator (`multibody-sim integrators` lists them); default: as Scene.run() chooses, the
            scene's [simulation] integrator, timestepping for a contact scene, else rk4 (with the scene's rtol,
            atol and max_step).
        initial_q, initial_v: the centre of the start distribution (default: default_pose() and rest).
        reset_noise_q: half-width of the uniform perturbation of q in the tangent space [rad, m].
        reset_noise_v: half-width of the uniform perturbation of v [rad/s, m/s].
        failure_reward: the reward of a step that failed.
        observation: "state" (q, v), "sensors" (every sensor of the scene) or a list of sensor names.
        randomize: randomised physics (README "Randomised physics"): None draws each episode's scene parameters
            from the scene's own [randomize] table when it has one, a dict in that table's form draws from it
            instead, False draws nothing. They are drawn from the environment's generator at each reset, after the
            start, and reset's info holds them ("parameters"); ``system.with_parameters(them)`` is the episode's
            scene.
        render_mode: None only.
        **options: the integrator's options (rtol, atol, max_step for adaptive ones).
    """

    metadata: dict[str, Any] = {"render_modes": []}

    def __init__(
        self,
        system: Robot,
        *,
        reward: Reward,
        terminated: Termination | None = None,
        max_episode_steps: int | None = None,
        control_dt: float | None = None,
        dt: float | None = None,
        method: str | Integrator | None = None,
        initial_q: Any = None,
        initial_v: Any = None,
        reset_noise_q: float = 0.01,
        reset_noise_v: float = 0.01,
        failure_reward: float = 0.0,
        observation: str | list[str] = "state",
        randomize: Any = None,
        render_mode: str | None = None,
        **options: Any,
    ):
        _check_render_mode(render_mode)
        self.task = task = _Task.check(
            system, reward, terminated, max_episode_steps, control_dt, dt, method, options,
            initial_q, initial_v, reset_noise_q, reset_noise_v, failure_reward, observation, randomize,
        )  # fmt: skip
        self.render_mode = None
        self.observation_space = task.observation_space()
        self.action_space = task.action_space()
        self.stepper = self._stepper(task.system)
        self._elapsed = 0

    def _stepper(self, system: Robot) -> Stepper:
        task = self.task
        return Stepper(
            system, dt=task.dt, integrator=task.method, control_dt=task.control_dt, q0=task.initial_q,
            v0=task.initial_v, **task.options,
        )  # fmt: skip

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode: from options' "q" (and "v") if given, else drawn around the default pose.

        Returns:
            The observation ((q, v), shape (nq + nv,), or the sensors' readings), and info {"t": 0.0} (randomised
            physics: and "parameters", the episode's scene parameter values).
        """
        options = _check_options(options)
        seed = _check_seed(seed)
        super().reset(seed=seed)
        q, v = self.task.initial_state(self.np_random, options)
        system, drawn = self.task.parameters(self.np_random)
        if drawn:
            self.stepper = self._stepper(system)
        state = self.stepper.reset(q, v, 0.0, sensor_seed=seed)
        self._elapsed = 0
        return self.task.observe(state.q, state.v, self.stepper.readings), {"t": state.t, **drawn}

    def step(self, action: Any) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        """Hold the action as joint torque over one control interval.

        Returns:
            (observation, reward, terminated, truncated, info), as the class docstring says.
        """
        task = self.task
        info: dict[str, Any] = {}
        try:
            state = self.stepper.step(action)
        except SimulationError as exc:
            state = self.stepper.state
            reward, terminated = task.failure_reward, True
            info = {"failure": exc.status, "message": str(exc)}
        else:
            reward, terminated = task.outcome(state.q, state.v, self.stepper.tau)
        self._elapsed += 1
        truncated = task.max_episode_steps is not None and self._elapsed >= task.max_episode_steps
        observation = task.observe(state.q, state.v, self.stepper.readings)
        return observation, reward, terminated, truncated, {"t": state.t, **info}


class MultibodyVectorEnv(VectorEnv):
    """``num_envs`` copies of MultibodyEnv stepped together on one stepping core over the rows (BatchStepper: the
    batch kernel where it renders the method, as rollout() does).

    Each row is the single environment: with the same seeds and actions, row i gives MultibodyEnv's episode seeded
    with seed + i (``reset(seed=s)``, as gymnasium's SyncVectorEnv seeds its copies) bit for bit, but to round-off
    on free-flyer, spherical and planar joints with multi-stage methods (the batch kernel's chart map sums its
    products in another order). A row whose step fails terminates its own episode, with ``infos["failure"]`` and
    ``infos["message"]`` set for it; the other rows go on. Rows reset automatically after their episode ends, as
    ``autoreset_mode`` says (gymnasium 1.x: NEXT_STEP, the default: the step after a row's end resets it, with reward
    0 and its action ignored; SAME_STEP: the ending step returns the reset observation, the last one in
    ``infos["final_obs"]``; DISABLED: reset rows yourself with ``reset(options={"reset_mask": mask})``).

    Args:
        system: a Robot or a Scene.
        num_envs: the number of rows.
        autoreset_mode: an ``AutoresetMode`` or its value ("NextStep", "SameStep", "Disabled").
        num_threads: threads of Pinocchio's abaInParallel in the batch kernel.
        **kwargs: MultibodyEnv's (reward, terminated, max_episode_steps, control_dt, dt, method, initial_q,
            initial_v, reset_noise_q, reset_noise_v, failure_reward, observation, randomize, the integrator's
            options): with randomised physics each row draws its episode's scene parameters from its own generator at
            its reset (infos["parameters"]).
    """

    def __init__(
        self,
        system: Robot,
        num_envs: int,
        *,
        reward: Reward,
        terminated: Termination | None = None,
        max_episode_steps: int | None = None,
        control_dt: float | None = None,
        dt: float | None = None,
        method: str | Integrator | None = None,
        initial_q: Any = None,
        initial_v: Any = None,
        reset_noise_q: float = 0.01,
        reset_noise_v: float = 0.01,
        failure_reward: float = 0.0,
        observation: str | list[str] = "state",
        autoreset_mode: str | AutoresetMode = AutoresetMode.NEXT_STEP,
        num_threads: int = 1,
        randomize: Any = None,
        render_mode: str | None = None,
        **options: Any,
    ):
        _check_render_mode(render_mode)
        if isinstance(num_envs, bool) or not isinstance(num_envs, (int, np.integer)) or num_envs < 1:
            raise InvalidArgumentError(f"num_envs must be a positive whole number, got {num_envs!r}")
        try:
            mode = autoreset_mode if isinstance(autoreset_mode, AutoresetMode) else AutoresetMode(autoreset_mode)
        except ValueError:
            valid = ", ".join(repr(m.value) for m in AutoresetMode)
            raise InvalidArgumentError(f"autoreset_mode must be one of {valid}, got {autoreset_mode!r}") from None
        self.task = task = _Task.check(
            system, reward, terminated, max_episode_steps, control_dt, dt, method, options,
            initial_q, initial_v, reset_noise_q, reset_noise_v, failure_reward, observation, randomize,
        )  # fmt: skip
        system = task.system
        self.num_envs = n = int(num_envs)
        check_allocation(
            ROW_COPIES * sample_bytes(system, n),
            f"{n} environments would keep their states, spaces and stepping rows",
            "use fewer environments (num_envs)",
        )
        self.autoreset_mode = mode
        self.metadata = {"render_modes": [], "autoreset_mode": mode}
        self.render_mode = None
        self.single_observation_space = task.observation_space()
        self.single_action_space = task.action_space()
        self.observation_space = batch_space(self.single_observation_space, n)
        self.action_space = batch_space(self.single_action_space, n)
        Q0 = np.tile(task.initial_q, (n, 1))
        V0 = np.tile(task.initial_v, (n, 1))
        self.stepper = BatchStepper(
            system, Q0, V0, dt=task.dt, integrator=task.method, control_dt=task.control_dt, num_threads=num_threads,
            **task.options,
        )  # fmt: skip
        self._rngs: list[np.random.Generator | None] = [None] * n
        self._elapsed = np.zeros(n, dtype=np.int64)
        self._autoreset = np.zeros(n, dtype=bool)

    def _rng(self, i: int) -> np.random.Generator:
        rng = self._rngs[i]
        if rng is None:  # as gymnasium.Env.np_random: seeded at random on first use
            rng, _ = seeding.np_random()
            self._rngs[i] = rng
        return rng

    def reset(
        self, *, seed: int | list[int | None] | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start every row's episode (or the rows of ``options["reset_mask"]``, a bool array of shape (num_envs,)).

        Args:
            seed: None (each row's generator goes on), an int s (row i seeded with s + i) or one seed per row.
            options: ``reset_mask``; ``q`` (num_envs or masked rows, nq) and ``v`` to start from exact states.

        Returns:
            Observations, shape (num_envs, nq + nv), and infos {"t": zeros, "_t": the reset rows}.
        """
        n = self.num_envs
        seeds: list[int | None]
        if seed is None or isinstance(seed, (int, np.integer)):
            first = _check_seed(seed)
            seeds = [None if first is None else first + i for i in range(n)]
        elif isinstance(seed, (list, tuple)) and len(seed) == n:
            seeds = [_check_seed(s, f"seed[{i}]") for i, s in enumerate(seed)]
        else:
            got = f"a list of {len(seed)}" if isinstance(seed, (list, tuple)) else f"{seed!r:.80}"
            raise InvalidArgumentError(
                f"seed must be None, a whole number >= 0 or a list of one per row ({n}), got {got}"
            )
        if seeds[0] is not None and seed is not None and not isinstance(seed, (list, tuple)):
            super().reset(seed=seeds[0])
        options = _check_options(options)
        mask = options.pop("reset_mask", None)
        if mask is None:
            rows = np.arange(n)
        else:
            mask = np.asarray(mask) if isinstance(mask, np.ndarray) else np.asarray(mask, dtype=object)
            if mask.shape != (n,) or mask.dtype != np.bool_ or not mask.any():
                raise InvalidArgumentError(
                    f"options['reset_mask'] must be a bool array of shape ({n},) with a True entry, got "
                    f"{'no True entry' if mask.shape == (n,) and mask.dtype == np.bool_ else _described(mask)}"
                )
            rows = np.flatnonzero(mask)
        system = self.task.system
        Qs = self._exact_rows(options.pop("q", None), "q", len(rows), system.nq)
        Vs = self._exact_rows(options.pop("v", None), "v", len(rows), system.nv)
        infos: dict[str, Any] = {}
        states = []
        rngs = {i: seeding.np_random(seeds[i])[0] if seeds[i] is not None else self._rng(i) for i in rows.tolist()}
        systems = []
        for j, i in enumerate(rows.tolist()):
            exact: dict[str, Any] | None = None  # an exact start, as MultibodyEnv's options
            if Qs is not None or Vs is not None:
                exact = {key: value[j] for key, value in (("q", Qs), ("v", Vs)) if value is not None}
            states.append(self.task.initial_state(rngs[i], exact, f"[{j}]"))
            scene, drawn = self.task.parameters(rngs[i])
            systems.append(scene)
            infos = self._add_info(infos, {"t": 0.0, **drawn}, i)
        for i, rng in rngs.items():  # every row checked: the rows' generators change only now
            self._rngs[i] = rng
        self.stepper.reset(
            rows,
            np.array([q for q, _ in states]),
            np.array([v for _, v in states]),
            sensor_seed=None if seed is None else [seeds[i] for i in rows.tolist()],
            systems=systems if self.task.randomizer is not None else None,
        )
        self._elapsed[rows] = 0
        self._autoreset[rows] = False
        return self._observations(), infos

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict[str, Any]]:
        """Hold each row's action as its joint torque over one control interval (rows due for an autoreset are
        reset instead, NEXT_STEP).

        Returns:
            (observations (num_envs, nq + nv), rewards (num_envs,), terminations, truncations, infos).
        """
        task, n = self.task, self.num_envs
        TAU = real_array(actions, "actions", f"an array of real numbers of shape ({n}, {task.system.nv})")
        if TAU.shape != (n, task.system.nv):
            raise InvalidArgumentError(f"actions must have shape ({n}, {task.system.nv}), got {TAU.shape}")
        resetting = self._autoreset.copy() if self.autoreset_mode == AutoresetMode.NEXT_STEP else np.zeros(n, bool)
        if self.autoreset_mode == AutoresetMode.DISABLED and self._autoreset.any():
            rows = np.flatnonzero(self._autoreset).tolist()
            raise InvalidArgumentError(
                f"rows {rows} ended their episodes: reset them first (reset(options={{'reset_mask': mask}}))"
            )
        TAU[resetting] = 0.0  # their actions are ignored: they start a new episode instead
        result = self.stepper.step(TAU)
        rewards = np.zeros(n)
        terminations = np.zeros(n, dtype=bool)
        truncations = np.zeros(n, dtype=bool)
        infos: dict[str, Any] = {}
        row_infos: list[dict[str, Any]] = []
        for i in range(n):
            if resetting[i]:
                row_infos.append({})
                continue
            failure = result.failures.get(i)
            info: dict[str, Any] = {"t": float(result.t[i])}
            if failure is not None:
                rewards[i], terminations[i] = task.failure_reward, True
                info.update(failure=failure[0], message=failure[1])
            else:
                rewards[i], terminations[i] = task.outcome(result.q[i], result.v[i], result.tau[i])
            self._elapsed[i] += 1
            truncations[i] = task.max_episode_steps is not None and self._elapsed[i] >= task.max_episode_steps
            row_infos.append(info)
        ended = terminations | truncations
        if resetting.any():
            self._reset_rows(np.flatnonzero(resetting), row_infos)
        if self.autoreset_mode == AutoresetMode.SAME_STEP and ended.any():
            final = self._observations()
            for i in np.flatnonzero(ended).tolist():
                infos = self._add_info(infos, {"final_obs": final[i], "final_info": row_infos[i]}, i)
            self._reset_rows(np.flatnonzero(ended), row_infos)
        for i, info in enumerate(row_infos):
            infos = self._add_info(infos, info, i)
        self._autoreset = ended
        return self._observations(), rewards, terminations, truncations, infos

    @staticmethod
    def _exact_rows(value: Any, key: str, rows: int, size: int) -> np.ndarray | None:
        """options' "q" or "v" for `rows` reset rows as a float array (rows, size), or None when not given."""
        if value is None:
            return None
        name = f"options['{key}']"
        values = real_array(value, name, f"an array of real numbers of shape ({rows}, {size}), one row per reset row")
        if values.shape != (rows, size):
            raise InvalidArgumentError(
                f"{name} must have shape ({rows}, {size}), one row per reset row, got {values.shape}"
            )
        return values

    def _reset_rows(self, rows: np.ndarray, row_infos: list[dict[str, Any]]) -> None:
        """Autoreset: rows start new episodes drawn from their own generators (their infos become reset infos)."""
        states, systems, drawn = [], [], []
        for i in rows.tolist():
            states.append(self.task.initial_state(self._rng(i), None))
            scene, values = self.task.parameters(self._rng(i))
            systems.append(scene)
            drawn.append(values)
        self.stepper.reset(
            rows, np.array([q for q, _ in states]), np.array([v for _, v in states]),
            systems=systems if self.task.randomizer is not None else None,
        )  # fmt: skip
        self._elapsed[rows] = 0
        for i, values in zip(rows.tolist(), drawn, strict=True):
            row_infos[i] = {"t": 0.0, **values}

    def _observations(self) -> np.ndarray:
        stepper = self.stepper
        return self.task.observe(stepper.q, stepper.v, stepper.readings if self.task.sensors is not None else {})


def _check_render_mode(render_mode: Any) -> None:
    if render_mode is not None:
        raise InvalidArgumentError(
            f"render_mode must be None, got {render_mode!r}: the viewer is a meshcat page in a browser, not a frame "
            "source; record the states and view them with multibody_sim.viz (export_html, export_video)"
        )


__all__ = ["MultibodyEnv", "MultibodyVectorEnv"]
