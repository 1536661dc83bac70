"""The variational integrator: discrete Euler–Lagrange equations of the midpoint discrete Lagrangian, by Newton.

Discrete Hamilton's principle with the midpoint rule: over a step of h from q_k to q_{k+1} = q_k ⊕ h w,

    Ld(q_k, q_{k+1}) = h L(q̄, w),   q̄ = q_k ⊕ (h/2) w,   L(q, w) = ½ wᵀ M(q) w − V(q),

and the discrete Lagrange–d'Alembert principle for the non-conservative force F = tau − D w, applied at the
midpoint (f⁻ = f⁺ = (h/2) F(q̄, w)). In position–momentum form, with p = M(q) v:

    R(w)    = M(q̄) w − (h/2) ∂L/∂q(q̄, w) − (h/2) F − p_k = 0        (solved for w by Newton)
    p_{k+1} = M(q̄) w + (h/2) ∂L/∂q(q̄, w) + (h/2) F,   v_{k+1} = M(q_{k+1})⁻¹ p_{k+1}.

Every term comes from one Pinocchio RNEA-derivatives call at (q̄, 0, w): ``rnea(q, 0, w) = M(q) w + g(q)``
gives M = ∂τ/∂a and K + ∂g/∂q = ∂τ/∂q with K = ∂(M(q) w)/∂q, and ∂T/∂q(q, w) = ½ Kᵀ w (because
∂T/∂q_i = ½ wᵀ (∂M/∂q_i) w = ½ Σ_j w_j K_ji).

Newton's Jacobian is dR/dw = M + (h/2)(K − Kᵀ) + (h²/4) ∂g/∂q + (h/2) D − (h²/4) ∂²T/∂q². Pinocchio has no
second-order RNEA derivatives in Python, so the last term is dropped: the iteration then contracts linearly
with factor ‖J⁻¹ (h²/4) ∂²T/∂q²‖ ≈ (h |w| / 2)² times the relative curvature of M, a few digits per iteration
at ordinary steps.

Only flat configuration spaces (revolute, prismatic and continuous joints) are handled: there q ⊕ (h/2) w has
tangent derivative (h/2) I and Pinocchio's tangent-space derivatives are coordinate derivatives.
"""

from __future__ import annotations

import functools
import math
from typing import Any, NamedTuple

import numpy as np
import pinocchio as pin

from ..exceptions import InvalidArgumentError
from .base import Integrator, StepFailure, System

_WORLD = pin.Convention.WORLD
_LEDGER = ("joint_torques", "joint_damping")


class Evaluation(NamedTuple):
    """The discrete Euler–Lagrange residual at one trial midpoint velocity w, and what Newton needs from it.

    Attributes:
        residual: R(w) [N·m·s, N·s], shape (nv,).
        jacobian: Newton's dR/dw without the (h²/4) ∂²T/∂q² term, shape (nv, nv).
        momentum_next: p_{k+1} that this w gives, shape (nv,).
        scale: the size of the terms R sums [N·m·s, N·s], for the relative convergence test.
    """

    residual: np.ndarray
    jacobian: np.ndarray
    momentum_next: np.ndarray
    scale: float


def evaluate(
    model: pin.Model,
    data: pin.Data,
    damping: np.ndarray,
    q: np.ndarray,
    p: np.ndarray,
    tau: np.ndarray,
    h: float,
    w: np.ndarray,
) -> Evaluation:
    """The residual R(w) of the forced discrete Euler–Lagrange equation and its Newton Jacobian.

    Args:
        model, data: the Pinocchio model (flat configuration space) and a workspace for it.
        damping: joint viscous damping D, shape (nv,).
        q: configuration at the step's start, shape (nq,).
        p: momentum M(q) v at the step's start, shape (nv,).
        tau: torque held over the step, shape (nv,).
        h: step [s].
        w: trial midpoint velocity (q_{k+1} ⊖ q_k) / h, shape (nv,).

    Returns:
        The residual, Jacobian, next momentum and scale at w; 3 Pinocchio dynamics calls.
    """
    half = 0.5 * h
    q_mid = pin.integrate(model, q, half * w)
    dtau_dq, _, M = pin.computeRNEADerivatives(model, data, q_mid, np.zeros_like(w), w)
    dtau_dq = dtau_dq.copy()  # the next calls reuse the workspace
    M = _symmetric(M)
    dg_dq = pin.computeGeneralizedGravityDerivatives(model, data, q_mid)
    K = dtau_dq - dg_dq  # ∂(M(q) w)/∂q at q̄
    g = pin.computeGeneralizedGravity(model, data, q_mid)
    Mw = M @ w
    dL_dq = 0.5 * (w @ K) - g
    force = tau - damping * w
    half_terms = half * (dL_dq + force)
    residual = Mw - half_terms - p
    jacobian = M + half * (K - K.T) + (half * half) * dg_dq
    jacobian.flat[:: len(w) + 1] += half * damping
    scale = float(np.abs(np.concatenate((p, Mw, half * dL_dq, half * force))).max(initial=0.0))
    return Evaluation(residual, jacobian, Mw + half_terms, scale)


