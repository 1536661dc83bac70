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

from .. import native
from ..core import EMPTY, FULL, REACHED, STEPPED, Core, RowStop, collapsed_detail, diverged_detail
from ..exceptions import InvalidArgumentError
from ..integrators import INTEGRATORS, Integrator
from ..integrators.explicit_rk import DormandPrince853, EmbeddedRungeKutta, ExplicitRungeKutta
from ..integrators.partitioned import SemiImplicitEuler
from ..integrators.timestepping import ANDERSON_CAPACITY, TOLERANCE, TimeStepping, solver_counts
from ..recording import SampleStore
from ..robot import Robot
from ..scenes.scene import Scene
from ..state import _HALF_SERIES
from ..step_control import LANDING_FRACTION, SLIVER, ConstantStep, PIController

# The registry's explicit methods, which the engine renders (its kinds: kernel.hpp's Kind).
NATIVE_METHODS = {
    ExplicitRungeKutta: 0,
    EmbeddedRungeKutta: 1,
    DormandPrince853: 2,
    SemiImplicitEuler: 3,
    TimeStepping: 4,  # on contact scenes (contact_data)
}
# The collision shapes the engine rebuilds (src/native/contact.cpp's ShapeKind); others stay on the Python kernel.
NATIVE_SHAPES = {"halfspace": 0, "box": 1, "sphere": 2, "cylinder": 3}
# advance() returns to Python after about this much work [s] (interrupts, signals)
BUDGET_SECONDS = 0.03
_STATUSES = (REACHED, STEPPED, FULL, EMPTY)
_NEED_ROOM = 4
_DIVERGED, _COLLAPSED, _CONTROL = 1, 2, 3


def why_not_native(system: Any, method: Integrator) -> str | None:
    """None when the native kernel runs `method` on `system`, else why not (one phrase for describe() and the
    run header)."""
    if os.environ.get(native.ENV, "") == "0":  # read at every run (native.available: once, at import)
        return f"{native.ENV}=0"
    if not native.available:
        return native.why_unavailable
    if type(method) is TimeStepping:  # any max_iterations: the engine takes it as data
        if getattr(system, "contact", None) is None:
            return "integrator 'timestepping' runs natively on contact scenes only"
    elif type(method) not in NATIVE_METHODS or INTEGRATORS.get(method.name) is not method:
        return f"integrator '{method.name}' is not an explicit method of the registry"
    elif getattr(system, "contact", None) is not None:
        return "the scene has contact, which only the timestepping integrator steps"
    if type(system) is Scene:
        reason = _scene_reason(system)
        if reason is not None:
            return reason
    elif type(system) is not Robot:
        return f"the system is a {type(system).__name__}, not a Robot or a Scene"
    elif system.record_fields:
        return "the system records fields per sample"
    replaced = [name for name in _SYSTEM_HOOKS if name in vars(system)]
    replaced += [f"space.{name}" for name in _SPACE_HOOKS if name in vars(system.space)]
    if replaced:  # e.g. a test or a study that wraps the dynamics: the engine would not call it
        return f"the system's {', '.join(replaced)} replaced in Python"
    return None


def _scene_reason(scene: Scene) -> str | None:
    """Why the native kernel cannot render this scene's physics (constraints, contact, mimic joints, a force whose
    shape is Python code), or None."""
    if scene.contact is not None:
        shapes = sorted({g.kind for g in scene.contact.geometries} - set(NATIVE_SHAPES))
        if shapes:
            return (
                f"the scene's collision geometry has {', '.join(shapes)} shapes (the native kernel renders "
                f"{', '.join(NATIVE_SHAPES)})"
            )
    if scene.constraints is not None:
        return f"the scene has constraints ({', '.join(scene.constraints.names)}), which run on the Python kernel"
    if scene.mimic:
        return "the scene honours mimic joints (forward dynamics by CRBA), which run on the Python kernel"
    elements = scene.elements
    if elements is not None:
        reason = elements.native_reason()
        if reason is not None:
            return reason
        replaced = [name for name in ("evaluate", "powers", "potential_energies") if name in vars(elements)]
        if replaced:
            return f"the scene's elements.{', elements.'.join(replaced)} replaced in Python"
    return None


# What the engine computes itself: replaced on an instance (a wrapper), the run stays on the Python kernel.
_SYSTEM_HOOKS = ("unchecked_forward_dynamics", "ledger_power", "unchecked_energies")
_SPACE_HOOKS = ("integrate", "difference", "chart_velocity")


