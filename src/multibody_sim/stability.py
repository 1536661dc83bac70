"""Stability at the extremes: the linearised system, its stiffness ratio, and the largest stable step per method."""

from __future__ import annotations

import math
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
import pinocchio as pin

from .exceptions import InvalidArgumentError, SimulationError
from .integrators import Integrator, get_integrator
from .robot import Robot, check_system
from .simulation import simulate
from .trajectory import Trajectory
from .validation import positive_number

# A mode decays when Re λ < -DECAY_TOLERANCE · max|λ|. The undamped modes of an equilibrium come out of LAPACK
# with real parts of round-off size: at most 5e-14 of max|λ| on catalog robots and on arms whose mass matrix has a
# condition number of 1e10, 200 times below this threshold, which still resolves stiffness ratios up to ~1e10.
DECAY_TOLERANCE = 1e-11
DEFAULT_ENERGY_FRACTION = 0.1
DEFAULT_MAX_STEPS = 200_000


# ---- the linearised system ---------------------------------------------------------------------------------
def linearization(system: Robot, q: Any, v: Any, tau: Any = None) -> np.ndarray:
    """The state matrix A of the first-order system x' = f(x), x = (δq, v), linearised at (q, v, tau).

    ``A = [[∂ξ'/∂ξ, I], [da/dq, da/dv]]``, shape (2 nv, 2 nv), where the configuration is perturbed in the
    tangent space (q ⊕ ξ) and ``da/dq``, ``da/dv`` are Pinocchio's analytic ABA derivatives with the joint
    damping included (``Robot.unchecked_dynamics_derivatives``). ``∂ξ'/∂ξ`` is zero on flat joints (revolute,
    prismatic, continuous) and at v = 0; on a non-commutative joint (free-flyer SE(3), spherical SO(3), planar
    SE(2)) moving at v ≠ 0 it is ``-½ ad_v``, the derivative of the chart velocity ``ξ' = J(ξ)⁻¹ v`` at
    ξ = 0: A is then exactly the Jacobian of the ODE that the explicit Runge–Kutta stages integrate in the local
    chart around q. At an equilibrium (v = 0, a = 0) its eigenvalues are the modes' rates λ [1/s]; elsewhere A
    is a frozen-coefficient Jacobian, useful for step-size limits (|h λ| inside a method's stability region).
    This is the continuous-time system; the Jacobians of one integrator step are :func:`multibody_sim.linearize`.

    Args:
        system: the robot.
        q: configuration, shape (nq,).
        v: velocity [rad/s, m/s], shape (nv,).
        tau: joint torques [N·m, N], shape (nv,); None means zero.

    Returns:
        A [1/s and 1/s² blocks], shape (2 nv, 2 nv), ordered (tangent configuration, velocity).

    Raises:
        InvalidArgumentError: q, v or tau has the wrong shape or is not finite.
    """
    check_system(system)
    q = system.check_q(q)
    v = system.check_v(v)
    tau = np.zeros(system.nv) if tau is None else system.check_tau(tau)
    nv = system.nv
    da_dq, da_dv, _ = system.unchecked_dynamics_derivatives(q, v, tau)
    A = np.zeros((2 * nv, 2 * nv))
    A[:nv, nv:] = np.eye(nv)
    A[nv:, :nv] = da_dq
    A[nv:, nv:] = da_dv
    for start, stop in system.space.curved_blocks:
        A[start:stop, start:stop] = -0.5 * _ad(system.model, start, v[start:stop])
    return A


def _ad(model: pin.Model, start: int, v: np.ndarray) -> np.ndarray:
    """ad_v, the Lie bracket [v, ·] of the group of the joint whose velocity block starts at `start`."""
    joint = next(j for j in model.joints[1:] if j.idx_v == start)
    if joint.nv == 6:  # free-flyer: se(3), v = (linear, angular); Pinocchio's motion cross-product matrix
        return np.array(pin.Motion(v).action)
    if joint.shortname() == "JointModelPlanar":  # se(2), v = (vx, vy, ω): [v, ξ] = (ω J ξ_t - ξ_ω J v_t, 0)
        turn = np.array([[0.0, -1.0], [1.0, 0.0]])
        ad = np.zeros((3, 3))
        ad[:2, :2] = v[2] * turn
        ad[:2, 2] = -turn @ v[:2]
        return ad
    if joint.nv == 3:  # spherical: so(3), [ω, ξ] = ω × ξ
        return np.array(pin.skew(v))
    raise InvalidArgumentError(f"linearization: unsupported joint type {joint.shortname()}")  # pragma: no cover


