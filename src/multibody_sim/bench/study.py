"""work_precision(): the study itself: each integrator's ladder of steps or tolerances, the reference and its check,
the timing and the error of every run."""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Iterable, Sequence
from typing import Any

import numpy as np

from ..exceptions import InvalidArgumentError, SimulationError, SimulationInterrupted
from ..integrators import INTEGRATORS, Integrator, get_integrator
from ..metadata import versions
from ..robot import Robot, check_system
from ..simulation import Controller, simulate
from ..torques import controller_name
from ..trajectory import Trajectory, check_trajectory
from ..validation import MAX_STEPS, check_callable, positive_number
from .results import (
    REFERENCE_MARGIN,
    STATUS_COMPLETED,
    STATUS_REFUSED,
    Measurement,
    Reference,
    WorkPrecision,
    observed_orders,
)

# The common sample grid [s]: 20 ms resolves the motions of robots (periods of a second or more) to ~0.1 % of
# the error's peaks, and every step of the 1-2-5 ladder below divides it.
OUTPUT_DT = 0.02
# Fixed steps [s]: a 1-2-5 series (values users recognise), 20 ms down to 1 µs; a study stops each ladder early.
STEP_LADDER = tuple(m * 10.0**e for e in range(-2, -7, -1) for m in (2, 1, 0.5)) + (1e-6,)
# Tolerances of adaptive methods (rtol = atol): half decades from 1e-2 to 1e-11.
TOLERANCE_LADDER = tuple(10.0 ** (-k / 2) for k in range(4, 23))
ADAPTIVE_FIRST_STEP = 1e-3  # [s] an adaptive run's first trial step (what `run` uses too)
# The reference: DOP853 at rtol = atol = 1e-14, checked against 1e-15. dp54 at 1e-12 (the former reference) was
# only ~1e-11 accurate on the double pendulum: RK4's 1 ms run fell within 10x of it, was left out of the fit, and
# the fit on coarser, pre-asymptotic steps read 4.60 (MISMATCH). DOP853 at 1e-14 is within 3e-13 of its 1e-15
# check there, at about the cost of dp54 at 1e-12 (800 against 860 evaluations over 1 s).
REFERENCE_INTEGRATOR = "dop853"
REFERENCE_TOLERANCE = 1e-14  # rtol = atol of the reference; the check runs `refinement` times tighter
# A contact scene is not smooth: no higher-order method converges faster on it, and only timestepping steps it.
# Its reference is the same integrator at a much smaller step, checked at half that step.
CONTACT_REFERENCE_DT = 2e-5
REFINEMENT = 10.0
MIN_ERROR = 1e-10  # a ladder stops once its error is below this: nothing finer is asked of a robot simulator
REPEAT_BELOW = 0.2  # [s] runs shorter than this are timed `repeats` times (median); longer ones once
# [s] the period at which a study holds its controller when none is given (1 kHz, a common control rate)
CONTROL_DT = 1e-3


class BenchInterrupted(SimulationInterrupted):
    """Ctrl-C (or SIGTERM in the CLI) stopped a study; `.result` holds what was measured so far.

    Attributes:
        result: the partial WorkPrecision (``complete`` is False).
    """

    def __init__(self, message: str, *, result: WorkPrecision, signal_name: str = "SIGINT"):
        super().__init__(message, signal_name=signal_name)
        self.result = result


