"""The driver of a run: control instants, sampling, recording, interrupts and early stops, for one row (simulate,
Stepper) or many (rollout), with the torques of torques.py and the energy monitor of monitor.py. It knows nothing of
Runge–Kutta: the stepping core (core.py) advances the rows between its events.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .core import EMPTY, FULL, REACHED, Core, Sampler, cure_for_dt
from .exceptions import ControllerOutputError, MultibodySimError, TrajectoryFileError
from .files import signals_held
from .integrators import Integrator
from .kernels.native import NativeCore, NativeKernel, why_not_native
from .kernels.row import RowKernel
from .metadata import run_metadata
from .monitor import Monitor
from .recording import COUNTERS, SampleStore, check_memory, contacts_at, file_bytes, samples_needed, sensor_width
from .safety import check_file_size
from .sensors import Sensing, run_sensing
from .step_control import SLIVER, ConstantStep, PIController
from .torques import Saturation, Torques, check_sensor_controller
from .trajectory import (
    PARTS_SUFFIX,
    LimitViolations,
    Trajectory,
    chunk_path,
    combine_limit_violations,
    merge_parts,
    write_chunk,
)
from .validation import run_numbers, step_count

# The core returns to the driver at least every this many steps (progress, interrupts, the monitor).
BLOCK_STEPS = 2048
# ... and whenever the store holds this many more samples (in-memory runs).
BLOCK_SAMPLES = 1024


# A run whose contact solver stopped at its iteration cap on more than this fraction of its steps failed.
SOLVER_FAILURE_FRACTION = 0.01


# ---- kernels ------------------------------------------------------------------------------------------------------
def choose_kernel(
    system: Any,
    method: Integrator,
    Q0: np.ndarray,
    V0: np.ndarray,
    *,
    rtol: float | None = None,
    atol: float | None = None,
    num_threads: int = 1,
    native: bool | None = None,
    systems: list[Any] | None = None,
) -> RowKernel | NativeKernel:
    """The kernel a run of these rows takes: the native kernel when it runs the method on the system
    (kernels.native.why_not_native; `native`: its answer, when the caller has it), else the row kernel, for one row
    or many (simulate(), Stepper, BatchStepper and rollout() share this rule). `systems`: each row's own system (a
    randomised scene's rows, Scene.with_parameters: the same structure as `system`, other values), or None."""
    if native is None:
        native = why_not_native(system, method, systems) is None
    if native:
        return NativeKernel(system, method, Q0, V0, rtol=rtol, atol=atol, num_threads=num_threads, systems=systems)
    return RowKernel(system, method, Q0, V0, rtol=rtol, atol=atol, systems=systems)


def core_class(kernel: Any) -> type[Core]:
    """The core that drives this kernel: NativeCore for the native kernel (its loop runs in C++), else Core."""
    return NativeCore if isinstance(kernel, NativeKernel) else Core


def kernel_name(kernel: Any) -> str:
    """The kernel's name in the run header and the metadata: "native" or "python (row)"."""
    return "native" if isinstance(kernel, NativeKernel) else "python (row)"


# ---- a run ---------------------------------------------------------------------------------------------------------
@dataclass
class Sink:
    """Where samples go besides memory: nowhere, one file at the end, or chunk files merged at the end.

    Attributes:
        out: the trajectory file, or None.
        chunk: samples per chunk file (out.npz.parts/), or None (one file at the end).
        run_id: the run's identifier, recorded in each chunk file (files.RunLock makes it).
        written: chunk files written so far.
        samples: samples in them.
        violations: their limit-violation reports.
        write_error: why a chunk could not be written (the run stopped there), or None.
    """

    out: Path | None = None
    chunk: int | None = None
    run_id: str = ""
    written: int = 0
    samples: int = 0
    violations: list[LimitViolations] = field(default_factory=list)
    write_error: BaseException | None = None

    @property
    def parts(self) -> Path:
        assert self.out is not None
        return self.out.with_name(self.out.name + PARTS_SUFFIX)


