"""Step-size control, separate from the methods it steers: constant steps, or a PI controller on an error estimate.

A controller proposes the next step towards a stop time and judges the attempted step; the stepping core owns
nothing else about time. Both controllers land exactly on the stop time they are given (a control instant, a
sample of a chunk boundary, the end of the run).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, NamedTuple

# A step is landed on the stop time when it comes within this fraction of the step's time scale, max(dt, |t_stop|),
# and an adaptive step below the same fraction has collapsed. The scale needs no duration: it follows the
# resolution of the time values themselves (simulate, Stepper and rollout share this rule).
LANDING_FRACTION = 1e-12
# Fixed steps: a remainder below this fraction of dt is round-off, not a step (1.0 / 0.1 is 10 steps, not 11).
SLIVER = 1e-9


class ConstantStepState(NamedTuple):
    """What a ConstantStep advances: the grid's start t0 [s], the steps k taken on it, the current time [s]."""

    t0: float
    k: int
    time: float


class PIState(NamedTuple):
    """What a PIController advances: the current time [s], the next trial step h [s], the latest accepted error
    norm and whether the latest attempt was rejected."""

    time: float
    h: float
    previous_error: float
    rejected_last: bool


# A NamedTuple's own __new__ is a Python function; tuple.__new__ makes the same object in less than half the time
# (the controllers' snapshot() runs at every Stepper.step).
_new_state = tuple.__new__


class ConstantStep:
    """Steps of dt on the grid t0 + k·dt (k counted, never summed); the step that reaches a stop time off the grid
    is shortened to land on it exactly, and the grid starts again there.

    Attributes:
        dt: the step [s].
        time: the current time [s].
    """

    adaptive = False

    def __init__(self, dt: float, t0: float = 0.0):
        self.dt = dt
        self._t0, self._k = t0, 0
        self.time = t0

    def propose(self, t_stop: float) -> float:
        """The next step's end time towards t_stop (> time)."""
        k_stop = max(self._k + 1, math.ceil((t_stop - self._t0) / self.dt - SLIVER))
        if self._k + 1 < k_stop:
            return self._t0 + (self._k + 1) * self.dt
        return t_stop

    def step_size(self, t_next: float) -> float:
        """The step h that ends at t_next: dt on the grid, the remainder off it."""
        grid = self._t0 + (self._k + 1) * self.dt
        return self.dt if t_next == grid else t_next - self.time

    @property
    def h(self) -> float:
        """The next step [s]."""
        return self.dt

    def scale(self, t_stop: float) -> float:
        """The time scale [s] of the landing rule (as PIController's): max(dt, |t_stop|)."""
        return max(self.dt, abs(t_stop))

    def judge(self, h: float, error: float | None) -> bool:
        """Every step is accepted."""
        return True

    def commit(self, t_next: float) -> None:
        """The step to t_next was accepted."""
        if t_next == self._t0 + (self._k + 1) * self.dt:
            self._k += 1
        else:  # landed off the grid: a new grid starts there
            self._t0, self._k = t_next, 0
        self.time = t_next

    def reached(self, t_stop: float) -> bool:
        return self.time >= t_stop

    def restart(self, t: float) -> None:
        """Continue from time t (set by hand), on a grid starting there."""
        self._t0, self._k, self.time = t, 0, t

    def snapshot(self) -> ConstantStepState:
        """The controller's state (restore() returns to it; the native kernel advances it as data)."""
        return _new_state(ConstantStepState, (self._t0, self._k, self.time))

    def restore(self, state: ConstantStepState) -> None:
        self._t0, self._k, self.time = state

    def write_native_state(self, loop: Any) -> None:
        """Put the state in the native kernel's loop state (_native.LoopState's step_t0, step_k, step_time): what
        snapshot() holds, without making one (the engine is entered once per Stepper.step)."""
        loop.step_t0, loop.step_k, loop.step_time = self._t0, self._k, self.time

    def read_native_state(self, loop: Any) -> None:
        """Take the state back from the loop state the engine advanced."""
        self._t0, self._k, self.time = loop.step_t0, loop.step_k, loop.step_time

    def native_data(self) -> dict[str, Any]:
        """The constants as the native kernel takes them (_native.ConstantStep's fields)."""
        return {"dt": self.dt, "sliver": SLIVER, "landing": LANDING_FRACTION}


