"""Work-precision studies: the error every integrator reaches at each cost on one system, and the cheapest choice.

A study runs each integrator over a ladder of steps (fixed-step methods) or tolerances (adaptive ones) from one
initial state, and measures

- the error: max over a common sample grid of ‖(q ⊖ q_ref, v − v_ref)‖∞ (Pinocchio's difference in the tangent
  space, CONTRACTS.md's `--tolerance`), against a reference computed by DOP853 at a tight tolerance; the reference
  is checked by refining it once more (a tolerance `refinement` times tighter), and the largest difference
  between the two is its estimated error;
- the energy error max |H − H(0) − work + dissipated| from the ledger, shown beside the error and never used as
  it (the ledger does not see phase error);
- the cost: the CPU time of the run (median over repeats), the stepping loop's wall time (median) and the dynamics
  evaluations. CPU time is what "cheapest" means by default: it is what the run costs on an idle machine, while
  wall time on a shared machine also counts the turns other processes take (the wall time is kept beside it).

From the measurements it fits each integrator's observed order and recommends, for a requested accuracy, the
cheapest measured configuration whose error, plus the reference's own estimated error, stays within it.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import os
import time
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .driver import controller_name
from .exceptions import InvalidArgumentError, SimulationError, SimulationInterrupted
from .files import write_atomically
from .integrators import INTEGRATORS, Integrator, get_integrator
from .kernels.native import why_not_native
from .metadata import versions
from .robot import Robot
from .safety import MAX_JSON_DEPTH, json_depth, safe_name
from .simulation import Controller, simulate
from .trajectory import Trajectory
from .validation import (
    MAX_STEPS,
    check_callable,
    check_flag,
    check_path,
    check_system,
    check_text,
    check_trajectory,
    positive_number,
)

FORMAT = "multibody-sim work-precision"
FORMAT_VERSION = 1
# The common sample grid [s]: 20 ms resolves the motions of robots (periods of a second or more) to ~0.1 % of
# the error's peaks, and every step of the 1-2-5 ladder below divides it.
OUTPUT_DT = 0.02
# Fixed steps [s]: a 1-2-5 series (values users recognise), 20 ms down to 1 µs; a study stops each ladder early.
STEP_LADDER = tuple(m * 10.0**e for e in range(-2, -7, -1) for m in (2, 1, 0.5)) + (1e-6,)
# Tolerances of adaptive methods (rtol = atol): half decades from 1e-2 to 1e-11.
TOLERANCE_LADDER = tuple(10.0 ** (-k / 2) for k in range(4, 23))
ADAPTIVE_FIRST_STEP = 1e-3  # [s] an adaptive run's first trial step (what `run` uses too)
# The reference: DOP853 at rtol = atol = 1e-14, checked against 1e-15. dp54 at 1e-12 (the former reference) was
# only ~1e-11 accurate on the double pendulum: RK4's 1 ms run fell within 10x of it, was left out of the fit, and
# the fit on coarser, pre-asymptotic steps read 4.60 (MISMATCH). DOP853 at 1e-14 is within 3e-13 of its 1e-15
# check there, at about the cost of dp54 at 1e-12 (800 against 860 evaluations over 1 s).
REFERENCE_INTEGRATOR = "dop853"
REFERENCE_TOLERANCE = 1e-14  # rtol = atol of the reference; the check runs `refinement` times tighter
# A contact scene is not smooth: no higher-order method converges faster on it, and only timestepping steps it.
# Its reference is the same integrator at a much smaller step, checked at half that step.
CONTACT_REFERENCE_DT = 2e-5
REFINEMENT = 10.0
# Errors within this factor of the reference's estimated error may be the reference's: flagged, not fitted.
REFERENCE_MARGIN = 10.0
MIN_ERROR = 1e-10  # a ladder stops once its error is below this: nothing finer is asked of a robot simulator
FIT_POINTS = 3  # fixed steps: the order is the slope over the finest usable rungs (coarse ones are pre-asymptotic)
ADAPTIVE_FIT_POINTS = 9  # 4 decades of tolerance: its rungs are close in evaluations and noisy one by one
# A fit over 3 rungs a factor 2-2.5 apart moves by ~0.1-0.3 with the error's curvature: beyond these it is off.
ORDER_MISMATCH = 0.4
# Adaptive methods are fitted against evaluations: an effective order, which comes out steeper than the classical
# order, the more so the higher it is (measured 2.6-3.1 for bs32, 5.4-6.8 for dp54 and 9-11.4 for dop853 on the
# double pendulum, ur5, solo12 and talos, as the controller's start-up and landing steps weigh more at loose
# tolerances). It is reported as what it is, never judged against the classical order.
REPEAT_BELOW = 0.2  # [s] runs shorter than this are timed `repeats` times (median); longer ones once
# A reference whose check differs from it by more than this [rad, m, rad/s, m/s] has not converged: the loosest
# accuracy the study recommends for is 1e-2.
UNCONVERGED_REFERENCE = 1e-2
# [s] the period at which a study holds its controller when none is given (1 kHz, a common control rate)
CONTROL_DT = 1e-3
PILOT_HORIZON = 1.0  # [s] `run --tolerance` studies min(duration, this)
PILOT_MIN_ERROR = 1e-8  # the pilot's ladders go down to min(tolerance, this), so one study serves many tolerances
PILOT_MAX_RUN_TIME = 0.5  # [s] the pilot stops a ladder after a run this long
# The pilot measures the error on the 20 ms grid; the run's own samples (every step) fall between, where the
# error can peak a little higher (~1 % for motions of a few rad/s): the choice keeps 10 % in hand.
PILOT_SAFETY = 0.9
CSV_COLUMNS = (
    "integrator",
    "order",
    "adaptive",
    "dt",
    "rtol",
    "atol",
    "status",
    "error",
    "reference_error",
    "below_reference",
    "energy_error",
    "evaluations",
    "steps",
    "rejected_steps",
    "cpu_time",
    "wall_time",
    "kernel",
    "message",
)
STATUS_COMPLETED = "completed"
STATUS_REFUSED = "refused"  # the integrator's check_system refused the system (e.g. variational, floating base)


class BenchInterrupted(SimulationInterrupted):
    """Ctrl-C (or SIGTERM in the CLI) stopped a study; `.result` holds what was measured so far.

    Attributes:
        result: the partial WorkPrecision (``complete`` is False).
    """

    def __init__(self, message: str, *, result: WorkPrecision, signal_name: str = "SIGINT"):
        super().__init__(message, signal_name=signal_name)
        self.result = result


@dataclass
class Measurement:
    """One run of one integrator at one step (or tolerance).

    Attributes:
        integrator: registry name.
        dt: the step [s] (fixed-step methods) or the first trial step (adaptive ones).
        rtol, atol: the tolerances of adaptive methods (None for fixed-step ones).
        status: "completed", or why the run stopped ("diverged", "newton_failed", "step_collapsed", ...).
        error: max over the sample grid of ‖(q ⊖ q_ref, v − v_ref)‖∞ [rad, m, rad/s, m/s]; nan unless completed.
        energy_error: max |energy_error| over the samples [J] (a consistency check, not the error).
        evaluations: forward-dynamics evaluations (rejected steps and Newton iterations included).
        steps: accepted steps.
        rejected_steps: rejected steps (adaptive methods).
        cpu_time: the process CPU time of the whole simulate() call [s], median over `cpu_times`.
        cpu_times: every CPU timing of this run [s].
        wall_time: the stepping loop's wall time (stats["wall_time"]) [s], median over `wall_times`.
        wall_times: every wall timing of this run [s].
        below_reference: the error is within REFERENCE_MARGIN times the reference's estimated error, so it may
            be the reference's: left out of order fits.
        kernel: the stepping kernel that ran it (the run's metadata["kernel"]: "native", "python (row)", ...), the
            one `simulate` takes for this system and integrator; "" when unknown (a refused integrator).
        message: why the run stopped early, if it did.
    """

    integrator: str
    dt: float
    rtol: float | None
    atol: float | None
    status: str
    error: float = math.nan
    energy_error: float = math.nan
    evaluations: int = 0
    steps: int = 0
    rejected_steps: int = 0
    cpu_time: float = math.nan
    cpu_times: list[float] = field(default_factory=list)
    wall_time: float = math.nan
    wall_times: list[float] = field(default_factory=list)
    below_reference: bool = False
    kernel: str = ""
    message: str = ""

    @property
    def adaptive(self) -> bool:
        """Whether this is an adaptive run (it has tolerances)."""
        return self.rtol is not None

    @property
    def completed(self) -> bool:
        """Whether the run reached the end of the study (it has an error)."""
        return self.status == STATUS_COMPLETED

    def settings(self) -> str:
        """The configuration in words: "dt 0.002 s" or "rtol 1e-06, atol 1e-06"."""
        if self.adaptive:
            return f"rtol {self.rtol:.3g}, atol {self.atol:.3g}"
        return f"dt {self.dt:g} s"

    def simulate_options(self) -> dict[str, Any]:
        """Keyword arguments that make `simulate` repeat this configuration: integrator, dt (and rtol, atol)."""
        options: dict[str, Any] = {"integrator": self.integrator, "dt": self.dt}
        if self.adaptive:
            options.update(rtol=self.rtol, atol=self.atol)
        return options


@dataclass
class Reference:
    """The reference solution and its check.

    Attributes:
        integrator: the reference's integrator (dop853; timestepping for a contact scene).
        rtol, atol: its tolerances (nan for a fixed-step reference).
        check_rtol, check_atol: the refined check's tolerances.
        dt, check_dt: a fixed-step reference's step and its check's (nan for dop853).
        error: its estimated error: max over the grid of the state difference to the refined check.
        evaluations, wall_time: the reference run's cost.
        t, q, v: its samples on the grid (not stored in JSON files).
    """

    integrator: str
    rtol: float
    atol: float
    check_rtol: float
    check_atol: float
    error: float
    evaluations: int
    wall_time: float
    dt: float = math.nan
    check_dt: float = math.nan
    t: np.ndarray | None = None
    q: np.ndarray | None = None
    v: np.ndarray | None = None


@dataclass
class OrderFit:
    """An integrator's observed order of convergence beside its theoretical one.

    Attributes:
        integrator: registry name.
        theoretical: the integrator's classical order.
        observed: the fitted order (nan when fewer than 2 usable points).
        against: "dt" (fixed-step: the slope of log error against log dt) or "evaluations" (adaptive: minus the
            slope of log error against log evaluations, an effective order: an order-p method with N evaluations
            reaches error ∝ N^-p).
        points: how many measurements the fit used.
        mismatch: fixed-step only: observed and theoretical differ by more than ORDER_MISMATCH, judged on 3
            points or more (an adaptive method's effective order is no classical order: never flagged).
        note: why there is no fit, or what to look at.
    """

    integrator: str
    theoretical: int
    observed: float
    against: str
    points: int
    mismatch: bool
    note: str = ""


@dataclass
class WorkPrecision:
    """A work-precision study of one system from one initial state.

    Attributes:
        system: the system's name.
        duration: the simulated time of every run [s].
        output_dt: the common sample grid's period [s].
        q0, v0: the initial state.
        reference: the reference and its estimated error (None if interrupted before it was computed).
        measurements: every run, in the order they were made.
        orders: observed orders, per integrator (registry order).
        settings: the study's parameters (ladders, budgets, repeats).
        metadata: package versions and how the system was loaded (the load_robot arguments, URDF SHA-256).
        complete: False when the study was interrupted.
    """

    system: str
    duration: float
    output_dt: float
    q0: list[float]
    v0: list[float]
    reference: Reference | None
    measurements: list[Measurement]
    orders: dict[str, OrderFit]
    settings: dict[str, Any]
    metadata: dict[str, Any]
    complete: bool = True

    @property
    def reference_error(self) -> float:
        """The reference's estimated error (inf when there is no reference)."""
        return self.reference.error if self.reference is not None else math.inf

    def integrators(self) -> list[str]:
        """The integrators measured, in registry order."""
        names = {m.integrator for m in self.measurements}
        return [n for n in INTEGRATORS if n in names] + sorted(names - set(INTEGRATORS))

    def for_integrator(self, name: str) -> list[Measurement]:
        """The measurements of one integrator, coarsest first."""
        rows = [m for m in self.measurements if m.integrator == name]
        return sorted(rows, key=lambda m: -(m.rtol if m.adaptive else m.dt))  # type: ignore[operator]

    # ---- tables ----------------------------------------------------------------------------------------
    def rows(self) -> list[dict[str, Any]]:
        """One dict per measurement (the CSV's rows), grouped by integrator, coarsest first."""
        rows = []
        for name in self.integrators():
            method = INTEGRATORS.get(name)
            for m in self.for_integrator(name):
                rows.append(
                    {
                        "integrator": m.integrator,
                        "order": method.order if method else "",
                        "adaptive": m.adaptive,
                        "dt": m.dt,
                        "rtol": m.rtol,
                        "atol": m.atol,
                        "status": m.status,
                        "error": m.error,
                        "reference_error": self.reference_error,
                        "below_reference": m.below_reference,
                        "energy_error": m.energy_error,
                        "evaluations": m.evaluations,
                        "steps": m.steps,
                        "rejected_steps": m.rejected_steps,
                        "cpu_time": m.cpu_time,
                        "wall_time": m.wall_time,
                        "kernel": m.kernel,
                        "message": m.message,
                    }
                )
        return rows

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON-ready data (no arrays; nan becomes None)."""
        reference = None
        if self.reference is not None:
            reference = {k: v for k, v in dataclasses.asdict(self.reference).items() if k not in ("t", "q", "v")}
        return _json_ready(
            {
                "format": FORMAT,
                "format_version": FORMAT_VERSION,
                "system": self.system,
                "duration": self.duration,
                "output_dt": self.output_dt,
                "q0": self.q0,
                "v0": self.v0,
                "complete": self.complete,
                "reference": reference,
                "measurements": [dataclasses.asdict(m) for m in self.measurements],
                "orders": [dataclasses.asdict(o) for o in self.orders.values()],
                "settings": self.settings,
                "metadata": self.metadata,
            }
        )

    @classmethod
    def from_dict(cls, data: dict[str, Any]) -> WorkPrecision:
        """The study that to_dict() wrote.

        Raises:
            InvalidArgumentError: not a work-precision table of this format version.
        """
        try:
            if data.get("format") != FORMAT or data.get("format_version") != FORMAT_VERSION:
                raise InvalidArgumentError("not a multibody-sim work-precision table (format or version differs)")
            reference = None if data["reference"] is None else Reference(**_nan_back(data["reference"]))
            return cls(
                system=str(data["system"]),
                duration=float(data["duration"]),
                output_dt=float(data["output_dt"]),
                q0=[float(x) for x in data["q0"]],
                v0=[float(x) for x in data["v0"]],
                reference=reference,
                measurements=[Measurement(**_nan_back(m)) for m in data["measurements"]],
                orders={o["integrator"]: OrderFit(**_nan_back(o)) for o in data["orders"]},
                settings=dict(data["settings"]),
                metadata=dict(data["metadata"]),
                complete=bool(data["complete"]),
            )
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            if isinstance(exc, InvalidArgumentError):
                raise
            raise InvalidArgumentError(f"malformed work-precision table: {exc!r}") from None

    def to_json(self, path: str | os.PathLike[str]) -> Path:
        """Write the study as JSON, atomically."""
        text = json.dumps(self.to_dict(), indent=1, allow_nan=False)
        return _write_text_atomically(Path(path), text)

    @classmethod
    def from_json(cls, path: str | os.PathLike[str]) -> WorkPrecision:
        """Read a study written by to_json().

        Raises:
            InvalidArgumentError: the file is unreadable or not a work-precision table.
        """
        try:
            text = Path(path).read_text(encoding="utf-8")
            depth = json_depth(text)  # json.loads recurses per level: refuse deep nesting unparsed
            if depth > MAX_JSON_DEPTH:
                raise ValueError(f"it nests {depth} levels deep, more than the {MAX_JSON_DEPTH} a table may")
            data = json.loads(text)
        except (OSError, UnicodeDecodeError, ValueError) as exc:  # json.JSONDecodeError is a ValueError
            raise InvalidArgumentError(f"cannot read work-precision table {path}: {exc}") from None
        if not isinstance(data, dict):
            raise InvalidArgumentError(f"cannot read work-precision table {path}: not a JSON object")
        return cls.from_dict(data)

    def to_csv(self, path: str | os.PathLike[str]) -> Path:
        """Write one row per measurement as CSV, atomically (empty cells for missing values)."""
        import csv  # here: `import multibody_sim` need not pay for what a study's files need

        rows = self.rows()
        buffer = _StringBuffer()
        writer = csv.DictWriter(buffer, fieldnames=CSV_COLUMNS, lineterminator="\n")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: _csv_cell(v) for k, v in row.items()})
        return _write_text_atomically(Path(path), buffer.text)

    def orders_table(self) -> str:
        """Observed against theoretical order per integrator, as aligned text (mismatches flagged)."""
        rows = []
        for name in self.integrators():
            fit = self.orders.get(name)
            points = self.for_integrator(name)
            done = [m for m in points if m.completed]
            best = min((m.error for m in done), default=math.nan)
            statuses = sorted({m.status for m in points if not m.completed})
            if fit is None:
                rows.append([name, "", "", "", "", "", ", ".join(statuses)])
                continue
            value = "—" if math.isnan(fit.observed) else f"{fit.observed:.2f}"
            observed, effective = ("", value) if fit.against == "evaluations" else (value, "")
            flag = "MISMATCH" if fit.mismatch else ""
            notes = "; ".join(filter(None, [fit.note, _stopped_note(points)]))
            rows.append([name, str(fit.theoretical), observed, effective, flag, _fmt(best, ".1e"), notes])
        headers = ["integrator", "order", "observed (vs dt)", "effective (vs evaluations)", "flag", "best error"]
        return _text_table([*headers, "notes"], rows)

    def kernels_line(self) -> str:
        """Which stepping kernel measured which integrators, in one line ("" when no run says)."""
        reasons = self.metadata.get("why_not_native", {})
        groups: dict[tuple[str, str], list[str]] = {}
        for name in self.integrators():
            ran = {m.kernel for m in self.measurements if m.integrator == name and m.kernel}
            why = str(reasons.get(name, "")).replace(f"integrator '{name}'", "the integrator")
            for kernel in sorted(ran):
                groups.setdefault((kernel, "" if kernel == "native" else why), []).append(name)
        if not groups:
            return ""
        parts = [
            f"{kernel} for {', '.join(names)}" + (f" (not native: {why})" if why else "")
            for (kernel, why), names in groups.items()
        ]
        return "kernel measured (the one each run takes): " + "; ".join(parts)

    def summary(self, tolerances: Sequence[float] = (1e-2, 1e-4, 1e-6, 1e-8)) -> str:
        """What the `bench` command prints: the reference, the orders and the recommendations."""
        controller = self.settings.get("controller")
        lines = [
            f"work-precision study of {safe_name(self.system)}: {self.duration:g} s"
            + (f" under its controller ({safe_name(str(controller))})" if controller else ", no applied torque")
            + f", error = max over samples every {self.output_dt:g} s of |(q ⊖ q_ref, v − v_ref)|∞"
            + ("" if self.complete else " (INTERRUPTED: partial results)")
        ]
        if self.reference is not None:
            r = self.reference
            if math.isnan(r.dt):
                lines.append(
                    f"reference: {r.integrator} rtol {r.rtol:.0e}, atol {r.atol:.0e}; checked against rtol "
                    f"{r.check_rtol:.0e}: estimated error {r.error:.1e}"
                )
            else:
                lines.append(
                    f"reference: {r.integrator} at dt {r.dt:g} s, checked against dt {r.check_dt:g} s: estimated "
                    f"error {r.error:.1e} (a contact scene is not smooth: it has no higher-order reference, so the "
                    "reference is the same integrator at a much smaller step)"
                )
        kernels = self.kernels_line()
        if kernels:
            lines.append(kernels)
        lines += ["", self.orders_table(), ""]
        done = [m for m in self.measurements if m.completed]
        if self.reference is not None and self.reference.error > UNCONVERGED_REFERENCE:
            lines += [
                f"note: the reference did not converge (two runs of it, one at half the step or a tenth of the "
                f"tolerance, differ by {self.reference.error:.1e}): this motion is too sensitive to the step to "
                "measure an error (e.g. a robot collapsing onto the ground with nothing holding it, whose impacts "
                "come at other instants at every step); measure the motion the scene makes with its controller, a "
                "shorter duration or another initial state",
                "",
            ]
        elif done and all(m.below_reference for m in done):
            lines += [
                "note: every run is as accurate as the reference: this motion is too simple to tell integrators "
                "apart (e.g. a floating robot in free fall with no joint motion); pass another initial state",
                "",
            ]
        rows = []
        for tol in tolerances:
            rec = recommend(self, tol)
            if rec is None:
                rows.append([f"{tol:.0e}", "none measured meets it", "", "", "", ""])
            else:
                rows.append(
                    [
                        f"{tol:.0e}",
                        rec.integrator,
                        rec.settings(),
                        f"{rec.error:.1e}",
                        f"{rec.cpu_time:.3g}",
                        str(rec.evaluations),
                    ]
                )
        lines.append(
            "recommended (least CPU time among the runs whose error + the reference's is within the accuracy):"
        )
        lines.append(_text_table(["accuracy", "integrator", "settings", "error", "CPU [s]", "evaluations"], rows, 2))
        return "\n".join(lines)

    def write(self, out_dir: str | os.PathLike[str], stem: str = "work_precision") -> dict[str, Path | str]:
        """Write OUT_DIR/STEM.csv, .json and .png.

        Returns:
            {"csv": path, "json": path, "png": path or the reason it was not drawn (matplotlib missing)}.
        """
        folder = Path(out_dir)
        folder.mkdir(parents=True, exist_ok=True)
        written: dict[str, Path | str] = {
            "csv": self.to_csv(folder / f"{stem}.csv"),
            "json": self.to_json(folder / f"{stem}.json"),
        }
        try:
            written["png"] = plot_work_precision(self, folder / f"{stem}.png")
        except ModuleNotFoundError as exc:
            written["png"] = str(exc)
        return written


# ---- the study -------------------------------------------------------------------------------------------
def work_precision(
    system: Robot,
    q0: Any,
    v0: Any,
    *,
    duration: float,
    integrators: Iterable[str | Integrator] | None = None,
    steps: Sequence[float] | None = None,
    tolerances: Sequence[float] | None = None,
    output_dt: float | None = None,
    reference_tolerance: float = REFERENCE_TOLERANCE,
    refinement: float = REFINEMENT,
    min_error: float = MIN_ERROR,
    max_steps: int = 2**17,
    max_run_time: float = 1.0,
    repeats: int = 3,
    prune: bool = False,
    progress: Callable[[str], None] | None = None,
    controller: Controller | None = None,
    control_dt: float | None = None,
) -> WorkPrecision:
    """Measure error against cost for each integrator over a ladder of steps or tolerances.

    Each fixed-step integrator runs at the steps of `steps` (default STEP_LADDER) from the coarsest down, each
    adaptive one at the tolerances of `tolerances` (default TOLERANCE_LADDER, rtol = atol) from the loosest
    down; a ladder stops once its error is below max(min_error, REFERENCE_MARGIN × the reference's error),
    before a fixed-step run predicted (from the previous run's time per step) to take longer than
    `max_run_time` or to take more than `max_steps` steps, after an adaptive run longer than `max_run_time`, and (with
    `prune`) after two consecutive runs that another integrator beat on both error and CPU time. Runs that
    diverge or fail are recorded with their status, not raised.

    Args:
        system: the robot (or scene).
        q0: initial configuration, shape (nq,).
        v0: initial velocity, shape (nv,).
        duration: simulated time of every run [s].
        integrators: names (or Integrator objects) to measure; None measures every registered integrator and
            records those that refuse the system as "refused" (named ones that refuse it are an error).
        steps: fixed steps [s]; each must divide output_dt.
        tolerances: adaptive tolerances (rtol = atol).
        output_dt: the common sample grid [s] (default min(OUTPUT_DT, duration)).
        reference_tolerance: rtol = atol of the DOP853 reference.
        refinement: the check runs at reference_tolerance / refinement.
        min_error: a ladder stops below this error.
        max_steps: the largest number of steps of a fixed-step run.
        max_run_time: the CPU-time budget of one run [s] (see above).
        repeats: runs shorter than REPEAT_BELOW seconds are timed this many times (median).
        prune: stop a ladder that other integrators dominate (the pilot study of `run --tolerance`).
        progress: called with one line of text per measurement.
        controller: ``controller(t, q, v) -> tau`` applied in every run, the reference included (reset before each
            run, as simulate does), so the study measures the motion the run will make; None applies no torque.
        control_dt: the controller's period [s] (simulate's ``control_dt``); fixed steps that do not divide it are
            left out of the ladder. None: CONTROL_DT (a controller called at every step of an adaptive method
            would make the motion depend on the steps, and no run could be measured against another).

    Returns:
        The study.

    Raises:
        InvalidArgumentError: a bad argument (named in the message), or a named integrator refuses the system.
        SimulationError: the reference itself failed.
        BenchInterrupted: Ctrl-C; ``.result`` holds what was measured so far.
    """
    check_system(system)
    q0 = system.check_q(q0, "q0")
    v0 = system.check_v(v0, "v0")
    duration = positive_number(duration, "duration")
    if steps is None:  # the ladder's finest step must fit in the run, and the run's steps must stay countable
        finest = STEP_LADDER[-1]
        if not finest <= duration <= MAX_STEPS * finest:
            raise InvalidArgumentError(
                f"duration must be from {finest:g} s (the finest step of the bench's ladder) to "
                f"{MAX_STEPS * finest:.4g} s (2**53 of those steps), got {duration:g} s"
            )
    methods, refused = _methods(system, integrators)
    grid = min(OUTPUT_DT, duration) if output_dt is None else positive_number(output_dt, "output_dt")
    if grid > duration * (1 + 1e-12):
        raise InvalidArgumentError(f"output_dt must not exceed the duration ({duration:g} s), got {grid:g} s")
    if steps is None:
        ladder = [dt for dt in STEP_LADDER if dt <= grid * (1 + 1e-12) and _divides(dt, grid)]
    else:
        if not isinstance(steps, (list, tuple, np.ndarray)):
            raise InvalidArgumentError(f"steps must be a list of steps [s], got {type(steps).__name__}")
        ladder = sorted({positive_number(dt, "steps") for dt in steps}, reverse=True)
        for dt in ladder:
            if not _divides(dt, grid):
                raise InvalidArgumentError(
                    f"steps: {dt:g} s does not divide output_dt = {grid:g} s (the common sample grid)"
                )
    tols = sorted(
        {positive_number(t, "tolerances", None) for t in (TOLERANCE_LADDER if tolerances is None else tolerances)},
        reverse=True,
    )
    reference_tolerance = positive_number(reference_tolerance, "reference_tolerance", None)
    refinement = positive_number(refinement, "refinement", None)
    if refinement <= 1:
        raise InvalidArgumentError(f"refinement must be > 1 (the check is that many times tighter), got {refinement}")
    min_error = positive_number(min_error, "min_error", None)
    max_run_time = positive_number(max_run_time, "max_run_time")
    if not isinstance(repeats, (int, np.integer)) or isinstance(repeats, bool) or repeats < 1:
        raise InvalidArgumentError(f"repeats must be a positive integer, got {repeats!r}")
    if not isinstance(max_steps, (int, np.integer)) or isinstance(max_steps, bool) or max_steps < 1:
        raise InvalidArgumentError(f"max_steps must be a positive integer, got {max_steps!r}")
    check_callable(progress, "progress", "progress(line)")
    check_callable(controller, "controller", "controller(t, q, v) -> tau")
    if controller is None:
        control_dt = None
    else:
        control_dt = CONTROL_DT if control_dt is None else positive_number(control_dt, "control_dt")
        ladder = [dt for dt in ladder if _divides(dt, control_dt)]
    say = progress or (lambda line: None)

    result = WorkPrecision(
        system=getattr(system, "name", type(system).__name__),
        duration=duration,
        output_dt=grid,
        q0=q0.tolist(),
        v0=v0.tolist(),
        reference=None,
        measurements=[Measurement(name, math.nan, None, None, STATUS_REFUSED, message=why) for name, why in refused],
        orders={},
        settings={
            "steps": ladder,
            "tolerances": tols,
            "adaptive_first_step": ADAPTIVE_FIRST_STEP,
            "reference_tolerance": reference_tolerance,
            "refinement": refinement,
            "min_error": min_error,
            "max_steps": int(max_steps),
            "max_run_time": max_run_time,
            "repeats": int(repeats),
            "prune": bool(prune),
            "cost": "cpu_time: process CPU time of the simulate() call, median over repeats",
            "controller": None if controller is None else controller_name(controller),
            "control_dt": control_dt,
        },
        metadata={"versions": dict(versions()), "source": getattr(system, "source", {})},
        complete=False,
    )
    study = _Study(system, q0, v0, duration, grid, result, say, int(repeats), max_run_time, controller, control_dt)
    if study.contact:
        say(
            f"measuring {len(methods)} integrator(s) over {duration:g} s against timestepping at dt "
            f"{CONTACT_REFERENCE_DT:g} s (checked at {CONTACT_REFERENCE_DT / 2:g} s): a contact scene is not smooth, "
            "so its reference is the same integrator at a much smaller step ..."
        )
        ladder = [dt for dt in ladder if dt >= 2 * CONTACT_REFERENCE_DT]
        result.settings["steps"] = ladder
    else:
        say(
            f"measuring {len(methods)} integrators over {duration:g} s against a {REFERENCE_INTEGRATOR} reference at "
            f"rtol {reference_tolerance:.0e} (checked at {reference_tolerance / refinement:.0e}) ..."
        )
    try:
        result.reference = study.reference(reference_tolerance, refinement)
        say(f"reference: estimated error {result.reference.error:.1e}")
        floor = max(min_error, REFERENCE_MARGIN * result.reference.error)
        # Cheap, high-order methods first: with pruning, they are what the others are measured against.
        for method in sorted(methods, key=lambda m: (m.implicit, -m.order)):
            if method.adaptive:
                rungs: list[tuple[float, float | None]] = [(ADAPTIVE_FIRST_STEP, t) for t in tols]
            else:
                rungs = [(dt, None) for dt in ladder]
            study.ladder(method, rungs, floor, int(max_steps), prune)
    except KeyboardInterrupt:
        result.orders = observed_orders(result)
        raise BenchInterrupted(f"interrupted after {len(result.measurements)} measurements", result=result) from None
    result.orders = observed_orders(result)
    result.complete = True
    return result


class _Study:
    """The running study: timing, error measurement and the ladder stops."""

    def __init__(
        self,
        system: Robot,
        q0: np.ndarray,
        v0: np.ndarray,
        duration: float,
        grid: float,
        result: WorkPrecision,
        say: Callable[[str], None],
        repeats: int,
        max_run_time: float,
        controller: Controller | None = None,
        control_dt: float | None = None,
    ):
        self.system, self.q0, self.v0 = system, q0, v0
        self.controller, self.control_dt = controller, control_dt
        self.duration, self.grid = duration, grid
        self.result, self.say = result, say
        self.repeats, self.max_run_time = repeats, max_run_time
        self.contact = getattr(system, "contact", None) is not None

    def reference(self, tolerance: float, refinement: float) -> Reference:
        if self.contact:  # no smooth reference: the same method at a much smaller step, checked at half of it
            dt = CONTACT_REFERENCE_DT
            run = self._simulate("timestepping", dt, None)
            check = self._simulate("timestepping", dt / 2, None)
            return Reference(
                integrator="timestepping",
                rtol=math.nan,
                atol=math.nan,
                check_rtol=math.nan,
                check_atol=math.nan,
                error=trajectory_error(self.system, run, check),
                evaluations=int(run.stats["evaluations"]),
                wall_time=float(run.stats["wall_time"]),
                dt=dt,
                check_dt=dt / 2,
                t=run.t,
                q=run.q,
                v=run.v,
            )
        run = self._simulate(REFERENCE_INTEGRATOR, ADAPTIVE_FIRST_STEP, tolerance)
        check = self._simulate(REFERENCE_INTEGRATOR, ADAPTIVE_FIRST_STEP, tolerance / refinement)
        return Reference(
            integrator=REFERENCE_INTEGRATOR,
            rtol=tolerance,
            atol=tolerance,
            check_rtol=tolerance / refinement,
            check_atol=tolerance / refinement,
            error=trajectory_error(self.system, run, check),
            evaluations=int(run.stats["evaluations"]),
            wall_time=float(run.stats["wall_time"]),
            t=run.t,
            q=run.q,
            v=run.v,
        )

    def _simulate(self, integrator: str | Integrator, dt: float, tolerance: float | None) -> Trajectory:
        options: dict[str, Any] = {"output_dt": self.grid}
        if tolerance is not None:
            options.update(rtol=tolerance, atol=tolerance)
        if self.control_dt is not None:
            options["control_dt"] = self.control_dt
        return simulate(
            self.system,
            self.q0,
            self.v0,
            duration=self.duration,
            dt=dt,
            integrator=integrator,
            controller=self.controller,
            **options,
        )

    def ladder(
        self, method: Integrator, rungs: list[tuple[float, float | None]], floor: float, max_steps: int, prune: bool
    ) -> None:
        dominated_in_a_row = 0
        per_step = math.nan  # the latest run's CPU time per step [s]: predicts a fixed-step run's time
        for dt, tolerance in rungs:
            if tolerance is None:
                n_steps = math.ceil(self.duration / dt - 1e-9)
                if n_steps > max_steps:
                    self.say(f"{method.name}: stopped before dt {dt:g} s (more than {max_steps} steps)")
                    return
                if per_step * n_steps > self.max_run_time:
                    self.say(
                        f"{method.name}: stopped before dt {dt:g} s (it would take ~{per_step * n_steps:.2g} s, "
                        f"budget {self.max_run_time:g} s)"
                    )
                    return
            m = self.measure(method, dt, tolerance)
            self.result.measurements.append(m)
            if m.completed:  # a run that stopped early is dominated by the fixed per-call cost: no estimate
                per_step = m.cpu_time / m.steps
            shown = f"error {m.error:.2e}" if m.completed else m.status
            self.say(f"{method.name:<20} {m.settings():<26} {shown:<16} {m.cpu_time:8.3f} s  {m.evaluations} evals")
            if not m.completed:
                continue
            if m.error < floor:
                return
            if tolerance is not None and m.cpu_time > self.max_run_time:
                self.say(f"{method.name}: stopped after a {m.cpu_time:.2f} s run (budget {self.max_run_time:g} s)")
                return
            if prune:
                dominated = any(
                    o.completed and o.integrator != m.integrator and o.error <= m.error and o.cpu_time <= m.cpu_time
                    for o in self.result.measurements
                )
                dominated_in_a_row = dominated_in_a_row + 1 if dominated else 0
                if dominated_in_a_row >= 2:
                    self.say(f"{method.name}: stopped (another integrator is more accurate for less)")
                    return

    def measure(self, method: Integrator, dt: float, tolerance: float | None) -> Measurement:
        m = Measurement(method.name, dt, tolerance, tolerance, STATUS_COMPLETED)
        start = time.process_time()
        try:
            traj = self._simulate(method, dt, tolerance)
        except SimulationError as exc:
            m.cpu_time = time.process_time() - start
            m.cpu_times = [m.cpu_time]
            m.status, m.message = exc.status, str(exc).splitlines()[0]
            partial = exc.trajectory
            if partial is not None:
                m.kernel = str(partial.metadata.get("kernel", ""))
                m.steps = int(partial.stats.get("steps", 0))
                m.evaluations = int(partial.stats.get("evaluations", 0))
                m.wall_time = float(partial.stats.get("wall_time", math.nan))
                m.wall_times = [m.wall_time]
            return m
        m.cpu_times = [time.process_time() - start]
        m.wall_times = [float(traj.stats["wall_time"])]
        m.kernel = str(traj.metadata.get("kernel", ""))
        why = traj.metadata.get("why_not_native")
        if why:
            self.result.metadata.setdefault("why_not_native", {})[method.name] = str(why)
        # Repeat only short runs: their timing is the noisiest, and repeating them costs little.
        while len(m.cpu_times) < self.repeats and sum(m.cpu_times) < REPEAT_BELOW:
            start = time.process_time()
            again = self._simulate(method, dt, tolerance)
            m.cpu_times.append(time.process_time() - start)
            m.wall_times.append(float(again.stats["wall_time"]))
        import statistics  # here: it pulls random and fractions into `import multibody_sim`

        m.cpu_time = statistics.median(m.cpu_times)
        m.wall_time = statistics.median(m.wall_times)
        m.steps = int(traj.stats["steps"])
        m.rejected_steps = int(traj.stats["rejected_steps"])
        m.evaluations = int(traj.stats["evaluations"])
        m.energy_error = traj.max_abs_energy_error
        reference = self.result.reference
        assert reference is not None
        m.error = _grid_error(self.system, traj.t, traj.q, traj.v, reference.t, reference.q, reference.v)
        m.below_reference = m.error < REFERENCE_MARGIN * reference.error
        return m


def _methods(
    system: Robot, integrators: Iterable[str | Integrator] | None
) -> tuple[list[Integrator], list[tuple[str, str]]]:
    """(integrators to measure, [(name, why) of those that refuse the system])."""
    named = integrators is not None
    if integrators is None:
        candidates = list(INTEGRATORS.values())
    else:
        if isinstance(integrators, (str, Integrator)):
            raise InvalidArgumentError(
                f"integrators must be a list of names, got {type(integrators).__name__} (write [{integrators!r}])"
            )
        if not isinstance(integrators, Iterable):
            raise InvalidArgumentError(f"integrators must be a list of names, got {type(integrators).__name__}")
        candidates = [get_integrator(i) for i in integrators]
        if not candidates:
            raise InvalidArgumentError("integrators must name at least one integrator, got an empty list")
        names = [m.name for m in candidates]
        duplicates = sorted({n for n in names if names.count(n) > 1})
        if duplicates:
            raise InvalidArgumentError(f"integrators: {', '.join(duplicates)} named more than once")
    methods, refused = [], []
    for method in candidates:
        try:
            method.check_system(system)
        except InvalidArgumentError as exc:
            if named:
                raise
            refused.append((method.name, str(exc).split(";")[0]))
            continue
        methods.append(method)
    return methods, refused


# ---- errors and orders -----------------------------------------------------------------------------------
def trajectory_error(system: Robot, trajectory: Trajectory, reference: Trajectory) -> float:
    """max over samples of ‖(q ⊖ q_ref, v − v_ref)‖∞, the error `--tolerance` bounds (CONTRACTS.md).

    Args:
        system: the robot both trajectories belong to.
        trajectory: the run to measure.
        reference: the reference, sampled at the same times.

    Raises:
        InvalidArgumentError: the trajectories are not sampled at the same times.
    """
    check_system(system)
    check_trajectory(trajectory, "trajectory")
    check_trajectory(reference, "reference")
    return _grid_error(system, trajectory.t, trajectory.q, trajectory.v, reference.t, reference.q, reference.v)


def _grid_error(
    system: Robot,
    t: np.ndarray,
    Q: np.ndarray,
    V: np.ndarray,
    t_ref: np.ndarray | None,
    Q_ref: np.ndarray | None,
    V_ref: np.ndarray | None,
) -> float:
    assert t_ref is not None and Q_ref is not None and V_ref is not None
    scale = max(float(abs(t_ref[-1])) if len(t_ref) else 1.0, 1.0)
    if len(t) != len(t_ref) or not np.allclose(t, t_ref, rtol=0.0, atol=1e-9 * scale):
        raise InvalidArgumentError(
            f"the trajectories are not sampled at the same times ({len(t)} and {len(t_ref)} samples)"
        )
    space = system.space
    worst = 0.0
    for q, v, q_ref, v_ref in zip(Q, V, Q_ref, V_ref, strict=True):
        worst = max(worst, float(np.abs(space.difference(q_ref, q)).max()), float(np.abs(v - v_ref).max()))
    return worst


def observed_orders(result: WorkPrecision) -> dict[str, OrderFit]:
    """Fit each integrator's observed order from a study's measurements.

    Fixed-step: the least-squares slope of log(error) against log(dt) over the finest FIT_POINTS usable
    measurements. Adaptive: minus the slope of log(error) against log(evaluations) over the tightest
    ADAPTIVE_FIT_POINTS usable ones (an effective order: error ∝ evaluations^-p for an order-p method).
    Usable: completed, not within REFERENCE_MARGIN of the reference's error, and below 0.1 (larger errors are
    far from the asymptotic regime).
    """
    _check_study(result)
    fits = {}
    for name in result.integrators():
        method = INTEGRATORS.get(name)
        points = result.for_integrator(name)
        if method is None or not points or all(m.status == STATUS_REFUSED for m in points):
            continue
        adaptive = method.adaptive
        usable = [m for m in points if m.completed and not m.below_reference and 0 < m.error < 0.1]
        usable = usable[-(ADAPTIVE_FIT_POINTS if adaptive else FIT_POINTS) :]
        against = "evaluations" if adaptive else "dt"
        # Where stability, not accuracy, limits an adaptive method's step (a stiff system), its cost hardly moves
        # with the tolerance: a slope over such points is meaningless.
        flat = (
            adaptive
            and len(usable) >= 2
            and max(m.evaluations for m in usable) < 1.5 * min(m.evaluations for m in usable)
        )
        if len(usable) < 2 or flat:
            done = [m for m in points if m.completed]
            if flat:
                note = "its cost hardly changes with the tolerance (stability limits the step): no order"
            elif done and all(m.below_reference for m in done):
                note = "every error is within the reference's: exact to its accuracy here"
            else:
                note = "too few usable points to fit"
            fits[name] = OrderFit(name, method.order, math.nan, against, len(usable), False, note)
            continue
        x = np.log([m.evaluations if adaptive else m.dt for m in usable])
        y = np.log([m.error for m in usable])
        slope = float(np.polyfit(x, y, 1)[0])
        observed = -slope if adaptive else slope
        # Two points make a slope but not a judgement: their error may still be pre-asymptotic. An effective order
        # (adaptive) is not a classical order: it is shown, not judged.
        mismatch = not adaptive and len(usable) >= 3 and abs(observed - method.order) > ORDER_MISMATCH
        note = ""
        if mismatch:
            where = ", ".join(m.settings().removeprefix("dt ").removeprefix("rtol ").split(",")[0] for m in usable)
            note = f"fitted on {where}: see the errors"
        fits[name] = OrderFit(name, method.order, observed, against, len(usable), mismatch, note)
    return fits


# ---- the recommendation ---------------------------------------------------------------------------------
_COSTS = ("cpu_time", "wall_time", "evaluations")


def _check_study(result: Any) -> None:
    if not isinstance(result, WorkPrecision):
        raise InvalidArgumentError(f"result must be a WorkPrecision (work_precision's), got {type(result).__name__}")


def recommend(result: WorkPrecision, tolerance: float, *, cost: str = "cpu_time") -> Measurement | None:
    """The cheapest measured configuration that meets `tolerance` on this system, or None.

    A measurement meets it when it completed and its error plus the reference's estimated error is at most
    `tolerance` (so the true error is within it as far as the reference can tell).

    Args:
        result: a study.
        tolerance: the accuracy wanted, in the error's units (CONTRACTS.md `--tolerance`).
        cost: what "cheapest" minimises: "cpu_time" (default), "wall_time" or "evaluations"; ties are broken by
            evaluations, then CPU time.

    Raises:
        InvalidArgumentError: tolerance is not a positive number, or cost is unknown.
    """
    _check_study(result)
    tolerance = positive_number(tolerance, "tolerance", None)
    if cost not in _COSTS:
        raise InvalidArgumentError(f"cost must be one of {', '.join(map(repr, _COSTS))}, got {cost!r}")
    meeting = [m for m in result.measurements if m.completed and m.error + result.reference_error <= tolerance]
    if not meeting:
        return None
    return min(meeting, key=lambda m: (getattr(m, cost), m.evaluations, m.cpu_time))


# ---- the pilot study of `run --tolerance` ------------------------------------------------------------------
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


# ---- the picture -----------------------------------------------------------------------------------------
def plot_work_precision(result: WorkPrecision, path: str | os.PathLike[str], *, title: str | None = None) -> Path:
    """Draw the work-precision diagram: error against CPU time and against evaluations, log-log, one curve per
    integrator (hollow markers: within the reference's error), and max |energy_error| against CPU time.

    Raises:
        ModuleNotFoundError: matplotlib is missing (the message says which extra installs it).
    """
    _check_study(result)
    check_path(path, "path", "a PNG file")
    check_text(title, "title")
    try:
        import matplotlib

        matplotlib.use("Agg")  # files only: never open a window
        import matplotlib.pyplot as plt
    except ImportError:
        raise ModuleNotFoundError(
            "the work-precision PNG needs matplotlib: pip install 'multibody-sim[viz]'", name="matplotlib"
        ) from None
    fig, axes = plt.subplots(1, 3, figsize=(16, 5.2))
    markers = "os^vD<>ph*"
    for name in result.integrators():
        k = _color_index(name)
        done = [m for m in result.for_integrator(name) if m.completed and m.error > 0]
        if not done:
            continue
        fit = result.orders.get(name)
        label = name
        if fit is not None:
            observed = "—" if math.isnan(fit.observed) else f"{fit.observed:.1f}"
            kind = "effective" if fit.against == "evaluations" else "obs"
            label += f" (p={fit.theoretical}, {kind} {observed}{'!' if fit.mismatch else ''})"
        style = {
            "marker": markers[k % len(markers)],
            "color": METHOD_COLORS[k % len(METHOD_COLORS)],
            "ms": 4,
            "lw": 1.2,
            "ls": "--" if done[0].adaptive else "-",
        }
        cpu = [m.cpu_time for m in done]
        evals = [m.evaluations for m in done]
        errors = [m.error for m in done]
        (line,) = axes[0].loglog(cpu, errors, label=label, **style)
        axes[1].loglog(evals, errors, **style)
        energy = [(m.cpu_time, m.energy_error) for m in done if m.energy_error > 0]
        if energy:
            axes[2].loglog(*zip(*energy, strict=True), **style)
        hollow = [(m.cpu_time, m.evaluations, m.error) for m in done if m.below_reference]
        if hollow:
            w, e, err = zip(*hollow, strict=True)
            for ax, x in ((axes[0], w), (axes[1], e)):
                ax.plot(x, err, ls="none", marker=style["marker"], ms=7, mfc="white", mec=line.get_color())
    if result.reference is not None and math.isfinite(result.reference.error) and result.reference.error > 0:
        for ax in axes[:2]:
            ax.axhline(result.reference.error, color="grey", ls=":", lw=1, label="reference's estimated error")
    axes[0].set_xlabel("CPU time of the run [s]")
    axes[1].set_xlabel("dynamics evaluations")
    axes[2].set_xlabel("CPU time of the run [s]")
    axes[0].set_ylabel("max error |(q ⊖ q_ref, v − v_ref)|∞")
    axes[1].set_ylabel("max error |(q ⊖ q_ref, v − v_ref)|∞")
    axes[2].set_ylabel("max |energy_error| [J] (a check, not the error)")
    for ax in axes:
        ax.grid(True, which="both", alpha=0.3)
    if axes[0].get_legend_handles_labels()[0]:  # none when no run completed: matplotlib would warn
        axes[0].legend(fontsize=7, loc="best")
    fig.suptitle(title or f"{safe_name(result.system)}: work-precision over {result.duration:g} s (dashed: adaptive)")
    fig.tight_layout()
    path = Path(path)
    write_atomically(path, lambda f: fig.savefig(f, dpi=110, format=path.suffix.lstrip(".") or "png"))
    plt.close(fig)
    return path


# One colour per integrator, the same in every diagram: Paul Tol's "muted" scheme, whose nine colours stay apart
# under the common colour-vision deficiencies, then black and blue (eleven methods are registered; the blue keeps
# every pair apart under the three simulated deficiencies, as tests/test_bench.py checks).
METHOD_COLORS = (
    "#332288",
    "#88CCEE",
    "#44AA99",
    "#117733",
    "#999933",
    "#DDCC77",
    "#CC6677",
    "#882255",
    "#AA4499",
    "#000000",
    "#0077BB",
)


def _color_index(name: str) -> int:
    """An integrator's place in the registry (its colour); integrators outside it follow."""
    names = list(INTEGRATORS)
    return names.index(name) if name in names else len(names) + sum(map(ord, name)) % len(METHOD_COLORS)


# ---- helpers ---------------------------------------------------------------------------------------------
def _divides(dt: float, period: float) -> bool:
    k = round(period / dt)
    return k >= 1 and abs(k * dt - period) <= 1e-9 * period


def _stopped_note(points: list[Measurement]) -> str:
    failed = [m for m in points if not m.completed and m.status != STATUS_REFUSED]
    refused = [m for m in points if m.status == STATUS_REFUSED]
    if refused:
        return f"refused: {refused[0].message}"
    if not failed:
        return ""
    kinds = sorted({m.status for m in failed})
    return f"{', '.join(kinds)} at {', '.join(m.settings().split(',')[0] for m in failed)}"


def _fmt(value: float, spec: str) -> str:
    return format(value, spec) if isinstance(value, (int, float)) and math.isfinite(value) else "—"


def _text_table(headers: list[str], rows: list[list[str]], indent: int = 0) -> str:
    cells = [headers, *rows]
    widths = [max(len(row[i]) for row in cells) for i in range(len(headers))]
    pad = " " * indent
    return "\n".join(pad + "  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)).rstrip() for row in cells)


def _json_ready(value: Any) -> Any:
    if isinstance(value, dict):
        return {str(k): _json_ready(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_json_ready(v) for v in value]
    if isinstance(value, (np.floating, float)):
        return float(value) if math.isfinite(value) else None
    if isinstance(value, (np.integer,)):
        return int(value)
    if isinstance(value, (np.bool_,)):
        return bool(value)
    if isinstance(value, np.ndarray):
        return _json_ready(value.tolist())
    if isinstance(value, Path):
        return str(value)
    return value


def _nan_back(data: dict[str, Any]) -> dict[str, Any]:
    """JSON null back to nan in the float fields that are never None (rtol/atol of fixed steps stay None)."""
    out = dict(data)
    for key in ("dt", "error", "energy_error", "cpu_time", "wall_time", "observed"):
        if key in out and out[key] is None:
            out[key] = math.nan
    for key in ("cpu_times", "wall_times"):
        if key in out:
            out[key] = [math.nan if x is None else float(x) for x in out[key]]
    return out


def _csv_cell(value: Any) -> Any:
    if value is None or (isinstance(value, float) and not math.isfinite(value)):
        return ""
    if isinstance(value, float):
        return repr(value)
    return value


class _StringBuffer:
    """A minimal text sink for csv.writer."""

    def __init__(self) -> None:
        self.parts: list[str] = []

    def write(self, text: str) -> int:
        self.parts.append(text)
        return len(text)

    @property
    def text(self) -> str:
        return "".join(self.parts)


def _write_text_atomically(path: Path, text: str) -> Path:
    """Write text to path through a temporary file and a rename (readers never see half a file)."""
    write_atomically(path, lambda f: f.write(text.encode("utf-8")))
    return path


__all__ = [
    "BenchInterrupted",
    "Choice",
    "Measurement",
    "OrderFit",
    "Reference",
    "WorkPrecision",
    "choose_integrator",
    "default_cache_dir",
    "observed_orders",
    "plot_work_precision",
    "recommend",
    "trajectory_error",
    "work_precision",
]
