"""Benchmark of the stepping loop's per-step cost against its Pinocchio floor and MuJoCo.

Writes docs/step_cost.md. For each robot, in one run and round-robin (the machine is shared and noisy, so each
figure is a median over rounds in which every variant was timed once, under the same conditions):

- ``simulate`` with zero torque from a random state, per integrator: µs/step from the process's CPU time of
  the whole call (minus the fixed per-call cost), beside the wall time of the loop (``stats["wall_time"]``)
  and of the whole call;
- the floor: 4 × ``pin.aba`` (WORLD convention) + 4 × ``pin.integrate`` per step in a tight Python loop;
- MuJoCo as a peer on the same URDF (RK4, dt = 1 ms, what Pinocchio does not model disabled): ``mj_step``
  in a Python loop and ``mujoco.rollout``, plus a check that MuJoCo's accelerations equal Pinocchio's.

The native kernel (the C++ loop that `simulate` and `rollout` take when the extension is built) is timed in its own
section: `simulate` RK4 per step and `rollout` (B rows, one thread) per state-step, against a floor measured in the
same rounds, 4 × one ``pin.abaInParallel`` call over B = 1000 states on one thread, per state (what C++ ABA costs
per state), and against MuJoCo's ``mj_step`` RK4 and ``mujoco.rollout`` over the same B states. The integrator
columns of the first table run the Python kernel (``MULTIBODY_SIM_NATIVE=0``), whose loop the parts break down.

Then it breaks one RK4 step into its parts (the Pinocchio calls and the robot's hot-path methods timed alone,
and a cProfile of one robot's loop) and writes the report. MuJoCo is optional (``pip install mujoco``; a
benchmark-only dependency): without it those columns are skipped with a note.

Usage:
    .venv/bin/python scripts/bench_step_cost.py [--repeats 31] [--steps 500] [--out docs/step_cost.md]
"""

from __future__ import annotations

import argparse
import contextlib
import cProfile
import datetime
import gc
import io
import math
import os
import platform
import pstats
import statistics
import sys
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from multibody_sim import INTEGRATORS, load_robot, native, rollout, simulate

sys.path.insert(0, str(Path(__file__).resolve().parent))
from mujoco_peer import StateMap, mj_set_state  # noqa: E402, F401  (the shared MuJoCo peer; re-exported for siblings)
from mujoco_peer import mujoco_model as peer_model  # noqa: E402

try:
    import mujoco
except ImportError:  # a benchmark-only dependency: the report says it was skipped
    mujoco = None

try:
    from mujoco import rollout as mj_rollout
except ImportError:
    mj_rollout = None

ROBOTS = ("double_pendulum", "ur5", "panda", "solo12", "talos")
METHODS = ("euler", "semi_implicit_euler", "midpoint", "rk4")
DT = 1e-3
SEED = 0
V0_SCALE = 0.1  # "small random v0": standard deviation of the Gaussian velocity [rad/s, m/s]
PROFILED_ROBOT = "solo12"  # a floating base exercises every part of the RK step, the chart map included
PROFILED_STEPS = 2000
FLOOR_STATES = 1000  # abaInParallel's batch for the native floor
ROLLOUT_B = 256  # rows of the timed rollouts (ours and MuJoCo's)
ROLLOUT_STEPS = 50
_WORLD = pin.Convention.WORLD
ROOT = Path(__file__).resolve().parent.parent

Profile = tuple[str, float, int, list[tuple[str, int, float]]]  # robot, total [s], steps, (function, calls, share)


def para(text: str) -> str:
    """One Markdown paragraph from a wrapped triple-quoted string (whitespace runs become single spaces)."""
    return " ".join(text.split())


def median(values: list[float]) -> float:
    return statistics.median(values) if values else math.nan


def fmt(x: float | None, digits: int = 1) -> str:
    if x is None or math.isnan(x):
        return "—"
    return f"{x:.{digits}f}"


@dataclass
class Samples:
    """Per-round measurements of one robot: CPU time of this process unless stated, µs per step.

    CPU time is the headline because the machine is time-shared: wall time also counts the time other
    processes held the core. The stepping loop's own wall time (stats["wall_time"]) is kept alongside.
    """

    call: dict[str, list[float]] = field(default_factory=dict)  # whole simulate() call / steps, per method
    fixed_ms: dict[str, list[float]] = field(default_factory=dict)  # a one-step call: the fixed cost [ms]
    stats_wall: dict[str, list[float]] = field(default_factory=dict)  # stats["wall_time"] / steps (wall)
    call_wall: dict[str, list[float]] = field(default_factory=dict)  # whole call / steps (wall)
    rk4_sparse: list[float] = field(default_factory=list)  # rk4 with output_dt = 10 dt, whole call / steps
    floor: list[float] = field(default_factory=list)
    mj_step: list[float] = field(default_factory=list)
    mj_rollout: list[float] = field(default_factory=list)
    cpu_share: list[float] = field(default_factory=list)  # CPU time / wall time of the timed calls
    native: list[float] = field(default_factory=list)  # native simulate rk4, whole call / steps
    native_fixed_ms: list[float] = field(default_factory=list)  # a one-step native call [ms]
    floor_batch: list[float] = field(default_factory=list)  # 4 × abaInParallel per state
    native_rollout: list[float] = field(default_factory=list)  # rollout rk4 per state-step
    native_rollout_sparse: list[float] = field(default_factory=list)  # ... recording every 10th step
    mj_rollout_batch: list[float] = field(default_factory=list)  # mujoco.rollout over ROLLOUT_B states, per state-step

    def native_loop(self, steps: int) -> float:
        """CPU µs per step of the native loop: the call's cost minus its fixed per-call cost."""
        return median(self.native) - median(self.native_fixed_ms) * 1e3 / steps

    def loop(self, method: str, steps: int) -> float:
        """CPU µs per step of the stepping loop: the call's cost minus its fixed per-call cost."""
        return median(self.call[method]) - median(self.fixed_ms[method]) * 1e3 / steps

    def loop_sparse(self, steps: int) -> float:
        return median(self.rk4_sparse) - median(self.fixed_ms["rk4"]) * 1e3 / steps


@dataclass
class RobotResult:
    """Everything the report shows for one robot."""

    name: str
    nq: int
    nv: int
    floating: bool
    samples: Samples
    parts: dict[str, float] = field(default_factory=dict)  # the parts of one RK4 step, timed alone [µs/step]
    extras: dict[str, float] = field(default_factory=dict)  # related costs, not in the parts' sum [µs/step]
    qacc_error: float = math.nan  # max |qacc_MuJoCo - a_Pinocchio| at (q0, v0)
    qacc_scale: float = math.nan  # max |a_Pinocchio|
    final_state_error: float = math.nan  # max |state difference| after the same RK4 steps, ours vs MuJoCo


# ---- MuJoCo: the same URDF, the same dynamics --------------------------------------------------------------
def mujoco_model(robot: Any) -> Any:
    """The MuJoCo peer (scripts/mujoco_peer.py) with RK4 at the same 1 ms step."""
    model = peer_model(robot)
    model.opt.integrator = int(mujoco.mjtIntegrator.mjINT_RK4)
    model.opt.timestep = DT
    return model


