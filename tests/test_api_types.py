"""Every public function checks the types of its arguments: a wrong type is an InvalidArgumentError that names the
argument, never a raw TypeError, ValueError or AttributeError from inside numpy or Pinocchio.

The table below lists, for each public callable, a valid call and the wrong-typed values to put in each argument
(a string where an array or a number is expected, a float where a whole number is, None where a path is, a robot's
name where the robot is). `test_every_public_callable_is_in_the_table` walks `multibody_sim.__all__`, the
submodules' `__all__` and the public methods of the result classes: a new public function without a row (or a
reason to be exempt) fails it.
"""

from __future__ import annotations

import functools
import inspect
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import multibody_sim as ms
import multibody_sim.analysis as analysis
import multibody_sim.bench as bench
import multibody_sim.scenes as scenes


@functools.cache
def robot() -> ms.Robot:
    return ms.load_robot("pendulum")


@functools.cache
def run() -> ms.Trajectory:
    return ms.simulate(robot(), [0.1], [0.0], duration=0.01, dt=1e-3)


@functools.cache
def batch() -> ms.BatchTrajectory:
    return ms.rollout(robot(), [[0.1], [0.2]], [[0.0], [0.0]], duration=0.01, dt=1e-3)


@functools.cache
def study() -> ms.WorkPrecision:
    return ms.work_precision(robot(), [0.1], [0.0], duration=0.02, integrators=["euler"], steps=[0.01, 0.005])


@dataclass(frozen=True)
class Row:
    """One public callable: how to call it validly, and the wrong-typed values to put in its arguments."""

    name: str
    call: Callable[..., Any]
    valid: Callable[[Path], dict[str, Any]]
    bad: dict[str, tuple[Any, ...]]


SYSTEM = ("pendulum", 42, None)  # a robot's name where the robot goes, a number, nothing
ARRAY = ("0.1", ["a"], {"q": 0.1}, None)
NUMBER = ("1", [1.0], None, True)
OPTIONAL_NUMBER = ("1", [1.0], True)
WHOLE = (2.5, "3", True)
PATH = (None, 42, 1.5)
TRAJ = (42, "run.npz", None)
FLAG = ("yes", 1.5)
NAME = (42, None, ["rk4"])
CALLABLE = (42, "pd")


def s(**kwargs: Any) -> Callable[[Path], dict[str, Any]]:
    return lambda tmp: {k: v(tmp) if callable(v) and not isinstance(v, ms.Robot) else v for k, v in kwargs.items()}


def adaptive() -> dict[str, Any]:
    return {"integrator": "dp54", "rtol": 1e-6, "atol": 1e-8}


