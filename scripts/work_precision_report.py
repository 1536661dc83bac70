"""Work-precision report: error against cost for every integrator on an arm, a legged robot, a humanoid and a stiff
arm, and for MuJoCo's integrators on the same URDFs, measured against the same reference.

For each system, a seeded random state (floating bases also spin; no torque, the URDF's damping) is simulated for
DURATION seconds by `multibody_sim.work_precision` (every integrator over its ladder; errors against a dp54
reference checked by refining it; cost = CPU time of the run). Then MuJoCo runs the same URDF from the same state
with its Euler, implicitfast and RK4 integrators over the same ladder of steps (`mj_step` in a Python loop;
contacts, limits and equality constraints off, armature and friction loss zeroed, joint damping set to ours), its
states mapped to Pinocchio's convention joint by joint (a free joint's quaternion is w-first in MuJoCo, its linear
velocity in the world frame) and measured against the same reference on the same sample grid.

Writes docs/work_precision.md, docs/work_precision_<system>.png (ours) and docs/work_precision_<system>_mujoco.png
(MuJoCo beside our rk4, dp54 and implicit_euler). MuJoCo is optional (a benchmark-only dependency): without it
those parts are skipped with a note. matplotlib is needed for the pictures.

Usage:
    .venv/bin/python scripts/work_precision_report.py [--duration 1] [--systems ur5,solo12,talos,stiff_arm]
        [--max-run-time 1] [--out-dir docs]
"""

from __future__ import annotations

import argparse
import datetime
import math
import os
import platform
import statistics
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import matplotlib
import numpy as np
import pinocchio as pin

import multibody_sim as ms
from multibody_sim import bench

sys.path.insert(0, str(Path(__file__).resolve().parent))
from mujoco_peer import StateMap, mujoco_model  # noqa: E402  (the shared MuJoCo peer)

matplotlib.use("Agg")  # files only, no display
import matplotlib.pyplot as plt  # noqa: E402 (the backend must be chosen first)

try:
    import mujoco
except ImportError:  # a benchmark-only dependency: the report says it was skipped
    mujoco = None

ROOT = Path(__file__).resolve().parent.parent
SEED = 20240611
ACCURACIES = (1e-2, 1e-4, 1e-6, 1e-8)


@dataclass(frozen=True)
class System:
    """A system of the report: catalog name, base, base spin [rad/s], and what it stands for."""

    name: str
    floating_base: bool | None
    spin: float
    kind: str
    note: str = ""  # what the numbers alone do not say (physics, not measurements)
    q0: tuple[float, ...] | None = None  # a fixed initial state (q0, zero velocity) instead of the seeded random one
    at_end: bool = False  # the error is the one at t = duration only (the sample grid is the whole run)