@dataclass(frozen=True)
class Stiffness:
    """The stiffness of a system linearised at one state (see :func:`stiffness_ratio`).

    Attributes:
        ratio: |Re λ| of the fastest decaying mode over |Re λ| of the slowest decaying mode; nan when no mode
            decays.
        eigenvalues: every eigenvalue of the state matrix [1/s], shape (2 nv,), complex, sorted from the
            fastest decay (most negative real part) to the least stable.
        fastest: the decaying eigenvalue with the largest |Re λ| [1/s], or None.
        slowest: the decaying eigenvalue with the smallest |Re λ| [1/s], or None.
        decaying: number of decaying eigenvalues (Re λ < -decay_tolerance · spectral_radius).
        spectral_radius: max |λ| [1/s]: what limits an explicit method's step on oscillatory modes too.
    """

    ratio: float
    eigenvalues: np.ndarray
    fastest: complex | None
    slowest: complex | None
    decaying: int
    spectral_radius: float


def stiffness_ratio(
    system: Robot, q: Any, v: Any, tau: Any = None, *, decay_tolerance: float = DECAY_TOLERANCE
) -> Stiffness:
    """The stiffness ratio of the system linearised at (q, v, tau), with the eigenvalues behind it.

    The ratio is ``max |Re λ| / min |Re λ|`` over the DECAYING modes only: the eigenvalues λ of
    :func:`linearization` with ``Re λ < -decay_tolerance · max|λ|``. The other ``2 nv - decaying`` eigenvalues
    are left out on purpose: undamped oscillatory modes (Re λ = 0 up to round-off: an undamped stiff spring is
    oscillatory, not stiff in this sense, and limits explicit steps through ``spectral_radius`` instead),
    neutral modes (λ = 0: a free body's position and orientation, cyclic joints) and growing modes (Re λ > 0,
    e.g. an inverted pendulum). A complex pair counts as two decaying eigenvalues with the same real part. With
    no decaying mode the ratio is nan; with a single decay rate it is 1.

    At an equilibrium the eigenvalues are the rates of the modes of small motions. Elsewhere they belong to a
    frozen-coefficient Jacobian: a conservative system then shows pairs ±λ, and a saddle's -λ counts as decaying.

    Args:
        system: the robot.
        q: configuration, shape (nq,).
        v: velocity [rad/s, m/s], shape (nv,).
        tau: joint torques [N·m, N], shape (nv,); None means zero.
        decay_tolerance: the relative threshold on Re λ below which a mode counts as decaying (default 1e-11,
            200 times the round-off seen on undamped equilibria); ratios above ~1/decay_tolerance cannot be
            resolved.

    Returns:
        The ratio, the eigenvalues and the fastest and slowest decaying ones.

    Raises:
        InvalidArgumentError: q, v or tau has the wrong shape or is not finite, or decay_tolerance is not positive.
    """
    tolerance = positive_number(decay_tolerance, "decay_tolerance", None)
    eigenvalues = np.linalg.eigvals(linearization(system, q, v, tau))
    eigenvalues = eigenvalues[np.lexsort((eigenvalues.imag, eigenvalues.real))]
    radius = float(np.max(np.abs(eigenvalues))) if len(eigenvalues) else 0.0
    decaying = eigenvalues[eigenvalues.real < -tolerance * radius]
    if not len(decaying):
        return Stiffness(math.nan, eigenvalues, None, None, 0, radius)
    fastest, slowest = complex(decaying[0]), complex(decaying[-1])
    return Stiffness(fastest.real / slowest.real, eigenvalues, fastest, slowest, len(decaying), radius)


# ---- the largest stable step ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class LadderRung:
    """One step size tried by :func:`largest_stable_dt`.

    Attributes:
        dt: the step [s].
        stable: whether the run met the criterion (see StabilityLimit.criterion).
        status: the run's status: "completed", or why it stopped ("diverged", "newton_failed", ...).
        max_energy_error: max |energy_error| over the samples it kept [J].
        reached: the last sample's time [s] (the horizon when completed).
        steps: steps taken.
        wall_time: wall-clock time of the run [s].
        reason: why the rung is unstable, "" when stable.
    """

    dt: float
    stable: bool
    status: str
    max_energy_error: float
    reached: float
    steps: int
    wall_time: float
    reason: str


