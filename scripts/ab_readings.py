"""In-process A/B of the sensors' readings on scripts/bench_sensors.py's workloads: made by the extension
(make_readings, one call per row and engine call) against the Python specification (SensorStream._read_python),
the two paths interleaved round by round in one process, so that both see the same machine load.

Each round runs every variant once per path (the order of the paths alternating between rounds); a variant's time
per step is a long run's CPU time minus a one-step run's, over the steps between them (as bench_sensors.py). The
two paths' readings are first checked equal, bit for bit, on every variant. Then the same for a Stepper that
steps the "actuators + sensors" scenes one step at a time (a push per step, as a controller or a gym environment at
every step makes): CPU time per step() over `--stepper-steps` steps, the paths interleaved the same way.

Usage:
    .venv/bin/python scripts/ab_readings.py [--rounds 15] [--steps 4000]
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from typing import Any

import numpy as np
from bench_sensors import DT, cpu, go2, go2_sensors, ur5, ur5_sensors, variants

import multibody_sim as ms
from multibody_sim import readings


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--steps", type=int, default=4000)
    parser.add_argument("--stepper-steps", type=int, default=1000)
    args = parser.parse_args()
    native = readings._native_readings
    paths: dict[str, Any] = {"native": native, "python": lambda stream: None}
    chosen = ("bare", "sensors", "actuators + sensors")
    runs = {scene: {label: table[label] for label in chosen} for scene, table in variants(None).items()}
    for scene, table in runs.items():  # warm up, and the same readings on both paths
        for label, run in table.items():
            made = {}
            for path, factory in paths.items():
                readings._native_readings = factory
                made[path] = run(200)
            assert made["native"].metadata["kernel"] == "native"
            for name, values in made["python"].sensors.items():
                np.testing.assert_array_equal(made["native"].sensors[name], values, err_msg=f"{scene} {label} {name}")
    times: dict[tuple[str, str, str], list[float]] = {}
    load = os.getloadavg()[0]
    for r in range(args.rounds):
        for scene, table in runs.items():
            for label, run in table.items():
                for path in list(paths) if r % 2 == 0 else list(paths)[::-1]:
                    readings._native_readings = paths[path]
                    (long, _), (short, _) = cpu(run, args.steps), cpu(run, 1)
                    times.setdefault((scene, label, path), []).append((long - short) / (args.steps - 1) * 1e6)
    readings._native_readings = native
    print(f"rounds {args.rounds}, steps {args.steps}, 1-minute load {load:.1f} -> {os.getloadavg()[0]:.1f}")
    print(
        "| scene | variant | µs/step native | µs/step python | ratio to bare, native | ratio to bare, python "
        "| python − native, per bare step (median of per-round) |"
    )
    print("|---|---|---:|---:|---:|---:|---:|")
    for scene, table in runs.items():
        bare = [
            (a + b) / 2 for a, b in zip(times[(scene, "bare", "native")], times[(scene, "bare", "python")], strict=True)
        ]
        for label in table:
            n, p = times[(scene, label, "native")], times[(scene, label, "python")]
            rn = statistics.median(a / b for a, b in zip(n, bare, strict=True))
            rp = statistics.median(a / b for a, b in zip(p, bare, strict=True))
            gain = statistics.median((b - a) / c for a, b, c in zip(n, p, bare, strict=True))
            print(
                f"| {scene} | {label} | {statistics.median(n):.2f} | {statistics.median(p):.2f} | {rn:.3f} | "
                f"{rp:.3f} | {gain:+.3f} |"
            )
    stepping(paths, args.rounds, args.stepper_steps)


def stepping(paths: dict[str, Any], rounds: int, steps: int) -> None:
    """Stepper.step's CPU time [µs] on ur5 (rk4) and go2_standing (time-stepper) with actuators and sensors, per
    readings path, medians over the rounds."""
    scenes = {
        "ur5": (ur5(True, ur5_sensors(None)), "rk4"),
        "go2_standing": (go2(True, go2_sensors(None)), "timestepping"),
    }
    times: dict[tuple[str, str], list[float]] = {}
    for r in range(rounds):
        for scene, (system, integrator) in scenes.items():
            for path in list(paths) if r % 2 == 0 else list(paths)[::-1]:
                readings._native_readings = paths[path]
                stepper = ms.Stepper(system, dt=DT, integrator=integrator, q0=system.q0, v0=np.zeros(system.nv))
                tau = np.zeros(system.nv)
                for _ in range(50):  # warm up
                    stepper.step(tau)
                start = time.process_time()
                for _ in range(steps):
                    stepper.step(tau)
                times.setdefault((scene, path), []).append((time.process_time() - start) / steps * 1e6)
    readings._native_readings = paths["native"]
    print()
    print("| scene (actuators + sensors) | Stepper.step µs, native readings | Stepper.step µs, python readings |")
    print("|---|---:|---:|")
    for scene in scenes:
        native, python = (statistics.median(times[(scene, path)]) for path in ("native", "python"))
        print(f"| {scene} | {native:.1f} | {python:.1f} |")


if __name__ == "__main__":
    main()
