"""What actuators and sensors cost per step on the native kernel (issue 25's target: together they add at most 10 %
per step on ur5 and go2_standing).

Writes docs/sensor_cost.md. For each scene, four variants run round-robin (each figure is a median over rounds in
which every variant ran once, under the same load; each ratio is taken per round against the same round's bare
scene, then its median):

- bare: the scene as shipped (the reference);
- actuators: ur5 with position servos on every joint (kp = 1e3 N·m/rad, kv = 30 N·m·s/rad, held at its start
  pose by a constant target), go2_standing with the catalog's motors (actuators = "catalog": gear, rotor inertia,
  limits, torque–speed curve) under its PD + gravity controller;
- sensors: a typical set read at every step: ur5: an IMU at tool0 (noise, bias, latency), joint positions and
  velocities (noise) and torques; go2_standing: an IMU at the base (noise, latency), the four feet's contact forces
  (noise), joint positions and velocities (noise);
- both.

The workload is a rollout of one row on the native kernel, sampling every step at dt = 1 ms: ur5 with rk4,
go2_standing with the time-stepper. A variant's time per step is a long run's CPU time minus a one-step run's (the
fixed cost per call), over the steps between them. `--rate` also measures the sensors read at that rate [Hz]
instead of every step (as a controller at that rate would read them).

Usage:
    .venv/bin/python scripts/bench_sensors.py [--rounds 15] [--steps 4000] [--rate 500]
"""

from __future__ import annotations

import argparse
import datetime
import os
import platform
import statistics
import time
from pathlib import Path
from typing import Any

import numpy as np

import multibody_sim as ms
from multibody_sim.scenes import make_scene, shipped_scenes
from multibody_sim.scenes.parse import parse_toml

ROOT = Path(__file__).resolve().parent.parent
DT = 1e-3
UR5_SERVOS = [{"joints": "*", "kind": "position", "kp": 1e3, "kv": 30.0}]


def ur5_sensors(rate: float | None) -> list[dict[str, Any]]:
    sensors: list[dict[str, Any]] = [
        {"name": "imu", "kind": "imu", "frame": "tool0", "noise": 0.01, "bias": 0.001, "latency": 1},
        {"name": "enc", "kind": "joint_position", "noise": 1e-4},
        {"name": "gyro", "kind": "joint_velocity", "noise": 1e-3},
        {"name": "tq", "kind": "joint_torque"},
    ]
    return [{**s, "rate": rate} for s in sensors] if rate else sensors


def go2_sensors(rate: float | None) -> list[dict[str, Any]]:
    legs = ("FL", "FR", "RL", "RR")
    sensors: list[dict[str, Any]] = [{"name": "imu", "kind": "imu", "frame": "base", "noise": 0.05, "latency": 1}]
    sensors += [{"name": f"{leg}_touch", "kind": "contact_force", "body": f"{leg}_foot", "noise": 0.5} for leg in legs]
    sensors += [
        {"name": "enc", "kind": "joint_position", "noise": 1e-4},
        {"name": "gyro", "kind": "joint_velocity", "noise": 1e-3},
    ]
    return [{**s, "rate": rate} for s in sensors] if rate else sensors


def ur5(actuators: bool, sensors: list[dict[str, Any]]) -> ms.Scene:
    return make_scene(robot={"source": "ur5"}, actuator=UR5_SERVOS if actuators else [], sensor=sensors)


def go2(actuators: bool, sensors: list[dict[str, Any]]) -> ms.Scene:
    tables = parse_toml(shipped_scenes()["go2_standing"].read_text(), "go2_standing")
    tables.pop("simulation", None)
    if actuators:
        tables["actuators"] = "catalog"
    return make_scene(**tables, sensor=sensors)


def runner(scene: ms.Scene, integrator: str, **commands: Any) -> Any:
    """run(steps): a one-row native rollout of `steps` steps under the same commands (a controller, or `taus`
    held: (nv,))."""
    q0, v0 = scene.q0[None], np.zeros((1, scene.nv))

    def run(steps: int) -> ms.BatchTrajectory:
        extra = dict(commands)
        if "taus" in extra:
            extra["taus"] = np.repeat(extra["taus"][None, None], steps, axis=1)
        return ms.rollout(scene, q0, v0, duration=steps * DT, dt=DT, integrator=integrator, progress=False, **extra)

    return run


def variants(rate: float | None) -> dict[str, dict[str, Any]]:
    """scene name -> variant name -> run(steps)."""
    out: dict[str, dict[str, Any]] = {"ur5": {}, "go2_standing": {}}
    suffix = f", sensors at {rate:g} Hz" if rate else ""
    for actuators, sensors, label in (
        (False, False, "bare"),
        (True, False, "actuators"),
        (False, True, "sensors"),
        (True, True, "actuators + sensors"),
    ):
        if rate and not sensors:
            continue
        name = label + (suffix if sensors else "")
        arm = ur5(actuators, ur5_sensors(rate) if sensors else [])
        # the same command: the start pose, a servo's target or (bare) a small torque
        out["ur5"][name] = runner(arm, "rk4", taus=arm.q0.copy())
        legs = go2(actuators, go2_sensors(rate) if sensors else [])
        out["go2_standing"][name] = runner(legs, "timestepping", controller=legs.make_controller())
    if not rate:  # where the sensors' time goes: their measurement without the readings' noise, and the IMU alone
        clean = [{k: v for k, v in s.items() if k not in ("noise", "bias", "latency")} for s in ur5_sensors(None)]
        imu: list[dict[str, Any]] = [{"name": "imu", "kind": "imu", "frame": "tool0"}]
        for label, chosen in (("sensors without noise, bias, latency", clean), ("the IMU alone, without noise", imu)):
            arm = ur5(False, chosen)
            out["ur5"][label] = runner(arm, "rk4", taus=arm.q0.copy())
    return out


