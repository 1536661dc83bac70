"""Batched rollouts: many initial states, controllers or torque sequences at once, on one machine or on Ray.

A batch is the driver (driver.py) over a stepping core of B rows: fixed-step methods step the rows together, in the
native kernel where it runs (kernels/native.py), else in the row kernel (kernels/row.py); adaptive methods, whose
rows choose their own steps, run one row at a time through the same driver. So every element gets ``simulate()``'s
samples, status and message, bit for bit.
"""

from __future__ import annotations

import copy
import dataclasses
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from .driver import Run, RunSettings
from .exceptions import InvalidArgumentError, SimulationInterrupted
from .integrators import Integrator, get_integrator
from .integrators.timestepping import SOLVER_COUNTS  # a contact scene's, in stats only when kept
from .progress import ProgressBar
from .recording import delivered_torques, ledger_sums, limit_reports, sensor_arrays, split_records
from .robot import Robot, check_system, real_array
from .scenes import randomized_scene
from .torques import Torques, controller_name
from .trajectory import ARRAYS, ConstraintRecord, Contacts, LedgerEntry, LimitViolations, Trajectory
from .validation import check_options, positive_count, positive_number

_RECORD_PARTS = ("force", "drift", "velocity_drift")  # a ConstraintRecord's arrays
_COUNTS = ("steps", "rejected_steps", "evaluations", "controller_calls", "saturated_controls")
_BACKENDS = ("local", "ray")


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
        contacts: a contact scene's active contacts of each element, as Trajectory.contacts (sample indices
            within its real samples), length B; None for an element of a run without contact.
        ctrl: a scene with actuators: the commands, shape (B, N, nv), as Trajectory.ctrl (tau then holds the joint
            torques the actuators delivered); None otherwise.
        sensors: a scene's sensor readings, as Trajectory.sensors, shape (B, N, components) each (element b's
            noise drawn from each sensor's seed + b).
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
    contacts: list[Contacts | None] = field(default_factory=list)
    ctrl: np.ndarray | None = None
    sensors: dict[str, np.ndarray] = field(default_factory=dict)

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
        if isinstance(b, (bool, np.bool_)) or not isinstance(b, (int, np.integer)):
            raise InvalidArgumentError(f"b must be a whole number (an element's index), got {b!r}")
        if not -len(self) <= b < len(self):
            raise IndexError(f"element {b} out of range for a batch of {len(self)}")
        n = int(self.n_samples[b])
        arrays = {name: getattr(self, name)[b, :n].copy() for name in ARRAYS}
        dof_names = self.metadata.get("robot", {}).get("dof_names", [])
        saturated = self.stats["saturated_dofs"][b]
        stats: dict[str, Any] = {
            name: int(self.stats[name][b]) for name in _COUNTS + SOLVER_COUNTS if name in self.stats
        }
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
            metadata=self._element_metadata(b),
            contacts=self.contacts[b] if self.contacts else None,
            ctrl=self.ctrl[b, :n].copy() if self.ctrl is not None else None,
            sensors={name: readings[b, :n].copy() for name, readings in self.sensors.items()},
        )

    def _element_metadata(self, b: int) -> dict[str, Any]:
        """Element b's metadata: the batch's, its index, and its own parameter values (randomised batches)."""
        metadata = {**self.metadata, "element": b % len(self)}
        parameters = self.metadata.get("parameters")
        if isinstance(parameters, list):
            metadata["parameters"] = parameters[b]
        return metadata

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
        if "solver_steps" in self.stats:  # a contact scene's cone solver, over every element
            unconverged = int(np.sum(self.stats["solver_unconverged"]))
            lines.append(
                f"contact solver: {int(np.sum(self.stats['solver_steps']))} steps with constraints, "
                f"{int(np.sum(self.stats['solver_iterations']))} iterations; {unconverged} unconverged"
            )
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
    randomize: Any = None,
    **options: Any,
) -> BatchTrajectory:
    """Simulate a batch of initial states (with controllers or open-loop torques) for `duration` seconds.

    Each element gets the samples ``simulate(system, q0s[b], v0s[b], ...)`` would return, bit for bit; an element
    that stops early (diverges, or its controller raises or returns something that is not a torque: status "failed")
    keeps its samples, its status and its message, and never stops the others.

    Args:
        system: the robot (or scene).
        q0s: initial configurations, shape (B, nq).
        v0s: initial velocities, shape (B, nv).
        duration: simulated time [s], > 0.
        dt: integration step [s], > 0 (adaptive methods: the first trial step).
        integrator: a registry name or an Integrator. Fixed-step methods step the whole batch together; adaptive
            ones run one element at a time.
        controller: one of: a per-state callable ``(t, q, v) -> tau`` used by every element (an object with a
            ``reset()`` method holds state: each element gets its own deep copy, reset before the run); a
            sequence of B such callables, one per element (parameter sweeps); or a batched controller, an
            object with ``batched = True`` called as ``(t, Q (n, nq), V (n, nv)) -> (n, nv)`` on the elements
            still running (its rows must not depend on one another: adaptive methods call it one row at a time,
            and Ray on chunks of the batch). Controllers with ``reset()`` are reset before the run, as simulate()
            does. None applies no torque.
        taus: open-loop torques, shape (B, n_control, nv), exclusive with `controller`: ``taus[b, j]`` is held
            from the j-th control instant (every ``control_dt``, default every step) to the next; n_control is
            the number of control instants in the run (adaptive methods need ``control_dt``). Torques beyond
            the URDF's effort limits are clipped and counted, as controller outputs are.
        progress: a tqdm progress bar: None shows one on a terminal for runs longer than a second, True always,
            False never.
        backend: "local" (this process) or "ray" (chunks of the batch as Ray tasks on the cluster that
            ``ray.init`` connected to; ``pip install 'multibody-sim[ray]'``).
        num_threads: threads the native kernel splits the batch over on the local backend (each Ray task uses 1;
            the row kernel runs on one).
        chunk_size: elements per Ray task (default: the batch split into two chunks per CPU of the cluster).
        randomize: randomised physics (README "Randomised physics"): None draws each element's scene parameters
            from the scene's own [randomize] table when it has one; a dict in that table's form ({"seed": 0,
            "parameter": [{"name": "mass", "bodies": "*", "distribution": "uniform", "scale": [0.9, 1.1]}]})
            draws from it instead; False draws nothing (the declared values). Element b draws with the seed
            (seed, b); its values are ``element(b).metadata["parameters"]`` (``metadata["parameters"]``: one dict
            per element), and ``system.with_parameters(them)`` re-runs it alone bit for bit.
        **options: simulate()'s options: ``output_dt``, ``control_dt``; adaptive methods also ``rtol``,
            ``atol``, ``max_step``.

    Returns:
        The batch's samples, statuses and stats.

    Raises:
        InvalidArgumentError: a bad argument or option.
        SimulationInterrupted: Ctrl-C; ``.trajectory`` holds the BatchTrajectory so far (interrupted elements
            have status "interrupted"; on Ray it is None: the unfinished chunks are cancelled).
    """
    check_system(system)
    method = get_integrator(integrator)
    method.check_contract()
    check_options(method, options)
    Q0, V0 = check_batch(system, q0s, v0s)
    B = len(Q0)
    duration = positive_number(duration, "duration")
    dt = positive_number(dt, "dt")
    if backend not in _BACKENDS:
        raise InvalidArgumentError(f"backend must be one of {', '.join(_BACKENDS)}, got {backend!r}")
    num_threads = positive_count(num_threads, "num_threads")
    if chunk_size is not None:
        chunk_size = positive_count(chunk_size, "chunk_size", "elements")
    if progress is not None and not isinstance(progress, bool):
        raise InvalidArgumentError(f"progress must be True, False or None, got {progress!r}")
    method.check_system(system)
    settings = RunSettings.check(method, duration, dt, options)
    system, parameters = _randomized(system, randomize, B)
    torques = _torques(system, method, settings, controller, taus, B)
    job = _Job(system, method, Q0, V0, settings, torques, options, np.arange(B), parameters)
    if backend == "ray":
        return _ray_rollout(job, progress=progress, chunk_size=chunk_size)
    if settings.adaptive:
        bar = ProgressBar(progress, B, "element", "rollout")
    else:
        bar = ProgressBar(progress, settings.n_steps * B, "element-step", "rollout")
    try:
        return _local(job, num_threads=num_threads, bar=bar)
    finally:
        bar.close()