SYSTEMS = {
    "double_pendulum": System(
        "double_pendulum",
        None,
        0.0,
        "double pendulum released from q = (π/2, 0), v = 0: error at t = 1 s",
        q0=(math.pi / 2, 0.0),
        at_end=True,
    ),
    "ur5": System("ur5", None, 0.0, "arm, fixed base"),
    "panda": System("panda", None, 0.0, "arm, fixed base"),
    "solo12": System("solo12", True, 5.0, "legged robot, floating base"),
    "talos": System(
        "talos",
        True,
        3.0,
        "humanoid, floating base",
        note="""Its URDF damps light joints (up to 1 N·m·s/rad): those damped modes make it mildly stiff, so explicit
        adaptive methods are held near their stability limit (steps of a few ms) whatever their tolerance, and their
        cost hardly falls with a looser one (without the damping, `load_robot("talos", floating_base=True,
        damping=False)`, dp54 needs about a quarter of the evaluations at the same tolerance, 0.4 times as many to
        the same error). MuJoCo's Euler and implicitfast treat damping implicitly, but are first order. Taking the
        damping term linearly implicitly does not pay (scripts/damping_imex_study.py: J ≈ [[0, I], [0, −M⁻¹D]] with
        M from CRBA at each step's start, one factorization of M + hγD per step; evaluations to reach an error of
        1e-6 in the same step loop and controller): the Rosenbrock-W method ROS34PW2 (order 3) needs about 8100,
        the IMEX pairs ARK4(3)6L[2]SA and ARK5(4)8L[2]SA about 4000 and 4200, dp54 about 2100; to 1e-8,
        ARK5(4)8L[2]SA about 11900 against dp54's 3400. ROS34PW2's step count hardly changes with the damping, but
        its order (3) makes it the costliest. The ARK pairs' error estimate is carried by the damped joints'
        velocities, which relax quasi-statically (M⁻¹D's eigenvalues reach about 900 /s) and whose local error
        falls only about like h³ at the steps these methods take, not like h⁴ or h⁵ (order reduction: an ESDIRK's
        stage order is 2), so with the damping their step counts at a given tolerance grow 3.5–6 fold, as much as
        dp54's (3–4 fold), for accuracy instead of stability. Without the damping they would still need 1.3x
        (ARK5(4)8L[2]SA) to 2x (ARK4(3)6L[2]SA) dp54's evaluations to the same error.""",
    ),
    "g1": System("g1", True, 3.0, "humanoid, floating base"),
    "stiff_arm": System(
        "stiff_arm",
        None,
        0.0,
        "stiff arm: 10 g tip on an elbow damped at 100 N·m·s/rad",
        note="""The elbow's relative motion decays at about 4e4 /s: explicit methods are stable only below dt ≈ 2/4e4 =
        5e-5 s (RK4 2.8/4e4 ≈ 7e-5 s), and adaptive explicit ones are held at that step by stability whatever their
        tolerance. Implicit Euler damps the stiff mode at any step (L-stable); implicit midpoint and the variational
        integrator are A-stable but not L-stable: they keep the stiff mode oscillating, undamped, at coarse steps
        (hence their large errors there). MuJoCo's Euler and implicitfast integrate joint damping implicitly, which
        is exactly this system's stiffness.""",
    ),
}
DEFAULT_SYSTEMS = ("double_pendulum", "ur5", "solo12", "talos", "stiff_arm")
# Issue 15's accuracy-per-cost targets: (system, accuracy) -> the largest ratio of our cheapest explicit run's CPU time
# to MuJoCo's cheapest run reaching the same accuracy (on the double pendulum MuJoCo's RK4, elsewhere any of its
# integrators).
TARGETS = {
    ("double_pendulum", 1e-6): 0.6,
    ("double_pendulum", 1e-8): 0.3,
    **{(name, tol): 0.5 for name in ("ur5", "solo12", "talos") for tol in (1e-6, 1e-8)},
}
TARGET_MUJOCO = {"double_pendulum": ("RK4",)}  # MuJoCo integrators a target compares with (default: all)
ROUNDS = 11  # interleaved timing rounds of the target comparisons (median CPU time of each candidate)
RNG = np.random.default_rng(SEED)  # the rounds' orders
# Each side's candidates: the cheapest run of each method reaching the accuracy (by the study's timings), timed
# again, interleaved. One per method, not the cheapest few overall: a study timed under load can rank a method's
# runs by noise, and the few cheapest would then all be one method's.
MUJOCO_INTEGRATORS = ("Euler", "implicitfast", "RK4")
MUJOCO_EVALUATIONS = {"Euler": 1, "implicitfast": 1, "RK4": 4}  # forward-dynamics passes per step
DIVERGED_ERROR = 1e3
IMPORT_WARNINGS: list[str] = []  # MuJoCo's warnings while compiling the URDFs (the report lists them)
RUNTIME_WARNINGS: list[str] = []  # and while stepping (unstable runs: counted as diverged, not listed)


# ---- the state -------------------------------------------------------------------------------------------------
def initial_state(robot: ms.Robot, system: System) -> tuple[np.ndarray, np.ndarray]:
    """The system's fixed state, else a seeded random configuration within the limits, joint velocities in [-1, 1];
    a floating base spins at `system.spin`."""
    if system.q0 is not None:
        return np.array(system.q0), np.zeros(robot.nv)
    spin = system.spin
    rng = np.random.default_rng(SEED)
    q0 = robot.random_configuration(rng)
    v0 = rng.uniform(-1.0, 1.0, robot.nv)
    if robot.floating_base:
        axis = rng.normal(size=3)
        v0[3:6] = spin * axis / np.linalg.norm(axis)
    return q0, v0


# ---- MuJoCo on the same URDF ------------------------------------------------------------------------------------
@dataclass
class MujocoRun:
    integrator: str
    dt: float
    status: str
    error: float = math.nan
    cpu_time: float = math.nan
    evaluations: int = 0


@dataclass
class MujocoStudy:
    runs: list[MujocoRun] = field(default_factory=list)
    qacc_error: float = math.nan  # max |a_MuJoCo − a_Pinocchio| at the initial state
    qacc_scale: float = math.nan
    note: str = ""
    # (integrator, dt) -> (CPU time of the stepping loop [s], samples): one more run, as the study timed them
    rerun: Any = None


def mujoco_run(
    model: Any, data: Any, start_state: tuple[np.ndarray, np.ndarray], integrator: str, dt: float, duration: float,
    output_dt: float,
) -> tuple[float, list[tuple[np.ndarray, np.ndarray]]]:  # fmt: skip
    """One MuJoCo run from start_state = (qpos, qvel): the CPU time of its stepping loop [s] and its samples
    (qpos, qvel) every output_dt and at the end."""
    model.opt.integrator = int(getattr(mujoco.mjtIntegrator, f"mjINT_{integrator.upper()}"))
    model.opt.timestep = dt
    n_steps = math.ceil(duration / dt - 1e-9)
    every = round(output_dt / dt)
    mujoco.mj_resetData(model, data)
    data.qpos[:], data.qvel[:] = start_state
    samples = [(data.qpos.copy(), data.qvel.copy())]
    start = time.process_time()
    for k in range(1, n_steps + 1):
        mujoco.mj_step(model, data)
        if k % every == 0 or k == n_steps:
            samples.append((data.qpos.copy(), data.qvel.copy()))
    return time.process_time() - start, samples


