"""The one generic explicit Runge–Kutta step, driven by a Butcher tableau, on the configuration manifold."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..state import chart_terms
from .base import Integrator, System
from .tableau import ButcherTableau, EmbeddedTableau


class ExplicitRungeKutta(Integrator):
    """An explicit Runge–Kutta method given by its tableau.

    The step integrates the extended state y = (xi, v, ledger) where xi is the chart coordinate around the
    step's start q_n (see ConfigurationSpace): stage configurations are ``integrate(q_n, xi_i)`` with
    ``xi_i = h Σ a_ij xi'_j``, which keeps the tableau's order on floating bases, and the energy ledger's
    work and dissipation are integrated with the same tableau, so the ledger is as accurate as the trajectory.
    Stage derivatives are the rows of one matrix K, so each stage costs one small matrix product.
    """

    def __init__(self, name: str, tableau: ButcherTableau, description: str, *, notes: str = ""):
        self.name = name
        self.tableau = tableau
        self.order = tableau.order
        self.chart_terms = chart_terms(tableau.order)  # the chart map's series, truncated where the order allows
        self.description = description
        self.notes = notes
        self.evaluations_per_step = tableau.stages
        self._a = np.array(tableau.a, dtype=float)
        self._b = np.array(tableau.b, dtype=float)
        self._c = np.array(tableau.c, dtype=float)

    def step(
        self, system: System, q: np.ndarray, v: np.ndarray, tau: np.ndarray, dt: float, t: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        K, _, _ = self._stages(system, q, v, tau, dt, t)
        nv = len(v)
        increment = (self._b @ K) * dt
        return system.space.integrate(q, increment[:nv]), v + increment[nv : 2 * nv], increment[2 * nv :]

    def _stages(
        self,
        system: System,
        q: np.ndarray,
        v: np.ndarray,
        tau: np.ndarray,
        h: float,
        t: float,
        first_row: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Stage derivatives K, shape (s, 2 nv + n_ledger), rows (xi', v', ledger power), for the step from time t;
        and the last stage's (q, v). `first_row` is a known first row (FSAL reuse)."""
        nv = len(v)
        K = np.empty((len(self._a), 2 * nv + len(system.ledger_elements)))
        K[0, :nv] = v  # at the step's start: xi = 0, where the chart Jacobian is the identity
        if first_row is not None:  # its chart rate was taken in the previous step's chart: not reused
            K[0, nv:] = first_row[nv:]
        else:
            K[0, nv : 2 * nv] = system.unchecked_forward_dynamics(q, v, tau, t)
            system.ledger_power(q, v, tau, K[0, 2 * nv :], t)
        q_stage, v_stage = _fill_stages(system, q, v, tau, h, t, K, self._a, self._c, 1, len(self._a), self.chart_terms)
        return K, q_stage, v_stage


def _fill_stages(
    system: System,
    q: np.ndarray,
    v: np.ndarray,
    tau: np.ndarray,
    h: float,
    t: float,
    K: np.ndarray,
    a: np.ndarray,
    c: np.ndarray,
    start: int,
    stop: int,
    terms: int,
) -> tuple[np.ndarray, np.ndarray]:
    """Fill rows start..stop-1 of K, each stage built from the rows before it with coefficients a[i, :i] at time
    t + c[i] h, the chart map's series truncated after A^terms; returns the last stage's (q, v)."""
    space = system.space
    flat = space.is_flat
    nv = len(v)
    q_stage, v_stage = q, v
    for i in range(start, stop):
        row = K[i]
        y = (a[i, :i] @ K[:i]) * h
        xi = y[:nv]
        v_stage = v + y[nv : 2 * nv]
        q_stage = space.integrate(q, xi)
        row[:nv] = v_stage if flat else space.chart_velocity(xi, v_stage, terms)
        t_stage = t + c[i] * h
        row[nv : 2 * nv] = system.unchecked_forward_dynamics(q_stage, v_stage, tau, t_stage)
        system.ledger_power(q_stage, v_stage, tau, row[2 * nv :], t_stage)
    return q_stage, v_stage