ROWS = [
    # ---- loading -------------------------------------------------------------------------------------------
    Row(
        "load_robot",
        ms.load_robot,
        s(source="pendulum"),
        {
            "source": (None, 42),
            "floating_base": ("yes",),
            "damping": ("no", None),
            "package_dirs": ("/x", 42),
            "allowed_roots": ("/x", 42),
            "srdf": (42,),
        },
    ),
    Row("load_scene", ms.load_scene, s(path="four_bar"), {"path": PATH, "allowed_roots": ("/x", 42)}),
    Row("make_scene", ms.make_scene, s(robot={"source": "pendulum"}), {"robot": (42, "pendulum")}),
    Row(
        "scenes.scene_from_metadata",
        scenes.scene_from_metadata,
        lambda tmp: {"scene": {"source": "s.toml", "toml": "[robot]\nsource = 'pendulum'\n"}},
        {"scene": (42, None, "[robot]")},
    ),
    Row("get_integrator", ms.get_integrator, s(integrator="rk4"), {"integrator": (42, None)}),
    Row(
        "make_controller",
        ms.make_controller,
        s(name="pd", robot=robot(), params=["kp=1", "q_ref=0"]),
        {"name": NAME, "robot": SYSTEM, "params": (42, "kp=1")},
    ),
    # ---- running -------------------------------------------------------------------------------------------
    Row(
        "simulate",
        ms.simulate,
        s(system=robot(), q0=[0.1], v0=[0.0], duration=0.01, dt=1e-3),
        {
            "system": SYSTEM,
            "q0": ARRAY,
            "v0": ARRAY,
            "duration": NUMBER,
            "dt": NUMBER,
            "integrator": NAME,
            "controller": CALLABLE,
            "out": (42, 1.5),
            "on_sample": CALLABLE,
            "progress": ("yes",),
        },
    ),
    Row(
        "simulate (options)",
        ms.simulate,
        s(system=robot(), q0=[0.1], v0=[0.0], duration=0.01, dt=1e-3, **adaptive()),
        {"rtol": NUMBER, "atol": NUMBER, "max_step": OPTIONAL_NUMBER, "output_dt": OPTIONAL_NUMBER},
    ),
    Row(
        "simulate (chunk)",
        ms.simulate,
        s(system=robot(), q0=[0.1], v0=[0.0], duration=0.01, dt=1e-3, out=lambda tmp: tmp / "c.npz", chunk=5),
        {"chunk": WHOLE},
    ),
    Row(
        "rollout",
        ms.rollout,
        s(system=robot(), q0s=[[0.1]], v0s=[[0.0]], duration=0.01, dt=1e-3),
        {
            "system": SYSTEM,
            "q0s": ARRAY,
            "v0s": ARRAY,
            "duration": NUMBER,
            "dt": NUMBER,
            "integrator": NAME,
            "controller": CALLABLE,
            "taus": ("a", ["a"]),
            "progress": ("yes",),
            "backend": (42,),
            "num_threads": WHOLE,
            "chunk_size": WHOLE,
            "randomize": ("yes", 42, [{"name": "mass"}]),  # a robot: there is no scene to draw
        },
    ),
    Row(
        "Stepper",
        ms.Stepper,
        s(system=robot(), dt=1e-3),
        {
            "system": SYSTEM,
            "dt": NUMBER,
            "integrator": NAME,
            "control_dt": OPTIONAL_NUMBER,
            "q0": ARRAY[:3],
            "v0": ARRAY[:3],
            "t0": NUMBER,
            "check_energy": FLAG,
        },
    ),
    Row("Stepper.step", lambda **kw: ms.Stepper(robot(), dt=1e-3).step(**kw), s(tau=[0.0]), {"tau": ARRAY[:3]}),
    Row(
        "Stepper.advance_to",
        lambda **kw: ms.Stepper(robot(), dt=1e-3).advance_to(**kw),
        s(t=0.002),
        {"t": NUMBER, "controller": CALLABLE},
    ),
    Row(
        "Stepper.reset",
        lambda **kw: ms.Stepper(robot(), dt=1e-3).reset(**kw),
        s(q=[0.1]),
        {"q": ARRAY[:3], "v": ARRAY[:3], "t": OPTIONAL_NUMBER},
    ),
    Row(
        "BatchStepper",
        ms.BatchStepper,
        s(system=robot(), Q0=[[0.1]], V0=[[0.0]], dt=1e-3),
        {
            "system": SYSTEM,
            "Q0": ARRAY,
            "V0": ARRAY,
            "dt": NUMBER,
            "integrator": NAME,
            "check_energy": FLAG,
            "num_threads": WHOLE,
        },
    ),
    Row(
        "BatchStepper.step",
        lambda **kw: ms.BatchStepper(robot(), [[0.1]], [[0.0]], dt=1e-3).step(**kw),
        s(tau=[[0.0]]),
        {"tau": ARRAY},
    ),
    # ---- controllers ---------------------------------------------------------------------------------------
    Row(
        "PD",
        ms.PD,
        s(robot=robot(), q_ref=[0.0], kp=1.0),
        {
            "robot": SYSTEM,
            "q_ref": ARRAY,
            "kp": ARRAY,
            "kd": ARRAY[:3],
            "v_ref": ARRAY[:3],
        },
    ),
    Row("PDGravity", ms.PDGravity, s(robot=robot(), q_ref=[0.0], kp=1.0), {"robot": SYSTEM, "q_ref": ARRAY}),
    Row("GravityCompensation", ms.GravityCompensation, s(robot=robot()), {"robot": SYSTEM}),
    Row(
        "ComputedTorque",
        ms.ComputedTorque,
        s(robot=robot(), times=[0.0, 1.0], waypoints=[[0.0], [0.1]]),
        {
            "robot": SYSTEM,
            "times": ARRAY,
            "waypoints": ARRAY,
            "kp": ARRAY[:3],
            "bc_type": (42,),
        },
    ),
    Row(
        "PotentialField",
        ms.PotentialField,
        s(robot=robot(), goal=[0.5]),
        {
            "robot": SYSTEM,
            "goal": ARRAY,
            "frame": (42,),
            "k_attract": NUMBER,
            "obstacles": (42, "x"),
        },
    ),
    # ---- stability, linearization, bench -------------------------------------------------------------------
    Row(
        "linearization",
        ms.linearization,
        s(system=robot(), q=[0.1], v=[0.0]),
        {"system": SYSTEM, "q": ARRAY, "v": ARRAY, "tau": ARRAY[:3]},
    ),
    Row(
        "linearize",
        ms.linearize,
        s(system=robot(), q=[0.1], v=[0.0], tau=[0.0], dt=1e-3),
        {
            "system": SYSTEM,
            "q": ARRAY,
            "v": ARRAY,
            "tau": ARRAY,
            "dt": NUMBER,
            "integrator": NAME,
            "t": NUMBER,
        },
    ),
    Row(
        "stiffness_ratio",
        ms.stiffness_ratio,
        s(system=robot(), q=[0.1], v=[0.0]),
        {"system": SYSTEM, "q": ARRAY, "v": ARRAY, "decay_tolerance": NUMBER},
    ),
    Row(
        "largest_stable_dt",
        ms.largest_stable_dt,
        s(system=robot(), integrator="euler", q0=[0.1], v0=[0.0], horizon=0.05),
        {
            "system": SYSTEM,
            "integrator": NAME,
            "q0": ARRAY,
            "v0": ARRAY,
            "horizon": NUMBER,
            "dt_max": OPTIONAL_NUMBER,
            "ratio": NUMBER,
            "max_steps": WHOLE,
        },
    ),
    Row(
        "work_precision",
        ms.work_precision,
        s(system=robot(), q0=[0.1], v0=[0.0], duration=0.02, integrators=["euler"], steps=[0.01]),
        {
            "system": SYSTEM,
            "q0": ARRAY,
            "v0": ARRAY,
            "duration": NUMBER,
            "integrators": (42, "euler"),
            "steps": ("0.01", 0.01),
            "repeats": WHOLE,
            "max_steps": WHOLE,
            "progress": CALLABLE,
        },
    ),
    Row(
        "choose_integrator",
        ms.choose_integrator,
        s(system=robot(), q0=[0.1], v0=[0.0], tolerance=1e-3, duration=0.02, cache=False),
        {
            "system": SYSTEM,
            "q0": ARRAY,
            "v0": ARRAY,
            "tolerance": NUMBER,
            "duration": NUMBER,
            "cache": FLAG,
            "cache_dir": (42,),
        },
    ),
    Row(
        "recommend",
        ms.recommend,
        lambda tmp: {"result": study(), "tolerance": 1e-2},
        {"result": (42, None), "tolerance": NUMBER, "cost": (42, "money")},
    ),
    Row(
        "trajectory_error",
        ms.trajectory_error,
        lambda tmp: {"system": robot(), "trajectory": run(), "reference": run()},
        {"system": SYSTEM, "trajectory": TRAJ, "reference": TRAJ},
    ),
    Row(
        "plot_work_precision",
        ms.plot_work_precision,
        lambda tmp: {"result": study(), "path": tmp / "wp.png"},
        {"result": (42, None), "path": PATH, "title": (42,)},
    ),
    Row("bench.observed_orders", bench.observed_orders, lambda tmp: {"result": study()}, {"result": (42, None)}),
    Row(
        "bench.measure_savings",
        bench.measure_savings,
        lambda tmp: {"scene": ms.make_scene(robot={"source": "pendulum"}), "steps": 2, "repeats": 1},
        {"scene": (*SYSTEM, robot()), "steps": WHOLE, "repeats": WHOLE},
    ),
    # ---- trajectories --------------------------------------------------------------------------------------
    Row(
        "Trajectory.load",
        ms.Trajectory.load,
        lambda tmp: {"path": run().save(tmp / "r.npz")},
        {"path": PATH, "mmap": FLAG},
    ),
    Row("Trajectory.save", lambda **kw: run().save(**kw), lambda tmp: {"path": tmp / "r.npz"}, {"path": PATH}),
    Row("Trajectory.concatenate", ms.Trajectory.concatenate, lambda tmp: {"pieces": [run()]}, {"pieces": (42, [42])}),
    Row("BatchTrajectory.element", lambda **kw: batch().element(**kw), s(b=1), {"b": WHOLE}),
    # ---- analysis ------------------------------------------------------------------------------------------
    Row("analysis.frame_names", analysis.frame_names, s(robot=robot()), {"robot": SYSTEM}),
    Row(
        "analysis.frame_placements",
        analysis.frame_placements,
        lambda tmp: {"robot": robot(), "traj": run(), "frame": "base"},
        {"robot": SYSTEM, "traj": TRAJ, "frame": (42, None)},
    ),
    Row(
        "analysis.frame_velocities",
        analysis.frame_velocities,
        lambda tmp: {"robot": robot(), "traj": run(), "frame": "base"},
        {"robot": SYSTEM, "traj": TRAJ, "frame": (42, None)},
    ),
    Row(
        "analysis.center_of_mass",
        analysis.center_of_mass,
        lambda tmp: {"robot": robot(), "traj": run()},
        {"robot": SYSTEM, "traj": TRAJ},
    ),
    Row(
        "analysis.center_of_mass_velocity",
        analysis.center_of_mass_velocity,
        lambda tmp: {"robot": robot(), "traj": run()},
        {"robot": SYSTEM, "traj": TRAJ},
    ),
    Row(
        "analysis.centroidal_momentum",
        analysis.centroidal_momentum,
        lambda tmp: {"robot": robot(), "traj": run()},
        {"robot": SYSTEM, "traj": TRAJ},
    ),
    # ---- the robot's dynamics ------------------------------------------------------------------------------
    *[
        Row(
            f"Robot.{method}",
            lambda method=method, **kw: getattr(robot(), method)(**kw),
            s(**{name: [0.1] for name in names}),
            {name: ARRAY for name in names},
        )
        for method, names in [
            ("mass_matrix", ["q"]),
            ("gravity", ["q"]),
            ("potential_energy", ["q"]),
            ("coriolis_matrix", ["q", "v"]),
            ("nonlinear_effects", ["q", "v"]),
            ("kinetic_energy", ["q", "v"]),
            ("total_energy", ["q", "v"]),
            ("forward_dynamics", ["q", "v", "tau"]),
            ("inverse_dynamics", ["q", "v", "a"]),
            ("integrate", ["q", "dv"]),
            ("difference", ["q0", "q1"]),
        ]
    ],
    Row("Robot.pose", lambda **kw: robot().pose(**kw), None, {"name": (42, None)}),
    Row(
        "Robot.random_configuration", lambda **kw: robot().random_configuration(**kw), s(rng=1), {"rng": ("seed", 2.5)}
    ),
    # ---- viewing -------------------------------------------------------------------------------------------
    Row(
        "viz.export_html",
        lambda **kw: _viz().export_html(**kw),
        lambda tmp: {"trajectory": run(), "path": tmp / "x.html"},
        {
            "trajectory": TRAJ,
            "path": PATH,
            "robot": ("pendulum", 42),
            "fps": NUMBER,
            "speed": NUMBER,
            "loop": FLAG,
            "plot": FLAG,
            "title": (42,),
        },
    ),
    Row(
        "viz.inline_view",
        lambda **kw: _viz().inline_view(**kw),
        lambda tmp: {"trajectory": run()},
        {
            "trajectory": TRAJ,
            "robot": ("pendulum", 42),
            "fps": NUMBER,
            "speed": NUMBER,
            "height": WHOLE,
            "plot": FLAG,
        },
    ),
    Row(
        "viz.resample",
        lambda **kw: _viz().resample(**kw),
        lambda tmp: {"robot": robot(), "trajectory": run()},
        {"robot": SYSTEM, "trajectory": TRAJ, "fps": NUMBER},
    ),
    Row(
        "viz.frame_times",
        lambda **kw: _viz().frame_times(**kw),
        s(t_start=0.0, t_end=1.0, fps=30.0),
        {"t_start": NUMBER, "t_end": NUMBER, "fps": NUMBER},
    ),
    Row(
        "viz.robot_from_trajectory",
        lambda **kw: _viz().robot_from_trajectory(**kw),
        lambda tmp: {"trajectory": run()},
        {"trajectory": TRAJ},
    ),
    Row(
        "viz.plot_trajectory",
        lambda **kw: _viz().plot_trajectory(**kw),
        lambda tmp: {"trajectory": run(), "path": tmp / "p.png"},
        {
            "trajectory": TRAJ,
            "path": (42, 1.5),
            "robot": ("pendulum", 42),
            "joints": (42,),
            "title": (42,),
            "dpi": WHOLE,
        },
    ),
    Row(
        "viz.plot_png",
        lambda **kw: _viz().plot_png(**kw),
        lambda tmp: {"trajectory": run()},
        {"trajectory": TRAJ, "robot": ("pendulum", 42)},
    ),
    Row(
        "viz.plot_command",
        lambda **kw: _viz().plot_command(**kw),
        lambda tmp: {"trajectory": run()},
        {"trajectory": TRAJ, "robot": ("pendulum", 42)},
    ),
    Row(
        "viz.MeshcatServer",
        lambda **kw: _viz().MeshcatServer(**kw),
        None,
        {"host": (42,), "port": WHOLE, "title": (42,)},
    ),
    Row("viz.Viewer", lambda **kw: _viz().Viewer(**kw), None, {"robot": SYSTEM, "host": (42,), "port": WHOLE}),
    Row("viz.RobotScene", lambda **kw: _viz().RobotScene(**kw), None, {"robot": SYSTEM}),
    Row(
        "gym.MultibodyEnv",
        lambda **kw: _gym().MultibodyEnv(**kw),
        lambda tmp: {"system": robot(), "reward": lambda q, v, tau: 0.0, "control_dt": 0.01},
        {
            "system": SYSTEM,
            "reward": CALLABLE,
            "terminated": CALLABLE,
            "max_episode_steps": WHOLE,
            "control_dt": ("1", [1.0], True),  # None: the default (a scene's, else dt)
            "initial_q": ARRAY[:3],
            "reset_noise_q": NUMBER,
            "failure_reward": NUMBER[:2],
            "randomize": ("yes", 42),
        },
    ),
    Row(
        "gym.MultibodyVectorEnv",
        lambda **kw: _gym().MultibodyVectorEnv(**kw),
        lambda tmp: {"system": robot(), "num_envs": 2, "reward": lambda q, v, tau: 0.0, "control_dt": 0.01},
        {"system": SYSTEM, "num_envs": WHOLE, "reward": CALLABLE, "num_threads": WHOLE},
    ),
    Row(
        "viz.export_video",
        lambda **kw: _viz().export_video(**kw),
        None,
        {
            "trajectory": TRAJ,
            "path": PATH,
            "fps": NUMBER,
            "speed": NUMBER,
            "width": WHOLE,
            "height": WHOLE,
            "camera": (42,),
            "camera_position": ("top", [1, 2]),
            "camera_target": ("x",),
        },
    ),
]


