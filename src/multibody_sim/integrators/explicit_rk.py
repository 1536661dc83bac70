"""The one generic explicit Runge–Kutta step, driven by a Butcher tableau, on the configuration manifold."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

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
        self.description = description
        self.notes = notes
        self.evaluations_per_step = tableau.stages
        self._a = np.array(tableau.a, dtype=float)
        self._b = np.array(tableau.b, dtype=float)

    def step(
        self, system: System, q: np.ndarray, v: np.ndarray, tau: np.ndarray, dt: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        K, _, _ = self._stages(system, q, v, tau, dt)
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
        first_row: np.ndarray | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Stage derivatives K, shape (s, 2 nv + n_ledger), rows (xi', v', ledger power); and the last stage's
        (q, v). `first_row` is a known first row (FSAL reuse)."""
        space = system.space
        flat = space.is_flat
        nv = len(v)
        a = self._a
        K = np.empty((len(a), 2 * nv + len(system.ledger_elements)))
        q_stage, v_stage = q, v
        for i in range(len(a)):
            row = K[i]
            if i == 0:  # at the step's start: xi = 0, where the chart Jacobian is the identity
                row[:nv] = v
                if first_row is not None:  # its chart rate was taken in the previous step's chart: not reused
                    row[nv:] = first_row[nv:]
                    continue
            else:
                y = (a[i, :i] @ K[:i]) * h
                xi = y[:nv]
                v_stage = v + y[nv : 2 * nv]
                q_stage = space.integrate(q, xi)
                row[:nv] = v_stage if flat else space.chart_velocity(q, xi, v_stage)
            row[nv : 2 * nv] = system.unchecked_forward_dynamics(q_stage, v_stage, tau)
            system.ledger_power(q_stage, v_stage, tau, out=row[2 * nv :])
        return K, q_stage, v_stage


class Attempt(NamedTuple):
    """One trial step of an embedded method (accepted or not by the step-size controller)."""

    q: np.ndarray
    v: np.ndarray
    flows: np.ndarray
    error: float  # scaled RMS error norm: accept when ≤ 1
    stages: np.ndarray  # K: the stage derivatives (xi', v', ledger power), one row per stage
    evaluations: int


class EmbeddedRungeKutta(ExplicitRungeKutta):
    """An explicit Runge–Kutta pair with error estimation and dense output, for adaptive stepping.

    The error is estimated on the chart coordinates and velocities (the tangent space, so floating bases
    work) and scaled by ``atol + rtol · max(|y_n|, |y_n+1|)``, where a configuration's magnitude is its
    distance from the neutral configuration in the tangent space.
    """

    adaptive = True

    def __init__(self, name: str, tableau: EmbeddedTableau, description: str, *, notes: str = ""):
        super().__init__(name, tableau, description, notes=notes)
        self.tableau: EmbeddedTableau = tableau
        self.embedded_order = tableau.embedded_order
        self._e = self._b - np.array(tableau.b_hat, dtype=float)
        self._d = np.array(tableau.dense, dtype=float) if tableau.dense else None

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
    ) -> Attempt:
        """Try a step of h [s]. `first_stage`: the first row of K at (q, v, tau) if already known (the last stage
        of the previous accepted step with an FSAL tableau, or the first of a rejected attempt)."""
        K, q_last, v_last = self._stages(system, q, v, tau, h, first_stage)
        nv = len(v)
        increment = (self._b @ K) * h
        if self.tableau.fsal:  # the last stage is the new state
            q_next, v_next = q_last, v_last
        else:
            q_next, v_next = system.space.integrate(q, increment[:nv]), v + increment[nv : 2 * nv]
        error = (self._e @ K[:, : 2 * nv]) * h
        space = system.space
        scale = np.empty(2 * nv)
        scale[:nv] = np.maximum(
            np.abs(space.difference(space.neutral, q)), np.abs(space.difference(space.neutral, q_next))
        )
        scale[nv:] = np.maximum(np.abs(v), np.abs(v_next))
        scaled = error / (atol + rtol * scale)
        norm = math.sqrt((scaled @ scaled) / (2 * nv))
        if not math.isfinite(norm) or not math.isfinite(q_next @ q_next + v_next @ v_next):
            norm = math.inf
        evaluations = len(K) - (first_stage is not None)
        return Attempt(q_next, v_next, increment[2 * nv :], norm, K, evaluations)

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