@dataclass
class Attempt:
    """One trial step of an adaptive method (accepted or not by the step-size controller)."""

    q: np.ndarray
    v: np.ndarray
    flows: np.ndarray
    error: float  # scaled error norm: accept when ≤ 1
    stages: np.ndarray  # K: the stage derivatives (xi', v', ledger power), one row per stage
    evaluations: int
    tau: np.ndarray  # the torque held over the step (dense output may need more stages)
    t: float  # the step's start time [s]
    dense: np.ndarray | None = None  # interpolation data, built on the first dense_output call
    extra_evaluations: int = 0  # dynamics evaluations the dense output added (DOP853's extra stages)


class AdaptiveRungeKutta(ExplicitRungeKutta):
    """An explicit Runge–Kutta method with an error estimate, for adaptive stepping: one trial step (attempt) with
    its scaled error norm; subclasses say how the norm is formed from the stages.

    The error is estimated on the chart coordinates and velocities (the tangent space, so floating bases
    work) and scaled by ``atol + rtol · max(|y_n|, |y_n+1|)``, where a configuration's magnitude is its
    distance from the neutral configuration in the tangent space.
    """

    adaptive = True
    fsal: bool  # the last stage is at the new state (and is the next step's first)

    def attempt(
        self,
        system: System,
        q: np.ndarray,
        v: np.ndarray,
        tau: np.ndarray,
        h: float,
        *,
        rtol: float,
        atol: float,
        first_stage: np.ndarray | None = None,
        t: float = 0.0,
    ) -> Attempt:
        """Try a step of h [s]. `first_stage`: the first row of K at (q, v, tau) if already known (the last stage
        of the previous accepted step with an FSAL tableau, or the first of a rejected attempt)."""
        K, q_last, v_last = self._stages(system, q, v, tau, h, t, first_stage)
        nv = len(v)
        increment = (self._b @ K) * h
        if self.fsal:  # the last stage is the new state
            q_next, v_next = q_last, v_last
        else:
            q_next, v_next = system.space.integrate(q, increment[:nv]), v + increment[nv : 2 * nv]
        scale = _error_scale(system, q, v, q_next, v_next, rtol, atol)
        norm = self._error_norm(K[:, : 2 * nv], h, scale)
        if not math.isfinite(norm) or not math.isfinite(q_next @ q_next + v_next @ v_next):
            norm = math.inf
        evaluations = len(K) - (first_stage is not None)
        return Attempt(q_next, v_next, increment[2 * nv :], norm, K, evaluations, tau, t)

    def _error_norm(self, K: np.ndarray, h: float, scale: np.ndarray) -> float:
        """The scaled error norm (accept when ≤ 1) from the stages' (xi', v') rows K, shape (s, 2 nv)."""
        raise NotImplementedError


