"""The native kernel: the stepping core's loop (core.Core.advance) run in C++ for an eligible run.

The Python core is the specification; the C++ engine (src/native/kernel.cpp, ``_native.Kernel``) renders the same
loop and arithmetic: the method arrives as data (its tableau, error weights and dense-output coefficients, read from
the Python integrator), the chart map as the Python space's own tables, the step-size controller as its constants
and state. NativeCore is a Core whose advance() hands the whole loop to the engine between the driver's events and
returns at least every ~50 ms of work (so Ctrl-C and SIGTERM are honoured with every sample kept); everything else
(recording at the driver's request, stopping rows, the messages of rows that stop) is Core's own code.
"""

from __future__ import annotations

import math
import os
import time
from typing import Any

import numpy as np
import pinocchio as pin

from .core import EMPTY, FULL, REACHED, STEPPED, Core, KernelAttempt, RowStop, collapsed_message, diverged_message
from .integrators import INTEGRATORS, Integrator
from .integrators.explicit_rk import DormandPrince853, EmbeddedRungeKutta, ExplicitRungeKutta
from .integrators.partitioned import SemiImplicitEuler
from .recording import SampleStore
from .robot import Robot
from .state import _HALF_SERIES
from .step_control import LANDING_FRACTION, SLIVER, ConstantStep, PIController

# The registry's explicit methods, which the engine renders (its kinds: kernel.hpp's Kind).
NATIVE_METHODS = {
    ExplicitRungeKutta: 0,
    EmbeddedRungeKutta: 1,
    DormandPrince853: 2,
    SemiImplicitEuler: 3,
}
ENVIRONMENT = "MULTIBODY_SIM_NATIVE"  # "0" forces the Python kernel
# advance() returns to Python after about this much work [s] (interrupts, signals)
BUDGET_SECONDS = 0.03
_STATUSES = (REACHED, STEPPED, FULL, EMPTY)
_NEED_ROOM = 4
_DIVERGED, _COLLAPSED = 1, 2


def extension() -> tuple[Any, str | None]:
    """(the compiled module, None) when it imports, else (None, why not)."""
    try:
        from . import _native  # type: ignore[attr-defined]
    except ImportError as exc:
        return None, f"the compiled extension is not available ({exc})"
    return _native, None


def why_not_native(system: Any, method: Integrator) -> str | None:
    """None when the native kernel runs `method` on `system`, else why not (one phrase for describe() and the
    run header)."""
    if os.environ.get(ENVIRONMENT, "") == "0":
        return f"{ENVIRONMENT}=0"
    module, missing = extension()
    if module is None:
        return missing
    if type(system) is not Robot:
        return "a scene's physics runs on the Python kernel"
    if type(method) not in NATIVE_METHODS or INTEGRATORS.get(method.name) is not method:
        return f"integrator '{method.name}' is not an explicit method of the registry"
    if system.record_fields:
        return "the system records fields per sample"
    return None


def method_data(method: Integrator) -> dict[str, Any]:
    """The method as the engine takes it: kind, tableau (a row-major), error and dense-output weights."""
    kind = NATIVE_METHODS[type(method)]
    data: dict[str, Any] = {
        "kind": kind,
        "stages": 1,
        "a": [0.0],
        "b": [1.0],
        "c": [0.0],
        "chart_terms": 0,
        "fsal": False,
        "e": [],
        "dense": [],
        "e5": [],
        "e3": [],
        "extended_stages": 0,
        "a_extended": [],
        "c_extended": [],
        "dense_weights": [],
    }
    if isinstance(method, ExplicitRungeKutta):
        data.update(
            stages=len(method.b),
            a=method.a.ravel().tolist(),
            b=method.b.tolist(),
            c=method.c.tolist(),
            chart_terms=method.chart_terms,
        )
    if isinstance(method, EmbeddedRungeKutta):
        dense = method._d
        data.update(fsal=method.fsal, e=method._e.tolist(), dense=dense.tolist() if dense is not None and dense.any() else [])
    if isinstance(method, DormandPrince853):
        data.update(
            fsal=True,
            e5=method._e5.tolist(),
            e3=method._e3.tolist(),
            extended_stages=len(method._c_extended),
            a_extended=method._a_extended.ravel().tolist(),
            c_extended=method._c_extended.tolist(),
            dense_weights=method._dense_weights.ravel().tolist(),
        )
    return data


def model_bytes(model: pin.Model) -> bytes:
    """The model in Pinocchio's binary serialization (what the engine loads)."""
    buffer = pin.serialization.StreamBuffer()
    model.saveToBinary(buffer)
    return bytes(buffer.tobytes())


