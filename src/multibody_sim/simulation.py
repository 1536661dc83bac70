"""THE time-stepping loop: sampling, control timing, the energy ledger, divergence and early stops."""

from __future__ import annotations

import importlib.metadata
import math
import time
from typing import Any, Protocol

import numpy as np

from .exceptions import InvalidArgumentError, SimulationError, SimulationInterrupted
from .integrators import INTEGRATORS, Integrator, StepFailure, get_integrator
from .robot import Robot
from .trajectory import LedgerEntry, LimitViolations, Trajectory

# Energy blow-up: |energy_error| beyond this many times the run's energy scale is divergence, not error.
BLOWUP_FACTOR = 1e3
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
    **options: Any,
) -> Trajectory:
    """Integrate M(q) v' + C(q, v) v + g(q) = tau - D v from (q0, v0) for `duration` seconds.

    Args:
        system: the robot (or scene) to simulate.
        q0: initial configuration, shape (nq,).
        v0: initial velocity, shape (nv,).
        duration: simulated time [s], > 0.
        dt: integration step [s], > 0; the last step is shortened so that t[-1] == duration.
        integrator: a registry name (`multibody-sim integrators` lists them) or an Integrator.
        controller: ``controller(t, q, v) -> tau`` (shape (nv,)), zero-order held; None applies no torque.
        **options: ``output_dt`` (sampling period [s], a multiple of dt; default every step) and
            ``control_dt`` (controller period [s], a multiple of dt; default every step).

    Returns:
        The trajectory, with status "completed".

    Raises:
        InvalidArgumentError: a bad argument or option (the message names it).
        SimulationError: the state diverged; ``.trajectory`` holds every finite sample so far.
        SimulationInterrupted: Ctrl-C; ``.trajectory`` holds every sample so far.
    """
    method = get_integrator(integrator)
    _check_options(method, options)
    q0 = system.check_q(q0, "q0")
    v0 = system.check_v(v0, "v0")
    duration = _positive(duration, "duration")
    dt = _positive(dt, "dt")
    if controller is not None and not callable(controller):
        raise InvalidArgumentError(f"controller must be callable as controller(t, q, v), got {type(controller).__name__}")
    output_every = _steps_per(options.get("output_dt"), dt, "output_dt")
    control_every = _steps_per(options.get("control_dt"), dt, "control_dt")
    run = _Run(system, method, q0, v0, duration, dt, controller, output_every, control_every, options)
    return run.execute()


def _check_options(method: Integrator, options: dict[str, Any]) -> None:
    valid = _ADAPTIVE_OPTIONS if method.adaptive else _FIXED_STEP_OPTIONS
    for name in options:
        if name in valid:
            continue
        if name in _ADAPTIVE_OPTIONS:
            adaptive = sorted(n for n, m in INTEGRATORS.items() if m.adaptive)
            where = f" (it applies to the adaptive integrators: {', '.join(adaptive)})" if adaptive else ""
            raise InvalidArgumentError(
                f"option '{name}' does not apply to the fixed-step integrator '{method.name}'{where}"
            )
        raise InvalidArgumentError(f"unknown option '{name}' (valid for '{method.name}': {', '.join(valid)})")


def _positive(value: Any, name: str) -> float:
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise InvalidArgumentError(f"{name} must be a positive number of seconds, got {value!r}") from None
    if not (math.isfinite(value) and value > 0):
        raise InvalidArgumentError(f"{name} must be a positive number of seconds, got {value!r}")
    return value


def _steps_per(period: Any, dt: float, name: str) -> int:
    """How many steps of dt make `period` (None: 1), which must be a whole multiple of dt."""
    if period is None:
        return 1
    period = _positive(period, name)
    k = round(period / dt)
    if k < 1 or abs(k * dt - period) > 1e-9 * period:
        raise InvalidArgumentError(f"{name} must be a whole multiple of dt = {dt:g} s, got {period:g} s")
    return k