# ---- the free-flyer chart map's accuracy ---------------------------------------------------------------------
_BERNOULLI = (1.0, -1 / 2, 1 / 6, 0.0, -1 / 30, 0.0, 1 / 42, 0.0, -1 / 30, 0.0, 5 / 66, 0.0, -691 / 2730, 0.0, 7 / 6)
THETAS = np.logspace(-6, -1, 21)  # the sweep's stage-twist sizes
EVERYDAY_THETA = 1e-3  # an RK4 stage at dt = 1 ms has θ ≈ 0.5–1 ms × the base's speed
ROUND_OFF = 1000 * np.finfo(float).eps  # errors below this are not fitted: round-off, not truncation
RK4_TERMS = INTEGRATORS["rk4"].chart_terms  # the series' last power each method keeps
DOP853_TERMS = INTEGRATORS["dop853"].chart_terms
SERIES_RK4 = f"chart_velocity(xi, v, {RK4_TERMS})"
SERIES_DOP853 = f"chart_velocity(xi, v, {DOP853_TERMS})"
CLOSED_FORM = "Jlog6(exp6(xi))"
IN_USE = "chart_velocity inside rk4 runs"
IN_USE_JLOG = "Jlog6(exp6(xi)) on the same stages"


@dataclass
class ChartError:
    """One row of the chart map's accuracy table: errors per unit velocity against the 15-term series."""

    kept: str  # what the map computes: "A²" for the series kept up to A², or "closed form"
    worst: float
    theta: float  # where the worst error was (|xi|)
    everyday: float = math.nan  # worst for θ ≤ EVERYDAY_THETA (sweep rows only)
    order: float | None = None  # slope of log(worst error) against log θ where above ROUND_OFF (≥ 3 points)
    calls: int = 0  # chart maps checked (in-use rows only)


def _power(k: int) -> str:
    return "A" + str(k).translate(str.maketrans("0123456789", "⁰¹²³⁴⁵⁶⁷⁸⁹"))


def _hat(x: np.ndarray) -> np.ndarray:
    return np.array([[0.0, -x[2], x[1]], [x[2], 0.0, -x[0]], [-x[1], x[0], 0.0]])


def inverse_right_jacobian_series(xi: np.ndarray) -> np.ndarray:
    """J_r(xi)^-1 of SE(3) for a small twist xi = (linear, angular), by its Bernoulli series Σ B_n (-ad)^n / n!.

    Written here apart from the package's truncated series and Pinocchio's closed forms (its own ad and
    coefficients), and accurate to round-off for |xi| ≤ 0.1 with these 15 terms.
    """
    ad = np.zeros((6, 6))
    ad[:3, :3] = ad[3:, 3:] = _hat(xi[3:])
    ad[:3, 3:] = _hat(xi[:3])
    result, power = np.zeros((6, 6)), np.eye(6)
    for n, b in enumerate(_BERNOULLI):
        result += (b / math.factorial(n)) * power
        power = -power @ ad
    return result


def chart_map_accuracy(robot: Any, seed: int = SEED) -> dict[str, ChartError]:
    """Errors [per unit velocity] of free-flyer chart rates against the 15-term series, over a θ sweep.

    Rows: the package's series truncated as rk4 uses it (after A², the truncation being the error by design) and
    as dop853 uses it (after A⁶), and Pinocchio's closed form. Both the translation and rotation parts of the stage
    twist xi have norm θ, swept over 1e-6 … 1e-1; an RK4 stage at dt = 1 ms has θ ≈ 1e-3 · |v| to 5e-4 · |v|.
    """
    rng = np.random.default_rng(seed)
    space = robot.space
    maps: dict[str, tuple[str, Callable[[np.ndarray, np.ndarray], np.ndarray]]] = {
        SERIES_RK4: (_power(RK4_TERMS), lambda xi, v: space.chart_velocity(xi, v, RK4_TERMS)[:6]),
        SERIES_DOP853: (_power(DOP853_TERMS), lambda xi, v: space.chart_velocity(xi, v, DOP853_TERMS)[:6]),
        CLOSED_FORM: ("closed form (Pinocchio)", lambda xi, v: pin.Jlog6(pin.exp6(xi[:6])) @ v[:6]),
    }
    errors = {name: np.zeros(len(THETAS)) for name in maps}  # worst per θ
    for i, theta in enumerate(THETAS):
        for _ in range(10):
            xi = np.zeros(robot.nv)
            xi[:3], xi[3:6] = rng.normal(size=3), rng.normal(size=3)
            xi[:3] *= theta / np.linalg.norm(xi[:3])
            xi[3:6] *= theta / np.linalg.norm(xi[3:6])
            v = rng.normal(size=robot.nv)
            v /= np.max(np.abs(v[:6]))
            reference = inverse_right_jacobian_series(xi[:6]) @ v[:6]
            for name, (_, rates) in maps.items():
                errors[name][i] = max(errors[name][i], float(np.max(np.abs(rates(xi, v) - reference))))
    rows = {}
    for name, (kept, _) in maps.items():
        err = errors[name]
        fitted = err > ROUND_OFF
        order = None
        if name != CLOSED_FORM and fitted.sum() >= 3:  # a power law is expected of the truncated series only
            order = float(np.polyfit(np.log(THETAS[fitted]), np.log(err[fitted]), 1)[0])
        worst = int(np.argmax(err))
        everyday = float(err[THETAS <= EVERYDAY_THETA * (1 + 1e-9)].max())
        rows[name] = ChartError(kept, float(err[worst]), float(THETAS[worst]), everyday, order)
    return rows


def chart_map_in_use(robot: Any, steps: int = 200, seed: int = SEED) -> dict[str, ChartError]:
    """Worst error of the chart rates the rk4 integrator actually uses, against the series (and where); and
    of the closed form Jlog6 on the same stages.

    Wraps the robot's own `space.chart_velocity` for a few runs in which the base spins at 0.3, 0.6 and 1.2
    rad/s, so that the stage twists sweep θ ≈ 1.5e-4 … 1.2e-3 at dt = 1 ms. In a stage the velocity is
    nearly parallel to the twist, unlike the general-position sweep of chart_map_accuracy.
    """
    space = robot.space
    original = space.chart_velocity
    worst = {IN_USE: (0.0, 0.0), IN_USE_JLOG: (0.0, 0.0)}
    terms_seen: set[int] = set()
    calls = 0

    def checked(xi: np.ndarray, v: np.ndarray, terms: int) -> np.ndarray:
        nonlocal calls
        rates = original(xi, v, terms)
        calls += 1
        terms_seen.add(terms)
        reference = inverse_right_jacobian_series(xi[:6]) @ v[:6]
        theta = float(np.linalg.norm(xi[3:6]))
        for name, candidate in ((IN_USE, rates[:6]), (IN_USE_JLOG, pin.Jlog6(pin.exp6(xi[:6])) @ v[:6])):
            error = float(np.max(np.abs(candidate - reference)))
            if error > worst[name][0]:
                worst[name] = (error, theta)
        return rates

    rng = np.random.default_rng(seed)
    space.chart_velocity = checked  # an instance attribute shadows the method for these runs only
    try:
        for speed in (0.3, 0.6, 1.2):
            q0 = robot.random_configuration(rng)
            v0 = rng.normal(size=robot.nv)
            v0[3:6] *= speed / np.linalg.norm(v0[3:6])
            simulate(robot, q0, v0, duration=steps * DT, dt=DT, integrator="rk4")
    finally:
        del space.chart_velocity
    if not calls:  # the loop no longer goes through chart_velocity: these rows would be empty, not good news
        raise RuntimeError("rk4 runs made no chart_velocity call: update chart_map_in_use")
    kept = ", ".join(_power(k) for k in sorted(terms_seen))
    return {
        IN_USE: ChartError(kept, *worst[IN_USE], calls=calls),
        IN_USE_JLOG: ChartError("closed form (Pinocchio)", *worst[IN_USE_JLOG], calls=calls),
    }


