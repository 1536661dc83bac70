"""The sensors' Gaussian noise (multibody_sim/noise.py): its draws are standard normal (checked against the normal
distribution's CDF and its tail mass, independently of the tables), and the compiled extension's draws are the
specification's bit for bit, with the same stream state after them."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from conftest import needs_native
from multibody_sim import native, noise


def _python_draws(seed: int, sizes: list[int]) -> tuple[np.ndarray, np.ndarray]:
    stream = noise.NormalStream(seed)
    parts = []
    for size in sizes:
        out = np.empty(size)
        noise.fill_python(stream.state, out)
        parts.append(out)
    return np.concatenate(parts), stream.state


def test_draws_are_standard_normal_over_a_million() -> None:
    """Kolmogorov–Smirnov against the normal CDF, the first four moments within 4 standard errors, and the mass
    beyond the ziggurat's last edge R (the tail the slow path draws) within 4 standard errors of 2 Φ(−R)."""
    draws, _ = _python_draws(2024, [1_000_000])
    n = len(draws)
    assert stats.kstest(draws, "norm").pvalue > 1e-3
    assert abs(draws.mean()) < 4 / np.sqrt(n)
    assert abs(draws.var() - 1.0) < 4 * np.sqrt(2.0 / n)
    assert abs(stats.skew(draws)) < 4 * np.sqrt(6.0 / n)
    assert abs(stats.kurtosis(draws)) < 4 * np.sqrt(24.0 / n)
    beyond = 2 * stats.norm.sf(noise.R)
    assert abs(np.mean(np.abs(draws) > noise.R) - beyond) < 4 * np.sqrt(beyond / n)
    # the wedges: counts in 200 equal-probability bins agree with the normal distribution (chi-square)
    edges = stats.norm.ppf(np.linspace(0.0, 1.0, 201))
    counts, _ = np.histogram(draws, edges)
    assert stats.chisquare(counts).pvalue > 1e-3


def test_fill_writes_draws_in_order_into_any_array() -> None:
    """A 2-d array, a column of one (not contiguous) and float32: the stream's next draws in C order."""
    expected, _ = _python_draws(5, [12])
    stream = noise.NormalStream(5)
    square = np.empty((2, 3))
    stream.fill(square)
    column = np.zeros((3, 2))[:, 1]
    stream.fill(column)
    assert np.array_equal(np.concatenate([square.ravel(), column]), expected[:9])
    single = np.empty(3, dtype=np.float32)
    stream.fill(single)
    assert np.array_equal(single, expected[9:].astype(np.float32))


def test_a_stream_gives_the_same_draws_in_one_fill_or_many_and_seeds_differ() -> None:
    whole, state = _python_draws(9, [50_000])
    pieces, state_pieces = _python_draws(9, [1, 2, 3, 7, 100, 1000, 5000, 43_887])
    assert np.array_equal(whole, pieces)
    assert np.array_equal(state, state_pieces)
    other, _ = _python_draws(10, [50_000])
    assert not np.any(whole == other)


@needs_native
def test_the_extensions_draws_are_the_specifications_bit_for_bit() -> None:
    """Fills of many sizes, 600 000 draws with hundreds of slow-path draws (tail and wedge): the same numbers and
    the same stream state after each fill."""
    tables = native.module.ZigguratTables(**noise.native_tables())
    sizes = [1, 5, 6, 12, 1000, 4000, 24_000, 170_976, 400_000]
    for seed in (0, 7, 123_456_789):
        expected, python_state = _python_draws(seed, sizes)
        stream = noise.NormalStream(seed)
        parts = []
        for size in sizes:
            out = np.empty(size)
            native.module.fill_normals(stream.state, out, tables)
            parts.append(out)
        drawn = np.concatenate(parts)
        assert drawn.tobytes() == expected.tobytes()
        assert np.array_equal(stream.state, python_state)
        assert np.sum(np.abs(drawn) > noise.R) > 50  # the tail's slow path ran


@pytest.mark.parametrize(
    "state, out",
    [
        (np.zeros(4, dtype=np.int64), np.empty(3)),  # (a converted copy would not advance)
        (np.zeros(3, dtype=np.uint64), np.empty(3)),
        (np.zeros(4, dtype=np.uint64), np.empty(3, dtype=np.float32)),
        (np.zeros(4, dtype=np.uint64), np.empty((4, 2))[:, 0]),  # not contiguous: draws would go to a copy
    ],
)
@needs_native
def test_the_extension_refuses_what_it_could_not_write_in_place(state: np.ndarray, out: np.ndarray) -> None:
    tables = native.module.ZigguratTables(**noise.native_tables())
    with pytest.raises(TypeError):
        native.module.fill_normals(state, out, tables)


def test_the_specification_refuses_what_it_could_not_write_in_place() -> None:
    state = noise.NormalStream(1).state
    for out in (np.empty(3, dtype=np.float32), np.empty((4, 2))[:, 0]):
        with pytest.raises(TypeError):
            noise.fill_python(state, out)
