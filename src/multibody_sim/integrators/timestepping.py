"""Velocity-level time-stepping for contact (Moreau–Jean, semi-implicit), on Pinocchio 4.1's cone solvers.

One step from (q, v) over h with tau held:

    v_free = v + h a(q, v, tau)                       (every smooth force: gravity, torques, elements)
    λ      = argmin ½ λᵀ G λ + gᵀ λ over the cones     (G = J M⁻¹ Jᵀ, g = J v_free + b: scenes/contact.py)
    v⁺     = v_free + M⁻¹ Jᵀ λ,      q⁺ = q ⊕ h v⁺

λ are impulses [N·s]: the contact problem is solved at the velocity level, so impacts, stiction and sliding are
exact within one step (no stiffness, no regularization), at first order in h. The solver is Pinocchio's ADMM
(SPECTRAL rule, Anderson acceleration of capacity 10: it converges reliably there) or PGS, warm-started from the
impulses of the previous step at the same contact (the solver state), so a resting contact costs a few
iterations.

Energy ledger (each term from its own formula; energy_error then checks that they close):

- smooth elements (torques, damping, forces): h · power(q, v⁺) (the end-point rule);
- ``contact`` (dissipated): what the impulses take out, ``D = -λᵀ(b_corr + b_rest) - W`` with
  ``W = ½ λᵀ J (v⁺ + v_free) = T(q, v⁺) - T(q, v_free)``; complementarity makes D ≥ 0 on every step
  (``D = -λᵀ(u⁺ + b) + λᵀ b_spec + ½ λᵀ G λ``, each term ≥ 0);
- ``penetration_correction`` (work): ``-λᵀ b_corr ≥ 0``, what pushing penetrations out puts back;
- ``restitution`` (work): ``-λᵀ b_rest ≥ 0``, what a bounce gives back;
- ``timestep_error`` (work): the semi-implicit step's own O(h²) energy error per step,
  ``[T(q, v_free) - T(q, v)] + [T(q⁺, v⁺) - T(q, v⁺)] + [V(q⁺) - V(q)] - Σ smooth flows`` (in free fall
  -½ m g² h² per step, at rest +½ m g² h², which the contact takes out again).

A step whose solver stops at its iteration cap continues with the best impulses found and is counted in the solver
state (``stats``: ``solver_unconverged``); the driver ends a run where that happened on more than 1 % of the steps
with status "solver_failed".
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pinocchio as pin

from ..ordered import ordered_dot, ordered_matvec
from .base import Attempt, Integrator, System, velocity_update
from .partitioned import SemiImplicitEuler

MAX_ITERATIONS = 1000
TOLERANCE = 1e-12  # absolute and relative feasibility and complementarity tolerances of the solvers
ANDERSON_CAPACITY = 10
_SEMI_IMPLICIT = SemiImplicitEuler()


@dataclass
class ContactState:
    """The solver state of the time-stepper: warm-start impulses and counts.

    Attributes:
        impulses: the latest impulses of each constraint block, by key (see ContactProblem.keys).
        steps: steps taken with a constraint problem to solve.
        unconverged: of those, steps whose solver reached its iteration cap.
        iterations: solver iterations in all.
        landed: pair index -> approach speed of the pairs that landed on the latest step (they bounce next).
        active: the contacts of the latest step: (problem, impulses), for recording.
    """

    impulses: dict[tuple[Any, ...], np.ndarray] = field(default_factory=dict)
    steps: int = 0
    unconverged: int = 0
    iterations: int = 0
    landed: dict[int, float] = field(default_factory=dict)
    active: tuple[Any, np.ndarray] | None = None


# The counts a contact run's stats gain (Trajectory.stats, BatchTrajectory.stats, Stepper.stats).
SOLVER_COUNTS = ("solver_steps", "solver_unconverged", "solver_iterations")


def solver_counts(state: Any) -> dict[str, int]:
    """The SOLVER_COUNTS of a solver state with steps, unconverged and iterations (ContactState, or the native
    kernel's row state)."""
    return dict(zip(SOLVER_COUNTS, (state.steps, state.unconverged, state.iterations), strict=True))


def admm_settings(max_iterations: int = MAX_ITERATIONS) -> Any:
    """ADMM with the SPECTRAL update rule and Anderson acceleration (capacity 10), tolerances TOLERANCE."""
    settings = pin.ADMMSolverSettings()
    settings.admm_update_rule = pin.ADMMUpdateRule.SPECTRAL
    settings.anderson_capacity = ANDERSON_CAPACITY
    settings.max_iterations = max_iterations
    for name in (
        "absolute_feasibility_tol",
        "relative_feasibility_tol",
        "absolute_complementarity_tol",
        "relative_complementarity_tol",
    ):
        setattr(settings, name, TOLERANCE)
    return settings


def pgs_settings(max_iterations: int = MAX_ITERATIONS) -> Any:
    """PGS with tolerances TOLERANCE and max_iterations sweeps."""
    settings = pin.PGSSolverSettings()
    settings.max_iterations = max_iterations
    for name in (
        "absolute_feasibility_tol",
        "relative_feasibility_tol",
        "absolute_complementarity_tol",
        "relative_complementarity_tol",
    ):
        if hasattr(settings, name):
            setattr(settings, name, TOLERANCE)
    return settings


class TimeStepping(Integrator):
    """Moreau–Jean velocity-level time-stepping with Pinocchio's ADMM (or PGS) cone solver (module docstring)."""

    name = "timestepping"
    order = 1
    description = "velocity-level contact time-stepping (Moreau–Jean), Pinocchio's ADMM or PGS cone solver"
    evaluations_per_step = 1
    steps_contact = True
    notes = (
        "the one integrator of contact scenes ([ground], [contact], [[object]]): exact Coulomb friction, impacts "
        "and stiction at first order; without contact it is semi-implicit Euler"
    )

    def __init__(self, *, max_iterations: int = MAX_ITERATIONS):
        """A time-stepper whose solver stops after max_iterations (the registry's: MAX_ITERATIONS).

        Raises:
            ValueError: max_iterations is not a positive integer.
        """
        if int(max_iterations) != max_iterations or max_iterations < 1:
            raise ValueError(f"max_iterations must be a positive integer, got {max_iterations!r}")
        self.max_iterations = int(max_iterations)

    def native_data(self) -> dict[str, Any]:
        """The method as the native kernel renders it (_native.Method's fields; its solver's constants and the
        scene's geometry cross as _native.ContactScene, kernels/native.contact_data)."""
        return {"kind": "timestepping", "stages": 1, "a": [0.0], "b": [1.0], "c": [0.0], "chart_terms": 0}

    def init(self, system: System, q: np.ndarray, v: np.ndarray) -> ContactState:
        return ContactState()

    def restart(self, system: System, q: np.ndarray, v: np.ndarray, state: Any) -> Any:
        """A new torque does not invalidate the impulses: the warm start and counts carry over."""
        return state if isinstance(state, ContactState) else self.init(system, q, v)

    def contact_records(self, system: System, state: Any) -> np.ndarray | None:
        """The active contacts of the step that produced this state: (k, 11) rows of pair (2 body indices), point
        (3), normal (3) and impulse on body 2 (3, world, [N·s]); None when there were none."""
        if not isinstance(state, ContactState) or state.active is None:
            return None
        problem, impulses = state.active
        return system.contact.records(problem, impulses)  # type: ignore[attr-defined]

    def jacobians(
        self, system: System, q: np.ndarray, v: np.ndarray, tau: np.ndarray, h: float, t: float
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """Semi-implicit Euler's without contact; None with contact (the step is not differentiable there)."""
        if getattr(system, "contact", None) is not None:
            return None
        return _SEMI_IMPLICIT.jacobians(system, q, v, tau, h, t)

    def solver_stats(self, state: Any) -> dict[str, int]:
        if not isinstance(state, ContactState):
            return {}
        return solver_counts(state)

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
        scene: Any = system
        contact = getattr(scene, "contact", None)
        # Servo terms taken implicitly raise the armature for the whole velocity update, the contact problem's
        # M included (scenes/actuators.py), and come off before the energies below.
        v_free, evaluations, servos = velocity_update(system, q, v, tau, h, t)
        try:
            if contact is None:  # nothing to touch: semi-implicit Euler, with the end-point rule for the ledger
                if servos is not None:
                    servos.end_implicit()
                q_next = system.space.integrate(q, h * v_free)
                flows = h * system.ledger_power(q_next, v_free, tau, None, t + h)
                return Attempt(q_next, v_free, flows, None, state, evaluations)
            state = state if isinstance(state, ContactState) else ContactState()
            problem = contact.problem(q, v, v_free, h, state.landed)
            new = ContactState(state.impulses, state.steps, state.unconverged, state.iterations)
            if problem is None:
                v_next, impulses, work, correction, bounce = v_free, np.zeros(0), 0.0, 0.0, 0.0
                new.impulses = {}
            else:
                impulses, converged, iterations = self._solve(contact.solver, problem, state.impulses)
                new.steps += 1
                new.iterations += iterations
                new.unconverged += not converged
                new.impulses = _split(impulses, problem.keys, problem.sizes)
                # sums in index order (ordered.py), as the native kernel (src/native/contact.cpp) forms them
                generalized = ordered_matvec(problem.jacobian.T, impulses)
                v_next = v_free + contact.inverse_mass_times(generalized)
                work = 0.5 * ordered_dot(generalized, v_next + v_free)  # ½ λᵀ J (v⁺ + v_free)
                correction = -ordered_dot(impulses, problem.correction)
                bounce = -ordered_dot(impulses, problem.restitution)
                new.active = (problem, impulses)
                new.landed = problem.landings
        finally:
            if servos is not None:
                servos.end_implicit()
        q_next = system.space.integrate(q, h * v_next)
        flows = h * system.ledger_power(q_next, v_next, tau, None, t + h)
        # The contact's elements come last: contact, penetration_correction, restitution, timestep_error.
        flows[-4:] = 0.0
        smooth = 0.0
        for flow, (_, kind) in zip(flows[:-4], system.ledger_elements, strict=False):
            smooth += flow if kind == "work" else -flow
        kinetic, potential = scene.unchecked_energies(q, v)
        kinetic_free = scene.unchecked_energies(q, v_free)[0]
        kinetic_next = scene.unchecked_energies(q, v_next)[0] if problem is not None else kinetic_free
        kinetic_end, potential_end = scene.unchecked_energies(q_next, v_next)
        flows[-4] = correction + bounce - work
        flows[-3] = correction
        flows[-2] = bounce
        flows[-1] = (kinetic_free - kinetic) + (kinetic_end - kinetic_next) + (potential_end - potential) - smooth
        if servos is not None and problem is not None:
            # λᵀJ(v⁺ + v_free)/2 is T's change under the raised armature; the rest of that change is the step's
            flows[-1] += (kinetic_next - kinetic_free) - work
        return Attempt(q_next, v_next, flows, None, new, evaluations + (problem is not None))

    def _solve(
        self, solver_name: str, problem: Any, guesses: dict[tuple[Any, ...], np.ndarray]
    ) -> tuple[np.ndarray, bool, int]:
        """(impulses, converged, iterations) of the problem, warm-started from the blocks seen last step."""
        m = len(problem.g)
        guess = np.zeros(m)
        start = 0
        for key, size in zip(problem.keys, problem.sizes, strict=True):
            previous = guesses.get(key)
            if previous is not None and len(previous) == size:
                guess[start : start + size] = previous
            start += size
        if solver_name == "pgs":
            solver, settings, result = (
                pin.PGSConstraintSolver(m),
                pgs_settings(self.max_iterations),
                pin.PGSSolverResult(),
            )
        else:
            solver, settings, result = (
                pin.ADMMConstraintSolver(m),
                admm_settings(self.max_iterations),
                pin.ADMMSolverResult(),
            )
        result.setConstraintImpulseGuess(guess)
        converged = bool(solver.solve(problem.delassus, problem.g, problem.models, problem.datas, settings, result))
        impulses = np.array(result.retrieveConstraintImpulses(), dtype=float)
        return impulses, converged, int(result.iterations)


def _split(impulses: np.ndarray, keys: list[tuple[Any, ...]], sizes: list[int]) -> dict[tuple[Any, ...], np.ndarray]:
    out = {}
    start = 0
    for key, size in zip(keys, sizes, strict=True):
        out[key] = impulses[start : start + size].copy()
        start += size
    return out
