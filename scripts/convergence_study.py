"""Convergence study: the observed order of every integrator on arms, floating legged robots and a pendulum.

For each robot, a seeded random state is simulated for DURATION seconds by every registered integrator over a
ladder of steps (1e-3 s included). The error of the final state, max(‖q ⊖ q_ref‖∞, ‖v − v_ref‖∞) in the
tangent space, is measured against RK4 at a step 8x finer than the finest rung (its own error is estimated by
Richardson extrapolation and printed), and the observed order is the least-squares slope of log(error) against
log(dt) over the finest rungs that stand clear of the reference's error. Adaptive pairs are run at fixed steps
with their propagating weights (their step control is not what an order against dt measures).

Writes docs/convergence.md (tables) and docs/convergence.png (log-log error against dt).

Usage: .venv/bin/python scripts/convergence_study.py [--duration 0.5] [--robots ur5,panda] [--out-dir docs]
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib
import matplotlib.ticker
import numpy as np

import multibody_sim as ms

matplotlib.use("Agg")  # files only, no display
import matplotlib.pyplot as plt  # noqa: E402 (the backend must be chosen first)

# (catalog name, floating_base, base spin [rad/s]): the floating robots tumble while they fall, so the
# free-flyer's rotation (where naive Lie-group stages would lose order) takes part.
ROBOTS = [
    ("ur5", None, 0.0),
    ("panda", None, 0.0),
    ("solo12", True, 5.0),
    ("talos", True, 3.0),
    ("double_pendulum", None, 0.0),
]
LADDER = tuple(1e-3 * 2.0**j for j in (3, 2, 1, 0, -1, -2, -3))  # 8 ms ... 0.125 ms, 1 ms included
REFERENCE_REFINEMENT = 8  # the reference step is the finest rung / 8
FIT_POINTS = 3  # the order is fitted on the finest rungs: coarse ones can be pre-asymptotic
# Round-off: the reference takes 3.2e4 steps on states of size ~10 (falling robots reach ~5 m/s), so its
# accumulated round-off reaches ~1e-12 (dp54's errors stall at 2e-12 on solo12): rungs below 3e-11 are not fitted.
ROUND_OFF_FLOOR = 3e-11
SEED = 20240611


@dataclass
class MethodResult:
    """One integrator on one robot."""

    name: str
    order: int
    errors: list[float] = field(default_factory=list)  # per rung of LADDER; nan when the run diverged
    observed: float = math.nan
    error_at_1ms: float = math.nan
    energy_error_at_1ms: float = math.nan
    wall_at_1ms: float = math.nan
    note: str = ""


def initial_state(robot: ms.Robot, spin: float) -> tuple[np.ndarray, np.ndarray]:
    """A seeded random configuration, velocities in [-1, 1]; a floating base spins at `spin` rad/s."""
    rng = np.random.default_rng(SEED)
    q0 = robot.random_configuration(rng)
    v0 = rng.uniform(-1.0, 1.0, robot.nv)
    if robot.floating_base:
        axis = rng.normal(size=3)
        v0[3:6] = spin * axis / np.linalg.norm(axis)
    return q0, v0


def error_floor(ref_error: float) -> float:
    """Errors below this say nothing about the method: within 30x the reference's truncation error (which
    would bend the slope by > 0.05) or near round-off."""
    return max(30 * ref_error, ROUND_OFF_FLOOR)


def state_error(robot: ms.Robot, q: np.ndarray, v: np.ndarray, q_ref: np.ndarray, v_ref: np.ndarray) -> float:
    """max(‖q ⊖ q_ref‖∞, ‖v − v_ref‖∞) in the tangent space."""
    return max(float(np.abs(robot.difference(q_ref, q)).max()), float(np.abs(v - v_ref).max()))


def fixed_step_methods() -> list[tuple[ms.Integrator, str]]:
    """Every registered integrator as a fixed-step method, with a note for the adaptive ones."""
    methods = []
    for name, method in ms.INTEGRATORS.items():
        if not method.adaptive:
            methods.append((method, ""))
        elif isinstance(method, ms.ExplicitRungeKutta):
            fixed = ms.ExplicitRungeKutta(name, method.tableau, f"{name} at fixed steps")
            methods.append((fixed, "adaptive pair, run at fixed steps"))
    return methods


def study_robot(name: str, floating_base: bool | None, spin: float, duration: float) -> tuple[dict, list]:
    """Reference and every method's ladder on one robot."""
    robot = ms.load_robot(name, floating_base=floating_base)
    q0, v0 = initial_state(robot, spin)
    ref_dt = LADDER[-1] / REFERENCE_REFINEMENT
    start = time.perf_counter()
    fine = ms.simulate(robot, q0, v0, duration=duration, dt=ref_dt, output_dt=duration)
    coarse = ms.simulate(robot, q0, v0, duration=duration, dt=2 * ref_dt, output_dt=duration)
    q_ref, v_ref = fine.q[-1], fine.v[-1]
    ref_error = state_error(robot, coarse.q[-1], coarse.v[-1], q_ref, v_ref) / 15  # Richardson, order 4
    info = {
        "robot": robot,
        "ref_dt": ref_dt,
        "ref_error": ref_error,
        "ref_wall": time.perf_counter() - start,
        "energy_drop": float(fine.potential_energy[0] - fine.potential_energy[-1]),
        "kinetic_end": float(fine.kinetic_energy[-1]),
    }
    floor = error_floor(ref_error)
    results = []
    for method, note in fixed_step_methods():
        result = MethodResult(method.name, method.order, note=note)
        try:
            method.check_system(robot)
        except ms.InvalidArgumentError as exc:
            result.note = f"refuses this robot: {str(exc).split(';')[0]}"
            results.append(result)
            continue
        for dt in LADDER:
            t0 = time.perf_counter()
            try:
                traj = ms.simulate(robot, q0, v0, duration=duration, dt=dt, integrator=method)
            except ms.SimulationError as exc:
                result.errors.append(math.nan)
                if not result.note:
                    result.note = f"{exc.status} at dt = {dt:g} s"
                continue
            result.errors.append(state_error(robot, traj.q[-1], traj.v[-1], q_ref, v_ref))
            if math.isclose(dt, 1e-3):
                result.error_at_1ms = result.errors[-1]
                result.energy_error_at_1ms = traj.max_abs_energy_error
                result.wall_at_1ms = time.perf_counter() - t0
        usable = [(dt, e) for dt, e in zip(LADDER, result.errors, strict=True) if math.isfinite(e) and e > floor]
        usable = usable[-FIT_POINTS:]
        if len(usable) >= 3:
            dts, errors = zip(*usable, strict=True)
            result.observed = float(np.polyfit(np.log(dts), np.log(errors), 1)[0])
        elif not result.note:
            result.note = "too few rungs above the error floor to fit"
        if math.isfinite(result.observed) and abs(result.observed - result.order) > 0.3:
            fitted = ", ".join(f"{dt * 1e3:g}" for dt, _ in usable)
            result.note = "; ".join(
                filter(None, [result.note, f"off its order: fitted on {fitted} ms, see the errors below"])
            )
        results.append(result)
    return info, results


