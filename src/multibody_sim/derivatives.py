"""Derivatives of one integrator step: the Jacobians (A, B) that LQR and MPC need, from analytic ABA derivatives."""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from .exceptions import InvalidArgumentError, SimulationError
from .integrators import Integrator, StepFailure, get_integrator
from .robot import Robot, check_system
from .validation import finite_number, positive_number

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
    check_system(system)
    method = get_integrator(integrator)
    q = system.check_q(q)
    v = system.check_v(v)
    tau = system.check_tau(tau)
    dt = positive_number(dt, "dt")
    t = finite_number(t, "t")
    method.check_system(system)
    failure: StepFailure | None = None
    with np.errstate(over="ignore", invalid="ignore"):
        try:
            jacobians = method.jacobians(system, q, v, tau, dt, t)
        except StepFailure as exc:
            failure = exc
    if failure is not None:  # raised outside the except block: the failure is the cause, not a context
        raise SimulationError(f"linearize: {failure}; try a smaller dt (now {dt:g} s)", status=failure.status)
    if jacobians is None:
        raise InvalidArgumentError(
            f"linearize does not support integrator '{method.name}' yet (supported: {_SUPPORTED})"
        )
    A, B = jacobians
    if not (np.isfinite(A).all() and np.isfinite(B).all()):
        raise SimulationError(
            f"linearize: the step of {dt:g} s from this state is not finite (its derivatives overflow); "
            "try a smaller dt",
            status="diverged",
        )
    return StepJacobians(A, B)
