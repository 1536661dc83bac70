"""The native kernel: the stepping core's loop (core.Core.advance) run in C++ for an eligible run.

The Python core is the specification; the C++ engine (src/native/, ``_native.Kernel``) renders the same loop and
arithmetic. Everything crosses as named data: each object the engine renders exports its own ``native_data()``
(the method, the configuration space's chart map, the step-size controller, a scene's force elements and contact
model, the built-in controllers), which this module hands over as the bound structs of the same field names
(``_native.Method``, ``Chart``, ``ConstantStep`` / ``PIController``, ``SceneForces``, ``ContactScene``, ``Policies``);
a field missing or misnamed on either side fails there, naming it. The state the loop advances (the core's counts,
the store's count, the sampler's next output, the controller's state) crosses as a ``_native.LoopState`` the engine
advances in place; the run's settings and initial states as a ``_native.RunSettings`` (NativeKernel.native_data()),
and what each engine call reads and reports beside (the sampler, the stops, the contacts, the rows' evaluations) as
a ``_native.AdvanceIO``.

NativeCore is a Core whose advance() hands the whole loop to the engine between the driver's events and returns at
least every ~30 ms of work (so Ctrl-C and SIGTERM are honoured with every sample kept); everything else (recording
at the driver's request, stopping rows, the messages of rows that stop) is Core's own code.
"""

from __future__ import annotations

import math
import os
import time
import weakref
from operator import attrgetter
from typing import Any

import numpy as np

from .. import native
from ..core import STEPPED, Core, RowStop, collapsed_detail, diverged_detail
from ..exceptions import InvalidArgumentError
from ..integrators import INTEGRATORS, Integrator
from ..integrators.explicit_rk import DormandPrince853, EmbeddedRungeKutta, ExplicitRungeKutta
from ..integrators.partitioned import SemiImplicitEuler
from ..integrators.timestepping import TimeStepping, solver_counts
from ..recording import STORE_ARRAYS, SampleStore
from ..robot import Robot
from ..scenes.contact import NATIVE_SHAPES
from ..scenes.scene import Scene
from ..step_control import LANDING_FRACTION, ConstantStep, PIController
from ..torques import command_bounds

# The registry's explicit methods (and the contact time-stepper), which the engine renders from their native_data().
NATIVE_METHODS = (ExplicitRungeKutta, EmbeddedRungeKutta, DormandPrince853, SemiImplicitEuler, TimeStepping)
# advance() returns to Python after about this much work [s] (interrupts, signals)
BUDGET_SECONDS = 0.03
_NEED_ROOM = "need_room"  # the engine's status besides core.py's REACHED, STEPPED, FULL, EMPTY
# Randomised rows' physics as rendered for the engine, by row system (a Scene.with_parameters scene, not modified
# after it is built) with the time-stepper's solver settings they were rendered with: a BatchStepper (gym vector
# environments) makes a new engine at every reset, and renders again only the rows whose scene is new.
_RENDERED: weakref.WeakKeyDictionary[Any, tuple[Any, Any]] = weakref.WeakKeyDictionary()


def why_not_native(system: Any, method: Integrator, systems: list[Any] | None = None) -> str | None:
    """None when the native kernel runs `method` on `system` (with `systems`, each row's own: a randomised scene's
    rows), else why not (one phrase for describe() and the run header)."""
    if os.environ.get(native.ENV, "") == "0":  # read at every run (native.available: once, at import)
        return f"{native.ENV}=0"
    if not native.available:
        return native.why_unavailable
    if systems is not None and getattr(system, "contact", None) is not None:
        held = [[jid for jid, _ in row.contact.friction_joints] for row in systems]  # (their forces may differ)
        if any(joints != held[0] for joints in held):  # the engine's rows share their constraints (same_contact)
            return "the rows' joints with exact dry friction differ, which runs on the Python kernel"
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
    if scene.sensors is not None:
        reason = scene.sensors.native_reason()
        if reason is not None:
            return f"the scene's sensors: {reason}"
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
    """A contact scene's geometry, constraints and constants as _native.ContactScene takes them: the contact model's
    native_data() with the time-stepper's solver settings (TimeStepping.solver_data) among its constants, read at
    each run."""
    data = scene.contact.native_data()
    return {**data, "constants": {**data["constants"], **method.solver_data()}}


