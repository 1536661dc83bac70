"""Partitioned methods that update velocity and configuration in turn (not expressible as one tableau)."""

from __future__ import annotations

import numpy as np

from .base import Integrator, System


class SemiImplicitEuler(Integrator):
    """Semi-implicit (symplectic) Euler in velocity form: v first, then q with the new v.

    ``v_{n+1} = v_n + dt a(q_n, v_n)``, ``q_{n+1} = q_n ⊕ dt v_{n+1}``. Symplectic only where M is constant
    (a single pendulum, a point mass): for general M(q) the velocity form is not the symplectic momentum form
    and its energy error can drift.
    """

    name = "semi_implicit_euler"
    order = 1
    description = "semi-implicit Euler: velocity first, then configuration"
    evaluations_per_step = 1
    notes = "symplectic only where M is constant (e.g. a single pendulum), not for general M(q)"

    def step(
        self, system: System, q: np.ndarray, v: np.ndarray, tau: np.ndarray, dt: float, t: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        v_next = v + dt * system.unchecked_forward_dynamics(q, v, tau, t)
        q_next = system.space.integrate(q, dt * v_next)
        # The configuration moved along v_next, so that is the velocity the torques and dampers work against.
        return q_next, v_next, dt * system.ledger_power(q_next, v_next, tau, None, t + dt)
