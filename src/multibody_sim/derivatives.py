"""Derivatives of one integrator step: the Jacobians (A, B) that LQR and MPC need, from analytic ABA derivatives."""

from __future__ import annotations

import functools
import math
from fractions import Fraction
from typing import Any, NamedTuple

import numpy as np
import pinocchio as pin

from .exceptions import InvalidArgumentError, SimulationError
from .integrators import Integrator, StepFailure, get_integrator
from .integrators.explicit_rk import ExplicitRungeKutta
from .integrators.implicit import ImplicitEuler, ImplicitMidpoint
from .integrators.partitioned import SemiImplicitEuler
from .robot import Robot

_ARG_Q = pin.ArgumentPosition.ARG0
_ARG_V = pin.ArgumentPosition.ARG1
_SUPPORTED = (
    "the explicit Runge–Kutta methods (euler, midpoint, rk4, bs32, dp54, dop853), semi_implicit_euler, "
    "implicit_euler and implicit_midpoint"
)


class StepJacobians(NamedTuple):
    """The Jacobians of one step x_{n+1} = Φ(x_n, tau) in the tangent space, x = (δq, v).

    Attributes:
        A: ∂x_{n+1}/∂x_n, shape (2 nv, 2 nv), blocks ordered (configuration in the tangent space, velocity).
        B: ∂x_{n+1}/∂tau, shape (2 nv, nv).
    """

    A: np.ndarray
    B: np.ndarray


def linearize(
    system: Robot, q: Any, v: Any, tau: Any, dt: float, *, integrator: str | Integrator = "rk4", t: float = 0.0
) -> StepJacobians:
    """The Jacobians (A, B) of ONE integrator step of dt from (q, v) with tau held, in the tangent space.

    A perturbation of the state is δx = (δq, δv) with the configuration moved to ``q ⊕ δq`` (Pinocchio's
    integrate) and the velocity to ``v + δv``; the step's result is compared in the same way, with ``⊖``
    (Pinocchio's difference) at the unperturbed result. So, to first order::

        step(q ⊕ δq, v + δv, tau + δtau) = (q' ⊕ (A δx + B δtau)[:nv], v' + (A δx + B δtau)[nv:])

    where (q', v') = step(q, v, tau). On a fixed base with revolute and prismatic joints δq is plain
    coordinates. B has a column for every entry of tau; on a floating base the first 6 are the response to a
    wrench on the unactuated base (drop them, ``B[:, 6:]``, for the actuated part).

    The derivatives are analytic: Pinocchio's ABA derivatives (damping included) chained through every stage of
    the method. For explicit Runge–Kutta stages, built in a local chart around q (``q ⊕ ξ``), the chain goes
    through ``dIntegrate`` with respect to both arguments and through the chart velocity ``ξ' = J(ξ)⁻¹ v``,
    whose derivative on a floating base (SE(3)), a spherical (SO(3)) or a planar (SE(2)) joint is summed from its
    Bernoulli series in ``ad_ξ`` to round-off. Implicit methods are differentiated through their converged
    equation by the implicit function theorem. The result is exact to round-off for the step as computed
    (implicit methods: up to their Newton tolerance, 1e-10 relative by default). Torques are NOT saturated at
    the effort limits here, whereas simulate() and Stepper saturate a controller's output.

    Args:
        system: the robot.
        q: configuration, shape (nq,).
        v: velocity [rad/s, m/s], shape (nv,).
        tau: joint torques held over the step [N·m, N], shape (nv,).
        dt: the step [s], > 0.
        integrator: a registry name or an Integrator: an explicit Runge–Kutta method (for the adaptive ones,
            bs32, dp54 and dop853, one step of dt as if the step-size controller had accepted it), semi-implicit
            Euler, implicit Euler or implicit midpoint. The variational integrator is not supported yet.
        t: the step's start time [s] (a scene's time-dependent forces are taken at the stages' times).

    Returns:
        StepJacobians (A, B): unpack as ``A, B = linearize(...)``.

    Raises:
        InvalidArgumentError: a bad argument, an unsupported integrator, or a step that turns a body by more
            than π rad within one Runge–Kutta stage (take a smaller dt).
        SimulationError: the step itself failed (Newton did not converge: status "newton_failed"; non-finite:
            status "diverged").
    """
    method = get_integrator(integrator)
    q = system.check_q(q)
    v = system.check_v(v)
    tau = system.check_tau(tau)
    dt = _positive(dt, "dt")
    if isinstance(t, bool) or not isinstance(t, (int, float, np.integer, np.floating)) or not math.isfinite(t):
        raise InvalidArgumentError(f"t must be a finite number of seconds, got {t!r}")
    t = float(t)
    method.check_system(system)
    with np.errstate(over="ignore", invalid="ignore"):
        if isinstance(method, ExplicitRungeKutta):
            A, B = _explicit_rk(system, method, q, v, tau, dt, t)
        elif isinstance(method, SemiImplicitEuler):
            A, B = _semi_implicit_euler(system, q, v, tau, dt, t)
        elif isinstance(method, (ImplicitEuler, ImplicitMidpoint)):
            A, B = _implicit(system, method, q, v, tau, dt, t)
        else:
            raise InvalidArgumentError(
                f"linearize does not support integrator '{method.name}' yet (supported: {_SUPPORTED})"
            )
    if not (np.isfinite(A).all() and np.isfinite(B).all()):
        raise SimulationError(
            f"linearize: the step of {dt:g} s from this state is not finite (its derivatives overflow); "
            "try a smaller dt",
            status="diverged",
        )
    return StepJacobians(A, B)