def work_precision(
    system: Robot,
    q0: Any,
    v0: Any,
    *,
    duration: float,
    integrators: Iterable[str | Integrator] | None = None,
    steps: Sequence[float] | None = None,
    tolerances: Sequence[float] | None = None,
    output_dt: float | None = None,
    reference_tolerance: float = REFERENCE_TOLERANCE,
    refinement: float = REFINEMENT,
    min_error: float = MIN_ERROR,
    max_steps: int = 2**17,
    max_run_time: float = 1.0,
    repeats: int = 3,
    prune: bool = False,
    progress: Callable[[str], None] | None = None,
    controller: Controller | None = None,
    control_dt: float | None = None,
) -> WorkPrecision:
    """Measure error against cost for each integrator over a ladder of steps or tolerances.

    Each fixed-step integrator runs at the steps of `steps` (default STEP_LADDER) from the coarsest down, each
    adaptive one at the tolerances of `tolerances` (default TOLERANCE_LADDER, rtol = atol) from the loosest
    down; a ladder stops once its error is below max(min_error, REFERENCE_MARGIN × the reference's error),
    before a fixed-step run predicted (from the previous run's time per step) to take longer than
    `max_run_time` or to take more than `max_steps` steps, after an adaptive run longer than `max_run_time`, and (with
    `prune`) after two consecutive runs that another integrator beat on both error and CPU time. Runs that
    diverge or fail are recorded with their status, not raised.

    Args:
        system: the robot (or scene).
        q0: initial configuration, shape (nq,).
        v0: initial velocity, shape (nv,).
        duration: simulated time of every run [s].
        integrators: names (or Integrator objects) to measure; None measures every registered integrator and
            records those that refuse the system as "refused" (named ones that refuse it are an error).
        steps: fixed steps [s]; each must divide output_dt.
        tolerances: adaptive tolerances (rtol = atol).
        output_dt: the common sample grid [s] (default min(OUTPUT_DT, duration)).
        reference_tolerance: rtol = atol of the DOP853 reference.
        refinement: the check runs at reference_tolerance / refinement.
        min_error: a ladder stops below this error.
        max_steps: the largest number of steps of a fixed-step run.
        max_run_time: the CPU-time budget of one run [s] (see above).
        repeats: runs shorter than REPEAT_BELOW seconds are timed this many times (median).
        prune: stop a ladder that other integrators dominate (the pilot study of `run --tolerance`).
        progress: called with one line of text per measurement.
        controller: ``controller(t, q, v) -> tau`` applied in every run, the reference included (reset before each
            run, as simulate does), so the study measures the motion the run will make; None applies no torque.
        control_dt: the controller's period [s] (simulate's ``control_dt``); fixed steps that do not divide it are
            left out of the ladder. None: CONTROL_DT (a controller called at every step of an adaptive method
            would make the motion depend on the steps, and no run could be measured against another).

    Returns:
        The study.

    Raises:
        InvalidArgumentError: a bad argument (named in the message), or a named integrator refuses the system.
        SimulationError: the reference itself failed.
        BenchInterrupted: Ctrl-C; ``.result`` holds what was measured so far.
    """
    check_system(system)
    q0 = system.check_q(q0, "q0")
    v0 = system.check_v(v0, "v0")
    duration = positive_number(duration, "duration")
    if steps is None:  # the ladder's finest step must fit in the run, and the run's steps must stay countable
        finest = STEP_LADDER[-1]
        if not finest <= duration <= MAX_STEPS * finest:
            raise InvalidArgumentError(
                f"duration must be from {finest:g} s (the finest step of the bench's ladder) to "
                f"{MAX_STEPS * finest:.4g} s (2**53 of those steps), got {duration:g} s"
            )
    methods, refused = _methods(system, integrators)
    grid = min(OUTPUT_DT, duration) if output_dt is None else positive_number(output_dt, "output_dt")
    if grid > duration * (1 + 1e-12):
        raise InvalidArgumentError(f"output_dt must not exceed the duration ({duration:g} s), got {grid:g} s")
    if steps is None:
        ladder = [dt for dt in STEP_LADDER if dt <= grid * (1 + 1e-12) and _divides(dt, grid)]
    else:
        if not isinstance(steps, (list, tuple, np.ndarray)):
            raise InvalidArgumentError(f"steps must be a list of steps [s], got {type(steps).__name__}")
        ladder = sorted({positive_number(dt, "steps") for dt in steps}, reverse=True)
        for dt in ladder:
            if not _divides(dt, grid):
                raise InvalidArgumentError(
                    f"steps: {dt:g} s does not divide output_dt = {grid:g} s (the common sample grid)"
                )
    tols = sorted(
        {positive_number(t, "tolerances", None) for t in (TOLERANCE_LADDER if tolerances is None else tolerances)},
        reverse=True,
    )
    reference_tolerance = positive_number(reference_tolerance, "reference_tolerance", None)
    refinement = positive_number(refinement, "refinement", None)
    if refinement <= 1:
        raise InvalidArgumentError(f"refinement must be > 1 (the check is that many times tighter), got {refinement}")
    min_error = positive_number(min_error, "min_error", None)
    max_run_time = positive_number(max_run_time, "max_run_time")
    if not isinstance(repeats, (int, np.integer)) or isinstance(repeats, bool) or repeats < 1:
        raise InvalidArgumentError(f"repeats must be a positive integer, got {repeats!r}")
    if not isinstance(max_steps, (int, np.integer)) or isinstance(max_steps, bool) or max_steps < 1:
        raise InvalidArgumentError(f"max_steps must be a positive integer, got {max_steps!r}")
    check_callable(progress, "progress", "progress(line)")
    check_callable(controller, "controller", "controller(t, q, v) -> tau")
    if controller is None:
        control_dt = None
    else:
        control_dt = CONTROL_DT if control_dt is None else positive_number(control_dt, "control_dt")
        ladder = [dt for dt in ladder if _divides(dt, control_dt)]
    say = progress or (lambda line: None)

    result = WorkPrecision(
        system=getattr(system, "name", type(system).__name__),
        duration=duration,
        output_dt=grid,
        q0=q0.tolist(),
        v0=v0.tolist(),
        reference=None,
        measurements=[Measurement(name, math.nan, None, None, STATUS_REFUSED, message=why) for name, why in refused],
        orders={},
        settings={
            "steps": ladder,
            "tolerances": tols,
            "adaptive_first_step": ADAPTIVE_FIRST_STEP,
            "reference_tolerance": reference_tolerance,
            "refinement": refinement,
            "min_error": min_error,
            "max_steps": int(max_steps),
            "max_run_time": max_run_time,
            "repeats": int(repeats),
            "prune": bool(prune),
            "cost": "cpu_time: process CPU time of the simulate() call, median over repeats",
            "controller": None if controller is None else controller_name(controller),
            "control_dt": control_dt,
        },
        metadata={"versions": dict(versions()), "source": getattr(system, "source", {})},
        complete=False,
    )
    study = _Study(system, q0, v0, duration, grid, result, say, int(repeats), max_run_time, controller, control_dt)
    if study.contact:
        say(
            f"measuring {len(methods)} integrator(s) over {duration:g} s against timestepping at dt "
            f"{CONTACT_REFERENCE_DT:g} s (checked at {CONTACT_REFERENCE_DT / 2:g} s): a contact scene is not smooth, "
            "so its reference is the same integrator at a much smaller step ..."
        )
        ladder = [dt for dt in ladder if dt >= 2 * CONTACT_REFERENCE_DT]
        result.settings["steps"] = ladder
    else:
        say(
            f"measuring {len(methods)} integrators over {duration:g} s against a {REFERENCE_INTEGRATOR} reference at "
            f"rtol {reference_tolerance:.0e} (checked at {reference_tolerance / refinement:.0e}) ..."
        )
    try:
        result.reference = study.reference(reference_tolerance, refinement)
        say(f"reference: estimated error {result.reference.error:.1e}")
        floor = max(min_error, REFERENCE_MARGIN * result.reference.error)
        # Cheap, high-order methods first: with pruning, they are what the others are measured against.
        for method in sorted(methods, key=lambda m: (m.implicit, -m.order)):
            if method.adaptive:
                rungs: list[tuple[float, float | None]] = [(ADAPTIVE_FIRST_STEP, t) for t in tols]
            else:
                rungs = [(dt, None) for dt in ladder]
            study.ladder(method, rungs, floor, int(max_steps), prune)
    except KeyboardInterrupt:
        result.orders = observed_orders(result)
        raise BenchInterrupted(f"interrupted after {len(result.measurements)} measurements", result=result) from None
    result.orders = observed_orders(result)
    result.complete = True
    return result