def _viz() -> Any:
    pytest.importorskip("meshcat")
    import multibody_sim.viz as viz

    return viz


def _gym() -> Any:
    pytest.importorskip("gymnasium")
    import multibody_sim.gym as gym

    return gym


def _cases() -> list[tuple[Row, str, Any]]:
    return [(row, argument, value) for row in ROWS for argument, values in row.bad.items() for value in values]


def _id(case: tuple[Row, str, Any]) -> str:
    row, argument, value = case
    return f"{row.name}-{argument}={value!r}"[:90]


@pytest.mark.parametrize("case", _cases(), ids=_id)
def test_a_wrong_type_is_an_invalid_argument_naming_it(case: tuple[Row, str, Any], tmp_path: Path) -> None:
    row, argument, value = case
    kwargs = row.valid(tmp_path) if row.valid is not None else {}
    for required in _required(row, kwargs):
        kwargs.setdefault(required, _filler(required, tmp_path))
    kwargs[argument] = value
    with pytest.raises(ms.InvalidArgumentError) as info:
        row.call(**kwargs)
    message = str(info.value).lower().replace("_", " ")
    named = {argument.lower().replace("_", " "), argument.lower().rstrip("s")}  # "q0s" may be named per element
    assert any(name in message for name in named), f"the message does not name '{argument}': {info.value}"


