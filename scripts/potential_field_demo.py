"""Potential-field demo: the planar point robot among obstacles, a symmetric local minimum, and an arm's end effector.

Three runs of multibody_sim.PotentialField, each drawn over the potential it follows:

1. point_robot through a field of circular obstacles, start to goal (path over the contours of U);
2. point_robot with one obstacle dead ahead on the line of symmetry: without escapes it stalls where repulsion
   cancels the pull (the equilibrium is computed independently and marked); with escapes the stall is detected
   and a seeded random push sends it round;
3. ur5's tool0 to a goal point past a spherical obstacle: a task-space field mapped to the joints by the frame
   Jacobian transpose, with joint damping and gravity compensation (path projected on two planes, and the
   distance to the goal over time).

Writes docs/potential_field.md and docs/potential_field_{point,local_minimum,arm}.png.

Usage: .venv/bin/python scripts/potential_field_demo.py [--out-dir docs]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import matplotlib
import numpy as np
from scipy.optimize import brentq

import multibody_sim as ms

matplotlib.use("Agg")  # files only, no display
import matplotlib.pyplot as plt  # noqa: E402 (the backend must be chosen first)
from matplotlib.patches import Circle  # noqa: E402

DT = 5e-3  # the puck's dynamics are slow (ω ≈ 3 rad/s, repulsion stiffness < 200 N/m where it goes): 5 ms is ample
START, GOAL = np.array([-3.5, -0.6]), np.array([3.5, 0.6])
OBSTACLES = [((-1.8, -0.4), 0.6), ((-0.3, 0.9), 0.55), ((0.6, -0.7), 0.5), ((2.2, 0.3), 0.45)]
ARM_START = np.array([0.0, -1.2, 1.4, -0.6, 1.2, 0.5])
ARM_MOVE = np.array([-0.3, 0.35, 0.15])  # goal = tool0 at the start + this [m]
ARM_RADIUS = 0.08


def contour_potential(ax, field: ms.PotentialField, xlim: tuple[float, float], ylim: tuple[float, float]) -> None:
    """Filled contours of U over the plane (clipped: it is infinite inside obstacles)."""
    xs, ys = np.linspace(*xlim, 400), np.linspace(*ylim, 300)
    X, Y = np.meshgrid(xs, ys)
    U = field.potential(np.stack([X, Y], axis=-1))
    cap = np.nanpercentile(U[np.isfinite(U)], 97)
    U = np.minimum(np.where(np.isfinite(U), U, cap), cap)
    filled = ax.contourf(X, Y, U, levels=30, cmap="viridis")
    ax.contour(X, Y, U, levels=30, colors="k", linewidths=0.2, alpha=0.5)
    plt.colorbar(filled, ax=ax, label="U [J] (clipped)")
    for center, radius in zip(field.obstacle_centers, field.obstacle_radii, strict=True):
        ax.add_patch(Circle(center, radius, color="0.25", zorder=3))
        ax.add_patch(Circle(center, radius + field.influence, fill=False, ls=":", color="w", lw=0.8, zorder=3))
    ax.set_aspect("equal")
    ax.set_xlim(*xlim)
    ax.set_ylim(*ylim)
    ax.set_xlabel("x [m]")
    ax.set_ylabel("y [m]")


def clearance(points: np.ndarray, field: ms.PotentialField) -> float:
    """Smallest distance from any point to any obstacle surface [m]."""
    offsets = points[:, None, :] - field.obstacle_centers[None]
    return float((np.linalg.norm(offsets, axis=-1) - field.obstacle_radii).min())


def run(robot: ms.Robot, field: ms.PotentialField, q0: np.ndarray, duration: float, dt: float) -> dict:
    started = time.perf_counter()
    traj = ms.simulate(robot, q0, np.zeros(robot.nv), duration=duration, dt=dt, controller=field)
    wall = time.perf_counter() - started
    path = traj.q if field.frame is None else np.array([field.position(q) for q in traj.q])
    distance = np.linalg.norm(path - field.goal, axis=1)
    arrived = np.flatnonzero(distance <= field.goal_tolerance)
    return {
        "traj": traj,
        "path": path,
        "distance": distance,
        "arrival": float(traj.t[arrived[0]]) if len(arrived) else float("nan"),
        "clearance": clearance(path, field),
        "wall": wall,
        "saturated": traj.stats.get("saturated_controls", 0),
        "max_tau": float(np.abs(traj.tau).max()),
    }


def point_robot_figure(puck: ms.Robot, out: Path) -> tuple[ms.PotentialField, dict]:
    field = ms.PotentialField(puck, GOAL, obstacles=OBSTACLES)
    result = run(puck, field, START, 25.0, DT)
    fig, ax = plt.subplots(figsize=(10, 4.6))
    contour_potential(ax, field, (-4.5, 4.5), (-2.2, 2.2))
    path = result["path"]
    ax.plot(path[:, 0], path[:, 1], color="tab:red", lw=2, label="path", zorder=4)
    ax.plot(*START, "o", color="w", mec="k", ms=8, label="start", zorder=5)
    ax.plot(*GOAL, "*", color="gold", mec="k", ms=14, label="goal", zorder=5)
    for event in field.local_minima:
        ax.plot(*event.position, "X", color="tab:orange", mec="k", ms=10, zorder=5)
    ax.set_title(
        f"point_robot: potential field around {len(OBSTACLES)} obstacles (dotted: influence), "
        f"goal reached at t = {result['arrival']:.2f} s"
    )
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return field, result


def axis_equilibrium(field: ms.PotentialField, radius: float) -> float:
    """x on the symmetry line where the constant pull k dc equals the repulsion k_rep (1/ρ − 1/ρ0)/ρ²."""
    pull = field.k_attract * field.conic_distance
    rho = brentq(
        lambda r: field.k_repulse * (1 / r - 1 / field.influence) / r**2 - pull, 1e-3, field.influence * (1 - 1e-9)
    )
    return -(radius + rho)


def local_minimum_figure(puck: ms.Robot, out: Path) -> dict:
    obstacle = [((0.0, 0.0), 0.5)]
    start, goal = np.array([-2.0, 0.0]), np.array([2.0, 0.0])
    stuck_field = ms.PotentialField(puck, goal, obstacles=obstacle, escape=False)
    stuck = run(puck, stuck_field, start, 12.0, DT)
    free_field = ms.PotentialField(puck, goal, obstacles=obstacle, seed=0)
    free = run(puck, free_field, start, 12.0, DT)
    x_eq = axis_equilibrium(stuck_field, 0.5)
    fig, ax = plt.subplots(figsize=(10, 4.2))
    contour_potential(ax, free_field, (-2.5, 2.5), (-1.3, 1.3))
    ax.plot(stuck["path"][:, 0], stuck["path"][:, 1], color="tab:orange", lw=3, label="escape off: stalls")
    ax.plot(free["path"][:, 0], free["path"][:, 1], color="tab:red", lw=1.8, label="escape on (seed 0)")
    ax.plot(x_eq, 0.0, "|", color="w", ms=22, mew=2, label="equilibrium k·dc = repulsion (brentq)")
    for event in free_field.local_minima:
        ax.annotate(
            "",
            xy=event.position + 0.06 * event.push,
            xytext=event.position,
            arrowprops={"arrowstyle": "->", "color": "w", "lw": 2},
            zorder=6,
        )
        ax.plot(*event.position, "X", color="tab:orange", mec="k", ms=10, zorder=6)
    ax.plot(*start, "o", color="w", mec="k", ms=8, zorder=5)
    ax.plot(*goal, "*", color="gold", mec="k", ms=14, zorder=5)
    ax.set_title("symmetric local minimum: detected after a 0.5 s stall, escaped by a seeded random push (arrow)")
    ax.legend(loc="lower right", fontsize=8)
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return {"stuck": stuck, "stuck_field": stuck_field, "free": free, "free_field": free_field, "x_eq": x_eq}


def arm_figure(ur5: ms.Robot, out: Path) -> tuple[ms.PotentialField, dict, np.ndarray]:
    probe = ms.PotentialField(ur5, np.zeros(3), frame="tool0")
    start = probe.position(ARM_START)
    goal = start + ARM_MOVE
    center = (start + goal) / 2 + np.array([0.05, 0.0, 0.0])
    field = ms.PotentialField(
        ur5,
        goal,
        frame="tool0",
        obstacles=[(center, ARM_RADIUS)],
        k_attract=100.0,
        conic_distance=0.3,
        k_repulse=0.01,
        influence=0.1,  # the start lies just outside it
    )
    result = run(ur5, field, ARM_START, 5.0, 2e-3)
    # The straight line from start to goal passes through the sphere: the field has to go round it.
    line = start + np.linspace(0, 1, 200)[:, None] * (goal - start)
    line_clearance = float((np.linalg.norm(line - center, axis=1) - ARM_RADIUS).min())
    path = result["path"]
    fig, axes = plt.subplots(1, 3, figsize=(14, 4.4))
    for ax, (i, j), title in zip(axes[:2], [(0, 1), (0, 2)], ["top view (x, y)", "side view (x, z)"], strict=True):
        ax.plot(line[:, i], line[:, j], "--", color="0.5", lw=1, label="straight line")
        ax.plot(path[:, i], path[:, j], color="tab:red", lw=2, label="tool0 path")
        ax.add_patch(Circle((center[i], center[j]), ARM_RADIUS, color="0.25", label="obstacle"))
        ax.add_patch(Circle((center[i], center[j]), ARM_RADIUS + field.influence, fill=False, ls=":", color="0.4"))
        ax.plot(start[i], start[j], "o", color="w", mec="k", ms=8, label="start")
        ax.plot(goal[i], goal[j], "*", color="gold", mec="k", ms=14, label="goal")
        ax.set_aspect("equal")
        ax.set_xlabel("xyz"[i] + " [m]")
        ax.set_ylabel("xyz"[j] + " [m]")
        ax.set_title(title)
    axes[0].legend(fontsize=7, loc="best")
    t = result["traj"].t
    axes[2].semilogy(t, result["distance"], color="tab:red", label="|tool0 − goal|")
    rho = np.linalg.norm(path - center, axis=1) - ARM_RADIUS
    axes[2].semilogy(t, rho, color="0.3", label="distance to the sphere's surface")
    axes[2].axhline(field.goal_tolerance, ls=":", color="k", lw=0.8, label="goal tolerance")
    axes[2].set_xlabel("t [s]")
    axes[2].set_ylabel("[m]")
    axes[2].legend(fontsize=7)
    axes[2].set_title("distances")
    fig.suptitle("ur5: task-space potential field on tool0 (Jᵀ F, LOCAL_WORLD_ALIGNED) + joint damping + g(q)")
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return field, result, np.array([line_clearance, *start, *goal, *center])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out-dir", default="docs", help="folder for the report and figures (default: docs)")
    args = parser.parse_args()
    out = Path(args.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    puck = ms.load_robot("point_robot")
    ur5 = ms.load_robot("ur5")

    field, point = point_robot_figure(puck, out / "potential_field_point.png")
    trap = local_minimum_figure(puck, out / "potential_field_local_minimum.png")
    arm_field, arm, geometry = arm_figure(ur5, out / "potential_field_arm.png")
    line_clearance, start, goal, center = geometry[0], geometry[1:4], geometry[4:7], geometry[7:10]

    stuck, free, free_field = trap["stuck"], trap["free"], trap["free_field"]
    [stall] = trap["stuck_field"].local_minima
    pushes = free_field.local_minima
    fmt = ", ".join
    lines = [
        "# Potential-field controller",
        "",
        "Generated by `.venv/bin/python scripts/potential_field_demo.py` (multibody_sim.PotentialField; RK4, the",
        "controller called every step).",
        "",
        "The robot follows the negative gradient of U = U_att + U_rep: U_att = ½ k d² up to `conic_distance`, then",
        "linear (a constant pull k·dc); U_rep = Σ ½ k_rep (1/ρ − 1/ρ0)² within ρ0 (`influence`) of each obstacle's",
        "surface, ρ the distance to that surface. Joint damping (default: critical per joint) and gravity",
        "compensation are added. A local minimum is declared after `stall_time` = 0.5 s slow (< 2 cm/s), far from the",
        "goal, with the net field force below 10 % of the pull; a seeded random push (twice the largest pull, 1 s)",
        "then breaks it.",
        "",
        "## Point robot among obstacles",
        "",
        "![point robot](potential_field_point.png)",
        "",
        f"`point_robot` (a 1 kg puck on prismatic x, y joints) from {START.tolist()} to {GOAL.tolist()} among "
        f"{len(OBSTACLES)} circles, default gains (k_attract 10 N/m, conic_distance 0.5 m, k_repulse 0.1 N·m, "
        f"influence 0.5 m), dt {DT * 1e3:g} ms:",
        "",
        "| | value |",
        "|---|---|",
        f"| goal reached (within {field.goal_tolerance:g} m) at | {point['arrival']:.2f} s |",
        f"| final distance to the goal | {point['distance'][-1]:.2e} m |",
        f"| closest approach to an obstacle's surface | {point['clearance']:.3f} m |",
        f"| local minima detected | {len(field.local_minima)} |",
        f"| largest force / effort limit (20 N) | {point['max_tau']:.2f} N (saturated calls: {point['saturated']}) |",
        f"| wall time, {len(point['traj'].t) - 1} steps | {point['wall']:.2f} s |",
        "",
        "## A symmetric local minimum",
        "",
        "![local minimum](potential_field_local_minimum.png)",
        "",
        "One circle (radius 0.5 m) centred on the line from (−2, 0) to (2, 0). On that line the repulsion points",
        "straight back, so the robot stops where it balances the pull: a saddle of U that a gradient follower never",
        "leaves (y stays exactly 0 in floating point). The equilibrium, solved independently with brentq from",
        f"k·dc = k_rep (1/ρ − 1/ρ0)/ρ², is x = {trap['x_eq']:.4f} m.",
        "",
        "| | escape off | escape on (seed 0) |",
        "|---|---|---|",
        f"| final position | ({stuck['path'][-1][0]:.4f}, {stuck['path'][-1][1]:.1g}) | "
        f"({free['path'][-1][0]:.4f}, {free['path'][-1][1]:.1e}) |",
        f"| local minima detected (t) | 1 ({stall.t:.2f} s at x = {stall.position[0]:.4f}) | "
        f"{len(pushes)} ({fmt(f'{e.t:.2f} s' for e in pushes)}) |",
        f"| goal reached at | never (distance {stuck['distance'][-1]:.2f} m) | {free['arrival']:.2f} s |",
        f"| closest approach to the surface | {stuck['clearance']:.3f} m | {free['clearance']:.3f} m |",
        "",
        "Runs are deterministic: the pushes' directions come from `np.random.default_rng(seed)`, reseeded by",
        "`reset()` (and when a reused controller sees time go back, i.e. a new run).",
        "",
        "## An arm's end effector",
        "",
        "![arm](potential_field_arm.png)",
        "",
        f"`ur5`, field on frame `tool0` (k_attract 100 N/m, conic_distance 0.3 m, k_repulse 0.01 N·m, influence "
        f"0.1 m), from tool0 at ({fmt(f'{c:.3f}' for c in start)}) m to ({fmt(f'{c:.3f}' for c in goal)}) m, a "
        f"sphere of radius {ARM_RADIUS} m at ({fmt(f'{c:.3f}' for c in center)}) m: the straight line would pass "
        f"{-line_clearance:.3f} m inside it. Torques tau = Jᵀ(−∇U) − Kd v + g(q), J the position rows of "
        "`pin.computeFrameJacobian(..., LOCAL_WORLD_ALIGNED)`, dt 2 ms:",
        "",
        "| | value |",
        "|---|---|",
        f"| goal reached (within {arm_field.goal_tolerance:g} m) at | {arm['arrival']:.2f} s |",
        f"| final distance to the goal | {arm['distance'][-1]:.2e} m |",
        f"| closest approach to the sphere's surface | {arm['clearance']:.3f} m |",
        f"| largest joint torque | {arm['max_tau']:.1f} N·m (saturated calls: {arm['saturated']}) |",
        f"| wall time, {len(arm['traj'].t) - 1} steps | {arm['wall']:.2f} s |",
        "",
    ]
    (out / "potential_field.md").write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