def contact_data(scene: Any, method: TimeStepping) -> dict[str, Any]:
    """A contact scene's geometry, constraints and constants as _native.ContactScene takes them (contact.py's
    ContactModel and module constants, timestepping.py's solver settings), read at each run."""
    from ..scenes import contact as c

    model = scene.contact
    body_index = {name: k for k, name in enumerate(model.body_names)}
    shapes = [
        (
            NATIVE_SHAPES[g.kind],
            int(g.joint),
            body_index[g.body],
            np.array(g.placement.rotation, dtype=float),
            np.array(g.placement.translation, dtype=float),
            [float(x) for x in g.dimensions],
        )
        for g in model.geometries
    ]
    nv = scene.model.nv
    bound = np.zeros(nv)
    for jid, force in model.friction_joints:
        bound[scene.model.joints[jid].idx_v] = force
    return {
        "shapes": shapes,
        "pairs": [(int(a), int(b)) for a, b in model.pairs],
        "friction": [float(mu) for mu, _ in model._coefficients],
        "restitution": [float(e) for _, e in model._coefficients],
        "limited_joints": [int(j) for j in model.limited_joints],
        "limit_margin": np.full(scene.model.nq, c.LIMIT_MARGIN),
        "friction_joints": [int(j) for j, _ in model.friction_joints],
        "friction_bound": bound,
        "reals": [
            c.SPECULATIVE_MARGIN,
            c.PENETRATION_CORRECTION,
            c.PENETRATION_SLOP,
            c.MAX_CORRECTION_SPEED,
            c.TOUCHING,
            c.DELASSUS_DAMPING,
            TOLERANCE,
            model.gravity,
        ],
        "ints": [c.MAX_PATCH_POINTS, ANDERSON_CAPACITY, method.max_iterations, int(model.solver == "pgs")],
        "flow_work": [kind == "work" for _, kind in scene.ledger_elements[:-4]],
    }


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
        data.update(
            fsal=method.fsal, e=method._e.tolist(), dense=dense.tolist() if dense is not None and dense.any() else []
        )
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