# ---- timed pieces ------------------------------------------------------------------------------------------
def time_simulate(
    robot: Any, q0: np.ndarray, v0: np.ndarray, steps: int, method: str, *, kernel: str = "python", **options: Any
) -> tuple[float, float, float]:
    """(CPU µs/step of the whole call, wall µs/step of the whole call, stats["wall_time"] µs/step) on the Python
    kernel or the native one (`kernel`)."""
    with kernel_env(kernel):
        wall0, cpu0 = time.perf_counter(), time.process_time()
        traj = simulate(robot, q0, v0, duration=steps * DT, dt=DT, integrator=method, **options)
        cpu, wall = time.process_time() - cpu0, time.perf_counter() - wall0
    expected = "native" if kernel == "native" else "python (row)"
    if traj.metadata["kernel"] != expected:  # a figure under the wrong name would be worse than none
        raise RuntimeError(f"simulate ran the {traj.metadata['kernel']} kernel, not the {expected} one")
    n = traj.stats["steps"]
    return cpu / n * 1e6, wall / n * 1e6, traj.stats["wall_time"] / n * 1e6


@contextlib.contextmanager
def kernel_env(kernel: str) -> Iterator[None]:
    """Runs inside take the Python kernel or the native one (MULTIBODY_SIM_NATIVE), as before afterwards."""
    before = os.environ.get(native.ENV)
    os.environ[native.ENV] = "1" if kernel == "native" else "0"
    try:
        yield
    finally:
        if before is None:
            del os.environ[native.ENV]
        else:
            os.environ[native.ENV] = before


def time_native_rollout(robot: Any, Q0: np.ndarray, V0: np.ndarray, steps: int, **options: Any) -> float:
    """CPU µs per state-step of a native rk4 rollout (one thread; output every step, energies logged, unless
    options say otherwise)."""
    with kernel_env("native"):
        cpu0 = time.process_time()
        batch = rollout(robot, Q0, V0, duration=steps * DT, dt=DT, integrator="rk4", progress=False, **options)
        cpu = time.process_time() - cpu0
    if batch.metadata["kernel"] != "native":
        raise RuntimeError(f"rollout ran the {batch.metadata['kernel']} kernel, not the native one")
    return cpu / (len(Q0) * steps) * 1e6


def time_floor_batch(robot: Any, pool: Any, Q: np.ndarray, V: np.ndarray, out: np.ndarray) -> float:
    """µs per state of 4 × one pin.abaInParallel call over the states (columns of Q, V), one thread: what an
    RK4 step's four ABA passes cost in C++ per state."""
    tau = np.zeros_like(V)
    start = time.process_time()
    for _ in range(4):
        pin.abaInParallel(1, pool, Q, V, tau, out)
    return (time.process_time() - start) / Q.shape[1] * 1e6


def time_mj_rollout_batch(model: Any, data: Any, states0: np.ndarray, steps: int) -> float:
    """µs per state-step of mujoco.rollout over many initial states (one thread, every state recorded)."""
    start = time.process_time()
    mj_rollout.rollout(model, data, states0, nstep=steps)
    return (time.process_time() - start) / (len(states0) * steps) * 1e6


def time_floor(robot: Any, q: np.ndarray, v: np.ndarray, steps: int) -> float:
    """µs per step of 4 aba + 4 integrate, the Pinocchio calls an RK4 step cannot avoid (unrolled)."""
    model, data, tau, dv = robot.model, robot.data, np.zeros(robot.nv), v * DT
    aba, integrate = pin.aba, pin.integrate
    start = time.process_time()
    for _ in range(steps):
        aba(model, data, q, v, tau, _WORLD)
        aba(model, data, q, v, tau, _WORLD)
        aba(model, data, q, v, tau, _WORLD)
        aba(model, data, q, v, tau, _WORLD)
        integrate(model, q, dv)
        integrate(model, q, dv)
        integrate(model, q, dv)
        integrate(model, q, dv)
    return (time.process_time() - start) / steps * 1e6


def time_mj_step(model: Any, data: Any, qpos: np.ndarray, qvel: np.ndarray, steps: int) -> float:
    """µs per mj_step (RK4) in a Python loop, from (qpos, qvel)."""
    mj_set_state(model, data, qpos, qvel)
    step = mujoco.mj_step
    start = time.process_time()
    for _ in range(steps):
        step(model, data)
    return (time.process_time() - start) / steps * 1e6


def time_mj_rollout(model: Any, data: Any, state0: np.ndarray, steps: int) -> float:
    """µs per step of mujoco.rollout (one trajectory, one thread, its output allocation included)."""
    start = time.process_time()
    mj_rollout.rollout(model, data, state0[None, :], nstep=steps)
    return (time.process_time() - start) / steps * 1e6


class PartTimer:
    """Cost of each call an RK4 step makes, timed alone, times its count per step [µs/step]; and extras.

    An RK4 step makes 4 forward-dynamics calls, 4 integrate calls (3 stages and the update), 4 ledger-power
    calls, 3 chart-velocity maps on a floating base (stages 2 to 4), and the loop records energies every step
    (the default output). The extras are related costs (other ways to compute the same energies and chart
    rates), so the report can say whether a change would pay. Timed
    once per round of the main measurement, so that both see the same machine.
    """

    def __init__(self, robot: Any, q: np.ndarray, v: np.ndarray):
        self.calls, self.extras = _part_calls(robot, q, v)
        self.runs: dict[str, list[float]] = {label: [] for label in [*self.calls, *self.extras]}

    def time_round(self, reps: int) -> None:
        for label, (_, fn) in [*self.calls.items(), *self.extras.items()]:
            start = time.process_time()
            for _ in range(reps):
                fn()
            self.runs[label].append((time.process_time() - start) / reps * 1e6)

    def costs(self) -> tuple[dict[str, float], dict[str, float]]:
        """(parts, extras) in µs per RK4 step: medians over rounds × calls per step."""
        parts = {label: count * median(self.runs[label]) for label, (count, _) in self.calls.items()}
        extras = {label: count * median(self.runs[label]) for label, (count, _) in self.extras.items()}
        return parts, extras


Calls = dict[str, tuple[int, Callable[[], Any]]]
CHART_CLOSED_FORM_COST = "chart rates, closed form"  # Jlog6(exp6(xi)) on rk4's 3 chart maps per step


def _part_calls(robot: Any, q: np.ndarray, v: np.ndarray) -> tuple[Calls, Calls]:
    model, data, tau, dv, space = robot.model, robot.data, np.zeros(robot.nv), v * DT, robot.space
    power = np.empty(len(robot.ledger_elements))
    try:
        robot.ledger_power(q, v, tau, out=power)
        ledger_power: Callable[[], Any] = lambda: robot.ledger_power(q, v, tau, out=power)  # noqa: E731
    except TypeError:  # an older signature without `out`
        ledger_power = lambda: robot.ledger_power(q, v, tau)  # noqa: E731

    def energies_one_pass() -> tuple[float, float]:
        pin.forwardKinematics(model, data, q, v)
        return pin.computeKineticEnergy(model, data), pin.computePotentialEnergy(model, data)

    calls: Calls = {
        "4 × pin.aba": (4, lambda: pin.aba(model, data, q, v, tau, _WORLD)),
        "4 × pin.integrate": (4, lambda: pin.integrate(model, q, dv)),
        "4 × ledger_power": (4, ledger_power),
        "1 × energies (record)": (1, lambda: robot.unchecked_energies(q, v)),
    }
    extras: Calls = {"energies, one kinematics pass": (1, energies_one_pass)}
    if not space.is_flat:
        calls["3 × chart_velocity"] = (3, lambda: space.chart_velocity(dv, v, RK4_TERMS))
        free = [(a, b) for a, b in space.curved_blocks if b - a == 6 and robot.floating_base and a == 0]
        if free == list(space.curved_blocks):  # only a free-flyer: its chart Jacobian has a closed-form inverse

            def chart_closed_form() -> np.ndarray:
                rates = v.copy()
                rates[:6] = pin.Jlog6(pin.exp6(dv[:6])) @ v[:6]
                return rates

            extras[CHART_CLOSED_FORM_COST] = (3, chart_closed_form)
    return calls, extras


