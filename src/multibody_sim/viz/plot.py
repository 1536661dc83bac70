"""Plots of a trajectory: the energy ledger and the joint positions against time (matplotlib, no display needed)."""

from __future__ import annotations

import io
import os
from pathlib import Path
from typing import Any

import numpy as np

from ..robot import Robot
from ..trajectory import Trajectory, write_atomically
from ._deps import require

_MAX_LEGEND = 12  # more lines than this: a legend would hide the plot


def plot_trajectory(
    trajectory: Trajectory,
    path: str | os.PathLike[str] | None = None,
    *,
    robot: Robot | None = None,
    title: str | None = None,
    dpi: int = 110,
) -> Any:
    """Plot a trajectory: energies, energy_error and joint positions against time.

    Panels, top to bottom: kinetic T, potential V and total H = T + V energy, the work put in and the energy
    dissipated [J]; energy_error = H - H(0) - work + dissipated [J]; the joint positions (one line per joint
    coordinate: revolute [rad], prismatic [m], continuous joints as their angle); for a floating base, the
    base position x, y, z [m]. Uses matplotlib's Agg renderer (no display, no pyplot state).

    Args:
        trajectory: the trajectory to plot.
        path: write a PNG there (atomically); None only returns the figure.
        robot: its robot, for joint names and types; None reads names from the metadata and treats every
            coordinate as a joint position (a free-flyer's 7 base coordinates are then recognised by nq - nv).
        title: the figure title (default: robot name, integrator and step).
        dpi: resolution of the PNG.

    Returns:
        The matplotlib Figure.
    """
    figure_module = require("matplotlib.figure", "plots")
    t = np.asarray(trajectory.t, dtype=float)
    joints, base = _joint_series(trajectory, robot)
    panels = 3 + (base is not None)
    fig = figure_module.Figure(figsize=(9.0, 2.4 * panels + 0.6), dpi=dpi, layout="constrained")
    axes = fig.subplots(panels, 1, sharex=True)
    energy, error, positions = axes[0], axes[1], axes[2]
    energy.plot(t, trajectory.kinetic_energy, label="kinetic T")
    energy.plot(t, trajectory.potential_energy, label="potential V")
    energy.plot(t, trajectory.total_energy, label="total H = T + V", linewidth=2.0)
    energy.plot(t, trajectory.work, label="work (in)", linestyle="--")
    energy.plot(t, trajectory.dissipated, label="dissipated (out)", linestyle="--")
    energy.set_ylabel("energy [J]")
    energy.legend(loc="best", fontsize="small", ncols=3)
    error.plot(t, trajectory.energy_error, color="tab:red", label="energy_error")
    error.set_ylabel("energy_error [J]")
    error.set_title("H - H(0) - work + dissipated (zero for the exact solution)", fontsize="small")
    error.ticklabel_format(axis="y", style="sci", scilimits=(-3, 3))
    for name, values in joints:
        positions.plot(t, values, label=name)
    positions.set_ylabel("joint position [rad, m]")
    if 0 < len(joints) <= _MAX_LEGEND:
        positions.legend(loc="best", fontsize="x-small", ncols=2)
    if base is not None:
        axis = axes[3]
        for k, name in enumerate("xyz"):
            axis.plot(t, base[:, k], label=f"base {name}")
        axis.set_ylabel("base position [m]")
        axis.legend(loc="best", fontsize="small")
    for axis in axes:
        axis.grid(True, alpha=0.3)
    axes[-1].set_xlabel("time [s]")
    fig.suptitle(title or _title(trajectory, robot))
    if path is not None:
        target = Path(path)
        write_atomically(target, lambda f: fig.savefig(f, format="png"))
    return fig


def plot_png(trajectory: Trajectory, *, robot: Robot | None = None) -> bytes:
    """The plot_trajectory figure as PNG bytes."""
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


def _joint_series(
    trajectory: Trajectory, robot: Robot | None
) -> tuple[list[tuple[str, np.ndarray]], np.ndarray | None]:
    """(label, values) per joint coordinate, and the base position (n, 3) for a floating base (else None)."""
    Q = np.asarray(trajectory.q, dtype=float)
    if robot is not None:
        model = robot.model
        series: list[tuple[str, np.ndarray]] = []
        base = None
        for jid in range(1, model.njoints):
            joint = model.joints[jid]
            name, iq = model.names[jid], joint.idx_q
            short = joint.shortname()
            if "FreeFlyer" in short:
                base = Q[:, iq : iq + 3]
            elif joint.nq == 1:
                series.append((name, Q[:, iq]))
            elif joint.nq == 2 and joint.nv == 1:  # continuous: (cos, sin) -> angle, unwrapped
                series.append((name, np.unwrap(np.arctan2(Q[:, iq + 1], Q[:, iq]))))
            else:
                series += [(f"{name}[{k}]", Q[:, iq + k]) for k in range(joint.nq)]
        return series, base
    info = trajectory.metadata.get("robot", {}) if isinstance(trajectory.metadata.get("robot"), dict) else {}
    nv = np.asarray(trajectory.v).shape[1] if np.asarray(trajectory.v).ndim == 2 else Q.shape[1]
    floating = bool(info.get("floating_base")) and Q.shape[1] - nv == 1
    offset = 7 if floating else 0
    names = list(info.get("dof_names", []))[6 if floating else 0 :]
    series = []
    for k in range(offset, Q.shape[1]):
        label = (
            names[k - offset] if k - offset < len(names) and Q.shape[1] == nv + (1 if floating else 0) else f"q[{k}]"
        )
        series.append((label, Q[:, k]))
    return series, (Q[:, :3] if floating else None)


def _title(trajectory: Trajectory, robot: Robot | None) -> str:
    meta = trajectory.metadata
    name = robot.name if robot is not None else (meta.get("robot") or {}).get("name", "trajectory")
    parts = [str(name)]
    if meta.get("integrator"):
        parts.append(str(meta["integrator"]))
    dt = (meta.get("options") or {}).get("dt")
    if dt:
        parts.append(f"dt {dt:g} s")
    return ", ".join(parts)