def _required(row: Row, kwargs: dict[str, Any]) -> list[str]:
    """Arguments a row without a valid call still needs (so that the bad one is the only problem)."""
    if row.valid is not None:
        return []
    return {
        "Robot.pose": [],
        "viz.MeshcatServer": [],
        "viz.Viewer": ["robot"],
        "viz.RobotScene": ["robot"],
        "viz.export_video": ["trajectory", "path"],
    }.get(row.name, [])


def _filler(name: str, tmp: Path) -> Any:
    return {"robot": robot(), "trajectory": run(), "path": tmp / "x.mp4"}[name]


@pytest.mark.parametrize("row", [row for row in ROWS if row.valid is not None], ids=lambda row: row.name)
def test_the_valid_calls_of_the_table_work(row: Row, tmp_path: Path) -> None:
    """The table's valid calls succeed: each refusal above is the bad argument's doing."""
    if row.name.startswith("viz."):
        _viz()
    result = row.call(**row.valid(tmp_path))
    if isinstance(result, _viz_server_types()):
        result.close()


def test_a_batch_is_not_a_trajectory() -> None:
    """A BatchTrajectory where one trajectory goes is refused in one line (its arrays have a leading batch axis:
    trajectory_error raised a raw TypeError on one, the plots a ValueError)."""
    with pytest.raises(ms.InvalidArgumentError, match="^trajectory must be a Trajectory, got BatchTrajectory$"):
        ms.trajectory_error(robot(), batch(), run())