class VariationalIntegrator(Integrator):
    """Midpoint variational integrator (discrete Euler–Lagrange), solved by Newton to a relative 1e-12.

    Symplectic in (q, p = M(q) v) and momentum-preserving (discrete Noether): a momentum the Lagrangian's
    symmetry conserves (e.g. about a vertical first joint under vertical gravity) is kept to the solver
    tolerance. Energy errors stay bounded on conservative systems instead of drifting. Torques and damping
    enter through the discrete Lagrange–d'Alembert principle at the midpoint; the ledger's flows over a step
    are ``h tau·w`` (work) and ``h wᵀ D w`` (dissipated).

    Fixed bases only (revolute, prismatic and continuous joints): ``check_system`` refuses the rest.

    Attributes:
        tolerance: converged when max|R| ≤ tolerance · (largest term of R, max-norm).
        max_iterations: Newton iterations before the step fails with status "newton_failed".
        last_evaluations: Pinocchio dynamics calls (CRBA, ABA, RNEA derivatives, gravity and its derivatives)
            of the last step: 3 + 3 per Newton iteration.
        last_iterations: Newton iterations of the last step.
        last_residual: relative residual max|R| / scale at which the last step stopped.
    """

    name = "variational"
    order = 2
    description = "variational midpoint (discrete Euler–Lagrange), implicit, Newton-solved to 1e-12"
    implicit = True
    symplectic = True
    # Linear mechanical systems (M q'' + D q' + K q = tau, M constant) make the scheme exactly the trapezoidal
    # rule, which is A-stable (tested against its closed form); see notes for what that does not promise.
    a_stable = True
    notes = (
        "fixed bases only; conserves symmetry momenta to solver tolerance and keeps energy errors bounded; "
        "on linear(ised) systems it is the trapezoidal rule: A-stable but not L-stable (a stiff damped mode "
        "flips sign each step, decaying slowly, instead of being damped out)"
    )
    # Nominal count, 2 Newton iterations; the loop reads last_evaluations for the real one.
    evaluations_per_step = 9

    def __init__(self, *, tolerance: float = 1e-12, max_iterations: int = 50):
        self.tolerance = tolerance
        self.max_iterations = max_iterations
        self.last_evaluations = 0
        self.last_iterations = 0
        self.last_residual = math.nan

    def check_system(self, system: System) -> None:
        """Refuse systems this method cannot integrate yet.

        Raises:
            InvalidArgumentError: a floating base, a spherical or planar joint, or energy-ledger elements
                other than joint torques and joint damping (scene elements).
        """
        name = getattr(system, "name", type(system).__name__)
        if getattr(system, "floating_base", False):
            raise InvalidArgumentError(
                f"integrator 'variational' does not support floating bases yet (robot '{name}' has one); "
                "use rk4, dp54 or another explicit integrator"
            )
        space = system.space
        if not space.is_flat:
            model = system.model  # type: ignore[attr-defined]
            start = space.curved_blocks[0][0]
            joint = next(model.names[i] for i in range(1, model.njoints) if model.joints[i].idx_v == start)
            raise InvalidArgumentError(
                f"integrator 'variational' supports only revolute, prismatic and continuous joints yet "
                f"(robot '{name}' has joint '{joint}' of type {model.joints[model.getJointId(joint)].shortname()}); "
                "use rk4, dp54 or another explicit integrator"
            )
        elements = [element for element, _ in getattr(system, "ledger_elements", [])]
        if not hasattr(system, "model") or any(element not in _LEDGER for element in elements):
            others = [element for element in elements if element not in _LEDGER]
            raise InvalidArgumentError(
                f"integrator 'variational' handles joint torques and joint damping only, not {others or name}; "
                "use rk4, dp54 or another explicit integrator"
            )

    def step(
        self, system: System, q: np.ndarray, v: np.ndarray, tau: np.ndarray, dt: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        if not system.space.is_flat:  # a cheap guard in case a caller skipped check_system
            self.check_system(system)
        robot: Any = system
        model, data, damping = robot.model, robot.data, robot.damping
        M = pin.crba(model, data, q)
        p = _symmetric(M) @ v
        # The midpoint velocity is v(t + h/2) + O(h²): start Newton there (one ABA call).
        w = v + (0.5 * dt) * robot.unchecked_forward_dynamics(q, v, tau)
        evaluations, iterations = 2, 0
        while True:
            ev = evaluate(model, data, damping, q, p, tau, dt, w)
            evaluations += 3
            error = float(np.abs(ev.residual).max(initial=0.0))
            relative = error / ev.scale if ev.scale > 0.0 else error
            if relative <= self.tolerance:
                break
            if not math.isfinite(error) or iterations == self.max_iterations:
                self.last_evaluations, self.last_iterations, self.last_residual = evaluations, iterations, relative
                raise StepFailure(
                    f"Newton did not solve the discrete Euler–Lagrange equations in {iterations} iterations "
                    f"(relative residual {relative:.3g}, tolerance {self.tolerance:g})",
                    status="newton_failed",
                )
            try:
                w = w - np.linalg.solve(ev.jacobian, ev.residual)
            except np.linalg.LinAlgError:
                self.last_evaluations, self.last_iterations, self.last_residual = evaluations, iterations, relative
                raise StepFailure("Newton's Jacobian is singular", status="newton_failed") from None
            iterations += 1
        q_next = pin.integrate(model, q, dt * w)
        v_next = np.linalg.solve(_symmetric(pin.crba(model, data, q_next)), ev.momentum_next)
        evaluations += 1
        self.last_evaluations, self.last_iterations, self.last_residual = evaluations, iterations, relative
        flows = [dt * (tau @ w)]
        if len(robot.ledger_elements) > 1:
            flows.append(dt * (w @ (damping * w)))
        return q_next, v_next, np.array(flows)


def _symmetric(upper: np.ndarray) -> np.ndarray:
    """The symmetric matrix whose upper triangle Pinocchio filled (CRBA leaves the lower one stale)."""
    return np.where(_upper_mask(len(upper)), upper, upper.T)


@functools.lru_cache(maxsize=None)
def _upper_mask(n: int) -> np.ndarray:
    return np.triu(np.ones((n, n), dtype=bool))
