"""The integrator contract: one step of a method on a system, plus the flags users choose by."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Protocol

import numpy as np

from ..exceptions import InvalidArgumentError
from ..state import ConfigurationSpace


class StepFailure(Exception):
    """An integrator could not complete a step (e.g. Newton did not converge); never a silently wrong state.

    The stepping loop ends the run with ``status`` (fixed-step) or retries a shorter step (adaptive).

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


class Integrator(ABC):
    """One method of advancing (q, v) by a step, with the torque held constant over the step.

    Attributes:
        name: registry name.
        order: classical order of convergence of the state.
        description: one line for `multibody-sim integrators`.
        evaluations_per_step: forward-dynamics evaluations per step (fixed-step methods).
        adaptive: chooses its own steps under error control.
        implicit: solves equations at each step.
        symplectic: preserves the symplectic form for general M(q).
        a_stable: stable on every decaying linear mode at any step.
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
    notes: str = ""
    last_evaluations: int = 0  # implicit methods: dynamics evaluations of the latest step (Newton varies)

    @abstractmethod
    def step(
        self, system: System, q: np.ndarray, v: np.ndarray, tau: np.ndarray, dt: float, t: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Advance one step.

        Args:
            system: the robot or scene.
            q: configuration at the step's start, shape (nq,).
            v: velocity at the step's start, shape (nv,).
            tau: torque held over the step [N·m, N], shape (nv,).
            dt: step [s].
            t: the step's start time [s] (time-dependent scene forces are evaluated at the stages' times).

        Returns:
            (q_next, v_next, flows): the new state and the energy [J] that went through each ledger element
            over the step, integrated with the method's own quadrature.
        """

    def check_system(self, system: System) -> None:
        """Refuse, before any step, a system this method cannot integrate (raise InvalidArgumentError).

        Implicit methods need the dynamics' analytic derivatives, which a scene with constraints or mimic joints
        does not provide: they refuse it, naming the integrators that accept it.
        """
        if self.implicit and not getattr(system, "has_derivatives", True):
            from . import INTEGRATORS  # the registry imports this module

            able = sorted(name for name, method in INTEGRATORS.items() if not method.implicit)
            why = getattr(system, "no_derivatives_reason", "")
            raise InvalidArgumentError(
                f"integrator '{self.name}' needs the dynamics' analytic derivatives, which scene "
                f"'{getattr(system, 'name', '?')}' does not provide ({why}); use one of: {', '.join(able)}"
            )

    def __repr__(self) -> str:
        return f"<integrator {self.name}: order {self.order}>"
