"""What a scene and a built-in controller cost on the kernel a run takes (native where eligible), per step.

Two measurements, each a CPU-time median over interleaved rounds in one process (2 cores shared: ratios, not
absolute times, are the result):

- Model only what a scene requires: simulate() of talos_upper_body (legs locked, nv 20) against the full talos
  (nv 32) from the same configuration, RK4, dt = 1 ms, output every 10 ms, no controller (issue 15's target:
  ≤ 0.75).
- A built-in controller: simulate() of ur5 with PDGravity at every step against the same run without a controller
  (a built-in controller runs inside the native kernel: no call into Python per control instant), and the same
  controller behind a Python function (called by the driver at every control instant).

Usage: python scripts/bench_native_scenes.py [--steps 2000] [--repeats 9]
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import numpy as np

import multibody_sim as ms
from multibody_sim import native
from multibody_sim.controllers import PDGravity


def cpu_us(run: Callable[[], object], steps: int) -> float:
    """CPU µs per step of one call of run()."""
    start = time.process_time()
    run()
    return (time.process_time() - start) / steps * 1e6


def interleaved(runs: dict[str, Callable[[], object]], steps: int, repeats: int) -> dict[str, list[float]]:
    """Each run's CPU µs per step in every round, the runs interleaved (each run once untimed first)."""
    for run in runs.values():
        run()
    times: dict[str, list[float]] = {label: [] for label in runs}
    for _ in range(repeats):
        for label, run in runs.items():
            times[label].append(cpu_us(run, steps))
    return times


def ratio(times: dict[str, list[float]], label: str, floor: str) -> tuple[float, float, float]:
    """Median and quartiles of the per-round ratios label / floor."""
    ratios = [a / b for a, b in zip(times[label], times[floor], strict=True)]
    q1, median, q3 = statistics.quantiles(ratios, n=4)
    return median, q1, q3


def python_controller(controller: Callable) -> Callable:
    """The controller behind a plain function: the driver calls it at every control instant (as any user code)."""
    return lambda t, q, v: controller(t, q, v)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=2000, help="RK4 steps of 1 ms per timed run")
    parser.add_argument("--repeats", type=int, default=9, help="interleaved rounds")
    args = parser.parse_args()
    steps, dt = args.steps, 1e-3
    duration = steps * dt
    print(f"kernel: {native.kernel()}; {steps} steps per run, {args.repeats} interleaved rounds, CPU time\n")

    scene = ms.load_scene("talos_upper_body")
    full = scene.full_robot
    q_full = scene.full_configuration(scene.q0)
    kwargs = {"duration": duration, "dt": dt, "output_dt": 10 * dt, "progress": False}
    runs = {
        "talos_upper_body (nv 20)": lambda: ms.simulate(scene, scene.q0, np.zeros(scene.nv), **kwargs),
        "talos (nv 32)": lambda: ms.simulate(full, q_full, np.zeros(full.nv), **kwargs),
    }
    kernels = {label: run().metadata["kernel"] for label, run in runs.items()}  # type: ignore[attr-defined]
    times = interleaved(runs, steps, args.repeats)
    print("## Locked joints: talos_upper_body against the full talos, simulate RK4, per step")
    for label in runs:
        print(f"- {label}: {statistics.median(times[label]):.2f} µs/step ({kernels[label]})")
    median, q1, q3 = ratio(times, "talos_upper_body (nv 20)", "talos (nv 32)")
    print(f"- ratio: {median:.3f} (IQR {q1:.3f}–{q3:.3f}); target ≤ 0.75: {'met' if median <= 0.75 else 'NOT met'}\n")

    ur5 = ms.load_robot("ur5")
    q0 = ur5.default_pose()
    q_ref = q0 + 0.3
    runs = {
        "ur5, no controller": lambda: ms.simulate(ur5, q0, np.zeros(ur5.nv), **kwargs),
        "ur5, PDGravity every step": lambda: ms.simulate(
            ur5, q0, np.zeros(ur5.nv), controller=PDGravity(ur5, q_ref, kp=100.0), **kwargs
        ),
        "ur5, the same called from Python": lambda: ms.simulate(
            ur5, q0, np.zeros(ur5.nv), controller=python_controller(PDGravity(ur5, q_ref, kp=100.0)), **kwargs
        ),
    }
    kernels = {label: run().metadata["kernel"] for label, run in runs.items()}  # type: ignore[attr-defined]
    times = interleaved(runs, steps, args.repeats)
    print("## A built-in controller: ur5 with PDGravity at every step against no controller, simulate RK4, per step")
    for label in runs:
        print(f"- {label}: {statistics.median(times[label]):.2f} µs/step ({kernels[label]})")
    for label in ("ur5, PDGravity every step", "ur5, the same called from Python"):
        median, q1, q3 = ratio(times, label, "ur5, no controller")
        print(f"- {label} / no controller: {median:.3f} (IQR {q1:.3f}–{q3:.3f})")


if __name__ == "__main__":
    main()
