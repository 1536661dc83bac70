"""What a batch costs without the compiled extension: rollout() on the Python (row) kernel against the native kernel.

Where the extension is missing (no compiler at install) or switched off (MULTIBODY_SIM_NATIVE=0), a batch runs the
row kernel: each row's step is the integrator's own attempt() in Python. This script times, for each robot, in
interleaved rounds (the machine is shared and noisy: every variant once per round, under the same load), in CPU µs
per state-step (one state advanced by one step): rollout() on the native kernel, rollout() on the row kernel, and
the floor (4 × one ``pin.abaInParallel`` over the batch, one thread). Ratios are medians of per-round ratios.
RK4, dt = 1 ms, samples every 10 steps, robots loaded with ``damping=False``.

Usage:
    .venv/bin/python scripts/bench_python_batch.py [--robots double_pendulum,ur5,solo12] [--batch 64]
        [--steps 50] [--rounds 7]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from collections.abc import Callable

import numpy as np
import pinocchio as pin

from multibody_sim import load_robot, native, rollout

ENV = "MULTIBODY_SIM_NATIVE"


def cpu_seconds(run: Callable[[], object]) -> float:
    start = time.process_time()
    run()
    return time.process_time() - start


def measure(name: str, batch: int, steps: int, rounds: int) -> dict[str, float]:
    """Medians over rounds: µs per state-step of each variant, and the per-round ratios."""
    robot = load_robot(name, damping=False)
    rng = np.random.default_rng(0)
    Q0 = np.stack([robot.random_configuration(rng) for _ in range(batch)])
    V0 = rng.normal(0.0, 0.1, (batch, robot.nv))
    pool = pin.ModelPool(robot.model, 1)
    tau, acc = np.zeros((batch, robot.nv)), np.empty((batch, robot.nv))

    def floor() -> None:
        for _ in range(4 * steps):
            pin.abaInParallel(1, pool, Q0.T, V0.T, tau.T, acc.T)

    def run(kernel: str) -> Callable[[], object]:
        def go() -> object:
            os.environ[ENV] = "0" if kernel == "row" else "1"
            try:
                out = rollout(robot, Q0, V0, duration=steps * 1e-3, dt=1e-3, output_dt=1e-2, progress=False)
            finally:
                del os.environ[ENV]
            expected = "python (row)" if kernel == "row" else "native"
            if out.metadata["kernel"] != expected:
                raise SystemExit(f"{name}: the {kernel} run took the {out.metadata['kernel']} kernel")
            return out

        return go

    variants = {"native": run("native"), "row": run("row"), "floor": floor}
    for f in variants.values():  # warm-up: first calls build models and caches
        f()
    spent: dict[str, list[float]] = {key: [] for key in variants}
    for _ in range(rounds):
        for key, f in variants.items():
            spent[key].append(cpu_seconds(f) / (batch * steps) * 1e6)
    ratio = [r / n for r, n in zip(spent["row"], spent["native"], strict=True)]
    floor_ratio = [r / f for r, f in zip(spent["row"], spent["floor"], strict=True)]
    return {
        **{key: statistics.median(values) for key, values in spent.items()},
        "row / native": statistics.median(ratio),
        "row / floor": statistics.median(floor_ratio),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--robots", default="double_pendulum,ur5,solo12", help="comma-separated catalog names")
    parser.add_argument("--batch", type=int, default=64, help="states per rollout")
    parser.add_argument("--steps", type=int, default=50, help="steps per timed rollout")
    parser.add_argument("--rounds", type=int, default=7, help="interleaved rounds")
    args = parser.parse_args()
    if not native.available:
        raise SystemExit(f"the native kernel is not available here ({native.why_unavailable}): nothing to compare")
    print(f"B = {args.batch}, {args.steps} RK4 steps of 1 ms, {args.rounds} rounds; CPU µs per state-step (medians)")
    print(f"{'robot':<16} {'native':>8} {'row':>8} {'floor':>8} {'row / native':>13} {'row / floor':>12}")
    for name in args.robots.split(","):
        m = measure(name, args.batch, args.steps, args.rounds)
        print(
            f"{name:<16} {m['native']:8.2f} {m['row']:8.2f} {m['floor']:8.2f} {m['row / native']:13.1f} "
            f"{m['row / floor']:12.1f}",
            flush=True,
        )


if __name__ == "__main__":
    main()
