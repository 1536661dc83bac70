"""Step by step: a stateful stepper for co-simulation, RL and MPC loops: the stepping core of simulate(), advanced
one control interval per call."""

from __future__ import annotations

import math
from typing import Any, NamedTuple, cast

import numpy as np

from .core import Core, RowStop, cure_for_dt, stop_message
from .driver import choose_kernel, core_class
from .exceptions import InvalidArgumentError, SimulationError
from .integrators import Integrator, get_integrator
from .monitor import Monitor
from .recording import SampleStore
from .robot import Robot, check_system, real_array
from .rollout import check_batch
from .sensors import run_sensing
from .simulation import Controller, SensorController
from .step_control import SLIVER, ConstantStep, PIController
from .torques import Saturation, check_sensor_controller, check_torque, reads_sensors
from .trajectory import LedgerEntry, Trajectory
from .validation import (
    check_callable,
    check_flag,
    check_options,
    check_ratio,
    finite_number,
    positive_count,
    positive_number,
    relative_tolerance,
    steps_per,
    whole_number,
)

_ADAPTIVE_OPTIONS = ("atol", "max_step", "rtol")


class StepperState(NamedTuple):
    """The stepper's state after a step: time [s], configuration (nq,) and velocity (nv,) (read-only arrays)."""

    t: float
    q: np.ndarray
    v: np.ndarray