# ---- explicit Runge–Kutta --------------------------------------------------------------------------------------
def _explicit_rk(
    system: Robot, method: ExplicitRungeKutta, q: np.ndarray, v: np.ndarray, tau: np.ndarray, h: float, t: float
) -> tuple[np.ndarray, np.ndarray]:
    """Forward-mode chain rule through the stages of ExplicitRungeKutta.step.

    Stage i: ξ_i = h Σ_j a_ij ξ'_j, V_i = v + h Σ_j a_ij v'_j, Q_i = q ⊕ ξ_i, ξ'_i = J(ξ_i)⁻¹ V_i,
    v'_i = a(Q_i, V_i, tau). Every quantity carries its derivative with respect to y = (δq, δv, δtau), a
    (·, 3 nv) matrix; Q_i's is in the tangent space at Q_i: dQ_i = D_q(q, ξ_i) δq + D_ξ(q, ξ_i) dξ_i.
    """
    a = np.array(method.tableau.a, dtype=float)
    b = np.array(method.tableau.b, dtype=float)
    c = np.array(method.tableau.c, dtype=float)
    nv = system.nv
    space = system.space
    curved = space.curved_blocks
    stages = len(b)
    xi_rate = np.zeros((stages, nv))  # ξ'_i
    acc = np.zeros((stages, nv))  # v'_i
    d_xi_rate = np.zeros((stages, nv, 3 * nv))
    d_acc = np.zeros((stages, nv, 3 * nv))
    select_q, select_v, _ = _selectors(nv)
    for i in range(stages):
        weights = a[i, :i] * h
        xi = weights @ xi_rate[:i]
        V = v + weights @ acc[:i]
        d_xi = np.tensordot(weights, d_xi_rate[:i], axes=1) if i else np.zeros((nv, 3 * nv))
        d_V = select_v + (np.tensordot(weights, d_acc[:i], axes=1) if i else 0.0)
        Q = space.integrate(q, xi)
        d_Q = _d_integrate(space, q, xi, select_q, d_xi)
        da_dq, da_dv, da_dtau = system.unchecked_dynamics_derivatives(Q, V, tau, t + c[i] * h)
        acc[i] = system.unchecked_forward_dynamics(Q, V, tau, t + c[i] * h)
        d_acc[i] = da_dq @ d_Q + da_dv @ d_V
        d_acc[i][:, 2 * nv :] += da_dtau
        if not curved or i == 0:  # the first stage has ξ = 0 whatever y: there J = I and dξ = 0
            xi_rate[i] = V
            d_xi_rate[i] = d_V
        else:
            xi_rate[i] = space.chart_velocity(q, xi, V)
            J = pin.dIntegrate(space.model, q, xi, _ARG_V)
            d_xi_rate[i] = d_V
            for start, stop in curved:
                d_xi_rate[i][start:stop] = np.linalg.solve(J[start:stop, start:stop], d_V[start:stop])
            _add_chart_curvature(system, d_xi_rate[i], xi, V, d_xi)
    weights = b * h
    xi_end = weights @ xi_rate
    d_xi_end = np.tensordot(weights, d_xi_rate, axes=1)
    d_q_end = _d_integrate(space, q, xi_end, select_q, d_xi_end)
    d_v_end = select_v + np.tensordot(weights, d_acc, axes=1)
    return _split(np.vstack((d_q_end, d_v_end)), nv)


