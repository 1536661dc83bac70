"""Partitioned methods that update velocity and configuration in turn (not expressible as one tableau)."""

from __future__ import annotations

from typing import Any

import numpy as np

from ..exceptions import InvalidArgumentError
from .base import Attempt, Integrator, System, split_jacobian, tangent_selectors, velocity_update


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

    def native_data(self) -> dict[str, Any]:
        """The method as the native kernel renders it (_native.Method's fields): one stage, no chart map."""
        return {"kind": "semi_implicit_euler", "stages": 1, "a": [0.0], "b": [1.0], "c": [0.0], "chart_terms": 0}

    def attempt(
        self,
        system: System,
        q: np.ndarray,
        v: np.ndarray,
        tau: np.ndarray,
        h: float,
        t: float = 0.0,
        state: Any = None,
        *,
        rtol: float | None = None,
        atol: float | None = None,
    ) -> Attempt:
        v_next, evaluations, servos = velocity_update(system, q, v, tau, h, t)
        if servos is not None:
            servos.end_implicit()
        q_next = system.space.integrate(q, h * v_next)
        # The configuration moved along v_next, so that is the velocity the torques and dampers work against (and
        # the servo terms taken implicitly are the servos' torques at the step's end).
        flows = h * system.ledger_power(q_next, v_next, tau, None, t + h)
        return Attempt(q_next, v_next, flows, None, None, evaluations)

    def jacobians(
        self, system: System, q: np.ndarray, v: np.ndarray, tau: np.ndarray, h: float, t: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """v' = v + h a(q, v, tau), q' = q ⊕ h v' (see multibody_sim.linearize).

        Raises:
            InvalidArgumentError: the system has servos, or an overspeed brake that binds at (q, v, tau), whose
                terms this step takes implicitly (not differentiated).
        """
        actuators = getattr(system, "actuators", None)
        if actuators is not None and actuators.servos:
            raise InvalidArgumentError(
                f"linearize: {self.name} takes the scene's servo terms implicitly, which linearize does not "
                "differentiate yet; use rk4 or implicit_euler"
            )
        braking = actuators.braking(q, v, tau) if actuators is not None else []
        if braking:
            raise InvalidArgumentError(
                f"linearize: {self.name} takes the overspeed brake of {', '.join(braking)} implicitly at this state, "
                "which linearize does not differentiate yet; use rk4 or implicit_euler"
            )
        nv = system.nv
        select_q, select_v, _ = tangent_selectors(nv)
        da_dq, da_dv, da_dtau = system.unchecked_dynamics_derivatives(q, v, tau, t)
        v_next = v + h * system.unchecked_forward_dynamics(q, v, tau, t)
        d_v = select_v + h * np.hstack((da_dq, da_dv, da_dtau))
        d_q = system.space.d_integrate(q, h * v_next, select_q, h * d_v)
        return split_jacobian(np.vstack((d_q, d_v)), nv)
