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
            raise ValueError(f"tableau weights b must sum to 1, got {float(b.sum())!r}")
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


@dataclass(frozen=True)
class EmbeddedTableau(ButcherTableau):
    """An explicit tableau with a second, lower-order solution for error estimation, and its dense output.

    Attributes:
        b_hat: weights of the embedded solution, shape (s,); the error estimate is h Σ (b - b_hat)_i k_i.
        embedded_order: order of the embedded solution.
        fsal: the last stage is evaluated at the new state ("first same as last"): a step that keeps the torque
            can reuse it as its first stage.
        dense: weights d, shape (s,), of the quartic term of the continuous extension
            y(θ) = y0 + hθ(r1 + (1-θ)(r2 + θ(r3 + (1-θ) r4))), with r1 = Σ b_i k_i, r2 = k_1 - r1,
            r3 = 2 r1 - k_1 - k_s, r4 = Σ d_i k_i. All-zero d gives cubic Hermite interpolation
            (third order); Dormand–Prince's d gives its fourth-order interpolant. Needs fsal.
    """

    b_hat: tuple[float, ...] = ()
    embedded_order: int = 0
    fsal: bool = False
    dense: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        super().__post_init__()
        s = self.stages
        if len(self.b_hat) != s or abs(sum(self.b_hat) - 1.0) > 1e-12:
            raise ValueError("embedded weights b_hat must have one entry per stage and sum to 1")
        if not 1 <= self.embedded_order < self.order:
            raise ValueError("embedded_order must be at least 1 and below order")
        if self.fsal and (self.a[-1][:-1] != self.b[:-1] or self.b[-1] != 0.0 or self.c[-1] != 1.0):
            raise ValueError("an FSAL tableau's last row of a must equal b (its last stage is the new state)")
        if len(self.dense) not in (0, s) or (self.dense and not self.fsal):
            raise ValueError("dense weights need one entry per stage and an FSAL tableau")


BOGACKI_SHAMPINE_32 = EmbeddedTableau(
    a=((0.0, 0.0, 0.0, 0.0), (1 / 2, 0.0, 0.0, 0.0), (0.0, 3 / 4, 0.0, 0.0), (2 / 9, 1 / 3, 4 / 9, 0.0)),
    b=(2 / 9, 1 / 3, 4 / 9, 0.0),
    c=(0.0, 1 / 2, 3 / 4, 1.0),
    order=3,
    b_hat=(7 / 24, 1 / 4, 1 / 3, 1 / 8),
    embedded_order=2,
    fsal=True,
    dense=(0.0, 0.0, 0.0, 0.0),  # cubic Hermite: the pair's natural third-order interpolant
)

DORMAND_PRINCE_54 = EmbeddedTableau(
    a=(
        (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
        (1 / 5, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0),
        (3 / 40, 9 / 40, 0.0, 0.0, 0.0, 0.0, 0.0),
        (44 / 45, -56 / 15, 32 / 9, 0.0, 0.0, 0.0, 0.0),
        (19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729, 0.0, 0.0, 0.0),
        (9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656, 0.0, 0.0),
        (35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84, 0.0),
    ),
    b=(35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84, 0.0),
    c=(0.0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0, 1.0),
    order=5,
    b_hat=(5179 / 57600, 0.0, 7571 / 16695, 393 / 640, -92097 / 339200, 187 / 2100, 1 / 40),
    embedded_order=4,
    fsal=True,
    # Dormand and Prince's continuous extension (Hairer, Nørsett & Wanner, Solving ODEs I, II.6).
    dense=(
        -12715105075 / 11282082432,
        0.0,
        87487479700 / 32700410799,
        -10690763975 / 1880347072,
        701980252875 / 199316789632,
        -1453857185 / 822651844,
        69997945 / 29380423,
    ),
)