def write_markdown(path: Path, duration: float, studies: list[tuple[str, dict, list[MethodResult]]]) -> None:
    lines = [
        "# Convergence study",
        "",
        "Generated by `scripts/convergence_study.py`; do not edit by hand.",
        "",
        f"Each robot starts from a seeded random state (seed {SEED}; floating bases also spin) and moves freely for "
        f"{duration:g} s with no torques and the URDF's joint damping (floating robots fall: there is no contact). "
        f"Steps: {', '.join(f'{dt * 1e3:g}' for dt in LADDER)} ms. Error: max(‖q ⊖ q_ref‖∞, ‖v − v_ref‖∞) at the "
        "final time in the tangent space [rad, m, rad/s, m/s], against RK4 at the finest step / "
        f"{REFERENCE_REFINEMENT}. Observed order: least-squares slope of log(error) against log(dt) over the "
        f"finest {FIT_POINTS} rungs whose error stands clear of the error floor (30x the reference's "
        f"Richardson-estimated error, and at least {ROUND_OFF_FLOOR:g} for round-off). "
        "`max |energy_error|` is H − H(0) − work + dissipated over the 1 ms run: a consistency check, zero for the "
        "exact solution. Adaptive pairs are run at fixed steps with their propagating weights.",
        "",
    ]
    for name, info, results in studies:
        robot = info["robot"]
        base = "floating base" if robot.floating_base else "fixed base"
        lines += [
            f"## {name} (nq {robot.nq}, nv {robot.nv}, {base})",
            "",
            f"Reference: RK4 at dt = {info['ref_dt'] * 1e6:g} µs, estimated error {info['ref_error']:.1e}; "
            f"kinetic energy at the end {info['kinetic_end']:.3g} J, "
            f"potential energy lost {info['energy_drop']:.3g} J.",
            "",
            "| integrator | order | observed order | error at dt = 1 ms | max \\|energy_error\\| at 1 ms [J] "
            "| wall time at 1 ms [s] | note |",
            "|---|---:|---:|---:|---:|---:|---|",
        ]
        for r in results:
            lines.append(
                f"| {r.name} | {r.order} | {_fmt(r.observed, '.2f')} | {_fmt(r.error_at_1ms, '.2e')} | "
                f"{_fmt(r.energy_error_at_1ms, '.2e')} | {_fmt(r.wall_at_1ms, '.2f')} | {r.note} |"
            )
        lines += [
            "",
            f"Final-state error per step (floor {error_floor(info['ref_error']):.0e}; — diverged or refused):",
            "",
            "| integrator | " + " | ".join(f"{dt * 1e3:g} ms" for dt in LADDER) + " |",
            "|---|" + "---:|" * len(LADDER),
        ]
        for r in results:
            cells = [_fmt(e, ".1e") for e in r.errors] or ["—"] * len(LADDER)
            lines.append(f"| {r.name} | " + " | ".join(cells) + " |")
        lines.append("")
    lines += ["![error against dt](convergence.png)", ""]
    path.write_text("\n".join(lines))


