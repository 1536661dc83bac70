"""Checks of arguments at the public boundary: numbers and their ranges, periods, and the options an integrator takes.

The one place where numbers from users and files are range-checked (simulate, rollout, the Stepper, the viewer
and the command line call these): NaN, infinities, values that underflow to zero, overflow a count or leave
their range get one InvalidArgumentError naming the argument and its valid range, never a raw OverflowError
from deeper down and never a silently changed value.
"""

from __future__ import annotations

import math
import sys
from typing import Any

import numpy as np

from .exceptions import InvalidArgumentError
from .integrators import INTEGRATORS, Integrator

FIXED_STEP_OPTIONS = ("control_dt", "output_dt")
ADAPTIVE_OPTIONS = ("atol", "control_dt", "max_step", "output_dt", "rtol")

# Times are t0 + k·dt with k counted: float64 holds every whole number up to 2**53 exactly, and no run is longer.
MAX_STEPS = 2**53
# A relative tolerance below machine epsilon cannot be met in double precision; at 1 or more any step passes.
RTOL_RANGE = (sys.float_info.epsilon, 1.0)
FPS_RANGE = (1.0, 1000.0)  # frames per second of a playback or an export's animation
SPEED_RANGE = (1e-3, 1e3)  # playback speed (1 = real time): 1000x slower or faster at most
PORT_RANGE = (0, 65535)  # TCP ports; 0 lets the system choose


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
    check_ratio(period, dt, name, "dt")
    k = round(period / dt)
    if k < 1 or abs(k * dt - period) > 1e-9 * period:
        raise InvalidArgumentError(f"{name} must be a whole multiple of dt = {dt:g} s, got {period:g} s")
    return k


def check_callable(value: Any, name: str, signature: str) -> None:
    """InvalidArgumentError unless value is None or callable."""
    if value is not None and not callable(value):
        raise InvalidArgumentError(f"{name} must be callable as {signature}, got {type(value).__name__}")


def in_range(value: Any, name: str, low: float, high: float, unit: str = "", *, high_open: bool = False) -> float:
    """value as a float if it is a number in [low, high] ([low, high) with high_open), else InvalidArgumentError."""
    inside = (
        is_number(value) and math.isfinite(value) and low <= value and (value < high if high_open else value <= high)
    )
    if not inside:
        upper = f"to {high:g} ({high:g} excluded)" if high_open else f"to {high:g}"
        shown = f"{value:g}" if is_number(value) else repr(value)
        raise InvalidArgumentError(
            f"{name} must be a number from {low:g} {upper}{f' {unit}' if unit else ''}, got {shown}"
        )
    return float(value)


def whole_number(value: Any, name: str, low: int, high: int, unit: str = "") -> int:
    """value as an int if it is a whole number (not a float, string or bool) in [low, high], else
    InvalidArgumentError."""
    if not (isinstance(value, (int, np.integer)) and not isinstance(value, (bool, np.bool_)) and low <= value <= high):
        shown = repr(value) if not isinstance(value, (int, np.integer)) else str(value)
        raise InvalidArgumentError(
            f"{name} must be a whole number from {low} to {high}{f' {unit}' if unit else ''}, got {shown}"
        )
    return int(value)


def positive_count(value: Any, name: str, unit: str | None = None) -> int:
    """value as an int if it is a whole number (not a float, string or bool) from 1 to MAX_STEPS, else
    InvalidArgumentError (a count larger than 2**53 is no count a run can reach: numpy would refuse or wrap it)."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < 1:
        what = f"a positive whole number of {unit}" if unit else "a positive whole number"
        raise InvalidArgumentError(f"{name} must be {what}, got {value!r}")
    if value > MAX_STEPS:
        raise InvalidArgumentError(f"{name} must be at most 2**53 = {MAX_STEPS}, got {value}")
    return int(value)


def check_ratio(span: float, period: float, span_name: str, period_name: str) -> None:
    """span / period (a count of steps or samples) must stay within MAX_STEPS: no overflow, exact times."""
    ratio = span / period
    if not ratio <= MAX_STEPS:  # also inf and nan
        raise InvalidArgumentError(
            f"{span_name} / {period_name} = {span:g} s / {period:g} s = {ratio:.3g} is more than 2**53, the most a "
            f"run can count exactly: choose a larger {period_name} or a smaller {span_name}"
        )


def step_count(duration: float, dt: float, sliver: float) -> int:
    """Fixed steps of dt in `duration` (both checked positive), the last one shortened; a remainder under
    sliver·dt is round-off, not a step."""
    check_ratio(duration, dt, "duration", "dt")
    return max(1, math.ceil(duration / dt - sliver))


def relative_tolerance(value: Any, name: str = "rtol") -> float:
    """An adaptive method's rtol: from machine epsilon up to (not including) 1."""
    positive_number(value, name, "units")
    return in_range(value, name, RTOL_RANGE[0], RTOL_RANGE[1], high_open=True)