def _add_chart_curvature(system: Robot, d_rate: np.ndarray, xi: np.ndarray, V: np.ndarray, d_xi: np.ndarray) -> None:
    """Add ∂(J(ξ)⁻¹ V)/∂ξ · dξ on each non-commutative joint's block of the chart velocity's derivative."""
    for start, stop in system.space.curved_blocks:
        ad = _ad_function(system.model, start)
        N = _chart_velocity_derivative(ad, xi[start:stop], V[start:stop])
        d_rate[start:stop] += N @ d_xi[start:stop]


# ---- partitioned and implicit methods -------------------------------------------------------------------------
def _semi_implicit_euler(
    system: Robot, q: np.ndarray, v: np.ndarray, tau: np.ndarray, h: float, t: float
) -> tuple[np.ndarray, np.ndarray]:
    """v' = v + h a(q, v, tau), q' = q ⊕ h v' (SemiImplicitEuler.step)."""
    nv = system.nv
    select_q, select_v, _ = _selectors(nv)
    da_dq, da_dv, da_dtau = system.unchecked_dynamics_derivatives(q, v, tau, t)
    v_next = v + h * system.unchecked_forward_dynamics(q, v, tau, t)
    d_v = select_v + h * np.hstack((da_dq, da_dv, da_dtau))
    d_q = _d_integrate(system.space, q, h * v_next, select_q, h * d_v)
    return _split(np.vstack((d_q, d_v)), nv)


def _implicit(
    system: Robot,
    method: ImplicitEuler | ImplicitMidpoint,
    q: np.ndarray,
    v: np.ndarray,
    tau: np.ndarray,
    h: float,
    t: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The implicit function theorem on R(x; q, v, tau) = x - v - s a(q ⊕ s x, x, tau) = 0.

    dx/dy = (∂R/∂x)⁻¹ (δv + s (da/dq D_q(q, s x) δq + M⁻¹ δtau)), with ∂R/∂x = I - s (s da/dq D_ξ(q, s x) + da/dv).
    Backward Euler (s = h): v' = x, q' = q ⊕ h x. Implicit midpoint (s = h/2): v' = 2x - v, q' = q ⊕ h x.
    """
    nv = system.nv
    space = system.space
    midpoint = isinstance(method, ImplicitMidpoint)
    s = 0.5 * h if midpoint else h
    failure: StepFailure | None = None
    try:
        _, v_next = method.step(system, q, v, tau, h, t)[:2]
    except StepFailure as exc:
        failure = exc
    if failure is not None:  # raised outside the except block: the failure is the cause, not a context
        raise SimulationError(f"linearize: {failure}; try a smaller dt (now {h:g} s)", status=failure.status)
    x = 0.5 * (v_next + v) if midpoint else v_next  # the converged unknown (to round-off)
    q_x = space.integrate(q, s * x)
    da_dq, da_dv, da_dtau = system.unchecked_dynamics_derivatives(q_x, x, tau, t + s)
    D_q = pin.dIntegrate(space.model, q, s * x, _ARG_Q)
    D_xi = pin.dIntegrate(space.model, q, s * x, _ARG_V)
    dR_dx = np.eye(nv) - s * (s * da_dq @ D_xi + da_dv)
    rhs = np.hstack((s * da_dq @ D_q, np.eye(nv), s * da_dtau))
    d_x = np.linalg.solve(dR_dx, rhs)
    select_q, select_v, _ = _selectors(nv)
    d_q = _d_integrate(space, q, h * x, select_q, h * d_x)
    d_v = 2.0 * d_x - select_v if midpoint else d_x
    return _split(np.vstack((d_q, d_v)), nv)


# ---- the configuration manifold ------------------------------------------------------------------------------
def _d_integrate(space: Any, q: np.ndarray, xi: np.ndarray, select_q: np.ndarray, d_xi: np.ndarray) -> np.ndarray:
    """Derivative of (q ⊕ δq) ⊕ ξ(y) in the tangent space at q ⊕ ξ: D_q δq + D_ξ dξ (identities on flat models)."""
    if space.is_flat:
        return select_q + d_xi
    D_q = pin.dIntegrate(space.model, q, xi, _ARG_Q)
    D_xi = pin.dIntegrate(space.model, q, xi, _ARG_V)
    return D_q @ select_q + D_xi @ d_xi


def _chart_velocity_derivative(ad: Any, xi: np.ndarray, V: np.ndarray) -> np.ndarray:
    """∂/∂ξ of J(ξ)⁻¹ V on one Lie group, J = dIntegrate/dξ = Σ (-ad_ξ)ⁿ/(n+1)! (right Jacobian of exp).

    J(ξ)⁻¹ = Σ c_n Yⁿ with Y = -ad_ξ and c_n = B_n/n! (the Taylor coefficients of y/(eʸ - 1)). The derivative of
    Yⁿ V along η is Σ_k Y^k (-ad_η) Y^(n-1-k) V = Σ_k Y^k ad(w_{n-1-k}) η with w_m = Yᵐ V, so with
    T_n = Σ_{k<n} Y^k ad(w_{n-1-k}) = ad(w_{n-1}) + Y T_{n-1} the derivative is Σ c_n T_n. The series converges
    for rotations below 2π; it is summed until its terms fall below round-off.
    """
    angle = ad.angle(xi)
    if angle >= math.pi:
        raise InvalidArgumentError(
            f"linearize: a Runge–Kutta stage turns a joint by {angle:.3g} rad (more than π) within one step; "
            "take a smaller dt"
        )
    Y = -ad.matrix(xi)
    coefficients = _series_coefficients()
    w = V.copy()
    T = np.zeros((len(V), len(V)))
    N = np.zeros_like(T)
    scale = float(np.abs(ad.matrix(V)).max()) + 1e-300
    # Terms shrink like (angle / 2π)^n: at angle < π about 60 terms reach round-off.
    for n in range(1, len(coefficients)):
        T = ad.matrix(w) + Y @ T
        if coefficients[n]:
            term = coefficients[n] * T
            N += term
            if n > 2 and float(np.abs(term).max()) <= 1e-17 * scale:
                break
        w = Y @ w
    return N


@functools.cache
def _series_coefficients(count: int = 120) -> tuple[float, ...]:
    """c_n = B_n / n!, the Taylor coefficients of y / (eʸ - 1), exactly (from Σ_{k≤n} c_k/(n+1-k)! = 0)."""
    c = [Fraction(1)]
    factorials = [Fraction(math.factorial(k)) for k in range(count + 2)]
    for n in range(1, count):
        c.append(-sum((c[k] / factorials[n + 1 - k] for k in range(n)), Fraction(0)))
    return tuple(float(x) for x in c)


class _Se3:
    """se(3), v = (linear, angular): Pinocchio's motion cross-product matrix."""

    @staticmethod
    def matrix(v: np.ndarray) -> np.ndarray:
        return np.array(pin.Motion(v).action)

    @staticmethod
    def angle(v: np.ndarray) -> float:
        return float(np.linalg.norm(v[3:]))


class _So3:
    """so(3): ad_ω = [ω]×."""

    @staticmethod
    def matrix(v: np.ndarray) -> np.ndarray:
        return np.array(pin.skew(v))

    @staticmethod
    def angle(v: np.ndarray) -> float:
        return float(np.linalg.norm(v))


class _Se2:
    """se(2), v = (vx, vy, ω): [v, ξ] = (ω R ξ_t - ξ_ω R v_t, 0) with R the quarter turn."""

    @staticmethod
    def matrix(v: np.ndarray) -> np.ndarray:
        return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [0.0, 0.0, 0.0]])

    @staticmethod
    def angle(v: np.ndarray) -> float:
        return abs(float(v[2]))


