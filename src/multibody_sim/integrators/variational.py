"""The variational integrator: discrete Euler–Lagrange equations of the midpoint discrete Lagrangian, by Newton.

Discrete Hamilton's principle with the midpoint rule: over a step of h from q_k to q_{k+1} = q_k ⊕ h w,

    Ld(q_k, q_{k+1}) = h L(q̄, w),   q̄ = q_k ⊕ (h/2) w,   L(q, w) = ½ wᵀ M(q) w − V(q),

and the discrete Lagrange–d'Alembert principle for the non-conservative force F = tau − D w, applied at the
midpoint (f⁻ = f⁺ = (h/2) F(q̄, w)). In position–momentum form, with p = M(q) v:

    R(w)    = M(q̄) w − (h/2) ∂L/∂q(q̄, w) − (h/2) F − p_k = 0        (solved for w by Newton)
    p_{k+1} = M(q̄) w + (h/2) ∂L/∂q(q̄, w) + (h/2) F,   v_{k+1} = M(q_{k+1})⁻¹ p_{k+1}.

The map (q_k, p_k) -> (q_{k+1}, p_{k+1}) is symplectic; storing v = M(q)⁻¹ p instead of p is a fixed change of
coordinates at each q, so the integrator stays stateless.

The terms come from Pinocchio's RNEA derivatives at (q̄, 0, w): ``rnea(q, 0, w) = M(q) w + g(q)`` gives
M = ∂τ/∂a and K + ∂g/∂q = ∂τ/∂q with K = ∂(M(q) w)/∂q, and ∂T/∂q(q, w) = ½ Kᵀ w (because
∂T/∂q_i = ½ wᵀ (∂M/∂q_i) w = ½ Σ_j w_j K_ji; it also equals C(q, w)ᵀ w for Pinocchio's C).

Newton's Jacobian is dR/dw = M + (h/2)(K − Kᵀ) + (h²/4) ∂g/∂q + (h/2) D − (h²/4) ∂²T/∂q². Pinocchio has no
second-order RNEA derivatives in Python, so the last term is dropped: alone, the iteration then contracts
linearly with factor ≈ ‖J⁻¹ (h²/4) ∂²T/∂q²‖ = O(h²), several digits per iteration at ordinary steps but close to
1 at coarse ones. A structured secant (Broyden) correction learns the dropped term along the directions the
iteration explores, which keeps coarse steps converging superlinearly.

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
from .base import Attempt, Integrator, StepFailure, System, failed

_LEDGER = ("joint_torques", "joint_damping")
_ALTERNATIVES = "use rk4, dp54 or another explicit integrator"
# Relative residual below which the secant correction stops learning (its differences would be round-off).
_SECANT_FLOOR = 1e-9


class Evaluation(NamedTuple):
    """The discrete Euler–Lagrange residual at one trial midpoint velocity w, and what Newton needs from it.

    Attributes:
        residual: R(w) [N·m·s, N·s], shape (nv,).
        jacobian: Newton's dR/dw without the -(h²/4) ∂²T/∂q² term, shape (nv, nv).
        momentum_next: p_{k+1} that this w gives, shape (nv,).
        scale: the largest term R sums (max-norm) [N·m·s, N·s], for the relative convergence test.
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
        The residual, Jacobian, next momentum and scale at w (3 Pinocchio dynamics calls).
    """
    half = 0.5 * h
    n = len(w)
    q_mid = pin.integrate(model, q, half * w)
    dg_dq = pin.computeGeneralizedGravityDerivatives(model, data, q_mid)
    g = pin.computeGeneralizedGravity(model, data, q_mid)
    # Last: these two are views into Pinocchio's workspace, used before any other call can overwrite it.
    dtau_dq, _, M = pin.computeRNEADerivatives(model, data, q_mid, _zeros(n), w)
    K = dtau_dq - dg_dq  # ∂(M(q) w)/∂q at q̄
    M = _symmetric(M)
    Mw = M @ w
    half_dL_dq = (0.5 * half) * (w @ K) - half * g
    half_force = half * (tau - damping * w)
    half_terms = half_dL_dq + half_force
    jacobian = M + half * (K - K.T) + (half * half) * dg_dq
    jacobian.flat[:: n + 1] += half * damping
    scale = float(np.abs(np.concatenate((p, Mw, half_dL_dq, half_force))).max(initial=0.0))
    return Evaluation(Mw - half_terms - p, jacobian, Mw + half_terms, scale)


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
        last_evaluations: Pinocchio dynamics calls of the last step (CRBA, ABA, RNEA derivatives, gravity and
            its derivatives each count one): 3 + 3 per residual evaluation.
        last_iterations: Newton iterations (solves) of the last step.
        last_residual: relative residual max|R| / scale at which the last step stopped.
    """

    name = "variational"
    order = 2
    description = "variational midpoint (discrete Euler–Lagrange), symplectic, Newton-solved to 1e-12"
    implicit = True
    symplectic = True
    # On linear mechanical systems (M q'' + D q' + K q = tau, M constant) the scheme is exactly the trapezoidal
    # rule, which is A-stable (tested against its closed form); the notes say what that does not promise.
    a_stable = True
    notes = (
        "fixed bases only; conserves symmetry momenta to solver tolerance and keeps energy errors bounded; "
        "on linear(ised) systems it is the trapezoidal rule: A-stable but not L-stable (a stiff damped mode "
        "flips sign each step and decays slowly instead of being damped out)"
    )
    # Nominal: 2 Newton iterations (3 evaluations); the stepping loop reads last_evaluations for the real count.
    evaluations_per_step = 12

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
                other than joint torques and joint damping (scene elements such as springs).
        """
        super().check_system(system)
        name = getattr(system, "name", type(system).__name__)
        if getattr(system, "floating_base", False):
            raise InvalidArgumentError(
                f"integrator 'variational' does not support floating bases yet (robot '{name}' has one); "
                f"{_ALTERNATIVES}"
            )
        space = system.space
        if not space.is_flat:
            model = system.model  # type: ignore[attr-defined]
            start = space.curved_blocks[0][0]
            joint = next(j for j in range(1, model.njoints) if model.joints[j].idx_v == start)
            kind = model.joints[joint].shortname().removeprefix("JointModel").lower()
            raise InvalidArgumentError(
                "integrator 'variational' supports only revolute, prismatic and continuous joints yet (robot "
                f"'{name}' has the {kind} joint '{model.names[joint]}'); {_ALTERNATIVES}"
            )
        others = [element for element, _ in system.ledger_elements if element not in _LEDGER]
        others += [name for category, name, _ in getattr(system, "record_fields", ()) if category == "potential"]
        if others:
            raise InvalidArgumentError(
                "integrator 'variational' models joint torques and joint damping only, but "
                f"'{name}' also has: {', '.join(others)}; {_ALTERNATIVES}"
            )

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
        try:
            q_next, v_next, flows = self._step(system, q, v, tau, h)
        except StepFailure as failure:
            return failed(failure.status, str(failure), self.last_evaluations)
        return Attempt(q_next, v_next, flows, None, None, self.last_evaluations)

    def _step(
        self, system: System, q: np.ndarray, v: np.ndarray, tau: np.ndarray, dt: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q_next, v_next, flows); raises StepFailure when Newton fails."""
        if not system.space.is_flat:  # a cheap guard in case a caller skipped check_system
            self.check_system(system)
        robot: Any = system
        model, data, damping = robot.model, robot.data, robot.damping
        p = _symmetric(pin.crba(model, data, q)) @ v
        # The midpoint velocity is v(t + h/2) + O(h²): start Newton there (one ABA call).
        w = v + (0.5 * dt) * robot.unchecked_forward_dynamics(q, v, tau)
        evaluations, iterations = 2, 0
        correction = np.zeros((len(v), len(v)))
        previous_residual = step_w = None
        with np.errstate(all="ignore"):  # a diverging iterate becomes a StepFailure below, not warnings
            while True:
                ev = evaluate(model, data, damping, q, p, tau, dt, w)
                evaluations += 3
                error = float(np.abs(ev.residual).max(initial=0.0))
                relative = error / ev.scale if ev.scale > 0.0 else error
                if relative <= self.tolerance:
                    break
                if not math.isfinite(relative) or iterations == self.max_iterations:
                    self._record(evaluations, iterations, relative)
                    raise StepFailure(
                        "Newton did not solve the discrete Euler–Lagrange equations: relative residual "
                        f"{relative:.3g} > tolerance {self.tolerance:g} after {iterations} iteration(s)",
                        status="newton_failed",
                    )
                if step_w is not None and relative > _SECANT_FLOOR:
                    # Structured secant (Broyden) update of the dropped -(h²/4) ∂²T/∂q² along the last step;
                    # skipped near round-off, where the secant would only learn noise.
                    mismatch = ev.residual - previous_residual - (ev.jacobian + correction) @ step_w
                    correction += np.outer(mismatch, step_w / (step_w @ step_w))
                step_w, singular = _solve(ev.jacobian + correction, -ev.residual)
                if singular:
                    self._record(evaluations, iterations, relative)
                    raise StepFailure("Newton's Jacobian is singular", status="newton_failed")
                w = w + step_w
                previous_residual = ev.residual
                iterations += 1
        q_next = pin.integrate(model, q, dt * w)
        v_next, _ = _solve(_symmetric(pin.crba(model, data, q_next)), ev.momentum_next)  # M is positive definite
        self._record(evaluations + 1, iterations, relative)
        if len(robot.ledger_elements) == 1:
            return q_next, v_next, np.array([dt * (tau @ w)])
        return q_next, v_next, np.array([dt * (tau @ w), dt * (w @ (damping * w))])

    def _record(self, evaluations: int, iterations: int, relative: float) -> None:
        self.last_evaluations, self.last_iterations, self.last_residual = evaluations, iterations, relative


_DGESV: list[Any] = []  # scipy.linalg.lapack.dgesv, imported on first use: SciPy would slow `import multibody_sim`


def _solve(A: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, bool]:
    """x with A x = b and whether A was singular (LAPACK directly: numpy's solve costs 5x more on small A)."""
    if not _DGESV:
        from scipy.linalg.lapack import dgesv

        _DGESV.append(dgesv)
    _, _, x, info = _DGESV[0](A, b)
    return x, info != 0


def _symmetric(upper: np.ndarray) -> np.ndarray:
    """The symmetric matrix whose upper triangle Pinocchio filled (CRBA leaves the lower one stale)."""
    return np.where(_upper_mask(len(upper)), upper, upper.T)


@functools.cache
def _upper_mask(n: int) -> np.ndarray:
    return np.triu(np.ones((n, n), dtype=bool))


@functools.cache
def _zeros(n: int) -> np.ndarray:
    zeros = np.zeros(n)
    zeros.setflags(write=False)
    return zeros