def time_numpy_op(n: int, reps: int = 20000) -> float:
    """µs of one small-array numpy operation (`x * c` and `y += x`, averaged) on arrays of n floats."""
    x, y = np.ones(n), np.ones(n)
    runs = []
    for _ in range(7):
        start = time.process_time()
        for _ in range(reps):
            x * 0.5  # noqa: B018  # the allocation is what is timed
            y += x
        runs.append((time.process_time() - start) / (2 * reps) * 1e6)
    return statistics.median(runs)


def profile_rk4(robot: Any, q0: np.ndarray, v0: np.ndarray, steps: int) -> tuple[float, list[tuple[str, int, float]]]:
    """cProfile of one rk4 simulate(): (total own time [s], top [(function, calls, share of own time)])."""
    gc.collect()
    profiler = cProfile.Profile()
    profiler.enable()
    simulate(robot, q0, v0, duration=steps * DT, dt=DT, integrator="rk4")
    profiler.disable()
    entries = pstats.Stats(profiler, stream=io.StringIO()).stats  # type: ignore[attr-defined]
    total = sum(entry[2] for entry in entries.values())
    rows = []
    for (filename, _, func), (_, ncalls, tottime, _, _) in entries.items():
        label = f"{Path(filename).name}:{func}" if filename != "~" else func
        rows.append((label, ncalls, tottime / total if total else 0.0))
    rows.sort(key=lambda row: -row[2])
    return total, rows[:10]


def profile_call_overhead(robot: Any, q0: np.ndarray, v0: np.ndarray, calls: int = 20) -> str:
    """A sentence on what dominates simulate()'s fixed per-call cost (cProfile of short calls), or ""."""
    simulate(robot, q0, v0, duration=2 * DT, dt=DT)
    profiler = cProfile.Profile()
    profiler.enable()
    for _ in range(calls):
        simulate(robot, q0, v0, duration=2 * DT, dt=DT)
    profiler.disable()
    entries = pstats.Stats(profiler, stream=io.StringIO()).stats  # type: ignore[attr-defined]
    total = max((entry[3] for key, entry in entries.items() if key[2] == "simulate"), default=0.0)
    lookups = [entry for key, entry in entries.items() if key[2] == "version" and "metadata" in key[0]]
    if not total or not lookups:
        return ""
    entry = max(lookups, key=lambda e: e[3])  # the public importlib.metadata.version, which calls the others
    callers = ", ".join(sorted({f"`{Path(f).name}:{func}`" for (f, _, func) in entry[4]}))
    return para(f"""
        cProfile of {calls} two-step `simulate` calls on {robot.name}: {entry[3] / total:.0%} of their time is
        in `importlib.metadata.version` (called from {callers}, which looks the package versions up again for
        every Trajectory's metadata); computing them once per process would remove most of the fixed cost.""")


# ---- the run -----------------------------------------------------------------------------------------------
def bench_robot(name: str, repeats: int, steps: int, methods: list[str]) -> RobotResult:
    """All measurements of one robot."""
    robot = load_robot(name, damping=False)  # no URDF damping: the MuJoCo peer's is zeroed too
    rng = np.random.default_rng(SEED)
    q0 = robot.random_configuration(rng)
    v0 = rng.normal(scale=V0_SCALE, size=robot.nv)
    samples = Samples(
        call={m: [] for m in methods},
        fixed_ms={m: [] for m in methods},
        stats_wall={m: [] for m in methods},
        call_wall={m: [] for m in methods},
    )
    result = RobotResult(name, robot.nq, robot.nv, robot.floating_base, samples)

    mj = None
    if mujoco is not None:
        model = mujoco_model(robot)
        data = mujoco.MjData(model)
        smap = StateMap(robot, model)
        qpos, qvel = smap.to_mujoco(q0, v0)
        # Sanity check, not a test: the same state must give the same accelerations.
        mj_set_state(model, data, qpos, qvel)
        mujoco.mj_forward(model, data)
        a = pin.aba(robot.model, robot.data, q0, v0, np.zeros(robot.nv), _WORLD)
        expected = smap.acceleration(q0, v0, a)
        result.qacc_error = float(np.max(np.abs(data.qacc - expected)))
        result.qacc_scale = float(np.max(np.abs(expected)))
        full = mujoco.mjtState.mjSTATE_FULLPHYSICS
        state0 = np.empty(mujoco.mj_stateSize(model, full))
        mujoco.mj_getState(model, data, state0, full)
        mj = (model, data, qpos, qvel, state0)

    # The batches: FLOOR_STATES random states for the floor (columns, as abaInParallel takes them), the first
    # ROLLOUT_B of them for the rollouts (ours and MuJoCo's).
    Q_batch = np.array([robot.random_configuration(rng) for _ in range(FLOOR_STATES)])
    V_batch = rng.normal(scale=V0_SCALE, size=(FLOOR_STATES, robot.nv))
    pool = pin.ModelPool(robot.model, 1)
    floor_out = np.zeros((FLOOR_STATES, robot.nv))
    floor_args = (pool, Q_batch.T, V_batch.T, floor_out.T)
    Q0s, V0s = Q_batch[:ROLLOUT_B], V_batch[:ROLLOUT_B]
    mj_states = None
    if mj and mj_rollout is not None:
        model, data = mj[0], mj[1]
        full = mujoco.mjtState.mjSTATE_FULLPHYSICS
        mj_states = np.empty((ROLLOUT_B, mujoco.mj_stateSize(model, full)))
        for b in range(ROLLOUT_B):
            mj_set_state(model, data, *smap.to_mujoco(Q0s[b], V0s[b]))
            mujoco.mj_getState(model, data, mj_states[b], full)

    # An untimed round first: caches, allocators and lazy initialisations of both libraries.
    for method in methods:
        time_simulate(robot, q0, v0, 50, method)
    time_floor(robot, q0, v0, 50)
    time_simulate(robot, q0, v0, 50, "rk4", kernel="native")
    time_floor_batch(robot, *floor_args)
    time_native_rollout(robot, Q0s, V0s, 5)
    if mj:
        time_mj_step(mj[0], mj[1], mj[2], mj[3], 50)

    # Round-robin: each round times every variant once, so a slow phase of the machine hits all of them.
    part_timer = PartTimer(robot, q0, v0)
    for _ in range(repeats):
        part_timer.time_round(reps=steps)
        for method in methods:
            cpu, wall, stats_wall = time_simulate(robot, q0, v0, steps, method)
            samples.call[method].append(cpu)
            samples.call_wall[method].append(wall)
            samples.stats_wall[method].append(stats_wall)
            samples.cpu_share.append(cpu / wall)
            samples.fixed_ms[method].append(time_simulate(robot, q0, v0, 1, method)[0] * 1e-3)
        samples.rk4_sparse.append(time_simulate(robot, q0, v0, steps, "rk4", output_dt=10 * DT)[0])
        samples.floor.append(time_floor(robot, q0, v0, steps))
        samples.native.append(time_simulate(robot, q0, v0, steps, "rk4", kernel="native")[0])
        samples.native_fixed_ms.append(time_simulate(robot, q0, v0, 1, "rk4", kernel="native")[0] * 1e-3)
        samples.floor_batch.append(time_floor_batch(robot, *floor_args))
        samples.native_rollout.append(time_native_rollout(robot, Q0s, V0s, ROLLOUT_STEPS))
        samples.native_rollout_sparse.append(time_native_rollout(robot, Q0s, V0s, ROLLOUT_STEPS, output_dt=10 * DT))
        if mj_states is not None:
            samples.mj_rollout_batch.append(time_mj_rollout_batch(mj[0], mj[1], mj_states, ROLLOUT_STEPS))
        if mj:
            samples.mj_step.append(time_mj_step(mj[0], mj[1], mj[2], mj[3], steps))
            if mj_rollout is not None:
                samples.mj_rollout.append(time_mj_rollout(mj[0], mj[1], mj[4], steps))

    if mj:
        # Both RK4s from the same state for the same steps: the two columns must time the same motion.
        model, data, qpos, qvel, _ = mj
        mj_set_state(model, data, qpos, qvel)
        for _ in range(steps):
            mujoco.mj_step(model, data)
        traj = simulate(robot, q0, v0, duration=steps * DT, dt=DT, integrator="rk4")
        ours_qpos, ours_qvel = smap.to_mujoco(traj.q[-1], traj.v[-1])
        mj_qpos = data.qpos.copy()
        for kind, _, _, jq, _ in smap.joints:  # q and -q are the same rotation
            if kind == "free" and mj_qpos[jq + 3 : jq + 7] @ ours_qpos[jq + 3 : jq + 7] < 0:
                mj_qpos[jq + 3 : jq + 7] *= -1
        result.final_state_error = float(
            max(np.max(np.abs(mj_qpos - ours_qpos)), np.max(np.abs(data.qvel - ours_qvel)))
        )

    result.parts, result.extras = part_timer.costs()
    return result