def _ad_function(model: pin.Model, start: int) -> Any:
    """The Lie algebra (ad matrix and rotation angle) of the joint whose velocity block starts at `start`."""
    joint = next(j for j in model.joints[1:] if j.idx_v == start)
    if joint.nv == 6:
        return _Se3
    if joint.shortname() == "JointModelPlanar":
        return _Se2
    if joint.nv == 3 and joint.nq == 4:
        return _So3
    raise InvalidArgumentError(f"linearize: unsupported joint type {joint.shortname()}")  # pragma: no cover


# ---- small helpers -------------------------------------------------------------------------------------------
@functools.cache
def _selectors_cached(nv: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    eye, zero = np.eye(nv), np.zeros((nv, nv))
    blocks = (np.hstack((eye, zero, zero)), np.hstack((zero, eye, zero)), np.hstack((zero, zero, eye)))
    for block in blocks:
        block.setflags(write=False)
    return blocks


def _selectors(nv: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """[I 0 0], [0 I 0], [0 0 I]: the derivatives of δq, δv and δtau with respect to y = (δq, δv, δtau)."""
    return _selectors_cached(nv)


def _split(jacobian: np.ndarray, nv: int) -> tuple[np.ndarray, np.ndarray]:
    return jacobian[:, : 2 * nv].copy(), jacobian[:, 2 * nv :].copy()


def _positive(value: Any, name: str) -> float:
    is_number = isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))
    if not is_number or not (math.isfinite(value) and value > 0):
        raise InvalidArgumentError(f"{name} must be a positive number of seconds, got {value!r}")
    return float(value)