def mujoco_study(robot: ms.Robot, result: ms.WorkPrecision, max_run_time: float) -> MujocoStudy:
    """MuJoCo's integrators over the study's ladder of steps, against the study's reference."""
    study = MujocoStudy()
    RUNTIME_WARNINGS.clear()
    model = mujoco_model(robot)
    IMPORT_WARNINGS.extend(RUNTIME_WARNINGS)  # what the importer said while compiling this URDF
    RUNTIME_WARNINGS.clear()
    states = StateMap(robot, model)
    states.set_damping(model)
    data = mujoco.MjData(model)
    q0, v0 = np.array(result.q0), np.array(result.v0)
    qpos0, qvel0 = states.to_mujoco(q0, v0)
    # The same dynamics: MuJoCo's accelerations at the initial state, mapped to Pinocchio's v̇.
    mujoco.mj_resetData(model, data)
    data.qpos[:], data.qvel[:] = qpos0, qvel0
    mujoco.mj_forward(model, data)
    a_pin = robot.forward_dynamics(q0, v0, np.zeros(robot.nv))
    a_mj = np.zeros(robot.nv)
    for kind, iq, iv, _, jv in states.joints:
        if kind == "free":
            x, y, z, w = q0[iq + 3 : iq + 7]
            rotation = pin.Quaternion(w, x, y, z).toRotationMatrix()
            v_lin, omega = v0[iv : iv + 3], v0[iv + 3 : iv + 6]
            a_mj[iv : iv + 3] = rotation.T @ data.qacc[jv : jv + 3] - np.cross(omega, v_lin)
            a_mj[iv + 3 : iv + 6] = data.qacc[jv + 3 : jv + 6]
        else:
            a_mj[iv] = data.qacc[jv]
    study.qacc_error = float(np.abs(a_mj - a_pin).max())
    study.qacc_scale = float(np.abs(a_pin).max())

    reference = result.reference
    assert reference is not None and reference.t is not None
    floor = max(result.settings["min_error"], bench.REFERENCE_MARGIN * reference.error)
    bad_qacc = int(mujoco.mjtWarning.mjWARN_BADQACC)
    study.rerun = lambda name, dt: mujoco_run(model, data, (qpos0, qvel0), name, dt, result.duration, result.output_dt)
    for name in MUJOCO_INTEGRATORS:
        per_step = math.nan
        for dt in result.settings["steps"]:
            n_steps = math.ceil(result.duration / dt - 1e-9)
            if per_step * n_steps > max_run_time:
                break
            times = []
            run = MujocoRun(name, dt, "completed", evaluations=MUJOCO_EVALUATIONS[name] * n_steps)
            for _ in range(3):  # repeated while short, as the study times ours: the median CPU time
                cpu, samples = study.rerun(name, dt)
                times.append(cpu)
                if sum(times) > bench.REPEAT_BELOW:
                    break
            run.cpu_time = statistics.median(times)
            finite = all(np.isfinite(p).all() and np.isfinite(v).all() for p, v in samples)
            worst = math.inf
            if finite and data.warning[bad_qacc].number == 0 and len(samples) == len(reference.t):
                worst = 0.0
                for (qpos, qvel), q_ref, v_ref in zip(samples, reference.q, reference.v, strict=True):
                    q, v = states.to_pinocchio(qpos, qvel)
                    worst = max(worst, float(np.abs(pin.difference(robot.model, q_ref, q)).max()))
                    worst = max(worst, float(np.abs(v - v_ref).max()))
            # MuJoCo resets the state on a bad acceleration and has no blow-up check of its own: a run it reset,
            # or whose state is 1e3 (rad, rad/s, m, m/s) off, diverged.
            if worst > DIVERGED_ERROR:
                run.status = "diverged"
                study.runs.append(run)
                continue
            per_step = run.cpu_time / n_steps
            run.error = worst
            study.runs.append(run)
            if worst < floor:
                break
    return study


def mujoco_orders(study: MujocoStudy, reference_error: float) -> dict[str, float]:
    """Observed orders of MuJoCo's integrators: slope over the finest 3 usable steps, as bench fits ours."""
    orders = {}
    for name in MUJOCO_INTEGRATORS:
        usable = [
            r
            for r in study.runs
            if r.integrator == name
            and r.status == "completed"
            and bench.REFERENCE_MARGIN * reference_error <= r.error < 0.1
        ][-bench.FIT_POINTS :]
        if len(usable) >= 2:
            orders[name] = float(np.polyfit(np.log([r.dt for r in usable]), np.log([r.error for r in usable]), 1)[0])
        else:
            orders[name] = math.nan
    return orders


def cheapest_mujoco(study: MujocoStudy, tolerance: float, reference_error: float) -> MujocoRun | None:
    meeting = [r for r in study.runs if r.status == "completed" and r.error + reference_error <= tolerance]
    return min(meeting, key=lambda r: r.cpu_time) if meeting else None


