"""Step-size control for adaptive methods: the PI controller, separate from the methods it steers."""

from __future__ import annotations

import math
from dataclasses import dataclass, field


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
        min_step: below this the step has collapsed [s].
    """

    error_order: int
    max_step: float = math.inf
    min_step: float = 0.0
    safety: float = 0.9
    factor_min: float = 0.2
    factor_max: float = 5.0
    _previous_error: float = field(default=1.0, init=False)  # neutral: the first step is a plain P step
    _rejected_last: bool = field(default=False, init=False)

    def __post_init__(self) -> None:
        k = self.error_order + 1
        self.alpha = 0.7 / k
        self.beta = 0.4 / k

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
