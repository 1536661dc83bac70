"""Butcher tableaux: the coefficients of explicit Runge–Kutta methods (data only, validated on creation)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class ButcherTableau:
    """Coefficients of an explicit Runge–Kutta method.

    Attributes:
        a: stage coefficients, strictly lower-triangular, shape (s, s).
        b: weights of the solution, shape (s,).
        c: stage times as fractions of the step, shape (s,).
        order: classical order of the solution.
    """

    a: tuple[tuple[float, ...], ...]
    b: tuple[float, ...]
    c: tuple[float, ...]
    order: int

    def __post_init__(self) -> None:
        a, b, c = np.array(self.a, dtype=float), np.array(self.b, dtype=float), np.array(self.c, dtype=float)
        s = len(b)
        if a.shape != (s, s) or c.shape != (s,):
            raise ValueError(f"tableau shapes disagree: a {a.shape}, b ({s},), c {c.shape}")
        if np.any(np.triu(a) != 0.0):
            raise ValueError("an explicit tableau's a must be strictly lower-triangular")
        if abs(b.sum() - 1.0) > 1e-12:
            raise ValueError(f"tableau weights b must sum to 1, got {b.sum()!r}")
        if np.max(np.abs(a.sum(axis=1) - c)) > 1e-12:
            raise ValueError("tableau rows of a must sum to c")
        if self.order < 1:
            raise ValueError(f"tableau order must be >= 1, got {self.order}")

    @property
    def stages(self) -> int:
        return len(self.b)


EULER = ButcherTableau(a=((0.0,),), b=(1.0,), c=(0.0,), order=1)

MIDPOINT = ButcherTableau(a=((0.0, 0.0), (0.5, 0.0)), b=(0.0, 1.0), c=(0.0, 0.5), order=2)

RK4 = ButcherTableau(
    a=((0.0, 0.0, 0.0, 0.0), (0.5, 0.0, 0.0, 0.0), (0.0, 0.5, 0.0, 0.0), (0.0, 0.0, 1.0, 0.0)),
    b=(1 / 6, 1 / 3, 1 / 3, 1 / 6),
    c=(0.0, 0.5, 0.5, 1.0),
    order=4,
)
