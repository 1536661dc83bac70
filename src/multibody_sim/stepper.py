"""Step by step: a stateful stepper for co-simulation, RL and MPC loops, with simulate()'s arithmetic."""

from __future__ import annotations

import math
from typing import Any, NamedTuple

import numpy as np

from .exceptions import InvalidArgumentError, SimulationError
from .integrators import Integrator, StepFailure, get_integrator
from .robot import Robot
from .simulation import (
    BLOWUP_FACTOR,
    MIN_STEP_FRACTION,
    Controller,
    check_options,
    finite_number,
    positive_number,
    stable_implicit_integrators,
)
from .step_control import PIController
from .trajectory import LedgerEntry, Trajectory

_ADAPTIVE_OPTIONS = ("atol", "max_step", "rtol")


class StepperState(NamedTuple):
    """The stepper's state after a step: time [s], configuration (nq,) and velocity (nv,) (read-only arrays)."""

    t: float
    q: np.ndarray
    v: np.ndarray


class Stepper:
    """Advance a robot step by step with a torque you choose at every step (what mj_step and Drake's
    Simulator.AdvanceTo give their users), with exactly the arithmetic of :func:`multibody_sim.simulate`.

    ``step(tau)`` holds tau over one step of dt; ``advance_to(t, controller)`` steps to time t, calling the
    controller at the start of every step. N calls of ``step(controller(t, q, v))`` from (q0, v0) at t = 0 give
    simulate()'s samples bit for bit (same integrator, same dt, control every step): times are ``t0 + k·dt``
    with k counted, never summed, and torques saturate at the URDF's effort limits (clipped and counted in
    ``stats``), as simulate's controller outputs do.

    Adaptive integrators (bs32, dp54, dop853) are supported: each step of dt is then covered by error-controlled
    substeps (the PI controller of simulate, its step size carried from one call to the next) that land exactly
    on the step's end, as simulate() does with ``control_dt = output_dt = dt``. They need ``rtol`` and ``atol``.
    Where simulate() scales its landing tolerance and its smallest step by the duration, the stepper, which has
    none, scales them by max(dt, |t|): a substep below MIN_STEP_FRACTION of that is a collapse.

    A step that fails (the state turns non-finite, the energy blows up, Newton fails, the adaptive step
    collapses) raises :class:`SimulationError` as simulate() does and leaves the stepper at the state before
    that step; the error's ``.trajectory`` holds that state as its one sample.

    The energy ledger accumulates as the stepper runs: ``work`` and ``dissipated`` (and ``ledger`` per element)
    come from the integrator's own quadrature, and the energies are computed on demand from the current state.
    Setting ``q`` or ``v`` by hand is an intervention, not dynamics: it shifts the reference energy so that
    ``energy_error`` (H − H_ref − work + dissipated) stays a check on the integration alone.

    Attributes:
        system: the robot (or scene).
        integrator: the integration method.
        dt: the step [s].
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
            q0: initial configuration, shape (nq,); default the neutral configuration. reset() returns here.
            v0: initial velocity, shape (nv,); default zero. reset() returns here.
            t0: initial time [s].
            check_energy: after every step, also check that the energy error and the dissipated energy stay
                below BLOWUP_FACTOR times the run's energy scale (simulate's check at each sample; it costs one
                kinematics pass per step). Non-finite states are detected whatever this says.
            **options: adaptive integrators only: ``rtol`` and ``atol`` (required) and ``max_step`` [s].

        Raises:
            InvalidArgumentError: a bad argument or option (the message names it).
            UnknownIntegratorError: an unknown integrator name.
        """
        method = get_integrator(integrator)
        check_options(method, options, fixed_step=(), adaptive_only=_ADAPTIVE_OPTIONS)
        self.system = system
        self.integrator = method
        self.dt = positive_number(dt, "dt")
        self.options = dict(options)
        self._adaptive = method.adaptive
        if self._adaptive:
            self._rtol = positive_number(options["rtol"], "rtol", "units")
            self._atol = positive_number(options["atol"], "atol", "units")
            max_step = options.get("max_step")
            self._max_step = positive_number(max_step, "max_step") if max_step is not None else math.inf
            # simulate()'s contract for adaptive methods: attempt(), embedded_order and fsal.
            self._fsal = bool(getattr(method, "fsal", False))
        method.check_system(system)
        self._q0 = system.check_q(q0, "q0") if q0 is not None else system.neutral()
        self._v0 = system.check_v(v0, "v0") if v0 is not None else np.zeros(system.nv)
        self._t0_initial = finite_number(t0, "t0")
        self.check_energy = bool(check_energy)
        elements = system.ledger_elements
        self._element_names = [name for name, _ in elements]
        self._kinds = [kind for _, kind in elements]
        self._is_work = np.array([kind == "work" for kind in self._kinds])
        limited = np.isfinite(system.effort_limit)
        self._effort = system.effort_limit if limited.any() else None
        self.reset()

    # ---- state ---------------------------------------------------------------------------------------
    def reset(self, q: Any = None, v: Any = None, t: float | None = None) -> StepperState:
        """Return to a state with a fresh ledger, zero torque and fresh stats.

        Args:
            q: configuration, shape (nq,); default the stepper's q0.
            v: velocity, shape (nv,); default the stepper's v0.
            t: time [s]; default the stepper's t0 (0 unless given at construction).

        Returns:
            The new state.
        """
        q = self.system.check_q(q, "q") if q is not None else self._q0.copy()
        v = self.system.check_v(v, "v") if v is not None else self._v0.copy()
        t = finite_number(t, "t") if t is not None else self._t0_initial
        self._q, self._v = _frozen(q), _frozen(v)
        self._t0, self._k = t, 0  # time is t0 + k·dt: counted, never summed, as in simulate()
        self._tau = _frozen(np.zeros(self.system.nv))
        self._flows = np.zeros(len(self._element_names))
        kinetic, potential = self.system.unchecked_energies(self._q, self._v)
        self._energy_reference = kinetic + potential
        self._energy_scale = kinetic + abs(potential) + self.system.energy_scale
        # Adaptive FSAL methods: the next step's first stage and the torque it was evaluated with, if known.
        self._fsal_row: tuple[np.ndarray, np.ndarray] | None = None
        self._h = min(self.dt, self._max_step) if self._adaptive else self.dt  # adaptive: the next trial step
        self._pi = (
            PIController(self.integrator.embedded_order, max_step=self._max_step)  # type: ignore[attr-defined]
            if self._adaptive
            else None
        )
        self.stats: dict[str, Any] = {
            "steps": 0,
            "rejected_steps": 0,
            "evaluations": 0,
            "controller_calls": 0,
            "saturated_controls": 0,
            "saturated_dofs": {},
        }
        self._saturated = np.zeros(self.system.nv, dtype=int)
        return self.state

    @property
    def state(self) -> StepperState:
        """(t, q, v) now."""
        return StepperState(self.t, self._q, self._v)

    @property
    def t(self) -> float:
        """Time [s]."""
        return self._t0 + self._k * self.dt

    @t.setter
    def t(self, value: float) -> None:
        self._t0, self._k = finite_number(value, "t"), 0

    @property
    def q(self) -> np.ndarray:
        """Configuration, shape (nq,) (read-only; assign a new one to change it, checked like Robot's)."""
        return self._q

    @q.setter
    def q(self, value: Any) -> None:
        self._jump(self.system.check_q(value, "q"), self._v)

    @property
    def v(self) -> np.ndarray:
        """Velocity, shape (nv,) (read-only; assign a new one to change it, checked like Robot's)."""
        return self._v

    @v.setter
    def v(self, value: Any) -> None:
        self._jump(self._q, self.system.check_v(value, "v"))

    @property
    def tau(self) -> np.ndarray:
        """The torque applied over the latest step (after saturation) [N·m, N], shape (nv,); zero after reset."""
        return self._tau

    def _jump(self, q: np.ndarray, v: np.ndarray) -> None:
        """Move to (q, v) by hand: the energy reference moves with it, so energy_error keeps measuring
        integration only."""
        before = sum(self.system.unchecked_energies(self._q, self._v))
        kinetic, potential = self.system.unchecked_energies(q, v)
        self._energy_reference += kinetic + potential - before
        self._energy_scale = max(self._energy_scale, kinetic + abs(potential) + self.system.energy_scale)
        self._q, self._v = _frozen(q), _frozen(v)
        self._fsal_row = None

    # ---- energy ledger -------------------------------------------------------------------------------
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
        return self.system.unchecked_energies(self._q, self._v)[0]

    @property
    def potential_energy(self) -> float:
        """Gravitational potential energy V(q) [J] now."""
        return self.system.unchecked_energies(self._q, self._v)[1]

    @property
    def total_energy(self) -> float:
        """H = T + V [J] now."""
        return sum(self.system.unchecked_energies(self._q, self._v))

    @property
    def energy_error(self) -> float:
        """H − H_ref − work + dissipated [J]: zero for the exact solution (H_ref: H at the reset, moved by
        hand-set states)."""
        return self.total_energy - self._energy_reference - self.work + self.dissipated

    # ---- stepping ------------------------------------------------------------------------------------
    def step(self, tau: Any = None) -> StepperState:
        """Advance by dt with tau held over the step.

        Args:
            tau: joint torques [N·m, N], shape (nv,); saturated at the URDF's effort limits. None applies
                the torque of the previous step (zero after a reset).

        Returns:
            The new state.

        Raises:
            InvalidArgumentError: tau has the wrong shape, is not finite, or pushes on a floating base.
            SimulationError: the step failed ("diverged", "newton_failed", "step_collapsed"); the stepper stays
                at the state before the step.
        """
        if tau is not None:
            self._tau = self._torque(tau, None)
        self._advance(self._t0 + (self._k + 1) * self.dt, on_grid=True)
        return StepperState(self.t, self._q, self._v)

    def advance_to(self, t: float, controller: Controller | None = None) -> StepperState:
        """Step to time t, the last step shortened to land on it exactly (as simulate() ends on its duration).

        Args:
            t: the time to reach [s], not before the current time.
            controller: ``controller(t, q, v) -> tau``, called at the start of every step (its output saturated
                at the effort limits); None holds the torque of the previous step (zero after a reset).

        Returns:
            The state at t.

        Raises:
            InvalidArgumentError: t is before the current time, the controller is not callable or returned a bad
                torque.
            SimulationError: a step failed; the stepper stays at the last good state, before t.
        """
        t_end = finite_number(t, "t")
        now = self.t
        if t_end < now:
            raise InvalidArgumentError(f"t must not be before the current time {now!r} s, got {t_end!r} s")
        if controller is not None and not callable(controller):
            raise InvalidArgumentError(
                f"controller must be callable as controller(t, q, v), got {type(controller).__name__}"
            )
        if t_end == now:
            return self.state
        # As simulate(): never count a last sliver of round-off as a step (1.0 / 0.1 is 10 steps, not 11).
        n_steps = max(1, math.ceil((t_end - now) / self.dt - 1e-9))
        for i in range(n_steps):
            if controller is not None:
                self._tau = self._torque(controller(self.t, self._q, self._v), self.t)
                self.stats["controller_calls"] += 1
            if i < n_steps - 1:
                self._advance(self._t0 + (self._k + 1) * self.dt, on_grid=True)
            else:
                grid = self._t0 + (self._k + 1) * self.dt
                self._advance(t_end, on_grid=grid == t_end)
        return self.state

    def _advance(self, t_next: float, *, on_grid: bool) -> None:
        """One step of dt (or the shortened last step of advance_to) to t_next, committed only if it succeeds."""
        t = self.t
        if self._adaptive:
            q, v, flows, steps = self._adaptive_step(t, t_next)
        else:
            q, v, flows, steps = self._fixed_step(t, t_next - t if not on_grid else self.dt)
        self._check(t_next, q, v, flows, self.stats["steps"] + steps)
        self._q, self._v, self._flows = _frozen(q), _frozen(v), flows
        self.stats["steps"] += steps
        if on_grid:
            self._k += 1
        else:  # a step that lands off the grid starts a new one there
            self._t0, self._k = t_next, 0

    def _fixed_step(self, t: float, h: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """One step of the fixed-step method: (q, v, flows, 1)."""
        method = self.integrator
        failure: StepFailure | None = None
        try:
            q, v, step_flows = method.step(self.system, self._q, self._v, self._tau, h, t)
        except StepFailure as exc:
            failure = exc
        if failure is not None:  # reported outside the except block: the failure is the cause, not a context
            self.stats["evaluations"] += method.last_evaluations
            self._fail(
                failure.status,
                f"{failure.status} at t = {t:.6g} s (step {self.stats['steps'] + 1}): {failure}; "
                f"try a smaller dt (now {self.dt:g} s)",
            )
        self.stats["evaluations"] += method.last_evaluations if method.implicit else method.evaluations_per_step
        return q, v, self._flows + step_flows, 1

    def _adaptive_step(self, t: float, t_stop: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, int]:
        """Error-controlled substeps from t to t_stop with the torque held: simulate()'s adaptive loop between two
        control instants, its PI controller and step size carried over from the previous call.

        Returns:
            (q, v, flows, accepted substeps).
        """
        method: Any = self.integrator
        pi = self._pi
        assert pi is not None
        min_step = MIN_STEP_FRACTION * max(self.dt, abs(t_stop))
        q, v, flows, tau = self._q, self._v, self._flows, self._tau
        first_stage = self._fsal_row
        if first_stage is not None and not np.array_equal(first_stage[1], tau):
            first_stage = None  # the stage's acceleration was taken with another torque
        first = first_stage[0] if first_stage is not None else None
        h, steps = self._h, 0
        while t < t_stop:
            landing = t + h >= t_stop - 1e-12 * max(self.dt, abs(t_stop))
            h_try = t_stop - t if landing else h
            attempt = method.attempt(
                self.system, q, v, tau, h_try, rtol=self._rtol, atol=self._atol, first_stage=first, t=t
            )
            self.stats["evaluations"] += attempt.evaluations
            accepted, h = pi.next_step(h_try, attempt.error)
            if not accepted or h < min_step:
                if not accepted:
                    self.stats["rejected_steps"] += 1
                    first = attempt.stages[0]  # same start state, same torque
                if h < min_step:
                    self._fail(
                        "step_collapsed",
                        f"step_collapsed at t = {t:.6g} s (step {self.stats['steps'] + steps + 1}): the step fell to "
                        f"{h:.3g} s, below the {min_step:.3g} s minimum (error norm {attempt.error:.3g}); the problem "
                        f"may be stiff or singular here: {_stiff_cure(self.system)}",
                    )
                continue
            q, v, flows = attempt.q, attempt.v, flows + attempt.flows
            t = t_stop if landing else t + h_try
            first = attempt.stages[-1] if self._fsal else None
            steps += 1
        self._h = h
        self._fsal_row = (first, tau) if first is not None else None
        return q, v, flows, steps

    def _check(self, t_next: float, q: np.ndarray, v: np.ndarray, flows: np.ndarray, step: int) -> None:
        """Raise SimulationError if the result of step number `step` diverged (simulate's checks), before it is
        committed."""
        if not math.isfinite(q @ q + v @ v) and not (np.isfinite(q).all() and np.isfinite(v).all()):
            bad_v = ~np.isfinite(v)
            if bad_v.any():
                dof = int(np.argmax(bad_v))
            else:
                finite_q = np.where(np.isfinite(q), q, 0.0)
                dof = int(np.argmax(~np.isfinite(self.system.space.difference(self._q, finite_q))))
            self._fail(
                "diverged",
                f"diverged at t = {t_next:.6g} s (step {step}): the state became non-finite in "
                f"'{self.system.dof_names[dof]}'; {_cure(self.system, self.dt)}",
            )
        if not self.check_energy:
            return
        with np.errstate(over="ignore", invalid="ignore"):
            kinetic, potential = self.system.unchecked_energies(q, v)
            work = float(flows[self._is_work].sum())
            dissipated = float(flows[~self._is_work].sum())
            error = kinetic + potential - self._energy_reference - work + dissipated
        bound = BLOWUP_FACTOR * (self._energy_scale + abs(work))
        if math.isfinite(error) and abs(error) <= bound and dissipated <= bound:
            return
        fastest = int(np.argmax(np.abs(v)))
        if not math.isfinite(error):
            what = "the energy became non-finite"
        elif abs(error) > bound:
            what = f"the energy error {error:.3g} J exceeds {BLOWUP_FACTOR:g} times the run's energy scale"
        else:
            what = f"the dissipated energy {dissipated:.3g} J exceeds {BLOWUP_FACTOR:g} times the run's energy scale"
        scale = f" ({bound / BLOWUP_FACTOR:.3g} J)" if math.isfinite(error) else ""
        self._fail(
            "diverged",
            f"diverged at t = {t_next:.6g} s (step {step}): {what}{scale}, fastest in "
            f"'{self.system.dof_names[fastest]}' ({v[fastest]:.3g}); {_cure(self.system, self.dt)}",
        )

    def _fail(self, status: str, message: str) -> None:
        """Raise SimulationError carrying the state before the failed step as a one-sample trajectory."""
        self._fsal_row = None
        raise SimulationError(message, status=status, trajectory=self._snapshot(status))

    def _torque(self, tau: Any, t: float | None) -> np.ndarray:
        """tau checked like simulate()'s controller outputs and saturated at the effort limits (counted)."""
        system = self.system
        fast = type(tau) is np.ndarray and tau.dtype == np.float64 and tau.shape == (system.nv,)
        if not fast or not math.isfinite(tau @ tau) or (system.floating_base and tau[:6].any()):
            try:  # the full check, with the precise reason
                tau = system.check_tau(tau)
            except InvalidArgumentError as exc:
                if t is None:
                    raise
                raise InvalidArgumentError(f"controller output at t = {t:.6g} s: {exc}") from None
        if self._effort is not None:  # actuators saturate at the URDF's effort limits: clip, count, report
            over = np.abs(tau) > self._effort
            if over.any():
                tau = np.clip(tau, -self._effort, self._effort)
                self.stats["saturated_controls"] += 1
                self._saturated += over
                self.stats["saturated_dofs"] = {system.dof_names[i]: int(n) for i, n in enumerate(self._saturated) if n}
        return _frozen(np.array(tau, dtype=float))

    def _snapshot(self, status: str) -> Trajectory:
        """The current state as a one-sample Trajectory (what a failed step's SimulationError carries)."""
        kinetic, potential = self.system.unchecked_energies(self._q, self._v)
        work, dissipated = self.work, self.dissipated
        total = kinetic + potential
        one = np.ones(1)
        return Trajectory(
            t=np.array([self.t]),
            q=self._q[None, :].copy(),
            v=self._v[None, :].copy(),
            tau=self._tau[None, :].copy(),
            kinetic_energy=kinetic * one,
            potential_energy=potential * one,
            total_energy=total * one,
            work=work * one,
            dissipated=dissipated * one,
            energy_error=(total - self._energy_reference - work + dissipated) * one,
            ledger={
                name: LedgerEntry(kind, flow * one)
                for name, kind, flow in zip(self._element_names, self._kinds, self._flows, strict=True)
            },
            stats=dict(self.stats),
            status=status,
            metadata={"integrator": self.integrator.name, "options": {"dt": self.dt, **self.options}},
        )

    def __repr__(self) -> str:
        name = getattr(self.system, "name", type(self.system).__name__)
        return f"<Stepper {name} {self.integrator.name} dt={self.dt:g} s at t={self.t:g} s>"


def _frozen(array: np.ndarray) -> np.ndarray:
    """The array made read-only: users see the state without copies and cannot edit it behind our back."""
    array.setflags(write=False)
    return array


def _cure(system: Robot, dt: float) -> str:
    implicit = stable_implicit_integrators(system)
    also = f", or an implicit integrator ({', '.join(implicit)})" if implicit else ""
    return f"try a smaller dt (now {dt:g} s){also}"


def _stiff_cure(system: Robot) -> str:
    implicit = stable_implicit_integrators(system)
    return (
        f"try an implicit integrator ({', '.join(implicit)}) or looser tolerances"
        if implicit
        else "try looser tolerances"
    )