class EmbeddedRungeKutta(AdaptiveRungeKutta):
    """An explicit Runge–Kutta pair with error estimation and dense output, for adaptive stepping (the error is
    the difference of the two solutions, RMS over the tangent components)."""

    def __init__(self, name: str, tableau: EmbeddedTableau, description: str, *, notes: str = ""):
        super().__init__(name, tableau, description, notes=notes)
        self.tableau: EmbeddedTableau = tableau
        self.embedded_order = tableau.embedded_order  # the order the step-size controller assumes of the error
        self.fsal = tableau.fsal
        self._e = self._b - np.array(tableau.b_hat, dtype=float)
        self._d = np.array(tableau.dense, dtype=float) if tableau.dense else None

    def _error_norm(self, K: np.ndarray, h: float, scale: np.ndarray) -> float:
        scaled = (self._e @ K) * h / scale
        return math.sqrt((scaled @ scaled) / len(scale))

    def dense_output(
        self, system: System, q: np.ndarray, v: np.ndarray, attempt: Attempt, h: float, theta: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q, v, ledger flows since the step's start) at t_n + θh, 0 ≤ θ ≤ 1, from an accepted attempt.

        The continuous extension h θ (r1 + (1-θ)(r2 + θ(r3 + (1-θ) r4))) with r1 = Σ b_i k_i,
        r2 = k_1 - r1, r3 = 2 r1 - k_1 - k_s, r4 = Σ d_i k_i, applied to the extended chart state.
        """
        K = attempt.stages
        nv = len(v)
        r1 = self._b @ K
        r2 = K[0] - r1
        r3 = 2.0 * r1 - K[0] - K[-1]
        if self._d is not None and self._d.any():
            r3 = r3 + (1.0 - theta) * (self._d @ K)
        y = h * theta * (r1 + (1.0 - theta) * (r2 + theta * r3))
        return system.space.integrate(q, y[:nv]), v + y[nv : 2 * nv], y[2 * nv :]


def _error_scale(
    system: System, q: np.ndarray, v: np.ndarray, q_next: np.ndarray, v_next: np.ndarray, rtol: float, atol: float
) -> np.ndarray:
    """atol + rtol · max(|y_n|, |y_n+1|) per tangent component; a configuration's size is its distance from the
    neutral configuration in the tangent space."""
    space = system.space
    nv = len(v)
    size = np.empty(2 * nv)
    size[:nv] = np.maximum(np.abs(space.difference(space.neutral, q)), np.abs(space.difference(space.neutral, q_next)))
    size[nv:] = np.maximum(np.abs(v), np.abs(v_next))
    return atol + rtol * size


class DormandPrince853(AdaptiveRungeKutta):
    """DOP853: Dormand and Prince's 8th-order method with Hairer's 5th/3rd-order combined error estimate
    (7th order) and 7th-order dense output from three extra stages.

    The coefficients are the published tables (Hairer, Nørsett & Wanner, Solving ODEs I), as scipy ships them in
    `scipy.integrate._ivp.dop853_coefficients`; the step, the error norm on the tangent space and the dense
    output on the chart are this package's.
    """

    fsal = True
    embedded_order = 7  # the combined estimate behaves like a 7th-order one (scipy's error_estimator_order)

    def __init__(self) -> None:
        from scipy.integrate._ivp import dop853_coefficients as tables

        n = tables.N_STAGES  # 12 stages; the 13th (row 12) is the new state, first same as last
        tableau = ButcherTableau(
            a=tuple(tuple(float(x) for x in row[: n + 1]) for row in tables.A[: n + 1]),
            b=(*(float(x) for x in tables.B), 0.0),
            c=tuple(float(x) for x in tables.C[: n + 1]),
            order=8,
        )
        super().__init__(
            "dop853",
            tableau,
            "Dormand–Prince 8(5,3), adaptive, 7th-order dense output",
            notes="pays at tight tolerances (rtol ≤ 1e-9): 2-3x fewer evaluations than dp54 for the same error",
        )
        self._e5 = np.array(tables.E5, dtype=float)
        self._e3 = np.array(tables.E3, dtype=float)
        self._a_extended = np.array(tables.A, dtype=float)  # rows 13..15: the dense output's extra stages
        self._c_extended = np.array(tables.C, dtype=float)
        self._dense_weights = np.array(tables.D, dtype=float)

    def _error_norm(self, K: np.ndarray, h: float, scale: np.ndarray) -> float:
        """Hairer's combined estimate: h |err5|² / sqrt((|err5|² + 0.01 |err3|²) · 2 nv)."""
        err5 = (self._e5 @ K) / scale
        err3 = (self._e3 @ K) / scale
        e5, e3 = err5 @ err5, err3 @ err3
        return 0.0 if e5 == 0.0 and e3 == 0.0 else h * e5 / math.sqrt((e5 + 0.01 * e3) * len(scale))

    def dense_output(
        self, system: System, q: np.ndarray, v: np.ndarray, attempt: Attempt, h: float, theta: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q, v, ledger flows since the step's start) at t_n + θh from an accepted attempt."""
        nv = len(v)
        if attempt.dense is None:  # three more stages, once per step, then the interpolation polynomial's data
            K = np.empty((len(self._a_extended), attempt.stages.shape[1]))
            K[: len(attempt.stages)] = attempt.stages
            _fill_stages(
                system,
                q,
                v,
                attempt.tau,
                h,
                attempt.t,
                K,
                self._a_extended,
                self._c_extended,
                len(attempt.stages),
                len(K),
                self.chart_terms,
            )
            attempt.extra_evaluations = len(K) - len(attempt.stages)
            delta = (self._b @ attempt.stages) * h
            F = np.empty((7, K.shape[1]))
            F[0] = delta
            F[1] = h * K[0] - delta
            F[2] = 2.0 * delta - h * (attempt.stages[-1] + K[0])
            F[3:] = h * (self._dense_weights @ K)
            attempt.dense = F
        y = np.zeros(attempt.dense.shape[1])
        for i, f in enumerate(attempt.dense[::-1]):  # nested form: alternate factors θ and (1 - θ)
            y += f
            y *= theta if i % 2 == 0 else 1.0 - theta
        return system.space.integrate(q, y[:nv]), v + y[nv : 2 * nv], y[2 * nv :]