class _Study:
    """The running study: timing, error measurement and the ladder stops."""

    def __init__(
        self,
        system: Robot,
        q0: np.ndarray,
        v0: np.ndarray,
        duration: float,
        grid: float,
        result: WorkPrecision,
        say: Callable[[str], None],
        repeats: int,
        max_run_time: float,
        controller: Controller | None = None,
        control_dt: float | None = None,
    ):
        self.system, self.q0, self.v0 = system, q0, v0
        self.controller, self.control_dt = controller, control_dt
        self.duration, self.grid = duration, grid
        self.result, self.say = result, say
        self.repeats, self.max_run_time = repeats, max_run_time
        self.contact = getattr(system, "contact", None) is not None

    def reference(self, tolerance: float, refinement: float) -> Reference:
        if self.contact:  # no smooth reference: the same method at a much smaller step, checked at half of it
            dt = CONTACT_REFERENCE_DT
            run = self._simulate("timestepping", dt, None)
            check = self._simulate("timestepping", dt / 2, None)
            return Reference(
                integrator="timestepping",
                rtol=math.nan,
                atol=math.nan,
                check_rtol=math.nan,
                check_atol=math.nan,
                error=trajectory_error(self.system, run, check),
                evaluations=int(run.stats["evaluations"]),
                wall_time=float(run.stats["wall_time"]),
                dt=dt,
                check_dt=dt / 2,
                t=run.t,
                q=run.q,
                v=run.v,
            )
        run = self._simulate(REFERENCE_INTEGRATOR, ADAPTIVE_FIRST_STEP, tolerance)
        check = self._simulate(REFERENCE_INTEGRATOR, ADAPTIVE_FIRST_STEP, tolerance / refinement)
        return Reference(
            integrator=REFERENCE_INTEGRATOR,
            rtol=tolerance,
            atol=tolerance,
            check_rtol=tolerance / refinement,
            check_atol=tolerance / refinement,
            error=trajectory_error(self.system, run, check),
            evaluations=int(run.stats["evaluations"]),
            wall_time=float(run.stats["wall_time"]),
            t=run.t,
            q=run.q,
            v=run.v,
        )

    def _simulate(self, integrator: str | Integrator, dt: float, tolerance: float | None) -> Trajectory:
        options: dict[str, Any] = {"output_dt": self.grid}
        if tolerance is not None:
            options.update(rtol=tolerance, atol=tolerance)
        if self.control_dt is not None:
            options["control_dt"] = self.control_dt
        return simulate(
            self.system,
            self.q0,
            self.v0,
            duration=self.duration,
            dt=dt,
            integrator=integrator,
            controller=self.controller,
            **options,
        )

    def ladder(
        self, method: Integrator, rungs: list[tuple[float, float | None]], floor: float, max_steps: int, prune: bool
    ) -> None:
        dominated_in_a_row = 0
        per_step = math.nan  # the latest run's CPU time per step [s]: predicts a fixed-step run's time
        for dt, tolerance in rungs:
            if tolerance is None:
                n_steps = math.ceil(self.duration / dt - 1e-9)
                if n_steps > max_steps:
                    self.say(f"{method.name}: stopped before dt {dt:g} s (more than {max_steps} steps)")
                    return
                if per_step * n_steps > self.max_run_time:
                    self.say(
                        f"{method.name}: stopped before dt {dt:g} s (it would take ~{per_step * n_steps:.2g} s, "
                        f"budget {self.max_run_time:g} s)"
                    )
                    return
            m = self.measure(method, dt, tolerance)
            self.result.measurements.append(m)
            if m.completed:  # a run that stopped early is dominated by the fixed per-call cost: no estimate
                per_step = m.cpu_time / m.steps
            shown = f"error {m.error:.2e}" if m.completed else m.status
            self.say(f"{method.name:<20} {m.settings():<26} {shown:<16} {m.cpu_time:8.3f} s  {m.evaluations} evals")
            if not m.completed:
                continue
            if m.error < floor:
                return
            if tolerance is not None and m.cpu_time > self.max_run_time:
                self.say(f"{method.name}: stopped after a {m.cpu_time:.2f} s run (budget {self.max_run_time:g} s)")
                return
            if prune:
                dominated = any(
                    o.completed and o.integrator != m.integrator and o.error <= m.error and o.cpu_time <= m.cpu_time
                    for o in self.result.measurements
                )
                dominated_in_a_row = dominated_in_a_row + 1 if dominated else 0
                if dominated_in_a_row >= 2:
                    self.say(f"{method.name}: stopped (another integrator is more accurate for less)")
                    return

    def measure(self, method: Integrator, dt: float, tolerance: float | None) -> Measurement:
        m = Measurement(method.name, dt, tolerance, tolerance, STATUS_COMPLETED)
        start = time.process_time()
        try:
            traj = self._simulate(method, dt, tolerance)
        except SimulationError as exc:
            m.cpu_time = time.process_time() - start
            m.cpu_times = [m.cpu_time]
            m.status, m.message = exc.status, str(exc).splitlines()[0]
            partial = exc.trajectory
            if partial is not None:
                m.kernel = str(partial.metadata.get("kernel", ""))
                m.steps = int(partial.stats.get("steps", 0))
                m.evaluations = int(partial.stats.get("evaluations", 0))
                m.wall_time = float(partial.stats.get("wall_time", math.nan))
                m.wall_times = [m.wall_time]
            return m
        m.cpu_times = [time.process_time() - start]
        m.wall_times = [float(traj.stats["wall_time"])]
        m.kernel = str(traj.metadata.get("kernel", ""))
        why = traj.metadata.get("why_not_native")
        if why:
            self.result.metadata.setdefault("why_not_native", {})[method.name] = str(why)
        # Repeat only short runs: their timing is the noisiest, and repeating them costs little.
        while len(m.cpu_times) < self.repeats and sum(m.cpu_times) < REPEAT_BELOW:
            start = time.process_time()
            again = self._simulate(method, dt, tolerance)
            m.cpu_times.append(time.process_time() - start)
            m.wall_times.append(float(again.stats["wall_time"]))
        import statistics  # here: it pulls random and fractions into `import multibody_sim`

        m.cpu_time = statistics.median(m.cpu_times)
        m.wall_time = statistics.median(m.wall_times)
        m.steps = int(traj.stats["steps"])
        m.rejected_steps = int(traj.stats["rejected_steps"])
        m.evaluations = int(traj.stats["evaluations"])
        m.energy_error = traj.max_abs_energy_error
        reference = self.result.reference
        assert reference is not None
        m.error = _grid_error(self.system, traj.t, traj.q, traj.v, reference.t, reference.q, reference.v)
        m.below_reference = m.error < REFERENCE_MARGIN * reference.error
        return m


