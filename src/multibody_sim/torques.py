"""Torques: where a run's torques (commands, with a scene's actuators) come from (nothing, one controller per row, a
batched controller, open-loop sequences), the check every torque passes, and saturation at the commands' bounds."""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np

from .exceptions import InvalidArgumentError


def check_torque(system: Any, tau: Any, t: float | None, what: str = "controller output") -> np.ndarray:
    """tau as a float array (nv,) if it is a valid torque, else InvalidArgumentError naming the time and reason."""
    fast = type(tau) is np.ndarray and tau.dtype == np.float64 and tau.shape == (system.nv,)
    # max - min in Python floats: finite exactly when every entry is, and a huge finite torque overflows to inf
    # silently (tau @ tau made NumPy warn), taking the full check.
    if fast and math.isfinite(float(tau.max()) - float(tau.min())) and not system.unactuated_load(tau):
        return tau
    try:  # the full check, with the precise reason
        return system.check_tau(tau)
    except InvalidArgumentError as exc:
        if t is None:
            raise
        raise InvalidArgumentError(f"{what} at t = {t:.6g} s: {exc}") from None


def command_bounds(system: Any) -> tuple[np.ndarray, np.ndarray]:
    """The range of each entry of a command, (low, high), each shape (nv,) (±inf where unbounded): ± the effort limit
    for a torque; for a scene's actuators (scenes/actuators.py) ± the effort limit (kind torque), the joint's position
    limits (position servo) or ± the velocity limit (velocity servo)."""
    high = np.array(system.effort_limit, dtype=float)
    low = -high
    actuators = getattr(system, "actuators", None)
    if actuators is not None:
        actuators.command_bounds(low, high, system.lower_limit, system.upper_limit)
    return low, high


class Saturation:
    """Commands saturate at their bounds (command_bounds: torques at the URDF's effort limits, a scene's servo targets
    at their joints' ranges): they are clipped, and the calls and dofs counted.

    Attributes:
        low, high: the bounds, shape (nv,) each, or None when nothing is bounded.
        calls: per row, how many control instants clipped something, shape (B,).
        dofs: per row and dof, how many times it was clipped, shape (B, nv).
    """

    def __init__(self, system: Any, B: int, systems: list[Any] | None = None):
        low, high = command_bounds(system)
        if systems is not None:  # randomised rows: their own actuators' bounds, (B, nv), where any row differs
            bounds = [command_bounds(row) for row in systems]
            if any(not (np.array_equal(a, low) and np.array_equal(b, high)) for a, b in bounds):
                low, high = np.array([a for a, _ in bounds]), np.array([b for _, b in bounds])
        bounded = (np.isfinite(low) | np.isfinite(high)).any()
        self.low: np.ndarray | None = low if bounded else None
        self.high: np.ndarray | None = high if bounded else None
        # Torques' bounds are ± the effort limits: then |TAU| > high finds the same entries as the two comparisons
        # with one NumPy call less (Stepper.step checks at every call).
        self._symmetric = bool(bounded and low.ndim == 1 and np.array_equal(low, -high))
        self.calls = np.zeros(B, dtype=np.int64)
        self.dofs = np.zeros((B, system.nv), dtype=np.int64)

    def apply(self, TAU: np.ndarray, rows: np.ndarray) -> np.ndarray:
        """TAU (n, nv) of `rows`, clipped (a new array where anything was clipped)."""
        if self.low is None or self.high is None:
            return TAU
        low, high = (self.low, self.high) if self.low.ndim == 1 else (self.low[rows], self.high[rows])
        over = np.abs(TAU) > high if self._symmetric else (low > TAU) | (high < TAU)
        if not over.any():
            return TAU
        self.calls[rows] += over.any(axis=1)
        self.dofs[rows] += over
        return np.minimum(np.maximum(TAU, low), high)

    def snapshot(self) -> tuple[np.ndarray, np.ndarray]:
        return self.calls.copy(), self.dofs.copy()

    def restore(self, snapshot: tuple[np.ndarray, np.ndarray]) -> None:
        self.calls, self.dofs = snapshot[0].copy(), snapshot[1].copy()


