"""Derivatives of one integrator step: the Jacobians (A, B) that LQR and MPC need, from analytic ABA derivatives."""

from __future__ import annotations

import functools
from typing import Any, NamedTuple

import numpy as np
import pinocchio as pin

from .exceptions import InvalidArgumentError, SimulationError
from .integrators import Integrator, StepFailure, get_integrator
from .integrators.explicit_rk import ExplicitRungeKutta
from .integrators.implicit import ImplicitEuler, ImplicitMidpoint
from .integrators.partitioned import SemiImplicitEuler
from .robot import Robot
from .simulation import finite_number, positive_number
from .state import CHART_SERIES

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
    dt = positive_number(dt, "dt")
    t = finite_number(t, "t")
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
    terms = method.chart_terms
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
        if not curved or i == 0:  # the first stage has ξ = 0 whatever y: there the chart map is the identity
            xi_rate[i] = V
            d_xi_rate[i] = d_V
        else:
            xi_rate[i] = space.chart_velocity(xi, V, terms)
            d_xi_rate[i] = d_V
            for (start, stop), P in zip(curved, space.chart_matrix(xi, terms), strict=True):
                d_xi_rate[i][start:stop] = P @ d_V[start:stop]
            _add_chart_curvature(system, d_xi_rate[i], xi, V, d_xi, terms)
    weights = b * h
    xi_end = weights @ xi_rate
    d_xi_end = np.tensordot(weights, d_xi_rate, axes=1)
    d_q_end = _d_integrate(space, q, xi_end, select_q, d_xi_end)
    d_v_end = select_v + np.tensordot(weights, d_acc, axes=1)
    return _split(np.vstack((d_q_end, d_v_end)), nv)


def _add_chart_curvature(
    system: Robot, d_rate: np.ndarray, xi: np.ndarray, V: np.ndarray, d_xi: np.ndarray, terms: int
) -> None:
    """Add ∂(chart_velocity(ξ, V))/∂ξ · dξ on each non-commutative joint's block of the chart rate's derivative."""
    space = system.space
    for (start, stop), G in zip(space.curved_blocks, space.chart_generators, strict=True):
        N = _chart_velocity_derivative(G, xi[start:stop], V[start:stop], terms)
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


def _chart_velocity_derivative(G: np.ndarray, xi: np.ndarray, V: np.ndarray, terms: int) -> np.ndarray:
    """∂/∂ξ of Σ_{n≤terms} b_n A(ξ)ⁿ V (ConfigurationSpace.chart_velocity) on one block, A(x) = (x @ G).reshape(d, d).

    The derivative of Aⁿ V along η is Σ_k A^k A(η) A^(n-1-k) V, and A(η) w = -A(w) η (A is ± the Lie algebra's ad,
    antisymmetric in its two arguments). With w_m = Aᵐ V and T_n = Σ_{k<n} A^k A(w_{n-1-k}) = A(w_{n-1}) + A T_{n-1}
    the derivative is -Σ b_n T_n.
    """
    d = len(V)
    A = (xi @ G).reshape(d, d)
    w = V.copy()
    T = np.zeros((d, d))
    N = np.zeros((d, d))
    for n in range(1, terms + 1):
        T = (w @ G).reshape(d, d) + A @ T
        if CHART_SERIES[n]:
            N -= CHART_SERIES[n] * T
        w = A @ w
    return N


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
