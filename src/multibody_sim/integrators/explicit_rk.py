"""The one generic explicit Runge–Kutta step, driven by a Butcher tableau, on the configuration manifold."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from .base import Integrator, System
from .tableau import ButcherTableau, EmbeddedTableau


class ExplicitRungeKutta(Integrator):
    """An explicit Runge–Kutta method given by its tableau.

    Stages are built in the local chart around the step's start q_n (see ConfigurationSpace): the stage
    configuration is ``integrate(q_n, dt Σ a_ij xi'_j)`` with chart rates ``xi'_j``, which keeps the
    tableau's order on floating bases. The energy ledger is integrated as extra ODE components with the
    same tableau, so its error has the method's order too.
    """

    def __init__(self, name: str, tableau: ButcherTableau, description: str, *, notes: str = ""):
        self.name = name
        self.tableau = tableau
        self.order = tableau.order
        self.description = description
        self.notes = notes
        self.evaluations_per_step = tableau.stages
        # Only non-zero coefficients are ever multiplied (RK4's a is mostly zeros).
        self._rows = [[(j, a_ij) for j, a_ij in enumerate(row) if a_ij != 0.0] for row in tableau.a]
        self._weights = [(i, b_i) for i, b_i in enumerate(tableau.b) if b_i != 0.0]

    def step(
        self, system: System, q: np.ndarray, v: np.ndarray, tau: np.ndarray, dt: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        space = system.space
        flat = space.is_flat
        chart_rates: list[np.ndarray] = []
        accelerations: list[np.ndarray] = []
        powers: list[np.ndarray] = []
        for row in self._rows:
            if row:
                xi = _combine(chart_rates, row, dt)
                v_stage = v + _combine(accelerations, row, dt)
                q_stage = space.integrate(q, xi)
                chart_rates.append(v_stage if flat else space.chart_velocity(q, xi, v_stage))
            else:  # the chart Jacobian is the identity at xi = 0
                v_stage, q_stage = v, q
                chart_rates.append(v)
            accelerations.append(system.unchecked_forward_dynamics(q_stage, v_stage, tau))
            powers.append(system.ledger_power(q_stage, v_stage, tau))
        q_next = space.integrate(q, _combine(chart_rates, self._weights, dt))
        v_next = v + _combine(accelerations, self._weights, dt)
        return q_next, v_next, _combine(powers, self._weights, dt)


def _combine(values: list[np.ndarray], coefficients: list[tuple[int, float]], dt: float) -> np.ndarray:
    """dt · Σ c_j values[j] over the given non-zero coefficients."""
    (j, c), *rest = coefficients
    total = values[j] * (dt * c)
    for j, c in rest:
        total += values[j] * (dt * c)
    return total


class Attempt(NamedTuple):
    """One trial step of an embedded method (accepted or not by the step-size controller)."""

    q: np.ndarray
    v: np.ndarray
    flows: np.ndarray
    error: float  # scaled RMS error norm: accept when ≤ 1
    stages: tuple[list[np.ndarray], list[np.ndarray], list[np.ndarray]]  # chart rates, accelerations, powers
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
        error_weights = np.array(tableau.b) - np.array(tableau.b_hat)
        self._error_weights = [(i, e) for i, e in enumerate(error_weights) if e != 0.0]
        self._dense = [(i, d) for i, d in enumerate(tableau.dense) if d != 0.0]

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
        first_stage: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> Attempt:
        """Try a step of h [s]; `first_stage` = (acceleration, power) at (q, v, tau) from the previous step's
        last stage (FSAL), when the torque has not changed."""
        space = system.space
        flat = space.is_flat
        chart_rates: list[np.ndarray] = []
        accelerations: list[np.ndarray] = []
        powers: list[np.ndarray] = []
        evaluations = 0
        q_stage, v_stage = q, v
        for row in self._rows:
            if row:
                xi = _combine(chart_rates, row, h)
                v_stage = v + _combine(accelerations, row, h)
                q_stage = space.integrate(q, xi)
                chart_rates.append(v_stage if flat else space.chart_velocity(q, xi, v_stage))
            else:
                chart_rates.append(v)
                if first_stage is not None:
                    accelerations.append(first_stage[0])
                    powers.append(first_stage[1])
                    continue
            accelerations.append(system.unchecked_forward_dynamics(q_stage, v_stage, tau))
            powers.append(system.ledger_power(q_stage, v_stage, tau))
            evaluations += 1
        if self.tableau.fsal:  # the last stage is the new state
            q_next, v_next = q_stage, v_stage
        else:
            q_next = space.integrate(q, _combine(chart_rates, self._weights, h))
            v_next = v + _combine(accelerations, self._weights, h)
        flows = _combine(powers, self._weights, h)
        error_xi = _combine(chart_rates, self._error_weights, h)
        error_v = _combine(accelerations, self._error_weights, h)
        size_q = np.abs(space.difference(space.neutral, q_next))
        scale_q = atol + rtol * np.maximum(np.abs(space.difference(space.neutral, q)), size_q)
        scale_v = atol + rtol * np.maximum(np.abs(v), np.abs(v_next))
        squares = (error_xi / scale_q) @ (error_xi / scale_q) + (error_v / scale_v) @ (error_v / scale_v)
        error = math.sqrt(squares / (2 * len(v)))
        if not math.isfinite(error) or not math.isfinite(q_next @ q_next + v_next @ v_next):
            error = math.inf
        return Attempt(q_next, v_next, flows, error, (chart_rates, accelerations, powers), evaluations)

    def dense_output(
        self, system: System, q: np.ndarray, v: np.ndarray, attempt: Attempt, h: float, theta: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q, v, flows since the step's start) at time t_n + θh, 0 ≤ θ ≤ 1, from an accepted attempt."""
        chart_rates, accelerations, powers = attempt.stages
        xi_end = _combine(chart_rates, self._weights, 1.0)  # r1 per unit h
        xi = self._continuous(chart_rates, xi_end, h, theta)
        dv = self._continuous(accelerations, _combine(accelerations, self._weights, 1.0), h, theta)
        flows = self._continuous(powers, _combine(powers, self._weights, 1.0), h, theta)
        return system.space.integrate(q, xi), v + dv, flows

    def _continuous(self, k: list[np.ndarray], r1: np.ndarray, h: float, theta: float) -> np.ndarray:
        """h θ (r1 + (1-θ)(r2 + θ(r3 + (1-θ) r4))): the increment from the step's start at θ."""
        r2 = k[0] - r1
        r3 = 2.0 * r1 - k[0] - k[-1]
        inner = r3 + (1.0 - theta) * _combine(k, self._dense, 1.0) if self._dense else r3
        return h * theta * (r1 + (1.0 - theta) * (r2 + theta * inner))