@dataclass
class PIController:
    """Proportional–integral step-size control on a scaled error norm (accept when norm ≤ 1).

    ``h_new = h · clip(safety · err^(-alpha) · err_prev^(beta), factor_min, factor_max)`` with
    alpha = 0.7/k and beta = 0.4/k, k = embedded order + 1 (Gustafsson's PI controller; the integral part
    damps the step-size oscillation a plain controller shows where stability, not accuracy, limits the step).
    After a rejection the step may not grow.

    Attributes:
        error_order: order of the embedded (error-estimating) solution.
        max_step: largest step [s].
        min_step: below this the step has collapsed [s] (next_step's rule; the stepping core uses
            LANDING_FRACTION of the time scale instead).
        first_step: the first trial step [s] (also the time scale's floor).
        time: the current time [s].
        h: the next trial step [s].
    """

    error_order: int
    max_step: float = math.inf
    min_step: float = 0.0
    safety: float = 0.9
    factor_min: float = 0.2
    factor_max: float = 5.0
    first_step: float = math.nan
    time: float = 0.0
    _previous_error: float = field(default=1.0, init=False)  # neutral: the first step is a plain P step
    _rejected_last: bool = field(default=False, init=False)

    adaptive = True

    def __post_init__(self) -> None:
        k = self.error_order + 1
        self.alpha = 0.7 / k
        self.beta = 0.4 / k
        self.h = min(self.first_step, self.max_step) if math.isfinite(self.first_step) else self.max_step

    def next_step(self, h: float, error: float) -> tuple[bool, float]:
        """(accepted?, next step [s]) after a step of h with scaled error norm `error` (inf when non-finite)."""
        if not math.isfinite(error):
            self._rejected_last = True
            return False, h * self.factor_min
        if error <= 1.0:
            error = max(error, 1e-10)  # a zero error would ask for an infinite step
            factor = self.safety * error**-self.alpha * self._previous_error**self.beta
            factor = min(self.factor_max if not self._rejected_last else 1.0, max(self.factor_min, factor))
            self._previous_error = error
            self._rejected_last = False
            return True, min(h * factor, self.max_step)
        factor = max(self.factor_min, self.safety * error**-self.alpha)
        self._rejected_last = True
        return False, h * factor

    # ---- the stepping core's interface (as ConstantStep's) -------------------------------------------------------
    def scale(self, t_stop: float) -> float:
        """The time scale [s] of the landing and collapse rules: max(first step, |t_stop|)."""
        return max(self.first_step, abs(t_stop))

    def propose(self, t_stop: float) -> float:
        """The next trial step's end time: time + h, or t_stop when that is within reach (landing)."""
        if self.time + self.h >= t_stop - LANDING_FRACTION * self.scale(t_stop):
            return t_stop
        return self.time + self.h

    def step_size(self, t_next: float) -> float:
        return t_next - self.time

    def judge(self, h: float, error: float | None) -> bool:
        """Accept or reject the attempted step of h with this error norm; sets the next trial step."""
        accepted, self.h = self.next_step(h, math.inf if error is None else error)
        return accepted

    def commit(self, t_next: float) -> None:
        self.time = t_next

    def reached(self, t_stop: float) -> bool:
        return self.time >= t_stop

    def restart(self, t: float) -> None:
        self.time = t

    def snapshot(self) -> PIState:
        """The controller's state (restore() returns to it; the native kernel advances it as data)."""
        return _new_state(PIState, (self.time, self.h, self._previous_error, self._rejected_last))

    def restore(self, state: PIState) -> None:
        self.time, self.h, self._previous_error, self._rejected_last = state

    def write_native_state(self, loop: Any) -> None:
        """Put the state in the native kernel's loop state (_native.LoopState's step_time, step_h, previous_error,
        rejected_last): what snapshot() holds, without making one."""
        loop.step_time, loop.step_h = self.time, self.h
        loop.previous_error, loop.rejected_last = self._previous_error, self._rejected_last

    def read_native_state(self, loop: Any) -> None:
        """Take the state back from the loop state the engine advanced."""
        self.time, self.h = loop.step_time, loop.step_h
        self._previous_error, self._rejected_last = loop.previous_error, loop.rejected_last

    def native_data(self) -> dict[str, Any]:
        """The constants as the native kernel takes them (_native.PIController's fields)."""
        return {
            "alpha": self.alpha,
            "beta": self.beta,
            "safety": self.safety,
            "factor_min": self.factor_min,
            "factor_max": self.factor_max,
            "max_step": self.max_step,
            "first_step": self.first_step,
            "landing": LANDING_FRACTION,
        }
