"""The integrator chooser of `run --tolerance`: a pilot work-precision study over the run's first second, cached,
and the cheapest integrator and step it measured within the tolerance."""

from __future__ import annotations

import hashlib
import json
import math
import os
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..exceptions import InvalidArgumentError
from ..integrators import INTEGRATORS, Integrator, get_integrator
from ..kernels.native import why_not_native
from ..metadata import versions
from ..robot import Robot, check_system
from ..simulation import Controller
from ..text import safe_name
from ..validation import check_callable, check_flag, check_path, positive_number
from .results import FORMAT, FORMAT_VERSION, STATUS_REFUSED, Measurement, WorkPrecision, recommend
from .study import (
    CONTACT_REFERENCE_DT,
    CONTROL_DT,
    OUTPUT_DT,
    REFERENCE_INTEGRATOR,
    REFERENCE_TOLERANCE,
    REFINEMENT,
    STEP_LADDER,
    TOLERANCE_LADDER,
    work_precision,
)

PILOT_HORIZON = 1.0  # [s] `run --tolerance` studies min(duration, this)
PILOT_MIN_ERROR = 1e-8  # the pilot's ladders go down to min(tolerance, this), so one study serves many tolerances
PILOT_MAX_RUN_TIME = 0.5  # [s] the pilot stops a ladder after a run this long
# The pilot measures the error on the 20 ms grid; the run's own samples (every step) fall between, where the
# error can peak a little higher (~1 % for motions of a few rad/s): the choice keeps 10 % in hand.
PILOT_SAFETY = 0.9


@dataclass
class Choice:
    """What `run --tolerance` chose, and from which study.

    Attributes:
        tolerance: the accuracy asked for.
        horizon: the pilot study's duration, min(duration, PILOT_HORIZON) [s].
        measurement: the chosen configuration with its measured error and cost.
        study: the pilot study.
        cached: whether the study came from the cache.
        cache_path: the cache file (None when caching was off).
        note: what happened to the cache, if anything worth saying (an unreadable entry rebuilt, ...).
    """

    tolerance: float
    horizon: float
    measurement: Measurement
    study: WorkPrecision
    cached: bool
    cache_path: Path | None
    note: str = ""

    def describe(self) -> str:
        """One line: what was chosen and why (the pilot's measured error and cost)."""
        m = self.measurement
        source = "cached pilot study" if self.cached else "pilot study"
        ran = [r for r in self.study.measurements if r.status != STATUS_REFUSED]
        controller = self.study.settings.get("controller")
        return (
            f"tolerance {self.tolerance:g} over the first {self.horizon:g} s: chose {m.integrator}, {m.settings()} "
            f"({source}: error {m.error:.2e} + reference {self.study.reference_error:.0e}, "
            f"max |energy_error| {m.energy_error:.2e} J, {m.evaluations} dynamics evaluations, "
            f"{m.cpu_time:.3g} s CPU on the {m.kernel or 'unrecorded'} kernel; cheapest of {len(ran)} runs of "
            f"{len({r.integrator for r in ran})} integrators)"
            + self._reference_note()
            + (f"; measured under the controller ({safe_name(str(controller))})" if controller else "")
        )

    def _reference_note(self) -> str:
        """For a contact scene: what the reference was (the same integrator, at a much smaller step)."""
        r = self.study.reference
        if r is None or math.isnan(r.dt):
            return ""
        return (
            f"; reference: {r.integrator} at dt {r.dt:g} s (a contact scene is not smooth: no higher-order reference, "
            "the same integrator at a much smaller step)"
        )


def default_cache_dir() -> Path:
    """$XDG_CACHE_HOME/multibody-sim, else ~/.cache/multibody-sim."""
    root = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(root) / "multibody-sim"


