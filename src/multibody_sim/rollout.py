"""Batched rollouts: many initial states, controllers or torque sequences at once, on one machine or on Ray.

The fixed-step explicit methods (every Runge–Kutta tableau, semi-implicit Euler) advance the whole batch
together: one ``pin.abaInParallel`` call per stage over a ``pin.ModelPool``, the stage arithmetic in a few
operations over the whole batch, configuration updates vectorised (vector coordinates by numpy, the other
joints by one Pinocchio ``integrate`` call over copies of them). Per element the arithmetic is simulate()'s:
the same BLAS calls (multi-term stage sums, the step's combination, the ledger's dot products), exact products
where a stage sum has one power-of-two coefficient (RK4's), the same Pinocchio calls; so a batch gives
``simulate()``'s samples bit for bit. One exception: the chart map of free-flyer, spherical and planar joints
(in the Runge–Kutta stages after the first) is the same series as simulate()'s but its products are summed over
the whole batch in another order (ConfigurationSpace.chart_rates), which can round differently by an ulp: there
the batch equals simulate() to round-off. Adaptive and implicit methods run element by element through
``simulate()``.
"""

from __future__ import annotations

import copy
import functools
import math
import time
import weakref
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pinocchio as pin

from .exceptions import InvalidArgumentError, SimulationError, SimulationInterrupted
from .integrators import Integrator, get_integrator
from .integrators.explicit_rk import EmbeddedRungeKutta, ExplicitRungeKutta
from .integrators.partitioned import SemiImplicitEuler
from .robot import Robot, real_array
from .simulation import (
    BLOWUP_FACTOR,
    ProgressBar,
    check_options,
    find_limit_violations,
    positive_number,
    run_metadata,
    simulate,
    split_records,
    stable_implicit_integrators,
    steps_per,
)
from .trajectory import ARRAYS, ConstraintRecord, LedgerEntry, LimitViolations, Trajectory

_RECORD_PARTS = ("force", "drift", "velocity_drift")  # a ConstraintRecord's arrays
_COUNTS = ("steps", "rejected_steps", "evaluations", "controller_calls", "saturated_controls")
_BACKENDS = ("local", "ray")
# numpy >= 2 has vecdot, which calls the same BLAS dot as `x @ y` on 1-D arrays (so the ledger's powers match
# simulate()'s bit for bit); the stacked matmul does the same on older numpy.
_vecdot = getattr(np, "vecdot", None)


def _rowdot(x: np.ndarray, y: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
    """Row-wise dot products, each computed exactly as ``x[i] @ y[i]``; written into `out` when given."""
    if _vecdot is not None:
        return _vecdot(x, y, out=out)
    dots = np.matmul(x[:, None, :], y[:, :, None])[:, 0, 0]
    if out is None:
        return dots
    out[...] = dots
    return out


@dataclass
class BatchTrajectory:
    """Samples of a batch of simulations: Trajectory's fields with a leading batch axis.

    Elements may stop early (``status[b] != "completed"``) or, with adaptive methods, take different numbers of
    samples, so element b's real samples are the first ``n_samples[b]``; the rows after them repeat its last
    sample (time included), so every array is finite and each element's curves stay plottable. ``mask`` marks
    the real samples and ``element(b)`` gives element b as the Trajectory ``simulate()`` would have returned.
    An element with no sample at all (its initial energy overflowed) holds its initial state with zero energies.

    Attributes:
        t: sample times [s], shape (B, N).
        q: configurations, shape (B, N, nq).
        v: velocities, shape (B, N, nv).
        tau: torque applied from each sample to the next [N·m, N], shape (B, N, nv).
        kinetic_energy, potential_energy, total_energy, work, dissipated, energy_error: [J], shape (B, N);
            as in Trajectory.
        n_samples: number of real samples of each element, shape (B,).
        status: "completed" or why each element stopped ("diverged", ...), shape (B,).
        messages: why each element stopped, as simulate()'s SimulationError would say ("" when completed).
        ledger: per-element breakdown of work and dissipated (and a scene's spring potentials), each
            LedgerEntry's energy of shape (B, N).
        constraints: a scene's holonomic constraints, as in Trajectory: each ConstraintRecord's force of shape
            (B, N, rows), drift and velocity_drift of shape (B, N) (empty for a robot alone).
        limit_violations: position-limit violations of each element, length B.
        stats: per-element counts as arrays of shape (B,): steps, rejected_steps, evaluations,
            controller_calls, saturated_controls; saturated_dofs, shape (B, nv); and wall_time [s] of the
            whole batch (a float).
        metadata: package versions, robot, integrator, options, controller, backend.
    """

    t: np.ndarray
    q: np.ndarray
    v: np.ndarray
    tau: np.ndarray
    kinetic_energy: np.ndarray
    potential_energy: np.ndarray
    total_energy: np.ndarray
    work: np.ndarray
    dissipated: np.ndarray
    energy_error: np.ndarray
    n_samples: np.ndarray
    status: np.ndarray
    messages: list[str]
    ledger: dict[str, LedgerEntry] = field(default_factory=dict)
    limit_violations: list[LimitViolations] = field(default_factory=list)
    stats: dict[str, Any] = field(default_factory=dict)
    metadata: dict[str, Any] = field(default_factory=dict)
    constraints: dict[str, ConstraintRecord] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.n_samples)

    def __repr__(self) -> str:
        names, counts = np.unique(self.status, return_counts=True)
        statuses = ", ".join(f"{n} {s}" for s, n in zip(names.tolist(), counts.tolist(), strict=True))
        return f"<BatchTrajectory {len(self)} elements, up to {self.t.shape[1]} samples each: {statuses}>"

    @property
    def mask(self) -> np.ndarray:
        """True at the real samples, shape (B, N)."""
        return np.arange(self.t.shape[1]) < self.n_samples[:, None]

    @property
    def completed(self) -> np.ndarray:
        """Which elements reached the duration, shape (B,)."""
        return self.status == "completed"

    def element(self, b: int) -> Trajectory:
        """Element b as a Trajectory (its real samples only); ``stats["wall_time"]`` is its share of the batch's."""
        if not -len(self) <= b < len(self):
            raise IndexError(f"element {b} out of range for a batch of {len(self)}")
        n = int(self.n_samples[b])
        arrays = {name: getattr(self, name)[b, :n].copy() for name in ARRAYS}
        dof_names = self.metadata.get("robot", {}).get("dof_names", [])
        saturated = self.stats["saturated_dofs"][b]
        stats: dict[str, Any] = {name: int(self.stats[name][b]) for name in _COUNTS}
        stats["saturated_dofs"] = {dof_names[i]: int(c) for i, c in enumerate(saturated) if c}
        stats["wall_time"] = self.stats["wall_time"] / len(self)
        return Trajectory(
            **arrays,
            ledger={name: LedgerEntry(e.kind, e.energy[b, :n].copy()) for name, e in self.ledger.items()},
            constraints={
                name: ConstraintRecord(*(getattr(r, part)[b, :n].copy() for part in _RECORD_PARTS))
                for name, r in self.constraints.items()
            },
            limit_violations=self.limit_violations[b],
            stats=stats,
            status=str(self.status[b]),
            metadata={**self.metadata, "element": b % len(self)},
        )

    def summary(self) -> str:
        """A few lines for people: statuses, cost, and the worst elements."""
        names, counts = np.unique(self.status, return_counts=True)
        wall = self.stats.get("wall_time", math.nan)
        steps = int(np.sum(self.stats["steps"]))
        lines = [
            f"{len(self)} elements: " + ", ".join(f"{n} {s}" for s, n in zip(names, counts, strict=True)),
            f"steps: {steps} in total  wall time: {wall:.3f} s  ({wall / max(steps, 1) * 1e6:.2f} µs per element-step)",
        ]
        last = np.take_along_axis(np.abs(self.energy_error), np.maximum(self.n_samples - 1, 0)[:, None], 1)[:, 0]
        lines.append(f"largest final |energy_error|: {float(np.max(last)) if len(last) else 0.0:.3e} J")
        stopped = np.flatnonzero(~self.completed)
        for b in stopped[:3]:
            lines.append(f"element {b}: {self.messages[b]}")
        if len(stopped) > 3:
            lines.append(f"... and {len(stopped) - 3} more stopped early")
        violating = sum(1 for lv in self.limit_violations if lv.count)
        if violating:
            lines.append(f"{violating} elements violated position limits")
        return "\n".join(lines)