def cpu(run: Any, steps: int) -> float:
    start = time.process_time()
    run(steps)
    return time.process_time() - start


def measure(runs: dict[str, dict[str, Any]], rounds: int, steps: int) -> tuple[dict, dict]:
    kernels = {}
    for scene, table in runs.items():
        for label, run in table.items():
            batch = run(10)  # warm up, and say which kernel runs it
            kernels[(scene, label)] = batch.metadata["kernel"]
    times: dict[tuple[str, str], list[float]] = {key: [] for key in kernels}
    for _ in range(rounds):
        for scene, table in runs.items():
            for label, run in table.items():
                long, short = cpu(run, steps), cpu(run, 1)
                times[(scene, label)].append((long - short) / (steps - 1) * 1e6)
    return times, kernels


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--steps", type=int, default=4000)
    parser.add_argument("--rate", type=float, default=None, help="also the sensors read at this rate [Hz]")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "sensor_cost.md")
    args = parser.parse_args()
    started = time.time()
    load_before = os.getloadavg()[0]
    runs = variants(None)
    if args.rate:
        for scene, table in variants(args.rate).items():
            runs[scene].update(table)
    times, kernels = measure(runs, args.rounds, args.steps)
    command = f".venv/bin/python scripts/bench_sensors.py --rounds {args.rounds} --steps {args.steps}"
    command += f" --rate {args.rate:g}" if args.rate else ""
    lines = [
        "# What actuators and sensors cost per step (native kernel)",
        "",
        "Generated by `scripts/bench_sensors.py`; do not edit by hand.",
        "",
        f"- Command: `{command}`",
        f"- Date: {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC; the whole run took "
        f"{time.time() - started:.0f} s",
        f"- Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, shared with other jobs "
        f"(1-minute load {load_before:.1f} at the start, {os.getloadavg()[0]:.1f} at the end), so single figures "
        "are noisy: every variant runs once per round, round-robin; times are medians over the rounds, ratios are "
        "per round to the same round's bare scene, then their median.",
        "- Workload: a one-row `rollout` at dt = 1 ms sampling every step: ur5 with rk4 under a constant command "
        "(bare: a torque; with servos: their target, the start pose), go2_standing with the time-stepper under its "
        f"PD + gravity controller (in the engine); CPU time of a {args.steps}-step run minus a one-step run, per step. "
        "Sensors read at every step unless a rate is given (the readings' noise, bias and latency are made in "
        "Python once per call of the engine).",
        "",
        "| scene | variant | kernel | µs per step (median) | ratio to bare (median of per-round ratios) |",
        "|---|---|---|---:|---:|",
    ]
    for scene, table in runs.items():
        reference = times[(scene, "bare")]
        for label in table:
            ratios = [a / b for a, b in zip(times[(scene, label)], reference, strict=True)]
            lines.append(
                f"| {scene} | {label} | {kernels[(scene, label)]} | {statistics.median(times[(scene, label)]):.2f} | "
                f"{statistics.median(ratios):.3f} |"
            )
    lines += [
        "",
        "Reading the table: an IMU's reading takes a second-order forward-kinematics pass (Pinocchio's per-joint "
        "step, on the joints from the root to the IMU's only: go2's base IMU 1 joint of 13, ur5's tool0 all 6) and "
        "the frame's placement, velocity and classical acceleration, in the engine; joint sensors copy numbers "
        "(a joint_torque sensor with actuators evaluates their law at the tick); a contact_force sensor sums the "
        "step's impulses on its body. The readings are made in Python once per call of the engine, vectorised: "
        "their cost is mostly the noise draws (numpy PCG64 standard_normal, one per noisy component per reading, "
        "~12 ns each here: the ur5 set draws 18 per step). ur5's bare step is ~5 µs (rk4 over 6 joints), so there the "
        "IMU's kinematics pass alone is about a tenth of a step (its row above) and the targeted 10 % for actuators "
        "and sensors together is not met; go2_standing's step is ~30 µs. A force-torque sensor (not in these sets) "
        "adds an RNEA per reading.",
        "",
        "Actuators (ur5): position servos on every joint, kp = 1e3, kv = 30; (go2_standing): the catalog's motors.",
        "Sensors (ur5): " + ", ".join(f"{s['name']} ({s['kind']})" for s in ur5_sensors(None)) + ".",
        "Sensors (go2_standing): " + ", ".join(f"{s['name']} ({s['kind']})" for s in go2_sensors(None)) + ".",
        "",
    ]
    args.out.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
