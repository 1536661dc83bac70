"""Gaussian noise for the sensors: standard normal draws from a seeded stream, the same numbers in Python and in C++.

`NormalStream` draws with a 256-layer ziggurat (Marsaglia and Tsang, "The Ziggurat Method for Generating Random
Variables", J. Stat. Softw. 5(8), 2000) on the 64-bit outputs of numpy's SFC64 bit generator (seeded through
numpy's SeedSequence, as `numpy.random.default_rng` seeds). Every step is written out so that the compiled
extension (src/native/noise.hpp) renders it bit for bit: integer masks and shifts, one rounded product per draw on
the fast path (~99 % of draws), and on the rare slow paths only libm's `exp` and `log` (Python's `math` module calls
the same functions). The tables are made here and handed to C++ (`native_tables()`); this module is the
specification, and draws go through the extension when it is available (tests/test_noise.py checks both give the
same numbers and states).

One draw, from a 64-bit output ``r``: layer ``i = r & 255``, sign bit ``(r >> 8) & 1``, ``u = r >> 11`` (53 bits),
``x = u · W[i]``. If ``u < K[i]``, x (signed) is the draw. Otherwise, in layer 0, a draw from the tail beyond R
(pairs of outputs until one is accepted); in another layer, the next output ``v`` (53 bits, ``U = v · 2⁻⁵³``) is
accepted if ``F[i] + U · D[i] < exp(−½ x²)``; else the draw starts over with the next output.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

LAYERS = 256
#: The rightmost layer's edge for 256 layers under exp(−x²/2) (Marsaglia and Tsang, 2000).
R = 3.6541528853610088
_SCALE = 2.0**-53


def _tables() -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """W (256,): each layer's width · 2⁻⁵³; K (256,) uint64: the 53-bit u below which a draw is inside the next
    layer's edge; F (257,): exp(−x²/2) at the layer edges; D (256,): F[i + 1] − F[i]."""

    def f(x: float) -> float:
        return math.exp(-0.5 * x * x)

    area = R * f(R) + math.sqrt(math.pi / 2.0) * math.erfc(R / math.sqrt(2.0))  # each layer's area
    edges = [area / f(R), R]  # layer 0: the base strip (its width covers the tail's area), layer 1 from R in
    for _ in range(2, LAYERS):
        edges.append(math.sqrt(-2.0 * math.log(f(edges[-1]) + area / edges[-1])))
    edges.append(0.0)
    X = np.array(edges)
    W = X[:LAYERS] * _SCALE
    K = np.array([math.floor(X[i + 1] / X[i] * 2.0**53) for i in range(LAYERS)], dtype=np.uint64)
    F = np.array([f(x) for x in X])
    return W, K, F, np.diff(F)


W, K, F, D = _tables()


def native_tables() -> dict[str, Any]:
    """The tables as the extension takes them (_native.ZigguratTables' fields)."""
    return {"width": W.tolist(), "inside": K.tolist(), "density": F.tolist(), "rise": D.tolist(), "edge": R}


