"""Checks of a run's arguments at the public boundary: numbers, periods and the options an integrator takes."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .exceptions import InvalidArgumentError
from .integrators import INTEGRATORS, Integrator

FIXED_STEP_OPTIONS = ("control_dt", "output_dt")
ADAPTIVE_OPTIONS = ("atol", "control_dt", "max_step", "output_dt", "rtol")


def check_options(
    method: Integrator,
    options: dict[str, Any],
    fixed_step: tuple[str, ...] = FIXED_STEP_OPTIONS,
    adaptive_only: tuple[str, ...] = ADAPTIVE_OPTIONS,
) -> None:
    """Refuse options the method does not take (simulate's by default; the Stepper passes its own sets)."""
    valid = adaptive_only if method.adaptive else fixed_step
    for name in options:
        if name in valid:
            continue
        if name in adaptive_only:
            adaptive = sorted(n for n, m in INTEGRATORS.items() if m.adaptive)
            where = f" (it applies to the adaptive integrators: {', '.join(adaptive)})" if adaptive else ""
            raise InvalidArgumentError(
                f"option '{name}' does not apply to the fixed-step integrator '{method.name}'{where}"
            )
        raise InvalidArgumentError(f"unknown option '{name}' (valid for '{method.name}': {', '.join(valid) or 'none'})")
    if method.adaptive:
        missing = [name for name in ("rtol", "atol") if options.get(name) is None]
        if missing:
            raise InvalidArgumentError(
                f"integrator '{method.name}' is adaptive: pass {' and '.join(missing)} (error tolerances; "
                "e.g. rtol=1e-6, atol=1e-8)"
            )


def is_number(value: Any) -> bool:
    """Numbers only: float() would also take "0.5" and True (1 s), which hide mistakes at the public boundary."""
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def positive_number(value: Any, name: str, unit: str | None = "seconds") -> float:
    """value as a float if it is a positive finite number (not a string or bool), else InvalidArgumentError."""
    if not is_number(value) or not (math.isfinite(value) and value > 0):
        what = f"a positive number of {unit}" if unit else "a positive number"
        raise InvalidArgumentError(f"{name} must be {what}, got {value!r}")
    return float(value)


def finite_number(value: Any, name: str) -> float:
    """value as a float if it is a finite number of seconds (a time; not a string or bool), else
    InvalidArgumentError."""
    if not is_number(value) or not math.isfinite(value):
        raise InvalidArgumentError(f"{name} must be a finite number of seconds, got {value!r}")
    return float(value)


def steps_per(period: Any, dt: float, name: str) -> int:
    """How many steps of dt make `period` (None: 1), which must be a whole multiple of dt."""
    if period is None:
        return 1
    period = positive_number(period, name)
    k = round(period / dt)
    if k < 1 or abs(k * dt - period) > 1e-9 * period:
        raise InvalidArgumentError(f"{name} must be a whole multiple of dt = {dt:g} s, got {period:g} s")
    return k


def check_callable(value: Any, name: str, signature: str) -> None:
    """InvalidArgumentError unless value is None or callable."""
    if value is not None and not callable(value):
        raise InvalidArgumentError(f"{name} must be callable as {signature}, got {type(value).__name__}")