class Stepper:
    """Advance a robot one control interval at a time with a torque you choose at every call (what mj_step and
    Drake's Simulator.AdvanceTo give their users), through the stepping core of :func:`multibody_sim.simulate`.

    ``step(tau)`` holds tau over one control interval (``control_dt``, default ``dt``); ``advance_to(t,
    controller)`` steps to time t, calling the controller at the start of every control interval. N calls of
    ``step(controller(t, q, v))`` from (q0, v0) at t = 0 give ``simulate(..., controller=..., control_dt=...)``'s
    samples at the control instants bit for bit (same integrator, same dt): times are ``t0 + k·dt`` with k
    counted, never summed, and torques saturate at the URDF's effort limits (clipped and counted in ``stats``), as
    simulate's controller outputs do. A torque given to step() restarts the integrator's solver state (an FSAL
    stage taken with the previous torque is not reused), as a controller call in simulate() does; step() without
    a torque holds the previous one and keeps it.

    Adaptive integrators (bs32, dp54, dop853) cover each control interval with error-controlled steps (the PI
    controller of simulate, its step size carried from one call to the next) landing on its end, as simulate()
    does with ``control_dt``. They need ``rtol`` and ``atol``; the landing tolerance and the smallest step are
    simulate's: a fraction of max(dt, |t|).

    A step that fails (the state turns non-finite, the energy blows up, Newton fails, the adaptive step
    collapses, the controller raises) raises :class:`SimulationError` as simulate() does and leaves the stepper
    at the state before the call; the error's ``.trajectory`` holds that state as its one sample.

    The energy ledger accumulates as the stepper runs: ``work`` and ``dissipated`` (and ``ledger`` per element)
    come from the integrator's own quadrature, and the energies are computed on demand from the current state.
    Setting ``q`` or ``v`` by hand is an intervention, not dynamics: it shifts the reference energy so that
    ``energy_error`` (H − H_ref − work + dissipated) stays a check on the integration alone.

    Attributes:
        system: the robot (or scene).
        integrator: the integration method.
        dt: the step [s].
        control_dt: the control interval [s] one step() covers.
        options: the adaptive options (rtol, atol, max_step) as given.
        stats: steps, rejected_steps, evaluations (forward dynamics), controller_calls, saturated_controls and
            saturated_dofs since the last reset.
    """

    def __init__(
        self,
        system: Robot,
        *,
        dt: float,
        integrator: str | Integrator = "rk4",
        control_dt: float | None = None,
        q0: Any = None,
        v0: Any = None,
        t0: float = 0.0,
        check_energy: bool = True,
        **options: Any,
    ):
        """A stepper at (q0, v0) and time t0.

        Args:
            system: the robot (or scene) to advance.
            dt: the step [s], > 0.
            integrator: a registry name (`multibody-sim integrators` lists them) or an Integrator.
            control_dt: the control interval [s] one step() covers (a multiple of dt for fixed-step methods);
                default dt.
            q0: initial configuration, shape (nq,); default the neutral configuration. reset() returns here.
            v0: initial velocity, shape (nv,); default zero. reset() returns here.
            t0: initial time [s].
            check_energy: after every control interval, also check that the energy error and the dissipated
                energy stay below BLOWUP_FACTOR times the run's energy scale (simulate's check at each sample; it
                costs one kinematics pass per call). Non-finite states are detected whatever this says.
            **options: adaptive integrators only: ``rtol`` and ``atol`` (required) and ``max_step`` [s].

        Raises:
            InvalidArgumentError: a bad argument or option (the message names it).
            UnknownIntegratorError: an unknown integrator name.
        """
        method, self.dt, self.control_dt, self._interval_steps = _check_settings(
            system, integrator, dt, control_dt, options
        )
        self.system = system
        self.integrator = method
        self.options = dict(options)
        self._adaptive = method.adaptive
        if self._adaptive:
            self._rtol = relative_tolerance(options["rtol"])
            self._atol = positive_number(options["atol"], "atol", "units")
            max_step = options.get("max_step")
            self._max_step = positive_number(max_step, "max_step") if max_step is not None else math.inf
        self._q0 = system.check_q(q0, "q0") if q0 is not None else system.neutral()
        self._v0 = system.check_v(v0, "v0") if v0 is not None else np.zeros(system.nv)
        self._t0_initial = finite_number(t0, "t0")
        self.check_energy = bool(check_flag(check_energy, "check_energy"))
        elements = system.ledger_elements
        self._element_names = [name for name, _ in elements]
        self._kinds = [kind for _, kind in elements]
        self._is_work = np.array([kind == "work" for kind in self._kinds])
        self._sensing = run_sensing(system, method, self.dt, self._interval_steps, np.zeros(1, dtype=int))
        self.reset()

    # ---- state ---------------------------------------------------------------------------------------
    def reset(
        self, q: Any = None, v: Any = None, t: float | None = None, *, sensor_seed: int | None = None
    ) -> StepperState:
        """Return to a state with a fresh ledger, zero torque and fresh stats; a scene's sensors read the new state
        (their latency starts afresh; their noise goes on from where it was).

        Args:
            q: configuration, shape (nq,); default the stepper's q0.
            v: velocity, shape (nv,); default the stepper's v0.
            t: time [s]; default the stepper's t0 (0 unless given at construction).
            sensor_seed: a whole number >= 0: each sensor's noise starts anew from a generator seeded with its seed
                and this (the same sensor_seed, the same noise); None: it goes on.

        Returns:
            The new state.
        """
        system = self.system
        q = system.check_q(q, "q") if q is not None else self._q0.copy()
        v = system.check_v(v, "v") if v is not None else self._v0.copy()
        t = finite_number(t, "t") if t is not None else self._t0_initial
        method = self.integrator
        if self._adaptive:
            control: ConstantStep | PIController = PIController(
                method.embedded_order,  # type: ignore[attr-defined]
                max_step=self._max_step,
                first_step=self.dt,
                time=t,
            )
        else:
            control = ConstantStep(self.dt, t)
        kernel = choose_kernel(
            system, method, q[None, :], v[None, :], rtol=getattr(self, "_rtol", None), atol=getattr(self, "_atol", None)
        )
        kernel.start_at(t)
        self._kernel: Any = kernel
        record_width = sum(width for _, _, width in system.record_fields)
        self._store = SampleStore(1, system.nq, system.nv, len(system.ledger_elements), record_width, 1)
        self._store.make_room(math.inf)  # it holds the state of the latest call only: the core never waits for room
        self._core: Core = core_class(kernel)(
            system=system, method=method, kernel=kernel, control=control, sampler=None, store=self._store, B=1
        )
        self._grid = (t, 0)  # control instants t0 + k · control interval, k counted
        self._monitor = Monitor(system, 1)
        self._monitor.start(np.array([0]), np.array([system.unchecked_energies(q, v)]))
        self._saturation = Saturation(system, 1)
        self._controller_calls = 0
        self._tau = _frozen(np.zeros(system.nv))
        if self._sensing is not None:
            entropy = None if sensor_seed is None else whole_number(sensor_seed, "sensor_seed", 0, 2**63 - 1)
            self._sensing.stream.restart(np.zeros(1, dtype=int), entropy)
            self._sensing.attach(self._core, self.dt)
        self._freeze()
        return self.state

    @property
    def readings(self) -> dict[str, np.ndarray]:
        """The scene's sensors' readings now, by sensor name, shape (components,) each (copies; see
        multibody_sim.sensors); {} for a system without sensors."""
        return {} if self._sensing is None else self._sensing.stream.readings(0)

    @property
    def state(self) -> StepperState:
        """(t, q, v) now."""
        return StepperState(self.t, self.q, self.v)

    @property
    def t(self) -> float:
        """Time [s]."""
        return self._core.t

    @t.setter
    def t(self, value: float) -> None:
        t = finite_number(value, "t")
        self._kernel.start_at(t)
        self._core.control.restart(t)
        self._grid = (t, 0)

    @property
    def q(self) -> np.ndarray:
        """Configuration, shape (nq,) (read-only; assign a new one to change it, checked like Robot's)."""
        return self._q

    @q.setter
    def q(self, value: Any) -> None:
        self._jump(self.system.check_q(value, "q"), self.v)

    @property
    def v(self) -> np.ndarray:
        """Velocity, shape (nv,) (read-only; assign a new one to change it, checked like Robot's)."""
        return self._v

    @v.setter
    def v(self, value: Any) -> None:
        self._jump(self.q, self.system.check_v(value, "v"))

    @property
    def tau(self) -> np.ndarray:
        """The torque applied over the latest step (after saturation) [N·m, N], shape (nv,); zero after reset."""
        return self._tau

    def _jump(self, q: np.ndarray, v: np.ndarray) -> None:
        """Move to (q, v) by hand: the energy reference moves with it, so energy_error keeps measuring
        integration only."""
        system, monitor = self.system, self._monitor
        before = sum(system.unchecked_energies(self.q, self.v))
        kinetic, potential = system.unchecked_energies(q, v)
        monitor.initial[0] += kinetic + potential - before
        monitor.scale[0] = max(monitor.scale[0], kinetic + abs(potential) + system.energy_scale)
        self._kernel.set_row(0, q, v)
        self._freeze()

    def _freeze(self) -> None:
        """The state arrays handed out are read-only: users see the state without copies and cannot edit it."""
        Q, V = self._kernel.states()
        self._q, self._v = Q[0], V[0]
        self._q.setflags(write=False)
        self._v.setflags(write=False)

    # ---- energy ledger -------------------------------------------------------------------------------
    @property
    def _flows(self) -> np.ndarray:
        return self._kernel.flows_of(0)

    @property
    def work(self) -> float:
        """Energy put in since the reset by the ledger's "work" elements (joint torques, ...) [J]."""
        return float(self._flows[self._is_work].sum())

    @property
    def dissipated(self) -> float:
        """Energy taken out since the reset by the ledger's "dissipated" elements (joint damping, ...) [J]."""
        return float(self._flows[~self._is_work].sum())

    @property
    def ledger(self) -> dict[str, float]:
        """Energy [J] through each ledger element since the reset (name -> cumulative energy)."""
        return {name: float(flow) for name, flow in zip(self._element_names, self._flows, strict=True)}

    @property
    def kinetic_energy(self) -> float:
        """T = ½ vᵀ M(q) v [J] now."""
        return self.system.unchecked_energies(self.q, self.v)[0]

    @property
    def potential_energy(self) -> float:
        """Gravitational potential energy V(q) [J] now."""
        return self.system.unchecked_energies(self.q, self.v)[1]

    @property
    def total_energy(self) -> float:
        """H = T + V [J] now."""
        return sum(self.system.unchecked_energies(self.q, self.v))

    @property
    def energy_error(self) -> float:
        """H − H_ref − work + dissipated [J]: zero for the exact solution (H_ref: H at the reset, moved by
        hand-set states)."""
        return self.total_energy - float(self._monitor.initial[0]) - self.work + self.dissipated

    @property
    def stats(self) -> dict[str, Any]:
        """Counts since the reset: steps, rejected_steps, evaluations, controller_calls, saturated_controls,
        saturated_dofs; a contact scene's cone solver adds solver_steps, solver_unconverged, solver_iterations."""
        saturation, dofs = self._saturation, self.system.dof_names
        steps, rejected, evaluations = self._core.counts(0)
        solver_stats = getattr(self._core.kernel, "solver_stats", None)
        return {
            "steps": steps,
            "rejected_steps": rejected,
            "evaluations": evaluations,
            "controller_calls": self._controller_calls,
            "saturated_controls": int(saturation.calls[0]),
            "saturated_dofs": {dofs[i]: int(n) for i, n in enumerate(saturation.dofs[0]) if n},
            **(solver_stats(0) if solver_stats is not None else {}),
        }

    # ---- stepping ------------------------------------------------------------------------------------
    def step(self, tau: Any = None) -> StepperState:
        """Advance by one control interval with tau held over it.

        Args:
            tau: joint torques [N·m, N], shape (nv,); saturated at the URDF's effort limits. None applies
                the torque of the previous step (zero after a reset).

        Returns:
            The new state.

        Raises:
            InvalidArgumentError: tau has the wrong shape, is not finite, or pushes on a floating base.
            SimulationError: the step failed ("diverged", "newton_failed", "step_collapsed"); the stepper stays
                at the state before the call.
        """
        snapshot = self._snapshot()
        if tau is not None:
            self._set_torque(check_torque(self.system, tau, None))
        self._advance(self._instant(1), snapshot)
        return self.state

    def advance_to(self, t: float, controller: Controller | SensorController | None = None) -> StepperState:
        """Step to time t, the last control interval shortened to land on it exactly (as simulate() ends on its
        duration).

        Args:
            t: the time to reach [s], not before the current time.
            controller: ``controller(t, q, v) -> tau``, called at the start of every control interval (its output
                saturated at the effort limits); None holds the torque of the previous step (zero after a reset).

        Returns:
            The state at t.

        Raises:
            InvalidArgumentError: t is before the current time, or the controller is not callable.
            SimulationError: a step failed, or the controller raised or returned something that is not a torque
                (status "failed"); the stepper stays at the last good state, before t.
        """
        t_end = finite_number(t, "t")
        now = self.t
        if t_end < now:
            raise InvalidArgumentError(f"t must not be before the current time {now!r} s, got {t_end!r} s")
        check_callable(controller, "controller", "controller(t, q, v)")
        check_sensor_controller(self.system, reads_sensors(controller))
        if t_end > now:  # the control instants up to t_end are counted: their number must stay exact
            check_ratio(t_end - now, self.control_dt, "(t - current time)", "control_dt")
        while self.t < t_end:
            snapshot = self._snapshot()
            if controller is not None:
                t_now = self.t
                try:
                    if reads_sensors(controller):
                        out = cast(SensorController, controller)(t_now, self.q, self.v, self.readings)
                    else:
                        out = cast(Controller, controller)(t_now, self.q, self.v)
                except Exception as exc:  # user code: the stepper stays where it is
                    message = f"failed at t = {t_now:.6g} s: the controller raised {type(exc).__name__}: {exc}"
                    raise SimulationError(message, status="failed", trajectory=self._one_sample("failed")) from exc
                self._set_torque(check_torque(self.system, out, t_now))
                self._controller_calls += 1
            t0, k = self._grid
            interval = self._interval_steps * self.dt if not self._adaptive else self.control_dt
            k_stop = max(k + 1, math.ceil((t_end - t0) / interval - SLIVER))
            self._advance(self._instant(1) if k + 1 < k_stop else t_end, snapshot)
        return self.state

    def _instant(self, ahead: int) -> float:
        """The control instant `ahead` intervals after the last one [s]: t0 + k·dt counted in steps (fixed-step),
        t0 + k·control_dt (adaptive)."""
        t0, k = self._grid
        if self._adaptive:
            return t0 + (k + ahead) * self.control_dt
        return t0 + ((k + ahead) * self._interval_steps) * self.dt

    def _set_torque(self, tau: np.ndarray) -> None:
        """Hold tau (saturated at the effort limits, counted) from now on: a new torque, so a jump."""
        tau = self._saturation.apply(tau[None, :], self._core.rows)[0]
        self._tau = _frozen(np.array(tau, dtype=float))
        self._core.set_torques(self._tau[None, :], jump=True)

    def _advance(self, t_next: float, snapshot: tuple[Any, ...]) -> None:
        """Advance to t_next (a control instant, or advance_to's end); on failure restore `snapshot` and raise."""
        core = self._core
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):  # divergence is reported
            core.advance(t_next)
        stops = core.take_stops()
        if stops:
            self._restore(snapshot)
            stop = stops[0]
            raise SimulationError(stop.message, status=stop.status, trajectory=self._one_sample(stop.status))
        if self._sensing is not None:
            self._sensing.update()
        if self.check_energy:
            store = self._store
            store.clear()  # it holds the state of the latest call only
            core.recorded = math.nan
            core.record()
            problem = self._monitor.first_problem(store, 0, 0, 1)
            if problem is not None:
                _, what, _ = problem
                step = core.steps
                self._restore(snapshot)
                raise SimulationError(
                    f"diverged at t = {t_next:.6g} s (step {step}): {what}; {cure_for_dt(self.system, self.dt)}",
                    status="diverged",
                    trajectory=self._one_sample("diverged"),
                )
        t0, k = self._grid
        self._grid = (t0, k + 1) if t_next == self._instant(1) else (t_next, 0)  # off the grid: a new one starts
        self._freeze()

    def _snapshot(self) -> tuple[Any, ...]:
        core = self._core
        return (
            self._kernel.snapshot(),
            core.control.snapshot(),
            (core.steps, core.rejected, core.evaluations, core.extra_evaluations.copy()),
            self._saturation.snapshot(),
            self._controller_calls,
            self._tau,
            self._grid,
            self._sensing.stream.snapshot() if self._sensing is not None else None,
        )

    def _restore(self, snapshot: tuple[Any, ...]) -> None:
        core = self._core
        kernel, control, counts, saturation, calls, tau, grid, sensing = snapshot
        if self._sensing is not None:
            self._sensing.ticks.clear()
            self._sensing.stream.restore(sensing)
        self._kernel.restore(kernel)
        core.control.restore(control)
        core._set_rows(np.arange(1))
        core.store.running[0] = True
        core.steps, core.rejected, core.evaluations, core.extra_evaluations = counts[:3] + (counts[3].copy(),)
        self._saturation.restore(saturation)
        self._controller_calls, self._tau, self._grid = calls, tau, grid  # q, v: still the snapshot's (_freeze)

    def _one_sample(self, status: str) -> Trajectory:
        """The current state as a one-sample Trajectory (what a failed step's SimulationError carries)."""
        kinetic, potential = self.system.unchecked_energies(self.q, self.v)
        work, dissipated = self.work, self.dissipated
        total = kinetic + potential
        one = np.ones(1)
        return Trajectory(
            t=np.array([self.t]),
            q=self.q[None, :].copy(),
            v=self.v[None, :].copy(),
            tau=self._tau[None, :].copy(),
            kinetic_energy=kinetic * one,
            potential_energy=potential * one,
            total_energy=total * one,
            work=work * one,
            dissipated=dissipated * one,
            energy_error=(total - float(self._monitor.initial[0]) - work + dissipated) * one,
            ledger={
                name: LedgerEntry(kind, flow * one)
                for name, kind, flow in zip(self._element_names, self._kinds, self._flows, strict=True)
            },
            stats=self.stats,
            status=status,
            metadata={"integrator": self.integrator.name, "options": {"dt": self.dt, **self.options}},
        )

    def __repr__(self) -> str:
        name = getattr(self.system, "name", type(self.system).__name__)
        return f"<Stepper {name} {self.integrator.name} dt={self.dt:g} s at t={self.t:g} s>"