def run_numbers(adaptive: bool, duration: float, dt: float, options: dict[str, Any]) -> dict[str, Any]:
    """The numbers of a run (simulate, rollout, the command line), checked: returns duration, dt and the options
    given as floats, plus for fixed-step methods output_every and control_every (steps per sample and per
    control instant).
    """
    duration = positive_number(duration, "duration")
    dt = positive_number(dt, "dt")
    checked: dict[str, Any] = {"duration": duration, "dt": dt}
    if adaptive:
        check_ratio(duration, dt, "duration", "dt")
        if options.get("rtol") is not None:
            checked["rtol"] = relative_tolerance(options["rtol"])
        if options.get("atol") is not None:
            checked["atol"] = positive_number(options["atol"], "atol", "units")
        for name in ("max_step", "output_dt", "control_dt"):
            if options.get(name) is not None:
                checked[name] = positive_number(options[name], name)
                check_ratio(duration, checked[name], "duration", name)
        return checked
    checked["n_steps"] = step_count(duration, dt, 1e-9)
    checked["output_every"] = steps_per(options.get("output_dt"), dt, "output_dt")
    checked["control_every"] = steps_per(options.get("control_dt"), dt, "control_dt")
    return checked


def frame_rate(value: Any, name: str = "fps") -> float:
    """Frames per second of a playback or an animation: FPS_RANGE."""
    return in_range(value, name, *FPS_RANGE, "frames per second")


def playback_speed(value: Any, name: str = "speed") -> float:
    """A playback speed (1 = real time): SPEED_RANGE."""
    return in_range(value, name, *SPEED_RANGE, "(1 = real time)")


def port_number(value: Any, name: str = "port") -> int | None:
    """A TCP port to listen on (None: the caller's default; 0: any free port); a port above 65535 never wraps."""
    if value is None:
        return None
    return whole_number(value, name, *PORT_RANGE, "(0: any free port)")


def sample_times(t: np.ndarray, name: str = "t") -> None:
    """Sample times must be finite and strictly increasing (one row per distinct time)."""
    bad = np.flatnonzero(~np.isfinite(t))
    if bad.size:
        raise InvalidArgumentError(f"{name} must hold finite times, got {float(t[bad[0]])!r} at index {bad[0]}")
    back = np.flatnonzero(np.diff(t) <= 0)
    if back.size:
        i = int(back[0])
        raise InvalidArgumentError(
            f"{name} must be strictly increasing, got {float(t[i])!r} then {float(t[i + 1])!r} at indices {i} and "
            f"{i + 1}"
        )


# ---- types at the public boundary: one wrong-typed argument is one InvalidArgumentError naming it ------------
def check_path(value: Any, name: str, what: str = "a file") -> Any:
    """value if it is a path (str or os.PathLike), else InvalidArgumentError."""
    import os

    if not isinstance(value, (str, os.PathLike)) or (isinstance(value, str) and not value):
        raise InvalidArgumentError(f"{name} must be a path to {what}, got {type(value).__name__}")
    return value


def check_flag(value: Any, name: str, *, optional: bool = False) -> bool | None:
    """value as a bool if it is True or False (None too when optional), else InvalidArgumentError (a string such as
    "no" would be true)."""
    if value is None and optional:
        return None
    if not isinstance(value, (bool, np.bool_)):
        raise InvalidArgumentError(f"{name} must be True or False{' or None' if optional else ''}, got {value!r}")
    return bool(value)


def check_text(value: Any, name: str, *, optional: bool = True) -> str | None:
    """value if it is a string (or None when optional), else InvalidArgumentError."""
    if value is None and optional:
        return None
    if not isinstance(value, str):
        raise InvalidArgumentError(
            f"{name} must be a string{' or None' if optional else ''}, got {type(value).__name__}"
        )
    return value