@dataclass(frozen=True)
class _Job:
    """A batch to run: the system and method, the initial states (B, nq) and (B, nv), the checked settings, the
    torques and the options as given (for the metadata)."""

    system: Robot
    method: Integrator
    Q0: np.ndarray
    V0: np.ndarray
    settings: RunSettings
    torques: Torques
    options: dict[str, Any]
    rows: np.ndarray  # each element's index in the whole batch (its sensors' seeds)
    parameters: list[dict[str, Any]] | None = None  # randomised: each element's scene parameter values

    def subset(self, rows: np.ndarray) -> _Job:
        """The same job for the elements `rows` only."""
        return _Job(
            self.system,
            self.method,
            self.Q0[rows],
            self.V0[rows],
            self.settings,
            self.torques.subset(rows),
            self.options,
            self.rows[rows],
            [self.parameters[b] for b in rows] if self.parameters is not None else None,
        )

    def run(self, **kwargs: Any) -> Run:
        """A run of the driver over these elements (randomised: each on its scene with its parameter values)."""
        systems = None
        if self.parameters is not None:
            systems = [self.system.with_parameters(p) for p in self.parameters]  # type: ignore[attr-defined]
        return Run(
            system=self.system,
            method=self.method,
            Q0=self.Q0,
            V0=self.V0,
            settings=self.settings,
            torques=self.torques,
            options=self.options,
            row_ids=self.rows,
            systems=systems,
            **kwargs,
        )


