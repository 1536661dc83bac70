"""Velocity-level time-stepping for contact (Moreau–Jean, semi-implicit), with an exact Coulomb cone solver.

One step from (q, v) over h with tau held:

    v_free = v + h a(q, v, tau)                       (every smooth force: gravity, torques, elements)
    λ      = Coulomb's law on u = G λ + g             (G = J M⁻¹ Jᵀ, g = J v_free + b: scenes/contact.py)
    v⁺     = v_free + M⁻¹ Jᵀ λ,      q⁺ = q ⊕ h v⁺

λ are impulses [N·s]: the contact problem is solved at the velocity level, so impacts, stiction and sliding are
exact within one step (no stiffness, no regularization), at first order in h. The solver (cone_solver.py) is an
semismooth Newton method with an ADMM fallback (cone_solver.py), warm-started from the impulses of the previous
step at the same contact (the solver state: by the contact's pair and feature), so a resting contact costs one
linear solve.

Energy ledger (each term from its own formula; energy_error then checks that they close):

- smooth elements (torques, damping, forces): h · power(q, v⁺) (the end-point rule);
- ``contact`` (dissipated): what the impulses take out, ``D = -λᵀ(b_corr + b_rest) - W`` with
  ``W = ½ λᵀ J (v⁺ + v_free) = T(q, v⁺) - T(q, v_free)``; complementarity makes D ≥ 0 on every step
  (``D = -λᵀ(u⁺ + b) + λᵀ b_spec + ½ λᵀ G λ``, each term ≥ 0);
- ``penetration_correction`` (work): ``-λᵀ b_corr ≥ 0``, what pushing penetrations out puts back;
- ``restitution`` (work): ``-λᵀ b_rest ≥ 0``, what a bounce gives back;
- a velocity-limit row's work ``w = ½ λ J (v⁺ + v_free)`` (scenes/contact.py) is booked as dissipated (``-w``) in
  its actuator's ``actuator_overspeed:<joint>`` line and comes out of ``contact``'s W;
- ``timestep_error`` (work): the semi-implicit step's own O(h²) energy error per step,
  ``[T(q, v_free) - T(q, v)] + [T(q⁺, v⁺) - T(q, v⁺)] + [V(q⁺) - V(q)] - Σ smooth flows`` (in free fall
  -½ m g² h² per step, at rest +½ m g² h², which the contact takes out again).

A step whose solver stops at its iteration cap continues with the best impulses found and is counted in the solver
state (``stats``: ``solver_unconverged``); the driver ends a run where that happened on more than 1 % of the steps
with status "solver_failed". An exception raised inside the step by a library it calls (coal, Pinocchio, NumPy)
ends the row's run with status "failed" and the library's message, as any failed step does.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from . import cone_solver
from .base import Attempt, Integrator, System, failed, velocity_update
from .cone_solver import Solution, matvec, solve, zsum
from .partitioned import SemiImplicitEuler

MAX_ITERATIONS = 1000
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
        fallbacks: of the steps, those that needed the solver's fallback (cone_solver.py).
    """

    impulses: dict[tuple[Any, ...], np.ndarray] = field(default_factory=dict)
    steps: int = 0
    unconverged: int = 0
    iterations: int = 0
    landed: dict[int, float] = field(default_factory=dict)
    active: tuple[Any, np.ndarray] | None = None
    fallbacks: int = 0


# The counts a contact run's stats gain (Trajectory.stats, BatchTrajectory.stats, Stepper.stats).
SOLVER_COUNTS = ("solver_steps", "solver_unconverged", "solver_iterations", "solver_fallbacks")


def solver_counts(state: Any) -> dict[str, int]:
    """The SOLVER_COUNTS of a solver state with steps, unconverged, iterations and fallbacks (ContactState, or the
    native kernel's row state)."""
    return dict(
        zip(SOLVER_COUNTS, (state.steps, state.unconverged, state.iterations, state.fallbacks), strict=True)
    )