def _methods(
    system: Robot, integrators: Iterable[str | Integrator] | None
) -> tuple[list[Integrator], list[tuple[str, str]]]:
    """(integrators to measure, [(name, why) of those that refuse the system])."""
    named = integrators is not None
    if integrators is None:
        candidates = list(INTEGRATORS.values())
    else:
        if isinstance(integrators, (str, Integrator)):
            raise InvalidArgumentError(
                f"integrators must be a list of names, got {type(integrators).__name__} (write [{integrators!r}])"
            )
        if not isinstance(integrators, Iterable):
            raise InvalidArgumentError(f"integrators must be a list of names, got {type(integrators).__name__}")
        candidates = [get_integrator(i) for i in integrators]
        if not candidates:
            raise InvalidArgumentError("integrators must name at least one integrator, got an empty list")
        names = [m.name for m in candidates]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise InvalidArgumentError(f"integrators: {', '.join(duplicates)} named more than once")
    methods, refused = [], []
    for method in candidates:
        try:
            method.check_system(system)
        except InvalidArgumentError as exc:
            if named:
                raise
            refused.append((method.name, str(exc).split(";")[0]))
            continue
        methods.append(method)
    return methods, refused


def trajectory_error(system: Robot, trajectory: Trajectory, reference: Trajectory) -> float:
    """max over samples of ‖(q ⊖ q_ref, v − v_ref)‖∞, the error `--tolerance` bounds (CONTRACTS.md).

    Args:
        system: the robot both trajectories belong to.
        trajectory: the run to measure.
        reference: the reference, sampled at the same times.

    Raises:
        InvalidArgumentError: the trajectories are not sampled at the same times.
    """
    check_system(system)
    check_trajectory(trajectory, "trajectory")
    check_trajectory(reference, "reference")
    return _grid_error(system, trajectory.t, trajectory.q, trajectory.v, reference.t, reference.q, reference.v)


def _grid_error(
    system: Robot,
    t: np.ndarray,
    Q: np.ndarray,
    V: np.ndarray,
    t_ref: np.ndarray | None,
    Q_ref: np.ndarray | None,
    V_ref: np.ndarray | None,
) -> float:
    assert t_ref is not None and Q_ref is not None and V_ref is not None
    scale = max(float(abs(t_ref[-1])) if len(t_ref) else 1.0, 1.0)
    if len(t) != len(t_ref) or not np.allclose(t, t_ref, rtol=0.0, atol=1e-9 * scale):
        raise InvalidArgumentError(
            f"the trajectories are not sampled at the same times ({len(t)} and {len(t_ref)} samples)"
        )
    space = system.space
    worst = 0.0
    for q, v, q_ref, v_ref in zip(Q, V, Q_ref, V_ref, strict=True):
        worst = max(worst, float(np.abs(space.difference(q_ref, q)).max()), float(np.abs(v - v_ref).max()))
    return worst


def _divides(dt: float, period: float) -> bool:
    k = round(period / dt)
    return k >= 1 and abs(k * dt - period) <= 1e-9 * period