def _local(job: _Job, *, num_threads: int, bar: ProgressBar) -> BatchTrajectory:
    """The batch in this process: one run over every row (fixed steps), or one run per row (adaptive methods)."""
    start = time.perf_counter()
    Q0 = job.Q0
    if job.settings.adaptive:
        return _row_by_row(job, bar=bar, start=start)
    run = job.run(num_threads=num_threads, progress=bar if bar.active else None)
    try:
        run.execute()
    except KeyboardInterrupt:
        batch = _from_run(run, time.perf_counter() - start)
        stopped = int(np.sum(batch.status == "interrupted"))
        raise SimulationInterrupted(
            f"interrupted at t = {run.core.t:.6g} s (step {run.core.steps}); {stopped} of "
            f"{len(Q0)} elements were running",
            trajectory=batch,  # type: ignore[arg-type]
        ) from None
    return _from_run(run, time.perf_counter() - start)


def _randomized(system: Robot, randomize: Any, B: int) -> tuple[Robot, list[dict[str, Any]] | None]:
    """The system the batch runs on and each element's scene parameter values (None: not randomised), element b's
    drawn with the seed (seed, b) (scenes.randomized_scene: from the scene's [randomize], or `randomize`)."""
    system, randomizer = randomized_scene(system, randomize, "rollout")
    return system, None if randomizer is None else [randomizer.row(b) for b in range(B)]