@dataclass(frozen=True)
class StabilityLimit:
    """The result of :func:`largest_stable_dt`: the answer, the ladder it came from, and what "stable" meant.

    Attributes:
        integrator: the method's registry name.
        largest_stable_dt: the first rung from the top that is stable and whose next smaller rung is stable
            too [s]; None when the ladder found none.
        confirmed: False when the answer's next smaller rung could not be run (the ladder hit max_steps).
        rungs: every rung tried, from the largest step down.
        horizon: the simulated duration of every run [s].
        energy_bound: the bound on max |energy_error| [J].
        criterion: the stability criterion, in words.
        notes: what the ladder saw that the answer alone does not say (isolated stable rungs above the answer,
            the ladder running out).
    """

    integrator: str
    largest_stable_dt: float | None
    confirmed: bool
    rungs: tuple[LadderRung, ...]
    horizon: float
    energy_bound: float
    criterion: str
    notes: tuple[str, ...] = ()

    def table(self) -> str:
        """The ladder as Markdown table rows: dt, stable, status, reached, max |energy_error|."""
        lines = ["| dt [s] | stable | status | reached [s] | max abs energy error [J] |", "|---|---|---|---|---|"]
        for rung in self.rungs:
            lines.append(
                f"| {rung.dt:.4g} | {'yes' if rung.stable else 'no'} | {rung.status} | {rung.reached:.4g} | "
                f"{rung.max_energy_error:.3g} |"
            )
        return "\n".join(lines)


def largest_stable_dt(
    system: Robot,
    integrator: str | Integrator,
    q0: Any,
    v0: Any,
    *,
    horizon: float,
    dt_max: float | None = None,
    ratio: float = 2.0**0.5,
    energy_bound: float | None = None,
    energy_fraction: float = DEFAULT_ENERGY_FRACTION,
    max_steps: int = DEFAULT_MAX_STEPS,
    **options: Any,
) -> StabilityLimit:
    """The largest step at which a fixed-step integrator runs stably from (q0, v0), over a geometric ladder.

    The ladder tries ``dt_max, dt_max / ratio, dt_max / ratio², ...`` from the top. A run is STABLE when all
    three hold:

    1. ``simulate(system, q0, v0, duration=horizon, dt=dt, integrator=integrator, **options)`` completes the
       horizon (no SimulationError: no divergence, Newton failure, ...);
    2. every sample is finite;
    3. ``max |energy_error| <= energy_bound`` over the samples (the energy ledger's consistency check:
       ``H - H(0) - work + dissipated``).

    The default bound is ``energy_fraction`` (10 %) of the run's energy scale ``T(q0, v0) + m |g| · 1 m``
    (the kinetic energy at the start plus the work of lifting the whole robot by one metre, as the stepping
    loop's blow-up check uses, without the arbitrary offset of V(q0)); pass ``energy_bound`` in joules when a
    system's energy in play is far smaller or larger (a 1 cm pendulum, a small oscillation). On a conservative
    system an explicit method's energy drifts at any step, so there the criterion also measures accuracy.

    Stability need not be monotone in dt (a large step can land on an isolated stable rung, e.g. where a
    mode's growth and the horizon conspire). So the answer is the first rung from the top that is stable AND
    whose next smaller rung is stable too; stable rungs above it that fail this check are reported in
    ``notes``. Rungs below the confirming one are not run. The ladder stops before a run would take more than
    ``max_steps`` steps: with no answer, or with an unconfirmed one (``confirmed=False``) when the last rung it
    could run was stable.

    Args:
        system: the robot.
        integrator: a fixed-step integrator's registry name or object (adaptive methods choose their own steps
            and are refused).
        q0: initial configuration, shape (nq,).
        v0: initial velocity, shape (nv,).
        horizon: simulated duration of each run [s], > 0.
        dt_max: the ladder's top [s], in (0, horizon]; default horizon / 10.
        ratio: the ladder's ratio between successive steps, > 1 (default √2).
        energy_bound: the bound on max |energy_error| [J], > 0; default energy_fraction times the energy scale.
        energy_fraction: the default bound's fraction of the energy scale, > 0.
        max_steps: the largest number of steps one run may take, ≥ 1.
        **options: passed to simulate (e.g. controller); periods that must be whole multiples of dt (output_dt,
            control_dt) do not fit a geometric ladder in general.

    Returns:
        The answer, every rung tried (step, stability, status, energy error, time reached) and the criterion.

    Raises:
        InvalidArgumentError: a bad argument, or an adaptive integrator.
    """
    check_system(system)
    method = get_integrator(integrator)
    if method.adaptive:
        raise InvalidArgumentError(
            f"integrator '{method.name}' is adaptive: it chooses its own steps, so it has no largest stable dt "
            "(largest_stable_dt applies to fixed-step integrators)"
        )
    q0, v0 = system.check_q(q0, "q0"), system.check_v(v0, "v0")
    horizon = positive_number(horizon, "horizon", None)
    dt_max = horizon / 10 if dt_max is None else positive_number(dt_max, "dt_max", None)
    if dt_max > horizon:
        raise InvalidArgumentError(f"dt_max must be at most the horizon ({horizon:g} s), got {dt_max:g} s")
    ratio = positive_number(ratio, "ratio", None)
    if ratio <= 1.0:
        raise InvalidArgumentError(f"ratio must be greater than 1, got {ratio:g}")
    energy_fraction = positive_number(energy_fraction, "energy_fraction", None)
    if isinstance(max_steps, bool) or not isinstance(max_steps, (int, np.integer)) or max_steps < 1:
        raise InvalidArgumentError(f"max_steps must be a positive integer, got {max_steps!r}")
    scale = system.kinetic_energy(q0, v0) + system.energy_scale
    if energy_bound is None:
        bound = energy_fraction * scale
        bound_text = f"{bound:.3g} J ({energy_fraction:g} of the energy scale T(q0, v0) + m|g|·1 m = {scale:.3g} J)"
    else:
        bound = positive_number(energy_bound, "energy_bound", None)
        bound_text = f"{bound:.3g} J (given)"
    criterion = (
        f"stable: the run completes the {horizon:g} s horizon (no divergence, Newton failure or other early stop), "
        f"every sample is finite, and max |energy_error| <= {bound_text}; the answer is the first rung from the "
        f"top (dt_max = {dt_max:.4g} s, ratio {ratio:.4g}) that is stable and whose next smaller rung is stable too"
    )
    rungs: list[LadderRung] = []
    notes: list[str] = []
    answer: float | None = None
    confirmed = False
    dt = dt_max
    while True:
        if horizon / dt > max_steps * (1 + 1e-9):
            if rungs and rungs[-1].stable:  # a stable last rung that cannot be confirmed is still the answer
                answer = rungs[-1].dt
            notes.append(f"ladder stopped at dt = {dt:.4g} s: a run would take more than max_steps = {max_steps} steps")
            break
        rung = _run_rung(system, method, q0, v0, horizon, dt, bound, options)
        rungs.append(rung)
        if rung.stable and len(rungs) >= 2 and rungs[-2].stable:
            answer, confirmed = rungs[-2].dt, True
            break
        if not rung.stable and len(rungs) >= 2 and rungs[-2].stable:
            notes.append(
                f"isolated stable rung at dt = {rungs[-2].dt:.4g} s (the next smaller step, {dt:.4g} s, is "
                f"unstable: {rung.reason}); stability is not monotone in dt here"
            )
        dt /= ratio
    return StabilityLimit(
        integrator=method.name,
        largest_stable_dt=answer,
        confirmed=confirmed,
        rungs=tuple(rungs),
        horizon=horizon,
        energy_bound=bound,
        criterion=criterion,
        notes=tuple(notes),
    )