# ---- the report --------------------------------------------------------------------------------------------
def versions() -> dict[str, str]:
    return {
        "python": platform.python_version(),
        "pin": pin.__version__,
        "numpy": np.__version__,
        "mujoco": mujoco.__version__ if mujoco is not None else "not installed",
    }


def load_average() -> float:
    """The 1-minute load average (NaN where the platform has none)."""
    try:
        return os.getloadavg()[0]
    except OSError:
        return math.nan


def cpu_name() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def table(head: list[str], rows: list[list[str]]) -> list[str]:
    return ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)] + ["| " + " | ".join(r) + " |" for r in rows]


def chart_section(accuracy: dict[str, ChartError]) -> list[str]:
    """The chart map's table and what it says, written from this run's numbers."""
    rk4, dop, closed = accuracy[SERIES_RK4], accuracy[SERIES_DOP853], accuracy[CLOSED_FORM]
    in_use, in_use_jlog = accuracy[IN_USE], accuracy[IN_USE_JLOG]
    lines = [
        para(f"""Free-flyer chart map: the stage rates xi' = J_r(xi)^-1 v that keep RK4's order on a floating
            base. The integrators compute them by the series J_r(xi)^-1 = Σ b_n A^n (A = ad_xi; b = 1, 1/2,
            1/12, 0, -1/720, …) truncated after the power their order needs, K = `chart_terms` ({RK4_TERMS}
            for rk4, {DOP853_TERMS} for dop853). Each map is compared with the same series carried to 15 terms,
            written independently in this script (exact to round-off for θ ≤ 0.1), for stage twists whose
            linear and angular parts both have norm θ from 1e-6 to 1e-1 and velocities of unit size. At dt =
            1 ms an RK4 stage has θ ≈ 0.5–1 ms × the base's speed, so θ = 1e-4 … 1e-3 is the everyday range.
            The last two rows use the stages of actual rk4 runs instead (the first floating robot's base
            spinning at 0.3, 0.6 and 1.2 rad/s, dt = 1 ms; {in_use.calls} chart maps)."""),
        "",
    ]
    lines += table(
        ["chart rates by", "series kept", "worst error", "at θ", f"worst for θ ≤ {EVERYDAY_THETA:.0e}", "fitted order"],
        [
            [
                f"`{name}`",
                row.kept,
                f"{row.worst:.1e}",
                f"{row.theta:.0e}",
                "–" if math.isnan(row.everyday) else f"{row.everyday:.1e}",
                "–" if row.order is None else f"{row.order:.1f}",
            ]
            for name, row in accuracy.items()
        ],
    )
    eps = np.finfo(float).eps
    # The first term dropped after A^K is b_(K+1) A^(K+1), or b_(K+2) A^(K+2) when b_(K+1) = 0 (K even, K ≥ 2).
    expected = RK4_TERMS + (2 if RK4_TERMS >= 2 and RK4_TERMS % 2 == 0 else 1)
    if rk4.order is None:
        rk4_text = f"""rk4's map ({rk4.kept}) stays within {rk4.worst:.0e} over the whole sweep: round-off, no
            visible truncation."""
    else:
        where = "the top of the sweep" if rk4.theta == THETAS[-1] else "not at the top of the sweep"
        if abs(rk4.order - expected) < 0.5:
            rk4_text = f"""rk4's map ({rk4.kept}) errs by up to {rk4.worst:.0e}, at θ = {rk4.theta:.0e} ({where}):
                the truncation, by design. Its error grows as θ^{rk4.order:.1f} (fitted where above round-off),
                as the first dropped term, b_{expected} A^{expected} v, predicts; in the everyday range it is
                at most {rk4.everyday:.0e}. A stage's θ is O(dt), so the dropped terms change a step by
                O(dt^{expected + 1})"""
            local = INTEGRATORS["rk4"].order + 1
            rk4_text += f", no more than RK4's own local error, O(dt^{local})." if expected + 1 >= local else "."
        else:
            rk4_text = f"""rk4's map ({rk4.kept}) errs by up to {rk4.worst:.0e}, at θ = {rk4.theta:.0e} ({where}),
                and its error grows as θ^{rk4.order:.1f}, not as the θ^{expected} of the first dropped term,
                b_{expected} A^{expected} v: more than the truncation; check the map. In the everyday range it
                is at most {rk4.everyday:.0e}."""
    dop_text = f"""dop853's map ({dop.kept}) errs by at most {dop.worst:.0e} ({dop.worst / eps:.0f} × machine
        epsilon, at θ = {dop.theta:.0e}) and by {dop.everyday:.0e} for θ ≤ {EVERYDAY_THETA:.0e}."""
    if closed.worst > 1e-12 and closed.theta < 1e-2:
        closed_text = f"""Pinocchio's closed form errs by up to {closed.worst:.0e} at θ = {closed.theta:.0e},
            inside the everyday range: just above a small-angle switch, where its coefficients lose digits to
            cancellation. For θ ≤ {EVERYDAY_THETA:.0e} its worst error is
            {closed.everyday / max(rk4.everyday, eps):.0e} times that of rk4's truncated series."""
    else:
        closed_text = f"""Pinocchio's closed form errs by at most {closed.worst:.0e} (at θ = {closed.theta:.0e})."""
    if in_use.worst < 1e-11:
        use_text = f"""Inside the rk4 runs the map erred by at most {in_use.worst:.0e}, so its truncation does not
            limit the integrator in practice."""
    else:
        use_text = f"""Inside the rk4 runs the map erred by up to {in_use.worst:.0e}, which puts a floor under
            floating-base convergence studies."""
    if in_use.worst < rk4.everyday / 10:  # False for NaN
        use_text += f""" That is below the sweep's {rk4.everyday:.0e} in the same range: a stage's velocity is
            nearly parallel to its twist (exactly so in RK4's second stage), and ad_xi xi = 0."""
    if in_use_jlog.worst > 10 * max(in_use.worst, eps):
        use_text += f""" The closed form would have erred by {in_use_jlog.worst:.0e} on the same stages."""
    return [*lines, "", para(" ".join([rk4_text, dop_text, closed_text, use_text]))]


