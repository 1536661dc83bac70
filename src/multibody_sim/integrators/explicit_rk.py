"""The one generic explicit Runge–Kutta step, driven by a Butcher tableau, on the configuration manifold."""

from __future__ import annotations

import numpy as np

from .base import Integrator, System
from .tableau import ButcherTableau


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
