"""DOP853's coefficients (integrators/dop853_tables.py, written from Hairer's published tables): the order
conditions they must satisfy, and SciPy's copy of the same tables, read here only."""

from __future__ import annotations

import numpy as np
import pytest

from multibody_sim.integrators import dop853_tables as tables


def test_tables_equal_scipys_copy() -> None:
    reference = pytest.importorskip("scipy.integrate._ivp.dop853_coefficients")
    assert (tables.N_STAGES, tables.N_STAGES_EXTENDED) == (reference.N_STAGES, reference.N_STAGES_EXTENDED)
    for name in ("A", "B", "C", "D", "E3", "E5"):
        ours, theirs = getattr(tables, name), np.asarray(getattr(reference, name))
        assert ours.shape == theirs.shape, name
        np.testing.assert_array_equal(ours, theirs, err_msg=name)  # the same decimals read as the same doubles


def test_stage_times_are_the_row_sums() -> None:
    np.testing.assert_allclose(tables.A.sum(axis=1), tables.C, rtol=0, atol=1e-14)


@pytest.mark.parametrize("k", range(8))
def test_quadrature_conditions_of_order_8(k: int) -> None:
    """Σ b_i c_i^k = 1/(k+1) for k < 8: the weights integrate polynomials of degree 7 exactly."""
    b, c = tables.B, tables.C[: tables.N_STAGES]
    assert b @ c**k == pytest.approx(1.0 / (k + 1), rel=1e-14, abs=1e-14)


def test_tree_conditions_of_order_8() -> None:
    """A few of order 8's tree conditions beyond quadrature: Σ b_i c_i^m (A c^n)_i = 1/((n+1)(m+n+2))."""
    n_stages = tables.N_STAGES
    A, b, c = tables.A[:n_stages, :n_stages], tables.B, tables.C[:n_stages]
    for m, n in [(0, 1), (1, 1), (2, 3), (5, 1), (0, 6)]:
        assert b @ (c**m * (A @ c**n)) == pytest.approx(1.0 / ((n + 1) * (m + n + 2)), rel=1e-13, abs=1e-14)


def test_error_estimates_vanish_on_constants_and_are_of_their_orders() -> None:
    """Both error weights annihilate constants (Σ e_i = 0); the 3rd-order estimate's weights b - bhh are exact
    to degree 2 (bhh is a 3rd-order quadrature), so Σ e3_i c_i^k = 0 for k < 3 but not for k = 3."""
    c = tables.C[: tables.N_STAGES + 1]
    assert tables.E5.sum() == pytest.approx(0.0, abs=1e-14)
    for k in range(3):
        assert tables.E3 @ c**k == pytest.approx(0.0, abs=1e-14)
    assert abs(tables.E3 @ c**3) > 1e-6


@pytest.mark.parametrize("k", range(7))
def test_dense_output_is_exact_for_polynomials_of_degree_6(k: int) -> None:
    """On y' = t^k from y(0) = 0 with h = 1 (stages K_i = c_i^k), Hairer's 7th-order continuous extension
    y(θ) = r1 + θ(r2 + (1-θ)(r3 + θ(r4 + (1-θ)(r5 + θ(r6 + (1-θ)(r7 + θ r8)))))) gives θ^(k+1)/(k+1) exactly."""
    K = tables.C**k  # all 16 stages: the step's 12, the new state's and the dense output's 3
    delta = tables.B @ K[: tables.N_STAGES]
    r = [0.0, delta, K[0] - delta, 2.0 * delta - (K[0] + K[tables.N_STAGES]), *(tables.D @ K)]
    for theta in np.linspace(0.0, 1.0, 11):
        y = 0.0
        for i, coefficient in enumerate(reversed(r[1:])):  # innermost first: factors θ and (1 - θ) alternate
            y = (y + coefficient) * (theta if i % 2 == 0 else 1.0 - theta)
        assert y == pytest.approx(theta ** (k + 1) / (k + 1), rel=1e-12, abs=1e-13)