def choose_integrator(
    system: Robot,
    q0: Any,
    v0: Any,
    *,
    tolerance: float,
    duration: float,
    integrators: Iterable[str | Integrator] | None = None,
    cache: bool = True,
    cache_dir: str | os.PathLike[str] | None = None,
    progress: Callable[[str], None] | None = None,
    controller: Controller | None = None,
    control_dt: float | None = None,
) -> Choice:
    """The cheapest integrator and step meeting `tolerance`, from a pilot study over min(duration, 1 s).

    "Meeting" is recommend()'s criterion at PILOT_SAFETY × tolerance: the pilot sees the error on its 20 ms grid,
    and the run's samples fall between.

    The pilot is a pruned work_precision study whose ladders stop at min(tolerance, PILOT_MIN_ERROR). It is
    cached in `cache_dir` (default default_cache_dir()/pilot) under a key made of how the system was loaded
    (load_robot arguments and the URDF's SHA-256), the initial state, the horizon, the integrator set and the
    kernel each integrator runs on (native or Python: the costs differ, so does the choice); an entry is reused
    when its ladders went down to the tolerance asked for, and an unreadable entry is rebuilt.

    With a `controller`, held for `control_dt` (default CONTROL_DT; the run must use the same period, which
    ``study.settings["control_dt"]`` gives), the pilot runs under it: the choice is for the motion the controlled
    run makes. A built-in controller (make_controller, a scene's [controller]) is keyed in the cache by
    its name and parameters; any other callable has no such description, so its pilot is not cached.

    Raises:
        InvalidArgumentError: a bad argument, or no measured configuration meets the tolerance (the message
            gives the most accurate one measured).
        BenchInterrupted: Ctrl-C during the pilot.
    """
    check_system(system)
    check_flag(cache, "cache")
    if cache_dir is not None:
        check_path(cache_dir, "cache_dir", "a folder")
    tolerance = positive_number(tolerance, "tolerance", None)
    q0 = system.check_q(q0, "q0")
    v0 = system.check_v(v0, "v0")
    horizon = min(positive_number(duration, "duration"), PILOT_HORIZON)
    names = None if integrators is None else [get_integrator(i).name for i in integrators]
    min_error = min(tolerance, PILOT_MIN_ERROR)
    check_callable(controller, "controller", "controller(t, q, v) -> tau")
    if controller is None:
        control_dt = None
    elif control_dt is None:
        control_dt = CONTROL_DT
    else:
        control_dt = positive_number(control_dt, "control_dt")
    recipe = None if controller is None else getattr(controller, "recipe", None)
    key = _cache_key(system, q0, v0, horizon, names, recipe, control_dt)
    path = None
    note = ""
    study = None
    if cache and controller is not None and recipe is None:
        cache = False
        note = "the pilot study is not cached: a controller of your own has no description to key the cache on"
    if cache:
        path = Path(cache_dir) if cache_dir is not None else default_cache_dir() / "pilot"
        path = path / f"{key[:40]}.json"
        study, note = _read_cache(path, key, min_error)
    cached = study is not None
    if study is None:
        study = work_precision(
            system,
            q0,
            v0,
            duration=horizon,
            integrators=names,
            min_error=min_error,
            max_run_time=PILOT_MAX_RUN_TIME,
            prune=True,
            progress=progress,
            controller=controller,
            control_dt=control_dt,
        )
        study.settings["cache_key"] = key
        if path is not None:
            try:
                study.to_json(path)
            except OSError as exc:
                note = "; ".join(filter(None, [note, f"could not write the cache {path} ({exc.strerror or exc})"]))
    chosen = recommend(study, PILOT_SAFETY * tolerance)
    if chosen is None:
        done = [m for m in study.measurements if m.completed]
        best = min(done, key=lambda m: m.error) if done else None
        best_text = f"the most accurate was {best.integrator}, {best.settings()}: {best.error:.1e}" if best else ""
        raise InvalidArgumentError(
            f"no integrator met tolerance {tolerance:g} over the first {horizon:g} s in the pilot study ("
            + "; ".join(filter(None, [best_text, f"the reference is accurate to ~{study.reference_error:.0e}"]))
            + "): ask for a looser tolerance"
        )
    return Choice(tolerance, horizon, chosen, study, cached, path, note)


def _cache_key(
    system: Robot,
    q0: np.ndarray,
    v0: np.ndarray,
    horizon: float,
    names: list[str] | None,
    recipe: Any = None,
    control_dt: float | None = None,
) -> str:
    """SHA-256 of everything a pilot study depends on (floats by repr, which round-trips exactly), the kernel each
    integrator runs on included: costs measured on the Python kernel must not choose for a native run, nor the
    reverse. `recipe` is a built-in controller's (name, parameters), `control_dt` its period."""
    source = dict(getattr(system, "source", {}))
    methods = INTEGRATORS.values() if names is None else [get_integrator(n) for n in names]
    content = {
        "format": FORMAT,
        "format_version": FORMAT_VERSION,
        "source": source,
        "q0": [repr(float(x)) for x in q0],
        "v0": [repr(float(x)) for x in v0],
        "horizon": repr(horizon),
        "controller": recipe,
        "control_dt": None if control_dt is None else repr(float(control_dt)),
        "integrators": "all" if names is None else sorted(names),
        "kernels": {m.name: "python" if why_not_native(system, m) else "native" for m in methods},
        "versions": dict(versions()),
        "study": [
            OUTPUT_DT,
            STEP_LADDER,
            TOLERANCE_LADDER,
            REFERENCE_INTEGRATOR,
            REFERENCE_TOLERANCE,
            CONTACT_REFERENCE_DT,
            REFINEMENT,
            PILOT_MAX_RUN_TIME,
        ],
    }
    return hashlib.sha256(json.dumps(content, sort_keys=True, default=str).encode()).hexdigest()


def _read_cache(path: Path, key: str, min_error: float) -> tuple[WorkPrecision | None, str]:
    """(the cached study if usable, a note on why it was not when it existed)."""
    if not path.exists():
        return None, ""
    try:
        study = WorkPrecision.from_json(path)
    except InvalidArgumentError as exc:
        return None, f"ignored an unreadable pilot cache entry ({exc}); rebuilt it"
    if study.settings.get("cache_key") != key or not study.complete or study.reference is None:
        return None, "ignored a pilot cache entry that does not match this run; rebuilt it"
    if float(study.settings.get("min_error", math.inf)) > min_error:
        return None, ""  # it was made for a looser tolerance: a finer study replaces it
    return study, ""