class TimeStepping(Integrator):
    """Moreau–Jean velocity-level time-stepping with an exact Coulomb cone solver (module docstring)."""

    name = "timestepping"
    order = 1
    description = "velocity-level contact time-stepping (Moreau–Jean), exact Coulomb cone solver"
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

    def solver_data(self) -> dict[str, Any]:
        """The solver's settings as the native kernel takes them (_native.ContactConstants' max_iterations and
        solver, a _native.SolverSettings): this time-stepper's max_iterations and cone_solver.py's constants."""
        return {
            "max_iterations": self.max_iterations,
            "solver": {
                "tolerance": cone_solver.TOLERANCE,
                "fallback_tolerance": cone_solver.FALLBACK_TOLERANCE,
                "regularization": cone_solver.REGULARIZATION,
                "damping": cone_solver.DAMPING,
                "armijo": cone_solver.ARMIJO,
                "shortest_step": cone_solver.SHORTEST_STEP,
                "proximal": cone_solver.PROXIMAL,
                "relaxation": cone_solver.RELAXATION,
                "rho_power": cone_solver.RHO_POWER,
                "rho_step": cone_solver.RHO_STEP,
                "rho_balance": cone_solver.RHO_BALANCE,
                "rho_min": cone_solver.RHO_MIN,
                "rho_max": cone_solver.RHO_MAX,
                "newton_iterations": cone_solver.NEWTON_ITERATIONS,
                "fallback_rounds": cone_solver.FALLBACK_ROUNDS,
                "local_iterations": cone_solver.LOCAL_ITERATIONS,
            },
        }

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
            new = ContactState(
                state.impulses, state.steps, state.unconverged, state.iterations, fallbacks=state.fallbacks
            )
            try:  # a library's exception (coal, Pinocchio, NumPy) fails this row's step, as any failed step does
                problem = contact.problem(q, v, v_free, h, state.landed)
                solution = self._solve(contact.solver, problem, state) if problem is not None else None
            except Exception as exc:  # noqa: BLE001 - any library's error is the row's status and message
                return failed("failed", f"{type(exc).__name__} raised in the contact step: {exc}", evaluations, state)
            speed_work: list[tuple[int, float]] = []  # (ledger line, w) of each velocity-limit row
            # what the servos added to the armature the problem's M has (taken off its kinetic energies below)
            raised = servos.raised_armature() if servos is not None else None
            if problem is None or solution is None:
                v_next, impulses, work, correction, bounce = v_free, np.zeros(0), 0.0, 0.0, 0.0
                new.impulses = {}
            else:
                iterations = solution.iterations
                while True:  # velocity limits the impulses carried joints past: their rows added, solved again
                    # sums in index order from +0.0 (cone_solver.zsum), as the native kernel
                    # (src/native/contact.cpp) forms them
                    generalized = matvec(problem.jacobian.T, solution.impulses)
                    v_next = v_free + contact.inverse_mass_times(generalized)
                    added = contact.speeding(v_next, problem)
                    if not added:
                        break
                    try:
                        problem = contact.problem(q, v, v_free, h, state.landed, problem, added)
                        guess = np.concatenate([solution.impulses, np.zeros(len(added))])
                        solution = self._solve(contact.solver, problem, state, guess)
                    except Exception as exc:  # noqa: BLE001 - as above
                        message = f"{type(exc).__name__} raised in the contact step: {exc}"
                        return failed("failed", message, evaluations, state)
                    iterations += solution.iterations
                impulses = solution.impulses
                new.steps += 1
                new.iterations += iterations
                new.unconverged += not solution.converged
                new.fallbacks += solution.fallback
                new.impulses = _split(impulses, problem.keys, problem.sizes)
                row = len(impulses) - len(problem.speeds)
                for sign, iv, _, _, line, _ in problem.speeds:
                    speed_work.append((line, 0.5 * ((sign * impulses[row]) * (v_next[iv] + v_free[iv]))))
                    row += 1
                work = 0.5 * float(zsum(generalized * (v_next + v_free)))  # ½ λᵀ J (v⁺ + v_free)
                correction = -float(zsum(impulses * problem.correction))
                bounce = -float(zsum(impulses * problem.restitution))
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
        held = 0.0  # the velocity-limit rows' work, out of the contact's into their actuators' lines
        for line, w in speed_work:
            flows[line] -= w
            held += w
        kinetic, potential = scene.unchecked_energies(q, v)
        if problem is not None:
            # T at q from the problem's M there (½ vᵀ (M − diag(raised)) v under servos): the native kernel's
            # kinematic passes saved
            kinetic, kinetic_free, kinetic_next = (contact.kinetic_energy(x, raised) for x in (v, v_free, v_next))
        else:
            kinetic_free = scene.unchecked_energies(q, v_free)[0]
            kinetic_next = kinetic_free  # (no problem: v⁺ = v_free)
        kinetic_end, potential_end = scene.unchecked_energies(q_next, v_next)
        flows[-4] = correction + bounce - (work - held)
        flows[-3] = correction
        flows[-2] = bounce
        flows[-1] = (kinetic_free - kinetic) + (kinetic_end - kinetic_next) + (potential_end - potential) - smooth
        if servos is not None and problem is not None:
            # λᵀJ(v⁺ + v_free)/2 is T's change under the raised armature; the rest of that change is the step's
            flows[-1] += (kinetic_next - kinetic_free) - work
        return Attempt(q_next, v_next, flows, None, new, evaluations + (problem is not None))

    def _solve(self, solver_name: str, problem: Any, state: ContactState, guess: np.ndarray | None = None) -> Solution:
        """The problem's impulses (cone_solver.solve), warm-started from `guess` or the blocks seen last step."""
        if guess is None:
            guess = np.zeros(len(problem.g))
            start = 0
            for key, size in zip(problem.keys, problem.sizes, strict=True):
                previous = state.impulses.get(key)
                if previous is not None and len(previous) == size:
                    guess[start : start + size] = previous
                start += size
        return solve(
            problem.delassus,
            problem.g,
            problem.blocks,
            guess,
            problem.velocity_scale,
            self.max_iterations,
            pgs=solver_name == "pgs",
        )


def _split(impulses: np.ndarray, keys: list[tuple[Any, ...]], sizes: list[int]) -> dict[tuple[Any, ...], np.ndarray]:
    out = {}
    start = 0
    for key, size in zip(keys, sizes, strict=True):
        out[key] = impulses[start : start + size].copy()
        start += size
    return out