class NativeKernel:
    """The running rows' states in the engine (the Kernel interface of core.py for Core's own code: records, stops,
    torques; the steps themselves are taken by NativeCore.advance). The engine is made once the step-size controller
    is known (bind())."""

    def __init__(
        self,
        system: Any,
        method: Integrator,
        Q0: np.ndarray,
        V0: np.ndarray,
        *,
        rtol: float | None = None,
        atol: float | None = None,
        num_threads: int = 1,
    ):
        self.system, self.method = system, method
        self.rtol, self.atol = rtol, atol
        self.num_threads = num_threads
        self._initial = (np.ascontiguousarray(Q0, dtype=float), np.ascontiguousarray(V0, dtype=float))
        self.state = np.zeros(16)  # the core state the engine reads and writes (see kernel.cpp's pack())
        self.engine: Any = None
        self.method_data = method_data(method)

    def bind(self, control: ConstantStep | PIController) -> None:
        """Make the engine for this controller."""
        module, missing = extension()
        if module is None:  # pragma: no cover - choose_kernel checked it
            raise RuntimeError(missing)
        system, data = self.system, self.method_data
        space = system.space
        blocks = [
            (start, stop - start, index.ravel().astype(int).tolist(), sign.ravel().tolist())
            for (start, stop), (index, sign) in zip(space.curved_blocks, space._chart_entries, strict=True)
        ]
        pi = []
        if isinstance(control, PIController):
            pi = [
                control.alpha,
                control.beta,
                control.safety,
                control.factor_min,
                control.factor_max,
                control.max_step,
                control.first_step,
                float(self.rtol),  # type: ignore[arg-type]
                float(self.atol),  # type: ignore[arg-type]
            ]
        Q0, V0 = self._initial
        self.engine = module.Kernel(
            model_bytes(system.model),
            data["kind"],
            data["stages"],
            data["a"],
            data["b"],
            data["c"],
            data["chart_terms"],
            data["fsal"],
            data["e"],
            data["dense"],
            data["e5"],
            data["e3"],
            data["extended_stages"],
            data["a_extended"],
            data["c_extended"],
            data["dense_weights"],
            blocks,
            list(_HALF_SERIES),
            np.asarray(system.damping, dtype=float),
            len(system.ledger_elements),
            control.adaptive,
            control.dt if isinstance(control, ConstantStep) else math.nan,
            SLIVER,
            pi,
            LANDING_FRACTION,
            Q0,
            V0,
            self.num_threads,
        )

    # ---- the Kernel interface (core.py) ----------------------------------------------------------------------------
    @property
    def n(self) -> int:
        return len(self._initial[0]) if self.engine is None else int(self.engine.running)

    @property
    def t(self) -> float:
        return float(self.state[0])

    @property
    def k(self) -> int:
        return int(self.state[1])

    def start_at(self, t: float, k: int = 0) -> None:
        self.state[0], self.state[1] = t, k

    def set_torques(self, TAU: np.ndarray, jump: bool) -> None:
        self.engine.set_torques(np.ascontiguousarray(TAU, dtype=float), jump)

    def keep(self, keep: np.ndarray) -> None:
        self.engine.keep([bool(x) for x in keep])

    def states(self) -> tuple[list[np.ndarray], list[np.ndarray]]:
        return list(self.engine.running_q()), list(self.engine.running_v())

    def state_of(self, j: int) -> tuple[np.ndarray, np.ndarray]:
        return self.engine.running_q()[j].copy(), self.engine.running_v()[j].copy()

    def write_sample(self, store: SampleStore, i: int, index: Any, js: np.ndarray | None = None) -> None:
        """Write the current state of the run rows `index` (the store's columns: an int, a slice or the rows) as
        sample i (the engine knows each row's state by its row; js, their positions, need not be looked up)."""
        if type(index) is int:
            rows = [index]
        elif isinstance(index, slice):
            rows = list(range(store.B))[index]
        else:
            rows = [int(b) for b in index]
        self.engine.write_rows(i, rows, *store_arrays(store))

    def attempt(self, h: float) -> KernelAttempt:
        raise AssertionError("the native kernel steps inside NativeCore.advance")  # pragma: no cover

    def nonfinite(self) -> np.ndarray:
        raise AssertionError("the native kernel checks its steps itself")  # pragma: no cover

    def nonfinite_dof(self, j: int) -> int:
        raise AssertionError("the native kernel names non-finite coordinates itself")  # pragma: no cover

    def accept(self, t_next: float) -> None:
        raise AssertionError("the native kernel accepts its steps itself")  # pragma: no cover

    def reject(self) -> None:
        raise AssertionError("the native kernel rejects its steps itself")  # pragma: no cover

    def write_dense(self, store: SampleStore, i: int, rows: np.ndarray, theta: float, h: float, t_out: float) -> int:
        raise AssertionError("the native kernel writes its dense output itself")  # pragma: no cover