@dataclass
class Kept:
    """What a run's end kept, and where.

    Attributes:
        trajectory: every sample kept (from memory, the file or the parts); None when memory ran out even for them.
        saved_to: the file (or parts folder) that holds them, or None.
        problem: what could not be written and why ("" when all went well).
        interrupted: SIGINT or SIGTERM arrived while the samples were being written (they were written first).
    """

    trajectory: Trajectory | None
    saved_to: Path | None = None
    problem: str = ""
    interrupted: bool = False

    @property
    def samples(self) -> int:
        return len(self.trajectory) if self.trajectory is not None else 0

    @property
    def t_end(self) -> float:
        """The last sample's time [s] (0 without samples)."""
        return float(self.trajectory.t[-1]) if self.trajectory is not None and self.samples else 0.0


@dataclass(slots=True)
class RowOutcome:
    """How one row of a run ended: status, message, the user's exception, and its counts (never edited in place:
    rows that stop together may share one dict)."""

    status: str = "running"
    message: str = ""
    cause: BaseException | None = None
    counts: dict[str, int] = field(default_factory=dict)
    bad_output: bool = False  # failed on a controller output that is not a torque


@dataclass
class RunSettings:
    """A run's settings, checked: the step, the sampling and the control timing.

    Attributes:
        duration, dt: [s].
        adaptive: the method chooses its steps (rtol, atol, max_step apply).
        output_every: fixed-step: sample every this many steps.
        control_every: fixed-step: control every this many steps.
        output_dt, control_dt: adaptive: the sampling and control periods [s] (None: every step).
        n_steps: fixed-step: the number of steps (the last one shortened to land on the duration).
    """

    duration: float
    dt: float
    adaptive: bool
    rtol: float | None = None
    atol: float | None = None
    max_step: float = math.inf
    output_every: int = 1
    control_every: int = 1
    output_dt: float | None = None
    control_dt: float | None = None
    n_steps: int = 0

    @classmethod
    def check(cls, method: Integrator, duration: float, dt: float, options: dict[str, Any]) -> RunSettings:
        numbers = run_numbers(method.adaptive, duration, dt, options)
        if method.adaptive:
            return cls(
                numbers["duration"],
                numbers["dt"],
                True,
                rtol=numbers["rtol"],
                atol=numbers["atol"],
                max_step=numbers.get("max_step", math.inf),
                output_dt=numbers.get("output_dt"),
                control_dt=numbers.get("control_dt"),
            )
        return cls(
            numbers["duration"],
            numbers["dt"],
            False,
            output_every=numbers["output_every"],
            control_every=numbers["control_every"],
            n_steps=numbers["n_steps"],
        )

    @property
    def capacity(self) -> int:
        """Samples a row can take (adaptive methods without output_dt: a first guess, the store grows)."""
        if not self.adaptive:
            return (self.n_steps - 1) // self.output_every + 2
        return samples_needed(self.duration, self.output_dt) if self.output_dt else 1024

    def control_instant(self, j: int) -> float:
        """The time of control instant j [s] (the duration once it is past the last one)."""
        if self.adaptive:
            assert self.control_dt is not None
            return min(self.duration, j * self.control_dt)
        k = j * self.control_every
        return k * self.dt if k < self.n_steps else self.duration

    def n_control(self) -> int:
        """How many control instants the run has (fixed-step methods, or adaptive ones with control_dt)."""
        if self.adaptive:
            assert self.control_dt is not None
            return max(1, math.ceil(self.duration / self.control_dt - SLIVER))
        return -(-self.n_steps // self.control_every)


def _sensing(system: Any, method: Integrator, settings: RunSettings, core: Core, rows: np.ndarray) -> Sensing | None:
    """The run's sensors, ticking in the core and read at its start; None for a system without sensors."""
    dt = settings.dt
    sensing = run_sensing(system, method, dt, settings.control_every, rows)
    if sensing is not None:
        sensing.attach(core, dt)
    return sensing


def check_resources(system: Any, settings: RunSettings, sink: Sink, B: int = 1) -> None:
    """Refuse, before the run, what this process could not hold or write: the samples in memory (or a chunk's
    buffer) against usable_memory(), and the files against its file-size limit (check_file_sizes)."""
    if sink.chunk is None:
        check_memory(settings.capacity, system, B)
    else:  # the chunk buffer is allocated whole
        check_memory(sink.chunk, system, B, advice="choose a smaller chunk")
    if sink.out is not None:
        check_file_sizes(sink, settings, system)


def check_file_sizes(sink: Sink, settings: RunSettings, system: Any) -> None:
    """Refuse, before the run, files that this process's file-size limit (ulimit -f) would cut short: the chunk
    files and the final file, where their sample counts are known (an adaptive run without output_dt: only the
    chunks)."""
    per_sample = file_bytes(system)
    known = not settings.adaptive or settings.output_dt is not None
    advice = "sample less often (output_dt) or raise the limit"
    if known:
        check_file_size(settings.capacity * per_sample, f"out {sink.out}", advice)
    if sink.chunk is not None:
        check_file_size(sink.chunk * per_sample, "a chunk file", "choose a smaller chunk or raise the limit")


def n_steps(duration: float, dt: float) -> int:
    """Fixed steps of dt in a run of `duration`, the last one shortened (a sliver of round-off is no step)."""
    return step_count(duration, dt, SLIVER)


class Run:
    """One run of the driver over B rows from (Q0, V0) at t = 0 to the duration.

    Results: `outcomes` (one RowOutcome per row) and the store's samples; `trajectory(b)` and the batch arrays are
    built from them. Early stops never raise here: the callers (simulate, rollout) decide what to raise.
    """

    def __init__(
        self,
        *,
        system: Any,
        method: Integrator,
        Q0: np.ndarray,
        V0: np.ndarray,
        settings: RunSettings,
        torques: Torques,
        sink: Sink | None = None,
        on_sample: Callable[[float, np.ndarray, np.ndarray], None] | None = None,
        num_threads: int = 1,
        progress: Any = None,
        options: dict[str, Any] | None = None,
        row_ids: np.ndarray | None = None,
        systems: list[Any] | None = None,
    ):
        self.system, self.method, self.settings, self.torques = system, method, settings, torques
        self.systems = systems  # each row's own system (randomised rows), or None: `system` for every row
        self.options = dict(options or {})
        self.sink = sink or Sink()
        self.on_sample = on_sample
        self.progress = progress
        B = len(Q0)
        self.B = B
        self.Q0, self.V0 = Q0, V0
        chunk = self.sink.chunk
        check_resources(system, settings, self.sink, B)
        capacity = chunk if chunk is not None else min(settings.capacity, 1 << 20)
        record_width = sum(width for _, _, width in system.record_fields)
        self.store = SampleStore(
            B, system.nq, system.nv, len(system.ledger_elements), record_width, capacity, sensor_width(system)
        )
        self.store.make_room(chunk if chunk is not None else min(capacity, BLOCK_SAMPLES))
        if settings.adaptive:
            control: ConstantStep | PIController = PIController(
                method.embedded_order,
                max_step=settings.max_step,
                first_step=settings.dt,
            )
            sampler = Sampler(period=settings.output_dt)
        else:
            control = ConstantStep(settings.dt)
            sampler = Sampler(every=settings.output_every)
        self.why_not_native = why_not_native(system, method, systems)
        kernel = choose_kernel(
            system,
            method,
            Q0,
            V0,
            rtol=settings.rtol,
            atol=settings.atol,
            num_threads=num_threads,
            native=self.why_not_native is None,
            systems=systems,
        )
        self.kernel_name = kernel_name(kernel)
        self.core = core_class(kernel)(
            system=system, method=method, kernel=kernel, control=control, sampler=sampler, store=self.store, B=B
        )
        check_sensor_controller(system, torques.reads_sensors)
        self.sensing = _sensing(system, method, settings, self.core, np.arange(B) if row_ids is None else row_ids)
        self.monitor = Monitor(system, B, systems)
        self.saturation = Saturation(system, B, systems)
        self.controller_calls = np.zeros(B, dtype=np.int64)
        # Built-in controllers and open-loop torques run inside the native kernel, at its control instants (no
        # return to Python per instant); the counts land in controller_calls and saturation.
        self.native_control = isinstance(kernel, NativeKernel) and kernel.control_natively(
            torques, settings, self.saturation, self.controller_calls
        )
        self.outcomes = [RowOutcome() for _ in range(B)]
        self.checked = 0  # samples of the running rows the monitor has seen
        self.wall_time = 0.0

    # ---- the loop ------------------------------------------------------------------------------------------------
    def execute(self) -> None:
        """Run to the end; early stops are recorded in `outcomes`. Raises KeyboardInterrupt (after keeping the
        samples and marking the running rows "interrupted") and OSError-like failures of the sink."""
        start = time.perf_counter()
        try:
            with np.errstate(over="ignore", invalid="ignore", divide="ignore"):  # divergence is reported, not warned
                self._loop()
        except KeyboardInterrupt:
            self._stop_running("interrupted")
            raise
        except MemoryError as exc:  # the samples so far are kept (and written by finish) as for any early stop
            where = f"ran out of memory at t = {self.core.t:.6g} s"
            self._stop_running(
                "out_of_memory",
                f"{where}: {exc}; the run stopped" if str(exc) else f"{where} (MemoryError): the run stopped",
            )
        finally:
            self.wall_time = time.perf_counter() - start

    def _loop(self) -> None:
        settings, core, torques = self.settings, self.core, self.torques
        controlled = torques.kind != "none" and not self.native_control  # natively: the kernel's own instants
        every_step = controlled and settings.adaptive and settings.control_dt is None
        # Control instants: where a controller is called, and where adaptive steps land (given control_dt) even
        # without one.
        instants = not every_step and not self.native_control
        instants = instants and (controlled or (settings.adaptive and settings.control_dt is not None))
        instant = 0  # the next control instant's number
        target = settings.control_instant(0) if instants else settings.duration
        passed = math.nan  # the time of the latest control instant
        while True:
            t = core.t
            if t < settings.duration and t != passed:
                if every_step:
                    passed = t
                    self._control(t, instant)
                elif instants and t == settings.control_instant(instant):
                    passed = t
                    if controlled:
                        self._control(t, instant)
                    instant += 1
                    target = settings.control_instant(instant)
            reason = core.advance(target, max_steps=1 if every_step else BLOCK_STEPS)
            self._take_samples()
            if reason == EMPTY or not len(core.rows):
                return
            if reason == REACHED and core.t >= settings.duration:
                core.record()  # the final sample, with the torque of the last step
                self._take_samples()
                self._stop_running("completed")
                return
            if reason == FULL:
                self._make_room()
                if not len(core.rows):  # a chunk could not be written: the run stopped
                    return
            # REACHED a control instant, STEPPED (a block of steps, or one step between controls): carry on

    def _control(self, t: float, instant: int) -> None:
        core = self.core
        rows = core.rows
        readings = self.sensing.stream if self.sensing is not None else None
        TAU, failures = self.torques.compute(self.system, t, instant, rows, core.kernel.states, readings)
        self.controller_calls[rows] += 1
        if failures:
            js = [j for j, _, _ in failures]
            for j, exc, bad_output in failures:
                outcome = self.outcomes[int(rows[j])]
                outcome.bad_output = bad_output
                outcome.cause = exc
                outcome.message = (
                    str(exc)
                    if bad_output
                    else f"failed at t = {t:.6g} s: the controller raised {type(exc).__name__}: {exc}"
                )
            self._stop_positions(np.array(js, dtype=int), "failed")
            keep = np.ones(len(rows), dtype=bool)
            keep[js] = False
            TAU = TAU[keep]
            rows = core.rows
            if not len(rows):
                return
        core.set_torques(self.saturation.apply(TAU, rows))

    # ---- samples -------------------------------------------------------------------------------------------------
    def _take_samples(self) -> None:
        """Check the samples taken since the last call (the energy monitor), show them (on_sample, progress) and
        stop the rows the core or the monitor stopped."""
        store, core, monitor = self.store, self.core, self.monitor
        if self.sensing is not None:
            self.sensing.update(store)
        stops = {stop.row: stop for stop in core.take_stops()}
        rows = core.rows
        if stops:
            rows = np.concatenate([rows, np.fromiter(stops, dtype=rows.dtype, count=len(stops))])
        limits = store.n_samples[rows]
        if not monitor.all_started:
            fresh = rows[~monitor.started[rows] & (limits > 0)]
            if len(fresh):
                monitor.start(fresh, store.ENERGY[0, fresh])
        for j, b in enumerate(rows[len(core.rows) :].tolist()):
            if stops[b].added:  # a stop's own last sample: not judged
                limits[len(core.rows) + j] = stops[b].sample
        suspects = set(monitor.suspects(store, rows, self.checked, limits).tolist())
        limit = dict(zip(rows.tolist(), limits.tolist(), strict=True)) if suspects else {}
        todo = [b for b in rows.tolist() if b in suspects or b in stops] if suspects or stops else []  # in order
        for b in todo:
            stop = stops.get(b)
            problem = monitor.first_problem(store, b, self.checked, limit[b]) if b in suspects else None
            if problem is not None:
                i, what, keep = problem
                t = store.T[i, b]
                steps = int(store.COUNTS[i, b, 0])
                if stop is None:
                    self.core.stop(np.flatnonzero(core.rows == b))
                store.truncate(b, i + 1 if keep else i)  # a sample whose energy is not finite is not kept
                message = f"diverged at t = {t:.6g} s (step {steps}): {what}; {cure_for_dt(self.system, self._dt_hint)}"
                self._end(b, "diverged", message, counts_at=i)
                continue
            if stop is not None:
                outcome = self.outcomes[b]
                outcome.status, outcome.message, outcome.cause = stop.status, stop.message, stop.cause
                outcome.bad_output = stop.bad_output
                outcome.counts = self._core_counts(b)
                # only finite samples are kept; the stop's reason stands (a refused controller output keeps the state
                # it was given, as _control does)
                if stop.added and not stop.bad_output and not np.isfinite(store.ENERGY[stop.sample, b]).all():
                    store.truncate(b, stop.sample)
        self._show(rows)
        self.checked = store.count

    def _show(self, rows: np.ndarray) -> None:
        """on_sample and progress for the new samples (one-row runs)."""
        if self.on_sample is None and self.progress is None:
            return
        store = self.store
        b = 0
        if self.B != 1 or not len(rows):
            if self.progress is not None:
                core = self.core  # element-steps: the stopped rows' and the running rows'
                self.progress.update_to(int(core.stopped_counts[:, 0].sum()) + core.steps * len(core.rows))
            return
        start, end = self.checked, store.samples_of(b)
        # A callback that draws contacts (viz's LiveView with forces) gets each sample's first: (k, 11) rows or None.
        contacts = (
            getattr(self.on_sample, "contacts", None) if getattr(self.on_sample, "wants_contacts", False) else None
        )
        for i in range(start, end):
            if self.on_sample is not None:
                q, v = store.Q[i, b], store.V[i, b]
                try:
                    if contacts is not None:
                        contacts(contacts_at(store.contacts.get(b, []), i), self.settings.dt)
                    self.on_sample(float(store.T[i, b]), q, v)
                except Exception as exc:  # user code: the run stops with what it has
                    if len(self.core.rows):
                        self.core.stop(np.array([0]))
                    store.truncate(b, i + 1)
                    outcome = self.outcomes[b]
                    outcome.cause = exc
                    message = f"failed at t = {store.T[i, b]:.6g} s: on_sample raised {type(exc).__name__}: {exc}"
                    self._end(b, "failed", message, counts_at=i)
                    break
        if self.progress is not None:
            self.progress.update_to(float(store.T[max(end - 1, 0), b]))

    def _make_room(self) -> None:
        """The store reached its soft capacity: write a chunk file, or let it grow."""
        store = self.store
        if self.sink.chunk is None:
            store.make_room(store.count + BLOCK_SAMPLES)
            return
        try:
            self._flush()
        except (OSError, MemoryError) as exc:  # disk full, a file-size limit: stop, keeping what exists
            sink = self.sink
            sink.write_error = exc
            assert sink.out is not None
            self._stop_running(
                "write_failed",
                f"could not write {chunk_path(sink.out, sink.written)} ({describe_error(exc)}) at t = "
                f"{self.core.t:.6g} s: the run stopped",
            )

    def _flush(self) -> None:
        """Write the samples in memory as the next chunk file and empty the store (one-row runs). SIGINT and
        SIGTERM wait until the chunk and its bookkeeping are complete."""
        sink = self.sink
        assert sink.out is not None
        with signals_held("finish"):
            traj = self.trajectory(0, status="running")
            write_chunk(traj, sink.out, sink.written, run_id=sink.run_id, first_sample=sink.samples)
            sink.violations.append(traj.limit_violations)
            sink.written += 1
            sink.samples += len(traj)
            self.store.clear()
            self.checked = 0

    # ---- stopping rows -------------------------------------------------------------------------------------------
    def _stop_positions(self, js: np.ndarray, status: str) -> None:
        """Stop the running rows at positions js with `status`, their current state kept as a last sample."""
        core = self.core
        rows = core.rows[js]
        added = core._record_stopping(js)
        core.stop(js, with_last=added)
        for b in rows.tolist():
            outcome = self.outcomes[b]
            outcome.status = status
            outcome.counts = self._core_counts(b)

    def _stop_running(self, status: str, message: str = "") -> None:
        """Every running row ends with `status` (completed, interrupted; write_failed and out_of_memory with a
        message), its current state its last sample (interrupted)."""
        core = self.core
        if not len(core.rows):
            return
        if status == "interrupted":
            self._take_samples()  # what the monitor finds before the interrupt stands
            if not len(core.rows):
                return
            core.record()
        rows = core.rows.tolist()
        core.stop(np.arange(len(rows)))
        frozen = core.stopped_counts[rows].tolist()  # their counts, as core.counts(b) gives them now
        judge = status == "completed" and bool(core.solver_stats)
        shared: dict[tuple[int, ...], dict[str, int]] = {}  # rows that stop together mostly share their counts
        for b, counts in zip(rows, frozen, strict=True):
            outcome = self.outcomes[b]
            outcome.status, outcome.message = status, message
            key = tuple(counts)
            outcome.counts = shared.get(key) or shared.setdefault(key, dict(zip(COUNTERS, counts, strict=True)))
            if judge:
                self._judge_solver(b)

    def _judge_solver(self, b: int) -> None:
        """A completed run whose contact solver stopped at its iteration cap on more than
        SOLVER_FAILURE_FRACTION of the steps ends with status "solver_failed" (its samples kept)."""
        stats = self.core.solver_stats.get(b, {})
        unconverged, steps = stats.get("solver_unconverged", 0), self.outcomes[b].counts.get("steps", 0)
        if steps and unconverged > SOLVER_FAILURE_FRACTION * steps:
            outcome = self.outcomes[b]
            outcome.status = "solver_failed"
            outcome.message = (
                f"solver_failed: the contact solver did not converge on {unconverged} of {steps} steps (more than "
                f"{SOLVER_FAILURE_FRACTION:.0%}); each continued with the best impulses found; try a smaller dt"
                + (
                    ' or [contact] solver = "admm" (the default: it converges more reliably than PGS on many or '
                    "redundant contact rows)"
                    if getattr(getattr(self.system, "contact", None), "solver", None) == "pgs"
                    else ""
                )
            )

    def _end(self, b: int, status: str, message: str, *, counts_at: int) -> None:
        outcome = self.outcomes[b]
        outcome.status, outcome.message = status, message
        counts = self.store.COUNTS[counts_at, b]
        outcome.counts = {name: int(counts[i]) for i, name in enumerate(COUNTERS)}

    def _core_counts(self, b: int) -> dict[str, int]:
        return dict(zip(COUNTERS, self.core.counts(b), strict=True))

    @property
    def _dt_hint(self) -> float:
        return self.settings.dt

    # ---- results -------------------------------------------------------------------------------------------------
    def stats(self, b: int) -> dict[str, Any]:
        """Row b's stats, as Trajectory.stats holds them."""
        outcome = self.outcomes[b]
        counts = outcome.counts or self._core_counts(b)
        dofs = self.system.dof_names
        return {
            **counts,
            **self.core.solver_stats.get(b, {}),
            "controller_calls": int(self.controller_calls[b]),
            "saturated_controls": int(self.saturation.calls[b]),
            "saturated_dofs": {dofs[i]: int(n) for i, n in enumerate(self.saturation.dofs[b]) if n},
            "wall_time": self.wall_time,
        }

    def count_arrays(self) -> dict[str, np.ndarray]:
        """Every row's counts of stats(), shape (B,) each: steps, rejected_steps, evaluations, controller_calls,
        saturated_controls."""
        counts = [outcome.counts or self._core_counts(b) for b, outcome in enumerate(self.outcomes)]
        arrays = {name: np.array([c.get(name, 0) for c in counts], dtype=int) for name in COUNTERS}
        arrays["controller_calls"] = self.controller_calls.astype(int)
        arrays["saturated_controls"] = self.saturation.calls.astype(int)
        return arrays

    def metadata(self, b: int | None = None) -> dict[str, Any]:
        """The run's metadata; randomised rows: every row's parameter values (a list), or row b's."""
        rows = {}
        if self.systems is not None:
            rows["parameters"] = self.systems[b].parameters if b is not None else [s.parameters for s in self.systems]
        return {
            **run_metadata(self.system),
            "integrator": self.method.name,
            "options": {"dt": self.settings.dt, "duration": self.settings.duration, **self.options},
            "controller": self.torques.label,
            "kernel": self.kernel_name,
            **({"why_not_native": self.why_not_native} if self.why_not_native else {}),
            **rows,
        }

    def trajectory(self, b: int, *, status: str | None = None, copy: bool = True) -> Trajectory:
        """Row b's samples in memory as a Trajectory (copy=False: views of the store, see SampleStore.trajectory)."""
        if self.sensing is not None:
            self.sensing.update(self.store)
        return self.store.trajectory(
            b,
            system=self.system,
            initial_energy=float(self.monitor.initial[b]),
            status=status or self.outcomes[b].status,
            stats=self.stats(b),
            metadata=self.metadata(b),
            copy=copy,
        )

    def _assemble(self, b: int) -> Trajectory | None:
        """Row b's samples at the end of the run: copies (compact), else, when memory is short, views of the store;
        None when not even those fit."""
        try:
            return self.trajectory(b)
        except MemoryError:
            pass
        try:
            return self.trajectory(b, copy=False)
        except MemoryError:
            return None

    def finish(self, b: int = 0) -> Kept:
        """Row b's whole trajectory, also written to the sink's file (merging its chunks) when there is one.

        Never raises for the writing: a write that fails (disk full, a file-size limit, memory) or is interrupted
        is reported in the result, with what was kept and where (the file, the parts folder, or memory only).
        """
        sink, out = self.sink, self.sink.out
        if sink.chunk is None:
            traj = self._assemble(b)
            if traj is None:
                lost = self.store.samples_of(b)
                return Kept(None, None, f"its {lost} samples could not be assembled (out of memory)")
            if out is None:
                return Kept(traj)
            try:
                traj.save(out)
            except KeyboardInterrupt:  # delivered once the file was complete
                return Kept(traj, out, interrupted=True)
            except (OSError, MemoryError) as exc:
                return Kept(traj, None, f"{out} could not be written ({describe_error(exc)})")
            return Kept(traj, out)
        assert out is not None
        interrupted = False
        try:
            if sink.write_error is None and (self.store.count or not sink.written):
                self._flush()
            if sink.write_error is None:
                merge_parts(
                    out,
                    status=self.outcomes[b].status,
                    stats=self.stats(b),
                    limit_violations=combine_limit_violations(sink.violations),
                )
                return Kept(Trajectory.load(out, mmap=True), out)
        except KeyboardInterrupt:
            interrupted = True
            if not sink.parts.exists():  # the merge was complete when the signal was delivered
                return Kept(Trajectory.load(out, mmap=True), out, interrupted=True)
        except (OSError, MemoryError, TrajectoryFileError) as exc:  # TrajectoryFileError: check_parts refused
            sink.write_error = sink.write_error or exc
        return self._kept_in_parts(b, interrupted)

    def _kept_in_parts(self, b: int, interrupted: bool) -> Kept:
        """A chunked run whose parts could not be merged: its samples are the parts' and those still in memory."""
        sink = self.sink
        pieces = []
        if sink.written:
            try:
                pieces.append(Trajectory.load(sink.parts))
            except TrajectoryFileError:  # a stranger's chunk in the folder: the message names it (write_error)
                sink.samples = 0
        if self.store.samples_of(b):
            memory = self._assemble(b)
            if memory is not None:
                pieces.append(memory)
        traj = Trajectory.concatenate(pieces) if pieces else self.trajectory(b)
        traj.status = self.outcomes[b].status
        on_disk = f"{sink.samples} samples stay in {sink.parts} (Trajectory.load reads the folder)"
        in_memory = len(traj) - sink.samples
        if in_memory:
            on_disk += f", the last {in_memory} only in memory"
        if sink.write_error is not None and self.outcomes[b].status != "write_failed":
            problem = f"{sink.out} could not be written ({describe_error(sink.write_error)}): {on_disk}"
        elif interrupted:
            problem = f"merging the chunks was interrupted: {on_disk}"
        else:
            problem = on_disk
        return Kept(traj, sink.parts if sink.written else None, problem, interrupted)


def describe_error(exc: BaseException) -> str:
    """An OSError or MemoryError in a few words: "No space left on device", "File too large", "out of memory"."""
    if isinstance(exc, MemoryError):
        return "out of memory"
    if isinstance(exc, TrajectoryFileError):
        return str(exc)
    if isinstance(exc, OSError) and exc.strerror:
        return exc.strerror
    return str(exc) or type(exc).__name__


def stop_error(
    outcome: RowOutcome, trajectory: Any, *, problem: str = "", saved_to: Path | None = None
) -> MultibodySimError:
    """The error an early stop raises: SimulationError (ControllerOutputError for a controller output that is not a
    torque), its trajectory attached, the user's exception as its cause; `problem` (what could not be written)
    is added to the message, and `saved_to` says where the samples are on disk."""
    from .exceptions import SimulationError

    message = outcome.message + (f"; {problem}" if problem else "")
    if outcome.bad_output:
        error: SimulationError = ControllerOutputError(
            message, status="failed", trajectory=trajectory, saved_to=saved_to
        )
    else:
        error = SimulationError(message, status=outcome.status, trajectory=trajectory, saved_to=saved_to)
    return error
