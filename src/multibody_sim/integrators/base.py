"""The integrator contract: one attempted step of a method on a system, with its own solver state and status.

An integrator is stateless itself; what one step hands to the next (a first-same-as-last stage, a Newton warm
start, a contact solver's last impulses) is its *solver state*, threaded by the stepping core: ``init`` makes one,
``attempt`` takes one and returns the next, as diffrax's ``init``/``step`` and scipy's ``OdeSolver.step`` do. A step
that fails returns a status; it does not raise.
"""

from __future__ import annotations

import functools
from abc import ABC
from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from ..exceptions import InvalidArgumentError
from ..state import ConfigurationSpace

OK = "ok"  # the status of a step that succeeded


class StepFailure(Exception):
    """A step that could not be completed, raised by the convenience call ``Integrator.step`` (never by the core).

    Attributes:
        status: the run status this failure maps to, e.g. "newton_failed".
    """

    def __init__(self, message: str, *, status: str):
        super().__init__(message)
        self.status = status


class System(Protocol):
    """What an integrator needs from a robot or scene (unchecked, hot-path methods)."""

    nq: int
    nv: int
    space: ConfigurationSpace

    def unchecked_forward_dynamics(self, q: np.ndarray, v: np.ndarray, tau: np.ndarray, t: float = 0.0) -> np.ndarray:
        """Accelerations v' [rad/s², m/s²] at time t [s] (scenes may have time-dependent forces), shape (nv,)."""
        ...

    def unchecked_dynamics_derivatives(
        self, q: np.ndarray, v: np.ndarray, tau: np.ndarray, t: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(da/dq in the tangent space, da/dv, da/dtau), each (nv, nv), at time t: for implicit methods' Newton."""
        ...

    @property
    def ledger_elements(self) -> list[tuple[str, str]]:
        """(name, kind) of each energy-ledger element; kind "work" or "dissipated"."""
        ...

    def ledger_power(
        self, q: np.ndarray, v: np.ndarray, tau: np.ndarray, out: np.ndarray | None = None, t: float = 0.0
    ) -> np.ndarray:
        """Power [W] through each energy-ledger element at time t, shape (n_elements,), written into `out` if given."""
        ...


@dataclass(slots=True)
class Attempt:
    """The result of one attempted step from (q, v) at time t over h with the torque held.

    Attributes:
        q, v: the proposed new state (None when the step failed).
        flows: energy [J] through each ledger element over the step, shape (n_elements,).
        error: scaled error norm (the step is acceptable when ≤ 1), or None for methods without an estimate.
        state: the solver state for the next step, if this one is accepted.
        evaluations: forward-dynamics evaluations this attempt cost (failed attempts included).
        status: OK, or why the step failed ("newton_failed", ...).
        message: what went wrong ("" when status is OK).
        retry_state: the solver state to retry from this step's start after a rejection (None: the state the
            attempt was given).
        detail: method-specific data for dense output (stages, torque, start time).
    """

    q: Any
    v: Any
    flows: Any
    error: float | None
    state: Any
    evaluations: int
    status: str = OK
    message: str = ""
    retry_state: Any = None
    detail: Any = None


def velocity_update(
    system: Any, q: np.ndarray, v: np.ndarray, tau: np.ndarray, h: float, t: float
) -> tuple[Any, int, Any]:
    """Semi-implicit Euler's and the contact time-stepper's velocity update v + h a(q, v, tau), a scene's servos taken
    inside the step (scenes/actuators.py: armature raised, torques held, revised where a servo's limit is reached or
    left within the step).

    Returns:
        (v⁺, the dynamics evaluations it took, the actuators still holding the step or None): the caller ends them
        with end_implicit() before any energy (the time-stepper after its contact problem).
    """
    actuators = getattr(system, "actuators", None)
    servos = actuators if actuators is not None and actuators.begin_implicit(q, v, tau, h) else None
    evaluations = 1
    try:
        v_next = v + h * system.unchecked_forward_dynamics(q, v, tau, t)
        while servos is not None and servos.revise(v_next):
            v_next = v + h * system.unchecked_forward_dynamics(q, v, tau, t)
            evaluations += 1
    except BaseException:
        if servos is not None:
            servos.end_implicit()
        raise
    return v_next, evaluations, servos


def failed(status: str, message: str, evaluations: int, state: Any = None) -> Attempt:
    """An Attempt that did not produce a state."""
    return Attempt(None, None, None, None, state, evaluations, status, message)


class Integrator(ABC):
    """One method of advancing (q, v) by a step, with the torque held constant over the step.

    Subclasses implement ``attempt`` (and ``init`` when they carry solver state, ``dense_output`` when they have
    dense output, ``jacobians`` when ``linearize`` can differentiate their step). A subclass written against the
    first contract, which implements ``step(system, q, v, tau, dt, t)`` only, keeps working: ``attempt`` then
    calls it (fixed-step methods only).

    Attributes:
        name: registry name.
        order: classical order of convergence of the state.
        description: one line for `multibody-sim integrators`.
        evaluations_per_step: forward-dynamics evaluations per step (typical for implicit methods).
        adaptive: chooses its own steps under error control (attempt returns an error norm).
        implicit: solves equations at each step.
        symplectic: preserves the symplectic form for general M(q).
        a_stable: stable on every decaying linear mode at any step.
        has_dense_output: dense_output() interpolates within an accepted step.
        embedded_order: adaptive methods: the order of the embedded solution their error estimate assumes.
        notes: what users should know that the flags do not say.
    """

    name: str
    order: int
    description: str
    evaluations_per_step: int
    adaptive: bool = False
    implicit: bool = False
    symplectic: bool = False
    a_stable: bool = False
    has_dense_output: bool = False
    embedded_order: int = 0
    notes: str = ""
    last_evaluations: int = 0  # dynamics evaluations of the latest step() call (the convenience API)

    def init(self, system: System, q: np.ndarray, v: np.ndarray) -> Any:
        """The solver state for a run (or after a jump: a new torque, a state set by hand) starting at (q, v)."""
        return None

    def restart(self, system: System, q: np.ndarray, v: np.ndarray, state: Any) -> Any:
        """The solver state after a jump (a new torque) at (q, v), given the current one: init()'s by default (an
        FSAL stage taken with the old torque is stale); a contact solver keeps its warm start."""
        return self.init(system, q, v)

    def solver_stats(self, state: Any) -> dict[str, int]:
        """Counts a method keeps in its solver state, for the run's stats ({} for most methods)."""
        return {}

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
        """Attempt one step of h [s] from (q, v) at time t [s] with tau held; never raises for a failed step.

        Args:
            system: the robot or scene.
            q: configuration at the step's start, shape (nq,).
            v: velocity at the step's start, shape (nv,).
            tau: torque held over the step [N·m, N], shape (nv,).
            h: step [s].
            t: the step's start time [s] (time-dependent scene forces are evaluated at the stages' times).
            state: the solver state (from init() or the previous accepted attempt).
            rtol, atol: error tolerances of adaptive methods (the error norm's scale).
        """
        if type(self).step is Integrator.step:
            raise InvalidArgumentError(_CONTRACT.format(name=type(self).__qualname__))
        try:  # the first contract: step() raises StepFailure
            q_next, v_next, flows = self.step(system, q, v, tau, h, t)
        except StepFailure as exc:
            return failed(exc.status, str(exc), self.last_evaluations or self.evaluations_per_step)
        evaluations = self.last_evaluations if self.implicit else self.evaluations_per_step
        return Attempt(q_next, v_next, flows, None, None, evaluations)

    def step(
        self, system: System, q: np.ndarray, v: np.ndarray, tau: np.ndarray, dt: float, t: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """One step from a fresh solver state, for scripts and tests: (q_next, v_next, flows).

        Raises:
            StepFailure: the step failed (its status says why).
        """
        if type(self).attempt is Integrator.attempt:
            raise InvalidArgumentError(_CONTRACT.format(name=type(self).__qualname__))
        result = self.attempt(system, q, v, tau, dt, t, self.init(system, q, v))
        self.last_evaluations = result.evaluations
        if result.status != OK:
            raise StepFailure(result.message, status=result.status)
        return result.q, result.v, result.flows

    def dense_output(
        self, system: System, q: np.ndarray, v: np.ndarray, attempt: Attempt, h: float, theta: float
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q, v, ledger flows since the step's start) at t + θh, 0 ≤ θ ≤ 1, from an accepted attempt."""
        raise NotImplementedError(f"integrator '{self.name}' has no dense output")

    def jacobians(
        self, system: System, q: np.ndarray, v: np.ndarray, tau: np.ndarray, h: float, t: float
    ) -> tuple[np.ndarray, np.ndarray] | None:
        """(A, B): the derivatives of this method's step (see multibody_sim.linearize), or None if not available."""
        return None

    def check_system(self, system: System) -> None:
        """Refuse, before any step, a system this method cannot integrate (raise InvalidArgumentError).

        Implicit methods need the dynamics' analytic derivatives, which a scene with constraints or mimic joints
        does not provide: they refuse it, naming the integrators that accept it.
        """
        if getattr(system, "contact", None) is not None and not getattr(self, "steps_contact", False):
            raise InvalidArgumentError(
                f"integrator '{self.name}' cannot step scene '{getattr(system, 'name', '?')}': it has contact "
                "([ground], [contact] or [[object]]), which only integrator 'timestepping' steps"
            )
        if self.implicit and not getattr(system, "has_derivatives", True):
            able = sorted(name for name, method in REGISTRY.items() if not method.implicit)
            why = getattr(system, "no_derivatives_reason", "")
            raise InvalidArgumentError(
                f"integrator '{self.name}' needs the dynamics' analytic derivatives, which scene "
                f"'{getattr(system, 'name', '?')}' does not provide ({why}); use one of: {', '.join(able)}"
            )

    def check_contract(self) -> None:
        """Refuse an integrator class that implements neither attempt() nor step() (InvalidArgumentError)."""
        cls = type(self)
        if cls.attempt is Integrator.attempt and cls.step is Integrator.step:
            raise InvalidArgumentError(_CONTRACT.format(name=cls.__qualname__))
        if self.adaptive and cls.attempt is Integrator.attempt:
            raise InvalidArgumentError(
                f"integrator {cls.__qualname__} is adaptive, so it must implement attempt(system, q, v, tau, h, t, "
                "state, *, rtol, atol) returning an Attempt with its error norm (step() alone has no error estimate)"
            )

    def __repr__(self) -> str:
        return f"<integrator {self.name}: order {self.order}>"


# Every registered method by name: the registry (integrators/__init__.py, above every method's module) fills it, so
# that a refusal here can name the methods that would run instead.
REGISTRY: dict[str, Integrator] = {}

_CONTRACT = (
    "integrator {name} implements neither attempt(system, q, v, tau, h, t, state) -> Attempt (the contract) nor "
    "step(system, q, v, tau, dt, t) -> (q, v, flows) (the first contract, still accepted for fixed-step methods): "
    "implement one of them"
)


def tangent_selectors(nv: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """[I 0 0], [0 I 0], [0 0 I] (read-only): the derivatives of δq, δv and δtau with respect to y = (δq, δv, δtau),
    the variables a step's Jacobians (``Integrator.jacobians``) are taken against."""
    return _tangent_selectors(nv)


@functools.cache
def _tangent_selectors(nv: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    eye, zero = np.eye(nv), np.zeros((nv, nv))
    blocks = (np.hstack((eye, zero, zero)), np.hstack((zero, eye, zero)), np.hstack((zero, zero, eye)))
    for block in blocks:
        block.setflags(write=False)
    return blocks


def split_jacobian(jacobian: np.ndarray, nv: int) -> tuple[np.ndarray, np.ndarray]:
    """(A, B) from the derivative of the step's (δq, δv) with respect to y = (δq, δv, δtau), shape (2 nv, 3 nv)."""
    return jacobian[:, : 2 * nv].copy(), jacobian[:, 2 * nv :].copy()