# ---- issue 15's targets: our cheapest explicit run against MuJoCo's cheapest, timed again in interleaved rounds ----
@dataclass
class TargetRow:
    system: str
    tolerance: float
    target: float  # the largest ratio ours / MuJoCo's that meets the target
    ours: bench.Measurement | None = None
    ours_cpu: float = math.nan  # median CPU time over the interleaved rounds [s]
    theirs: MujocoRun | None = None
    theirs_cpu: float = math.nan
    note: str = ""

    @property
    def ratio(self) -> float:
        return self.ours_cpu / self.theirs_cpu

    @property
    def met(self) -> bool:
        return bool(self.ratio <= self.target)


def cheapest_of_each(runs: Iterable[Any]) -> list[Any]:
    """The cheapest run (by its cpu_time) of each integrator among `runs`, cheapest first."""
    best: dict[str, Any] = {}
    for run in runs:
        if run.integrator not in best or run.cpu_time < best[run.integrator].cpu_time:
            best[run.integrator] = run
    return sorted(best.values(), key=lambda run: run.cpu_time)


def target_rows(
    name: str, robot: ms.Robot, result: ms.WorkPrecision, mj: MujocoStudy | None, rounds: int = ROUNDS
) -> list[TargetRow]:
    """Issue 15's accuracy-per-cost targets for this system: the cheapest run of each explicit method of ours and
    of each MuJoCo integrator (by the study's timings) that reaches each accuracy is timed again, ROUNDS rounds
    interleaved (each round runs every candidate once), and each side's least median CPU time is compared."""
    r = result.reference
    assert r is not None
    rows = []
    q0, v0 = np.array(result.q0), np.array(result.v0)
    for (system, tol), target in TARGETS.items():
        if system != name:
            continue
        row = TargetRow(name, tol, target)
        rows.append(row)
        ours = cheapest_of_each(
            m for m in result.measurements if m.completed and not ms.INTEGRATORS[m.integrator].implicit
            and m.error + r.error <= tol
        )  # fmt: skip
        allowed = TARGET_MUJOCO.get(name, MUJOCO_INTEGRATORS)
        theirs = cheapest_of_each(
            x for x in (mj.runs if mj else []) if x.integrator in allowed and x.status == "completed"
            and x.error + r.error <= tol
        )  # fmt: skip
        if not ours or not theirs or mj is None:
            row.note = "ours reached no such accuracy" if not ours else "MuJoCo reached no such accuracy"
            continue
        runs: list[tuple[Any, Callable[[], float]]] = []
        for m in ours:
            options = m.simulate_options()

            def simulate_once(options: dict[str, Any] = options) -> float:
                start = time.process_time()
                ms.simulate(robot, q0, v0, duration=result.duration, output_dt=result.output_dt, **options)
                return time.process_time() - start

            runs.append((m, simulate_once))
        for x in theirs:
            runs.append((x, lambda x=x: mj.rerun(x.integrator, x.dt)[0]))
        times: dict[int, list[float]] = {i: [] for i in range(len(runs))}
        order = list(range(len(runs)))
        for _ in range(rounds):  # a new order each round: no candidate always runs right after the same one
            RNG.shuffle(order)
            for i in order:
                runs[i][1]()  # run once untimed: the timed run finds its caches warm, as a loop of calls does
                times[i].append(runs[i][1]())
        medians = {i: statistics.median(t) for i, t in times.items()}
        best_ours = min(range(len(ours)), key=lambda i: medians[i])
        best_theirs = min(range(len(ours), len(runs)), key=lambda i: medians[i])
        row.ours, row.ours_cpu = ours[best_ours], medians[best_ours]
        row.theirs, row.theirs_cpu = theirs[best_theirs - len(ours)], medians[best_theirs]
    return rows


def targets_table(rows: list[TargetRow]) -> list[str]:
    """The targets as a Markdown table: accuracy, our cheapest and MuJoCo's with their CPU times, ratio, met."""
    cells = []
    for row in rows:
        if row.ours is None or row.theirs is None:
            cells.append([row.system, f"{row.tolerance:.0e}", "—", "—", "—", "—", "—", "—", f"≤ {row.target:g}",
                          f"not measured ({row.note})"])  # fmt: skip
            continue
        m, x = row.ours, row.theirs
        cells.append(
            [
                row.system,
                f"{row.tolerance:.0e}",
                f"{m.integrator}, {m.settings()} ({m.kernel or '?'}; error {m.error:.1e})",
                f"{row.ours_cpu * 1e3:.2f}",
                f"{x.integrator}, dt {x.dt:g} s (error {x.error:.1e})",
                f"{row.theirs_cpu * 1e3:.2f}",
                f"{row.ratio:.2f}",
                f"{row.ours_cpu / m.evaluations * 1e6:.2f} / {row.theirs_cpu / x.evaluations * 1e6:.2f}",
                f"≤ {row.target:g}",
                "**met**" if row.met else "**missed**",
            ]
        )
    return table(
        ["system", "accuracy", "ours: cheapest explicit run (kernel; error)", "CPU [ms]", "MuJoCo: cheapest run",
         "CPU [ms]", "ratio", "µs per evaluation (ours / MuJoCo)", "target", "result"],
        cells,
    )  # fmt: skip