# ---- the public entry point --------------------------------------------------------------------------------
def rollout(
    system: Robot,
    q0s: Any,
    v0s: Any,
    *,
    duration: float,
    dt: float,
    integrator: str | Integrator = "rk4",
    controller: Any = None,
    taus: Any = None,
    progress: bool | None = None,
    backend: str = "local",
    num_threads: int = 1,
    chunk_size: int | None = None,
    **options: Any,
) -> BatchTrajectory:
    """Simulate a batch of initial states (with controllers or open-loop torques) for `duration` seconds.

    Each element gets the samples ``simulate(system, q0s[b], v0s[b], ...)`` would return: bit for bit on the
    local backend, but to round-off on free-flyer, spherical and planar joints with multi-stage methods (their
    chart map's products are summed over the batch in another order); an element that stops early keeps its
    samples and its status, and never stops the others.

    Args:
        system: the robot (or scene).
        q0s: initial configurations, shape (B, nq).
        v0s: initial velocities, shape (B, nv).
        duration: simulated time [s], > 0.
        dt: integration step [s], > 0 (adaptive methods: the first trial step).
        integrator: a registry name or an Integrator. The fixed-step explicit methods run batched; the others
            run element by element through simulate().
        controller: one of: a per-state callable ``(t, q, v) -> tau`` used by every element (an object with a
            ``reset()`` method holds state: each element gets its own deep copy, reset before the run); a
            sequence of B such callables, one per element (parameter sweeps); or a batched controller, an
            object with ``batched = True`` called as ``(t, Q (n, nq), V (n, nv)) -> (n, nv)`` on the elements
            still running (its rows must not depend on one another: adaptive and implicit methods call it one
            row at a time, and Ray on chunks of the batch). Controllers with ``reset()`` are reset before the
            run, as simulate() does. None applies no torque.
        taus: open-loop torques, shape (B, n_control, nv), exclusive with `controller`: ``taus[b, j]`` is held
            from the j-th control instant (every ``control_dt``, default every step) to the next; n_control is
            the number of control instants in the run (adaptive methods need ``control_dt``). Torques beyond
            the URDF's effort limits are clipped and counted, as controller outputs are.
        progress: a tqdm progress bar: None shows one on a terminal for runs longer than a second, True always,
            False never.
        backend: "local" (this process) or "ray" (chunks of the batch as Ray tasks on the cluster that
            ``ray.init`` connected to; ``pip install 'multibody-sim[ray]'``).
        num_threads: threads of Pinocchio's abaInParallel on the local backend (each Ray task uses 1).
        chunk_size: elements per Ray task (default: the batch split into two chunks per CPU of the cluster).
        **options: simulate()'s options: ``output_dt``, ``control_dt``; adaptive methods also ``rtol``,
            ``atol``, ``max_step``.

    Returns:
        The batch's samples, statuses and stats.

    Raises:
        InvalidArgumentError: a bad argument or option, or a controller output that is not a torque.
        SimulationInterrupted: Ctrl-C; ``.trajectory`` holds the BatchTrajectory so far (interrupted elements
            have status "interrupted"; on Ray it is None: the unfinished chunks are cancelled).
    """
    method = get_integrator(integrator)
    check_options(method, options)
    Q0, V0 = _check_batch(system, q0s, v0s)
    B = len(Q0)
    duration = positive_number(duration, "duration")
    dt = positive_number(dt, "dt")
    if backend not in _BACKENDS:
        raise InvalidArgumentError(f"backend must be one of {', '.join(_BACKENDS)}, got {backend!r}")
    if isinstance(num_threads, bool) or not isinstance(num_threads, (int, np.integer)) or num_threads < 1:
        raise InvalidArgumentError(f"num_threads must be a positive whole number, got {num_threads!r}")
    if chunk_size is not None and (
        isinstance(chunk_size, bool) or not isinstance(chunk_size, (int, np.integer)) or chunk_size < 1
    ):
        raise InvalidArgumentError(f"chunk_size must be a positive whole number of elements, got {chunk_size!r}")
    if progress is not None and not isinstance(progress, bool):
        raise InvalidArgumentError(f"progress must be True, False or None, got {progress!r}")
    method.check_system(system)
    control = _Control.build(system, method, controller, taus, B, duration, dt, options)
    if backend == "ray":
        return _ray_rollout(system, Q0, V0, duration, dt, method, control, progress, chunk_size, options)
    bar = ProgressBar(progress, B, "element", "rollout")
    start = time.perf_counter()
    try:
        if _batchable(system, method):
            runner = _BatchedRun(system, method, Q0, V0, duration, dt, control, options, num_threads, bar)
            return runner.execute(start)
        return _element_by_element(system, method, Q0, V0, duration, dt, control, options, bar, start)
    finally:
        bar.close()


def _check_batch(system: Robot, q0s: Any, v0s: Any) -> tuple[np.ndarray, np.ndarray]:
    Q0 = _as_batch(q0s, system.nq, "q0s")
    V0 = _as_batch(v0s, system.nv, "v0s")
    if len(Q0) != len(V0):
        raise InvalidArgumentError(f"q0s and v0s must hold as many states, got {len(Q0)} and {len(V0)}")
    if not len(Q0):
        raise InvalidArgumentError("q0s must hold at least one state, got an empty batch")
    if any(joint.nq != joint.nv for joint in system.model.joints[1:]):  # vector spaces need no unit norms
        is_normalized = system.space.is_normalized  # unit quaternions and (cos, sin) pairs (Q0 is finite)
        for b, q in enumerate(Q0):
            if not is_normalized(q):
                system.check_q(q, f"q0s[{b}]")  # raises, with check_q's message
    return Q0, V0