def _chart(space: Any) -> Any:
    """The configuration space's chart map as _native.Chart."""
    module = native.module
    data = space.native_data()
    return module.Chart(  # type: ignore[union-attr]
        blocks=[module.ChartBlock(**block) for block in data["blocks"]],  # type: ignore[union-attr]
        half_series=data["half_series"],
    )


def _scene_forces(elements: Any, model: Any) -> Any:
    """A scene's force elements (ForceElements.native_data()) as _native.SceneForces."""
    module = native.module
    data = elements.native_data(native.load_model)
    terms = {
        "springs": module.SpringTerm,  # type: ignore[union-attr]
        "circular": module.CircularTerm,  # type: ignore[union-attr]
        "damped": module.CoefficientTerm,  # type: ignore[union-attr]
        "rough": module.CoefficientTerm,  # type: ignore[union-attr]
        "ledger_damped": module.CoefficientTerm,  # type: ignore[union-attr]
        "ledger_rough": module.CoefficientTerm,  # type: ignore[union-attr]
        "wrenches": module.WrenchTerm,  # type: ignore[union-attr]
        "energies": module.SpringEnergy,  # type: ignore[union-attr]
    }
    for name, struct in terms.items():
        data[name] = [struct(**term) for term in data[name]]
    return module.SceneForces(model, **data)  # type: ignore[union-attr]


def _scene_actuators(actuators: Any, model: Any) -> Any:
    """A scene's actuators (Actuators.native_data()) as _native.SceneActuators."""
    module = native.module
    data = actuators.native_data()
    data["terms"] = [module.ActuatorTerm(**term) for term in data["terms"]]  # type: ignore[union-attr]
    return module.SceneActuators(model, **data)  # type: ignore[union-attr]


def _sensors(sensors: Any) -> Any:
    """A scene's sensors (Sensors.native_data()) as _native.Sensors."""
    module = native.module
    data = sensors.native_data()
    items = [module.SensorItem(**item) for item in data["items"]]  # type: ignore[union-attr]
    return module.Sensors(**{**data, "items": items})  # type: ignore[union-attr]


