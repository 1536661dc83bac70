"""A/B of two builds of the package on the batched rollout's cost, for changes of a few percent.

Full benchmark runs on this shared machine differ by ±3% from one run to the next on the same code, more than many
optimisations gain. This script alternates two interpreters (two worktrees' .venv, each with its own build) in
pairs of processes; each process times a rollout (RK4, dt = 1 ms, B = 256, every step recorded) and its floor
(4 × one `pin.abaInParallel` over the same states, one thread) back to back in each of its rounds and reports the
median ratio. The load of the moment then weighs on both sides of a pair alike. With `--stepper`, each process
times `steps` calls of Stepper.step instead (one row, RK4, dt = 1 ms, zero torque: the per-call cost of the entry
point that gym environments use) against 4 × `pin.aba` per step called from Python. With `--contact`, `--robots`
names contact scenes and each process times their native timestepping step from the scene's start under its
controller (a 10·steps run less a steps run, per step, as scripts/contact_mujoco.py does) against one `pin.aba` per
step called from Python. With `--velocity-limits`, each process times go2_standing with its catalog motors and
its velocity limits enforced, dropped 0.2 m under random torques within the effort limits (tests/test_velocity_limits.py's
falling go2: the impacts drive joints into their limits, so steps select and re-solve velocity-limit rows), a
`steps`-step native rollout of 4 episodes, against 4 × `steps` × one `pin.aba` called from Python (--robots unused);
`--velocity-scale s` draws every joint's velocity limit as s times the catalog's ([randomize]), so that most steps
hold joints at their limits.

With `--reports`, each process runs instead one side's own copy of scripts/bench_step_cost.py and
scripts/bench_rollout.py (the worktree that holds the interpreter's .venv) on the robots, and the figures of their
per-robot lines are taken as ratios to the floor that the same process measured: bench_step_cost's Python-kernel
RK4 step, native RK4 step and native rollout state-step, each / 4 × abaInParallel per state; bench_rollout's
rollout (output every 10 steps) / 4 × abaInParallel, floating robots also base welded. bench_rollout is stopped
once those lines are out (its scaling sections are not compared); neither writes its report into docs/.

Usage:
    python scripts/ab_builds.py --a /work/main/.venv/bin/python --b /work/wt/mine/.venv/bin/python \\
        [--robots double_pendulum,solo12] [--pairs 6] [--rounds 7] [--steps 100] [--batch 256] [--stepper | --reports |
        --contact | --velocity-limits [--velocity-scale 0.3]]

Prints each pair's ratios, then per robot the median ratio of each side and in how many pairs B read lower.
Check each build's kernel first (`multibody-sim --version`): a stale editable build runs the Python kernel.
"""

from __future__ import annotations

import argparse
import os
import re
import selectors
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

# bench_step_cost.py's per-robot line: python rk4 µs/step (CPU), native µs/step, floor per state, ..., rollout
STEP_COST_LINE = re.compile(
    r"^(\S+): python rk4 ([\d.]+) µs/step \(CPU\), native ([\d.]+), floor 4 × abaInParallel ([\d.]+), .*; "
    r"rollout ([\d.]+) µs/state-step"
)
# bench_rollout.py's per-robot line: rollout / floor, median (quartiles)
ROLLOUT_LINE = re.compile(r"^(.+?): rollout / floor ([\d.]+) ")


def measure(name: str, rounds: int, steps: int, batch: int) -> float:
    """Median over rounds of rollout / floor CPU time on one robot (runs in the interpreter under test)."""
    import numpy as np
    import pinocchio as pin

    from multibody_sim import load_robot, rollout

    robot = load_robot(name, damping=False)
    rng = np.random.default_rng(0)
    Q0 = np.stack([robot.random_configuration(rng) for _ in range(batch)])
    V0 = rng.normal(0.0, 0.1, (batch, robot.nv))
    pool = pin.ModelPool(robot.model, 1)
    tau, acc = np.zeros((batch, robot.nv)), np.empty((batch, robot.nv))

    def floor() -> None:
        for _ in range(4 * steps):
            pin.abaInParallel(1, pool, Q0.T, V0.T, tau.T, acc.T)

    def run() -> float:
        start = time.process_time()
        rollout(robot, Q0, V0, duration=steps * 1e-3, dt=1e-3, progress=False)
        return time.process_time() - start

    return median_ratio(run, floor, rounds)