def _signed(raw: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The fast path on outputs `raw` (n,) uint64: each one's signed draw and whether it is accepted."""
    layer = (raw & np.uint64(255)).astype(np.intp)
    u = raw >> np.uint64(11)
    x = u.astype(np.float64) * W[layer]
    x = np.where((raw >> np.uint64(8)) & np.uint64(1), -x, x)
    return x, u < K[layer]


class NormalStream:
    """A seeded stream of standard normal draws (module docstring). Its state is four 64-bit words (numpy's SFC64:
    three words and a counter)."""

    def __init__(self, seed: Any, state: np.ndarray | None = None):
        """seed: anything numpy.random.SeedSequence takes (an int, a list of ints); state: where the stream keeps its
        position, a (4,) uint64 array written in place (e.g. a view into the states of many streams), or None: its
        own."""
        self.state = np.empty(4, dtype=np.uint64) if state is None else state  # (4,): the stream's position
        self.state[:] = np.random.SFC64(seed).state["state"]["state"]

    def fill(self, out: np.ndarray) -> None:
        """The next out.size draws into `out`, in its C order, through the extension when it is available (the same
        numbers)."""
        fill = _FILL or _filler()
        try:
            fill(self.state, out)
        except TypeError:  # not float64 in C order: drawn into such an array, then copied
            flat = np.empty(out.size)
            fill(self.state, flat)
            out[...] = flat.reshape(out.shape)

    def snapshot(self) -> np.ndarray:
        return self.state.copy()

    def restore(self, state: np.ndarray) -> None:
        self.state[:] = state


def fill_python(state: np.ndarray, out: np.ndarray) -> None:
    """The specification: the next out.size draws of the stream at `state` (4,) uint64 into `out` (float64, C
    order); state is advanced past every output they used.

    Raises:
        TypeError: out is not float64 in C order (as the extension's fill_normals: its draws would be lost in a copy).
    """
    if out.dtype != np.float64 or not out.flags.c_contiguous:
        raise TypeError("fill_python: `out` must be float64 in C order")
    out = out.reshape(-1)
    n = len(out)
    bits = np.random.SFC64(0)
    start = {"bit_generator": "SFC64", "state": {"state": state.copy()}, "has_uint32": 0, "uinteger": 0}
    bits.state = start
    raw = bits.random_raw(n + n // 16 + 64)
    x, accepted = _signed(raw)
    rejected = np.flatnonzero(~accepted)  # where the fast path fails, ascending
    made, at, k = 0, 0, 0  # draws made; the next output to use; the next entry of `rejected` to look at
    while made < n:
        while k < len(rejected) and rejected[k] < at:  # (outputs a slow path used)
            k += 1
        stop = int(rejected[k]) if k < len(rejected) else len(raw)
        run = min(n - made, stop - at)
        out[made : made + run] = x[at : at + run]
        made, at = made + run, at + run
        if made == n:
            break
        if at + 64 > len(raw):  # room for the slow path's outputs: the stream goes on
            more = bits.random_raw(len(raw))
            more_x, more_accepted = _signed(more)
            rejected = np.concatenate([rejected[k:], len(raw) + np.flatnonzero(~more_accepted)])
            raw, x, k = np.concatenate([raw, more]), np.concatenate([x, more_x]), 0
            continue
        value, at = _slow(raw, at, x[at])
        if value is not None:
            out[made] = value
            made += 1
    bits.state = start  # the state after exactly `at` outputs
    bits.random_raw(at)
    state[:] = bits.state["state"]["state"]


def _slow(raw: np.ndarray, at: int, signed: float) -> tuple[float | None, int]:
    """The slow path of the draw begun at output `at` (rejected on the fast path, its signed value `signed`):
    (the draw, or None if it starts over, and the next output to use)."""
    r = int(raw[at])
    layer = r & 255
    negative = (r >> 8) & 1
    at += 1
    if layer == 0:  # the tail beyond R
        while True:
            a = -math.log(((int(raw[at]) >> 11) + 1) * _SCALE) / R
            b = -math.log(((int(raw[at + 1]) >> 11) + 1) * _SCALE)
            at += 2
            if b + b > a * a:
                return (-(R + a) if negative else R + a), at
    x = signed
    U = (int(raw[at]) >> 11) * _SCALE
    at += 1
    if float(F[layer]) + U * float(D[layer]) < math.exp(-0.5 * (x * x)):
        return x, at
    return None, at


_FILL: Any = None


def _filler() -> Any:
    """fill(state, out): the extension's fill_normals with its copy of the tables when it is available (made once),
    else fill_python."""
    global _FILL
    if _FILL is None:
        from . import native  # (the extension loads on first use)

        fill = native.function("fill_normals")
        if fill is not None:
            tables = native.module.ZigguratTables(**native_tables())  # type: ignore[union-attr]
            _FILL = lambda state, out: fill(state, out, tables)  # noqa: E731
        else:
            _FILL = fill_python
    return _FILL
