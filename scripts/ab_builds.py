"""A/B of two builds of the package on the batched rollout's cost, for changes of a few percent.

Full benchmark runs on this shared machine differ by ±3% from one run to the next on the same code, more than many
optimisations gain. This script alternates two interpreters (two worktrees' .venv, each with its own build) in
pairs of processes; each process times a rollout (RK4, dt = 1 ms, B = 256, every step recorded) and its floor
(4 × one `pin.abaInParallel` over the same states, one thread) back to back in each of its rounds and reports the
median ratio. The load of the moment then weighs on both sides of a pair alike. With `--stepper`, each process
times `steps` calls of Stepper.step instead (one row, RK4, dt = 1 ms, zero torque: the per-call cost of the entry
point that gym environments use) against 4 × `pin.aba` per step called from Python.

Usage:
    python scripts/ab_builds.py --a /work/main/.venv/bin/python --b /work/wt/mine/.venv/bin/python \\
        [--robots double_pendulum,solo12] [--pairs 6] [--rounds 7] [--steps 100] [--batch 256] [--stepper]

Prints each pair's ratios, then per robot the median ratio of each side and in how many pairs B read lower.
Check each build's kernel first (`multibody-sim --version`): a stale editable build runs the Python kernel.
"""

from __future__ import annotations

import argparse
import statistics
import subprocess
import sys
import time
from collections.abc import Callable


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
    parser.add_argument("--measure", action="store_true", help=argparse.SUPPRESS)  # one side's process
    args = parser.parse_args()
    robots = args.robots.split(",")
    if args.measure:
        for name in robots:
            if args.stepper:
                ratio = measure_stepper(name, args.rounds, args.steps)
            else:
                ratio = measure(name, args.rounds, args.steps, args.batch)
            print(f"{name}={ratio:.5f}", end=" ")
        print()
        return
    if not args.a or not args.b:
        parser.error("--a and --b name the two interpreters to compare")
    inner = [__file__, "--measure", "--robots", args.robots, "--rounds", str(args.rounds), "--steps", str(args.steps)]
    inner += ["--batch", str(args.batch)] + (["--stepper"] if args.stepper else [])
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
    timed = "stepper" if args.stepper else "rollout"
    for name in robots:
        a, b = results["a"][name], results["b"][name]
        lower = sum(y < x for x, y in zip(a, b, strict=True))
        print(
            f"{name}: {timed} / floor, median a {statistics.median(a):.4f}, b {statistics.median(b):.4f}; "
            f"b lower in {lower} of {len(a)} pairs"
        )


if __name__ == "__main__":
    sys.exit(main())
