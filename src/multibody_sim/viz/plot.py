"""Plots of a trajectory: energies, the energy ledger and the joint positions against time (matplotlib, no display)."""

from __future__ import annotations

import difflib
import io
import math
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..exceptions import InvalidArgumentError, ModelError, TrajectoryFileError, UnknownNameError
from ..files import check_output, write_atomically
from ..robot import Robot, check_system
from ..safety import check_allocation
from ..text import safe_name
from ..trajectory import Trajectory, check_trajectory
from ..validation import check_path, check_text, positive_count
from ._deps import require

PANEL_HEIGHT = 2.4  # [in]
FIGURE_WIDTH = 9.0  # [in], before the legends' extra columns
LEGEND_ROWS = 14  # entries per legend column: more joints take more columns (and a wider figure)
LEGEND_COLUMN_WIDTH = 1.6  # [in] added per legend column beyond the first
# Joint lines: ten colours (matplotlib's tab10), then the same colours dashed, dotted, dash-dotted: 40 distinct.
_STYLES = ("-", "--", ":", "-.")
# Ledger lines: totals solid; elements dashed with markers, placed at staggered samples so that an element equal
# to a total (or to another element) still shows.
_MARKERS = ("o", "s", "^", "v", "D", "P", "X", "*")
_MARKS_PER_LINE = 12
# The largest magnitude a plotted value may have: matplotlib's axis span (max - min, with margins) overflows near
# 8e307 and its tick locator then fails; 1e300 leaves it room.
PLOT_LIMIT = 1e300
ENERGY_CURVES = ("kinetic_energy", "potential_energy", "total_energy", "work", "dissipated", "energy_error")


@dataclass(frozen=True)
class _Series:
    joint: str  # the joint it belongs to (what --joints selects)
    label: str
    values: np.ndarray