def store_arrays(store: SampleStore) -> tuple[np.ndarray, ...]:
    """The store's arrays as the engine takes them (the store may have grown since the last call)."""
    return store.T, store.Q, store.V, store.TAU, store.ENERGY, store.FLOWS, store.COUNTS


class NativeCore(Core):
    """A Core whose loop runs in the engine (see the module docstring); its kernel is a NativeKernel."""

    kernel: NativeKernel  # type: ignore[assignment]

    def __init__(self, **kwargs: Any):
        super().__init__(**kwargs)
        self.kernel.bind(self.control)
        self._budget = 64  # steps per engine call, adapted to take about BUDGET_SECONDS

    def advance(self, t_stop: float, *, max_steps: int | None = None) -> str:
        """Core.advance, in the engine: the same statuses, samples, counts and stops."""
        kernel, control, sampler, store = self.kernel, self.control, self.sampler, self.store
        tolerance = LANDING_FRACTION * control.scale(t_stop) if control.adaptive else 0.0
        every = 0 if sampler is None or sampler.every is None else sampler.every
        period = 0.0 if sampler is None or sampler.period is None else sampler.period
        taken = 0
        while True:
            limit = self._budget if max_steps is None else min(self._budget, max_steps - taken)
            state = kernel.state
            self._push(state)
            start = time.perf_counter()
            status, steps, need, stops = kernel.engine.advance(
                t_stop, limit, tolerance, sampler is not None, every, period, *store_arrays(store), state
            )
            elapsed = time.perf_counter() - start
            self._pull(state)
            taken += steps
            if steps:
                self._budget = max(16, min(1 << 20, int(self._budget * BUDGET_SECONDS / max(elapsed, 1e-6))))
            if stops:
                self._native_stops(stops)
            if status == _NEED_ROOM:
                store.room(need)
                continue
            reason = _STATUSES[status]
            if reason == STEPPED and (max_steps is None or taken < max_steps):
                continue  # the budget, not the caller's limit: Python runs here (signals), then the engine again
            return reason

    def _push(self, state: np.ndarray) -> None:
        """The core's state as the engine reads it (the driver may have recorded, stopped rows or set a time)."""
        store, sampler, control = self.store, self.sampler, self.control
        state[2:10] = (
            self.steps,
            self.rejected,
            self.evaluations,
            self.recorded,
            store.count,
            store.full,
            store.soft_capacity,
            sampler.next_output if sampler is not None else 1,
        )
        if isinstance(control, ConstantStep):
            state[10:13] = control.snapshot()
        else:
            state[12:16] = control.snapshot()

    def _pull(self, state: np.ndarray) -> None:
        store, sampler, control = self.store, self.sampler, self.control
        self.steps, self.rejected, self.evaluations = int(state[2]), int(state[3]), int(state[4])
        self.recorded = float(state[5])
        store.count, store.full = int(state[6]), bool(state[7])
        if sampler is not None:
            sampler.next_output = int(state[9])
        if isinstance(control, ConstantStep):
            control.restore((float(state[10]), int(state[11]), float(state[12])))
        else:
            control.restore((float(state[12]), float(state[13]), float(state[14]), bool(state[15])))

    def _native_stops(self, stops: list[tuple[Any, ...]]) -> None:
        """Rows the engine stopped (it already took them out of its running rows): their RowStop, frozen counts and
        last samples, as Core._note_stops and Core.stop record them."""
        for code, row, when, step, dof, count, added, steps, rejected, evaluations, h, minimum, error in stops:
            if code == _DIVERGED:
                status, message = "diverged", diverged_message(self.system, when, step, dof, self.dt_hint)
            else:
                status = "step_collapsed"
                norm = None if math.isnan(error) else error
                message = collapsed_message(self.system, when, step, h, minimum, norm)
            self.stops.append(RowStop(int(row), status, message, when, count + added - 1, bool(added)))
            self.stopped_counts[row] = (steps, rejected, evaluations)
            self.store.stop(np.array([row]), bool(added), count=count)
            keep = self.rows != row
            n = int(keep.sum())
            self.extra_evaluations[:n] = self.extra_evaluations[: len(keep)][keep]
            self._set_rows(self.rows[keep])
