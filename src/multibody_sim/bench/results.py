"""A work-precision study's results: its measurements, reference and order fits (WorkPrecision), their tables and
files (CSV, JSON, the diagram), the observed orders fitted from them and the cheapest configuration meeting an
accuracy (recommend)."""

from __future__ import annotations

import dataclasses
import io
import json
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..exceptions import InvalidArgumentError
from ..files import write_atomically
from ..integrators import INTEGRATORS
from ..safety import MAX_JSON_DEPTH, json_depth
from ..text import safe_name, text_table
from ..trajectory import plain_data
from ..validation import (
    check_path,
    check_text,
    positive_number,
)

FORMAT = "multibody-sim work-precision"
FORMAT_VERSION = 1
# Errors within this factor of the reference's estimated error may be the reference's: flagged, not fitted.
REFERENCE_MARGIN = 10.0
FIT_POINTS = 3  # fixed steps: the order is the slope over the finest usable rungs (coarse ones are pre-asymptotic)
ADAPTIVE_FIT_POINTS = 9  # 4 decades of tolerance: its rungs are close in evaluations and noisy one by one
# A fit over 3 rungs a factor 2-2.5 apart moves by ~0.1-0.3 with the error's curvature: beyond these it is off.
ORDER_MISMATCH = 0.4
# Adaptive methods are fitted against evaluations: an effective order, which comes out steeper than the classical
# order, the more so the higher it is (measured 2.6-3.1 for bs32, 5.4-6.8 for dp54 and 9-11.4 for dop853 on the
# double pendulum, ur5, solo12 and talos, as the controller's start-up and landing steps weigh more at loose
# tolerances). It is reported as what it is, never judged against the classical order.
# A reference whose check differs from it by more than this [rad, m, rad/s, m/s] has not converged: the loosest
# accuracy the study recommends for is 1e-2.
UNCONVERGED_REFERENCE = 1e-2
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
        return plain_data(
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
        buffer = io.StringIO()
        writer = csv.DictWriter(buffer, fieldnames=CSV_COLUMNS, lineterminator="\n")
        writer.writeheader()
        for row in rows:
            writer.writerow({k: _csv_cell(v) for k, v in row.items()})
        return _write_text_atomically(Path(path), buffer.getvalue())

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
        return text_table([*headers, "notes"], rows)

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
        lines.append(text_table(["accuracy", "integrator", "settings", "error", "CPU [s]", "evaluations"], rows, 2))
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


def _write_text_atomically(path: Path, text: str) -> Path:
    """Write text to path through a temporary file and a rename (readers never see half a file)."""
    write_atomically(path, lambda f: f.write(text.encode("utf-8")))
    return path
