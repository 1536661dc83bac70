"""simulate(): one trajectory from one initial state, through the driver (driver.py) and the stepping core."""

from __future__ import annotations

import contextlib
import os
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

import numpy as np

from .driver import Run, RunSettings, Sink, stop_error
from .exceptions import InvalidArgumentError, SimulationError, SimulationInterrupted
from .files import RunLock, SigtermAsInterrupt, check_output, check_unlocked
from .integrators import Integrator, get_integrator
from .progress import ProgressBar
from .robot import Robot, check_system
from .torques import Torques
from .trajectory import PARTS_SUFFIX, Trajectory
from .validation import check_callable, check_flag, check_options, check_path, positive_count, positive_number


class Controller(Protocol):
    """A torque policy: ``controller(t, q, v) -> tau``, called at accepted states, held over the step."""

    def __call__(self, t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray: ...


class SensorController(Protocol):
    """A torque policy that reads a scene's sensors: it has an attribute ``sensors = True`` and is called as
    ``controller(t, q, v, readings) -> tau``, readings a dict of sensor name -> reading, shape (components,)."""

    sensors: bool

    def __call__(self, t: float, q: np.ndarray, v: np.ndarray, readings: dict[str, np.ndarray]) -> np.ndarray: ...


def simulate(
    system: Robot,
    q0: Any,
    v0: Any,
    *,
    duration: float,
    dt: float,
    integrator: str | Integrator = "rk4",
    controller: Controller | SensorController | None = None,
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
            object with a ``reset()`` method is reset before the run starts. One with an attribute ``sensors =
            True`` is called ``controller(t, q, v, readings)`` with the scene's sensors' readings (SensorController).
        out: write the trajectory to this .npz when the run ends, however it ends (completed, failed or
            interrupted), atomically.
        chunk: with `out`, stream the samples to disk every `chunk` samples (numbered files in out.npz.parts/,
            merged into `out` at the end or on an early stop), so memory stays bounded; the returned
            trajectory's arrays are then memory-mapped from `out`.
        on_sample: called as ``on_sample(t, q, v)`` at every sample, in order, shortly after it is computed (a live
            viewer, a progress display); it must not modify q or v.
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
        SimulationError: the run stopped early (status "diverged", "newton_failed", "step_collapsed", or "failed":
            the controller, on_sample or a scene's force raised, its exception chained as the cause; a controller
            output that is not a torque raises ControllerOutputError, also an InvalidArgumentError);
            ``.trajectory`` holds every finite sample so far.
        SimulationInterrupted: Ctrl-C; ``.trajectory`` holds every sample so far.
    """
    check_system(system)
    method = get_integrator(integrator)
    method.check_contract()
    check_options(method, options)
    q0 = system.check_q(q0, "q0")
    v0 = system.check_v(v0, "v0")
    duration = positive_number(duration, "duration")
    dt = positive_number(dt, "dt")
    check_callable(controller, "controller", "controller(t, q, v)")
    method.check_system(system)
    sink = make_sink(out, chunk)
    check_callable(on_sample, "on_sample", "on_sample(t, q, v)")
    check_flag(progress, "progress", optional=True)
    settings = RunSettings.check(method, duration, dt, options)
    reset = getattr(controller, "reset", None)
    if callable(reset):
        reset()  # a stateful controller starts every run afresh
    bar = ProgressBar(progress, duration, "s", "simulate", seconds=True)
    lock = RunLock(sink.out) if sink.out is not None else None
    # With an output, an unhandled SIGTERM stops the run like Ctrl-C (the samples written, the lock released),
    # then terminates the process as it would have.
    term = SigtermAsInterrupt() if lock is not None else None
    with term if term is not None else contextlib.nullcontext():
        if lock is not None:
            lock.acquire()  # two runs never write the same out; released however this run ends
            sink.run_id = lock.run_id
        try:
            run = Run(
                system=system,
                method=method,
                Q0=q0[None, :],
                V0=v0[None, :],
                settings=settings,
                torques=Torques.single(controller),
                sink=sink,
                on_sample=on_sample,
                progress=bar if bar.active else None,
                options=options,
            )
            try:
                run.execute()
            except KeyboardInterrupt:
                kept = run.finish()
                steps = run.stats(0)["steps"]
                raise SimulationInterrupted(
                    f"interrupted at t = {kept.t_end:.6g} s (step {steps}); {kept.samples} samples kept"
                    + (f"; {kept.problem}" if kept.problem else ""),
                    trajectory=kept.trajectory,
                    saved_to=kept.saved_to,
                    signal_name="SIGTERM" if term is not None and term.received else "SIGINT",
                ) from None
            finally:
                bar.close()
            outcome = run.outcomes[0]
            kept = run.finish()
            traj = kept.trajectory
            if kept.interrupted:  # the signal came while the samples were being written: they were written first
                raise SimulationInterrupted(
                    f"interrupted while writing the samples, after the run {outcome.status} at t = "
                    f"{kept.t_end:.6g} s; {kept.samples} samples kept" + (f"; {kept.problem}" if kept.problem else ""),
                    trajectory=traj,
                    saved_to=kept.saved_to,
                )
            if outcome.status != "completed":
                raise stop_error(outcome, traj, problem=kept.problem, saved_to=kept.saved_to) from outcome.cause
            if kept.problem:
                raise SimulationError(
                    f"the run completed, but {kept.problem}",
                    status="write_failed",
                    trajectory=traj,
                    saved_to=kept.saved_to,
                )
            assert traj is not None  # None only with a problem
            return traj
        finally:
            if lock is not None:
                lock.release()


def make_sink(out: str | os.PathLike[str] | None, chunk: Any) -> Sink:
    """Where the samples go besides memory (checked): nowhere, `out` at the end, or chunks of `out`.

    Checked before any work: out is a regular file or a new name in a writable folder (check_output), no other
    live run is writing it (its lock), and for a chunked run no parts folder is left from another run.
    """
    path = None
    if out is not None:
        check_path(out, "out", "a trajectory file (.npz)")
        check_output(out, "out")  # a symbolic link is written through (messages name the link)
        path = Path(out)
        check_unlocked(path)
    if chunk is not None:
        if path is None:
            raise InvalidArgumentError("chunk needs out: the chunks are streamed to out.npz.parts/ and merged")
        chunk = positive_count(chunk, "chunk", "samples")
        parts = path.with_name(path.name + PARTS_SUFFIX)
        if parts.exists():
            raise InvalidArgumentError(f"{parts} already exists (a previous chunked run's parts): move it first")
    return Sink(path, int(chunk) if chunk is not None else None)