def _run_rung(
    system: Robot,
    method: Integrator,
    q0: np.ndarray,
    v0: np.ndarray,
    horizon: float,
    dt: float,
    bound: float,
    options: dict[str, Any],
) -> LadderRung:
    start = time.perf_counter()
    traj: Trajectory | None
    try:
        traj = simulate(system, q0, v0, duration=horizon, dt=dt, integrator=method, **options)
    except SimulationError as failure:
        traj, status = failure.trajectory, failure.status
    else:
        status = traj.status
    wall = time.perf_counter() - start
    if traj is None or not len(traj):  # pragma: no cover (the loop always keeps the initial sample)
        return LadderRung(dt, False, status, math.nan, 0.0, 0, wall, f"{status} before the first sample")
    finite = bool(np.isfinite(traj.q).all() and np.isfinite(traj.v).all() and np.isfinite(traj.energy_error).all())
    error = traj.max_abs_energy_error if finite else math.inf
    reached = float(traj.t[-1])
    if status != "completed":
        reason = f"{status} at t = {reached:.4g} s"
    elif not finite:  # pragma: no cover (simulate keeps only finite samples; checked all the same)
        reason = "non-finite samples"
    elif not error <= bound:
        reason = f"max |energy_error| {error:.3g} J > {bound:.3g} J"
    else:
        reason = ""
    return LadderRung(dt, not reason, status, error, reached, int(traj.stats.get("steps", 0)), wall, reason)