def _contact_scene(data: dict[str, Any], model: Any) -> Any:
    """contact_data()'s dict as _native.ContactScene."""
    module = native.module
    shapes = [module.ContactShape(**shape) for shape in data["shapes"]]  # type: ignore[union-attr]
    solver = module.SolverSettings(**data["constants"]["solver"])  # type: ignore[union-attr]
    constants = module.ContactConstants(**{**data["constants"], "solver": solver})  # type: ignore[union-attr]
    return module.ContactScene(model, **{**data, "shapes": shapes, "constants": constants})  # type: ignore[union-attr]


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
        systems: list[Any] | None = None,
    ):
        self.system, self.method = system, method
        self.systems = systems
        self.rtol, self.atol = rtol, atol
        self.num_threads = num_threads
        self._initial = (np.ascontiguousarray(Q0, dtype=float), np.ascontiguousarray(V0, dtype=float))
        self._start = 0.0  # t until the engine exists
        self._saves = 0  # snapshots taken (the engine keeps the latest)
        self.engine: Any = None
        self.torques: Any = None  # native control: the driver's Torques (the Python controllers, for messages)
        self._keep: tuple[Any, ...] = ()  # arrays the engine writes or reads for the run
        self._store: tuple[Any, Any] = ((), None)  # a store's arrays and their _native.Store

    def bind(self, control: ConstantStep | PIController) -> None:
        """Make the engine for this controller."""
        system, module = self.system, native.module
        assert module is not None  # why_not_native said the extension runs
        model = native.load_model(system.model)
        step = module.ConstantStep if isinstance(control, ConstantStep) else module.PIController
        self.engine = module.Kernel(
            model,
            method=module.Method(**self.method.native_data()),  # type: ignore[attr-defined]
            chart=_chart(system.space),
            control=step(**control.native_data()),
            run=module.RunSettings(**self.native_data()),
        )
        self.engine.t = self._start
        actuators = getattr(system, "actuators", None)
        if actuators is not None:  # a Scene's actuators, before its elements (their ledger entries come first)
            self.engine.set_actuators(_scene_actuators(actuators, model))
        elements = getattr(system, "elements", None)
        if elements is not None:  # a Scene's force elements (why_not_native said they render)
            self.engine.set_scene(_scene_forces(elements, model))
        if type(self.method) is TimeStepping:  # a contact scene (why_not_native said it renders)
            flow_work = [kind == "work" for _, kind in system.ledger_elements[:-4]]  # the contact's four come last
            self.engine.set_contact(_contact_scene(contact_data(system, self.method), model), flow_work)
        if self.systems is not None:  # randomised rows: each its own model, damping, elements, contact, actuators
            self.engine.set_rows([self._row_physics(row) for row in self.systems])

    def _row_physics(self, system: Any) -> Any:
        """A row's own system (Scene.with_parameters) as _native.RowPhysics (made once per system and solver
        settings: _RENDERED)."""
        settings = self.method.solver_data() if type(self.method) is TimeStepping else None
        held = _RENDERED.get(system)
        if held is not None and held[0] == settings:
            return held[1]
        physics = self._render_row(system)
        _RENDERED[system] = (settings, physics)
        return physics

    def _render_row(self, system: Any) -> Any:
        module = native.module
        model = native.load_model(system.model)
        elements = getattr(system, "elements", None)
        actuators = getattr(system, "actuators", None)
        sensors = getattr(system, "sensors", None)
        contact = None
        if type(self.method) is TimeStepping:
            contact = _contact_scene(contact_data(system, self.method), model)
        return module.RowPhysics(  # type: ignore[union-attr]
            model=model,
            damping=np.asarray(system.damping, dtype=float),
            scene=_scene_forces(elements, model) if elements is not None else None,
            contact=contact,
            actuators=_scene_actuators(actuators, model) if actuators is not None else None,
            sensors=_sensors(sensors) if sensors is not None else None,
        )

    def native_data(self) -> dict[str, Any]:
        """The run's settings and initial states as _native.RunSettings takes them: damping (nv,) and whether its
        term is in play (its ledger line; a scene that draws damping keeps it in every row), the ledger's size,
        the tolerances (NaN: none), Q0 (B, nq), V0 (B, nv), the threads."""
        system = self.system
        Q0, V0 = self._initial
        return {
            "damping": np.asarray(system.damping, dtype=float),
            "damped": system.damped,
            "n_ledger": len(system.ledger_elements),
            "rtol": math.nan if self.rtol is None else float(self.rtol),
            "atol": math.nan if self.atol is None else float(self.atol),
            "Q0": Q0,
            "V0": V0,
            "num_threads": self.num_threads,
        }

    def control_natively(self, torques: Any, settings: Any, saturation: Any, calls: np.ndarray) -> bool:
        """Hand the run's torques to the engine when it renders them (native_policies): it then computes them at its
        own control instants, counted into `calls` and `saturation`'s arrays. Returns whether it does. Randomised rows
        whose command bounds differ (drawn effort limits) are controlled from Python: the engine's controllers clip
        at one (nv,) pair of bounds."""
        if saturation.low is not None and saturation.low.ndim == 2:
            return False
        native_torques = native_policies(self.system, torques, settings)
        if native_torques is None:
            return False
        policies, taus = native_torques
        self.engine.set_policies(policies, calls, saturation.calls, saturation.dofs)
        self.torques = torques
        self._keep = (policies, taus, calls, saturation.calls, saturation.dofs)
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

    # ---- sensors (sensors.Sensing) ----------------------------------------------------------------------------------
    def set_sensors(self, sensors: Any, every: int, done: np.ndarray) -> None:
        """The scene's sensors tick in the engine at the end of every `every`-th step of a row (done: the steps each
        row took before, (B,)); take_ticks() collects their measurements."""
        self.engine.set_sensors(_sensors(sensors), int(every), [int(d) for d in done])
        self._ticks = np.zeros((0, sensors.width))

    def take_ticks(self, into: Any = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The engine's ticks since the last call: times (n,), rows (n,), measurements (n, width), written into
        ``into(n)`` (a C-ordered (n, width) array, e.g. the samples the readings go to) or where it gives None, into
        a buffer the next call reuses (no fresh memory per call)."""
        n = self.engine.tick_count()
        values = into(n) if into is not None else None
        if values is None:
            if len(self._ticks) < n:
                self._ticks = np.empty((max(n, 2 * len(self._ticks)), self._ticks.shape[1]))
            values = self._ticks[:n]
        times, rows = self.engine.take_ticks(values)
        return np.asarray(times), np.asarray(rows, dtype=np.int64), values

    def measure_start(self, js: np.ndarray, h: float) -> np.ndarray:
        """The first measurements of the running rows at positions js (RowKernel.measure_start on their states: the
        same trial step, bit for bit, as the engine's steps are the row kernel's)."""
        from .row import RowKernel

        Q, V = self.engine.running_q(), self.engine.running_v()
        systems = None
        if self.systems is not None:  # randomised rows: each on its own system
            rows = self.engine.running_rows()
            systems = [self.systems[int(rows[j])] for j in js]
        trial = RowKernel(self.system, self.method, Q[js], V[js], rtol=self.rtol, atol=self.atol, systems=systems)
        trial.start_at(self.t)
        return trial.measure_start(np.arange(len(js)), h)

    def write_sample(self, store: SampleStore, i: int, index: Any, js: np.ndarray | None = None) -> None:
        """Write the current state of the run rows `index` (the store's columns: an int, a slice or the rows) as
        sample i (the engine knows each row's state by its row; js, their positions, need not be looked up)."""
        if type(index) is int:
            rows = [index]
        elif isinstance(index, slice):
            rows = list(range(store.B))[index]
        else:
            rows = [int(b) for b in index]
        self.engine.write_rows(i, rows, store=self.store_arrays(store), contacts=store.contacts)

    def store_arrays(self, store: SampleStore) -> Any:
        """The store's batch-major arrays as _native.Store (made again only when the store reallocates them)."""
        arrays, struct = self._store
        if arrays is not store.batch_arrays:
            arrays = store.batch_arrays
            struct = native.module.Store(**dict(zip(STORE_ARRAYS, arrays, strict=True)))  # type: ignore[union-attr]
            self._store = (arrays, struct)
        return struct


def native_policies(system: Any, torques: Any, settings: Any) -> tuple[Any, np.ndarray] | None:
    """The run's torques as _native.Policies (with the open-loop torques it reads, which must stay alive for the
    run), when the engine renders them: open-loop sequences (taus), or one built-in controller per row (PD,
    GravityCompensation, PDGravity, made for this very system: their native_data()); else None (a Python
    controller, called by the driver at its control instants)."""
    module = native.module
    assert module is not None
    rows = []
    taus = np.zeros((0, 0, 0))
    if torques.kind == "taus":
        taus = np.ascontiguousarray(torques.taus, dtype=float)
    elif torques.kind == "callables":
        for controller in torques.callables:
            # a built-in controller (its class defines native_data; a subclass may compute otherwise), unwrapped
            if "native_data" not in vars(type(controller)) or "__call__" in vars(controller):
                return None
            data = controller.native_data(system)
            if data is None:  # made for another model
                return None
            rows.append(module.Policy(**data))
    else:
        return None
    adaptive = bool(settings.adaptive)
    low, high = command_bounds(system)
    policies = module.Policies(
        nv=system.nv,
        a_start=system.actuated.start,
        a_stop=system.actuated.stop,
        rows=rows,
        taus=taus,
        low=low,
        high=high,
        saturate=bool((np.isfinite(low) | np.isfinite(high)).any()),
        adaptive=adaptive,
        every_step=adaptive and settings.control_dt is None,
        dt=float(settings.dt),
        duration=float(settings.duration),
        period=float(settings.control_dt) if settings.control_dt is not None else 0.0,
        every=int(settings.control_every),
        n_steps=int(settings.n_steps),
    )
    return policies, taus


def next_budget(budget: int, steps: int, elapsed: float) -> int:
    """The steps of the next engine call, so that it takes about BUDGET_SECONDS: the rate of the call just made
    (`steps` taken in `elapsed` seconds; a call that returned early at an event took fewer than its budget), at
    most 4 times the current budget (one fast call must not make the next one run for minutes, deaf to Ctrl-C), and
    from 16 to 2**20 steps."""
    estimate = int(steps * BUDGET_SECONDS / max(elapsed, 1e-6))
    return max(16, min(1 << 20, 4 * budget, estimate))


def _in_loop(name: str) -> property:
    """An attribute of NativeCore kept in its loop state (a _native.LoopState field of this name); read through
    attrgetter, without a Python frame (Core's code and the Stepper read the counts at every step)."""
    return property(attrgetter(f"loop.{name}"), lambda self, value: setattr(self.loop, name, value))


class NativeCore(Core):
    """A Core whose loop runs in the engine (see the module docstring); its kernel is a NativeKernel.

    The core's counts (steps, rejected, evaluations, recorded) live in the LoopState the engine advances in place:
    a Ctrl-C, whose handler runs as soon as the engine returns, finds them consistent with the samples. The store's
    count, the sampler's next output and the controller's state are copied from it when the engine returns (in a
    `finally`, so a Ctrl-C raised on the return itself still finds them copied). The rows the engine stopped are
    appended to `_pending` (StopEvent) and taken into account whenever the driver next looks (take_stops()).
    """

    kernel: NativeKernel  # type: ignore[assignment]

    def __init__(self, **kwargs: Any):
        self.loop = native.module.LoopState(  # type: ignore[union-attr]
            steps=0, rejected=0, evaluations=0, recorded=-math.inf, count=0, full=False, soft_capacity=0.0,
            next_output=1, step_t0=0.0, step_k=0, step_time=0.0, step_h=0.0, previous_error=1.0,
            rejected_last=False,
        )  # fmt: skip
        super().__init__(**kwargs)
        self.kernel.bind(self.control)
        sampler = self.sampler
        self._sampler = None if sampler is None else native.module.Sampler(**sampler.native_data())  # type: ignore[union-attr]
        self._budget = 64  # steps per engine call, adapted to take about BUDGET_SECONDS
        self._pending: list[Any] = []  # rows the engine stopped (StopEvent), not yet recorded as RowStops
        self._io: tuple[Any, Any, Any, Any] | None = None  # the AdvanceIO and the objects it holds (_advance_io())

    # The core's counts, in the engine's loop state (Core's code reads and writes them as attributes).
    steps = _in_loop("steps")
    rejected = _in_loop("rejected")
    evaluations = _in_loop("evaluations")
    recorded = _in_loop("recorded")

    def advance(self, t_stop: float, *, max_steps: int | None = None) -> str:
        """Core.advance, in the engine: the same statuses, samples, counts and stops."""
        kernel, control, store, loop = self.kernel, self.control, self.store, self.loop
        tolerance = LANDING_FRACTION * control.scale(t_stop) if control.adaptive else 0.0
        taken = 0
        while True:
            limit = self._budget if max_steps is None else min(self._budget, max_steps - taken)
            self._load()
            start = time.perf_counter()
            try:
                arrays, io = kernel.store_arrays(store), self._advance_io()
                result = kernel.engine.advance(t_stop, limit, tolerance, state=loop, store=arrays, io=io)
            finally:
                self._unload()
            elapsed = time.perf_counter() - start
            self._take_pending()
            taken += result.taken
            if result.taken:
                self._budget = next_budget(self._budget, result.taken, elapsed)
            status = result.status
            if status == _NEED_ROOM:
                store.room(result.need)
                continue
            if status == STEPPED and (max_steps is None or taken < max_steps):
                continue  # the budget, not the caller's limit: Python runs here (signals), then the engine again
            return str(status)

    def _advance_io(self) -> Any:
        """What the engine reads and reports beside the loop state, as _native.AdvanceIO: made again only when the
        store's contacts dict, the rows or their evaluations are new objects (it holds them: Stepper.step calls the
        engine once per step)."""
        held = self._io
        contacts, rows, extra = self.store.contacts, self.rows, self.extra_evaluations
        if held is None or held[0] is not contacts or held[1] is not rows or held[2] is not extra:
            io = native.module.AdvanceIO(  # type: ignore[union-attr]
                sampler=self._sampler, stops=self._pending, contacts=contacts, rows=rows, extra_evaluations=extra
            )
            held = self._io = (contacts, rows, extra, io)
        return held[3]

    def _load(self) -> None:
        """The loop state from the store, the sampler and the controller (the core's counts live there already)."""
        loop, store, sampler = self.loop, self.store, self.sampler
        loop.count, loop.full, loop.soft_capacity = store.count, store.full, store.soft_capacity
        if sampler is not None:
            loop.next_output = sampler.next_output
        self.control.write_native_state(loop)

    def _unload(self) -> None:
        """... and back, once the engine returned."""
        loop, store, sampler = self.loop, self.store, self.sampler
        store.count, store.full = loop.count, loop.full
        if sampler is not None:
            sampler.next_output = loop.next_output
        self.control.read_native_state(loop)

    def _control_failure(self, row: int, t: float) -> InvalidArgumentError:
        """Why row `row`'s native controller output at t was refused: its Python controller's output at the row's
        state, checked as the driver checks it (torques.check_torque)."""
        from ..torques import check_torque

        q, v = self.kernel.engine.row_state(row)
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
            event = self._pending[0]
            row = int(event.row)
            cause: BaseException | None = None
            failed_step: int | None = int(event.step)
            if event.kind == "diverged":
                status, detail = "diverged", diverged_detail(self.system, event.dof, self.dt_hint)
            elif event.kind == "failed":  # a library's exception inside the step (Core._fail_rows's wording)
                status, detail = "failed", f"{event.message}; try a smaller dt (now {self.dt_hint:g} s)"
            elif event.kind == "control":  # at a control instant, not in a step
                status, cause = "failed", self._control_failure(row, event.time)
                detail, failed_step = str(cause), None
            else:
                status = "step_collapsed"
                error = None if math.isnan(event.error) else event.error
                detail = collapsed_detail(self.system, event.h, event.minimum, error)
            if row in self.rows:
                stats = self.kernel.row_solver_stats(row)
                if stats:
                    self.solver_stats[row] = stats
                sample = event.count + event.added - 1
                self.stops.append(
                    RowStop(row, status, event.time, failed_step, detail, sample, event.added, cause, cause is not None)
                )
                self.stopped_counts[row] = (event.steps, event.rejected, event.evaluations)
                self.store.stop(np.array([row]), event.added, count=event.count)
                keep = self.rows != row
                n = int(keep.sum())
                self.extra_evaluations[:n] = self.extra_evaluations[: len(keep)][keep]
                self._set_rows(self.rows[keep])
            self._pending.pop(0)