def _viz_server_types() -> tuple[type, ...]:
    try:
        import multibody_sim.viz as viz
    except ImportError:
        return ()
    return (viz.Viewer, viz.MeshcatServer)


# Public callables that take no argument a caller could get wrong, or whose arguments are the documented
# fast path with no checks (the stepping core's `unchecked_*`), or result classes built by the package.
EXEMPT = {
    "catalog_table": "no arguments",
    "bench.default_cache_dir": "no arguments",
    "scenes.shipped_scenes": "no arguments",
    "viz.InlineView": "built by inline_view",
}


def public_callables() -> set[str]:
    """Names of the public functions and classes a user calls: multibody_sim.__all__, the submodules' __all__ (and
    analysis's public functions), without exceptions, warnings, registries and result dataclasses."""
    import multibody_sim.viz as viz

    found: dict[int, str] = {}  # by object: a function exported at the top and in its module counts once
    for prefix, module, names in [
        ("", ms, ms.__all__),
        ("bench.", bench, bench.__all__),
        ("scenes.", scenes, scenes.__all__),
        ("viz.", viz, viz.__all__),
        ("analysis.", analysis, [n for n in dir(analysis) if not n.startswith("_")]),
        *([("gym.", _gym(), _gym().__all__)] if _has("gymnasium") else []),
    ]:
        for name in names:
            obj = getattr(module, name)
            if inspect.ismodule(obj) or not callable(obj):
                continue
            if prefix == "analysis." and getattr(obj, "__module__", "") != analysis.__name__:
                continue
            if inspect.isclass(obj) and (issubclass(obj, (BaseException, Warning)) or _is_record(obj)):
                continue
            found.setdefault(id(obj), prefix + name)
    return set(found.values())