def _from_run(run: Run, wall_time: float) -> BatchTrajectory:
    """The BatchTrajectory of a run over B rows, batch-major, padded as BatchTrajectory documents."""
    store, system = run.store, run.system
    n = store.n_samples.copy()
    N = max(1, int(n.max(initial=0)))
    run.wall_time = wall_time

    def batch_major(name: str) -> np.ndarray:
        # The store's own memory (no copy: the run ends here) when it holds just N samples, as it does for a fixed-step
        # run in memory; else its first N samples, copied.
        return np.ascontiguousarray(store.batch_major(name)[:, :N])

    # The energies, the ledger lines and the records are views of those arrays too: columns of a sample-major block,
    # not copied one by one (each copy would be fresh memory, paid for in page faults).
    energy, flows, extra = batch_major("ENERGY"), batch_major("FLOWS"), batch_major("EXTRA")
    elements = system.ledger_elements
    is_work = np.array([kind == "work" for _, kind in elements], dtype=bool)
    kinetic, potential = energy[:, :, 0], energy[:, :, 1]
    work, dissipated = ledger_sums(flows, is_work)
    total = kinetic + potential
    arrays = {
        "t": batch_major("T"),
        "q": batch_major("Q"),
        "v": batch_major("V"),
        "tau": batch_major("TAU"),
        "kinetic_energy": kinetic,
        "potential_energy": potential,
        "total_energy": total,
        "work": work,
        "dissipated": dissipated,
        "energy_error": total - run.monitor.initial[:, None] - work + dissipated,
    }
    ledger = {name: LedgerEntry(kind, flows[:, :, j]) for j, (name, kind) in enumerate(elements)}
    potentials, constraints = split_records(system.record_fields, extra, copy=False)
    ledger.update(potentials)
    delivered = delivered_torques(system.record_fields, extra, copy=False)
    ctrl = None
    if delivered is not None:  # actuators: tau is what they delivered, the commands are ctrl
        ctrl, arrays["tau"] = arrays["tau"], delivered
    records = {f"{name}.{part}": getattr(r, part) for name, r in constraints.items() for part in _RECORD_PARTS}
    if ctrl is not None:
        records["ctrl"] = ctrl
    if run.sensing is not None:
        run.sensing.update(store)
    sensors = sensor_arrays(system, batch_major("SENSORS"), copy=False)  # (views of the store's memory)
    _pad({**arrays, **records, **{f"sensor {name}": r for name, r in sensors.items()}}, ledger, n, run.Q0, run.V0)
    stats: dict[str, Any] = run.count_arrays()
    if run.core.solver_stats:  # a contact method's counts, per element
        solved = run.core.solver_stats
        stats.update({name: np.array([solved.get(b, {}).get(name, 0) for b in range(run.B)]) for name in SOLVER_COUNTS})
    stats["saturated_dofs"] = run.saturation.dofs.astype(int).copy()
    stats["wall_time"] = wall_time
    return BatchTrajectory(
        **arrays,
        n_samples=n,
        status=np.array([outcome.status for outcome in run.outcomes]),
        messages=[outcome.message for outcome in run.outcomes],
        ledger=ledger,
        constraints=constraints,
        limit_violations=limit_reports(system, arrays["t"], arrays["q"], n),
        stats=stats,
        metadata={**run.metadata(), "backend": "local"},
        contacts=[store.contacts_record(b, int(n[b]), system) for b in range(run.B)]
        if getattr(system, "contact", None) is not None
        else [None] * run.B,  # (what contacts_record gives without contact)
        ctrl=ctrl,
        sensors=sensors,
    )


def _row_by_row(job: _Job, *, bar: ProgressBar, start: float) -> BatchTrajectory:
    """Adaptive methods: each row chooses its own steps, so each is a run of its own (the same driver)."""
    system, Q0, V0 = job.system, job.Q0, job.V0
    trajectories: list[Trajectory] = []
    messages: list[str] = []
    metadata: dict[str, Any] = {}
    for b in range(len(Q0)):
        run = job.subset(np.array([b])).run()
        try:
            run.execute()
        except KeyboardInterrupt:
            trajectories.append(run.trajectory(0))
            messages.append(f"interrupted at t = {run.core.t:.6g} s")
            for rest in range(b + 1, len(Q0)):  # not run: their initial state, as their one sample
                trajectories.append(_initial_only(system, Q0[rest], V0[rest]))
                messages.append("interrupted before it started")
            batch = _stack(trajectories, messages, Q0, V0, time.perf_counter() - start)
            batch.metadata = _batch_metadata(run.metadata(), job, backend="local")
            raise SimulationInterrupted(
                f"interrupted in element {b} of {len(Q0)}; {messages[b]}",
                trajectory=batch,  # type: ignore[arg-type]
            ) from None
        trajectories.append(run.trajectory(0))
        messages.append(run.outcomes[0].message)
        metadata = run.metadata()
        bar.update(1)
    batch = _stack(trajectories, messages, Q0, V0, time.perf_counter() - start)
    batch.metadata = _batch_metadata(metadata, job, backend="local")
    return batch


def _batch_metadata(metadata: dict[str, Any], job: _Job, **more: Any) -> dict[str, Any]:
    """A batch's metadata: a run's (over some of its elements), what `more` adds (the backend, ...) and, randomised,
    every element's parameter values in place of that run's."""
    metadata = {**metadata, **more}
    if job.parameters is not None:
        metadata["parameters"] = job.parameters
    return metadata