def write_report(
    path: Path,
    results: list[RobotResult],
    methods: list[str],
    args: argparse.Namespace,
    command: str,
    elapsed: float,
    profile: Profile | None,
    call_profile: str,
    numpy_op_us: float,
    loads: tuple[float, float],
    accuracy: dict[str, ChartError] | None,
) -> str:
    load_before, load_after = loads
    v = versions()
    mj_on = mujoco is not None
    date = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    lines = [
        "# Per-step cost of the stepping loop",
        "",
        "Generated by `scripts/bench_step_cost.py`; do not edit by hand.",
        "",
        f"- Command: `{command}`",
        f"- Date: {date}; the whole run took {elapsed:.0f} s",
        f"- Versions: Python {v['python']}, pin {v['pin']}, numpy {v['numpy']}, mujoco {v['mujoco']}",
        para(f"""- Machine: {cpu_name()}, {os.cpu_count()} cores, shared: timings drift by tens of percent
            from minute to minute, so every variant is timed once per round, round-robin, and each figure is
            the median over {args.repeats} rounds of {args.steps} steps."""),
        para(f"""- Workload: `simulate(robot, q0, v0, duration={args.steps * DT:g}, dt={DT:g},
            integrator=...)` with zero torque,
            `q0 = robot.random_configuration(np.random.default_rng({SEED}))`,
            v0 ~ N(0, {V0_SCALE}²) per coordinate, output every step (the default); robots loaded with
            `damping=False` like the MuJoCo peer, whose damping is zeroed. Floating robots fall freely."""),
        "",
        "## Results (µs per step, medians; CPU time unless marked wall)",
        "",
    ]
    steps = args.steps
    head = [
        "robot",
        "nq/nv",
        *methods,
        "rk4 whole call",
        "rk4 wall: stats wall_time / whole call",
        "floor: 4 aba + 4 integrate",
        "rk4 / floor",
    ]
    if mj_on:
        head += ["MuJoCo mj_step (RK4)", "mujoco.rollout", "rk4 / mj_step"]
    rows = []
    for r in results:
        s = r.samples
        rk4, floor = s.loop("rk4", steps), median(s.floor)
        row = [
            r.name + (" (floating)" if r.floating else ""),
            f"{r.nq}/{r.nv}",
            *(fmt(s.loop(m, steps)) for m in methods),
            fmt(median(s.call["rk4"])),
            f"{fmt(median(s.stats_wall['rk4']))} / {fmt(median(s.call_wall['rk4']))}",
            fmt(floor),
            fmt(rk4 / floor, 2),
        ]
        if mj_on:
            mj_step = median(s.mj_step)
            row += [fmt(mj_step), fmt(median(s.mj_rollout)), fmt(rk4 / mj_step, 2)]
        rows.append(row)
    lines += table(head, rows)
    fixed = ", ".join(f"{r.name} {fmt(median(r.samples.fixed_ms['rk4']), 2)} ms" for r in results)
    shares = [x for r in results for x in r.samples.cpu_share]
    lines += [
        "",
        para(f"""- Why CPU time: the machine is shared. During this run the 1-minute load average was
            {load_before:.1f} at the start and {load_after:.1f} at the end on {os.cpu_count()} cores, and this
            process got {median(shares):.0%} of a core in the median timed call, {min(shares):.0%} in the
            worst. Wall time also counts the time other jobs held the core (the "rk4 wall" column shows
            it: the loop's own `stats['wall_time']` and the whole call's); CPU time does not, though a
            busy neighbour still slows the caches, so absolute figures from a loaded run are high by tens of
            percent. The ratios, measured in the same rounds, are the robust figures."""),
        para(f"""- Integrator columns: the CPU time of a {steps}-step `simulate` call minus that of a one-step
            call (the fixed per-call cost), per step: the stepping loop alone. "rk4 whole call": the
            {steps}-step call's CPU time per step, fixed cost included. That fixed cost (argument checks,
            allocation, building the Trajectory with its limit report and metadata) is {fixed} per call, so
            it matters only for short runs. {call_profile}"""),
        para("""- Floor: 4 × `pin.aba(model, data, q, v, tau, pin.Convention.WORLD)` + 4 × `pin.integrate`
            per step, unrolled in a tight Python loop: the Pinocchio calls an RK4 step cannot avoid, with
            their Python call overhead."""),
    ]
    if mj_on:
        rollout = (
            "`mujoco.rollout.rollout` runs the same steps in C++ (one trajectory, one thread)."
            if mj_rollout is not None
            else "(`mujoco.rollout` is not available in this version.)"
        )
        lines.append(
            para(f"""- MuJoCo: the same URDF through `mujoco.MjSpec.from_string` after removing its visual,
            collision and transmission elements; a free joint added on the root body of floating robots;
            `dof_damping`, `dof_armature` and `dof_frictionloss` zeroed; equality constraints (panda's finger
            mimic), joint limits and contacts disabled with `opt.disableflags`; `opt.integrator = RK4`,
            `opt.timestep = {DT:g}`. `mj_step` is called in a Python loop; {rollout}""")
        )
    lines += native_section(results, steps, mj_on)
    lines += ["", "## Sanity checks (not tests)", ""]
    if mj_on:
        lines += [
            para(f"""Same state, same accelerations: MuJoCo's `qacc` after `mj_forward` against Pinocchio's
            ABA at (q0, v0), mapped joint by joint by name, with the free joint's quaternion reordered (MuJoCo
            puts w first) and its velocity converted (MuJoCo's linear velocity is in the world frame,
            Pinocchio's in the base frame, so MuJoCo's linear acceleration is R (v̇_lin + ω × v_lin)). Then
            both RK4s run {args.steps} steps from that state and their final states are compared in MuJoCo's
            coordinates, a check that both columns time the same motion."""),
            "",
        ]
        lines += table(
            [
                "robot",
                "max \\|a_MuJoCo − a_Pinocchio\\|",
                "max \\|a\\|",
                f"max state difference after {args.steps} steps",
            ],
            [[r.name, f"{r.qacc_error:.1e}", f"{r.qacc_scale:.3g}", f"{r.final_state_error:.1e}"] for r in results],
        )
    else:
        lines.append("MuJoCo is not installed (`pip install mujoco` into .venv): its columns and checks were skipped.")

    if accuracy:
        lines += ["", *chart_section(accuracy)]
    lines += [
        "",
        "## Where the time goes in an RK4 step",
        "",
        para("""Each part timed alone in a tight loop (µs per step = cost per call × calls per step) against
            the rk4 column; "rest" is what the step spends outside these calls: the Python-side arithmetic
            that combines the stages, list handling and the loop's bookkeeping. The last column is rk4 with
            `output_dt = 10 dt` (recording one step in ten)."""),
        "",
    ]
    labels: list[str] = []
    for r in results:
        labels += [k for k in r.parts if k not in labels]
    lines += table(
        ["robot", "rk4", *labels, "rest", "rk4, output every 10 steps"],
        [
            [
                r.name,
                fmt(r.samples.loop("rk4", steps)),
                *(fmt(r.parts.get(k)) for k in labels),
                fmt(r.samples.loop("rk4", steps) - sum(r.parts.values())),
                fmt(r.samples.loop_sparse(steps)),
            ]
            for r in results
        ],
    )
    if profile is not None:
        name, total, steps, top = profile
        lines += [
            "",
            para(f"""cProfile of one rk4 `simulate` on {name} ({steps} steps), functions by their own time
                (profiling inflates Python-level calls, so read the shares, not the times; the total own time
                was {total * 1e3:.0f} ms):"""),
            "",
        ]
        lines += table(["function", "calls", "share of own time"], [[f"`{f}`", str(c), f"{s:.0%}"] for f, c, s in top])
    lines += ["", "## Reading", "", *interpretation(results, steps, numpy_op_us, profile, accuracy), ""]
    text = "\n".join(lines)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return text