def per_call_cost(rounds: int = 21) -> float:
    """simulate()'s fixed cost per call [s]: the median CPU time of a one-step rk4 run of the double pendulum."""
    robot = ms.load_robot("double_pendulum")
    times = []
    for _ in range(rounds):
        start = time.process_time()
        ms.simulate(robot, [0.1, 0.0], [0.0, 0.0], duration=1e-3, dt=1e-3, integrator="rk4")
        times.append(time.process_time() - start)
    return statistics.median(times)


# ---- pictures ------------------------------------------------------------------------------------------------------
def plot_mujoco(path: Path, result: ms.WorkPrecision, study: MujocoStudy) -> None:
    fig, ax = plt.subplots(figsize=(7.5, 5.2))
    for name, color in zip(MUJOCO_INTEGRATORS, ("tab:blue", "tab:green", "tab:red"), strict=True):
        done = [r for r in study.runs if r.integrator == name and r.status == "completed" and r.error > 0]
        if done:
            ax.loglog(
                [r.cpu_time for r in done], [r.error for r in done], "o-", color=color, ms=4, label=f"MuJoCo {name}"
            )
    for name, style in (("rk4", "s--"), ("dp54", "^:"), ("implicit_euler", "v-.")):
        done = [m for m in result.for_integrator(name) if m.completed and m.error > 0]
        if done:
            ax.loglog(
                [m.cpu_time for m in done], [m.error for m in done], style, color="grey", ms=3, label=f"ours: {name}"
            )
    if result.reference is not None and result.reference.error > 0:
        ax.axhline(result.reference.error, color="grey", ls=":", lw=1, label="reference's estimated error")
    ax.set_xlabel("CPU time of the run [s]")
    ax.set_ylabel("max error |(q ⊖ q_ref, v − v_ref)|∞")
    ax.set_title(f"{result.system}: MuJoCo's integrators (mj_step in Python) beside ours")
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


# ---- the report ----------------------------------------------------------------------------------------------------
def para(text: str) -> str:
    return " ".join(text.split())


def fmt(x: float, spec: str = ".1e") -> str:
    return format(x, spec) if isinstance(x, (int, float)) and math.isfinite(x) else "—"


def table(headers: list[str], rows: list[list[str]]) -> list[str]:
    lines = ["| " + " | ".join(headers) + " |", "|" + "---|" * len(headers)]
    lines += ["| " + " | ".join(row) + " |" for row in rows]
    return lines


def start_text(system: System, result: ms.WorkPrecision) -> str:
    """How the study starts, and where its error is measured."""
    if system.q0 is not None:
        start = f"From q0 = ({', '.join(f'{x:.6g}' for x in result.q0)}) rad at rest"
    else:
        start = "Seeded random state" + (f", base spinning at {system.spin:g} rad/s" if system.spin else "")
    if system.at_end:
        start += f"; the error is the one at t = {result.duration:g} s only (the runs record only their end)"
    return start