class NativeKernel:
    """The running rows' states in the engine: a Kernel (kernels/base.py) for Core's own code (records, stops,
    torques, snapshots); the steps themselves are taken by the engine inside NativeCore.advance. The engine is made
    once the step-size controller is known (bind())."""

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
        self._start = 0.0  # t until the engine exists
        self._saves = 0  # snapshots taken (the engine keeps the latest)
        self.engine: Any = None
        self.method_data = method_data(method)
        self.torques: Any = None  # native control: the driver's Torques (the Python controllers, for messages)
        self._keep: tuple[Any, ...] = ()  # arrays the engine writes or reads for the run

    def bind(self, control: ConstantStep | PIController) -> None:
        """Make the engine for this controller."""
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
        self.engine = native.module.Kernel(  # type: ignore[union-attr]
            native.load_model(system.model),
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
        self.engine.t = self._start
        elements = getattr(system, "elements", None)
        if elements is not None:  # a Scene's force elements (why_not_native said they render)
            data = elements.native_data(native.load_model)
            self.engine.set_scene(
                native.module.SceneForces(  # type: ignore[union-attr]
                    native.load_model(system.model),
                    data["zero_all"],
                    data["inv_vs"],
                    data["springs"],
                    data["circular"],
                    data["damped"],
                    data["rough"],
                    data["ledger_damped"],
                    data["ledger_rough"],
                    data["wrenches"],
                    data["push_models"],
                    data["energies"],
                )
            )
        if type(self.method) is TimeStepping:  # a contact scene (why_not_native said it renders)
            data = contact_data(system, self.method)
            flow_work = data.pop("flow_work")
            self.engine.set_contact(
                native.module.ContactScene(native.load_model(system.model), **data),  # type: ignore[union-attr]
                flow_work,
            )

    def control_natively(self, torques: Any, settings: Any, saturation: Any, calls: np.ndarray) -> bool:
        """Hand the run's torques to the engine when it renders them (native_policies): it then computes them at its
        own control instants, counted into `calls` and `saturation`'s arrays. Returns whether it does."""
        policies = native_policies(self.system, torques, settings)
        if policies is None:
            return False
        taus = policies.pop("taus")
        self.engine.set_policies(
            native.module.Policies(taus=taus, **policies),  # type: ignore[union-attr]
            calls,
            saturation.calls,
            saturation.dofs,
        )
        self.torques = torques
        self._keep = (taus, calls, saturation.calls, saturation.dofs)
        return True

    # ---- the Kernel interface (kernels/base.py) ---------------------------------------------------------------------
    @property
    def n(self) -> int:
        return len(self._initial[0]) if self.engine is None else int(self.engine.running)

    @property
    def t(self) -> float:
        return self._start if self.engine is None else float(self.engine.t)

    def start_at(self, t: float) -> None:
        if self.engine is None:
            self._start = t
        else:
            self.engine.t = t

    def set_torques(self, TAU: np.ndarray, jump: bool) -> None:
        self.engine.set_torques(np.ascontiguousarray(TAU, dtype=float), jump)

    def keep(self, keep: np.ndarray) -> None:
        self.engine.keep([bool(x) for x in keep])

    def states(self) -> tuple[list[np.ndarray], list[np.ndarray]]:
        return list(self.engine.running_q()), list(self.engine.running_v())

    def flows_of(self, j: int) -> np.ndarray:
        return np.asarray(self.engine.flows_of(self._row(j)))

    def set_row(self, j: int, q: np.ndarray, v: np.ndarray) -> None:
        row = self._row(j)
        self.engine.set_state(row, q, v, self.engine.flows_of(row))

    def snapshot(self) -> tuple[int, float]:
        """Every row's whole state (its contact solver's too) and the time (Stepper: one row). The engine keeps
        the state: only the latest snapshot can be restored."""
        self.engine.save()
        self._saves += 1
        return self._saves, self.t

    def restore(self, snapshot: tuple[int, float]) -> None:
        saves, t = snapshot
        if saves != self._saves:
            raise RuntimeError("the native kernel restores its latest snapshot only")
        self.engine.restore_saved()
        self.start_at(t)

    def solver_stats(self, j: int) -> dict[str, int]:
        """Running row j's contact solver counts (TimeStepping.solver_stats), {} without contact."""
        if not self.engine.has_contact:  # (without looking the row up: Core.stop asks for every row it stops)
            return {}
        return self.row_solver_stats(self._row(j))

    def row_solver_stats(self, row: int) -> dict[str, int]:
        """Run row `row`'s contact solver counts, {} without contact."""
        if not self.engine.has_contact:
            return {}
        return solver_counts(self.engine.contact_row(row))

    def _row(self, j: int) -> int:
        """The run row of running position j."""
        return int(self.engine.running_rows()[j])

    def write_sample(self, store: SampleStore, i: int, index: Any, js: np.ndarray | None = None) -> None:
        """Write the current state of the run rows `index` (the store's columns: an int, a slice or the rows) as
        sample i (the engine knows each row's state by its row; js, their positions, need not be looked up)."""
        if type(index) is int:
            rows = [index]
        elif isinstance(index, slice):
            rows = list(range(store.B))[index]
        else:
            rows = [int(b) for b in index]
        self.engine.write_rows(i, rows, store, *store.batch_arrays)


def native_policies(system: Any, torques: Any, settings: Any) -> dict[str, Any] | None:
    """The run's torques as _native.Policies takes them, when the engine renders them: open-loop sequences (taus), or
    one built-in controller per row (PD, GravityCompensation, PDGravity, made for this very system); else None (a
    Python controller, called by the driver at its control instants)."""
    from ..controllers import PD, GravityCompensation, PDGravity

    nv, actuated = system.nv, system.actuated
    n = actuated.stop - actuated.start
    rows: list[tuple[Any, ...]] = []
    taus = np.zeros((0, 0, 0))
    if torques.kind == "taus":
        taus = np.ascontiguousarray(torques.taus, dtype=float)
    elif torques.kind == "callables":
        for controller in torques.callables:
            kind = type(controller)
            if kind not in (PD, GravityCompensation, PDGravity) or "__call__" in vars(controller):
                return None
            if controller.robot is not system:
                return None
            if kind is GravityCompensation:
                if controller._model is not system.model or controller._a != actuated:
                    return None
                rows.append((1, system.neutral(), np.zeros(nv), np.zeros(n), np.zeros(n)))
                continue
            pd = controller if kind is PD else controller.pd
            if kind is PDGravity and (
                type(pd) is not PD
                or type(controller.gravity) is not GravityCompensation
                or "__call__" in vars(pd)
                or "__call__" in vars(controller.gravity)
                or controller.gravity._model is not system.model
                or controller.gravity._a != actuated
            ):
                return None
            if pd._model is not system.model or pd._a != actuated:
                return None
            rows.append((0 if kind is PD else 2, pd.q_ref, pd.v_ref, pd.kp, pd.kd))
    else:
        return None
    limited = np.isfinite(system.effort_limit)
    adaptive = bool(settings.adaptive)
    return {
        "nv": nv,
        "a_start": actuated.start,
        "a_stop": actuated.stop,
        "rows": rows,
        "taus": taus,
        "effort": np.array(system.effort_limit, dtype=float),
        "saturate": bool(limited.any()),
        "adaptive": adaptive,
        "every_step": adaptive and settings.control_dt is None,
        "dt": float(settings.dt),
        "duration": float(settings.duration),
        "period": float(settings.control_dt) if settings.control_dt is not None else 0.0,
        "every": int(settings.control_every),
        "n_steps": int(settings.n_steps),
    }


def next_budget(budget: int, steps: int, elapsed: float) -> int:
    """The steps of the next engine call, so that it takes about BUDGET_SECONDS: the rate of the call just made
    (`steps` taken in `elapsed` seconds; a call that returned early at an event took fewer than its budget), at
    most 4 times the current budget (one fast call must not make the next one run for minutes, deaf to Ctrl-C), and
    from 16 to 2**20 steps."""
    estimate = int(steps * BUDGET_SECONDS / max(elapsed, 1e-6))
    return max(16, min(1 << 20, 4 * budget, estimate))


class NativeCore(Core):
    """A Core whose loop runs in the engine (see the module docstring); its kernel is a NativeKernel.

    The engine writes the core's counts, the store's count, the sampler's and the controller's state itself before
    it returns (plain attribute assignments with the GIL held), and appends the rows it stopped to `_pending`: a
    Ctrl-C, whose handler runs as soon as the engine returns, finds the run's samples and counts consistent, and the
    stops are taken into account whenever the driver next looks (take_stops()).
    """

    kernel: NativeKernel  # type: ignore[assignment]

    def __init__(self, **kwargs: Any):
        super().__init__(**kwargs)
        self.kernel.bind(self.control)
        self._budget = 64  # steps per engine call, adapted to take about BUDGET_SECONDS
        self._pending: list[tuple[Any, ...]] = []  # rows the engine stopped, not yet recorded as RowStops

    def advance(self, t_stop: float, *, max_steps: int | None = None) -> str:
        """Core.advance, in the engine: the same statuses, samples, counts and stops."""
        kernel, control, sampler, store = self.kernel, self.control, self.sampler, self.store
        tolerance = LANDING_FRACTION * control.scale(t_stop) if control.adaptive else 0.0
        taken = 0
        while True:
            limit = self._budget if max_steps is None else min(self._budget, max_steps - taken)
            start = time.perf_counter()
            status, steps, need = kernel.engine.advance(
                t_stop, limit, tolerance, self, store, sampler, control, *store.batch_arrays, self._pending
            )
            elapsed = time.perf_counter() - start
            self._take_pending()
            taken += steps
            if steps:
                self._budget = next_budget(self._budget, steps, elapsed)
            if status == _NEED_ROOM:
                store.room(need)
                continue
            reason = _STATUSES[status]
            if reason == STEPPED and (max_steps is None or taken < max_steps):
                continue  # the budget, not the caller's limit: Python runs here (signals), then the engine again
            return reason

    def _control_failure(self, row: int, t: float) -> InvalidArgumentError:
        """Why row `row`'s native controller output at t was refused: its Python controller's output at the row's
        state, checked as the driver checks it (torques.check_torque)."""
        from ..torques import check_torque

        q, v = self.kernel.engine.snapshot_row(row)[:2]
        try:
            check_torque(self.system, self.kernel.torques.callables[row](t, q, v), t)
        except InvalidArgumentError as exc:
            return exc
        return InvalidArgumentError(f"controller output at t = {t:.6g} s: tau must be finite")

    def take_stops(self) -> list[RowStop]:
        self._take_pending()
        return super().take_stops()

    def _take_pending(self) -> None:
        """Record the rows the engine stopped (it already took them out of its running rows): their RowStop, frozen
        counts and last samples, as Core._note_stops and Core.stop record them. Each is taken whole or again."""
        while self._pending:
            code, row, when, step, dof, count, added, steps, rejected, evaluations, h, minimum, error = self._pending[0]
            cause: BaseException | None = None
            failed_step: int | None = int(step)
            if code == _DIVERGED:
                status, detail = "diverged", diverged_detail(self.system, dof, self.dt_hint)
            elif code == _CONTROL:  # at a control instant, not in a step
                status, cause = "failed", self._control_failure(row, when)
                detail, failed_step = str(cause), None
            else:
                status = "step_collapsed"
                detail = collapsed_detail(self.system, h, minimum, None if math.isnan(error) else error)
            if row in self.rows:
                stats = self.kernel.row_solver_stats(int(row))
                if stats:
                    self.solver_stats[int(row)] = stats
                sample = count + added - 1
                self.stops.append(
                    RowStop(int(row), status, when, failed_step, detail, sample, bool(added), cause, cause is not None)
                )
                self.stopped_counts[row] = (steps, rejected, evaluations)
                self.store.stop(np.array([row]), bool(added), count=count)
                keep = self.rows != row
                n = int(keep.sum())
                self.extra_evaluations[:n] = self.extra_evaluations[: len(keep)][keep]
                self._set_rows(self.rows[keep])
            self._pending.pop(0)
