"""THE time-stepping loop: sampling, control timing, the energy ledger, divergence and early stops."""

from __future__ import annotations

import functools
import importlib.metadata
import math
import os
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from .exceptions import InvalidArgumentError, SimulationError, SimulationInterrupted
from .integrators import INTEGRATORS, Integrator, StepFailure, get_integrator
from .robot import Robot
from .step_control import PIController
from .trajectory import (
    PARTS_SUFFIX,
    ConstraintRecord,
    LedgerEntry,
    LimitViolations,
    Trajectory,
    chunk_path,
    combine_limit_violations,
    merge_parts,
)

# Energy blow-up: |energy_error| beyond this many times the run's energy scale is divergence, not error.
BLOWUP_FACTOR = 1e3
# An adaptive step below this fraction of the duration has collapsed.
MIN_STEP_FRACTION = 1e-12
_FIXED_STEP_OPTIONS = ("control_dt", "output_dt")
_ADAPTIVE_OPTIONS = ("atol", "control_dt", "max_step", "output_dt", "rtol")


class Controller(Protocol):
    """A torque policy: ``controller(t, q, v) -> tau``, called at accepted states, held over the step."""

    def __call__(self, t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray: ...


def simulate(
    system: Robot,
    q0: Any,
    v0: Any,
    *,
    duration: float,
    dt: float,
    integrator: str | Integrator = "rk4",
    controller: Controller | None = None,
    out: str | os.PathLike[str] | None = None,
    chunk: int | None = None,
    on_sample: Callable[[float, np.ndarray, np.ndarray], None] | None = None,
    progress: bool | None = None,
    **options: Any,
) -> Trajectory:
    """Integrate M(q) v' + C(q, v) v + g(q) = tau - D v from (q0, v0) for `duration` seconds.

    Args:
        system: the robot (or scene) to simulate.
        q0: initial configuration, shape (nq,).
        v0: initial velocity, shape (nv,).
        duration: simulated time [s], > 0.
        dt: integration step [s], > 0; fixed-step methods shorten the last step so that t[-1] == duration;
            adaptive methods take it as their first trial step.
        integrator: a registry name (`multibody-sim integrators` lists them) or an Integrator.
        controller: ``controller(t, q, v) -> tau`` (shape (nv,)), zero-order held; None applies no torque. An
            object with a ``reset()`` method is reset before the run starts.
        out: write the trajectory to this .npz when the run ends, however it ends (completed, failed or
            interrupted), atomically.
        chunk: with `out`, stream the samples to disk every `chunk` samples (numbered files in out.npz.parts/,
            merged into `out` at the end or on an early stop), so memory stays bounded; the returned
            trajectory's arrays are then memory-mapped from `out`.
        on_sample: called as ``on_sample(t, q, v)`` at every sample as it is computed (a live viewer, a progress
            display); it must not modify q or v.
        progress: a progress bar over simulated time on stderr: None shows one on a terminal for runs longer than
            a second, True always, False never.
        **options: ``output_dt``: sampling period [s] (a multiple of dt for fixed-step methods; adaptive methods
            sample it by dense output); default: every step. ``control_dt``: controller period [s] (a multiple
            of dt for fixed-step methods; adaptive methods shorten steps to land on it); default: every step.
            Adaptive methods only: ``rtol`` and ``atol`` (required: the error tolerances, relative and absolute,
            on configurations in the tangent space and on velocities) and ``max_step`` [s].

    Returns:
        The trajectory, with status "completed".

    Raises:
        InvalidArgumentError: a bad argument or option (the message names it).
        SimulationError: the run stopped early (status "diverged", "newton_failed", "step_collapsed");
            ``.trajectory`` holds every finite sample so far.
        SimulationInterrupted: Ctrl-C; ``.trajectory`` holds every sample so far.
    """
    method = get_integrator(integrator)
    check_options(method, options)
    q0 = system.check_q(q0, "q0")
    v0 = system.check_v(v0, "v0")
    duration = positive_number(duration, "duration")
    dt = positive_number(dt, "dt")
    if controller is not None and not callable(controller):
        raise InvalidArgumentError(
            f"controller must be callable as controller(t, q, v), got {type(controller).__name__}"
        )
    method.check_system(system)
    sink = _Sink(out, chunk)
    if on_sample is not None and not callable(on_sample):
        raise InvalidArgumentError(f"on_sample must be callable as on_sample(t, q, v), got {type(on_sample).__name__}")
    sink.on_sample = on_sample
    bar = ProgressBar(progress, duration, "s", "simulate", seconds=True)
    if bar.bar is not None and not bar.bar.disable:
        done = [0.0]

        def advance(t: float, q: np.ndarray, v: np.ndarray) -> None:
            bar.update(t - done[0])
            done[0] = t
            if on_sample is not None:
                on_sample(t, q, v)

        sink.on_sample = advance
    reset = getattr(controller, "reset", None)
    if callable(reset):
        reset()  # a stateful controller starts every run afresh
    try:
        return _run(system, method, q0, v0, duration, dt, controller, options, sink)
    finally:
        bar.close()


def _run(
    system: Robot,
    method: Integrator,
    q0: np.ndarray,
    v0: np.ndarray,
    duration: float,
    dt: float,
    controller: Controller | None,
    options: dict[str, Any],
    sink: _Sink,
) -> Trajectory:
    if method.adaptive:
        run: _Run = _AdaptiveRun(system, method, q0, v0, duration, dt, controller, options, sink)
    else:
        run = _FixedStepRun(system, method, q0, v0, duration, dt, controller, options, sink)
    return run.execute()


class ProgressBar:
    """A tqdm progress bar on stderr, or nothing: None shows one only on a terminal and only once the work has
    lasted a second (short runs stay silent), True always, False never."""

    def __init__(self, progress: bool | None, total: float, unit: str, desc: str, *, seconds: bool = False):
        self.bar = None
        if progress is False or (progress is None and not _is_terminal(sys.stderr)):
            return  # nothing to show: not even tqdm's import on the way into a run
        from tqdm.auto import tqdm

        self.bar = tqdm(
            total=total,
            unit=unit,
            desc=desc,
            disable=None if progress is None else False,
            delay=1.0 if progress is None else 0.0,
            leave=progress is True,
            file=sys.stderr,
            dynamic_ncols=True,
            # simulated time is a float: show it rounded, not as 1.8900000000000001/3.0
            bar_format="{desc}: {percentage:3.0f}%|{bar}| t = {n:.4g}/{total:.4g} s [{elapsed}<{remaining}]"
            if seconds
            else None,
        )

    def reset(self, total: int, unit: str) -> None:
        if self.bar is not None:
            self.bar.unit = unit
            self.bar.reset(total=total)

    def update(self, n: float) -> None:
        if self.bar is not None and n:
            self.bar.update(n)

    def close(self) -> None:
        if self.bar is not None:
            self.bar.close()


def _is_terminal(stream: Any) -> bool:
    try:
        return bool(stream is not None and stream.isatty())
    except (AttributeError, OSError, ValueError):  # closed or replaced streams
        return False


class _Sink:
    """Where samples go besides memory: nowhere, one file at the end, or chunk files merged at the end."""

    def __init__(self, out: str | os.PathLike[str] | None, chunk: Any):
        self.out = Path(out) if out is not None else None
        if chunk is not None:
            if self.out is None:
                raise InvalidArgumentError("chunk needs out: the chunks are streamed to out.npz.parts/ and merged")
            if isinstance(chunk, bool) or not isinstance(chunk, (int, np.integer)) or chunk < 1:
                raise InvalidArgumentError(f"chunk must be a positive whole number of samples, got {chunk!r}")
            parts = self.out.with_name(self.out.name + PARTS_SUFFIX)
            if parts.exists():
                raise InvalidArgumentError(f"{parts} already exists (a previous chunked run's parts): move it first")
        self.chunk = int(chunk) if chunk is not None else None
        self.written = 0  # chunk files written so far
        self.on_sample: Callable[[float, np.ndarray, np.ndarray], None] | None = None


def check_options(
    method: Integrator,
    options: dict[str, Any],
    fixed_step: tuple[str, ...] = _FIXED_STEP_OPTIONS,
    adaptive_only: tuple[str, ...] = _ADAPTIVE_OPTIONS,
) -> None:
    """Refuse options the method does not take (simulate's by default; the Stepper passes its own sets)."""
    valid = adaptive_only if method.adaptive else fixed_step
    for name in options:
        if name in valid:
            continue
        if name in adaptive_only:
            adaptive = sorted(n for n, m in INTEGRATORS.items() if m.adaptive)
            where = f" (it applies to the adaptive integrators: {', '.join(adaptive)})" if adaptive else ""
            raise InvalidArgumentError(
                f"option '{name}' does not apply to the fixed-step integrator '{method.name}'{where}"
            )
        raise InvalidArgumentError(f"unknown option '{name}' (valid for '{method.name}': {', '.join(valid) or 'none'})")
    if method.adaptive:
        missing = [name for name in ("rtol", "atol") if options.get(name) is None]
        if missing:
            raise InvalidArgumentError(
                f"integrator '{method.name}' is adaptive: pass {' and '.join(missing)} (error tolerances; "
                "e.g. rtol=1e-6, atol=1e-8)"
            )


def _is_number(value: Any) -> bool:
    # Numbers only: float() would also take "0.5" and True (1 s), which hide mistakes at the public boundary.
    return isinstance(value, (int, float, np.integer, np.floating)) and not isinstance(value, (bool, np.bool_))


def positive_number(value: Any, name: str, unit: str | None = "seconds") -> float:
    """value as a float if it is a positive finite number (not a string or bool), else InvalidArgumentError."""
    if not _is_number(value) or not (math.isfinite(value) and value > 0):
        what = f"a positive number of {unit}" if unit else "a positive number"
        raise InvalidArgumentError(f"{name} must be {what}, got {value!r}")
    return float(value)


def finite_number(value: Any, name: str) -> float:
    """value as a float if it is a finite number of seconds (a time; not a string or bool), else
    InvalidArgumentError."""
    if not _is_number(value) or not math.isfinite(value):
        raise InvalidArgumentError(f"{name} must be a finite number of seconds, got {value!r}")
    return float(value)


def steps_per(period: Any, dt: float, name: str) -> int:
    """How many steps of dt make `period` (None: 1), which must be a whole multiple of dt."""
    if period is None:
        return 1
    period = positive_number(period, name)
    k = round(period / dt)
    if k < 1 or abs(k * dt - period) > 1e-9 * period:
        raise InvalidArgumentError(f"{name} must be a whole multiple of dt = {dt:g} s, got {period:g} s")
    return k


class _Samples:
    """Growable per-sample arrays (preallocated when the number of samples is known)."""

    def __init__(self, nq: int, nv: int, n_elements: int, capacity: int, n_extra: int = 0):
        self.n = 0
        self.EXTRA = np.empty((capacity, n_extra))  # what a scene records per sample (springs, constraints)
        self.T = np.empty(capacity)
        self.Q = np.empty((capacity, nq))
        self.V = np.empty((capacity, nv))
        self.TAU = np.empty((capacity, nv))
        self.KIN = np.empty(capacity)
        self.POT = np.empty(capacity)
        self.FLOWS = np.empty((capacity, n_elements))

    def append(
        self,
        t: float,
        q: np.ndarray,
        v: np.ndarray,
        tau: np.ndarray,
        kinetic: float,
        potential: float,
        flows: np.ndarray,
    ) -> None:
        i = self.n
        if i == len(self.T):
            for name in ("T", "Q", "V", "TAU", "KIN", "POT", "FLOWS", "EXTRA"):
                old = getattr(self, name)
                new = np.empty((2 * len(old) + 16, *old.shape[1:]))
                new[:i] = old
                setattr(self, name, new)
        self.T[i], self.Q[i], self.V[i], self.TAU[i] = t, q, v, tau
        self.KIN[i], self.POT[i], self.FLOWS[i] = kinetic, potential, flows
        self.n = i + 1


class _Run:
    """One simulation's state while it runs: recording, control, early stops; subclasses hold the loop."""

    def __init__(
        self,
        system: Robot,
        method: Integrator,
        q0: np.ndarray,
        v0: np.ndarray,
        duration: float,
        dt: float,
        controller: Controller | None,
        options: dict[str, Any],
        capacity: int,
        sink: _Sink,
    ):
        self.system, self.method = system, method
        self.sink = sink
        if sink.chunk is not None:
            capacity = sink.chunk
        else:
            _check_memory(capacity, system)
            capacity = min(capacity, 1 << 20)  # the buffer grows past this; a feasible run need not reserve it all
        self.chunk_violations: list[LimitViolations] = []
        self.initial_energy = (0.0, 0.0)  # (T, V) at t = 0
        self.last_recorded = -math.inf  # time of the latest sample, written to disk or not
        self.duration, self.dt = duration, dt
        self.controller = controller
        self.options = options
        self.elements = system.ledger_elements
        self.record_fields = system.record_fields  # (category, name, width) of what the system records per sample
        self.samples = _Samples(
            system.nq, system.nv, len(self.elements), capacity, sum(width for _, _, width in self.record_fields)
        )
        self.is_work = np.array([kind == "work" for _, kind in self.elements])
        # The latest accepted state, kept current so that an early stop loses nothing.
        self.q, self.v, self.t, self.k = q0, v0, 0.0, 0
        self.tau = np.zeros(system.nv)
        self.flows = np.zeros(len(self.elements))
        self.controller_calls = 0
        limited = np.isfinite(system.effort_limit)
        self.effort = system.effort_limit if limited.any() else None
        self.saturated_calls = 0
        self.saturated_dofs = np.zeros(system.nv, dtype=int)
        self.evaluations = 0
        self.rejected = 0
        self.energy_scale = 0.0

    def execute(self) -> Trajectory:
        self.start = time.perf_counter()
        try:
            with np.errstate(over="ignore", invalid="ignore"):  # divergence is detected and reported, not warned
                status = self._loop()
        except KeyboardInterrupt:
            self._record_current()
            traj = self._finish("interrupted")
            raise SimulationInterrupted(
                f"interrupted at t = {self.t:.6g} s (step {self.k}); {len(traj)} samples kept", trajectory=traj
            ) from None
        if status is not None:
            reason, message = status
            raise SimulationError(message, status=reason, trajectory=self._finish(reason))
        return self._finish("completed")

    def _finish(self, status: str) -> Trajectory:
        """The whole run's trajectory, also written to `out` when asked (merging the chunks of a chunked run)."""
        out = self.sink.out
        if self.sink.chunk is None:
            traj = self._trajectory(status, time.perf_counter() - self.start)
            if out is not None:
                traj.save(out)
            return traj
        assert out is not None
        if self.samples.n or not self.sink.written:
            self._flush()
        traj = self._trajectory(status, time.perf_counter() - self.start)  # for its stats only
        merge_parts(
            out, status=status, stats=traj.stats, limit_violations=combine_limit_violations(self.chunk_violations)
        )
        return Trajectory.load(out, mmap=True)

    def _flush(self) -> None:
        """Write the samples in memory as the next chunk file and empty the buffer."""
        assert self.sink.out is not None
        traj = self._trajectory("running", time.perf_counter() - self.start)
        self.chunk_violations.append(traj.limit_violations)
        traj.save(chunk_path(self.sink.out, self.sink.written))
        self.sink.written += 1
        self.samples.n = 0

    def _loop(self) -> tuple[str, str] | None:
        """Step to the end; returns (status, message) on an early stop, None on completion."""
        raise NotImplementedError

    def _control(self, t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        assert self.controller is not None
        q.setflags(write=False)  # the controller sees the state; it must not edit it
        v.setflags(write=False)
        tau = self.controller(t, q, v)
        self.controller_calls += 1
        system = self.system
        fast = type(tau) is np.ndarray and tau.dtype == np.float64 and tau.shape == (system.nv,)
        if not fast or not math.isfinite(tau @ tau) or (system.floating_base and tau[:6].any()):
            try:  # the full check, with the precise reason
                tau = system.check_tau(tau)
            except InvalidArgumentError as exc:
                raise InvalidArgumentError(f"controller output at t = {t:.6g} s: {exc}") from None
        if self.effort is not None:  # actuators saturate at the URDF's effort limits: clip, count, report
            over = np.abs(tau) > self.effort
            if over.any():
                tau = np.clip(tau, -self.effort, self.effort)
                self.saturated_calls += 1
                self.saturated_dofs += over
        return tau

    def _record(self, t: float, q: np.ndarray, v: np.ndarray, flows: np.ndarray) -> tuple[str, str] | None:
        """Store a sample (with the torque in force from t on); returns (status, message) if energy blew up."""
        samples = self.samples
        T, V = self.system.unchecked_energies(q, v)
        if not math.isfinite(T + V):  # a huge state whose energy overflows: keep only finite samples
            fastest = int(np.argmax(np.abs(v)))
            return "diverged", (
                f"diverged at t = {t:.6g} s (step {self.k}): the energy became non-finite, fastest in "
                f"'{self.system.dof_names[fastest]}' ({v[fastest]:.3g}); {self._cure()}"
            )
        if t == 0.0:
            self.initial_energy = (T, V)
            self.energy_scale = T + abs(V) + self.system.energy_scale
        samples.append(t, q, v, self.tau, T, V, flows)
        if self.record_fields:
            self.system.unchecked_record(q, v, self.tau, t, samples.EXTRA[samples.n - 1])
        self.last_recorded = t
        if self.sink.on_sample is not None:
            self.sink.on_sample(t, q, v)
        if samples.n == self.sink.chunk:
            self._flush()
        if t == 0.0:
            return None
        work = flows[self.is_work].sum()
        dissipated = flows[~self.is_work].sum()
        error = T + V - sum(self.initial_energy) - work + dissipated
        # Dissipation is left out of the scale: a diverging damped mode inflates it without bound, while a real
        # run can only dissipate what it had or was given (the scale and the work).
        bound = BLOWUP_FACTOR * (self.energy_scale + abs(work))
        if abs(error) > bound or dissipated > bound:
            fastest = int(np.argmax(np.abs(v)))
            what = (
                f"the energy error {error:.3g} J" if abs(error) > bound else f"the dissipated energy {dissipated:.3g} J"
            )
            return "diverged", (
                f"diverged at t = {t:.6g} s (step {self.k}): {what} exceeds {BLOWUP_FACTOR:g} times the run's "
                f"energy scale ({bound / BLOWUP_FACTOR:.3g} J), fastest in '{self.system.dof_names[fastest]}' "
                f"({v[fastest]:.3g}); {self._cure()}"
            )
        return None

    def _record_current(self) -> None:
        """Keep the latest state as a last sample if it is not one already (early stops lose nothing)."""
        if self.last_recorded == self.t:
            return
        self._record(self.t, self.q, self.v, self.flows)

    def _stopped(self, status: str, message: str) -> tuple[str, str]:
        self._record_current()
        return status, message

    def _diverged_nonfinite(self, t_next: float, q: np.ndarray, v: np.ndarray) -> tuple[str, str]:
        bad_v = ~np.isfinite(v)
        if bad_v.any():
            dof = int(np.argmax(bad_v))
        else:
            finite_q = np.where(np.isfinite(q), q, 0.0)
            dof = int(np.argmax(~np.isfinite(self.system.space.difference(self.q, finite_q))))
        return self._stopped(
            "diverged",
            (
                f"diverged at t = {t_next:.6g} s (step {self.k + 1}): the state became non-finite in "
                f"'{self.system.dof_names[dof]}'; {self._cure()}"
            ),
        )

    def _cure(self) -> str:
        implicit = stable_implicit_integrators(self.system)
        also = f", or an implicit integrator ({', '.join(implicit)})" if implicit else ""
        return f"try a smaller dt (now {self.dt:g} s){also}"

    def _trajectory(self, status: str, wall_time: float) -> Trajectory:
        s, system = self.samples, self.system
        n = s.n
        t, Q = s.T[:n].copy(), s.Q[:n].copy()
        kinetic, potential, flows = s.KIN[:n].copy(), s.POT[:n].copy(), s.FLOWS[:n]
        ledger = {name: LedgerEntry(kind, flows[:, j].copy()) for j, (name, kind) in enumerate(self.elements)}
        potentials, constraints = split_records(self.record_fields, s.EXTRA[:n])
        ledger.update(potentials)
        work = flows[:, self.is_work].sum(axis=1)
        dissipated = flows[:, ~self.is_work].sum(axis=1)
        total = kinetic + potential
        error = total - sum(self.initial_energy) - work + dissipated
        return Trajectory(
            t=t,
            q=Q,
            v=s.V[:n].copy(),
            tau=s.TAU[:n].copy(),
            kinetic_energy=kinetic,
            potential_energy=potential,
            total_energy=total,
            work=work,
            dissipated=dissipated,
            energy_error=error,
            ledger=ledger,
            constraints=constraints,
            limit_violations=find_limit_violations(system, t, Q),
            stats={
                "steps": self.k,
                "rejected_steps": self.rejected,
                "evaluations": self.evaluations,
                "controller_calls": self.controller_calls,
                "saturated_controls": self.saturated_calls,
                "saturated_dofs": {system.dof_names[i]: int(n) for i, n in enumerate(self.saturated_dofs) if n},
                "wall_time": wall_time,
            },
            status=status,
            metadata=self._metadata(),
        )

    def _metadata(self) -> dict[str, Any]:
        return {
            **run_metadata(self.system),
            "integrator": self.method.name,
            "options": {"dt": self.dt, "duration": self.duration, **self.options},
            "controller": None
            if self.controller is None
            else getattr(self.controller, "__qualname__", type(self.controller).__qualname__),
        }


class _FixedStepRun(_Run):
    """Steps of dt, the last one shortened to land on the duration."""

    def __init__(
        self,
        system: Robot,
        method: Integrator,
        q0: np.ndarray,
        v0: np.ndarray,
        duration: float,
        dt: float,
        controller: Controller | None,
        options: dict[str, Any],
        sink: _Sink,
    ):
        self.output_every = steps_per(options.get("output_dt"), dt, "output_dt")
        self.control_every = steps_per(options.get("control_dt"), dt, "control_dt")
        # Never count a last sliver of round-off as a step: 1.0 / 0.1 is 10 steps, not 11.
        self.n_steps = max(1, math.ceil(duration / dt - 1e-9))
        capacity = (self.n_steps - 1) // self.output_every + 2
        super().__init__(system, method, q0, v0, duration, dt, controller, options, capacity, sink)

    def _loop(self) -> tuple[str, str] | None:
        system, step, dt, n_steps = self.system, self.method.step, self.dt, self.n_steps
        controller, control_every, output_every = self.controller, self.control_every, self.output_every
        method = self.method
        count_evaluations = method.implicit  # Newton iterations vary; explicit methods have a fixed count
        q, v, tau, flows = self.q, self.v, self.tau, self.flows
        for k in range(n_steps):
            t = k * dt
            if controller is not None and k % control_every == 0:
                tau = self._control(t, q, v)
            self.tau = tau
            if k % output_every == 0:
                problem = self._record(t, q, v, flows)
                if problem:
                    return problem
            h = dt if k < n_steps - 1 else self.duration - t
            try:
                q_next, v_next, step_flows = step(system, q, v, tau, h, t)
            except StepFailure as failure:
                self.evaluations += method.last_evaluations  # a failed Newton solve still cost its evaluations
                return self._stopped(
                    failure.status,
                    f"{failure.status} at t = {t:.6g} s (step {k + 1}): {failure}; try a smaller dt (now {dt:g} s)",
                )
            self.evaluations += method.last_evaluations if count_evaluations else method.evaluations_per_step
            # Cheap finiteness check on every step: NaN or inf anywhere makes the sum non-finite (so can a huge
            # but finite state, whose squares overflow: the exact check below tells them apart).
            if not math.isfinite(q_next @ q_next + v_next @ v_next) and not (
                np.isfinite(q_next).all() and np.isfinite(v_next).all()
            ):
                return self._diverged_nonfinite(t + h, q_next, v_next)
            q, v = q_next, v_next
            flows = flows + step_flows
            self.q, self.v, self.t, self.k, self.flows = q, v, t + h, k + 1, flows
        self.t = self.duration
        return self._record(self.duration, q, v, flows)


class _AdaptiveRun(_Run):
    """Steps chosen by a PI controller on an embedded error estimate; samples by dense output."""

    method: Any  # an adaptive method: attempt(), dense_output(), embedded_order, fsal

    def __init__(
        self,
        system: Robot,
        method: Any,
        q0: np.ndarray,
        v0: np.ndarray,
        duration: float,
        dt: float,
        controller: Controller | None,
        options: dict[str, Any],
        sink: _Sink,
    ):
        self.rtol = positive_number(options["rtol"], "rtol", "units")
        self.atol = positive_number(options["atol"], "atol", "units")
        self.max_step = (
            positive_number(options["max_step"], "max_step") if options.get("max_step") is not None else math.inf
        )
        self.output_dt = (
            positive_number(options["output_dt"], "output_dt") if options.get("output_dt") is not None else None
        )
        self.control_dt = (
            positive_number(options["control_dt"], "control_dt") if options.get("control_dt") is not None else None
        )
        capacity = math.ceil(duration / self.output_dt) + 2 if self.output_dt else 1024
        super().__init__(system, method, q0, v0, duration, dt, controller, options, capacity, sink)

    def _loop(self) -> tuple[str, str] | None:
        system, method, duration = self.system, self.method, self.duration
        rtol, atol, output_dt, control_dt = self.rtol, self.atol, self.output_dt, self.control_dt
        controller = PIController(method.embedded_order, max_step=self.max_step, min_step=MIN_STEP_FRACTION * duration)
        fsal = method.fsal
        q, v, flows, t = self.q, self.v, self.flows, 0.0
        tau = self._control(t, q, v) if self.controller is not None else self.tau
        self.tau = tau
        problem = self._record(t, q, v, flows)
        if problem:
            return problem
        next_output, next_control = 1, 1  # indices of the next output and control instants
        h = min(self.dt, self.max_step)
        first_stage = None
        while t < duration:
            # Land exactly on the duration and on control instants (the torque changes there).
            t_stop = duration if control_dt is None else min(duration, next_control * control_dt)
            landing = t + h >= t_stop - 1e-12 * duration
            h_try = t_stop - t if landing else h
            attempt = method.attempt(system, q, v, tau, h_try, rtol=rtol, atol=atol, first_stage=first_stage, t=t)
            self.evaluations += attempt.evaluations
            accepted, h = controller.next_step(h_try, attempt.error)
            if not accepted:
                self.rejected += 1
                first_stage = attempt.stages[0]  # same start state, same torque
                if h < controller.min_step:
                    return self._stopped(
                        "step_collapsed",
                        (
                            f"step_collapsed at t = {t:.6g} s (step {self.k + 1}): the step fell to {h:.3g} s, below "
                            f"the {controller.min_step:.3g} s minimum (error norm {attempt.error:.3g}); "
                            f"the problem may be stiff or singular here: {self._stiff_cure()}"
                        ),
                    )
                continue
            if h < controller.min_step:
                return self._stopped(
                    "step_collapsed",
                    (
                        f"step_collapsed at t = {t:.6g} s (step {self.k + 1}): the step fell to {h:.3g} s, below "
                        f"the {controller.min_step:.3g} s minimum; the problem may be stiff or singular here: "
                        f"{self._stiff_cure()}"
                    ),
                )
            t_next = t_stop if landing else t + h_try
            if output_dt is not None:  # dense output at the sample instants inside the step
                while next_output * output_dt < min(t_next, duration) - 1e-12 * duration:
                    t_out = next_output * output_dt
                    q_out, v_out, flows_out = method.dense_output(system, q, v, attempt, h_try, (t_out - t) / h_try)
                    problem = self._record(t_out, q_out, v_out, flows + flows_out)
                    if problem:
                        return problem
                    next_output += 1
                self.evaluations += attempt.extra_evaluations
            q, v, t = attempt.q, attempt.v, t_next
            flows = flows + attempt.flows
            self.q, self.v, self.t, self.k, self.flows = q, v, t, self.k + 1, flows
            first_stage = attempt.stages[-1] if fsal else None
            reached_control = control_dt is not None and landing and t_stop == next_control * control_dt
            if reached_control:
                next_control += 1
            if self.controller is not None and t < duration and (control_dt is None or reached_control):
                tau = self._control(t, q, v)
                self.tau = tau
                first_stage = None  # the stage depends on the torque
            if output_dt is None or t >= duration:
                problem = self._record(t, q, v, flows)
                if problem:
                    return problem
            elif abs(t - next_output * output_dt) <= 1e-12 * duration:
                problem = self._record(t, q, v, flows)
                if problem:
                    return problem
                next_output += 1
        return None

    def _stiff_cure(self) -> str:
        implicit = stable_implicit_integrators(self.system)
        return (
            f"try an implicit integrator ({', '.join(implicit)}) or looser tolerances"
            if implicit
            else "try looser tolerances"
        )


def _check_memory(n_samples: int, system: Robot) -> None:
    """Refuse a run whose samples cannot fit in memory, before allocating them (a MemoryError helps no one)."""
    per_sample = 8 * (12 + system.nq + 3 * system.nv + 2 * len(system.ledger_elements))  # buffer and result
    needed = n_samples * per_sample
    try:
        available = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):  # not on Linux: assume a generous machine
        available = 1 << 40
    if needed > available:
        raise InvalidArgumentError(
            f"this run would keep {n_samples:.3g} samples ({needed / 2**30:.3g} GiB) in memory, more than the "
            f"{available / 2**30:.3g} GiB available: sample less often (output_dt) or stream to disk (out= and "
            "chunk=; --chunk in the CLI)"
        )


def stable_implicit_integrators(system: Robot) -> list[str]:
    """Names of the A-stable implicit integrators that accept this system (the cure for stiffness)."""
    names = []
    for name, method in sorted(INTEGRATORS.items()):
        if method.implicit and method.a_stable:
            try:
                method.check_system(system)
            except InvalidArgumentError:
                continue
            names.append(name)
    return names


def split_records(
    record_fields: tuple[tuple[str, str, int], ...], extra: np.ndarray
) -> tuple[dict[str, LedgerEntry], dict[str, ConstraintRecord]]:
    """A system's per-sample records (columns of `extra`, shape (n, Σ widths), as Robot.unchecked_record writes
    them) as the Trajectory's ledger potentials and constraint records (copies)."""
    potentials, constraints = {}, {}
    column = 0
    for category, name, width in record_fields:
        block = extra[:, column : column + width]
        column += width
        if category == "potential":
            potentials[name] = LedgerEntry("potential", block[:, 0].copy())
        else:  # "constraint": the forces, then the drift and the velocity drift
            constraints[name] = ConstraintRecord(block[:, :-2].copy(), block[:, -2].copy(), block[:, -1].copy())
    return potentials, constraints


def find_limit_violations(system: Robot, t: np.ndarray, Q: np.ndarray) -> LimitViolations:
    if not len(t):
        return LimitViolations()
    excess = system.limit_excess(Q)
    outside = excess > 0
    if not outside.any():
        return LimitViolations()
    i, j = np.unravel_index(int(np.argmax(excess)), excess.shape)
    joint = next(
        system.model.names[jid]
        for jid in range(1, system.model.njoints)
        if system.model.joints[jid].idx_q <= j < system.model.joints[jid].idx_q + system.model.joints[jid].nq
    )
    return LimitViolations(
        count=int(outside.sum()),
        samples=int(outside.any(axis=1).sum()),
        worst_joint=joint,
        worst_excess=float(excess[i, j]),
        worst_time=float(t[i]),
    )


def run_metadata(system: Robot) -> dict[str, Any]:
    """The metadata every trajectory starts with: package versions and how its robot (or scene) was made."""
    return {
        "versions": dict(_versions()),
        "robot": {
            "name": system.name,
            "nq": system.nq,
            "nv": system.nv,
            "floating_base": system.floating_base,
            "damping": bool(system.source.get("load_robot", {}).get("damping", True)),
            "joint_names": system.joint_names,
            "dof_names": system.dof_names,
            **system.source,  # load_robot (the full arguments), urdf_path, urdf_sha256; a scene's TOML
        },
    }


@functools.cache
def _versions() -> dict[str, str]:
    versions = {}
    for dist in ("multibody-sim", "pin", "example-robot-data", "numpy", "yourdfpy"):
        try:
            versions[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            versions[dist] = "not installed"
    return versions