class _Run:
    """One simulation's state while it runs; execute() is the stepping loop."""

    def __init__(self, system: Robot, method: Integrator, q0: np.ndarray, v0: np.ndarray, duration: float,
                 dt: float, controller: Controller | None, output_every: int, control_every: int,
                 options: dict[str, Any]):
        self.system, self.method = system, method
        self.duration, self.dt = duration, dt
        self.controller = controller
        self.output_every, self.control_every = output_every, control_every
        self.options = options
        # Never count a last sliver of round-off as a step: 1.0 / 0.1 is 10 steps, not 11.
        self.n_steps = max(1, math.ceil(duration / dt - 1e-9))
        n_samples = (self.n_steps - 1) // output_every + 2
        nq, nv = system.nq, system.nv
        self.elements = system.ledger_elements
        self.T = np.empty(n_samples)
        self.Q = np.empty((n_samples, nq))
        self.V = np.empty((n_samples, nv))
        self.TAU = np.empty((n_samples, nv))
        self.KIN = np.empty(n_samples)
        self.POT = np.empty(n_samples)
        self.FLOWS = np.empty((n_samples, len(self.elements)))
        self.is_work = np.array([kind == "work" for _, kind in self.elements])
        self.n = 0  # samples recorded
        self.q, self.v, self.t, self.k = q0, v0, 0.0, 0
        self.tau = np.zeros(nv)
        self.flows = np.zeros(len(self.elements))
        self.controller_calls = 0
        self.energy_scale = 0.0

    def execute(self) -> Trajectory:
        start = time.perf_counter()
        try:
            status = self._loop()
        except KeyboardInterrupt:
            self._record_current()
            traj = self._trajectory("interrupted", time.perf_counter() - start)
            raise SimulationInterrupted(
                f"interrupted at t = {self.t:.6g} s (step {self.k} of {self.n_steps}); "
                f"{len(traj)} samples kept", trajectory=traj
            ) from None
        wall = time.perf_counter() - start
        if status is not None:
            reason, message = status
            raise SimulationError(message, status=reason, trajectory=self._trajectory(reason, wall))
        return self._trajectory("completed", wall)

    def _loop(self) -> tuple[str, str] | None:
        """Step to the end; returns (status, message) on an early stop, None on completion."""
        system, step, dt, n_steps = self.system, self.method.step, self.dt, self.n_steps
        controller, control_every, output_every = self.controller, self.control_every, self.output_every
        nv = system.nv
        q, v, tau, flows = self.q, self.v, self.tau, self.flows
        for k in range(n_steps):
            t = k * dt
            if controller is not None and k % control_every == 0:
                tau = self._control(controller, t, q, v, nv)
            if k % output_every == 0:
                self.tau = tau
                problem = self._record(t, q, v, flows)
                if problem:
                    return problem
            h = dt if k < n_steps - 1 else self.duration - t
            try:
                q_next, v_next, step_flows = step(system, q, v, tau, h)
            except StepFailure as failure:
                self.tau = tau
                self._record_current()
                return failure.status, (
                    f"{failure.status} at t = {t:.6g} s (step {k + 1}): {failure}; {self._cure()}"
                )
            # Cheap finiteness check on every step: NaN or inf anywhere makes the sum non-finite.
            if not math.isfinite(q_next @ q_next + v_next @ v_next):
                self.tau = tau
                return self._diverged_nonfinite(k, t, q_next, v_next)
            q, v = q_next, v_next
            flows = flows + step_flows
            self.q, self.v, self.t, self.k, self.flows = q, v, t + h, k + 1, flows
        self.tau = tau
        self.t = self.duration
        return self._record(self.duration, q, v, flows)

    def _control(self, controller: Controller, t: float, q: np.ndarray, v: np.ndarray, nv: int) -> np.ndarray:
        q.setflags(write=False)  # the controller sees the state; it must not edit it
        v.setflags(write=False)
        tau = controller(t, q, v)
        self.controller_calls += 1
        if type(tau) is not np.ndarray or tau.dtype != np.float64:
            tau = np.asarray(tau, dtype=float)
        if tau.shape != (nv,) or not math.isfinite(tau @ tau) or (self.system.floating_base and tau[:6].any()):
            self.system.check_tau(tau, f"controller output at t = {t:.6g} s")  # raises with the precise reason
        return tau

    def _record(self, t: float, q: np.ndarray, v: np.ndarray, flows: np.ndarray) -> tuple[str, str] | None:
        """Store a sample; returns (status, message) if the energy has blown up."""
        i = self.n
        T, V = self.system.unchecked_energies(q, v)
        self.T[i], self.Q[i], self.V[i], self.TAU[i] = t, q, v, self.tau
        self.KIN[i], self.POT[i], self.FLOWS[i] = T, V, flows
        self.n = i + 1
        if i == 0:
            self.energy_scale = T + abs(V) + self.system.energy_scale
            return None
        work = flows[self.is_work].sum()
        dissipated = flows[~self.is_work].sum()
        error = T + V - self.KIN[0] - self.POT[0] - work + dissipated
        bound = BLOWUP_FACTOR * (self.energy_scale + abs(work) + abs(dissipated))
        if not math.isfinite(T + V) or abs(error) > bound:
            fastest = int(np.argmax(np.abs(v)))
            return "diverged", (
                f"diverged at t = {t:.6g} s (step {self.k}): the energy error {error:.3g} J exceeds "
                f"{BLOWUP_FACTOR:g} times the run's energy scale ({bound / BLOWUP_FACTOR:.3g} J), fastest in "
                f"'{self.system.dof_names[fastest]}' ({v[fastest]:.3g}); {self._cure()}"
            )
        return None

    def _record_current(self) -> None:
        """Keep the latest state as a last sample if it is not one already (early stops lose nothing)."""
        if self.n and self.T[self.n - 1] == self.t:
            return
        self._record(self.t, self.q, self.v, self.flows)

    def _diverged_nonfinite(self, k: int, t: float, q: np.ndarray, v: np.ndarray) -> tuple[str, str]:
        self._record_current()
        bad_v = ~np.isfinite(v)
        dof = int(np.argmax(bad_v)) if bad_v.any() else int(np.argmax(~np.isfinite(self.system.space.difference(
            self.q, np.where(np.isfinite(q), q, 0.0)))))
        name = self.system.dof_names[dof]
        return "diverged", (
            f"diverged at t = {t:.6g} s (step {k + 1}): the state became non-finite in '{name}'; {self._cure()}"
        )

    def _cure(self) -> str:
        implicit = sorted(n for n, m in INTEGRATORS.items() if m.implicit)
        also = f", or an implicit integrator ({', '.join(implicit)})" if implicit else ""
        return f"try a smaller dt (now {self.dt:g} s){also}"

    def _trajectory(self, status: str, wall_time: float) -> Trajectory:
        n, system = self.n, self.system
        t, Q = self.T[:n].copy(), self.Q[:n].copy()
        kinetic, potential, flows = self.KIN[:n].copy(), self.POT[:n].copy(), self.FLOWS[:n]
        ledger = {name: LedgerEntry(kind, flows[:, j].copy()) for j, (name, kind) in enumerate(self.elements)}
        work = flows[:, self.is_work].sum(axis=1)
        dissipated = flows[:, ~self.is_work].sum(axis=1)
        total = kinetic + potential
        error = total - total[0] - work + dissipated if n else total
        steps = self.k
        return Trajectory(
            t=t, q=Q, v=self.V[:n].copy(), tau=self.TAU[:n].copy(),
            kinetic_energy=kinetic, potential_energy=potential, total_energy=total,
            work=work, dissipated=dissipated, energy_error=error, ledger=ledger,
            limit_violations=_limit_violations(system, t, Q),
            stats={"steps": steps, "rejected_steps": 0, "evaluations": steps * self.method.evaluations_per_step,
                   "controller_calls": self.controller_calls, "wall_time": wall_time},
            status=status,
            metadata=self._metadata(),
        )

    def _metadata(self) -> dict[str, Any]:
        system = self.system
        return {
            "versions": _versions(),
            "robot": {"name": system.name, "nq": system.nq, "nv": system.nv, "floating_base": system.floating_base,
                      "joint_names": system.joint_names, "dof_names": system.dof_names, **system.source},
            "integrator": self.method.name,
            "options": {"dt": self.dt, "duration": self.duration, **self.options},
            "controller": None if self.controller is None else getattr(
                self.controller, "__qualname__", type(self.controller).__qualname__),
        }


def _limit_violations(system: Robot, t: np.ndarray, Q: np.ndarray) -> LimitViolations:
    if not len(t):
        return LimitViolations()
    excess = system.limit_excess(Q)
    outside = excess > 0
    if not outside.any():
        return LimitViolations()
    i, j = np.unravel_index(int(np.argmax(excess)), excess.shape)
    joint = next(system.model.names[jid] for jid in range(1, system.model.njoints)
                 if system.model.joints[jid].idx_q <= j < system.model.joints[jid].idx_q + system.model.joints[jid].nq)
    return LimitViolations(count=int(outside.sum()), samples=int(outside.any(axis=1).sum()), worst_joint=joint,
                           worst_excess=float(excess[i, j]), worst_time=float(t[i]))


def _versions() -> dict[str, str]:
    versions = {}
    for dist in ("multibody-sim", "pin", "example-robot-data", "numpy", "yourdfpy"):
        try:
            versions[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            versions[dist] = "not installed"
    return versions