class BatchStep(NamedTuple):
    """What one BatchStepper.step() did to every row.

    Attributes:
        t: each row's time after the call [s], shape (B,).
        q: configurations, shape (B, nq); v: velocities, shape (B, nv) (copies).
        tau: the torques applied over the interval (after saturation) [N·m, N], shape (B, nv).
        failures: row -> (status, message) for the rows whose step failed ("diverged", "newton_failed",
            "step_collapsed", "failed"); those rows are at their state before the call.
    """

    t: np.ndarray
    q: np.ndarray
    v: np.ndarray
    tau: np.ndarray
    failures: dict[int, tuple[str, str]]


class BatchStepper:
    """B rows of states advanced together one control interval per call, with a torque per row: the batched
    Stepper, for vector environments and batched MPC loops.

    Fixed-step methods on a system whose dynamics do not depend on time (a robot; a scene without time-varying
    forces) advance every row through one stepping core over the B rows, as rollout() does (the kernel
    driver.choose_kernel picks: native where it runs, else the row kernel); each row then gets a Stepper's states
    bit for bit. Adaptive methods, whose rows choose their own steps, and time-varying scenes, whose rows' clocks
    differ once rows are reset apart, advance one Stepper per row. A row whose step fails stops at its state before
    the call and says why (in the step's ``failures``); the others go on. Resetting rows (reset(rows, Q, V)) puts
    them at a new state with their clock at 0, a fresh energy reference and zero torque, as Stepper.reset does.

    Attributes:
        system, integrator, dt, control_dt: as Stepper's.
        B: the number of rows.
    """

    def __init__(
        self,
        system: Robot,
        Q0: Any,
        V0: Any,
        *,
        dt: float,
        integrator: str | Integrator = "rk4",
        control_dt: float | None = None,
        check_energy: bool = True,
        num_threads: int = 1,
        **options: Any,
    ):
        """B rows at (Q0, V0), time 0.

        Args:
            system: the robot (or scene).
            Q0: configurations, shape (B, nq); V0: velocities, shape (B, nv).
            dt, integrator, control_dt, check_energy, **options: as Stepper's.
            num_threads: threads the native kernel splits the rows over (the row kernel runs on one).

        Raises:
            InvalidArgumentError: a bad argument or option (the message names it).
        """
        method, self.dt, self.control_dt, self._interval_steps = _check_settings(
            system, integrator, dt, control_dt, options
        )
        self.system, self.integrator, self.options = system, method, dict(options)
        self.check_energy = bool(check_flag(check_energy, "check_energy"))
        self._num_threads = positive_count(num_threads, "num_threads")
        Q, V = self._check_states(Q0, V0, "Q0", "V0")
        self.B = len(Q)
        self._alone: list[Stepper] | None = None
        # each row's own system (a randomised scene's rows: reset(..., systems=)), or None: `system` for every row
        self._systems: list[Any] | None = None
        self._stepper_settings = {
            "dt": dt,
            "integrator": method,
            "control_dt": control_dt,
            "check_energy": check_energy,
        }
        if method.adaptive or not _time_invariant(system):
            self._alone = [self._row_stepper(b, system, q, v) for b, (q, v) in enumerate(zip(Q, V, strict=True))]
        self._sensing = (
            run_sensing(system, method, self.dt, self._interval_steps, np.arange(self.B))
            if self._alone is None
            else None
        )
        self._Q0, self._V0 = Q, V
        self._Q, self._V = Q.copy(), V.copy()
        self._steps = np.zeros(self.B, dtype=np.int64)  # control intervals since each row's reset
        self._TAU = np.zeros((self.B, system.nv))
        self._monitor = Monitor(system, self.B)
        self._ledger = np.zeros((self.B, len(system.ledger_elements)))  # each row's ledger flows since its reset
        self._base = self._ledger.copy()  # ... when the current core was built (its flows count from there)
        self._scratch = SampleStore(self.B, system.nq, system.nv, len(system.ledger_elements), 0, 1)
        self._scratch.make_room(math.inf)
        self._saturation = Saturation(system, self.B)
        self._core: Core | None = None
        self.reset()

    def _row_stepper(self, b: int, system: Any, q: np.ndarray | None, v: np.ndarray | None) -> Stepper:
        """Row b's own Stepper (adaptive methods, time-varying scenes) on `system`, at (q, v)."""
        stepper = Stepper(system, q0=q, v0=v, **self._stepper_settings, **self.options)  # type: ignore[arg-type]
        if stepper._sensing is not None:  # row b's sensors draw from their seeds + b
            stepper._sensing = run_sensing(system, self.integrator, stepper.dt, stepper._interval_steps, np.array([b]))
            stepper.reset()
        return stepper

    def _check_states(self, Q: Any, V: Any, q_name: str, v_name: str) -> tuple[np.ndarray, np.ndarray]:
        Q, V = check_batch(self.system, Q, V, q_name, v_name)
        return Q.copy(), V.copy()

    # ---- state ---------------------------------------------------------------------------------------
    @property
    def t(self) -> np.ndarray:
        """Each row's time since its reset [s], shape (B,), as a Stepper counts it: (k · steps per interval) · dt
        after k intervals (fixed-step methods), k · control_dt (adaptive ones)."""
        if self._interval_steps:
            return (self._steps * self._interval_steps) * self.dt
        return self._steps * self.control_dt

    @property
    def q(self) -> np.ndarray:
        """Configurations, shape (B, nq) (a copy)."""
        return self._Q.copy()

    @property
    def v(self) -> np.ndarray:
        """Velocities, shape (B, nv) (a copy)."""
        return self._V.copy()

    def reset(
        self, rows: Any = None, q: Any = None, v: Any = None, *, sensor_seed: Any = None, systems: Any = None
    ) -> None:
        """Put rows at new states, time 0, zero torque and a fresh energy reference; a scene's sensors read the new
        states (as Stepper.reset).

        Args:
            rows: the rows to reset (indices or a boolean mask of shape (B,)); None: all.
            q: their configurations, shape (len(rows), nq); None: the states given at construction.
            v: their velocities, shape (len(rows), nv); None: the states given at construction, or zero with q.
            sensor_seed: as Stepper.reset's: one whole number for every reset row, or one per reset row.
            systems: each reset row's own scene from now on (randomised physics: the scene's with_parameters()),
                one per row; None: they keep theirs.
        """
        entropy: Any = None
        if sensor_seed is not None:
            given = sensor_seed if isinstance(sensor_seed, (list, tuple, np.ndarray)) else None
            entropy = (
                [whole_number(s, f"sensor_seed[{i}]", 0, 2**63 - 1) for i, s in enumerate(given)]
                if given is not None
                else whole_number(sensor_seed, "sensor_seed", 0, 2**63 - 1)
            )
        index = np.arange(self.B) if rows is None else np.arange(self.B)[np.asarray(rows)]
        if q is None:
            Q, V = self._Q0[index], self._V0[index]
        else:
            if v is None:
                v = np.zeros((len(np.atleast_2d(np.asarray(q, dtype=object))), self.system.nv))
            Q, V = self._check_states(q, v, "q", "v")
            if len(Q) != len(index):
                raise InvalidArgumentError(f"q must hold one state per reset row ({len(index)}), got {len(Q)}")
        if isinstance(entropy, list) and len(entropy) != len(index):
            raise InvalidArgumentError(
                f"sensor_seed must hold one seed per reset row ({len(index)}), got {len(entropy)}"
            )
        self._Q[index], self._V[index] = Q, V
        self._steps[index] = 0
        self._TAU[index] = 0.0
        if systems is not None:
            self._set_systems(index, systems)
        self._ledger[index] = 0.0
        rows_systems = [self._system_of(b) for b in index.tolist()]
        energies = [row.unchecked_energies(q, v) for row, q, v in zip(rows_systems, Q, V, strict=True)]
        self._monitor.start(index, np.array(energies))
        if self._alone is not None:
            for k, (b, q_b, v_b) in enumerate(zip(index.tolist(), Q, V, strict=True)):
                self._alone[b].reset(q_b, v_b, 0.0, sensor_seed=entropy[k] if isinstance(entropy, list) else entropy)
        self._core = None  # rebuilt from the rows' states at the next step
        if self._sensing is not None:  # now: the rows read their new states
            self._sensing.stream.restart(index, entropy)
            self._build(fresh=index)

    def _system_of(self, b: int) -> Any:
        return self.system if self._systems is None else self._systems[b]

    def _set_systems(self, index: np.ndarray, systems: Any) -> None:
        """Rows `index` step on `systems` (one each, the structure of `system`) from now on."""
        systems = list(systems)
        if len(systems) != len(index):
            raise InvalidArgumentError(f"systems must hold one scene per reset row ({len(index)}), got {len(systems)}")
        elements = self.system.ledger_elements
        for row in systems:
            if (
                not isinstance(row, Robot)
                or (row.nq, row.nv) != (self.system.nq, self.system.nv)
                or (row.ledger_elements != elements)
            ):
                raise InvalidArgumentError(
                    "systems must be the stepper's scene with other parameter values (its with_parameters()), got "
                    f"{type(row).__name__} {getattr(row, 'name', '')}"
                )
        if self._systems is None:
            self._systems = [self.system] * self.B
        for b, row in zip(index.tolist(), systems, strict=True):
            self._systems[b] = row
            if self._alone is not None:
                self._alone[b] = self._row_stepper(b, row, None, None)
        self._monitor.energy_scale = np.array([row.energy_scale for row in self._systems])
        self._saturation = Saturation(self.system, self.B, self._systems)

    @property
    def readings(self) -> dict[str, np.ndarray]:
        """The rows' sensors' readings now, by sensor name, shape (B, components) each (copies; see
        multibody_sim.sensors; a row whose step failed keeps the readings it took before the failure); {} for a
        system without sensors."""
        if self._alone is not None:
            rows = [stepper.readings for stepper in self._alone]
            return {name: np.array([r[name] for r in rows]) for name in rows[0]}
        return {} if self._sensing is None else self._sensing.stream.batch_readings(np.arange(self.B))

    # ---- stepping ------------------------------------------------------------------------------------
    def step(self, tau: Any) -> BatchStep:
        """Advance every row by one control interval with its torque held over it.

        Args:
            tau: joint torques [N·m, N], shape (B, nv); saturated at the URDF's effort limits.

        Returns:
            The rows' new states and the failures.

        Raises:
            InvalidArgumentError: tau has the wrong shape, is not finite, or pushes on a floating base (the message
                names the row).
        """
        TAU = self._check_torques(tau)
        failures: dict[int, tuple[str, str]] = {}
        if self._alone is not None:
            for b, stepper in enumerate(self._alone):
                try:
                    stepper.step(TAU[b])
                except SimulationError as exc:
                    failures[b] = (exc.status, str(exc))
                    continue
                self._Q[b], self._V[b], self._TAU[b] = stepper.q, stepper.v, stepper.tau
                self._steps[b] += 1
            return self._result(failures)
        TAU = self._saturation.apply(TAU, np.arange(self.B))
        if self._core is None:
            self._build()
        core = self._core
        assert core is not None
        core.set_torques(TAU[core.rows], jump=True)
        self._interval += 1
        with np.errstate(over="ignore", invalid="ignore", divide="ignore"):  # divergence is reported
            core.advance(self._core_t0 + (self._interval * self._interval_steps) * self.dt)
        for stop in core.take_stops():  # the row stays at its state before the call
            failures[int(stop.row)] = (stop.status, self._on_row_clock(stop))
        if self._sensing is not None:
            self._sensing.update()
        store = self._store
        store.clear()
        core.recorded = math.nan
        core.record()
        rows = core.rows
        if len(rows):
            scratch = self._scratch
            scratch.clear()
            scratch.ENERGY[0, rows] = store.ENERGY[0, rows]
            scratch.FLOWS[0, rows] = self._base[rows] + store.FLOWS[0, rows]
            scratch.V[0, rows] = store.V[0, rows]
            scratch.advance()
            monitor = self._monitor
            for b in rows.tolist() if self.check_energy else ():
                problem = monitor.first_problem(scratch, b, 0, 1)
                if problem is not None:
                    step = int((self._steps[b] + 1) * self._interval_steps)
                    t_next = float((self._steps[b] + 1) * self.control_dt)
                    cure = cure_for_dt(self.system, self.dt)
                    failures[b] = ("diverged", f"diverged at t = {t_next:.6g} s (step {step}): {problem[1]}; {cure}")
            good = np.array([b for b in rows.tolist() if b not in failures], dtype=int)
            self._Q[good], self._V[good] = store.Q[0, good], store.V[0, good]
            self._TAU[good] = TAU[good]
            self._ledger[good] = scratch.FLOWS[0, good]
            self._steps[good] += 1
        if failures:
            self._core = None  # failed rows left the core, or must go back: rebuilt from the rows' states
        return self._result(failures)

    def _on_row_clock(self, stop: RowStop) -> str:
        """The core's message about a row, with the time and step counted from the row's reset (as its Stepper
        would say them) instead of the core's, which started when the core was built."""
        if stop.step is None:  # not a step's failure: the message names no step
            return stop.message
        steps_before = int(self._built_at[stop.row]) * self._interval_steps
        t = steps_before * self.dt + stop.time
        return stop_message(stop.status, t, steps_before + stop.step, stop.detail)

    def _build(self, fresh: np.ndarray | None = None) -> None:
        """A stepping core over every row from the rows' states (its ledger flows count from the rows' ledger);
        the rows `fresh` (default none) start afresh: their sensors read their state now."""
        system, B = self.system, self.B
        self._base = self._ledger.copy()
        self._built_at = self._steps.copy()
        kernel = choose_kernel(
            system, self.integrator, self._Q, self._V, num_threads=self._num_threads, systems=self._systems
        )
        self._store = SampleStore(B, system.nq, system.nv, len(system.ledger_elements), 0, 1)
        self._store.make_room(math.inf)  # it holds the state of the latest call only
        self._core = core_class(kernel)(
            system=system,
            method=self.integrator,
            kernel=kernel,
            control=ConstantStep(self.dt),
            sampler=None,
            store=self._store,
            B=B,
        )
        self._core_t0, self._interval = 0.0, 0
        if self._sensing is not None:
            done = self._steps * self._interval_steps
            self._sensing.attach(
                self._core, self.dt, fresh=np.zeros(0, dtype=int) if fresh is None else fresh, done=done
            )

    def _check_torques(self, tau: Any) -> np.ndarray:
        system = self.system
        TAU = real_array(tau, "tau", f"an array of real numbers of shape ({self.B}, {system.nv})")
        if TAU.shape != (self.B, system.nv):
            raise InvalidArgumentError(f"tau must have shape ({self.B}, {system.nv}), got {TAU.shape}")
        if not np.isfinite(TAU).all() or (system.floating_base and TAU[:, :6].any()):
            for b in range(self.B):
                system.check_tau(TAU[b], f"tau[{b}]")  # raises, with check_tau's message
        return TAU

    def _result(self, failures: dict[int, tuple[str, str]]) -> BatchStep:
        return BatchStep(self.t, self._Q.copy(), self._V.copy(), self._TAU.copy(), failures)

    def __repr__(self) -> str:
        name = getattr(self.system, "name", type(self.system).__name__)
        return f"<BatchStepper {name} {self.B} rows {self.integrator.name} dt={self.dt:g} s>"


def _time_invariant(system: Any) -> bool:
    """Whether the system's dynamics ignore time: a robot's do; a scene's unless it declares time-varying forces."""
    elements = getattr(system, "elements", None)
    return not bool(getattr(elements, "time_dependent", False))


def _check_settings(
    system: Robot, integrator: str | Integrator, dt: float, control_dt: float | None, options: dict[str, Any]
) -> tuple[Integrator, float, float, int]:
    """The checked method, dt, control interval and steps per interval (0: adaptive) of a stepper."""
    check_system(system)
    method = get_integrator(integrator)
    method.check_contract()
    check_options(method, options, fixed_step=(), adaptive_only=_ADAPTIVE_OPTIONS)
    dt = positive_number(dt, "dt")
    if method.adaptive:
        interval = positive_number(control_dt, "control_dt") if control_dt is not None else dt
        steps = 0
    else:
        steps = steps_per(control_dt, dt, "control_dt")
        interval = steps * dt
    method.check_system(system)
    return method, dt, interval, steps


def _frozen(array: np.ndarray) -> np.ndarray:
    """The array made read-only: users see the state without copies and cannot edit it behind our back."""
    array.setflags(write=False)
    return array
