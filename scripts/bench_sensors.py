"""What a scene's sensors cost per step on the native kernel (issue 25's target: actuators and sensors add at most 10 %
per step on ur5 and go2_standing).

Writes docs/sensor_cost.md. For each scene, round-robin (each figure is a median over rounds in which every variant
ran once, under the same load), the CPU time per step of `simulate` on the native kernel, sampling every step, of:

- the scene without sensors (the reference);
- the scene with a typical set, read at every step: ur5 (rk4, dt = 1 ms, a PD controller inside the engine): an
  IMU at tool0, joint positions, velocities and torques; go2_standing (timestepping, dt = 1 ms, its PD + gravity
  controller): an IMU at the base, the four feet's contact forces, joint positions and velocities;
- the same with force-torque sensors added (ur5: at the wrist's frame and the elbow; go2: at the four hips), which
  take one RNEA per reading.

Each variant's time per step is a long run's CPU time minus a one-step run's (the fixed cost per call), over the
steps between them. Noise, bias and latency are declared on some sensors, so the readings' Python side (drawn per
call of the engine, not per step) is included.

Usage:
    .venv/bin/python scripts/bench_sensors.py [--rounds 15] [--steps 2000]
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
from multibody_sim.scenes.parse import parse_scene

ROOT = Path(__file__).resolve().parent.parent
DT = 1e-3


def ur5(extra: list[dict[str, Any]]) -> ms.Scene:
    return ms.make_scene(robot={"source": "ur5"}, sensor=extra)


def noiseless(sensors: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [{k: v for k, v in s.items() if k not in ("noise", "bias", "latency")} for s in sensors]


def ur5_sensors(ft: bool) -> list[dict[str, Any]]:
    sensors: list[dict[str, Any]] = [
        {"name": "imu", "kind": "imu", "frame": "tool0", "noise": 0.01, "bias": 0.001, "latency": 1},
        {"name": "enc", "kind": "joint_position", "noise": 1e-4},
        {"name": "gyro", "kind": "joint_velocity", "noise": 1e-3},
        {"name": "tq", "kind": "joint_torque"},
    ]
    if ft:
        sensors += [
            {"name": "wrist", "kind": "force_torque", "frame": "ee_fixed_joint", "noise": 0.1},
            {"name": "elbow", "kind": "force_torque", "joint": "elbow_joint"},
        ]
    return sensors


def go2(extra: list[dict[str, Any]]) -> ms.Scene:
    import dataclasses

    scene = ms.load_scene(ROOT / "models" / "scenes" / "go2_standing.toml")
    parsed = parse_scene({"robot": {"source": "go2"}, "sensor": extra}, "<bench>", base_dir=None)
    return ms.Scene(dataclasses.replace(scene.spec, sensors=parsed.sensors))


def go2_sensors(ft: bool) -> list[dict[str, Any]]:
    legs = ("FL", "FR", "RL", "RR")
    sensors: list[dict[str, Any]] = [{"name": "imu", "kind": "imu", "frame": "base", "noise": 0.05, "latency": 1}]
    sensors += [{"name": f"{leg}_touch", "kind": "contact_force", "body": f"{leg}_foot", "noise": 0.5} for leg in legs]
    sensors += [
        {"name": "enc", "kind": "joint_position", "noise": 1e-4},
        {"name": "gyro", "kind": "joint_velocity", "noise": 1e-3},
    ]
    if ft:
        sensors += [{"name": f"{leg}_hip", "kind": "force_torque", "joint": f"{leg}_hip_joint"} for leg in legs]
    return sensors


def runner(scene: ms.Scene, integrator: str, controller: Any, q0: np.ndarray, v0: np.ndarray) -> Any:
    def run(steps: int) -> ms.Trajectory:
        return ms.simulate(
            scene, q0, v0, duration=steps * DT, dt=DT, integrator=integrator, controller=controller, progress=False
        )

    return run


def variants() -> dict[str, dict[str, Any]]:
    """scene name -> variant name -> run(steps)."""
    out: dict[str, dict[str, Any]] = {}
    arm = ur5([])
    rng = np.random.default_rng(0)
    q0 = arm.q0 + rng.uniform(-0.3, 0.3, arm.nv)
    v0 = rng.normal(0.0, 0.1, arm.nv)
    out["ur5"] = {}
    for label, sensors in (
        ("none", []),
        ("typical, noiseless", noiseless(ur5_sensors(False))),
        ("typical", ur5_sensors(False)),
        ("typical + force-torque", ur5_sensors(True)),
    ):
        scene = ur5(sensors) if sensors else arm
        pd = ms.PD(scene, q_ref=arm.q0, kp=100.0, kd=10.0)
        out["ur5"][label] = runner(scene, "rk4", pd, q0, v0)
    out["go2_standing"] = {}
    for label, sensors in (
        ("none", []),
        ("typical, noiseless", noiseless(go2_sensors(False))),
        ("typical", go2_sensors(False)),
        ("typical + force-torque", go2_sensors(True)),
    ):
        scene = go2(sensors) if sensors else go2([])
        if not sensors:
            scene = ms.load_scene(ROOT / "models" / "scenes" / "go2_standing.toml")
        out["go2_standing"][label] = runner(scene, "timestepping", scene.make_controller(), scene.q0, scene.v0)
    return out


def cpu(run: Any, steps: int) -> float:
    start = time.process_time()
    run(steps)
    return time.process_time() - start


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--steps", type=int, default=2000)
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "sensor_cost.md")
    args = parser.parse_args()
    started = time.time()
    load_before = os.getloadavg()[0]
    runs = variants()
    kernels = {}
    for scene, table in runs.items():
        for label, run in table.items():
            traj = run(10)  # warm up, and say which kernel runs it
            kernels[(scene, label)] = traj.metadata["kernel"]
    times: dict[tuple[str, str], list[float]] = {key: [] for key in kernels}
    for _ in range(args.rounds):
        for scene, table in runs.items():
            for label, run in table.items():
                long, short = cpu(run, args.steps), cpu(run, 1)
                times[(scene, label)].append((long - short) / (args.steps - 1) * 1e6)
    # per round ratios to the same round's reference, then their median (load drifts between rounds)
    lines = [
        "# What sensors cost per step (native kernel)",
        "",
        "Generated by `scripts/bench_sensors.py`; do not edit by hand.",
        "",
        f"- Command: `.venv/bin/python scripts/bench_sensors.py --rounds {args.rounds} --steps {args.steps}`",
        f"- Date: {datetime.datetime.now(datetime.timezone.utc):%Y-%m-%d %H:%M} UTC; the whole run took "
        f"{time.time() - started:.0f} s",
        f"- Machine: {platform.processor() or platform.machine()}, {os.cpu_count()} cores, shared (1-minute load "
        f"{load_before:.1f} at the start, {os.getloadavg()[0]:.1f} at the end): every variant runs once per round, "
        "round-robin; figures are medians over the rounds, ratios are per round to the same round's scene without "
        "sensors, then their median.",
        "- Workload: `simulate(scene, ..., dt=0.001)` sampling every step: ur5 with rk4 and a PD controller (in the "
        "engine), go2_standing with timestepping and its PD + gravity controller (in the engine); CPU time of a "
        f"{args.steps}-step run minus a one-step run, per step. Sensors read at every step (their default rate "
        "without control_dt), with noise, bias and latency on some (the readings are made in Python once per call "
        "of the engine).",
        "",
        "| scene | sensors | kernel | µs per step (median) | ratio to no sensors (median of per-round ratios) |",
        "|---|---|---|---|---|",
    ]
    for scene, table in runs.items():
        reference = times[(scene, "none")]
        for label in table:
            ratios = [a / b for a, b in zip(times[(scene, label)], reference, strict=True)]
            lines.append(
                f"| {scene} | {label} | {kernels[(scene, label)]} | {statistics.median(times[(scene, label)]):.2f} | "
                f"{statistics.median(ratios):.3f} |"
            )
    lines += [
        "",
        "Reading the table: a reading of an IMU takes a second-order kinematics pass (forwardKinematics with the "
        "step's acceleration) and the frame's velocity and acceleration, in the engine; joint sensors copy numbers; "
        "a force-torque sensor adds an RNEA (with the contact forces as external forces). The readings' Python side "
        "(noise, bias, latency, the samples' held readings) runs once per call of the engine, vectorised: its "
        "noise draws (numpy's standard_normal, ~18 ns each here) are most of it. Issue 25's target is at most 10 % "
        "per step with actuators and sensors; actuators run on the Python kernel, so only the sensors' share is "
        "measured here.",
        "",
        "Sensors (ur5): " + ", ".join(f"{s['name']} ({s['kind']})" for s in ur5_sensors(True)) + ".",
        "Sensors (go2_standing): " + ", ".join(f"{s['name']} ({s['kind']})" for s in go2_sensors(True)) + ".",
        "",
    ]
    args.out.write_text("\n".join(lines))
    print("\n".join(lines))


if __name__ == "__main__":
    main()
