"""The batch kernel: explicit Runge–Kutta tableaux and semi-implicit Euler over many rows of states at once.

The arithmetic per row is the row kernel's (the methods' own attempt()): the same ordered sums per row (multi-term
stage sums, the step's combination and the ledger's dot products, ordered.py), exact products where a stage sum has
one power-of-two coefficient (RK4's), the system's batched forward dynamics (System.rows_dynamics: Pinocchio's
``abaInParallel``, which equals ``aba`` per row), and the batched manifold (state.BatchSpace: Pinocchio's
``integrate`` per joint); so each row equals the row kernel bit for bit. One exception: the chart map of
free-flyer, spherical and planar joints (in the stages after the first) is the same series but its products are
summed over the whole batch in another order (ConfigurationSpace.chart_rates), which can round differently by an
ulp: there the batch equals the row kernel to round-off.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from ..ordered import ordered_sum
from ..recording import SampleStore
from .explicit_rk import ExplicitRungeKutta
from .partitioned import SemiImplicitEuler


def batch_kernel_supported(system: Any, method: Any) -> bool:
    """Whether the batch kernel renders `method` on `system`: a fixed-step explicit Runge–Kutta tableau stepped by
    ExplicitRungeKutta's own attempt, or semi-implicit Euler, on a system with batched dynamics."""
    if getattr(method, "adaptive", False) or getattr(method, "implicit", False):
        return False
    if isinstance(method, ExplicitRungeKutta):
        supported = type(method).attempt is ExplicitRungeKutta.attempt  # a subclass's own step is not rendered here
    else:
        supported = type(method).attempt is SemiImplicitEuler.attempt and isinstance(method, SemiImplicitEuler)
    return supported and hasattr(system, "rows_dynamics")


def _exact_power_of_two(c: float) -> bool:
    """Whether multiplying by c is exact (c = ±2^k): then (c K) h == K (c h) bit for bit."""
    return c != 0.0 and math.frexp(c)[0] in (0.5, -0.5)


@dataclass(frozen=True)
class _Layout:
    """Column layout of the stage buffers (see _Views)."""

    nq: int
    nv: int
    n_ledger: int
    stages: int
    k: int  # first column of K: v itself (the chart rate on flat spaces) or a separate xi' block

    @property
    def width(self) -> int:
        return self.k + 2 * self.nv + self.n_ledger

    @property
    def shift(self) -> int:
        """Flat offset from a vector coordinate of q (or v) to its rate in K, when the non-vector joints come
        first (each has nq - nv more coordinates than velocities)."""
        return self.k - (self.nq - self.nv)


class _Views:
    """Named views into one stage buffer W of shape (stages, n, width): W[i] is stage i's rows
    [q | v | xi' (curved charts only) | v' | ledger power], one contiguous block per stage; W[0] holds the state
    the step starts from. K, the stage derivatives (xi', v', ledger power) of each row, is a (n, stages, m) view
    whose per-row blocks the BLAS calls read as ExplicitRungeKutta's K."""

    def __init__(self, W: np.ndarray, layout: _Layout):
        nq, nv, k, shift = layout.nq, layout.nv, layout.k, layout.shift
        stages = range(len(W))
        self.W = W
        self.flat = [W[i].reshape(-1) for i in stages]
        # Flat views offset by `shift`: head[i][x] and tail[j][x] are the same row's column of stage i's state
        # [q | v] and the matching column of stage j's K (see BatchRungeKutta._rk_step).
        self.head = [f[: len(f) - shift] for f in self.flat]
        self.tail = [f[shift:] for f in self.flat]
        self.X = W[0][:, : nq + nv]  # the state [q | v]
        self.Q = W[0][:, :nq]
        self.V = W[0][:, nq : nq + nv]
        self.K = W[:, :, k:].transpose(1, 0, 2)
        self.Ks = [W[i][:, k:] for i in stages]
        self.Xs = [W[i][:, : nq + nv] for i in stages]
        self.Qs = [W[i][:, :nq] for i in stages]
        self.Vs = [W[i][:, nq : nq + nv] for i in stages]
        self.XI_DOT = [W[i][:, k : k + nv] for i in stages]
        self.A = [W[i][:, k + nv : k + 2 * nv] for i in stages]
        self.P = [W[i][:, k + 2 * nv :] for i in stages]
        self.flows = np.zeros((W.shape[1], layout.n_ledger))