def plot_trajectory(
    trajectory: Trajectory,
    path: str | os.PathLike[str] | None = None,
    *,
    robot: Robot | None = None,
    joints: Sequence[str] | None = None,
    title: str | None = None,
    dpi: int = 110,
) -> Any:
    """Plot a trajectory: energies, the energy ledger, energy_error and joint positions against time.

    Panels, top to bottom: kinetic T, potential V and total H = T + V [J]; the ledger: work put in, energy
    dissipated and each ledger element [J] (elements dashed with markers, so that curves that coincide stay
    visible); energy_error = H - H(0) - work + dissipated [J]; the joint positions (one line per joint
    coordinate: revolute [rad], prismatic [m], continuous joints as their angle); for a floating base, the base
    position x, y, z [m]. Legends sit to the right of their panel, in as many columns as the lines need. No
    panel shows an offset or a power of ten above its axis: they are written into the axis label instead
    ("energy_error [1e-06 J]"). Uses matplotlib's Agg renderer (no display, no pyplot state).

    Args:
        trajectory: the trajectory to plot.
        path: write a PNG there (atomically); None only returns the figure.
        robot: its robot, for joint names and types; None reads them from the metadata (loading the robot
            when the metadata alone cannot tell a joint's coordinates apart).
        joints: the joints to plot (names; a floating base's root joint is the base panel); None plots all.
        title: the figure title (default: robot name, integrator and step).
        dpi: resolution of the PNG.

    Returns:
        The matplotlib Figure.

    Raises:
        UnknownNameError: a name in `joints` is not a joint of the robot (the message lists close matches).
        InvalidArgumentError: an argument of the wrong type.
    """
    _check_plot_arguments(trajectory, robot)
    names = [joints] if isinstance(joints, str) else joints
    if names is not None and (not isinstance(names, (list, tuple)) or not all(isinstance(j, str) for j in names)):
        raise InvalidArgumentError(f"joints must be a list of joint names, got {joints!r:.80}")
    check_text(title, "title")
    positive_count(dpi, "dpi", "dots per inch")  # its canvas's size is checked against memory when drawn
    if path is not None:
        check_path(path, "path", "a PNG file")
        check_output(path, "out", "plot.png")  # before drawing: only a regular file is replaced
    figure_module = require("matplotlib.figure", "plots")
    t = np.asarray(trajectory.t, dtype=float)
    series, base, root = _joint_series(trajectory, robot)
    if joints is not None:
        chosen = _check_joints(joints, [*([root] if root else []), *dict.fromkeys(s.joint for s in series)])
        series = [s for s in series if s.joint in chosen]
        base = base if root in chosen else None
    _check_plottable(t, trajectory, series, base)
    legend_columns = max(1, math.ceil(len(series) / LEGEND_ROWS))
    joint_height = max(PANEL_HEIGHT, 0.17 * min(len(series), LEGEND_ROWS) + 0.5)
    heights = [PANEL_HEIGHT] * 3 + ([joint_height] if series else []) + ([PANEL_HEIGHT] if base is not None else [])
    size = (FIGURE_WIDTH + LEGEND_COLUMN_WIDTH * (legend_columns - 1), sum(heights) + 0.6)
    # Before drawing: the canvas (4 bytes a pixel) and the lines (matplotlib keeps ~4 copies of each point's x, y).
    lines = len(series) + 10 + len(trajectory.ledger)
    pixels = size[0] * size[1] * float(dpi) ** 2
    check_allocation(
        4 * pixels + 64 * len(t) * lines,
        f"a {size[0] * float(dpi):.0f}x{size[1] * float(dpi):.0f}-pixel plot of {lines} lines over {len(t)} samples "
        "would keep its canvas and lines",
        "plot fewer joints (joints=), a lower dpi, or a shorter trajectory",
    )
    fig = figure_module.Figure(
        figsize=size,
        dpi=dpi,
        layout="constrained",
    )
    axes = list(fig.subplots(len(heights), 1, sharex=True, gridspec_kw={"height_ratios": heights}))
    energy, ledger, error = axes[:3]
    energy.plot(t, trajectory.kinetic_energy, label="kinetic T")
    energy.plot(t, trajectory.potential_energy, label="potential V")
    energy.plot(t, trajectory.total_energy, label="total H = T + V", linewidth=2.0)
    energy.set_ylabel("energy [J]")
    _ledger_lines(ledger, t, trajectory)
    ledger.set_ylabel("ledger [J]")
    error.plot(t, trajectory.energy_error, color="tab:red", label="H - H(0) - work + dissipated\n(zero when exact)")
    error.set_ylabel("energy_error [J]")
    panel = 3
    if series:
        positions = axes[panel]
        for k, item in enumerate(series):
            color, style = f"C{k % 10}", _STYLES[(k // 10) % len(_STYLES)]
            positions.plot(t, item.values, label=item.label, color=color, linestyle=style, linewidth=1.2)
        positions.set_ylabel("joint position [rad, m]")
        panel += 1
    if base is not None:
        axis = axes[panel]
        for k, name in enumerate("xyz"):
            axis.plot(t, base[:, k], label=f"base {name}")
        axis.set_ylabel("base position [m]")
    for axis in axes:
        axis.grid(True, alpha=0.3)
        entries = len(axis.get_lines())
        columns = max(1, math.ceil(entries / LEGEND_ROWS))
        axis.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize="x-small", ncols=columns, borderaxespad=0)
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(title or _title(trajectory, robot))
    _offsets_into_labels(fig, axes)
    if path is not None:
        target = Path(path)
        write_atomically(target, lambda f: fig.savefig(f, format="png"))
    return fig


def plot_png(trajectory: Trajectory, *, robot: Robot | None = None) -> bytes:
    """The plot_trajectory figure as PNG bytes."""
    _check_plot_arguments(trajectory, robot)
    return plot_command(trajectory, robot=robot)["png"]


def plot_command(trajectory: Trajectory, *, robot: Robot | None = None) -> dict[str, Any]:
    """The page command that shows the plot beside the view, with where its time axis lies in the picture.

    The page draws a cursor over the plot at the time the robot shows: `cursor` gives the time range [s] of the
    x axis and the axes' left, right, top and bottom edges as fractions of the image (top-down).
    """
    fig = plot_trajectory(trajectory, robot=robot)
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png")  # also fixes the constrained layout: positions below are final
    first, last = fig.axes[0].get_position(), fig.axes[-1].get_position()
    t0, t1 = fig.axes[0].get_xlim()
    cursor = {"t0": t0, "t1": t1, "left": first.x0, "right": first.x1, "top": 1.0 - first.y1, "bottom": 1.0 - last.y0}
    return {"type": "multibody_sim_plot", "path": "", "png": buffer.getvalue(), "cursor": cursor}


def _check_plot_arguments(trajectory: Any, robot: Any) -> None:
    check_trajectory(trajectory, "trajectory")
    if robot is not None:
        check_system(robot, "robot")


def _check_plottable(t: np.ndarray, trajectory: Trajectory, series: list[_Series], base: np.ndarray | None) -> None:
    """Refuse a curve matplotlib cannot scale: a value beyond ±PLOT_LIMIT (its axis span overflows, its tick
    locator fails) or not finite, naming the curve, the value and its time."""
    curves: list[tuple[str, str, Any]] = [("time", "s", t)]
    curves += [(name, "J", getattr(trajectory, name)) for name in ENERGY_CURVES]
    curves += [(f"ledger element '{safe_name(name)}'", "J", entry.energy) for name, entry in trajectory.ledger.items()]
    curves += [(f"joint position {item.label}", "rad or m", item.values) for item in series]
    if base is not None:
        curves += [(f"base position {axis}", "m", base[:, k]) for k, axis in enumerate("xyz")]
    for name, unit, values in curves:
        values = np.asarray(values, dtype=float)
        if values.size and not np.abs(values).max() <= PLOT_LIMIT:  # NaN fails too
            i = int(np.argmax(np.nan_to_num(np.abs(values), nan=np.inf)))
            raise InvalidArgumentError(
                f"cannot plot {name}: it reaches {values[i]:.3g} {unit} at t = {t[i]:.6g} s, beyond the "
                f"±{PLOT_LIMIT:g} a plot's axes can span (the run diverged, or the file was edited); `multibody-sim "
                "export` writes its numbers as a table"
            )


def _ledger_lines(axis: Any, t: np.ndarray, trajectory: Trajectory) -> None:
    """Work and dissipated (solid), then each ledger element (dashed, markers at staggered samples)."""
    axis.plot(t, trajectory.work, label="work (in)", color="C0", linewidth=2.0)
    axis.plot(t, trajectory.dissipated, label="dissipated (out)", color="C1", linewidth=2.0)
    step = max(1, len(t) // _MARKS_PER_LINE)
    for k, (name, entry) in enumerate(trajectory.ledger.items()):
        axis.plot(
            t,
            entry.energy,
            label=f"{name} ({entry.kind})",
            color=f"C{(k + 2) % 10}",
            linestyle=_STYLES[1 + k % 3],
            marker=_MARKERS[k % len(_MARKERS)],
            markersize=4,
            markevery=(min(k * step // max(len(trajectory.ledger), 1), len(t) - 1), step) if len(t) else None,
        )


def _offsets_into_labels(fig: Any, axes: list[Any]) -> None:
    """Write an y axis's offset and power of ten into its label instead of above the axis (where it met titles).

    Where matplotlib would write one, the axis gets a fixed offset (matplotlib's) and a power of ten that is a
    multiple of 3, so that its ticks keep meaning what the label says whatever the final layout.
    """
    ticker = require("matplotlib.ticker", "plots")
    fig.draw_without_rendering()  # the formatters choose their offsets when drawn
    for axis in axes:
        formatter = axis.yaxis.get_major_formatter()
        if not isinstance(formatter, ticker.ScalarFormatter) or not formatter.get_offset():
            continue
        low, high = sorted(axis.get_ylim())
        offset = float(formatter.offset)
        ticks = [abs(tick - offset) for tick in axis.get_yticks() if low <= tick <= high]
        largest = max([tick for tick in ticks if tick > 0], default=1.0)
        order = 3 * math.floor(math.log10(largest) / 3) if not 1e-2 <= largest < 1e4 else 0
        formatter.set_useOffset(offset if offset else False)
        if order:
            formatter.set_powerlimits((order, order))
        else:
            formatter.set_scientific(False)
        axis.yaxis.get_offset_text().set_visible(False)
        name, _, unit = axis.get_ylabel().partition(" [")
        unit = unit.removesuffix("]")
        shifted = f"{name} - {offset:.10g}" if offset else name
        axis.set_ylabel(f"{shifted} [1e{order} {unit}]" if order else f"{shifted} [{unit}]")


def _check_joints(names: Sequence[str], available: list[str]) -> set[str]:
    """The selected joints, or UnknownNameError naming the first unknown one with close matches."""
    if isinstance(names, str):
        names = [names]
    for name in names:
        if name not in available:
            close = difflib.get_close_matches(name, available, n=3, cutoff=0.5)
            hint = f"did you mean {', '.join(close)}?" if close else f"joints: {', '.join(available)}"
            raise UnknownNameError(f"unknown joint '{name}' ({hint})")
    return set(names)


def _joint_series(trajectory: Trajectory, robot: Robot | None) -> tuple[list[_Series], np.ndarray | None, str | None]:
    """The joint-position series, the base position (n, 3) for a floating base (else None) and its joint name."""
    Q = np.asarray(trajectory.q, dtype=float)
    if robot is None:
        named = _series_from_metadata(trajectory, Q)
        if named is not None:
            return named
        try:  # the metadata does not say which joints have two coordinates: ask the robot itself
            from ..recorded import robot_from_trajectory

            robot = robot_from_trajectory(trajectory)
        except (ModelError, TrajectoryFileError):
            return [_Series(f"q[{k}]", f"q[{k}]", Q[:, k]) for k in range(Q.shape[1])], None, None
    model = robot.model
    series: list[_Series] = []
    base = root = None
    for jid in range(1, model.njoints):
        joint = model.joints[jid]
        name, iq = model.names[jid], joint.idx_q
        if "FreeFlyer" in joint.shortname():
            base, root = Q[:, iq : iq + 3], name
        elif joint.nq == 1:
            series.append(_Series(name, safe_name(name), Q[:, iq]))
        elif joint.nq == 2 and joint.nv == 1:  # continuous: (cos, sin) -> angle, unwrapped
            series.append(_Series(name, safe_name(name), np.unwrap(np.arctan2(Q[:, iq + 1], Q[:, iq]))))
        else:
            series += [_Series(name, f"{safe_name(name)}[{k}]", Q[:, iq + k]) for k in range(joint.nq)]
    return series, base, root


def _series_from_metadata(
    trajectory: Trajectory, Q: np.ndarray
) -> tuple[list[_Series], np.ndarray | None, str | None] | None:
    """Series named from the metadata when every joint has one coordinate (besides a free-flyer), else None."""
    info = trajectory.metadata.get("robot")
    if not isinstance(info, dict):
        return None
    joint_names, dof_names = info.get("joint_names"), info.get("dof_names")
    if not isinstance(joint_names, list) or not isinstance(dof_names, list):
        return None
    floating = bool(info.get("floating_base"))
    root = str(joint_names[0]) if floating and joint_names else None
    names = [str(n) for n in (joint_names[1:] if floating else joint_names)]
    offset = 7 if floating else 0
    if Q.ndim != 2 or Q.shape[1] != offset + len(names) or len(dof_names) != (6 if floating else 0) + len(names):
        return None
    series = [_Series(name, safe_name(name), Q[:, offset + k]) for k, name in enumerate(names)]
    return series, (Q[:, :3] if floating else None), root


def _title(trajectory: Trajectory, robot: Robot | None) -> str:
    meta = trajectory.metadata
    name = robot.name if robot is not None else (meta.get("robot") or {}).get("name", "trajectory")
    parts = [safe_name(name)]  # names from files: no control characters in a figure either
    if meta.get("integrator"):
        parts.append(str(meta["integrator"]))
    dt = (meta.get("options") or {}).get("dt")
    if dt:
        parts.append(f"dt {dt:g} s")
    return ", ".join(parts)
