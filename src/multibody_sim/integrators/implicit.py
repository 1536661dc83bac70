"""Implicit one-stage methods for stiff systems: backward Euler and implicit midpoint, solved by Newton.

Both methods solve for one velocity ``x`` at which the step is taken along the geodesic ``q_n ⊕ s x``:

    R(x) = x - v_n - s a(q_n ⊕ s x, x, tau) = 0,

with ``s = h`` for backward Euler (``x = v_{n+1}``) and ``s = h/2`` for implicit midpoint (``x`` is the
midpoint velocity). Newton's method uses the analytic Jacobian of R from Pinocchio's ABA derivatives (damping
included), chained through the configuration manifold with ``dIntegrate``; a step that Newton cannot solve
fails the attempt (status "newton_failed"), never a silently wrong state.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import Any

import numpy as np
import pinocchio as pin

from .base import Attempt, Integrator, StepFailure, System, failed, split_jacobian, tangent_selectors

_ARG_V = pin.ArgumentPosition.ARG1
_EPS = float(np.finfo(float).eps)


def residual(
    system: System, q: np.ndarray, v: np.ndarray, tau: np.ndarray, s: float, x: np.ndarray, t: float = 0.0
) -> tuple[np.ndarray, np.ndarray]:
    """The implicit equation's residual at the trial velocity x (exposed for tests).

    Args:
        system: the robot or scene.
        q: configuration at the step's start, shape (nq,).
        v: velocity at the step's start, shape (nv,).
        tau: torque held over the step, shape (nv,).
        s: the fraction of the step at which x acts [s] (h for backward Euler, h/2 for implicit midpoint).
        x: trial velocity, shape (nv,).
        t: the step's start time [s]; the dynamics are evaluated at t + s.

    Returns:
        (R, q_x): ``R = x - v - s a(q_x, x, tau)`` [m/s, rad/s], shape (nv,), and ``q_x = q ⊕ s x``,
        shape (nq,).
    """
    q_x = system.space.integrate(q, s * x)
    return x - v - s * system.unchecked_forward_dynamics(q_x, x, tau, t + s), q_x


def residual_jacobian(
    system: System, q: np.ndarray, tau: np.ndarray, s: float, x: np.ndarray, q_x: np.ndarray, t: float = 0.0
) -> np.ndarray:
    """dR/dx, the analytic Jacobian of residual() at x, shape (nv, nv) (exposed for tests).

    ``dR/dx = I - s (da/dq · s dIntegrate/dv(q, s x) + da/dv)``: Pinocchio's da/dq is taken in the tangent
    space at q_x, and dIntegrate maps a change of the tangent argument s x to that tangent space (the
    identity on flat models, where it is skipped).

    Args:
        system: the robot or scene; it must provide ``unchecked_dynamics_derivatives(q, v, tau)``.
        q: configuration at the step's start, shape (nq,).
        tau: torque held over the step, shape (nv,).
        s: as in residual() [s].
        x: trial velocity, shape (nv,).
        q_x: ``q ⊕ s x`` as returned by residual(), shape (nq,).
        t: the step's start time [s]; the derivatives are taken at t + s.
    """
    da_dq, da_dv, _ = system.unchecked_dynamics_derivatives(q_x, x, tau, t + s)
    space = system.space
    if not space.is_flat:
        # dIntegrate is block-diagonal, the identity except on non-commutative joints (free-flyer, ...).
        chart = pin.dIntegrate(space.model, q, s * x, _ARG_V)
        for start, stop in space.curved_blocks:
            da_dq[:, start:stop] = da_dq[:, start:stop] @ chart[start:stop, start:stop]
    jacobian = -s * (s * da_dq + da_dv)
    jacobian[np.diag_indices_from(jacobian)] += 1.0
    return jacobian


@dataclass
class _Counts:
    """What one Newton solve cost, kept up to date as it runs (so a failed solve is counted too)."""

    iterations: int = 0
    evaluations: int = 0  # forward-dynamics (ABA) calls
    jacobians: int = 0  # ABA-derivative calls


# A reused Jacobian is refreshed when the iteration contracts slower than this rate per iteration.
_REFRESH_RATE = 0.25
# Damped Newton halves a step at most this far before taking it anyway.
_MIN_STEP_FRACTION = 1.0 / 64


def _solve(
    system: System,
    q: np.ndarray,
    v: np.ndarray,
    tau: np.ndarray,
    s: float,
    t: float,
    *,
    max_iterations: int,
    rtol: float,
    atol: float,
    counts: _Counts,
) -> np.ndarray:
    """Solve R(x) = 0 by simplified Newton from x = v; raises StepFailure(status="newton_failed").

    The Jacobian is factorised once and reused while the iteration contracts fast (rate θ ≤ 0.5), and
    refreshed at the current iterate when it does not. With a reused Jacobian the iteration converges
    linearly, and the error left after an update of size ‖Δx‖ is about θ/(1 - θ)·‖Δx‖ (Hairer & Wanner,
    Solving ODEs II, IV.8): that estimate, not the bare update, must be within ``atol + rtol·max(‖x‖, ‖v‖)``
    (max norms), so no unconverged state passes. A full step from a fresh Jacobian that does not reduce the
    residual is halved (damped Newton) until it does, down to 1/64 of it; every residual counts as an iteration.
    """
    import scipy.linalg  # here, not at the top: SciPy would cost a third of `import multibody_sim`

    x = v.copy()
    factors: tuple[np.ndarray, np.ndarray] | None = None
    fresh = False  # whether the factorised Jacobian was taken at the current iterate
    previous_update = theta = math.nan
    residual_norm = update_norm = math.nan
    # Damped Newton: a full step from a fresh Jacobian that did not reduce the residual (a strongly nonlinear
    # force, e.g. stiff regularized friction, where the plain iteration cycles) is halved until it does.
    base: tuple[np.ndarray, np.ndarray, float] | None = None  # (iterate, full update, residual norm) to back off
    fraction = 1.0
    for iteration in range(1, max_iterations + 1):
        R, q_x = residual(system, q, v, tau, s, x, t)
        counts.iterations = counts.evaluations = iteration  # one forward-dynamics call per residual
        residual_norm = float(np.max(np.abs(R)))
        if base is not None and not residual_norm < base[2] and fraction > _MIN_STEP_FRACTION:
            fraction *= 0.5
            x = base[0] + fraction * base[1]
            continue
        if not math.isfinite(residual_norm):
            after = f" (last update norm {update_norm:.3g})" if iteration > 1 else " (at the step's start velocity)"
            raise StepFailure(
                f"Newton's residual became non-finite at iteration {iteration}{after}", status="newton_failed"
            )
        damped = fraction < 1.0
        base, fraction = None, 1.0
        if factors is None or damped or (not fresh and theta > _REFRESH_RATE):
            jacobian = residual_jacobian(system, q, tau, s, x, q_x, t)
            counts.jacobians += 1
            factors = _factorise(jacobian, iteration, residual_norm)
            fresh = True
        else:
            fresh = False
        update = scipy.linalg.lu_solve(factors, -R, check_finite=False)
        if fresh:
            base = (x, update, residual_norm)
        x = x + update
        update_norm = float(np.max(np.abs(update)))
        if not math.isfinite(update_norm):
            raise StepFailure(
                f"Newton's iterate became non-finite at iteration {iteration} (residual norm {residual_norm:.3g})",
                status="newton_failed",
            )
        if iteration == 1 or damped:  # no rate yet, but the Jacobian is fresh, so the error left is quadratic
            theta, error = math.nan, update_norm
        else:  # a rate >= 1 is not contracting (yet): keep iterating
            theta = update_norm / previous_update
            error = update_norm * max(1.0, theta / (1.0 - theta)) if theta < 1.0 else math.inf
        previous_update = update_norm
        tolerance = atol + rtol * max(float(np.max(np.abs(x))), float(np.max(np.abs(v))))
        if error <= tolerance:
            return x
    plural = "s" if max_iterations != 1 else ""
    rate = f", contraction {theta:.3g}" if max_iterations > 1 else ""
    raise StepFailure(
        f"Newton did not converge in {max_iterations} iteration{plural} (last update norm {update_norm:.3g}"
        f"{rate}, tolerance {tolerance:.3g}, residual norm {residual_norm:.3g})",
        status="newton_failed",
    )


def _factorise(jacobian: np.ndarray, iteration: int, residual_norm: float) -> tuple[np.ndarray, np.ndarray]:
    """LU factors of the Newton Jacobian; StepFailure when it is non-finite or numerically singular."""
    import scipy.linalg

    if not np.all(np.isfinite(jacobian)):
        raise StepFailure(
            f"Newton's Jacobian became non-finite at iteration {iteration} (residual norm {residual_norm:.3g})",
            status="newton_failed",
        )
    with warnings.catch_warnings():
        # An exactly zero pivot makes scipy warn; the pivot check below reports it as a failure instead.
        warnings.simplefilter("ignore", scipy.linalg.LinAlgWarning)
        lu, pivots = scipy.linalg.lu_factor(jacobian, check_finite=False)
    diagonal = np.abs(np.diag(lu))
    largest, smallest = float(diagonal.max()), float(diagonal.min())
    if smallest <= len(diagonal) * _EPS * largest:
        raise StepFailure(
            f"Newton's Jacobian is singular at iteration {iteration} "
            f"(pivots from {smallest:.3g} to {largest:.3g}, residual norm {residual_norm:.3g})",
            status="newton_failed",
        )
    return lu, pivots


class _ImplicitOneStage(Integrator):
    """Shared Newton machinery of backward Euler and implicit midpoint (see the module docstring).

    Attributes:
        max_iterations: Newton iterations allowed per step before StepFailure.
        rtol, atol: Newton stops when its estimated error in x is at most ``atol + rtol·max(‖x‖∞, ‖v_n‖∞)``
            [m/s, rad/s].
        last_evaluations: forward-dynamics (ABA) evaluations of the latest step, failed or not; the real count,
            where ``evaluations_per_step`` is only typical because the Newton iterations vary.
        last_jacobian_evaluations: ABA-derivative evaluations of the latest step (each costs about 2.5–5 ABA
            calls).
        last_iterations: Newton iterations of the latest step.
    """

    implicit = True
    a_stable = True
    _fraction: float  # the unknown acts at s = _fraction · h
    # Typical on catalog robots at dt = 1 ms (2 to 4 residuals, 1 Jacobian); last_evaluations is exact.
    evaluations_per_step = 3
    max_iterations = 20
    rtol = 1e-10
    atol = 1e-10

    def __init__(self, *, max_iterations: int | None = None, rtol: float | None = None, atol: float | None = None):
        """A method instance, optionally with its own Newton settings (the registry's use the defaults).

        Raises:
            ValueError: max_iterations < 1, or a tolerance that is not positive and finite.
        """
        if max_iterations is not None:
            if int(max_iterations) != max_iterations or max_iterations < 1:
                raise ValueError(f"max_iterations must be a positive integer, got {max_iterations!r}")
            self.max_iterations = int(max_iterations)
        for name, value in (("rtol", rtol), ("atol", atol)):
            if value is not None:
                if not (math.isfinite(value) and value > 0.0):
                    raise ValueError(f"{name} must be positive and finite, got {value!r}")
                setattr(self, name, float(value))
        self.last_evaluations = 0
        self.last_jacobian_evaluations = 0
        self.last_iterations = 0

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
            q_next, v_next, flows = self._step(system, q, v, tau, h, t)
        except StepFailure as failure:
            return failed(failure.status, str(failure), self.last_evaluations)
        return Attempt(q_next, v_next, flows, None, None, self.last_evaluations)

    def _step(
        self, system: System, q: np.ndarray, v: np.ndarray, tau: np.ndarray, h: float, t: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q_next, v_next, flows); raises StepFailure when Newton fails."""
        raise NotImplementedError

    def jacobians(
        self, system: System, q: np.ndarray, v: np.ndarray, tau: np.ndarray, h: float, t: float
    ) -> tuple[np.ndarray, np.ndarray]:
        """The implicit function theorem on R(x; q, v, tau) = x - v - s a(q ⊕ s x, x, tau) = 0.

        dx/dy = (∂R/∂x)⁻¹ (δv + s (da/dq D_q(q, s x) δq + M⁻¹ δtau)), with ∂R/∂x = I - s (s da/dq D_ξ(q, s x) + da/dv).
        Backward Euler (s = h): v' = x, q' = q ⊕ h x. Implicit midpoint (s = h/2): v' = 2x - v, q' = q ⊕ h x.
        Raises StepFailure when the step itself fails.
        """
        nv = system.nv
        space = system.space
        midpoint = self._fraction == 0.5
        s = self._fraction * h
        _, v_next, _ = self._step(system, q, v, tau, h, t)
        x = 0.5 * (v_next + v) if midpoint else v_next  # the converged unknown (to round-off)
        q_x = space.integrate(q, s * x)
        da_dq, da_dv, da_dtau = system.unchecked_dynamics_derivatives(q_x, x, tau, t + s)
        D_q = pin.dIntegrate(space.model, q, s * x, pin.ArgumentPosition.ARG0)
        D_xi = pin.dIntegrate(space.model, q, s * x, _ARG_V)
        dR_dx = np.eye(nv) - s * (s * da_dq @ D_xi + da_dv)
        rhs = np.hstack((s * da_dq @ D_q, np.eye(nv), s * da_dtau))
        d_x = np.linalg.solve(dR_dx, rhs)
        select_q, select_v, _ = tangent_selectors(nv)
        d_q = space.d_integrate(q, h * x, select_q, h * d_x)
        d_v = 2.0 * d_x - select_v if midpoint else d_x
        return split_jacobian(np.vstack((d_q, d_v)), nv)

    def _newton(self, system: System, q: np.ndarray, v: np.ndarray, tau: np.ndarray, s: float, t: float) -> np.ndarray:
        counts = _Counts()
        try:
            return _solve(
                system,
                q,
                v,
                tau,
                s,
                t,
                max_iterations=self.max_iterations,
                rtol=self.rtol,
                atol=self.atol,
                counts=counts,
            )
        finally:  # a failed solve costs evaluations too
            self.last_evaluations = counts.evaluations
            self.last_jacobian_evaluations = counts.jacobians
            self.last_iterations = counts.iterations


class ImplicitEuler(_ImplicitOneStage):
    """Backward Euler: ``v_{n+1} = v_n + h a(q_{n+1}, v_{n+1})``, ``q_{n+1} = q_n ⊕ h v_{n+1}``.

    Order 1, A- and L-stable: a stiff mode is damped in one step whatever h. It also damps oscillations
    (artificial dissipation): on a linear oscillator of frequency ω the energy shrinks by 1/(1 + (ωh)²) per
    step. The ledger uses the same end-point quadrature: h · power(q_{n+1}, v_{n+1}).
    """

    name = "implicit_euler"
    order = 1
    description = "implicit (backward) Euler, Newton with analytic ABA derivatives"
    notes = "A- and L-stable, for stiff systems; damps oscillations (energy × 1/(1 + (ωh)²) per step at frequency ω)"

    _fraction = 1.0  # the unknown x acts at s = h

    def _step(
        self, system: System, q: np.ndarray, v: np.ndarray, tau: np.ndarray, dt: float, t: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        v_next = self._newton(system, q, v, tau, dt, t)
        q_next = system.space.integrate(q, dt * v_next)
        return q_next, v_next, dt * system.ledger_power(q_next, v_next, tau, None, t + dt)


class ImplicitMidpoint(_ImplicitOneStage):
    """Implicit midpoint: ``u = v_n + (h/2) a(q_n ⊕ (h/2) u, u)``, then ``v_{n+1} = 2u - v_n`` and
    ``q_{n+1} = q_n ⊕ h u`` (the midpoint velocity u is the unknown).

    Order 2 (also on floating bases: q_n ⊕ t u is a geodesic along which the velocity stays u), A-stable but
    not L-stable: its stability function tends to -1 on stiff modes, which then ring with alternating sign
    instead of being damped. Linear oscillators keep their amplitude exactly, with the frequency ω turned into
    2 atan(ωh/2)/h. Symplectic only where M is constant (a single pendulum, a point mass): this velocity form
    is not the symplectic momentum form for general M(q). The ledger uses the midpoint rule:
    h · power(q_n ⊕ (h/2) u, u).
    """

    name = "implicit_midpoint"
    order = 2
    description = "implicit midpoint rule, Newton with analytic ABA derivatives"
    notes = (
        "A-stable, not L-stable (stiff modes ring with alternating sign and decay slowly); keeps linear "
        "oscillators' amplitude; symplectic only where M is constant, not for general M(q)"
    )

    _fraction = 0.5  # the unknown u acts at s = h / 2

    def _step(
        self, system: System, q: np.ndarray, v: np.ndarray, tau: np.ndarray, dt: float, t: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        half = 0.5 * dt
        u = self._newton(system, q, v, tau, half, t)
        q_next = system.space.integrate(q, dt * u)
        q_mid = system.space.integrate(q, half * u)
        return q_next, 2.0 * u - v, dt * system.ledger_power(q_mid, u, tau, None, t + half)