class Torques:
    """Where the rows' torques come from: nothing, one callable per row, a batched callable, or open-loop sequences.

    Attributes:
        kind: "none", "callables", "batched" or "taus".
        label: the controller's name for the metadata.
    """

    def __init__(
        self,
        kind: str,
        *,
        callables: list[Any] | None = None,
        batched: Any = None,
        taus: np.ndarray | None = None,
        label: str | None = None,
    ):
        self.kind, self.callables, self.batched, self.taus, self.label = kind, callables, batched, taus, label

    @classmethod
    def single(cls, controller: Any) -> Torques:
        """simulate()'s and Stepper's: one callable or None."""
        if controller is None:
            return cls("none")
        return cls("callables", callables=[controller], label=controller_name(controller))

    def subset(self, rows: np.ndarray) -> Torques:
        """The same torques for the rows `rows` only (Ray chunks, element-by-element runs)."""
        return Torques(
            self.kind,
            callables=[self.callables[b] for b in rows] if self.callables is not None else None,
            batched=self.batched,
            taus=self.taus[rows] if self.taus is not None else None,
            label=self.label,
        )

    @property
    def reads_sensors(self) -> bool:
        """Whether a controller asks for the sensors' readings (see reads_sensors())."""
        if self.kind == "batched":
            return reads_sensors(self.batched)
        return self.kind == "callables" and any(reads_sensors(c) for c in self.callables or ())

    def compute(
        self,
        system: Any,
        t: float,
        instant: int,
        rows: np.ndarray,
        states: Callable[[], tuple[list, list]],
        readings: Any = None,
    ) -> tuple[np.ndarray, list[tuple[int, BaseException, bool]]]:
        """The torques of the running rows at time t (control instant number `instant`), shape (n, nv), and the
        rows whose controller failed: (position, exception, is_bad_output). `readings`: the sensors' readings
        (readings.SensorStream), for controllers that read them."""
        n, nv = len(rows), system.nv
        failures: list[tuple[int, BaseException, bool]] = []
        if self.kind == "taus":
            assert self.taus is not None
            return self.taus[rows, min(instant, self.taus.shape[1] - 1)], failures
        Qs, Vs = states()
        if self.kind == "batched":
            Q, V = np.array(Qs), np.array(Vs)
            Q.setflags(write=False)  # the controller sees the state; it must not edit it
            V.setflags(write=False)
            try:
                if readings is not None and reads_sensors(self.batched):
                    out = self.batched(t, Q, V, readings.batch_readings(rows))
                else:
                    out = self.batched(t, Q, V)
            except Exception as exc:  # user code: every row fails with it
                return np.zeros((n, nv)), [(j, exc, False) for j in range(n)]
            shape = np.shape(out)
            if shape != (n, nv):
                error = InvalidArgumentError(
                    f"batched controller output at t = {t:.6g} s must have shape ({n}, {nv}), got {shape}"
                )
                return np.zeros((n, nv)), [(j, error, True) for j in range(n)]
            TAU = np.array(out, dtype=float)
            suspect = ~np.isfinite(TAU).all(axis=1) | system.unactuated_load(TAU, per_row=True)
            for j in np.flatnonzero(suspect).tolist():
                try:  # the full check, with the precise reason
                    system.check_tau(TAU[j])
                except InvalidArgumentError as exc:
                    failures.append(
                        (
                            j,
                            InvalidArgumentError(
                                f"batched controller output at t = {t:.6g} s, element {rows[j]}: {exc}"
                            ),
                            True,
                        )
                    )
            return TAU, failures
        assert self.callables is not None
        TAU = np.empty((n, nv))
        for j, b in enumerate(rows.tolist()):
            q, v = Qs[j], Vs[j]
            q.setflags(write=False)  # the controller sees the state; it must not edit it
            v.setflags(write=False)
            try:
                controller = self.callables[b]
                if readings is not None and reads_sensors(controller):
                    out = controller(t, q, v, readings.readings(b))
                else:
                    out = controller(t, q, v)
            except Exception as exc:  # user code: this row fails with it
                failures.append((j, exc, False))
                TAU[j] = 0.0
                continue
            try:
                TAU[j] = check_torque(system, out, t)
            except InvalidArgumentError as exc:
                failures.append((j, exc, True))
                TAU[j] = 0.0
        return TAU, failures


def reads_sensors(controller: Any) -> bool:
    """Whether a controller reads the sensors: it says so with an attribute ``sensors = True`` and is then called
    as ``controller(t, q, v, readings)``, readings a dict of sensor name -> array (components,) (a batched one:
    ``(t, Q, V, readings)``, arrays (n, components))."""
    return getattr(controller, "sensors", False) is True


def check_sensor_controller(system: Any, reads: bool) -> None:
    """InvalidArgumentError when a controller reads sensors (`reads`) and the system declares none."""
    if reads and getattr(system, "sensors", None) is None:
        raise InvalidArgumentError(
            "the controller reads sensors (sensors = True) but the system declares none: declare [[sensor]] tables "
            "in its scene, or drop the attribute"
        )


def controller_name(controller: Any) -> str:
    return str(getattr(controller, "__qualname__", type(controller).__qualname__))