def native_section(results: list[RobotResult], steps: int, mj_on: bool) -> list[str]:
    """The native kernel's table: simulate and rollout against the C++ floor and MuJoCo."""
    head = [
        "robot",
        "native simulate rk4",
        "floor: 4 × abaInParallel per state",
        "native / floor",
        "python rk4",
    ]
    if mj_on:
        head += ["MuJoCo mj_step (RK4)", "native / mj_step"]
    head += [
        f"native rollout (B = {ROLLOUT_B}) per state-step",
        "rollout / floor",
        "rollout recording every 10th step / floor",
    ]
    if mj_on:
        head += [f"mujoco.rollout (B = {ROLLOUT_B}) per state-step", "rollout / mujoco.rollout"]
    rows = []
    for r in results:
        s = r.samples
        ours, floor, batch = s.native_loop(steps), median(s.floor_batch), median(s.native_rollout)
        row = [r.name + (" (floating)" if r.floating else ""), fmt(ours, 2), fmt(floor, 2), fmt(ours / floor, 2)]
        row.append(fmt(s.loop("rk4", steps)))
        if mj_on:
            mj_step = median(s.mj_step)
            row += [fmt(mj_step, 2), fmt(ours / mj_step, 2)]
        row += [fmt(batch, 2), fmt(batch / floor, 2), fmt(median(s.native_rollout_sparse) / floor, 2)]
        if mj_on:
            mj_batch = median(s.mj_rollout_batch)
            row += [fmt(mj_batch, 2), fmt(batch / mj_batch, 2)]
        rows.append(row)
    fixed = ", ".join(f"{r.name} {fmt(median(r.samples.native_fixed_ms), 2)} ms" for r in results)

    def verdict(what: str, ratios: dict[str, float], target: float) -> str:
        met = [name for name, x in ratios.items() if x <= target]
        missed = [f"{name} ({x:.2f})" for name, x in ratios.items() if x > target]
        return f"{what} ≤ {target:g}: " + (
            f"met on {', '.join(met) or 'none'}" + (f"; missed on {', '.join(missed)}" if missed else "")
        )

    floors = {r.name: median(r.samples.floor_batch) for r in results}
    simulate_ratios = {r.name: r.samples.native_loop(steps) / floors[r.name] for r in results}
    verdicts = [
        verdict("native simulate / floor", simulate_ratios, 1.3),
        verdict("rollout / floor", {r.name: median(r.samples.native_rollout) / floors[r.name] for r in results}, 1.1),
    ]
    if mj_on:
        verdicts.append(
            verdict(
                "native simulate / mj_step on double_pendulum and ur5",
                {
                    r.name: r.samples.native_loop(steps) / median(r.samples.mj_step)
                    for r in results
                    if r.name in ("double_pendulum", "ur5")
                },
                1.0,
            )
        )
    return [
        "",
        "## The native kernel (µs per step, CPU-time medians)",
        "",
        *table(head, rows),
        "",
        "Issue 15's targets, in this run: " + "; ".join(verdicts) + ".",
        "",
        para(f"""- Native simulate rk4: `simulate(..., integrator="rk4")` on the native kernel (the extension's C++
            loop: the whole run between the driver's events), output every step with its energies and ledger,
            the CPU time of a {steps}-step call minus that of a one-step call, per step (fixed per-call cost:
            {fixed}). "python rk4": the same run on the Python kernel (the first table's rk4 column)."""),
        para(f"""- Floor: four calls of `pin.abaInParallel(1, pool, Q, V, tau, a)` over {FLOOR_STATES} random
            states on one thread, per state: what four C++ ABA passes cost per state, without Python per call.
            An RK4 step also integrates four times and records a sample (kinematics and two energies): the
            ratio says what the loop adds to the four ABA passes."""),
        para(f"""- Rollout: `rollout(robot, Q0s, V0s, duration={ROLLOUT_STEPS * DT:g}, dt={DT:g},
            integrator="rk4")`, {ROLLOUT_B} random states, one thread, output every step, the whole call's CPU time
            per state-step; `mujoco.rollout.rollout(model, data, states0, nstep={ROLLOUT_STEPS})` from the same
            {ROLLOUT_B} states (its full physics state recorded every step), one thread. "Recording every 10th
            step": the same rollout with `output_dt={10 * DT:g}`; the difference is what a sample costs (the
            kinematics pass of its two energies, which the Python kernel computes the same way, and the
            batch's assembly in Python)."""),
    ]