class BatchRungeKutta:
    """The batch kernel (see the module docstring) for the stepping core: the running rows' state lives in stage 0
    of one of two stage buffers, and each step writes the next state into the other's, so a step allocates nothing
    and the current state stays intact until the step is accepted; ``now = (buffer, t, k)`` switches in one
    assignment (an interrupt never sees a state from one step with the time of another).

    Args:
        system: a robot or scene with batched dynamics (rows_dynamics).
        method: an explicit Runge–Kutta tableau or semi-implicit Euler (batch_kernel_supported).
        Q0, V0: the rows' initial states, shapes (n, nq), (n, nv).
        dynamics: the system's batched dynamics (System.rows_dynamics).
        torque_free: no torque is ever applied (no controller): the ledger is skipped when it has only the
            torques' element (every flow is zero then).
    """

    def __init__(
        self,
        system: Any,
        method: Any,
        Q0: np.ndarray,
        V0: np.ndarray,
        *,
        dynamics: Any,
        torque_free: bool = False,
    ):
        self.system, self.method = system, method
        self.dynamics = dynamics
        self.space = system.space.batch
        self.chart_map = not system.space.is_flat
        self.sie = isinstance(method, SemiImplicitEuler)
        nq, nv = system.nq, system.nv
        self.nq, self.nv = nq, nv
        n_ledger = len(system.ledger_elements)
        self.ledger_needed = not (torque_free and n_ledger == 1)
        self.torques = not torque_free
        self.record_width = sum(width for _, _, width in system.record_fields)
        if self.sie:
            stages = 1
            self.stage_rules: list[Any] = []
        else:
            a = method.a
            stages = len(a)
            self.stage_rules = [self._rule(a[i, :i]) for i in range(1, stages)]
            self.weights = method.b
            self.c = method.c
            self.chart_terms = method.chart_terms  # the chart map's series, truncated as the method's step does
        self.layout = _Layout(nq, nv, n_ledger, stages, nq + nv if self.chart_map else nq)
        # (stage, source stage, coefficient) when every stage takes the fast path of _rk_step, else None
        self.shifted_stages: list[tuple[int, int, float]] | None = None
        if not self.sie and self.space.aligned and all(isinstance(r, tuple) for r in self.stage_rules):
            self.shifted_stages = [(i, r[0], r[1]) for i, r in enumerate(self.stage_rules, start=1)]
        self.pending_bad: np.ndarray | None = None
        self._allocate(np.concatenate([Q0, V0], axis=1), np.zeros((len(Q0), nv)), np.zeros((len(Q0), n_ledger)), 0.0, 0)

    @staticmethod
    def _rule(coefficients: np.ndarray) -> tuple[int, float] | np.ndarray:
        """How stage i's sum Σ_j a_ij K_j is formed: (j, a_ij) when it has one term whose coefficient is a power
        of two (one exact multiplication gives the BLAS call's result), else the coefficients (the BLAS call)."""
        nonzero = np.flatnonzero(coefficients)
        if len(nonzero) == 1 and _exact_power_of_two(float(coefficients[nonzero[0]])):
            return int(nonzero[0]), float(coefficients[nonzero[0]])
        return coefficients

    def _allocate(self, X: np.ndarray, TAU: np.ndarray, flows: np.ndarray, t: float, k: int) -> None:
        """Working arrays for len(X) running rows, starting from states X = [q | v], torques and flows."""
        n, layout = len(X), self.layout
        self.TAU = TAU.copy()
        self.Y = np.empty((n, layout.width - layout.k))  # a stage sum (when not shifted, see _rk_step)
        self.increment = np.zeros((n, layout.width))  # the step's increment in columns k: (0 before them)
        first, nv, shift, extra = layout.k, layout.nv, layout.shift, layout.nq - layout.nv
        self.increment_k, self.increment_flows = self.increment[:, first:], self.increment[:, first + 2 * nv :]
        self.increment_xi = self.increment[:, first : first + nv]
        self.increment_flat = self.increment.reshape(-1)
        self.increment_tail = self.increment_flat[shift:]
        # A stage's shifted product, whose rows hold c h K_j with its xi' block in columns extra:extra + nv
        shifted = np.empty(n * layout.width)
        self.shifted = shifted[: max(0, len(shifted) - shift)]
        self.shifted_xi = shifted.reshape(n, layout.width)[:, extra : extra + nv]
        self.views = [_Views(np.zeros((layout.stages, n, layout.width)), layout) for _ in range(2)]
        self.views[0].X[...] = X
        self.views[0].flows[...] = flows
        self.now = (0, t, k)

    # ---- the Kernel interface (core.py) --------------------------------------------------------------------------
    @property
    def n(self) -> int:
        return len(self.TAU)

    @property
    def t(self) -> float:
        return self.now[1]

    @property
    def k(self) -> int:
        return self.now[2]

    @property
    def current(self) -> _Views:
        """The buffer holding the running rows' latest accepted state (Q, V, flows)."""
        return self.views[self.now[0]]

    def start_at(self, t: float, k: int = 0) -> None:
        self.now = (self.now[0], t, k)

    def set_torques(self, TAU: np.ndarray, jump: bool) -> None:
        self.TAU[...] = TAU  # in place: no solver state to restart

    def attempt(self, h: float) -> Any:
        from ..core import KernelAttempt  # the core imports the integrators

        current = self.now[0]
        cur, nxt = self.views[current], self.views[1 - current]
        if self.sie:
            self._sie_step(cur, nxt, h)
        else:
            self._rk_step(cur, nxt, h)
        self.pending_bad = None
        return KernelAttempt(None, self.layout.stages, [])

    def nonfinite(self) -> np.ndarray:
        # NaN or inf anywhere makes the whole sum non-finite (so can a huge but finite state, or the junk beside the
        # state in the buffer: the exact check below tells them apart). One contiguous reduction over the new
        # state's buffer block is far cheaper than per-row ones.
        nxt = self.views[1 - self.now[0]]
        if math.isfinite(nxt.flat[0].sum()):
            return np.zeros(0, dtype=int)
        self.pending_bad = bad = np.flatnonzero(~np.isfinite(nxt.X).all(axis=1))
        return bad

    def nonfinite_dof(self, j: int) -> int:
        """The first non-finite coordinate of row j's pending state, as the row kernel names it (its step is redone
        exactly by the method's own attempt: which coordinates are NaN can depend on the order of operations)."""
        cur, nxt = self.current, self.views[1 - self.now[0]]
        q, v = cur.Q[j].copy(), cur.V[j].copy()
        h = self._last_h
        result = self.method.attempt(self.system, q, v, self.TAU[j].copy(), h, self.t)
        q_next, v_next = result.q, result.v
        if np.isfinite(q_next).all() and np.isfinite(v_next).all():  # only ever by round-off: keep ours
            q_next, v_next = nxt.Q[j], nxt.V[j]
        bad_v = ~np.isfinite(v_next)
        if bad_v.any():
            return int(np.argmax(bad_v))
        finite_q = np.where(np.isfinite(q_next), q_next, 0.0)
        return int(np.argmax(~np.isfinite(self.system.space.difference(q, finite_q))))

    def accept(self, t_next: float) -> None:
        self.now = (1 - self.now[0], t_next, self.now[2] + 1)

    def reject(self) -> None:
        raise AssertionError("the batch kernel steps fixed steps only")  # pragma: no cover

    def keep(self, keep: np.ndarray) -> None:
        if keep.all():
            return
        cur = self.current
        self._allocate(cur.X[keep], self.TAU[keep], cur.flows[keep], self.t, self.k)

    def state_of(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        cur = self.current
        return cur.Q[j].copy(), cur.V[j].copy()

    def states(self) -> tuple[list[np.ndarray], list[np.ndarray]]:
        cur = self.current
        return list(cur.Q.copy()), list(cur.V.copy())

    def write_sample(self, store: SampleStore, i: int, index: Any, js: np.ndarray | None = None) -> None:
        cur = self.current
        at = np.array([index]) if type(index) is int else index
        Q, V, flows, TAU = (cur.Q, cur.V, cur.flows, self.TAU) if js is None else (
            cur.Q[js], cur.V[js], cur.flows[js], self.TAU[js]
        )  # fmt: skip
        store.Q[i, at] = Q
        store.V[i, at] = V
        store.TAU[i, at] = TAU
        store.FLOWS[i, at] = flows
        store.ENERGY[i, at] = self.system.rows_energies(Q, V)
        if self.record_width:
            extra = np.empty((len(Q), self.record_width))
            self.system.rows_record(Q, V, TAU, self.t, extra)
            store.EXTRA[i, at] = extra

    def write_dense(self, store: SampleStore, i: int, rows: np.ndarray, theta: float, h: float, t_out: float) -> int:
        raise AssertionError("the batch kernel has no dense output")  # pragma: no cover

    # ---- the steps -----------------------------------------------------------------------------------------------
    def _rk_step(self, cur: _Views, nxt: _Views, h: float) -> None:
        """ExplicitRungeKutta.attempt on every row: stages into cur's buffer, the new state and flows into nxt's."""
        self._last_h = h
        t = self.t
        evaluate, c = self._evaluate, self.c
        if self.chart_map:  # at the step's start xi = 0, where the chart Jacobian is the identity
            np.copyto(cur.XI_DOT[0], cur.V)
        evaluate(cur, 0, t + c[0] * h)
        if self.shifted_stages is not None:
            # Vector coordinates and stage sums of one exact product: [q | v] + c h [xi'_j | v'_j] for all rows in
            # two contiguous operations. On flat views a vector coordinate's rate in K_j sits `shift` entries after
            # it, so that offset lines every row up with its own (the columns after the state, and those of the
            # non-vector joints, receive junk, which the stage's chart map, dynamics, ledger and Pinocchio's
            # integrate overwrite, or which nothing reads).
            head0, shifted, space = cur.head[0], self.shifted, self.space
            q_lie = space.lie_coordinates(cur.Q) if space.lie_joints else None  # the stages' common base
            for i, j, coefficient in self.shifted_stages:
                np.add(head0, np.multiply(cur.tail[j], coefficient * h, out=shifted), out=cur.head[i])
                if q_lie is not None:  # xi = c h xi'_j: the product's own columns
                    space.integrate_lie(q_lie, self.shifted_xi, cur.Qs[i])
                    if self.chart_map:
                        self.system.space.chart_rates(self.shifted_xi, cur.Vs[i], self.chart_terms, cur.XI_DOT[i])
                evaluate(cur, i, t + c[i] * h)
            # `(b @ K) * h` summed in the same order per row, into columns k: of a zeroed (n, width) buffer, then the
            # new [q | v] by the same offset addition.
            ordered_sum(self.weights, cur.K, axis=1, out=self.increment_k)
            np.multiply(self.increment_flat, h, out=self.increment_flat)
            np.add(head0, self.increment_tail, out=nxt.head[0])
            if q_lie is not None:
                space.integrate_lie(q_lie, self.increment_xi, nxt.Q)
            if self.ledger_needed:  # else every flow is zero (and the ledger columns of K hold junk)
                np.add(cur.flows, self.increment_flows, out=nxt.flows)
            return
        nv, K, space, k = self.nv, cur.K, self.space, self.layout.k
        system_space = self.system.space
        for i, rule in enumerate(self.stage_rules, start=1):
            if isinstance(rule, tuple):
                j, coefficient = rule
                Ys = np.multiply(cur.Ks[j], coefficient * h, out=self.Y)
            else:  # ExplicitRungeKutta's `ordered_sum(a[i, :i], K[:i])` for every row, then `* h`
                Ys = np.multiply(ordered_sum(rule, K[:, :i, :], axis=1, out=self.Y), h, out=self.Y)
            if space.vector_space:
                np.add(cur.X, Ys[:, : 2 * nv], out=cur.Xs[i])
            else:
                np.add(cur.V, Ys[:, nv : 2 * nv], out=cur.Vs[i])
                space.integrate(cur.Q, Ys[:, :nv], cur.Qs[i])
                if self.chart_map:
                    system_space.chart_rates(Ys[:, :nv], cur.Vs[i], self.chart_terms, cur.XI_DOT[i])
            evaluate(cur, i, t + self.c[i] * h)
        increment = self.increment
        ordered_sum(self.weights, K, axis=1, out=self.increment_k)  # `(b @ K) * h` in the same order per row
        np.multiply(self.increment_flat, h, out=self.increment_flat)
        if space.vector_space:
            np.add(cur.X, increment[:, k : k + 2 * nv], out=nxt.X)
        else:
            np.add(cur.V, increment[:, k + nv : k + 2 * nv], out=nxt.V)
            space.integrate(cur.Q, increment[:, k : k + nv], nxt.Q)
        if self.ledger_needed:  # else every flow is zero (and the ledger columns of K hold junk)
            np.add(cur.flows, self.increment_flows, out=nxt.flows)

    def _sie_step(self, cur: _Views, nxt: _Views, h: float) -> None:
        """SemiImplicitEuler.attempt on every row: v first, then q with the new v; the ledger at the new state."""
        self._last_h = h
        t = self.t
        nv = self.nv
        self.dynamics.accelerations(cur.Q, cur.V, self.TAU, t, cur.A[0])
        np.add(cur.V, np.multiply(cur.A[0], h, out=cur.A[0]), out=nxt.V)
        self.space.integrate(cur.Q, np.multiply(nxt.V, h, out=self.Y[:, :nv]), nxt.Q)
        if self.ledger_needed:
            power = cur.P[0]
            self.dynamics.ledger_power(nxt.Q, nxt.V, self.TAU, t + h, power, fresh=False, torques=self.torques)
            np.add(cur.flows, np.multiply(power, h, out=power), out=nxt.flows)

    def _evaluate(self, cur: _Views, i: int, t_stage: float) -> None:
        """Stage i's accelerations and ledger power (System.unchecked_forward_dynamics and ledger_power)."""
        self.dynamics.accelerations(cur.Qs[i], cur.Vs[i], self.TAU, t_stage, cur.A[i])
        if self.ledger_needed:
            self.dynamics.ledger_power(cur.Qs[i], cur.Vs[i], self.TAU, t_stage, cur.P[i], torques=self.torques)