def _has(module: str) -> bool:
    import importlib.util

    return importlib.util.find_spec(module) is not None


def _is_record(cls: type) -> bool:
    """A result or record class (dataclasses the package builds: Trajectory, Measurement, ...), or an abstract
    base users subclass (Integrator): its constructor is not where users pass arguments."""
    import dataclasses

    return (
        dataclasses.is_dataclass(cls)
        or issubclass(cls, tuple)
        or inspect.isabstract(cls)
        or cls.__name__
        in {
            "Integrator",
            "ExplicitRungeKutta",
            "ButcherTableau",
            "Scene",
            "Robot",
            "SceneSpec",
        }
    )


def test_every_public_callable_is_in_the_table() -> None:
    covered = {row.name.split(" (")[0] for row in ROWS} | set(EXEMPT)
    missing = sorted(public_callables() - covered)
    assert not missing, f"public callables without a row in test_api_types.ROWS (or a reason in EXEMPT): {missing}"


def test_trajectory_load_of_none_names_the_path() -> None:
    with pytest.raises(ms.InvalidArgumentError, match="^path must be a path to a trajectory file .*, got NoneType$"):
        ms.Trajectory.load(None)  # type: ignore[arg-type]


def test_numpy_arrays_and_numpy_numbers_are_accepted() -> None:
    """Type checks accept what numpy users hold: arrays, np.float64, np.int64."""
    traj = ms.simulate(robot(), np.array([0.1]), np.zeros(1), duration=np.float64(0.01), dt=np.float64(1e-3))
    assert traj.status == "completed"
    assert ms.rollout(robot(), np.zeros((2, 1)), np.zeros((2, 1)), duration=0.01, dt=1e-3, num_threads=np.int64(1))
