"""The row kernel: the integrator's own attempt(), row by row, the Python reference path of every method (the
specification the native kernel renders) and the kernel of every run without the compiled extension."""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from ..integrators import Integrator
from ..integrators.base import OK, Attempt
from ..recording import SampleStore
from .base import KernelAttempt


class RowState(NamedTuple):
    """The running rows' current state, replaced whole by every step (an interrupt never sees half a step).

    Attributes:
        q, v: each row's configuration (nq,) and velocity (nv,) (never modified in place: a step makes new ones).
        flows: each row's cumulative ledger flows [J], shape (n_elements,).
        solver: each row's solver state (Integrator.init / attempt).
        t: the time [s].
    """

    q: list[np.ndarray]
    v: list[np.ndarray]
    flows: list[np.ndarray]
    solver: list[Any]
    t: float


class RowKernel:
    """The integrator's own attempt(), row by row (a StepKernel, kernels/base.py).

    The state of each row lives in Python lists (`now`, a RowState); a step's result replaces it in one assignment.
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
        systems: list[Any] | None = None,
    ):
        self.system, self.method = system, method
        self.rtol, self.atol = rtol, atol
        # each running row's own system (a randomised scene's rows: same structure, other values), or None
        self.systems = list(systems) if systems is not None else None
        n_elements = len(system.ledger_elements)
        q = [np.array(row, dtype=float) for row in Q0]
        v = [np.array(row, dtype=float) for row in V0]
        flows = [np.zeros(n_elements) for _ in q]
        solver = [method.init(self.system_of(j), qj, vj) for j, (qj, vj) in enumerate(zip(q, v, strict=True))]
        self.tau = [np.zeros(system.nv) for _ in q]
        self.now = RowState(q, v, flows, solver, 0.0)
        self.pending: list[Attempt] = []
        self.v_before: list[np.ndarray] = []  # the rows' velocities before the latest accepted step (sensors)
        self.record_width = sum(width for _, _, width in system.record_fields)
        # The time-stepper of a contact scene records the contacts of each step (Trajectory.contacts).
        has_contact = getattr(system, "contact", None) is not None
        self._contact_records = getattr(method, "contact_records", None) if has_contact else None

    def system_of(self, j: int) -> Any:
        """The system running row j steps on."""
        return self.system if self.systems is None else self.systems[j]

    @property
    def n(self) -> int:
        return len(self.now.q)

    @property
    def t(self) -> float:
        return self.now.t

    def start_at(self, t: float) -> None:
        now = self.now
        self.now = RowState(now.q, now.v, now.flows, now.solver, t)

    def set_torques(self, TAU: np.ndarray, jump: bool) -> None:
        self.tau = list(TAU)
        if jump:
            method, system_of = self.method, self.system_of
            q, v, flows, solver, t = self.now
            solver = [
                method.restart(system_of(j), qj, vj, sj)
                for j, (qj, vj, sj) in enumerate(zip(q, v, solver, strict=True))
            ]
            self.now = RowState(q, v, flows, solver, t)

    def attempt(self, h: float) -> KernelAttempt:
        q, v, _, solver, t = self.now
        method, system, rtol, atol = self.method, self.system, self.rtol, self.atol
        if len(q) == 1:  # simulate() and Stepper: one row
            system = self.system_of(0)
            a = method.attempt(system, q[0], v[0], self.tau[0], h, t, solver[0], rtol=rtol, atol=atol)
            self.pending = [a]
            return KernelAttempt(a.error, a.evaluations, [] if a.status == OK else [(0, a.status, a.message)])
        systems = self.systems or [system] * len(q)
        self.pending = pending = [
            method.attempt(systems[j], q[j], v[j], self.tau[j], h, t, solver[j], rtol=rtol, atol=atol)
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
        a, q = self.pending[j], self.now.q[j]
        bad_v = ~np.isfinite(a.v)
        if bad_v.any():
            return int(np.argmax(bad_v))
        finite_q = np.where(np.isfinite(a.q), a.q, 0.0)
        return int(np.argmax(~np.isfinite(self.system_of(j).space.difference(q, finite_q))))

    def accept(self, t_next: float) -> None:
        flows = self.now.flows
        pending = self.pending
        self.v_before = self.now.v
        if len(pending) == 1:
            a = pending[0]
            self.now = RowState([a.q], [a.v], [flows[0] + a.flows], [a.state], t_next)
            return
        self.now = RowState(
            [a.q for a in pending],
            [a.v for a in pending],
            [f + a.flows for f, a in zip(flows, pending, strict=True)],
            [a.state for a in pending],
            t_next,
        )

    def reject(self) -> None:
        q, v, flows, solver, t = self.now
        retry = [a.retry_state if a.retry_state is not None else s for a, s in zip(self.pending, solver, strict=True)]
        self.now = RowState(q, v, flows, retry, t)

    def keep(self, keep: np.ndarray) -> None:
        q, v, flows, solver, t = self.now
        js = np.flatnonzero(keep).tolist()
        self.tau = [self.tau[j] for j in js]
        if self.systems is not None:
            self.systems = [self.systems[j] for j in js]
        self.pending = [self.pending[j] for j in js] if len(self.pending) == len(q) else []
        self.v_before = [self.v_before[j] for j in js] if len(self.v_before) == len(q) else []
        self.now = RowState([q[j] for j in js], [v[j] for j in js], [flows[j] for j in js], [solver[j] for j in js], t)

    def flows_of(self, j: int) -> np.ndarray:
        """Row j's cumulative ledger flows [J], shape (n_elements,) (not modified in place: a step makes new ones)."""
        return self.now.flows[j]

    def set_row(self, j: int, q: np.ndarray, v: np.ndarray) -> None:
        """Put row j at (q, v) by hand (a jump: its solver state restarts; its flows stay)."""
        Q, V, flows, solver, t = self.now
        Q, V, solver = list(Q), list(V), list(solver)
        Q[j], V[j], solver[j] = q, v, self.method.init(self.system_of(j), q, v)
        self.now = RowState(Q, V, flows, solver, t)

    def solver_stats(self, j: int) -> dict[str, int]:
        """Counts row j's solver state keeps (a contact solver's: steps, unconverged steps, iterations)."""
        return self.method.solver_stats(self.now.solver[j])

    def states(self) -> tuple[list[np.ndarray], list[np.ndarray]]:
        return self.now.q, self.now.v  # never modified in place: a step makes new arrays

    def write_sample(self, store: SampleStore, i: int, index: Any, js: np.ndarray | None = None) -> None:
        q, v, flows, solver, t = self.now
        if type(index) is int:  # one row
            j = 0 if js is None else int(js[0])
            self._write(store, i, index, q[j], v[j], flows[j], self.tau[j], t, j)
            self._write_contacts(store, i, index, solver[j], j)
            return
        rows = np.arange(store.B)[index] if isinstance(index, slice) else index
        positions = range(len(q)) if js is None else js.tolist()
        for j, b in zip(positions, rows.tolist(), strict=True):
            self._write(store, i, b, q[j], v[j], flows[j], self.tau[j], t, j)
            self._write_contacts(store, i, b, solver[j], j)

    def measure(self, js: np.ndarray, h: float) -> np.ndarray:
        """The sensors' measurements of the rows at positions js after the step of h they just took, shape
        (len(js), width): their state now, the step's (v⁺ − v) / h, its contacts and the torque held over it."""
        q, v, _, solver, t = self.now
        out = np.empty((len(js), self.system.sensors.width))
        for k, j in enumerate(js.tolist()):
            a = (v[j] - self.v_before[j]) / h
            records = self._records(solver[j], j)
            self.system_of(j).sensors.measure(q[j], v[j], a, self.tau[j], t, records, h, out[k])
        return out

    def measure_start(self, js: np.ndarray, h: float) -> np.ndarray:
        """The sensors' first measurements of the rows at positions js, at their state now (no step has ended):
        with the acceleration and contacts of a step of h under a zero command, taken and discarded (a step that fails
        or raises gives zero acceleration and no contact)."""
        method = self.method
        q, v, _, solver, t = self.now
        zero = np.zeros(self.system.nv)
        out = np.empty((len(js), self.system.sensors.width))
        for k, j in enumerate(js.tolist()):
            system = self.system_of(j)
            a, records = zero, None
            try:
                trial = method.attempt(system, q[j], v[j], zero, h, t, solver[j], rtol=self.rtol, atol=self.atol)
            except Exception:  # user code in the system: the run's first step says so
                trial = None
            if trial is not None and trial.status == OK:
                a, records = (trial.v - v[j]) / h, self._records(trial.state, j)
            system.sensors.measure(q[j], v[j], a, zero, t, records, h, out[k])
        return out

    def _records(self, state: Any, j: int) -> np.ndarray | None:
        """A contact method's contacts of row j's step that produced `state`, or None."""
        records = self._contact_records
        return records(self.system_of(j), state) if records is not None else None

    def _write_contacts(self, store: SampleStore, i: int, b: int, state: Any, j: int) -> None:
        """A contact method's active contacts (those of the step that ended at this sample) into the store."""
        records = self._contact_records
        if records is not None:
            store.write_contacts(i, b, records(self.system_of(j), state))

    def write_dense(self, store: SampleStore, i: int, index: Any, theta: float, h: float, t_out: float) -> int:
        q, v, flows = self.now.q, self.now.v, self.now.flows
        extra = 0
        rows = [index] if type(index) is int else (np.arange(store.B)[index] if isinstance(index, slice) else index)
        for j, b in enumerate(list(rows)):
            attempt = self.pending[j]
            q_out, v_out, flows_out = self.method.dense_output(self.system_of(j), q[j], v[j], attempt, h, theta)
            self._write(store, i, b, q_out, v_out, flows[j] + flows_out, self.tau[j], t_out, j)
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
        j: int,
    ) -> None:
        system = self.system_of(j)
        store.Q[i, b] = q
        store.V[i, b] = v
        store.TAU[i, b] = tau
        store.FLOWS[i, b] = flows
        store.ENERGY[i, b] = system.unchecked_energies(q, v)
        if self.record_width:
            system.unchecked_record(q, v, tau, t, store.EXTRA[i, b])

    def snapshot(self) -> tuple[RowState, list[np.ndarray]]:
        return self.now, list(self.tau)

    def restore(self, snapshot: tuple[RowState, list[np.ndarray]]) -> None:
        self.now, self.tau = snapshot[0], list(snapshot[1])
        self.pending = []


_NONE = np.zeros(0, dtype=int)
_FIRST = np.zeros(1, dtype=int)