def section(name: str, system: System, robot: ms.Robot, result: ms.WorkPrecision, mj: MujocoStudy | None,
            elapsed: float) -> list[str]:  # fmt: skip
    r = result.reference
    assert r is not None
    lines = [
        f"## {name} ({system.kind}; nq {robot.nq}, nv {robot.nv})",
        "",
        para(f"""{start_text(system, result)}; no torque, the URDF's damping (max {robot.damping.max():g});
        {result.duration:g} s. Reference: {r.integrator} at rtol =
        atol = {r.rtol:.0e}, {r.evaluations} evaluations; against its refinement at {r.check_rtol:.0e} its estimated
        error is {r.error:.1e}. Study time {elapsed:.0f} s."""),
        "",
        "![work-precision](" + f"work_precision_{name}.png)",
        "",
        "Observed against theoretical order (fixed-step: slope against dt; adaptive: effective order against "
        "evaluations):",
        "",
    ]
    rows = []
    for integrator in result.integrators():
        fit = result.orders.get(integrator)
        points = result.for_integrator(integrator)
        done = [m for m in points if m.completed]
        failed = sorted({m.status for m in points if not m.completed})
        best = min(done, key=lambda m: m.error) if done else None
        at_1ms = next((m for m in done if not m.adaptive and math.isclose(m.dt, 1e-3)), None)
        rows.append(
            [
                integrator,
                str(fit.theoretical) if fit else "—",
                fmt(fit.observed, ".2f") if fit else "—",
                "**yes**" if fit and fit.mismatch else "",
                f"{best.error:.1e} ({best.settings()})" if best else "—",
                fmt(at_1ms.error) if at_1ms else "—",
                fmt(at_1ms.energy_error) if at_1ms else "—",
                "; ".join(
                    filter(
                        None,
                        [
                            ", ".join(failed) + (f": {points[0].message}" if "refused" in failed else ""),
                            fit.note if fit else "",
                        ],
                    )
                ),
            ]
        )
    lines += table(
        [
            "integrator",
            "order",
            "observed",
            "mismatch",
            "best error (at)",
            "error at 1 ms",
            "max \\|energy_error\\| at 1 ms [J]",
            "failed runs; notes",
        ],
        rows,
    )
    lines += [
        "",
        "Cheapest measured configuration per accuracy (CPU time of the run; error + reference's ≤ accuracy):",
        "",
    ]
    rows = []
    for tol in ACCURACIES:
        rec = ms.recommend(result, tol)
        rk4 = min(
            (m for m in result.for_integrator("rk4") if m.completed and m.error + r.error <= tol),
            key=lambda m: m.cpu_time,
            default=None,
        )
        mj_best = cheapest_mujoco(mj, tol, r.error) if mj else None
        rows.append(
            [
                f"{tol:.0e}",
                f"{rec.integrator}, {rec.settings()}" if rec else "none measured",
                f"{rec.error:.1e}" if rec else "—",
                f"{rec.cpu_time * 1e3:.1f}" if rec else "—",
                f"{rk4.settings()}, {rk4.cpu_time * 1e3:.1f} ms" if rk4 else "—",
                f"{mj_best.integrator}, dt {mj_best.dt:g} s, {mj_best.cpu_time * 1e3:.1f} ms" if mj_best else "—",
            ]
        )
    lines += table(
        ["accuracy", "recommended", "its error", "CPU [ms]", "rk4 at its cheapest", "MuJoCo at its cheapest"], rows
    )
    if mj is not None:
        orders = mujoco_orders(mj, r.error)
        # Both RK4s are the same method on the same equations: their errors at the same step should agree.
        ours_rk4 = {m.dt: m.error for m in result.for_integrator("rk4") if m.completed}
        ratios = [
            x.error / ours_rk4[x.dt]
            for x in mj.runs
            if x.integrator == "RK4" and x.status == "completed" and x.dt in ours_rk4
            and x.error > bench.REFERENCE_MARGIN * r.error and ours_rk4[x.dt] > bench.REFERENCE_MARGIN * r.error
        ]  # fmt: skip
        same = (
            f" At the steps both RK4s completed, MuJoCo's error is {min(ratios):.2f}–{max(ratios):.2f} times ours "
            "(the same method on the same equations)."
            if ratios
            else ""
        )
        lines += [
            "",
            para(f"""MuJoCo on the same URDF: accelerations at the initial state agree with ours to
            {mj.qacc_error:.1e} (largest {mj.qacc_scale:.3g}). Observed orders: """
                 + ", ".join(f"{k} {fmt(v, '.2f')}" for k, v in orders.items())
                 + ". Euler is MuJoCo's semi-implicit Euler with implicit damping; implicitfast also treats damping "
                 "implicitly; RK4 is classical." + same),
            "",
            f"![MuJoCo](work_precision_{name}_mujoco.png)",
            "",
        ]  # fmt: skip
        mj_rows = []
        for integ in MUJOCO_INTEGRATORS:
            runs = [x for x in mj.runs if x.integrator == integ]
            cells = ", ".join(
                f"{x.dt * 1e3:g} ms: {fmt(x.error) if x.status == 'completed' else x.status}" for x in runs
            )
            mj_rows.append([integ, cells or "—"])
        lines += table(["MuJoCo integrator", "error per step"], mj_rows)
    lines += [
        "",
        "**Conclusion.** " + conclusion(name, result, mj) + (f" {para(system.note)}" if system.note else ""),
        "",
    ]
    return lines