def median_ratio(run: Callable[[], float], floor: Callable[[], None], rounds: int) -> float:
    """Median over rounds of run's CPU time (which it returns) / floor's, timed back to back, after one call of each."""
    run()
    floor()
    ratios = []
    for _ in range(rounds):
        start = time.process_time()
        floor()
        spent_floor = time.process_time() - start
        ratios.append(run() / spent_floor)
    return statistics.median(ratios)


def measure_stepper(name: str, rounds: int, steps: int) -> float:
    """Median over rounds of `steps` Stepper.step calls / 4 x `steps` pin.aba calls, CPU time (one robot)."""
    import numpy as np
    import pinocchio as pin

    from multibody_sim import Stepper, load_robot

    robot = load_robot(name, damping=False)
    q0 = robot.random_configuration(np.random.default_rng(0))
    tau = np.zeros(robot.nv)
    data = robot.model.createData()
    v0 = np.zeros(robot.nv)

    def floor() -> None:
        for _ in range(4 * steps):
            pin.aba(robot.model, data, q0, v0, tau)

    def run() -> float:
        stepper = Stepper(robot, dt=1e-3, integrator="rk4", q0=q0)
        start = time.process_time()
        for _ in range(steps):
            stepper.step(tau)
        return time.process_time() - start

    return median_ratio(run, floor, rounds)


def measure_contact(name: str, rounds: int, steps: int) -> float:
    """Median over rounds of a contact scene's native timestepping step (the difference of a 10·steps and a steps
    run from the scene's start under its controller, per step: scripts/contact_mujoco.py's figure) / one pin.aba on
    its model, CPU time."""
    import numpy as np
    import pinocchio as pin

    import multibody_sim as ms

    scene = ms.load_scene(name)
    controller = scene.make_controller() if scene.spec.controller is not None else None
    data = scene.model.createData()
    q0, v0, tau = np.asarray(scene.q0), np.zeros(scene.model.nv), np.zeros(scene.model.nv)

    def cpu(n: int) -> float:
        start = time.process_time()
        run = ms.simulate(scene, scene.q0, scene.v0, duration=n * 1e-3, dt=1e-3, integrator="timestepping",
                          controller=controller, output_dt=n * 1e-3, progress=False)  # fmt: skip
        assert run.metadata["kernel"] == "native", "the native kernel is not built"
        return time.process_time() - start

    def floor() -> None:
        for _ in range(9 * steps):
            pin.aba(scene.model, data, q0, v0, tau)

    return median_ratio(lambda: cpu(10 * steps) - cpu(steps), floor, rounds)


