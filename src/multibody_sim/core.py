"""THE stepping loop: advance rows of states, one time shared by the rows, to a stop time.

The core owns the step size (a step-size controller: constant steps or the PI controller), the solver state, the
per-step finiteness check, the step statistics and the sampling of the states it passes; a kernel does the
arithmetic of a step for every row (kernels/: the row kernel, the integrator's own ``attempt`` row by row, which is
the specification; the native kernel runs this same loop in C++, kernels/native.py). The driver (driver.py) decides
where to stop: control instants, the end of the run; it owns everything users see.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, cast

import numpy as np

from .exceptions import InvalidArgumentError
from .integrators import INTEGRATORS, Integrator
from .kernels.base import Kernel, StepKernel
from .recording import COUNTERS, SampleStore
from .step_control import LANDING_FRACTION, ConstantStep, PIController

# Why advance() returned.
REACHED = "reached"  # the stop time
STEPPED = "stepped"  # max_steps accepted steps
FULL = "full"  # the sample store reached its soft capacity
EMPTY = "empty"  # no row left running


@dataclass(frozen=True)
class RowStop:
    """A row that stopped inside the core: why, when, at which step, and the sample that holds its last state.

    Attributes:
        row: the row's index in the run (its batch index).
        status: "diverged", "newton_failed", "step_collapsed", "failed" (an exception from user code).
        time: the time of the event [s].
        step: the number of the step that failed (the core's count + 1), or None when the stop is not a step's
            (a native controller's output refused at a control instant).
        detail: what went wrong and what to try: the message after "<status> at t = ... (step n): " (the whole
            message when `step` is None).
        sample: index in the store of the row's last sample (its state before the failed step).
        added: whether that sample was taken for the stop (else it was a regular sample).
        cause: the user's exception, for status "failed".
        bad_output: "failed" on a controller output that is not a torque (native controllers).
    """

    row: int
    status: str
    time: float
    step: int | None
    detail: str
    sample: int
    added: bool
    cause: BaseException | None = None
    bad_output: bool = False

    @property
    def message(self) -> str:
        """The whole message, as SimulationError says it."""
        return self.detail if self.step is None else stop_message(self.status, self.time, self.step, self.detail)


def stop_message(status: str, time: float, step: int, detail: str) -> str:
    """How a row's stop inside a step reads: "<status> at t = <time> s (step <step>): <detail>"."""
    return f"{status} at t = {time:.6g} s (step {step}): {detail}"


class Sampler:
    """When the core records a sample of the rows: every `every` steps (fixed-step methods), or at every accepted
    step (adaptive methods without output_dt), or at the multiples of `period` by dense output (adaptive with it)."""

    def __init__(self, *, every: int | None = None, period: float | None = None):
        self.every, self.period = every, period
        self.next_output = 1  # index of the next multiple of period

    def native_data(self) -> dict[str, Any]:
        """The sampling rule as the native kernel takes it (_native.Sampler's fields; 0: none)."""
        return {"every": self.every or 0, "period": self.period or 0.0}

    def due(self, t: float, k: int, tolerance: float) -> bool:
        """Whether the state at (t, k) is a sample."""
        if self.period is not None:
            if abs(t - self.next_output * self.period) <= tolerance:
                self.next_output += 1
                return True
            return t == 0.0
        if self.every is None:
            return True
        return k % self.every == 0


class Core:
    """Advances the running rows to stop times (see the module docstring).

    Running rows step together, so they share their step counts (steps, rejected steps); their evaluation counts
    differ only where Newton iterations do (implicit methods). Counts of rows that stopped are frozen in
    `stopped_counts`.

    Attributes:
        system, method: what is integrated, and how.
        kernel: the rows' states and the arithmetic of a step (kernels/: the row kernel; NativeCore's is native).
        control: the step-size controller (ConstantStep, or PIController for one adaptive row).
        sampler: when states are recorded (None: only when the driver asks, record()).
        store: where the samples go.
        rows: the running rows' indices in the run, shape (n,).
        stops: rows that stopped inside the core since the driver last took them (take_stops()).
        recorded: the time of the latest sample of the running rows.
    """

    def __init__(
        self,
        *,
        system: Any,
        method: Integrator,
        kernel: Kernel,
        control: ConstantStep | PIController,
        sampler: Sampler | None,
        store: SampleStore,
        B: int,
    ):
        if control.adaptive and kernel.n != 1:
            raise InvalidArgumentError("an adaptive step-size controller steps one row at a time")
        self.system, self.method, self.kernel = system, method, kernel
        self.control, self.sampler, self.store = control, sampler, store
        self._set_rows(np.arange(B))
        self.steps = 0  # accepted steps of the running rows
        self.rejected = 0  # rejected attempts of the running rows
        self.evaluations = 0  # evaluations every running row made
        self.extra_evaluations = np.zeros(B, dtype=np.int64)  # per position: evaluations beyond `evaluations`
        self.stopped_counts = np.zeros((B, len(COUNTERS)), dtype=np.int64)
        self.solver_stats: dict[int, dict[str, int]] = {}  # stopped rows' solver counts (contact methods)
        self.stops: list[RowStop] = []
        self.recorded = -math.inf
        self.ticks: Any = None  # sensors.Ticks when the system's sensors tick (the entry point sets it)

    def _set_rows(self, rows: np.ndarray) -> None:
        self.rows = rows
        # How the running rows index the store: an int for one row, a slice for all of them (cheap), else the rows.
        self._index: Any = int(rows[0]) if len(rows) == 1 else (slice(None) if len(rows) == self.store.B else rows)

    @property
    def stepper(self) -> StepKernel:
        """The kernel as advance() steps it, one step at a time (NativeCore, whose kernel steps inside the engine,
        has its own advance())."""
        return cast(StepKernel, self.kernel)

    @property
    def t(self) -> float:
        """The time of the running rows' current state [s]."""
        return self.kernel.t

    def counts(self, b: int) -> tuple[int, int, int]:
        """Row b's (steps, rejected steps, evaluations) so far."""
        position = np.flatnonzero(self.rows == b)
        if len(position):
            return self.steps, self.rejected, self.evaluations + int(self.extra_evaluations[position[0]])
        steps, rejected, evaluations = self.stopped_counts[b]
        return int(steps), int(rejected), int(evaluations)

    # ---- the loop ------------------------------------------------------------------------------------------------
    def advance(self, t_stop: float, *, max_steps: int | None = None) -> str:
        """Step the running rows towards t_stop: until they reach it (REACHED), after max_steps accepted steps
        (STEPPED), when the sample store is full (FULL) or when no row is left (EMPTY). Samples due at the current
        time are recorded first, so that a sample at a control instant carries the torque set there."""
        kernel, control, sampler, store = self.stepper, self.control, self.sampler, self.store
        adaptive = control.adaptive
        tolerance = LANDING_FRACTION * control.scale(t_stop) if adaptive else 0.0
        steps = 0
        while True:
            t = kernel.t
            if t >= t_stop:  # a sample due here is taken by the next call, after the driver's control
                return REACHED
            if sampler is not None and self.recorded != t and sampler.due(t, self.steps, tolerance):
                self.record()
            if not kernel.n:
                return EMPTY
            if steps == max_steps:
                return STEPPED
            if store.full:
                return FULL
            t_next = control.propose(t_stop)
            h = control.step_size(t_next)
            try:
                result = kernel.attempt(h)
            except Exception as exc:  # user code in the system (a scene's force): every running row fails with it
                self._user_failure(exc, t)
                return EMPTY
            evaluations = result.evaluations
            if type(evaluations) is int:
                self.evaluations += evaluations
            else:
                self.extra_evaluations[: len(evaluations)] += evaluations
            if result.failures:
                self._fail_rows(result.failures, t)
                if not kernel.n:
                    return EMPTY
            if adaptive:
                if not control.judge(h, result.error):
                    self.rejected += 1
                    kernel.reject()
                    if control.h < tolerance:
                        self._collapse(t, control.h, tolerance, result.error)
                        return EMPTY
                    continue
                if control.h < tolerance:
                    self._collapse(t, control.h, tolerance, None)
                    return EMPTY
                if sampler is not None and sampler.period is not None:
                    self._dense_samples(t, t_next, h, tolerance)
            bad = kernel.nonfinite()
            if len(bad):  # their last sample is the state before this step; they leave once it is accepted
                added = self._note_stops(bad, ["diverged"] * len(bad), self._diverged_messages(bad), t_next)
            kernel.accept(t_next)
            control.commit(t_next)
            self.steps += 1
            steps += 1
            if len(bad):
                self.stop(bad, counted=True, with_last=added)
                if not kernel.n:
                    return EMPTY
            if self.ticks is not None:
                self.ticks.after_step(self, h, t_next)

    def _dense_samples(self, t: float, t_next: float, h: float, tolerance: float) -> None:
        """Samples at the output instants strictly inside the accepted step (t, t_next), by dense output."""
        sampler, store = self.sampler, self.store
        assert sampler is not None and sampler.period is not None
        extra = 0
        while sampler.next_output * sampler.period < t_next - tolerance:
            t_out = sampler.next_output * sampler.period
            i = store.room()
            store.T[i, self._index] = t_out
            extra = self.stepper.write_dense(store, i, self._index, (t_out - t) / h, h, t_out)
            self._count(i, self._index)
            store.advance()
            sampler.next_output += 1
        self.evaluations += extra  # DOP853's extra stages, once per step

    # ---- samples -------------------------------------------------------------------------------------------------
    def record(self) -> None:
        """Record the running rows' current state as a sample, unless it is one already."""
        t = self.kernel.t
        if self.recorded == t or not self.kernel.n:
            return
        store = self.store
        i = store.room()
        index = self._index
        store.T[i, index] = t
        self.kernel.write_sample(store, i, index)
        self._count(i, index)
        store.advance()
        self.recorded = t

    def _record_stopping(self, js: np.ndarray) -> bool:
        """Record the current state of the running rows at positions js as their last sample (at index count),
        unless it is a sample already; returns whether it was recorded."""
        if self.recorded == self.kernel.t:
            return False
        store = self.store
        i = store.room()
        rows = self.rows[js]
        store.T[i, rows] = self.kernel.t
        self.kernel.write_sample(store, i, rows, js)
        self._count(i, rows, js)
        return True

    def _count(self, i: int, index: Any, js: np.ndarray | None = None) -> None:
        """Write the counts of the rows at `index` (positions js, default all running rows) into sample i."""
        counts = self.store.COUNTS
        counts[i, index, 0] = self.steps
        counts[i, index, 1] = self.rejected
        extra = self.extra_evaluations[: len(self.rows)] if js is None else self.extra_evaluations[js]
        counts[i, index, 2] = self.evaluations + (int(extra[0]) if type(index) is int else extra)

    # ---- the driver's interface ----------------------------------------------------------------------------------
    def set_torques(self, TAU: np.ndarray, jump: bool = True) -> None:
        """Hold TAU (n, nv) from now on. A torque given at a control instant is a jump (diffrax's made_jump): the
        solver state restarts (e.g. an FSAL stage, taken with the previous torque, is not reused)."""
        self.kernel.set_torques(TAU, jump)

    def stop(self, js: np.ndarray, *, counted: bool = False, with_last: bool = False) -> None:
        """Stop the running rows at positions js (their counts frozen as they are now; `counted`: the latest step,
        which they did not take, is not theirs; `with_last`: they hold a last sample at the store's index count)."""
        rows = self.rows[js]
        if type(self.method).solver_stats is not Integrator.solver_stats:  # else {}
            solver_stats = self.kernel.solver_stats
            for j, b in zip(js.tolist(), rows.tolist(), strict=True):
                stats = solver_stats(j)
                if stats:
                    self.solver_stats[b] = stats
        counts = self.stopped_counts[rows]
        counts[:, 0] = self.steps - counted
        counts[:, 1] = self.rejected
        counts[:, 2] = self.evaluations + self.extra_evaluations[js]
        self.stopped_counts[rows] = counts
        self.store.stop(rows, with_last)
        keep = np.ones(self.kernel.n, dtype=bool)
        keep[js] = False
        self.kernel.keep(keep)
        n = int(keep.sum())
        self.extra_evaluations[:n] = self.extra_evaluations[: len(keep)][keep]
        self._set_rows(self.rows[keep])

    def take_stops(self) -> list[RowStop]:
        stops, self.stops = self.stops, []
        return stops

    # ---- rows that stop inside the core --------------------------------------------------------------------------
    def _stop_rows(self, js: np.ndarray, statuses: list[str], details: list[str], time: float) -> None:
        """Record the current state of rows js as their last sample (unless it is one already) and stop them."""
        added = self._note_stops(js, statuses, details, time)
        self.stop(js, with_last=added)

    def _note_stops(self, js: np.ndarray, statuses: list[str], details: list[str], time: float) -> bool:
        """Record the current state of rows js as their last sample (unless it is one already) and note why they
        stop at the next step (stop() removes them); returns whether a sample was added for them."""
        added = self._record_stopping(js)
        i = self.store.count + added - 1
        step = self.steps + 1
        for j, status, detail in zip(js.tolist(), statuses, details, strict=True):
            self.stops.append(RowStop(int(self.rows[j]), status, time, step, detail, i, added))
        return added

    def _fail_rows(self, failures: list[tuple[int, str, str]], t: float) -> None:
        details = [f"{message}; try a smaller dt (now {self.dt_hint:g} s)" for _, _, message in failures]
        js = np.array([j for j, _, _ in failures], dtype=int)
        self._stop_rows(js, [status for _, status, _ in failures], details, t)

    def _user_failure(self, exc: Exception, t: float) -> None:
        detail = f"{type(exc).__name__} raised in the dynamics: {exc}"
        js = np.arange(self.kernel.n)
        added = self._record_stopping(js)
        i = self.store.count + added - 1
        for j in js.tolist():
            self.stops.append(RowStop(int(self.rows[j]), "failed", t, self.steps + 1, detail, i, added, exc))
        self.stop(js, with_last=added)

    def _diverged_messages(self, bad: np.ndarray) -> list[str]:
        return [diverged_detail(self.system, self.stepper.nonfinite_dof(j), self.dt_hint) for j in bad.tolist()]

    def _collapse(self, t: float, h: float, minimum: float, error: float | None) -> None:
        detail = collapsed_detail(self.system, h, minimum, error)
        self._stop_rows(np.array([0]), ["step_collapsed"], [detail], t)

    @property
    def dt_hint(self) -> float:
        """The step the cure messages name [s]."""
        return self.control.dt if isinstance(self.control, ConstantStep) else self.control.first_step


# ---- why rows stop inside the core (the row kernel's and the native kernel's: RowStop.detail) -------------------
def diverged_detail(system: Any, dof: int, dt: float) -> str:
    """Why a row stopped when its state became non-finite in velocity coordinate `dof`."""
    return f"the state became non-finite in '{system.dof_names[dof]}'; {cure_for_dt(system, dt)}"


def collapsed_detail(system: Any, h: float, minimum: float, error: float | None) -> str:
    """Why an adaptive row stopped when its step fell to h [s] below `minimum` [s] (error: the norm, if judged)."""
    norm = f" (error norm {error:.3g})" if error is not None else ""
    return (
        f"the step fell to {h:.3g} s, below the {minimum:.3g} s minimum{norm}; the problem may be stiff or "
        f"singular here: {cure_for_stiffness(system)}"
    )


# ---- cures named in messages -------------------------------------------------------------------------------------
def stable_implicit_integrators(system: Any) -> list[str]:
    """Names of the A-stable implicit integrators that accept this system (the cure for stiffness)."""
    names = []
    for name, method in sorted(INTEGRATORS.items()):
        if method.implicit and method.a_stable:
            try:
                method.check_system(system)
            except InvalidArgumentError:
                continue
            names.append(name)
    return names


def cure_for_dt(system: Any, dt: float) -> str:
    """What to try after a divergence or a failed step: a smaller step, or a stable implicit method."""
    implicit = stable_implicit_integrators(system)
    also = f", or an implicit integrator ({', '.join(implicit)})" if implicit else ""
    return f"try a smaller dt (now {dt:g} s){also}"


def cure_for_stiffness(system: Any) -> str:
    """What to try after an adaptive step collapsed."""
    implicit = stable_implicit_integrators(system)
    return (
        f"try an implicit integrator ({', '.join(implicit)}) or looser tolerances"
        if implicit
        else "try looser tolerances"
    )