def _fmt(value: float, spec: str) -> str:
    return format(value, spec) if math.isfinite(value) else "—"


def plot(path: Path, studies: list[tuple[str, dict, list[MethodResult]]]) -> None:
    n = len(studies)
    cols = min(n, 3)
    rows = math.ceil(n / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(5.2 * cols, 4.2 * rows), squeeze=False)
    dts = np.array(LADDER)
    for ax, (name, info, results) in zip(axes.flat, studies, strict=False):
        for r in results:
            errors = np.array(r.errors if r.errors else [math.nan] * len(LADDER))
            if np.isfinite(errors).any():
                label = f"{r.name} (p={r.order}, obs {_fmt(r.observed, '.2f')})"
                ax.loglog(dts, errors, "o-", ms=3, label=label)
        ax.axhline(error_floor(info["ref_error"]), color="grey", ls=":", lw=1)
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())  # decade labels only: no overlap
        ax.set_title(name)
        ax.set_xlabel("dt [s]")
        ax.set_ylabel("final-state error")
        ax.grid(True, which="both", alpha=0.3)
        ax.legend(fontsize=6)
    for ax in list(axes.flat)[n:]:
        ax.axis("off")
    fig.suptitle("Final-state error against step (dotted: the error floor below which rungs are not fitted)")
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=0.5, help="simulated time per run [s]")
    parser.add_argument("--robots", default=",".join(r[0] for r in ROBOTS), help="comma-separated subset")
    parser.add_argument("--out-dir", type=Path, default=Path(__file__).resolve().parents[1] / "docs")
    args = parser.parse_args(argv)
    wanted = args.robots.split(",")
    studies = []
    start = time.perf_counter()
    for name, floating_base, spin in ROBOTS:
        if name not in wanted:
            continue
        t0 = time.perf_counter()
        info, results = study_robot(name, floating_base, spin, args.duration)
        studies.append((name, info, results))
        summary = ", ".join(f"{r.name} {_fmt(r.observed, '.2f')}" for r in results)
        print(f"{name}: {summary} ({time.perf_counter() - t0:.1f} s)", flush=True)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    write_markdown(args.out_dir / "convergence.md", args.duration, studies)
    plot(args.out_dir / "convergence.png", studies)
    print(f"wrote {args.out_dir / 'convergence.md'} and convergence.png in {time.perf_counter() - start:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