def check_batch(
    system: Robot, q0s: Any, v0s: Any, q_name: str = "q0s", v_name: str = "v0s"
) -> tuple[np.ndarray, np.ndarray]:
    """A batch of states (B, nq) and (B, nv) as float arrays, checked (finite, as many of each, unit quaternions),
    or InvalidArgumentError naming the argument (rollout's and BatchStepper's)."""
    Q0 = _as_batch(q0s, system.nq, q_name)
    V0 = _as_batch(v0s, system.nv, v_name)
    if len(Q0) != len(V0):
        raise InvalidArgumentError(f"{q_name} and {v_name} must hold as many states, got {len(Q0)} and {len(V0)}")
    if not len(Q0):
        raise InvalidArgumentError(f"{q_name} must hold at least one state, got an empty batch")
    if any(joint.nq != joint.nv for joint in system.model.joints[1:]):  # vector spaces need no unit norms
        is_normalized = system.space.is_normalized  # unit quaternions and (cos, sin) pairs (Q0 is finite)
        for b, q in enumerate(Q0):
            if not is_normalized(q):
                system.check_q(q, f"{q_name}[{b}]")  # raises, with check_q's message
    return Q0, V0


def _as_batch(value: Any, size: int, name: str) -> np.ndarray:
    arr = real_array(value, name, f"an array of real numbers of shape (B, {size})")
    if arr.ndim != 2 or arr.shape[1] != size:
        raise InvalidArgumentError(f"{name} must have shape (B, {size}), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        rows = np.flatnonzero(~np.isfinite(arr).all(axis=1)).tolist()
        raise InvalidArgumentError(f"{name} must be finite, got non-finite entries in rows {rows}")
    return arr


# ---- controllers and open-loop torques ---------------------------------------------------------------------------
def _torques(system: Robot, method: Integrator, settings: RunSettings, controller: Any, taus: Any, B: int) -> Torques:
    """Where each element's torque comes from, checked; stateful controllers copied per element and reset."""
    if controller is not None and taus is not None:
        raise InvalidArgumentError("controller and taus are exclusive: pass one of them")
    if taus is not None:
        if settings.adaptive and settings.control_dt is None:
            raise InvalidArgumentError(
                f"taus with the adaptive integrator '{method.name}' need control_dt (the period of the torque sequence)"
            )
        return Torques("taus", taus=_check_taus(system, taus, B, settings.n_control()), label="taus")
    if controller is None:
        return Torques("none")
    if getattr(controller, "batched", False) is True:
        if not callable(controller):
            raise InvalidArgumentError(
                f"a batched controller must be callable as controller(t, Q, V), got {type(controller).__name__}"
            )
        if callable(getattr(controller, "reset", None)):
            controller.reset()  # as simulate() does: a run starts afresh
        return Torques("batched", batched=controller, label=controller_name(controller))
    if callable(controller):
        if callable(getattr(controller, "reset", None)):
            # Internal state must not leak between elements: one copy each (the robot and its model are shared;
            # the copies are discarded at the end: pass a sequence of controllers to keep each element's).
            shared = {id(system): system, id(system.model): system.model}
            callables = [copy.deepcopy(controller, dict(shared)) for _ in range(B)]
            for c in callables:
                c.reset()
        else:
            callables = [controller] * B
        return Torques("callables", callables=callables, label=controller_name(controller))
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
        return Torques("callables", callables=list(controller), label=controller_name(controller[0]) + ", ...")
    raise InvalidArgumentError(
        "controller must be callable as controller(t, q, v), a sequence of such callables, or a batched "
        f"controller (batched = True), got {type(controller).__name__}"
    )


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
    end = system.actuated.stop
    if end < system.nv and np.any(arr[:, :, end:]):
        raise InvalidArgumentError(f"taus[:, :, {end}:] act on the scene's unactuated free objects and must be zero")
    return arr


# ---- results ----------------------------------------------------------------------------------------------------
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


# ---- row by row (adaptive methods) ------------------------------------------------------------------------------
def _initial_only(system: Robot, q0: np.ndarray, v0: np.ndarray) -> Trajectory:
    T, V = system.unchecked_energies(q0, v0)
    zero = np.zeros(1)
    extra = np.zeros((1, sum(width for _, _, width in system.record_fields)))
    system.unchecked_record(q0, v0, np.zeros(system.nv), 0.0, extra[0])  # a scene's springs and constraints
    potentials, constraints = split_records(system.record_fields, extra)
    delivered = delivered_torques(system.record_fields, extra)
    return Trajectory(
        t=zero.copy(),
        q=q0[None, :].copy(),
        v=v0[None, :].copy(),
        tau=np.zeros((1, system.nv)) if delivered is None else delivered,
        ctrl=None if delivered is None else np.zeros((1, system.nv)),
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
    ctrl = None
    if first.ctrl is not None:
        ctrl = np.zeros((B, N, first.ctrl.shape[1]))
        for b, tr in enumerate(trajectories):
            ctrl[b, : n[b]] = tr.ctrl
        records["ctrl"] = ctrl
    sensors = {}
    for name, readings in first.sensors.items():
        arr = np.zeros((B, N, readings.shape[1]))
        for b, tr in enumerate(trajectories):
            arr[b, : n[b]] = tr.sensors[name]
        sensors[name] = records[f"sensor {name}"] = arr
    _pad({**arrays, **records}, ledger, n, Q0, V0)  # (records keyed apart from the field names)
    nv = first.v.shape[1]
    dof_index = {name: i for i, name in enumerate(first.metadata.get("robot", {}).get("dof_names", []))}
    saturated = np.zeros((B, nv), dtype=int)
    for b, tr in enumerate(trajectories):
        for name, count in tr.stats.get("saturated_dofs", {}).items():
            saturated[b, dof_index[name]] = count
    counted = _COUNTS + (SOLVER_COUNTS if any("solver_steps" in tr.stats for tr in trajectories) else ())
    stats: dict[str, Any] = {
        name: np.array([int(tr.stats.get(name, 0)) for tr in trajectories], dtype=int) for name in counted
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
        contacts=[tr.contacts for tr in trajectories],
        ctrl=ctrl,
        sensors=sensors,
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
    counted = _COUNTS + (SOLVER_COUNTS if all("solver_steps" in bt.stats for bt in batches) else ())
    stats: dict[str, Any] = {name: np.concatenate([bt.stats[name] for bt in batches]) for name in counted}
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
        contacts=[c for bt in batches for c in (bt.contacts or [None] * len(bt))],
        ctrl=np.concatenate([widen(bt.ctrl) for bt in batches]) if batches[0].ctrl is not None else None,  # type: ignore[arg-type]
        sensors={name: np.concatenate([widen(bt.sensors[name]) for bt in batches]) for name in batches[0].sensors},
    )


# ---- Ray -----------------------------------------------------------------------------------------------------------
def _run_chunk(system: Robot, job: _Job) -> BatchTrajectory:
    """One Ray task: a local rollout of a chunk of the batch (its system shipped apart), with one thread."""
    return _local(
        dataclasses.replace(job, system=system), num_threads=1, bar=ProgressBar(False, 1, "element", "rollout")
    )


_REMOTE: dict[str, Any] = {}


def _ray_rollout(job: _Job, *, progress: bool | None, chunk_size: int | None) -> BatchTrajectory:
    try:
        import ray
    except ImportError:
        raise InvalidArgumentError(
            "backend='ray' needs Ray: pip install 'multibody-sim[ray]' (then ray.init() to start or join a cluster)"
        ) from None
    start = time.perf_counter()
    if not ray.is_initialized():  # what Ray would do on the first task anyway: a local instance
        ray.init()
    B = len(job.Q0)
    if chunk_size is None:
        cpus = max(1, int(ray.cluster_resources().get("CPU", 1)))
        chunk_size = max(1, -(-B // (2 * cpus)))
    bounds = [(lo, min(lo + chunk_size, B)) for lo in range(0, B, chunk_size)]
    remote = _REMOTE.get("chunk")
    if remote is None:
        remote = _REMOTE["chunk"] = ray.remote(num_cpus=1)(_run_chunk)
    system_ref = ray.put(job.system)  # shipped once, shared by every task
    shell = dataclasses.replace(job, system=None)  # type: ignore[arg-type]
    pending = {remote.remote(system_ref, shell.subset(np.arange(lo, hi))): i for i, (lo, hi) in enumerate(bounds)}
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
    batch.metadata = _batch_metadata(batch.metadata, job, backend="ray", chunks=len(bounds))
    return batch


__all__ = ["BatchTrajectory", "rollout"]