def measure_velocity_limits(rounds: int, steps: int, scale: float) -> float:
    """Median over rounds of a falling go2's native timestepping rollout with its velocity limits (scaled by `scale`)
    enforced (4 episodes of `steps` steps) / 4 x `steps` pin.aba calls on its model, CPU time."""
    import tomllib

    import numpy as np
    import pinocchio as pin

    import multibody_sim as ms

    tables = tomllib.loads((Path(__file__).parent.parent / "models" / "scenes" / "go2_standing.toml").read_text())
    for name in ("controller", "simulation", "description"):
        tables.pop(name, None)
    tables["actuators"] = "catalog"
    tables["contact"] = {**tables.get("contact", {}), "velocity_limits": "enforce"}
    if scale != 1.0:
        drawn = {"name": "velocity_limit", "joints": "*", "distribution": "uniform", "scale": [scale, scale]}
        tables["randomize"] = {"seed": 0, "parameter": [drawn]}
    scene = ms.make_scene(**tables)
    episodes = 4
    limit = scene.effort_limit[6:]
    taus = np.zeros((episodes, steps // 2, scene.nv))  # a new torque every 2 ms
    for b in range(episodes):
        taus[b, :, 6:] = np.random.default_rng(b).uniform(-limit, limit, size=(steps // 2, len(limit)))
    Q0 = np.tile(scene.q0, (episodes, 1))
    Q0[:, 2] += 0.2
    V0 = np.zeros((episodes, scene.nv))
    data = scene.model.createData()
    q0, v0, tau = np.asarray(scene.q0), np.zeros(scene.nv), np.zeros(scene.nv)

    def run() -> float:
        start = time.process_time()
        out = ms.rollout(scene, Q0, V0, duration=steps * 1e-3, dt=1e-3, integrator="timestepping", taus=taus,
                         control_dt=2e-3, progress=False)  # fmt: skip
        spent = time.process_time() - start
        assert out.metadata["kernel"] == "native", "the native kernel is not built"
        return spent

    def floor() -> None:
        for _ in range(4 * steps):
            pin.aba(scene.model, data, q0, v0, tau)

    return median_ratio(run, floor, rounds)


def report_figures(python: str, robots: str, rounds: int, steps: int) -> dict[str, float]:
    """Run the side's own bench_step_cost.py and bench_rollout.py (in the worktree of its .venv) and return their
    figures as ratios to the floor measured in the same process, named "<robot> <figure>"."""
    root = Path(python).absolute().parent.parent.parent  # <worktree>/.venv/bin/python
    figures: dict[str, float] = {}
    with tempfile.TemporaryDirectory() as tmp:
        step_cost = [python, str(root / "scripts" / "bench_step_cost.py"), "--robots", robots]
        step_cost += ["--repeats", str(rounds), "--steps", str(steps), "--out", str(Path(tmp) / "step_cost.md")]
        done = subprocess.run(step_cost, capture_output=True, text=True, check=True, cwd=root)
        for line in done.stdout.splitlines():
            match = STEP_COST_LINE.match(line)
            if match:
                name, python_rk4, native_rk4, floor, rollout = match.groups()
                figures[f"{name} step_cost python rk4"] = float(python_rk4) / float(floor)
                figures[f"{name} step_cost native rk4"] = float(native_rk4) / float(floor)
                figures[f"{name} step_cost rollout"] = float(rollout) / float(floor)
        bench = [python, str(root / "scripts" / "bench_rollout.py"), "--robots", robots, "--no-ray"]
        bench += ["--repeats", str(rounds), "--steps", str(steps), "--out", str(Path(tmp) / "rollout_cost.md")]
        with subprocess.Popen(bench, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, cwd=root) as run:
            assert run.stdout is not None
            for line in rollout_lines(run.stdout, len(robots.split(","))):
                match = ROLLOUT_LINE.match(line)
                assert match is not None
                figures[f"{match.group(1)} rollout"] = float(match.group(2))
            run.terminate()
    return figures


def rollout_lines(out: Any, robots: int) -> list[str]:
    """bench_rollout.py's per-robot ratio lines from its stdout (binary): the robots' lines, then those of the
    floating ones base welded, printed together; done when no line followed for 5 s after the robots' lines."""
    lines: list[str] = []
    buffer = b""
    with selectors.DefaultSelector() as selector:
        selector.register(out, selectors.EVENT_READ)
        while True:
            waiting = len(lines) >= robots
            if not selector.select(timeout=5.0 if waiting else None):
                return lines
            chunk = os.read(out.fileno(), 65536)
            if not chunk:
                return lines
            buffer += chunk
            *complete, buffer = buffer.split(b"\n")
            lines += [text for text in (c.decode() for c in complete) if ROLLOUT_LINE.match(text)]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--a", help="the first interpreter (the baseline)")
    parser.add_argument("--b", help="the second interpreter (the change)")
    parser.add_argument("--robots", default="double_pendulum,solo12", help="comma-separated catalog names")
    parser.add_argument("--pairs", type=int, default=6, help="pairs of processes, alternating a and b")
    parser.add_argument("--rounds", type=int, default=7, help="rounds per process")
    parser.add_argument("--steps", type=int, default=100, help="steps per timed rollout")
    parser.add_argument("--batch", type=int, default=256, help="states per rollout")
    parser.add_argument("--stepper", action="store_true", help="time Stepper.step instead of a rollout")
    parser.add_argument("--reports", action="store_true", help="run bench_step_cost.py and bench_rollout.py instead")
    parser.add_argument("--contact", action="store_true", help="time contact scenes' native steps (--robots: scenes)")
    parser.add_argument("--velocity-limits", action="store_true", help="time a falling go2 into its velocity limits")
    parser.add_argument("--velocity-scale", type=float, default=1.0, help="--velocity-limits: the limits' scale")
    parser.add_argument("--measure", action="store_true", help=argparse.SUPPRESS)  # one side's process
    args = parser.parse_args()
    robots = ["go2_velocity_limits"] if args.velocity_limits else args.robots.split(",")
    if args.measure:
        for name in robots:
            if args.velocity_limits:
                ratio = measure_velocity_limits(args.rounds, args.steps, args.velocity_scale)
            elif args.contact:
                ratio = measure_contact(name, args.rounds, args.steps)
            elif args.stepper:
                ratio = measure_stepper(name, args.rounds, args.steps)
            else:
                ratio = measure(name, args.rounds, args.steps, args.batch)
            print(f"{name}={ratio:.5f}", end=" ")
        print()
        return
    if not args.a or not args.b:
        parser.error("--a and --b name the two interpreters to compare")
    if args.reports:
        compare_reports(args)
        return
    inner = [__file__, "--measure", "--robots", args.robots, "--rounds", str(args.rounds), "--steps", str(args.steps)]
    inner += ["--batch", str(args.batch)] + (["--stepper"] if args.stepper else []) + (["--contact"] if args.contact else [])
    inner += ["--velocity-limits", "--velocity-scale", str(args.velocity_scale)] if args.velocity_limits else []
    results: dict[str, dict[str, list[float]]] = {"a": {}, "b": {}}
    for pair in range(args.pairs):
        line = []
        for side, python in (("a", args.a), ("b", args.b)):
            done = subprocess.run([python, *inner], capture_output=True, text=True, check=True)
            for item in done.stdout.split():
                name, ratio = item.split("=")
                results[side].setdefault(name, []).append(float(ratio))
            line.append(f"{side}: {done.stdout.strip()}")
        print(f"pair {pair + 1}/{args.pairs}  " + "  |  ".join(line), flush=True)
    timed = "velocity-limit rollout" if args.velocity_limits else "contact step" if args.contact else "stepper" if args.stepper else "rollout"
    for name in robots:
        a, b = results["a"][name], results["b"][name]
        lower = sum(y < x for x, y in zip(a, b, strict=True))
        print(
            f"{name}: {timed} / floor, median a {statistics.median(a):.4f}, b {statistics.median(b):.4f}; "
            f"b lower in {lower} of {len(a)} pairs"
        )


def compare_reports(args: argparse.Namespace) -> None:
    """--reports: the benchmark scripts' figures, pairs of processes alternating a and b."""
    results: dict[str, dict[str, list[float]]] = {"a": {}, "b": {}}
    for pair in range(args.pairs):
        for side, python in (("a", args.a), ("b", args.b)):
            for name, ratio in report_figures(python, args.robots, args.rounds, args.steps).items():
                results[side].setdefault(name, []).append(ratio)
        print(f"pair {pair + 1}/{args.pairs} done", flush=True)
    for name, a in results["a"].items():
        b = results["b"].get(name, [])
        if len(b) != len(a):
            print(f"{name}: missing on b")
            continue
        lower = sum(y < x for x, y in zip(a, b, strict=True))
        ma, mb = statistics.median(a), statistics.median(b)
        print(f"{name} / floor: median a {ma:.4f}, b {mb:.4f}, b/a {mb / ma:.3f}; b lower in {lower} of {len(a)} pairs")


if __name__ == "__main__":
    sys.exit(main())