def _as_batch(value: Any, size: int, name: str) -> np.ndarray:
    arr = real_array(value, name, f"an array of real numbers of shape (B, {size})")
    if arr.ndim != 2 or arr.shape[1] != size:
        raise InvalidArgumentError(f"{name} must have shape (B, {size}), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        rows = np.flatnonzero(~np.isfinite(arr).all(axis=1)).tolist()
        raise InvalidArgumentError(f"{name} must be finite, got non-finite entries in rows {rows}")
    return arr


def _batchable(system: Any, method: Integrator) -> bool:
    """Whether the batched path reproduces simulate() here: a plain Robot and a fixed-step explicit method."""
    if type(system) is not Robot:  # a scene (or a subclass) may have other dynamics or ledger elements
        return False
    if isinstance(method, EmbeddedRungeKutta) or method.adaptive or method.implicit:
        return False
    if type(method) is SemiImplicitEuler:
        return True
    return isinstance(method, ExplicitRungeKutta) and type(method).step is ExplicitRungeKutta.step


# ---- controllers, open-loop torques and saturation ------------------------------------------------------------
class _Control:
    """Where each element's torque comes from, checked and saturated as simulate() does."""

    def __init__(
        self,
        effort: np.ndarray | None,
        kind: str,
        per_element: list[Any] | None = None,
        batched: Any = None,
        taus: np.ndarray | None = None,
        period: float | None = None,
        label: str | None = None,
    ):
        self.effort = effort  # |tau| bounds where the URDF gives any, else None (no clipping)
        self.kind = kind  # "none", "per_element", "batched", "taus"
        self.per_element = per_element
        self.batched = batched
        self.taus = taus
        self.period = period  # the control period [s] of taus (element-by-element methods)
        self.label = label

    @classmethod
    def build(
        cls,
        system: Robot,
        method: Integrator,
        controller: Any,
        taus: Any,
        B: int,
        duration: float,
        dt: float,
        options: dict[str, Any],
    ) -> _Control:
        if controller is not None and taus is not None:
            raise InvalidArgumentError("controller and taus are exclusive: pass one of them")
        effort = system.effort_limit if np.isfinite(system.effort_limit).any() else None
        if taus is not None:
            n_control, period = _control_instants(method, duration, dt, options)
            return cls(effort, "taus", taus=_check_taus(system, taus, B, n_control), period=period, label="taus")
        if controller is None:
            return cls(effort, "none")
        if getattr(controller, "batched", False) is True:
            if not callable(controller):
                raise InvalidArgumentError(
                    f"a batched controller must be callable as controller(t, Q, V), got {type(controller).__name__}"
                )
            if callable(getattr(controller, "reset", None)):
                controller.reset()  # as simulate() does: a run starts afresh
            return cls(effort, "batched", batched=controller, label=_name(controller))
        if callable(controller):
            if callable(getattr(controller, "reset", None)):
                # Internal state must not leak between elements: one copy each (the robot and its model are shared;
                # the copies are discarded at the end: pass a sequence of controllers to keep each element's).
                shared = {id(system): system, id(system.model): system.model}
                per_element = [copy.deepcopy(controller, dict(shared)) for _ in range(B)]
                for c in per_element:
                    c.reset()
            else:
                per_element = [controller] * B
            return cls(effort, "per_element", per_element=per_element, label=_name(controller))
        if isinstance(controller, Sequence) and not isinstance(controller, (str, bytes)):
            if len(controller) != B:
                raise InvalidArgumentError(
                    f"controller as a sequence must hold one controller per element ({B}), got {len(controller)}"
                )
            for b, c in enumerate(controller):
                if not callable(c):
                    raise InvalidArgumentError(
                        f"controller[{b}] must be callable as controller(t, q, v), got {type(c).__name__}"
                    )
            for c in {id(c): c for c in controller}.values():
                if callable(getattr(c, "reset", None)):
                    c.reset()  # as simulate() does: every run starts afresh
            return cls(effort, "per_element", per_element=list(controller), label=_name(controller[0]) + ", ...")
        raise InvalidArgumentError(
            "controller must be callable as controller(t, q, v), a sequence of such callables, or a batched "
            f"controller (batched = True), got {type(controller).__name__}"
        )

    def subset(self, rows: np.ndarray) -> _Control:
        """The same control for the elements `rows` only (Ray chunks)."""
        per_element = [self.per_element[b] for b in rows] if self.per_element is not None else None
        taus = self.taus[rows] if self.taus is not None else None
        return _Control(self.effort, self.kind, per_element, self.batched, taus, self.period, self.label)

    def element_controller(self, b: int) -> Any:
        """Element b's controller as simulate() takes it (a callable or None)."""
        if self.kind == "per_element":
            assert self.per_element is not None
            return self.per_element[b]
        if self.kind == "batched":
            return _OneRow(self.batched)
        if self.kind == "taus":
            assert self.taus is not None and self.period is not None
            return _OpenLoop(self.taus[b], self.period)
        return None

    def saturate(self, tau: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(clipped torques, which entries were over the limits), rows of shape (n, nv)."""
        if self.effort is None:
            return tau, np.zeros(tau.shape, dtype=bool)
        over = np.abs(tau) > self.effort
        if over.any():
            tau = np.clip(tau, -self.effort, self.effort)
        return tau, over


def _name(controller: Any) -> str:
    return str(getattr(controller, "__qualname__", type(controller).__qualname__))


def _control_instants(method: Integrator, duration: float, dt: float, options: dict[str, Any]) -> tuple[int, float]:
    """(number of control instants, control period [s]) of a run, for open-loop torque sequences."""
    if method.adaptive:
        if options.get("control_dt") is None:
            raise InvalidArgumentError(
                f"taus with the adaptive integrator '{method.name}' need control_dt (the period of the torque sequence)"
            )
        period = positive_number(options["control_dt"], "control_dt")
        return max(1, math.ceil(duration / period - 1e-9)), period
    every = steps_per(options.get("control_dt"), dt, "control_dt")
    n_steps = _n_steps(duration, dt)
    return -(-n_steps // every), every * dt


def _n_steps(duration: float, dt: float) -> int:
    # As simulate(): never count a last sliver of round-off as a step (1.0 / 0.1 is 10 steps, not 11).
    return max(1, math.ceil(duration / dt - 1e-9))


def _check_taus(system: Robot, taus: Any, B: int, n_control: int) -> np.ndarray:
    got = f"dtype {taus.dtype}" if isinstance(taus, np.ndarray) else type(taus).__name__
    try:
        raw = np.asarray(taus)
    except ValueError:
        raw = None
    if raw is None or raw.dtype.kind not in "biuf":
        raise InvalidArgumentError(f"taus must be an array of real numbers, got {got}")
    arr = np.array(raw, dtype=float)
    if arr.shape != (B, n_control, system.nv):
        raise InvalidArgumentError(
            f"taus must have shape ({B}, {n_control}, {system.nv}) (elements, control instants, nv), got {arr.shape}"
        )
    if not np.all(np.isfinite(arr)):
        raise InvalidArgumentError("taus must be finite")
    if system.floating_base and np.any(arr[:, :, :6]):
        raise InvalidArgumentError("taus[:, :, 0:6] act on the unactuated floating base and must be zero")
    return arr


class _OpenLoop:
    """One element's torque sequence as a controller: the row of the control instant t falls on."""

    def __init__(self, taus: np.ndarray, period: float):
        self.taus, self.period = taus, period
        self.__qualname__ = "taus"

    def __call__(self, t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        j = min(round(t / self.period), len(self.taus) - 1)
        return self.taus[j].copy()


class _OneRow:
    """A batched controller called on one state (for the element-by-element methods)."""

    def __init__(self, batched: Any):
        self.batched = batched
        self.__qualname__ = _name(batched)

    def __call__(self, t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        out = self.batched(t, q[None, :], v[None, :])
        shape = np.shape(out)
        if shape != (1, len(v)):
            raise InvalidArgumentError(
                f"batched controller output at t = {t:.6g} s must have shape (1, {len(v)}), got {shape}"
            )
        return np.asarray(out)[0]


class _BatchSpace:
    """The configuration manifold over a batch: q ⊕ dv for n rows at once.

    Coordinates of joints whose configuration is a vector (revolute, prismatic: Pinocchio's integrate is
    q + dv there, checked) are added in one numpy operation per run of them; the other joints (free-flyer,
    spherical, continuous, planar) go through one ``pin.integrate`` call on a model made of n copies of just
    those joints: Pinocchio's own per-joint code, so its results bit for bit, in one C++ loop. (The chart map needs no
    batch version: ConfigurationSpace.chart_rates takes many rows.)
    """

    def __init__(self, system: Robot):
        model = system.model
        self.model = model
        self.nq, self.nv = model.nq, model.nv
        runs: list[list[int]] = []  # [q start, v start, length] of consecutive vector-coordinate joints
        lie: list[Any] = []
        lie_q: list[int] = []
        lie_v: list[int] = []
        for joint in model.joints[1:]:
            if joint.nq == joint.nv:
                if joint.nq == 0:
                    continue
                last = runs[-1] if runs else None
                if last is not None and last[0] + last[2] == joint.idx_q and last[1] + last[2] == joint.idx_v:
                    last[2] += joint.nq
                else:
                    runs.append([joint.idx_q, joint.idx_v, joint.nq])
            else:
                lie.append(joint)
                lie_q += range(joint.idx_q, joint.idx_q + joint.nq)
                lie_v += range(joint.idx_v, joint.idx_v + joint.nv)
        self.runs = [(q, v, n) for q, v, n in runs]
        self.lie_joints = lie
        self.lie_q, self.lie_v = _indexer(lie_q), _indexer(lie_v)
        self._lie_models: dict[int, pin.Model] = {}
        self.per_element = not self._check_integrate()
        self.vector_space = not lie and self.runs == [(0, 0, model.nq)] and not self.per_element
        # Whether every vector coordinate sits nq - nv columns after its velocity (the other joints come first,
        # as a floating base does): then q's vector coordinates and v line up with the stage rates' row under
        # one offset, as on a vector space (see _rk_step).
        extra = model.nq - model.nv
        self.aligned = not self.per_element and all(q - v == extra for q, v, _ in self.runs)

    def _check_integrate(self) -> bool:
        """Whether the vectorised integrate gives pin.integrate's results bit for bit on this model (a few random
        rows): vector coordinates must really be q + dv, and the copies-of-joints model must act as the original."""
        model = self.model
        rng = np.random.default_rng(0)
        rows = 3
        Q = np.array([pin.integrate(model, pin.neutral(model), rng.uniform(-3.0, 3.0, model.nv)) for _ in range(rows)])
        DV = rng.normal(size=(rows, model.nv)) * 10.0 ** rng.uniform(-8, 1, (rows, model.nv))
        out = np.empty_like(Q)
        self._vectorised_integrate(Q, DV, out)
        return all(np.array_equal(out[b], pin.integrate(model, Q[b], DV[b])) for b in range(rows))

    def _lie_model(self, n: int) -> pin.Model:
        model = self._lie_models.get(n)
        if model is None:
            if len(self._lie_models) >= _LIE_MODELS_KEPT:  # batches shrink as elements stop: keep the latest
                del self._lie_models[next(iter(self._lie_models))]
            model = pin.Model()
            for b in range(n):
                for j, joint in enumerate(self.lie_joints):
                    model.addJoint(0, joint, pin.SE3.Identity(), f"element{b}_joint{j}")
            self._lie_models[n] = model
        return model

    def integrate(self, Q: np.ndarray, DV: np.ndarray, out: np.ndarray) -> None:
        """out = Q ⊕ DV row by row, as pin.integrate; shapes (n, nq), (n, nv), (n, nq)."""
        if self.vector_space:
            np.add(Q, DV, out=out)
        elif self.per_element:
            model = self.model
            for j in range(len(Q)):
                out[j] = pin.integrate(model, Q[j], DV[j])
        else:
            self._vectorised_integrate(Q, DV, out)

    def _vectorised_integrate(self, Q: np.ndarray, DV: np.ndarray, out: np.ndarray) -> None:
        for q, v, n in self.runs:
            np.add(Q[:, q : q + n], DV[:, v : v + n], out=out[:, q : q + n])
        if self.lie_joints:
            self.integrate_lie(self.lie_coordinates(Q), DV, out)

    def lie_coordinates(self, Q: np.ndarray) -> np.ndarray:
        """The coordinates of Q's non-vector joints, flat and contiguous: integrate_lie's argument."""
        return np.ascontiguousarray(Q[:, self.lie_q]).reshape(-1)

    def integrate_lie(self, q_lie: np.ndarray, DV: np.ndarray, out: np.ndarray) -> None:
        """The non-vector joints' columns of out = Q ⊕ DV, from q_lie = lie_coordinates(Q); DV (n, nv)."""
        n = len(DV)
        dv = np.ascontiguousarray(DV[:, self.lie_v]).reshape(-1)
        out[:, self.lie_q] = pin.integrate(self._lie_model(n), q_lie, dv).reshape(n, -1)


# Set-up shared by the rollout calls on one robot (the bit-for-bit check of the vectorised integrate, and the
# copies-of-joints models: about a millisecond per call on solo12), kept while the robot lives.
_BATCH_SPACES: weakref.WeakKeyDictionary[Robot, _BatchSpace] = weakref.WeakKeyDictionary()
_LIE_MODELS_KEPT = 8  # copies-of-joints models kept per robot, one per batch size


def _batch_space(system: Robot) -> _BatchSpace:
    space = _BATCH_SPACES.get(system)
    if space is None:
        space = _BATCH_SPACES[system] = _BatchSpace(system)
    return space


def _indexer(indices: list[int]) -> slice | np.ndarray:
    """Column indices as a slice when they are consecutive (a view and a fast copy), else as an index array."""
    if indices and indices == list(range(indices[0], indices[-1] + 1)):
        return slice(indices[0], indices[-1] + 1)
    return np.array(indices, dtype=int)


def _exact_power_of_two(c: float) -> bool:
    """Whether multiplying by c is exact (c = ±2^k): then (c K) h == K (c h) bit for bit."""
    return c != 0.0 and math.frexp(c)[0] in (0.5, -0.5)


class _Views:
    """Named views into one stage buffer W of shape (stages, n, width): W[i] is stage i's rows
    [q | v | xi' (curved charts only) | v' | ledger power], one contiguous block per stage; W[0] holds the state
    the step starts from. K, the stage derivatives (xi', v', ledger power) of each element, is a (n, stages, m)
    view whose per-element blocks the BLAS calls read as ExplicitRungeKutta's K."""

    def __init__(self, W: np.ndarray, layout: _Layout, tau_effective: np.ndarray, num_threads: int, pool: Any):
        nq, nv, k, shift = layout.nq, layout.nv, layout.k, layout.shift
        stages = range(len(W))
        self.W = W
        self.flat = [W[i].reshape(-1) for i in stages]
        # Flat views offset by `shift`: head[i][x] and tail[j][x] are the same element's column of stage i's state
        # [q | v] and the matching column of stage j's K (see _rk_step).
        self.head = [f[: len(f) - shift] for f in self.flat]
        self.tail = [f[shift:] for f in self.flat]
        self.X = W[0][:, : nq + nv]  # the state [q | v]
        self.Q = W[0][:, :nq]
        self.V = W[0][:, nq : nq + nv]
        self.K = W[:, :, k:].transpose(1, 0, 2)
        self.Ks = [W[i][:, k:] for i in stages]
        self.Xs = [W[i][:, : nq + nv] for i in stages]
        self.Qs = [W[i][:, :nq] for i in stages]
        self.Vs = [W[i][:, nq : nq + nv] for i in stages]
        self.XI_DOT = [W[i][:, k : k + nv] for i in stages]
        self.A = [W[i][:, k + nv : k + 2 * nv] for i in stages]
        self.P = [[W[i][:, k + 2 * nv + e] for e in range(layout.n_ledger)] for i in stages]
        # Column-major (nq, n) views of row-major (n, nq) arrays: abaInParallel reads and writes them in place.
        self.aba = [
            functools.partial(
                pin.abaInParallel, num_threads, pool, self.Qs[i].T, self.Vs[i].T, tau_effective.T, self.A[i].T
            )
            for i in stages
        ]
        self.flows = np.zeros((W.shape[1], layout.n_ledger))
        self._rows: tuple[list[np.ndarray], list[np.ndarray]] | None = None

    @property
    def rows(self) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """One view of q and of v per element (made once: per-element calls need no new ones per sample)."""
        if self._rows is None:
            self._rows = list(self.Q), list(self.V)
        return self._rows


@dataclass(frozen=True)
class _Layout:
    """Column layout of the stage buffers (see _Views)."""

    nq: int
    nv: int
    n_ledger: int
    stages: int
    k: int  # first column of K: v itself (the chart rate on flat spaces) or a separate xi' block

    @property
    def width(self) -> int:
        return self.k + 2 * self.nv + self.n_ledger

    @property
    def shift(self) -> int:
        """Flat offset from a vector coordinate of q (or v) to its rate in K, when the non-vector joints come
        first (each has nq - nv more coordinates than velocities)."""
        return self.k - (self.nq - self.nv)


class _BatchedRun:
    """simulate()'s fixed-step loop over a batch: the same arithmetic per element, vectorised over elements.

    Running elements are the rows of the working arrays; ``rows`` maps them to batch indices. An element that
    stops leaves the working arrays, and the others go on. The current state lives in stage 0 of one of two
    stage buffers and each step writes the next state into the other's, so a step allocates nothing and the
    previous state stays intact until the step is accepted; ``now = (buffer, t, k)`` switches in one assignment
    (a Ctrl-C never sees a state from one step with the time of another).

    Arithmetic, per element as ExplicitRungeKutta.step does it: a stage sum with one non-zero coefficient that is
    a power of two (RK4's, midpoint's) is one multiplication, exact as the BLAS call's (for stage values in the
    normal floating-point range; where a step's values become non-finite, which ones can differ, so a diverged
    element's message comes from simulate()'s own step); other stage sums and the step's combination go through
    the same BLAS call per element (a batched matmul); ABA through abaInParallel (WORLD convention, as
    Robot.unchecked_forward_dynamics); the ledger's dot products through the same BLAS dot.
    """

    def __init__(
        self,
        system: Robot,
        method: Integrator,
        Q0: np.ndarray,
        V0: np.ndarray,
        duration: float,
        dt: float,
        control: _Control,
        options: dict[str, Any],
        num_threads: int,
        bar: ProgressBar,
    ):
        self.system, self.method, self.control, self.options = system, method, control, options
        self.model, self.data = system.model, system.data
        self.duration, self.dt = duration, dt
        self.output_every = steps_per(options.get("output_dt"), dt, "output_dt")
        self.control_every = steps_per(options.get("control_dt"), dt, "control_dt")
        self.n_steps = _n_steps(duration, dt)
        self.num_threads = int(num_threads)
        self.pool = pin.ModelPool(system.model, self.num_threads)
        self.bar = bar
        B, nq, nv = len(Q0), system.nq, system.nv
        self.B, self.nq, self.nv = B, nq, nv
        self.elements = system.ledger_elements
        n_ledger = len(self.elements)
        self.is_work = np.array([kind == "work" for _, kind in self.elements])
        self.damping = system.damping if np.any(system.damping) else None
        # Without a controller or torques tau is zero: its power tau·v is zero too (for the finite states that
        # are kept), so the column stays at its initial zeros.
        self.torque_power = control.kind != "none"
        # With neither torques nor damping every ledger flow is zero (as simulate() finds it): none is computed.
        self.ledger_needed = self.torque_power or self.damping is not None
        self.space = _batch_space(system)
        self.chart_map = not system.space.is_flat
        self.sie = type(method) is SemiImplicitEuler
        if self.sie:
            stages = 1
        else:
            assert isinstance(method, ExplicitRungeKutta)
            a = method._a
            stages = len(a)
            self.stage_rules = [self._rule(a[i, :i]) for i in range(1, stages)]
            self.weights = method._b
            self.chart_terms = method.chart_terms  # the chart map's series, truncated as the method's step does
        self.layout = _Layout(nq, nv, n_ledger, stages, nq + nv if self.chart_map else nq)
        # (stage, source stage, coefficient) when every stage takes the fast path of _rk_step, else None
        self.shifted_stages: list[tuple[int, int, float]] | None = None
        if not self.sie and self.space.aligned and all(isinstance(r, tuple) for r in self.stage_rules):
            self.shifted_stages = [(i, r[0], r[1]) for i, r in enumerate(self.stage_rules, start=1)]  # type: ignore[index]
        # Samples: every output step, plus the final one (and an early stop's last state, which fits: see below).
        N = (self.n_steps - 1) // self.output_every + 2
        # Sample-major while recording (a sample of all rows is one contiguous block), batch-major in the result.
        self.out_t = np.zeros((N, B))
        self.out_q = np.empty((N, B, nq))
        self.out_v = np.empty((N, B, nv))
        self.out_tau = np.empty((N, B, nv))
        self.out_energy = np.zeros((N, B, 2))  # (T, V)
        self.out_flows = np.zeros((N, B, n_ledger))
        self.n_samples = np.zeros(B, dtype=int)
        self.status = np.full(B, "running", dtype=object)
        self.messages = [""] * B
        self.steps = np.zeros(B, dtype=int)
        self.evaluations = np.zeros(B, dtype=int)
        self.controller_calls = np.zeros(B, dtype=int)
        self.saturated_calls = np.zeros(B, dtype=int)
        self.saturated_dofs = np.zeros((B, nv), dtype=int)
        self.initial_energy = np.zeros((B, 2))  # (T, V) at t = 0
        self.initial_total = np.zeros(B)  # T + V at t = 0
        self.energy_scale = np.zeros(B)
        # The ledger as Robot has it: one work column first, then at most one dissipated one (their sums over
        # kinds are then the columns themselves, as simulate()'s one-element sums are).
        kinds = [kind for _, kind in self.elements]
        self.simple_ledger = kinds in (["work"], ["work", "dissipated"])
        self.stopped = False  # whether some rows stopped since the last _compact
        self.rows = np.arange(B)
        self.last_recorded = -math.inf
        self.initial_q, self.initial_v = Q0, V0  # for elements with no sample at all
        self._allocate(np.concatenate([Q0, V0], axis=1), np.zeros((B, nv)), np.zeros((B, n_ledger)), 0.0, 0)

    @staticmethod
    def _rule(coefficients: np.ndarray) -> tuple[int, float] | np.ndarray:
        """How stage i's sum Σ_j a_ij K_j is formed: (j, a_ij) when it has one term whose coefficient is a power
        of two (one exact multiplication gives the BLAS call's result), else the coefficients (the BLAS call)."""
        nonzero = np.flatnonzero(coefficients)
        if len(nonzero) == 1 and _exact_power_of_two(float(coefficients[nonzero[0]])):
            return int(nonzero[0]), float(coefficients[nonzero[0]])
        return coefficients

    def _allocate(self, X: np.ndarray, TAU: np.ndarray, flows: np.ndarray, t: float, k: int) -> None:
        """Working arrays for len(X) running elements, starting from states X = [q | v], torques and flows."""
        n, layout = len(X), self.layout
        self.TAU = TAU.copy()
        self.tau_effective = np.empty_like(self.TAU) if self.damping is not None else self.TAU
        self.damping_v = np.empty_like(self.TAU)  # D v of the latest stage
        self.Y = np.empty((n, layout.width - layout.k))  # a stage sum (when not shifted, see _rk_step)
        self.increment = np.zeros((n, layout.width))  # the step's increment in columns k: (0 before them)
        first, nv, shift, extra = layout.k, layout.nv, layout.shift, layout.nq - layout.nv
        self.increment_k, self.increment_flows = self.increment[:, first:], self.increment[:, first + 2 * nv :]
        self.increment_xi = self.increment[:, first : first + nv]
        self.increment_flat = self.increment.reshape(-1)
        self.increment_tail = self.increment_flat[shift:]
        # A stage's shifted product, whose rows hold c h K_j with its xi' block in columns extra:extra + nv
        shifted = np.empty(n * layout.width)
        self.shifted = shifted[: max(0, len(shifted) - shift)]
        self.shifted_xi = shifted.reshape(n, layout.width)[:, extra : extra + nv]
        self.views = [
            _Views(np.zeros((layout.stages, n, layout.width)), layout, self.tau_effective, self.num_threads, self.pool)
            for _ in range(2)
        ]
        self.views[0].X[...] = X
        self.views[0].flows[...] = flows
        self.now = (0, t, k)

    @property
    def current(self) -> _Views:
        """The buffer holding the running elements' latest accepted state (Q, V, flows)."""
        return self.views[self.now[0]]

    @property
    def t(self) -> float:
        return self.now[1]

    @property
    def k(self) -> int:
        return self.now[2]

    # ---- the loop --------------------------------------------------------------------------------------------
    def execute(self, start: float) -> BatchTrajectory:
        self.bar.reset(self.n_steps * self.B, "element-step")
        try:
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):  # divergence is reported, not warned
                self._loop()
        except KeyboardInterrupt:
            if len(self.rows):
                self._record_current(np.arange(len(self.rows)))
                self._stop(np.arange(len(self.rows)), "interrupted")
            batch = self._batch(time.perf_counter() - start)
            stopped = int(np.sum(batch.status == "interrupted"))
            raise SimulationInterrupted(
                f"interrupted at t = {self.t:.6g} s (step {self.k}); {stopped} of {self.B} elements were running",
                trajectory=batch,  # type: ignore[arg-type]
            ) from None
        return self._batch(time.perf_counter() - start)

    def _loop(self) -> None:
        dt, n_steps, control = self.dt, self.n_steps, self.control
        control_every, output_every = self.control_every, self.output_every
        step = self._sie_step if self.sie else self._rk_step
        tick = max(1, n_steps // 200)  # progress updates: cheap enough at ~200 per run
        for k in range(n_steps):
            t = k * dt
            if control.kind != "none" and k % control_every == 0:
                self._control(t, k // control_every)
            if k % output_every == 0:
                self._record(t, problems=True)
                if not len(self.rows):
                    return
            h = dt if k < n_steps - 1 else self.duration - t
            current = self.now[0]
            cur, nxt = self.views[current], self.views[1 - current]
            step(cur, nxt, h)
            # NaN or inf anywhere makes the whole sum non-finite (so can a huge but finite state, or the junk
            # beside the state in the buffer: the exact check below tells them apart). One contiguous reduction
            # over the new state's buffer block is far cheaper than per-row ones.
            stopped = False
            if not math.isfinite(nxt.flat[0].sum()):
                bad = np.flatnonzero(~np.isfinite(nxt.X).all(axis=1))
                if len(bad):
                    self._diverged_nonfinite(bad, t + h, h)
                    stopped = True
            self.now = (1 - current, t + h, k + 1)  # the step is accepted: one assignment switches state and time
            if stopped:
                self._compact()
                if not len(self.rows):
                    return
            if (k + 1) % tick == 0:
                self.bar.update(tick * len(self.rows))
        self.now = (self.now[0], self.duration, self.now[2])
        self._record(self.duration, problems=True)
        self._stop(np.arange(len(self.rows)), "completed")
        self.rows = self.rows[:0]

    def _rk_step(self, cur: _Views, nxt: _Views, h: float) -> None:
        """ExplicitRungeKutta.step on every row: stages into cur's buffer, the new state and flows into nxt's."""
        evaluate = self._evaluate
        if self.chart_map:  # at the step's start xi = 0, where the chart Jacobian is the identity
            np.copyto(cur.XI_DOT[0], cur.V)
        evaluate(cur, 0)
        if self.shifted_stages is not None:
            # Vector coordinates and stage sums of one exact product: [q | v] + c h [xi'_j | v'_j] for all rows in
            # two contiguous operations. On flat views a vector coordinate's rate in K_j sits `shift` entries after
            # it, so that offset lines every element up with its own (the columns after the state, and those of
            # the non-vector joints, receive junk, which the stage's chart map, dynamics, ledger and Pinocchio's
            # integrate overwrite, or which nothing reads).
            head0, shifted, space = cur.head[0], self.shifted, self.space
            q_lie = space.lie_coordinates(cur.Q) if space.lie_joints else None  # the stages' common base
            for i, j, coefficient in self.shifted_stages:
                np.add(head0, np.multiply(cur.tail[j], coefficient * h, out=shifted), out=cur.head[i])
                if q_lie is not None:  # xi = c h xi'_j: the product's own columns
                    space.integrate_lie(q_lie, self.shifted_xi, cur.Qs[i])
                    if self.chart_map:
                        self.system.space.chart_rates(self.shifted_xi, cur.Vs[i], self.chart_terms, cur.XI_DOT[i])
                evaluate(cur, i)
            # `(b @ K) * dt` with the same per-element BLAS call, into columns k: of a zeroed (n, width) buffer,
            # then the new [q | v] by the same offset addition.
            np.matmul(self.weights, cur.K, out=self.increment_k)
            np.multiply(self.increment_flat, h, out=self.increment_flat)
            np.add(head0, self.increment_tail, out=nxt.head[0])
            if q_lie is not None:
                space.integrate_lie(q_lie, self.increment_xi, nxt.Q)
            if self.ledger_needed:  # else every flow is zero (and the ledger columns of K hold junk)
                np.add(cur.flows, self.increment_flows, out=nxt.flows)
            return
        nv, K, space, k = self.nv, cur.K, self.space, self.layout.k
        system_space = self.system.space
        for i, rule in enumerate(self.stage_rules, start=1):
            if isinstance(rule, tuple):
                j, coefficient = rule
                Ys = np.multiply(cur.Ks[j], coefficient * h, out=self.Y)
            else:  # the same per-element BLAS call as ExplicitRungeKutta's `a[i, :i] @ K[:i]`, then `* h`
                Ys = np.multiply(np.matmul(rule, K[:, :i, :], out=self.Y), h, out=self.Y)
            if space.vector_space:
                np.add(cur.X, Ys[:, : 2 * nv], out=cur.Xs[i])
            else:
                np.add(cur.V, Ys[:, nv : 2 * nv], out=cur.Vs[i])
                space.integrate(cur.Q, Ys[:, :nv], cur.Qs[i])
                if self.chart_map:
                    system_space.chart_rates(Ys[:, :nv], cur.Vs[i], self.chart_terms, cur.XI_DOT[i])
            evaluate(cur, i)
        increment = self.increment
        np.matmul(self.weights, K, out=self.increment_k)  # `(b @ K) * dt` with the same per-element BLAS call
        np.multiply(self.increment_flat, h, out=self.increment_flat)
        if space.vector_space:
            np.add(cur.X, increment[:, k : k + 2 * nv], out=nxt.X)
        else:
            np.add(cur.V, increment[:, k + nv : k + 2 * nv], out=nxt.V)
            space.integrate(cur.Q, increment[:, k : k + nv], nxt.Q)
        if self.ledger_needed:  # else every flow is zero (and the ledger columns of K hold junk)
            np.add(cur.flows, self.increment_flows, out=nxt.flows)

    def _sie_step(self, cur: _Views, nxt: _Views, h: float) -> None:
        """SemiImplicitEuler.step on every row: v first, then q with the new v; the ledger at the new state."""
        nv = self.nv
        self._accelerations(cur, 0)
        np.add(cur.V, np.multiply(cur.A[0], h, out=cur.A[0]), out=nxt.V)
        self.space.integrate(cur.Q, np.multiply(nxt.V, h, out=self.Y[:, :nv]), nxt.Q)
        if self.ledger_needed:
            power = self.Y[:, nv : nv + len(self.elements)]
            self._ledger_power(nxt.V, [power[:, e] for e in range(len(self.elements))])
            np.add(cur.flows, np.multiply(power, h, out=power), out=nxt.flows)

    def _evaluate(self, cur: _Views, i: int) -> None:
        """Stage i's accelerations and ledger power (Robot.unchecked_forward_dynamics and ledger_power)."""
        if self.damping is not None:  # tau - D v, as Robot.unchecked_forward_dynamics
            np.subtract(self.TAU, np.multiply(self.damping, cur.Vs[i], out=self.damping_v), out=self.tau_effective)
        cur.aba[i]()
        if self.ledger_needed:
            self._ledger_power(cur.Vs[i], cur.P[i], damping_v_known=True)

    def _accelerations(self, cur: _Views, i: int) -> None:
        if self.damping is not None:  # tau - D v, as Robot.unchecked_forward_dynamics
            np.subtract(self.TAU, np.multiply(self.damping, cur.Vs[i], out=self.damping_v), out=self.tau_effective)
        cur.aba[i]()

    def _ledger_power(self, V: np.ndarray, out: list[np.ndarray], damping_v_known: bool = False) -> None:
        """Robot.ledger_power of every row: tau·v, then v·(D v), written into the columns `out`."""
        if not len(V):
            return
        if self.torque_power:
            _rowdot(self.TAU, V, out=out[0])
        else:  # zero torque, zero power (the column may hold junk: see _rk_step)
            out[0][...] = 0.0
        if self.damping is not None:
            if not damping_v_known:
                np.multiply(self.damping, V, out=self.damping_v)
            _rowdot(V, self.damping_v, out=out[1])

    # ---- control -------------------------------------------------------------------------------------------
    def _control(self, t: float, instant: int) -> None:
        control, rows, n, nv = self.control, self.rows, len(self.rows), self.nv
        system = self.system
        if control.kind == "taus":
            assert control.taus is not None
            tau = control.taus[rows, instant]
        elif control.kind == "batched":
            Q, V = self.current.Q.copy(), self.current.V.copy()
            Q.setflags(write=False)  # the controller sees the state; it must not edit it
            V.setflags(write=False)
            out = control.batched(t, Q, V)
            shape = np.shape(out)
            if shape != (n, nv):
                raise InvalidArgumentError(
                    f"batched controller output at t = {t:.6g} s must have shape ({n}, {nv}), got {shape}"
                )
            tau = np.array(out, dtype=float)
            suspect = ~np.isfinite(tau).all(axis=1) | (system.floating_base and tau[:, :6].any(axis=1))
            for i in np.flatnonzero(suspect).tolist():
                try:  # the full check, with the precise reason
                    system.check_tau(tau[i])
                except InvalidArgumentError as exc:
                    raise InvalidArgumentError(
                        f"batched controller output at t = {t:.6g} s, element {rows[i]}: {exc}"
                    ) from None
        else:
            assert control.per_element is not None
            tau = np.empty((n, nv))
            Qs, Vs = self.current.Q, self.current.V
            for j, row in enumerate(rows.tolist()):
                q, v = Qs[j].copy(), Vs[j].copy()
                q.setflags(write=False)
                v.setflags(write=False)
                out = control.per_element[row](t, q, v)
                fast = type(out) is np.ndarray and out.dtype == np.float64 and out.shape == (nv,)
                if not fast or not math.isfinite(out @ out) or (system.floating_base and out[:6].any()):
                    try:  # the full check, with the precise reason (as simulate's)
                        out = system.check_tau(out)
                    except InvalidArgumentError as exc:
                        raise InvalidArgumentError(f"controller output at t = {t:.6g} s: {exc}") from None
                tau[j] = out
        self.controller_calls[rows] += 1
        tau, over = control.saturate(tau)
        if control.effort is not None:
            hit = over.any(axis=1)
            self.saturated_calls[rows] += hit
            self.saturated_dofs[rows] += over
        self.TAU[...] = tau  # in place: the stage buffers' ABA arguments view this array

    # ---- recording and early stops ------------------------------------------------------------------------
    def _energies(self, Q: list[np.ndarray], V: list[np.ndarray]) -> np.ndarray:
        """(T, V) of every row (given as lists of row arrays) as Robot.unchecked_energies computes them, (n, 2)."""
        model, data = self.model, self.data
        kinetic, potential = pin.computeKineticEnergy, pin.computePotentialEnergy
        out = np.empty((len(Q), 2))
        # computeKineticEnergy(model, data, q, v) is forwardKinematics then the data-only call: the same
        # arithmetic in two Python calls instead of three.
        out.reshape(-1)[:] = [
            e for q, v in zip(Q, V, strict=True) for e in (kinetic(model, data, q, v), potential(model, data))
        ]
        return out

    def _record(self, t: float, *, problems: bool, which: np.ndarray | None = None) -> None:
        """Store a sample of the running rows `which` (default all) with the torque in force from t on; rows
        whose energy is non-finite or has blown up stop as "diverged" (when `problems`)."""
        cur = self.current
        if which is None:
            which = np.arange(len(self.rows))
            Q, V, flows, tau = cur.Q, cur.V, cur.flows, self.TAU
            energies = self._energies(*cur.rows)
        else:
            Q, V, flows, tau = cur.Q[which], cur.V[which], cur.flows[which], self.TAU[which]
            energies = self._energies(list(Q), list(V))
        rows = self.rows[which]
        total = energies.sum(axis=1)  # T + V, as simulate adds them
        if not math.isfinite(total.sum()):  # a huge state whose energy overflows: keep only finite samples
            finite = np.isfinite(total)
            bad = np.flatnonzero(~finite)
            if problems:
                for j in bad:
                    fastest = int(np.argmax(np.abs(V[j])))
                    self.messages[rows[j]] = (
                        f"diverged at t = {t:.6g} s (step {self.k}): the energy became non-finite, fastest in "
                        f"'{self.system.dof_names[fastest]}' ({V[j, fastest]:.3g}); {self._cure()}"
                    )
                self._stop(which[bad], "diverged")
            which, rows, energies, total = which[finite], rows[finite], energies[finite], total[finite]
            Q, V, flows, tau = Q[finite], V[finite], flows[finite], tau[finite]
        at = slice(None) if len(rows) == self.B else rows  # all rows: basic slicing, no gathers
        if t == 0.0:
            self.initial_energy[rows] = energies
            self.initial_total[rows] = total  # simulate's sum((T, V))
            self.energy_scale[rows] = energies[:, 0] + np.abs(energies[:, 1]) + self.system.energy_scale
        if len(rows):
            # Running elements have all recorded the same samples so far: one column for all of them.
            col = int(self.n_samples[rows[0]])
            self.out_t[col, at] = t
            self.out_q[col, at] = Q
            self.out_v[col, at] = V
            self.out_tau[col, at] = tau
            self.out_energy[col, at] = energies
            self.out_flows[col, at] = flows
            self.n_samples[at] += 1
        self.last_recorded = t
        if t == 0.0 or not problems:
            self._compact()
            return
        if self.simple_ledger:
            work = flows[:, 0]
            dissipated = flows[:, 1] if flows.shape[1] == 2 else None
        else:
            work = flows[:, self.is_work].sum(axis=1)
            dissipated = flows[:, ~self.is_work].sum(axis=1)
        # As simulate: error = T + V - (T0 + V0) - work + dissipated, and the bound leaves dissipation out (a run
        # can only dissipate what it had or was given).
        error = total - self.initial_total[at]
        error -= work
        if dissipated is not None:
            error += dissipated
        bound = self.energy_scale[at] + np.abs(work)
        bound *= BLOWUP_FACTOR
        blown = np.abs(error) > bound
        if dissipated is not None:
            blown |= dissipated > bound
        if blown.any():
            for j in np.flatnonzero(blown):
                fastest = int(np.argmax(np.abs(V[j])))
                what = (
                    f"the energy error {error[j]:.3g} J"
                    if abs(error[j]) > bound[j]
                    else f"the dissipated energy {dissipated[j]:.3g} J"  # type: ignore[index]
                )
                self.messages[rows[j]] = (
                    f"diverged at t = {t:.6g} s (step {self.k}): {what} exceeds {BLOWUP_FACTOR:g} times the run's "
                    f"energy scale ({bound[j] / BLOWUP_FACTOR:.3g} J), fastest in "
                    f"'{self.system.dof_names[fastest]}' ({V[j, fastest]:.3g}); {self._cure()}"
                )
            self._stop(which[blown], "diverged")
        self._compact()

    def _record_current(self, which: np.ndarray) -> None:
        """Keep the latest state of rows `which` as a last sample if it is not one already."""
        if self.last_recorded == self.t:
            return
        self._record(self.t, problems=False, which=which)

    def _diverged_nonfinite(self, bad: np.ndarray, t_next: float, h: float) -> None:
        """Stop rows `bad`, whose step from the current state ended non-finite, with simulate()'s message."""
        method, system = self.method, self.system
        Q, V, TAU = self.current.Q, self.current.V, self.TAU
        nxt = self.views[1 - self.now[0]]
        for j in bad:
            # The message names the first non-finite coordinate; which ones are NaN can depend on the order of
            # operations, so the element's step is redone exactly as simulate() does it.
            q_next, v_next, _ = method.step(system, Q[j].copy(), V[j].copy(), TAU[j].copy(), h)
            if np.isfinite(q_next).all() and np.isfinite(v_next).all():  # only ever by round-off: keep ours
                q_next, v_next = nxt.Q[j], nxt.V[j]
            bad_v = ~np.isfinite(v_next)
            if bad_v.any():
                dof = int(np.argmax(bad_v))
            else:
                finite_q = np.where(np.isfinite(q_next), q_next, 0.0)
                dof = int(np.argmax(~np.isfinite(system.space.difference(Q[j], finite_q))))
            self.messages[self.rows[j]] = (
                f"diverged at t = {t_next:.6g} s (step {self.k + 1}): the state became non-finite in "
                f"'{system.dof_names[dof]}'; {self._cure()}"
            )
        self._record_current(bad)
        self._stop(bad, "diverged", attempted=self.k + 1)  # the failed step's evaluations count too

    def _stop(self, which: np.ndarray, status: str, attempted: int | None = None) -> None:
        """Mark running rows `which` as stopped after self.k steps and `attempted` (default self.k) evaluated
        ones (they leave the working arrays at the next _compact)."""
        rows = self.rows[which]
        self.stopped = True
        self.status[rows] = status
        self.steps[rows] = self.k
        self.evaluations[rows] = self.method.evaluations_per_step * (self.k if attempted is None else attempted)

    def _compact(self) -> None:
        if not self.stopped:
            return
        self.stopped = False
        keep = self.status[self.rows] == "running"
        if keep.all():
            return
        self.rows = self.rows[keep]
        cur = self.views[self.now[0]]
        self._allocate(cur.X[keep], self.TAU[keep], cur.flows[keep], self.t, self.k)

    def _cure(self) -> str:
        implicit = stable_implicit_integrators(self.system)
        also = f", or an implicit integrator ({', '.join(implicit)})" if implicit else ""
        return f"try a smaller dt (now {self.dt:g} s){also}"

    # ---- the result ------------------------------------------------------------------------------------------
    def _batch(self, wall_time: float) -> BatchTrajectory:
        n = self.n_samples
        out_t, out_q, out_v, out_tau, energy, flows = (
            np.ascontiguousarray(np.swapaxes(a, 0, 1))
            for a in (self.out_t, self.out_q, self.out_v, self.out_tau, self.out_energy, self.out_flows)
        )
        kin, pot = energy[:, :, 0].copy(), energy[:, :, 1].copy()
        work = flows[:, :, self.is_work].sum(axis=2)
        dissipated = flows[:, :, ~self.is_work].sum(axis=2)
        total = kin + pot
        error = total - self.initial_energy.sum(axis=1)[:, None] - work + dissipated
        arrays = {
            "t": out_t,
            "q": out_q,
            "v": out_v,
            "tau": out_tau,
            "kinetic_energy": kin,
            "potential_energy": pot,
            "total_energy": total,
            "work": work,
            "dissipated": dissipated,
            "energy_error": error,
        }
        ledger = {name: LedgerEntry(kind, flows[:, :, j]) for j, (name, kind) in enumerate(self.elements)}
        _pad(arrays, ledger, n, self.initial_q, self.initial_v)
        violations = _batch_limit_violations(self.system, out_t, out_q, n)
        return BatchTrajectory(
            **arrays,
            n_samples=n.copy(),
            status=np.array([str(s) for s in self.status]),
            messages=list(self.messages),
            ledger=ledger,
            limit_violations=violations,
            stats={
                "steps": self.steps.copy(),
                "rejected_steps": np.zeros(self.B, dtype=int),
                "evaluations": self.evaluations.copy(),
                "controller_calls": self.controller_calls.copy(),
                "saturated_controls": self.saturated_calls.copy(),
                "saturated_dofs": self.saturated_dofs.copy(),
                "wall_time": wall_time,
            },
            metadata=_metadata(self.system, self.method, self.dt, self.duration, self.options, self.control, "local"),
        )


def _batch_limit_violations(system: Robot, T: np.ndarray, Q: np.ndarray, n: np.ndarray) -> list[LimitViolations]:
    """simulate()'s limit report of each element; one vectorised pass finds the elements that need one."""
    B, N, nq = Q.shape
    excess = system.limit_excess(Q.reshape(B * N, nq)).reshape(B, N, nq)
    outside = np.asarray(((excess > 0).any(axis=2) & (np.arange(N) < n[:, None])).any(axis=1), dtype=bool)
    none = LimitViolations()  # frozen: one instance serves every element without violations
    return [find_limit_violations(system, T[b, : n[b]], Q[b, : n[b]]) if outside[b] else none for b in range(B)]


def _pad(
    arrays: dict[str, np.ndarray], ledger: dict[str, LedgerEntry], n: np.ndarray, Q0: np.ndarray, V0: np.ndarray
) -> None:
    """Rows past each element's last sample repeat it (in place); an element with none holds its initial state."""
    width = arrays["t"].shape[1]
    for b in np.flatnonzero(n < width):
        last = n[b] - 1
        if last < 0:  # no sample at all: its initial state, zero energies and torque
            for arr in arrays.values():
                arr[b] = 0.0
            arrays["q"][b], arrays["v"][b] = Q0[b], V0[b]
            for entry in ledger.values():
                entry.energy[b] = 0.0
            continue
        for arr in arrays.values():
            arr[b, last + 1 :] = arr[b, last]
        for entry in ledger.values():
            entry.energy[b, last + 1 :] = entry.energy[b, last]


def _metadata(
    system: Robot,
    method: Integrator,
    dt: float,
    duration: float,
    options: dict[str, Any],
    control: _Control,
    backend: str,
) -> dict[str, Any]:
    return {
        **run_metadata(system),
        "integrator": method.name,
        "options": {"dt": dt, "duration": duration, **options},
        "controller": control.label,
        "backend": backend,
    }


# ---- element by element (adaptive and implicit methods, scenes) ------------------------------------------------
def _element_by_element(
    system: Robot,
    method: Integrator,
    Q0: np.ndarray,
    V0: np.ndarray,
    duration: float,
    dt: float,
    control: _Control,
    options: dict[str, Any],
    bar: ProgressBar,
    start: float,
) -> BatchTrajectory:
    trajectories: list[Trajectory] = []
    messages: list[str] = []
    bar.reset(len(Q0), "element")
    for b in range(len(Q0)):
        controller = control.element_controller(b)
        try:
            traj = simulate(
                system, Q0[b], V0[b], duration=duration, dt=dt, integrator=method, controller=controller, **options
            )
            message = ""
        except SimulationError as exc:
            assert exc.trajectory is not None
            traj, message = exc.trajectory, str(exc)
        except SimulationInterrupted as exc:
            assert exc.trajectory is not None
            trajectories.append(exc.trajectory)
            messages.append(str(exc))
            for rest in range(b + 1, len(Q0)):  # not run: their initial state, as their one sample
                trajectories.append(_initial_only(system, Q0[rest], V0[rest]))
                messages.append("interrupted before it started")
            batch = _stack(trajectories, messages, Q0, V0, time.perf_counter() - start)
            batch.metadata = _metadata(system, method, dt, duration, options, control, "local")
            raise SimulationInterrupted(
                f"interrupted in element {b} of {len(Q0)}; {str(exc)}",
                trajectory=batch,  # type: ignore[arg-type]
            ) from None
        trajectories.append(traj)
        messages.append(message)
        bar.update(1)
    batch = _stack(trajectories, messages, Q0, V0, time.perf_counter() - start)
    batch.metadata = _metadata(system, method, dt, duration, options, control, "local")
    return batch


def _initial_only(system: Robot, q0: np.ndarray, v0: np.ndarray) -> Trajectory:
    T, V = system.unchecked_energies(q0, v0)
    zero = np.zeros(1)
    extra = np.zeros((1, sum(width for _, _, width in system.record_fields)))
    system.unchecked_record(q0, v0, np.zeros(system.nv), 0.0, extra[0])  # a scene's springs and constraints
    potentials, constraints = split_records(system.record_fields, extra)
    return Trajectory(
        t=zero.copy(),
        q=q0[None, :].copy(),
        v=v0[None, :].copy(),
        tau=np.zeros((1, system.nv)),
        kinetic_energy=np.array([T]),
        potential_energy=np.array([V]),
        total_energy=np.array([T + V]),
        work=zero.copy(),
        dissipated=zero.copy(),
        energy_error=zero.copy(),
        ledger={**{name: LedgerEntry(kind, zero.copy()) for name, kind in system.ledger_elements}, **potentials},
        constraints=constraints,
        stats={"steps": 0, "rejected_steps": 0, "evaluations": 0, "controller_calls": 0, "saturated_controls": 0},
        status="interrupted",
    )


def _stack(
    trajectories: list[Trajectory], messages: list[str], Q0: np.ndarray, V0: np.ndarray, wall_time: float
) -> BatchTrajectory:
    """One BatchTrajectory from per-element Trajectories (padded as BatchTrajectory documents)."""
    B = len(trajectories)
    n = np.array([len(tr) for tr in trajectories], dtype=int)
    N = max(1, int(n.max()))
    first = trajectories[0]
    arrays: dict[str, Any] = {}
    for name in ARRAYS:
        shape = getattr(first, name).shape[1:]
        arr = np.zeros((B, N, *shape))
        for b, tr in enumerate(trajectories):
            arr[b, : n[b]] = getattr(tr, name)
        arrays[name] = arr
    ledger = {}
    for name, entry in first.ledger.items():
        energy = np.zeros((B, N))
        for b, tr in enumerate(trajectories):
            energy[b, : n[b]] = tr.ledger[name].energy
        ledger[name] = LedgerEntry(entry.kind, energy)
    # Each constraint's record: force (B, N, rows), drift and velocity drift (B, N), padded as the arrays are
    constraints = {}
    for name, record in first.constraints.items():
        parts = []
        for part in _RECORD_PARTS:
            arr = np.zeros((B, N, *getattr(record, part).shape[1:]))
            for b, tr in enumerate(trajectories):
                arr[b, : n[b]] = getattr(tr.constraints[name], part)
            parts.append(arr)
        constraints[name] = ConstraintRecord(*parts)
    records = {f"{name}.{part}": getattr(r, part) for name, r in constraints.items() for part in _RECORD_PARTS}
    _pad({**arrays, **records}, ledger, n, Q0, V0)  # (records keyed apart from the field names)
    nv = first.v.shape[1]
    dof_index = {name: i for i, name in enumerate(first.metadata.get("robot", {}).get("dof_names", []))}
    saturated = np.zeros((B, nv), dtype=int)
    for b, tr in enumerate(trajectories):
        for name, count in tr.stats.get("saturated_dofs", {}).items():
            saturated[b, dof_index[name]] = count
    stats: dict[str, Any] = {
        name: np.array([int(tr.stats.get(name, 0)) for tr in trajectories], dtype=int) for name in _COUNTS
    }
    stats["saturated_dofs"] = saturated
    stats["wall_time"] = wall_time
    return BatchTrajectory(
        **arrays,
        n_samples=n,
        status=np.array([tr.status for tr in trajectories]),
        messages=messages,
        ledger=ledger,
        constraints=constraints,
        limit_violations=[tr.limit_violations for tr in trajectories],
        stats=stats,
    )


def _concatenate(batches: list[BatchTrajectory], wall_time: float | None = None) -> BatchTrajectory:
    """One BatchTrajectory from several along the batch axis (e.g. Ray chunks), padding to the longest."""
    N = max(bt.t.shape[1] for bt in batches)

    def widen(arr: np.ndarray) -> np.ndarray:
        if arr.shape[1] == N:
            return arr
        # Repeat each element's last row (its last sample, or its padding) out to N.
        extra = np.repeat(arr[:, -1:], N - arr.shape[1], axis=1)
        return np.concatenate([arr, extra], axis=1)

    arrays = {name: np.concatenate([widen(getattr(bt, name)) for bt in batches]) for name in ARRAYS}
    ledger = {
        name: LedgerEntry(entry.kind, np.concatenate([widen(bt.ledger[name].energy) for bt in batches]))
        for name, entry in batches[0].ledger.items()
    }
    constraints = {
        name: ConstraintRecord(
            *(np.concatenate([widen(getattr(bt.constraints[name], part)) for bt in batches]) for part in _RECORD_PARTS)
        )
        for name in batches[0].constraints
    }
    stats: dict[str, Any] = {name: np.concatenate([bt.stats[name] for bt in batches]) for name in _COUNTS}
    stats["saturated_dofs"] = np.concatenate([bt.stats["saturated_dofs"] for bt in batches])
    stats["wall_time"] = wall_time if wall_time is not None else sum(bt.stats["wall_time"] for bt in batches)
    return BatchTrajectory(
        **arrays,
        n_samples=np.concatenate([bt.n_samples for bt in batches]),
        status=np.concatenate([bt.status for bt in batches]),
        messages=[m for bt in batches for m in bt.messages],
        ledger=ledger,
        constraints=constraints,
        limit_violations=[lv for bt in batches for lv in bt.limit_violations],
        stats=stats,
        metadata=dict(batches[0].metadata),
    )


# ---- Ray -----------------------------------------------------------------------------------------------------------
def _run_chunk(
    system: Robot,
    Q0: np.ndarray,
    V0: np.ndarray,
    duration: float,
    dt: float,
    method: Integrator,
    control: _Control,
    options: dict[str, Any],
) -> BatchTrajectory:
    """One Ray task: a local rollout of a chunk of the batch, with one thread."""
    bar = ProgressBar(False, len(Q0), "element", "rollout")
    start = time.perf_counter()
    if _batchable(system, method):
        return _BatchedRun(system, method, Q0, V0, duration, dt, control, options, 1, bar).execute(start)
    return _element_by_element(system, method, Q0, V0, duration, dt, control, options, bar, start)


_REMOTE: dict[str, Any] = {}


def _ray_rollout(
    system: Robot,
    Q0: np.ndarray,
    V0: np.ndarray,
    duration: float,
    dt: float,
    method: Integrator,
    control: _Control,
    progress: bool | None,
    chunk_size: int | None,
    options: dict[str, Any],
) -> BatchTrajectory:
    try:
        import ray
    except ImportError:
        raise InvalidArgumentError(
            "backend='ray' needs Ray: pip install 'multibody-sim[ray]' (then ray.init() to start or join a cluster)"
        ) from None
    start = time.perf_counter()
    if not ray.is_initialized():  # what Ray would do on the first task anyway: a local instance
        ray.init()
    B = len(Q0)
    if chunk_size is None:
        cpus = max(1, int(ray.cluster_resources().get("CPU", 1)))
        chunk_size = max(1, -(-B // (2 * cpus)))
    bounds = [(lo, min(lo + chunk_size, B)) for lo in range(0, B, chunk_size)]
    remote = _REMOTE.get("chunk")
    if remote is None:
        remote = _REMOTE["chunk"] = ray.remote(num_cpus=1)(_run_chunk)
    system_ref = ray.put(system)  # shipped once, shared by every task
    pending = {
        remote.remote(
            system_ref, Q0[lo:hi], V0[lo:hi], duration, dt, method, control.subset(np.arange(lo, hi)), options
        ): i
        for i, (lo, hi) in enumerate(bounds)
    }
    results: list[BatchTrajectory | None] = [None] * len(bounds)
    bar = ProgressBar(progress, B, "element", "rollout")
    try:
        while pending:
            done, _ = ray.wait(list(pending), num_returns=1)
            for ref in done:
                i = pending.pop(ref)
                results[i] = ray.get(ref)
                bar.update(bounds[i][1] - bounds[i][0])
    except KeyboardInterrupt:
        for ref in pending:
            ray.cancel(ref, force=True)
        done_chunks = sum(r is not None for r in results)
        raise SimulationInterrupted(
            f"interrupted with {done_chunks} of {len(bounds)} chunks done; the others were cancelled"
        ) from None
    finally:
        bar.close()
    batch = _concatenate([r for r in results if r is not None], wall_time=time.perf_counter() - start)
    batch.metadata["backend"] = "ray"
    batch.metadata["chunks"] = len(bounds)
    return batch


__all__ = ["BatchTrajectory", "rollout"]