def interpretation(
    results: list[RobotResult],
    steps: int,
    numpy_op_us: float,
    profile: Profile | None,
    accuracy: dict[str, ChartError] | None,
) -> list[str]:
    """The paragraphs on where the time goes, written from this run's numbers.

    Each suggestion is made only when this run measured that it would pay, so the text stays true as the
    code changes.
    """
    rows = []
    for r in results:
        rk4, floor = r.samples.loop("rk4", steps), median(r.samples.floor)
        rows.append((r, rk4, floor, rk4 - sum(r.parts.values()), rk4 - r.samples.loop_sparse(steps)))
    ratios = [rk4 / floor for _, rk4, floor, _, _ in rows]
    shares = ", ".join(f"{r.name} {floor / rk4:.0%}" for r, rk4, floor, _, _ in rows)
    rests = ", ".join(f"{r.name} {fmt(rest)} µs ({rest / rk4:.0%})" for r, rk4, _, rest, _ in rows)
    records = ", ".join(f"{r.name} {fmt(record)}" for r, _, _, _, record in rows)
    text = [
        para(f"""On the Python kernel (the first table; the native kernel has its own section above), an rk4
        step costs {min(ratios):.1f}–{max(ratios):.1f} times its Pinocchio floor: the 4 dynamics
        evaluations and 4 configuration updates are {shares} of the step, so on every robot most of the
        time is spent in Python around them. The table's "rest" (what remains after the calls timed alone)
        is {rests}: the stage arithmetic and the step's and loop's bookkeeping, made of small-array numpy
        operations at ~{numpy_op_us:.1f} µs each (measured in this run on 18-element arrays; each allocates)
        and Python function calls. Recording every step costs {records} µs per step (rk4 with the default
        output minus rk4 recording one step in ten: a difference of two noisy medians)."""),
    ]
    if profile is not None:
        name, _, _, top = profile
        listed = ", ".join(f"`{label}` {share:.0%}" for label, _, share in top[:6])
        text += [
            "",
            para(f"""In the profile of {name}, the largest own-time shares are {listed}. cProfile does not see
            Pinocchio's Boost.Python functions, nor numpy's operators (`@`, `*`, indexing), as calls of their
            own: their time is the own time of the Python function that uses them (`unchecked_forward_dynamics`
            holds `pin.aba`, `integrate` holds `pin.integrate`, `chart_velocity` holds its truncated series'
            6 × 6 products and makes no Pinocchio call); numpy functions and array methods called by name
            (`copy`, `reshape`) do show."""),
        ]
    charts = [
        (r.name, r.parts["3 × chart_velocity"], r.extras[CHART_CLOSED_FORM_COST], rk4)
        for r, rk4, *_ in rows
        if "3 × chart_velocity" in r.parts and CHART_CLOSED_FORM_COST in r.extras
    ]
    if charts:
        listed = ", ".join(
            f"{n} {fmt(series)} µs ({series / rk4:.0%} of the step) against {fmt(closed)} µs"
            for n, series, closed, rk4 in charts
        )
        verdict = ""
        if accuracy:
            closed, series = accuracy[CLOSED_FORM].everyday, accuracy[SERIES_RK4].everyday
            if closed > 10 * max(series, np.finfo(float).eps):  # the cheaper map would cost digits
                verdict = f""" Whatever its cost, the closed form is no alternative: for θ ≤ {EVERYDAY_THETA:.0e}
                    it errs by up to {closed:.0e} against the series' {series:.0e} (the chart-map table)."""
        text += [
            "",
            para(f"""The chart map (3 × `chart_velocity` per step, the series kept up to {_power(RK4_TERMS)})
            against Pinocchio's closed form `Jlog6(exp6(xi)) @ v` on the same stages: {listed} per
            step.{verdict}"""),
        ]
    suggestions = []
    beyond = [(r.name, record - r.parts["1 × energies (record)"], rk4) for r, rk4, _, _, record in rows]
    if median([extra / rk4 for _, extra, rk4 in beyond]) > 0.05:
        listed = ", ".join(f"{n} {fmt(extra)} µs" for n, extra, _ in beyond)
        suggestions.append(
            f"""in `simulation.py`, make recording a sample cheaper: beyond its energy calls it costs {listed}
            (the call to store seven rows, boolean-mask indexing and sums for the blow-up check, arithmetic
            on numpy scalars); the blow-up check can run on Python floats (`flows.tolist()` with
            precomputed work/dissipated indices), or once every few samples"""
        )
    gains = []
    for r, rk4, *_ in rows:
        now, alt = r.parts.get("1 × energies (record)"), r.extras.get("energies, one kinematics pass")
        if now is not None and alt is not None:
            gains.append((r.name, now - alt, rk4))
    if gains and median([g / rk4 for _, g, rk4 in gains]) > 0.02:
        listed = ", ".join(f"{n} {fmt(g)} µs ({g / rk4:.0%})" for n, g, rk4 in gains)
        suggestions.append(
            f"""compute both energies after a single `forwardKinematics(model, data, q, v)` with the
            data-only `computeKineticEnergy(model, data)` and `computePotentialEnergy(model, data)` instead
            of two calls that each redo the kinematics: {listed} per recorded step"""
        )
    fixed = [median(r.samples.fixed_ms["rk4"]) for r in results]
    if median(fixed) > 0.5:
        suggestions.append(
            f"""for short runs, cut the fixed per-call cost ({min(fixed):.1f}–{max(fixed):.1f} ms per
            `simulate` call here; see the profile note under Results)"""
        )
    if suggestions:
        text += [
            "",
            para(
                "What this run says would help: " + "; ".join(f"({i + 1}) {x}" for i, x in enumerate(suggestions)) + "."
            ),
        ]
    text += [
        "",
        para("""Past such fixes, what separates the Python kernel's loop from MuJoCo is the Python overhead of
        about ten Pinocchio calls and a few dozen numpy operations per step: the native kernel (its section
        above) runs the same loop in C++, and the Python kernel remains its specification and the fallback
        where no compiler is found."""),
    ]
    return text


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=31, help="rounds; each figure is a median over them")
    parser.add_argument("--steps", type=int, default=500, help="steps per timed call")
    parser.add_argument("--robots", default=",".join(ROBOTS), help="comma-separated catalog names")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "step_cost.md")
    args = parser.parse_args(argv)
    python = Path(sys.executable)
    python_shown = str(python.relative_to(ROOT)) if python.is_relative_to(ROOT) else "python"
    command = " ".join([python_shown, "scripts/bench_step_cost.py", *(sys.argv[1:] if argv is None else argv)])
    methods = [m for m in METHODS if m in INTEGRATORS]
    if "rk4" not in methods:
        raise SystemExit("the rk4 integrator is missing from INTEGRATORS; nothing to compare")
    warnings: list[str] = []
    if mujoco is None:
        print("note: mujoco is not installed (pip install mujoco): its columns and checks are skipped")
    else:  # keep the URDF importer's warnings instead of letting it write MUJOCO_LOG.TXT into the cwd
        mujoco.set_mju_user_warning(lambda message: warnings.append(message.strip()))
        if mj_rollout is None:
            print("note: mujoco.rollout is not available: its column is skipped")

    if not native.available:
        raise SystemExit(f"the native kernel is not available here ({native.why_unavailable}): nothing to compare")
    os.environ[native.ENV] = "0"  # the Python kernel, but where a figure names the native one (kernel_env)
    start = time.perf_counter()
    load_before = load_average()
    names = args.robots.split(",")
    results = []
    for name in names:
        t0 = time.perf_counter()
        r = bench_robot(name, args.repeats, args.steps, methods)
        results.append(r)
        s = r.samples
        print(
            f"{name}: python rk4 {s.loop('rk4', args.steps):.1f} µs/step (CPU), "
            f"native {s.native_loop(args.steps):.2f}, "
            f"floor 4 × abaInParallel {median(s.floor_batch):.2f}, mj_step {median(s.mj_step):.2f}; rollout "
            f"{median(s.native_rollout):.2f} µs/state-step, mujoco.rollout {median(s.mj_rollout_batch):.2f} "
            f"({time.perf_counter() - t0:.0f} s)",
            flush=True,
        )
    profile, call_profile = None, ""
    floating = [r.name for r in results if r.floating]
    accuracy = None
    if floating:
        chart_robot = load_robot(floating[0], damping=False)
        accuracy = {**chart_map_accuracy(chart_robot), **chart_map_in_use(chart_robot)}
    if PROFILED_ROBOT in names:
        robot = load_robot(PROFILED_ROBOT, damping=False)
        rng = np.random.default_rng(SEED)
        q0 = robot.random_configuration(rng)
        v0 = rng.normal(scale=V0_SCALE, size=robot.nv)
        total, top = profile_rk4(robot, q0, v0, PROFILED_STEPS)
        profile = (PROFILED_ROBOT, total, PROFILED_STEPS, top)
        call_profile = profile_call_overhead(robot, q0, v0)
    numpy_op_us = time_numpy_op(18)
    for message in sorted(set(warnings)):
        print(f"note: MuJoCo's URDF importer warned: {message}")
    elapsed = time.perf_counter() - start
    loads = (load_before, load_average())
    text = write_report(
        args.out, results, methods, args, command, elapsed, profile, call_profile, numpy_op_us, loads, accuracy
    )
    print(text)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
