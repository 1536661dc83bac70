"""The registry of integrators: every method by name, and the lookup that lists valid names on a miss."""

from __future__ import annotations

import difflib

from ..exceptions import InvalidArgumentError, UnknownIntegratorError
from .base import OK, REGISTRY, Attempt, Integrator, StepFailure, System
from .explicit_rk import DormandPrince853, EmbeddedRungeKutta, ExplicitRungeKutta
from .implicit import ImplicitEuler, ImplicitMidpoint
from .partitioned import SemiImplicitEuler
from .tableau import BOGACKI_SHAMPINE_32, DORMAND_PRINCE_54, EULER, MIDPOINT, RK4, ButcherTableau, EmbeddedTableau
from .timestepping import TimeStepping
from .variational import VariationalIntegrator

# The registry is base.REGISTRY itself: base's refusals list its methods without importing this module.
INTEGRATORS: dict[str, Integrator] = REGISTRY
INTEGRATORS.update(
    (method.name, method)
    for method in [
        ExplicitRungeKutta("euler", EULER, "explicit (forward) Euler", notes="gains energy on oscillators"),
        SemiImplicitEuler(),
        ExplicitRungeKutta("midpoint", MIDPOINT, "explicit midpoint (RK2)"),
        ExplicitRungeKutta("rk4", RK4, "classical Runge–Kutta"),
        EmbeddedRungeKutta("bs32", BOGACKI_SHAMPINE_32, "Bogacki–Shampine 3(2), adaptive, cubic Hermite dense output"),
        EmbeddedRungeKutta("dp54", DORMAND_PRINCE_54, "Dormand–Prince 5(4), adaptive, 4th-order dense output"),
        DormandPrince853(),
        ImplicitEuler(),
        ImplicitMidpoint(),
        VariationalIntegrator(),
        TimeStepping(),
    ]
)


def get_integrator(integrator: str | Integrator) -> Integrator:
    """The integrator named `integrator` (or the object itself).

    Raises:
        UnknownIntegratorError: not a registry name; the message lists the valid ones.
    """
    if isinstance(integrator, Integrator):
        return integrator
    if not isinstance(integrator, str):
        raise InvalidArgumentError(f"integrator must be a name or an Integrator, got {type(integrator).__name__}")
    if integrator in INTEGRATORS:
        return INTEGRATORS[integrator]
    close = difflib.get_close_matches(integrator, INTEGRATORS, n=1, cutoff=0.6)
    hint = f"did you mean {close[0]}? " if close else ""
    raise UnknownIntegratorError(f"unknown integrator '{integrator}' ({hint}valid: {', '.join(sorted(INTEGRATORS))})")


__all__ = [
    "INTEGRATORS",
    "OK",
    "Attempt",
    "ButcherTableau",
    "EmbeddedRungeKutta",
    "EmbeddedTableau",
    "ExplicitRungeKutta",
    "Integrator",
    "SemiImplicitEuler",
    "StepFailure",
    "System",
    "get_integrator",
]
