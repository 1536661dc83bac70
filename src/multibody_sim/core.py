"""THE stepping loop: advance rows of states, one time shared by the rows, to a stop time.

The core owns the step size (a step-size controller: constant steps or the PI controller), the solver state, the
per-step finiteness check, the step statistics and the sampling of the states it passes; a kernel does the
arithmetic of a step for every row: the row kernel (the integrator's own ``attempt``, row by row: the Python
reference path) or a batch kernel (the same arithmetic vectorised over the rows, integrators/batch.py). The driver
(driver.py) decides where to stop: control instants, the end of the run; it owns everything users see.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from .exceptions import InvalidArgumentError
from .integrators import INTEGRATORS, Integrator
from .integrators.base import OK, Attempt
from .recording import COUNTERS, SampleStore
from .step_control import LANDING_FRACTION, ConstantStep, PIController

# Why advance() returned.
REACHED = "reached"  # the stop time
STEPPED = "stepped"  # max_steps accepted steps
FULL = "full"  # the sample store reached its soft capacity
EMPTY = "empty"  # no row left running


@dataclass(frozen=True)
class RowStop:
    """A row that stopped inside the core: why, when, and the sample that holds its last state.

    Attributes:
        row: the row's index in the run (its batch index).
        status: "diverged", "newton_failed", "step_collapsed", "failed" (an exception from user code).
        message: the whole message, as SimulationError says it.
        time: the time of the event [s].
        sample: index in the store of the row's last sample (its state before the failed step).
        added: whether that sample was taken for the stop (else it was a regular sample).
        cause: the user's exception, for status "failed".
    """

    row: int
    status: str
    message: str
    time: float
    sample: int
    added: bool
    cause: BaseException | None = None
    bad_output: bool = False  # "failed" on a controller output that is not a torque (native controllers)


class Kernel(Protocol):
    """The arithmetic of one step for the running rows (see RowKernel, integrators/batch.py)."""

    @property
    def n(self) -> int:
        """Running rows."""

    @property
    def t(self) -> float:
        """The time of the current state [s]."""

    @property
    def k(self) -> int:
        """Accepted steps so far."""

    def set_torques(self, TAU: np.ndarray, jump: bool) -> None:
        """Hold TAU (n, nv) from now on; with `jump`, every row restarts its solver state (a new torque)."""

    def attempt(self, h: float) -> KernelAttempt:
        """Attempt a step of h from the current state of every row (the result is kept as pending)."""

    def nonfinite(self) -> np.ndarray:
        """Rows (indices) whose pending state is not finite."""

    def accept(self, t_next: float) -> None:
        """The pending state becomes the current one, at time t_next (one assignment: never half done)."""

    def reject(self) -> None:
        """Drop the pending state; keep what the attempt learned of the step's start (its retry state)."""

    def keep(self, keep: np.ndarray) -> None:
        """Keep only the rows where `keep` (bool, shape (n,)) is true."""

    def write_sample(self, store: SampleStore, i: int, rows: np.ndarray, js: np.ndarray | None = None) -> None:
        """Write the current state of the running rows (q, v, tau, energies, flows, records) as sample i of `rows`
        (or of the rows at positions js only, whose indices in the run are `rows`)."""

    def nonfinite_dof(self, j: int) -> int:
        """The first velocity coordinate of row j's pending state that is not finite."""

    def write_dense(self, store: SampleStore, i: int, rows: np.ndarray, theta: float, h: float, t_out: float) -> int:
        """Write the pending step's dense output at t + θh (= t_out) as sample i; returns the evaluations it cost."""

    def state_of(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        """Row j's current (q, v) (copies)."""

    def states(self) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """The running rows' current q and v, one array each, which a controller may see but not modify."""


@dataclass(slots=True)
class KernelAttempt:
    """A step attempted for every running row.

    Attributes:
        error: the scaled error norm (adaptive methods: one row), or None.
        evaluations: evaluations each row's attempt cost, shape (n,) (or an int for every row).
        failures: (j, status, message) of rows whose step failed.
    """

    error: float | None
    evaluations: Any
    failures: list[tuple[int, str, str]]


class Sampler:
    """When the core records a sample of the rows: every `every` steps (fixed-step methods), or at every accepted
    step (adaptive methods without output_dt), or at the multiples of `period` by dense output (adaptive with it)."""

    def __init__(self, *, every: int | None = None, period: float | None = None):
        self.every, self.period = every, period
        self.next_output = 1  # index of the next multiple of period

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
        kernel: the arithmetic of a step (row or batch).
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

    def _set_rows(self, rows: np.ndarray) -> None:
        self.rows = rows
        # How the running rows index the store: an int for one row, a slice for all of them (cheap), else the rows.
        self._index: Any = int(rows[0]) if len(rows) == 1 else (slice(None) if len(rows) == self.store.B else rows)

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
        kernel, control, sampler, store = self.kernel, self.control, self.sampler, self.store
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
                added = self._note_stops(bad, ["diverged"] * len(bad), self._diverged_messages(bad, t_next), t_next)
            kernel.accept(t_next)
            control.commit(t_next)
            self.steps += 1
            steps += 1
            if len(bad):
                self.stop(bad, counted=True, with_last=added)
                if not kernel.n:
                    return EMPTY

    def _dense_samples(self, t: float, t_next: float, h: float, tolerance: float) -> None:
        """Samples at the output instants strictly inside the accepted step (t, t_next), by dense output."""
        sampler, store = self.sampler, self.store
        assert sampler is not None and sampler.period is not None
        extra = 0
        while sampler.next_output * sampler.period < t_next - tolerance:
            t_out = sampler.next_output * sampler.period
            i = store.room()
            store.T[i, self._index] = t_out
            extra = self.kernel.write_dense(store, i, self._index, (t_out - t) / h, h, t_out)
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
        solver_stats = getattr(self.kernel, "solver_stats", None)
        if solver_stats is not None and type(self.method).solver_stats is not Integrator.solver_stats:  # else {}
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
    def _stop_rows(self, js: np.ndarray, statuses: list[str], messages: list[str], time: float) -> None:
        """Record the current state of rows js as their last sample (unless it is one already) and stop them."""
        added = self._note_stops(js, statuses, messages, time)
        self.stop(js, with_last=added)

    def _note_stops(self, js: np.ndarray, statuses: list[str], messages: list[str], time: float) -> bool:
        """Record the current state of rows js as their last sample (unless it is one already) and note why they
        stop (stop() removes them); returns whether a sample was added for them."""
        added = self._record_stopping(js)
        i = self.store.count + added - 1
        for j, status, message in zip(js.tolist(), statuses, messages, strict=True):
            self.stops.append(RowStop(int(self.rows[j]), status, message, time, i, added))
        return added

    def _fail_rows(self, failures: list[tuple[int, str, str]], t: float) -> None:
        messages = [
            f"{status} at t = {t:.6g} s (step {self.steps + 1}): {message}; try a smaller dt (now {self.dt_hint:g} s)"
            for _, status, message in failures
        ]
        js = np.array([j for j, _, _ in failures], dtype=int)
        self._stop_rows(js, [status for _, status, _ in failures], messages, t)

    def _user_failure(self, exc: Exception, t: float) -> None:
        message = f"failed at t = {t:.6g} s (step {self.steps + 1}): {type(exc).__name__} raised in the dynamics: {exc}"
        js = np.arange(self.kernel.n)
        added = self._record_stopping(js)
        i = self.store.count + added - 1
        for j in js.tolist():
            self.stops.append(RowStop(int(self.rows[j]), "failed", message, t, i, added, exc))
        self.stop(js, with_last=added)

    def _diverged_messages(self, bad: np.ndarray, t_next: float) -> list[str]:
        return [
            diverged_message(self.system, t_next, self.steps + 1, self.kernel.nonfinite_dof(j), self.dt_hint)
            for j in bad.tolist()
        ]

    def _collapse(self, t: float, h: float, minimum: float, error: float | None) -> None:
        message = collapsed_message(self.system, t, self.steps + 1, h, minimum, error)
        self._stop_rows(np.array([0]), ["step_collapsed"], [message], t)

    @property
    def dt_hint(self) -> float:
        """The step the cure messages name [s]."""
        return self.control.dt if isinstance(self.control, ConstantStep) else self.control.first_step


# ---- the row kernel ---------------------------------------------------------------------------------------------
class RowKernel:
    """The integrator's own attempt(), row by row: the Python reference path of every method.

    The state of each row lives in Python lists; a step's result replaces them in one assignment.
    """

    def __init__(
        self,
        system: Any,
        method: Integrator,
        Q0: np.ndarray,
        V0: np.ndarray,
        *,
        rtol: float | None = None,
        atol: float | None = None,
    ):
        self.system, self.method = system, method
        self.rtol, self.atol = rtol, atol
        n_elements = len(system.ledger_elements)
        q = [np.array(row, dtype=float) for row in Q0]
        v = [np.array(row, dtype=float) for row in V0]
        flows = [np.zeros(n_elements) for _ in q]
        states = [method.init(system, qj, vj) for qj, vj in zip(q, v, strict=True)]
        self.tau = [np.zeros(system.nv) for _ in q]
        # (q, v, flows, solver states, t, k): replaced whole by accept(), so an interrupt never sees half a step
        self.now: tuple[list[Any], list[Any], list[Any], list[Any], float, int] = (q, v, flows, states, 0.0, 0)
        self.pending: list[Attempt] = []
        self.record_width = sum(width for _, _, width in system.record_fields)
        # The time-stepper of a contact scene records the contacts of each step (Trajectory.contacts).
        has_contact = getattr(system, "contact", None) is not None
        self._contact_records = getattr(method, "contact_records", None) if has_contact else None

    @property
    def n(self) -> int:
        return len(self.now[0])

    @property
    def t(self) -> float:
        return self.now[4]

    @property
    def k(self) -> int:
        return self.now[5]

    def start_at(self, t: float, k: int = 0) -> None:
        q, v, flows, states, _, _ = self.now
        self.now = (q, v, flows, states, t, k)

    def set_torques(self, TAU: np.ndarray, jump: bool) -> None:
        q, v, flows, states, t, k = self.now
        self.tau = list(TAU)
        if jump:
            method, system = self.method, self.system
            states = [method.restart(system, qj, vj, sj) for qj, vj, sj in zip(q, v, states, strict=True)]
            self.now = (q, v, flows, states, t, k)

    def attempt(self, h: float) -> KernelAttempt:
        q, v, _, states, t, _ = self.now
        method, system, rtol, atol = self.method, self.system, self.rtol, self.atol
        if len(q) == 1:  # simulate() and Stepper: one row
            a = method.attempt(system, q[0], v[0], self.tau[0], h, t, states[0], rtol=rtol, atol=atol)
            self.pending = [a]
            return KernelAttempt(a.error, a.evaluations, [] if a.status == OK else [(0, a.status, a.message)])
        self.pending = pending = [
            method.attempt(system, q[j], v[j], self.tau[j], h, t, states[j], rtol=rtol, atol=atol)
            for j in range(len(q))
        ]
        failures = [(j, a.status, a.message) for j, a in enumerate(pending) if a.status != OK]
        evaluations = np.array([a.evaluations for a in pending])
        return KernelAttempt(
            None, int(evaluations[0]) if (evaluations == evaluations[0]).all() else evaluations, failures
        )

    def nonfinite(self) -> np.ndarray:
        # NaN or inf anywhere makes the sum non-finite (so can a huge but finite state, whose squares overflow: the
        # exact check tells them apart).
        if len(self.pending) == 1:
            a = self.pending[0]
            if math.isfinite(a.q @ a.q + a.v @ a.v) or (np.isfinite(a.q).all() and np.isfinite(a.v).all()):
                return _NONE
            return _FIRST
        bad = [
            j
            for j, a in enumerate(self.pending)
            if not math.isfinite(a.q @ a.q + a.v @ a.v) and not (np.isfinite(a.q).all() and np.isfinite(a.v).all())
        ]
        return np.array(bad, dtype=int)

    def nonfinite_dof(self, j: int) -> int:
        """The first velocity coordinate of row j's pending state that is not finite (configuration: in the
        tangent space)."""
        a, q = self.pending[j], self.now[0][j]
        bad_v = ~np.isfinite(a.v)
        if bad_v.any():
            return int(np.argmax(bad_v))
        finite_q = np.where(np.isfinite(a.q), a.q, 0.0)
        return int(np.argmax(~np.isfinite(self.system.space.difference(q, finite_q))))

    def accept(self, t_next: float) -> None:
        _, _, flows, _, _, k = self.now
        pending = self.pending
        if len(pending) == 1:
            a = pending[0]
            self.now = ([a.q], [a.v], [flows[0] + a.flows], [a.state], t_next, k + 1)
            return
        self.now = (
            [a.q for a in pending],
            [a.v for a in pending],
            [f + a.flows for f, a in zip(flows, pending, strict=True)],
            [a.state for a in pending],
            t_next,
            k + 1,
        )

    def reject(self) -> None:
        q, v, flows, states, t, k = self.now
        retry = [a.retry_state if a.retry_state is not None else s for a, s in zip(self.pending, states, strict=True)]
        self.now = (q, v, flows, retry, t, k)

    def keep(self, keep: np.ndarray) -> None:
        q, v, flows, states, t, k = self.now
        js = np.flatnonzero(keep).tolist()
        self.tau = [self.tau[j] for j in js]
        self.pending = [self.pending[j] for j in js] if len(self.pending) == len(q) else []
        self.now = ([q[j] for j in js], [v[j] for j in js], [flows[j] for j in js], [states[j] for j in js], t, k)

    def state_of(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        return self.now[0][j].copy(), self.now[1][j].copy()

    def flows_of(self, j: int) -> np.ndarray:
        """Row j's cumulative ledger flows [J], shape (n_elements,) (not modified in place: a step makes new ones)."""
        return self.now[2][j]

    def set_row(self, j: int, q: np.ndarray, v: np.ndarray) -> None:
        """Put row j at (q, v) by hand (a jump: its solver state restarts; its flows stay)."""
        Q, V, flows, states, t, k = self.now
        Q, V, states = list(Q), list(V), list(states)
        Q[j], V[j], states[j] = q, v, self.method.init(self.system, q, v)
        self.now = (Q, V, flows, states, t, k)

    def solver_stats(self, j: int) -> dict[str, int]:
        """Counts row j's solver state keeps (a contact solver's: steps, unconverged steps, iterations)."""
        return self.method.solver_stats(self.now[3][j])

    def states(self) -> tuple[list[np.ndarray], list[np.ndarray]]:
        return self.now[0], self.now[1]  # never modified in place: a step makes new arrays

    def write_sample(self, store: SampleStore, i: int, index: Any, js: np.ndarray | None = None) -> None:
        q, v, flows, states, t, _ = self.now
        if type(index) is int:  # one row
            j = 0 if js is None else int(js[0])
            self._write(store, i, index, q[j], v[j], flows[j], self.tau[j], t)
            self._write_contacts(store, i, index, states[j])
            return
        rows = np.arange(store.B)[index] if isinstance(index, slice) else index
        positions = range(len(q)) if js is None else js.tolist()
        for j, b in zip(positions, rows.tolist(), strict=True):
            self._write(store, i, b, q[j], v[j], flows[j], self.tau[j], t)
            self._write_contacts(store, i, b, states[j])

    def _write_contacts(self, store: SampleStore, i: int, b: int, state: Any) -> None:
        """A contact method's active contacts (those of the step that ended at this sample) into the store."""
        records = self._contact_records
        if records is not None:
            store.write_contacts(i, b, records(self.system, state))

    def write_dense(self, store: SampleStore, i: int, index: Any, theta: float, h: float, t_out: float) -> int:
        q, v, flows, _, _, _ = self.now
        extra = 0
        rows = [index] if type(index) is int else (np.arange(store.B)[index] if isinstance(index, slice) else index)
        for j, b in enumerate(list(rows)):
            attempt = self.pending[j]
            q_out, v_out, flows_out = self.method.dense_output(self.system, q[j], v[j], attempt, h, theta)
            self._write(store, i, b, q_out, v_out, flows[j] + flows_out, self.tau[j], t_out)
            extra = getattr(attempt.detail, "extra_evaluations", 0)
        return extra

    def _write(
        self,
        store: SampleStore,
        i: int,
        b: int,
        q: np.ndarray,
        v: np.ndarray,
        flows: np.ndarray,
        tau: np.ndarray,
        t: float,
    ) -> None:
        system = self.system
        store.Q[i, b] = q
        store.V[i, b] = v
        store.TAU[i, b] = tau
        store.FLOWS[i, b] = flows
        store.ENERGY[i, b] = system.unchecked_energies(q, v)
        if self.record_width:
            system.unchecked_record(q, v, tau, t, store.EXTRA[i, b])

    def snapshot(self) -> tuple[Any, ...]:
        return self.now, list(self.tau)

    def restore(self, snapshot: tuple[Any, ...]) -> None:
        self.now, self.tau = snapshot[0], list(snapshot[1])
        self.pending = []


_NONE = np.zeros(0, dtype=int)
_FIRST = np.zeros(1, dtype=int)


# ---- messages of rows that stop inside the core (the row kernel's and the native kernel's) ----------------------
def diverged_message(system: Any, t_next: float, step: int, dof: int, dt: float) -> str:
    """Why a row stopped when its state became non-finite in velocity coordinate `dof` at step `step`."""
    return (
        f"diverged at t = {t_next:.6g} s (step {step}): the state became non-finite in "
        f"'{system.dof_names[dof]}'; {cure_for_dt(system, dt)}"
    )


def collapsed_message(system: Any, t: float, step: int, h: float, minimum: float, error: float | None) -> str:
    """Why an adaptive row stopped when its step fell to h [s] below `minimum` [s] (error: the norm, if judged)."""
    norm = f" (error norm {error:.3g})" if error is not None else ""
    return (
        f"step_collapsed at t = {t:.6g} s (step {step}): the step fell to "
        f"{h:.3g} s, below the {minimum:.3g} s minimum{norm}; the problem may be stiff or singular here: "
        f"{cure_for_stiffness(system)}"
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
