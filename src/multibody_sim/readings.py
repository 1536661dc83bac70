"""The readings made of the sensors' measurements, row by row: rate, latency, bias and noise (SensorStream; the
definition in multibody_sim/sensors.py's docstring). SensorStream._read_python is the specification; the
extension's make_readings (src/native/readings.hpp) renders it bit for bit, one call per row and engine call, and is
used when it is available."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from .noise import NormalStream


class SensorStream:
    """Readings from measurements, row by row (module docstring).

    Attributes:
        latest: each row's current readings, shape (B, width).
        count: ticks each row took since its start, shape (B,).
        history: per row, each late sensor's last `latency` measurements as a ring (its reading n's measurement in
            slot n % latency), sensor k's at [_history[k], _history[k + 1]), shape (B, Σ latency · width).
        states: per row and sensor, the position of its noise stream, shape (B, sensors, 4) uint64 (generators[b][k]
            keeps its state there).
    """

    def __init__(self, sensors: Any, strides: list[int], rows: np.ndarray, *, native: bool = True):
        """Args:
        sensors: what is measured (sensors.Sensors).
        strides: per sensor, readings every this many ticks.
        rows: each row's index for the seeds (a rollout's row b draws from seed + b).
        native: make the readings with the extension when it is available (False: always in Python).
        """
        self.sensors = sensors
        self.strides = strides
        self.seeds = [int(r) for r in rows]
        B = len(rows)
        self.latest = np.zeros((B, sensors.width))
        self.count = np.zeros(B, dtype=np.int64)
        self._history = np.cumsum([0] + [p.spec.latency * p.width for p in sensors.placed])
        self.history = np.zeros((B, int(self._history[-1])))
        self.states = np.zeros((B, len(sensors), 4), dtype=np.uint64)
        self.generators = [self._generators(b) for b in range(B)]
        self._spoiled = [bool(np.any(p.noise)) for p in sensors.placed]
        self.every_tick = all(stride == 1 for stride in strides)  # every sensor reads at every tick (the default)
        self._bias = np.concatenate([p.bias for p in sensors.placed]) if sensors.placed else np.zeros(0)
        self._scratch = np.zeros(0)  # the noise's draws (_draws)
        self._columns = [sensors.columns(k) for k in range(len(sensors))]
        self._native = _native_readings(self) if native else None  # (make_readings, its layout) or None

    def _generators(self, b: int, entropy: int | None = None) -> list[NormalStream]:
        """Row b's noise streams (their states in self.states[b]): seeded with each sensor's seed + b, or with (its
        seed, entropy)."""
        placed = self.sensors.placed
        seeds = [p.spec.seed + self.seeds[b] if entropy is None else [p.spec.seed, entropy] for p in placed]
        return [NormalStream(seed, self.states[b, k]) for k, seed in enumerate(seeds)]

    def native_data(self) -> dict[str, Any]:
        """The readings' layout as _native.ReadingLayout takes it (src/native/readings.hpp), its items and tables as
        dicts (ReadingItem, ZigguratTables)."""
        from .noise import native_tables

        items = [
            {
                "offset": int(self.sensors.offsets[k]),
                "width": p.width,
                "stride": int(self.strides[k]),
                "latency": int(p.spec.latency),
                "history": int(self._history[k]),
                "spoiled": self._spoiled[k],
                "bias": [float(x) for x in p.bias],  # type: ignore[union-attr]
                "noise": [float(x) for x in p.noise],  # type: ignore[union-attr]
            }
            for k, p in enumerate(self.sensors.placed)
        ]
        return {
            "width": self.sensors.width,
            "history": int(self._history[-1]),
            "items": items,
            "tables": native_tables(),
        }

    def restart(self, rows: np.ndarray, entropy: Any = None) -> None:
        """Rows start afresh (a reset): no history, no readings yet. `entropy`: None (their generators go on), or
        a whole number per row (or one for all): new generators seeded with (each sensor's seed, that number)."""
        rows = np.asarray(rows, dtype=int)
        entropies = [entropy] * len(rows) if entropy is None or np.ndim(entropy) == 0 else list(entropy)
        for b, e in zip(rows.tolist(), entropies, strict=True):
            self.count[b] = 0  # (the history fills at each late sensor's first reading)
            self.latest[b] = 0.0
            if e is not None:
                self.generators[b] = self._generators(b, int(e))

    def push(
        self,
        times: np.ndarray,
        rows: np.ndarray,
        values: np.ndarray,
        into: Callable[[int, np.ndarray], np.ndarray | None] | None = None,
    ) -> dict[int, list[tuple[np.ndarray, np.ndarray]]]:
        """Turn ticks (as Ticks.take gives them: times (n,), rows (n,), measurements (n, width), in time order)
        into readings; returns, per row that read, per sensor: the times of its new readings and the readings (for
        the samples in between).

        Args:
            into: ``into(b, times)``: where row b's readings at its ticks at `times` go, shape (len(times), width)
                (the sensors that read at every tick write their columns there), or None: a new array.
        """
        out: dict[int, list[tuple[np.ndarray, np.ndarray]]] = {}
        if not len(times):
            return out
        if rows[0] == rows[-1] and (rows == rows[0]).all():  # one row (simulate, Stepper)
            b = int(rows[0])
            out[b] = self._read(b, times, values, into(b, times) if into is not None else None)
            return out
        order = np.argsort(rows, kind="stable")  # each row's ticks, in time order
        rows, starts = np.unique(rows[order], return_index=True)
        stops = [*starts[1:].tolist(), len(order)]
        for b, start, stop in zip(rows.tolist(), starts.tolist(), stops, strict=True):
            picked = order[start:stop]
            row_times = times[picked]
            out[b] = self._read(b, row_times, values[picked], into(b, row_times) if into is not None else None)
        return out

    def _read(
        self, b: int, times: np.ndarray, Z: np.ndarray, out: np.ndarray | None = None
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """Row b's new readings, as _read_python makes them (the same numbers, placed alike), with the extension
        when it is available: one call for all its sensors and ticks."""
        if self._native is None:
            return self._read_python(b, times, Z, out)
        make, layout = self._native
        m, width = len(times), self.sensors.width
        count = int(self.count[b])
        whole = out if out is not None and out.dtype == np.float64 and out.flags.c_contiguous else np.empty((m, width))
        if self.every_tick:
            apart = _NOTHING
        else:
            firsts = [(-count) % stride for stride in self.strides]
            apart = np.empty(
                sum(
                    len(range(f, m, s)) * p.width
                    for f, s, p in zip(firsts, self.strides, self.sensors.placed, strict=True)
                    if s != 1
                )
            )
        make(layout, Z, whole, apart, count, self.latest[b], self.history[b], self.states[b])
        self.count[b] = count + m
        if out is not None and whole is not out:
            out[...] = whole
            whole = out
        if self.every_tick:
            return [(times, whole[:, c]) for c in self._columns]
        result = []
        at = 0
        for k, p in enumerate(self.sensors.placed):
            stride = self.strides[k]
            if stride == 1:
                result.append((times, whole[:, self._columns[k]]))
                continue
            due_times = times[firsts[k] :: stride]
            n = len(due_times) * p.width
            result.append((due_times, apart[at : at + n].reshape(-1, p.width)))
            at += n
        return result

    def _read_python(
        self, b: int, times: np.ndarray, Z: np.ndarray, out: np.ndarray | None = None
    ) -> list[tuple[np.ndarray, np.ndarray]]:
        """Row b's new readings from its ticks at `times` with measurements Z (m, width): the sensors that read at
        every tick into their columns of `out` (m, width; default a new array; it may be Z itself), their readings
        views of it, the others into arrays of their own. Each reading is ((z + bias) + noise · draw) element by
        element, z the measurement `latency` readings before (the first one before that), the draws (readings,
        width) of the sensor's generator in order: the specification (make_readings renders it)."""
        placed, columns = self.sensors.placed, self._columns
        m, count = len(times), int(self.count[b])
        ticks = count + np.arange(m) if not self.every_tick else None
        self.count[b] += m
        apart = {}  # the sensors at a rate or late: their readings' times and measurements (taken before Z is written)
        for k, p in enumerate(placed):
            stride = self.strides[k]
            if stride == 1 and not p.spec.latency:
                continue
            due_times, z = times, Z[:, columns[k]]
            if stride != 1:
                assert ticks is not None
                due = ticks % stride == 0
                due_times, z = times[due], Z[due, columns[k]]
            before = -(-count // stride)  # its readings before these
            apart[k] = (due_times, self._delayed(b, k, z, before) if p.spec.latency and len(z) else z)
        whole = np.empty_like(Z) if out is None else out
        np.add(Z, self._bias, out=whole)  # z + bias of every component at once (strided columns cost more)
        result = []
        for k, p in enumerate(placed):
            assert p.bias is not None and p.noise is not None
            if k in apart:
                due_times, z = apart[k]
                if not len(z):
                    result.append((np.zeros(0), np.zeros((0, p.width))))
                    continue
                readings = whole[:, columns[k]] if self.strides[k] == 1 else z  # (z: a copy of its own)
                np.add(z, p.bias, out=readings)
            else:
                due_times, readings = times, whole[:, columns[k]]
            if self._spoiled[k]:
                draws = self._draws(readings.size).reshape(readings.shape)
                self.generators[b][k].fill(draws)
                draws *= p.noise
                readings += draws
            if self.strides[k] != 1:
                self.latest[b, columns[k]] = readings[-1]
            result.append((due_times, readings))
        if self.every_tick:
            self.latest[b] = whole[-1]
        else:
            for k in range(len(placed)):
                if self.strides[k] == 1:
                    self.latest[b, columns[k]] = whole[-1, columns[k]]
        return result

    def _delayed(self, b: int, k: int, z: np.ndarray, n: int) -> np.ndarray:
        """Sensor k's measurements `latency` readings before row b's new ones z (m, its width), the first one before
        that (a new array), n its readings before these; keeps the last `latency` in the row's ring (history)."""
        latency, width = self.sensors.placed[k].spec.latency, self.sensors.placed[k].width
        ring = self.history[b, self._history[k] : self._history[k + 1]].reshape(latency, width)
        if n == 0:
            ring[:] = z[0]
        held = ring[(n + np.arange(latency)) % latency]  # measurements n - latency ... n - 1, oldest first
        sequence = np.concatenate([held, z])
        ring[(n + len(z) + np.arange(latency)) % latency] = sequence[len(z) :]
        return sequence[: len(z)]

    def _draws(self, n: int) -> np.ndarray:
        """A scratch array of n numbers for the noise's draws (reused: no new memory per reading)."""
        if len(self._scratch) < n:
            self._scratch = np.empty(max(n, 2 * len(self._scratch)))
        return self._scratch[:n]

    def readings(self, b: int) -> dict[str, np.ndarray]:
        """Row b's current readings by sensor name (copies)."""
        return {name: self.latest[b, self._columns[k]].copy() for k, name in enumerate(self.sensors.names)}

    def batch_readings(self, rows: np.ndarray) -> dict[str, np.ndarray]:
        """The rows' current readings by sensor name, shape (len(rows), width) each (copies)."""
        return {name: self.latest[rows, self._columns[k]] for k, name in enumerate(self.sensors.names)}

    def snapshot(self) -> Any:
        return self.latest.copy(), self.count.copy(), self.history.copy(), self.states.copy()

    def restore(self, snapshot: Any) -> None:
        """Back to a snapshot's readings, counts, histories and streams (in place: the generators keep their
        states in self.states)."""
        self.latest[...], self.count[...], self.history[...], self.states[...] = snapshot


_NOTHING = np.zeros(0)  # make_readings' `apart` when every sensor reads at every tick


def _native_readings(stream: SensorStream) -> tuple[Any, Any] | None:
    """The extension's make_readings and the stream's layout for it (_native.ReadingLayout), or None without the
    extension."""
    from . import native  # (the extension loads on first use)

    make = native.function("make_readings")
    if make is None:
        return None
    module = native.module
    data = stream.native_data()
    items = [module.ReadingItem(**item) for item in data["items"]]
    layout = module.ReadingLayout(**{**data, "items": items, "tables": module.ZigguratTables(**data["tables"])})
    return make, layout