def conclusion(name: str, result: ms.WorkPrecision, mj: MujocoStudy | None) -> str:
    """A few sentences written from this run's numbers (so they stay true when the code changes)."""
    r = result.reference
    assert r is not None
    parts = []
    picks = {tol: ms.recommend(result, tol) for tol in ACCURACIES}
    winners = sorted({m.integrator for m in picks.values() if m})
    if winners:
        said = ", ".join(f"{m.integrator} at {tol:.0e}" for tol, m in picks.items() if m)
        parts.append(f"The cheapest choice measured is {said}.")
    missing = [f"{tol:.0e}" for tol, m in picks.items() if m is None]
    if missing:
        parts.append(f"Nothing measured reached {', '.join(missing)} within the run-time budget.")
    mismatched = [f.integrator for f in result.orders.values() if f.mismatch]
    fitted = [f for f in result.orders.values() if math.isfinite(f.observed)]
    if fitted and not mismatched:
        parts.append("Every fitted order agrees with its theory.")
    elif mismatched:
        parts.append(f"Orders off their theory: {', '.join(mismatched)} (see the errors: pre-asymptotic or limited).")
    diverged = sorted({m.integrator for m in result.measurements if m.status == "diverged"})
    if diverged:
        coarsest_ok = {}
        for integ in diverged:
            ok = [m.dt for m in result.for_integrator(integ) if m.completed and not m.adaptive]
            coarsest_ok[integ] = max(ok) if ok else math.nan
        listed = ", ".join(
            f"{i} (first stable step {fmt(coarsest_ok[i], 'g')} s)" if math.isfinite(coarsest_ok[i]) else i
            for i in diverged
        )
        parts.append(f"Diverged at coarse steps: {listed}.")
    implicit = [m for m in result.measurements if m.completed and ms.INTEGRATORS[m.integrator].implicit]
    explicit = [m for m in result.measurements if m.completed and not ms.INTEGRATORS[m.integrator].implicit]
    for tol in (1e-2, 1e-4):
        best_i = min((m for m in implicit if m.error + r.error <= tol), key=lambda m: m.cpu_time, default=None)
        best_e = min((m for m in explicit if m.error + r.error <= tol), key=lambda m: m.cpu_time, default=None)
        if best_i and best_e:
            ratio = best_e.cpu_time / best_i.cpu_time
            if ratio > 1:
                parts.append(
                    f"At {tol:.0e} an implicit method ({best_i.integrator}, {best_i.settings()}) is {ratio:.1f}x "
                    f"cheaper than the best explicit one ({best_e.integrator}, {best_e.settings()})."
                )
            else:
                parts.append(
                    f"At {tol:.0e} the best implicit method ({best_i.integrator}, {best_i.settings()}) costs "
                    f"{1 / ratio:.1f}x the best explicit one ({best_e.integrator}, {best_e.settings()})."
                )
            break
    if mj is not None:
        for tol in (1e-4, 1e-2):
            ours, theirs = ms.recommend(result, tol), cheapest_mujoco(mj, tol, r.error)
            if ours and theirs:
                why = (
                    "ours takes fewer, costlier steps of a higher-order adaptive method"
                    if ms.INTEGRATORS[ours.integrator].adaptive
                    else "MuJoCo's step is compiled C, ours runs its stages in Python"
                )
                parts.append(
                    f"At {tol:.0e}, MuJoCo's cheapest ({theirs.integrator}, dt {theirs.dt:g} s, "
                    f"{theirs.cpu_time * 1e3:.1f} ms) against ours ({ours.integrator}, {ours.settings()}, "
                    f"{ours.cpu_time * 1e3:.1f} ms): {'MuJoCo' if theirs.cpu_time < ours.cpu_time else 'ours'} is "
                    f"{max(theirs.cpu_time, ours.cpu_time) / min(theirs.cpu_time, ours.cpu_time):.1f}x cheaper "
                    f"({why})."
                )
                break
            if ours and not theirs and any(x.status == "completed" for x in mj.runs):
                best = min((x for x in mj.runs if x.status == "completed"), key=lambda x: x.error)
                parts.append(
                    f"MuJoCo reached at best {best.error:.1e} ({best.integrator}, dt {best.dt:g} s) within the budget, "
                    f"short of {tol:.0e}."
                )
                break
    return " ".join(parts)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--duration", type=float, default=1.0, help="simulated time per run [s]")
    parser.add_argument(
        "--systems", default=",".join(DEFAULT_SYSTEMS), help=f"comma-separated, from {', '.join(SYSTEMS)}"
    )
    parser.add_argument("--max-run-time", type=float, default=1.0, help="CPU-time budget of one run [s]")
    parser.add_argument("--out-dir", type=Path, default=ROOT / "docs")
    args = parser.parse_args(argv)
    python = Path(sys.executable)
    shown = str(python.relative_to(ROOT)) if python.is_relative_to(ROOT) else "python"
    command = " ".join([shown, "scripts/work_precision_report.py", *(sys.argv[1:] if argv is None else argv)])
    if mujoco is not None:  # keep MuJoCo's warnings instead of a MUJOCO_LOG.TXT in the cwd
        mujoco.set_mju_user_warning(lambda message: RUNTIME_WARNINGS.append(message.strip()))
    args.out_dir.mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    load_before = os.getloadavg()[0] if hasattr(os, "getloadavg") else math.nan
    body: list[str] = []
    targets: list[TargetRow] = []
    call_cost = per_call_cost()
    for name in args.systems.split(","):
        system = SYSTEMS[name]
        robot = ms.load_robot(name, floating_base=system.floating_base)
        q0, v0 = initial_state(robot, system)
        t0 = time.perf_counter()
        result = ms.work_precision(
            robot,
            q0,
            v0,
            duration=args.duration,
            output_dt=args.duration if system.at_end else None,
            max_run_time=args.max_run_time,
        )
        ms.plot_work_precision(result, args.out_dir / f"work_precision_{name}.png")
        mj = None
        if mujoco is not None:
            try:
                mj = mujoco_study(robot, result, args.max_run_time)
                plot_mujoco(args.out_dir / f"work_precision_{name}_mujoco.png", result, mj)
            except (ValueError, NotImplementedError) as exc:  # a URDF MuJoCo cannot load, or a joint not mapped
                print(f"{name}: MuJoCo skipped: {exc}")
        rows = target_rows(name, robot, result, mj)
        targets += rows
        elapsed = time.perf_counter() - t0
        body += section(name, system, robot, result, mj, elapsed)
        picks = ", ".join(
            f"{tol:.0e}: {m.integrator if m else '—'}" for tol in ACCURACIES for m in [ms.recommend(result, tol)]
        )
        print(f"{name}: {elapsed:.0f} s; {picks}", flush=True)
    elapsed = time.perf_counter() - start
    load_after = os.getloadavg()[0] if hasattr(os, "getloadavg") else math.nan
    head = [
        "# Work-precision: how much accuracy each integrator buys per unit of cost",
        "",
        f"Generated by `{command}` on {datetime.date.today().isoformat()} ({platform.machine()}, "
        f"{os.cpu_count()} cores, load average {load_before:.1f} → {load_after:.1f}; {elapsed:.0f} s); do not edit "
        "by hand. The same study on any robot: `multibody-sim bench ROBOT`.",
        "",
        para(f"""**Error** is CONTRACTS.md's `--tolerance` quantity: the max over samples every
        {bench.OUTPUT_DT * 1e3:g} ms of ‖(q ⊖ q_ref, v − v_ref)‖∞ (Pinocchio's difference in the tangent space;
        rad, m, rad/s, m/s), against a {bench.REFERENCE_INTEGRATOR} reference at rtol = atol =
        {bench.REFERENCE_TOLERANCE:.0e} whose own error is estimated by refining it {bench.REFINEMENT:g}x; runs
        within {bench.REFERENCE_MARGIN:g}x of that estimate are drawn hollow and left out of the order fits.
        `max |energy_error|` (H − H(0) − work + dissipated) is shown beside the error, never used as it: it does not
        see phase error. **Cost** is the CPU time of the whole `simulate` call (median of up to 3 timings for runs
        under {bench.REPEAT_BELOW:g} s): on an idle machine that is the run's wall time, while wall time on a shared
        machine also counts other processes' turns. Dynamics evaluations are the second panel."""),
        "",
        para(f"""**Ladders.** Fixed steps {", ".join(f"{dt * 1e3:g}" for dt in bench.STEP_LADDER[:9])} … ms,
        adaptive tolerances 1e-2 … 1e-11 by half decades; each ladder stops once its error is below
        {bench.MIN_ERROR:g} (or within {bench.REFERENCE_MARGIN:g}x of the reference's), or before a run predicted to
        take more than {args.max_run_time:g} s of CPU. **Observed order**: fixed-step, the slope of log error against
        log dt over the finest {bench.FIT_POINTS} usable runs (error below 0.1, above the reference's), flagged when
        more than {bench.ORDER_MISMATCH} from theory; adaptive, an effective order, minus the slope against log
        evaluations over the tightest {bench.ADAPTIVE_FIT_POINTS} usable runs, reported in its own column and never
        flagged: a step controller makes it steeper than the classical order, the more so the higher it is, so it
        is no classical order to judge against. **Recommended**: the least CPU
        time among runs whose error plus the reference's estimated error is within the accuracy; `run
        --tolerance` makes the same choice from a pruned pilot study over min(duration, 1 s)."""),
        "",
        para(f"""**MuJoCo** runs the same URDF from the same state (`mj_step` in a Python loop; contacts, joint
        limits and equality constraints off, armature and friction loss zeroed, joint damping set to ours; a free
        joint added on a floating robot's root), its states mapped to Pinocchio's convention joint by joint
        (quaternion w-first → scalar-last, free-joint linear velocity world → base frame) and measured against the
        same reference on the same grid. Its cost is the CPU time of the stepping loop alone (our runs include
        `simulate`'s fixed per-call cost, measured here: {call_cost * 1e3:.2f} ms, the median of a one-step
        run)."""),
        "",
    ]
    if targets:
        head += [
            "## Accuracy per cost against MuJoCo (issue 15's targets)",
            "",
            para(f"""Our cheapest explicit run (any method, step or tolerance, on the kernel `simulate` takes for it)
            against MuJoCo's cheapest run reaching the same accuracy (error + the reference's ≤ accuracy; on the
            double pendulum MuJoCo's RK4, elsewhere any of its integrators). The cheapest run of each method of each
            side that reaches the accuracy in the study is timed again in {ROUNDS} interleaved rounds (each round
            runs every candidate in a new random order, each twice in a row and the second timed: its caches warm as
            in a loop of calls, not cooled by the candidate before): CPU time medians, ours of the whole `simulate`
            call, MuJoCo's of its stepping loop (`mj_step` in a Python loop). Ratio = ours / MuJoCo's."""),
            "",
            *targets_table(targets),
            "",
        ]
    if mujoco is None:
        head += ["MuJoCo is not installed (`pip install mujoco`): its comparison was skipped.", ""]
    elif IMPORT_WARNINGS:
        head += ["MuJoCo's URDF importer warned: " + "; ".join(sorted(set(IMPORT_WARNINGS))), ""]
    if targets:
        print("\n".join(targets_table(targets)))
    text = "\n".join(head + body)
    path = args.out_dir / "work_precision.md"
    path.write_text(text, encoding="utf-8")
    print(f"wrote {path} in {elapsed:.0f} s")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
