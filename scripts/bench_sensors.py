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
- both;
- without a rate: the sensors without their noise, bias and latency (both scenes), and ur5's IMU alone, without
  noise; and per scene the CPU time of its sensor set's noise draws per reading, timed beside the runs in each round
  (noise.NormalStream.fill, as SensorStream draws them), as a fraction of the bare step.

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
from multibody_sim.noise import NormalStream
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
        quiet = [{k: v for k, v in s.items() if k not in ("noise", "bias", "latency")} for s in go2_sensors(None)]
        legs = go2(False, quiet)
        out["go2_standing"]["sensors without noise, bias, latency"] = runner(
            legs, "timestepping", controller=legs.make_controller()
        )
    return out


def draws_cost(scene: str, steps: int) -> float:
    """CPU time of the noise draws the scene's sensor set makes in `steps` readings [µs per reading], drawn as
    SensorStream draws them (noise.NormalStream.fill, (steps, width) per noisy sensor)."""
    system = ur5(False, ur5_sensors(None)) if scene == "ur5" else go2(False, go2_sensors(None))
    sensors = system.sensors
    assert sensors is not None
    noisy = [p.width for p in sensors.placed if np.any(p.noise)]
    streams = [NormalStream(k) for k in range(len(noisy))]
    draws = [np.empty((steps, width)) for width in noisy]
    start = time.process_time()
    for stream, out in zip(streams, draws, strict=True):
        stream.fill(out)
    return (time.process_time() - start) / steps * 1e6


ENGINE = [0.0]  # CPU time spent inside the engine's calls (NativeCore.advance), see timed_engine()


def timed_engine() -> None:
    """Instrumentation: add the CPU time of every NativeCore.advance (the engine's stepping, with the small Python
    around each call) to ENGINE, so that a run's time splits into the engine's and the Python's around it."""
    from multibody_sim.kernels.native import NativeCore

    advance = NativeCore.advance

    def timed(self: Any, *args: Any, **kwargs: Any) -> Any:
        start = time.process_time()
        try:
            return advance(self, *args, **kwargs)
        finally:
            ENGINE[0] += time.process_time() - start

    NativeCore.advance = timed  # type: ignore[method-assign]


def cpu(run: Any, steps: int) -> tuple[float, float]:
    """CPU time of run(steps) [s], and of its engine calls."""
    ENGINE[0] = 0.0
    start = time.process_time()
    run(steps)
    return time.process_time() - start, ENGINE[0]


def measure(runs: dict[str, dict[str, Any]], rounds: int, steps: int) -> tuple[dict, dict, dict]:
    """Per variant, its µs per step in each round (and of them, inside the engine's calls); per scene (key (scene,
    "noise draws")), the CPU time of its sensor set's noise draws per reading in each round; and which kernel ran
    each variant."""
    kernels = {}
    for scene, table in runs.items():
        for label, run in table.items():
            batch = run(10)  # warm up, and say which kernel runs it
            kernels[(scene, label)] = batch.metadata["kernel"]
    times: dict[tuple[str, str], list[float]] = {key: [] for key in kernels}
    engine: dict[tuple[str, str], list[float]] = {key: [] for key in kernels}
    for scene in runs:
        times[(scene, "noise draws")] = []
    for _ in range(rounds):
        for scene, table in runs.items():
            for label, run in table.items():
                (long, long_engine), (short, short_engine) = cpu(run, steps), cpu(run, 1)
                times[(scene, label)].append((long - short) / (steps - 1) * 1e6)
                engine[(scene, label)].append((long_engine - short_engine) / (steps - 1) * 1e6)
            times[(scene, "noise draws")].append(draws_cost(scene, steps))
    return times, engine, kernels


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
    timed_engine()
    times, engine, kernels = measure(runs, args.rounds, args.steps)
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
        "Sensors read at every step unless a rate is given (the readings' noise, bias and latency are made once "
        "per call of the engine, by the extension's make_readings).",
        "",
        "| scene | variant | kernel | µs per step (median) | ratio to bare (median of per-round ratios) "
        "| of the µs, in the engine's calls | of the ratio's excess, in the engine's calls |",
        "|---|---|---|---:|---:|---:|---:|",
    ]
    for scene, table in runs.items():
        reference = times[(scene, "bare")]
        for label in table:
            ratios = [a / b for a, b in zip(times[(scene, label)], reference, strict=True)]
            inside = [
                (a - c) / b for a, b, c in zip(engine[(scene, label)], reference, engine[(scene, "bare")], strict=True)
            ]
            lines.append(
                f"| {scene} | {label} | {kernels[(scene, label)]} | {statistics.median(times[(scene, label)]):.2f} | "
                f"{statistics.median(ratios):.3f} | {statistics.median(engine[(scene, label)]):.2f} | "
                f"{statistics.median(inside):+.3f} |"
            )
        draws = times[(scene, "noise draws")]
        share = [a / b for a, b in zip(draws, reference, strict=True)]
        lines.append(
            f"| {scene} | its sensors' noise draws alone (timed beside the runs) | NormalStream | "
            f"{statistics.median(draws):.2f} | +{statistics.median(share):.3f} | | |"
        )
    lines += [
        "",
        "Reading the table: the last two columns split each variant's time: the part inside the engine's calls "
        "(NativeCore.advance, timed around each call: the stepping, the sensors' measurement and the samples' "
        "state; a little Python around each call), and that part's excess over the bare scene's, as a fraction of "
        "the bare step (the rest of the ratio's excess is Python after the engine: readings, recording, the "
        "trajectory). The last row of each scene is not a run: it is the CPU time of the noise draws its sensor "
        "set makes per reading (noise.NormalStream.fill, one per noisy component, as SensorStream draws them), "
        "timed in the same rounds, as a fraction of the bare step. Where the rest goes (perf profiles, and timers "
        "around the engine call apart from the Python around it): an IMU's "
        "(or frame_pose's) kinematics come from the next step's first ABA at the tick's state, which leaves each "
        "joint's calc, liMi and oMi as forwardKinematics computes them, so the engine adds only the acceleration "
        "recursion on the joints from the root to the sensor (ur5's tool0: all 6, written out for revolute joints "
        "about X, Y or Z; go2's base: 1 of 13) and the frame's quantities; a tick whose row takes no further step in "
        "the engine call, and every tick of a scene with a force-torque sensor (which needs the whole pass and an "
        "RNEA), gets a pass of its own. Joint sensors copy numbers (a joint_torque sensor with actuators evaluates "
        "their law at the tick); a contact_force sensor sums the step's impulses on its body. The readings are made "
        "once per engine call and row by the extension (readings.SensorStream, src/native/readings.hpp: latency, "
        "bias and noise sensor by sensor, the noise drawn by noise.hpp's ziggurat at ~1.6 ns a draw), in the "
        "samples' rows when the engine handed a lone row's measurements over there; the trajectory's sensors are "
        "views of that memory. The run's store is one block of memory that the C library reuses from run to run "
        "(no page faults in this benchmark's pattern of runs). "
        "Actuators evaluate their law and limits once per stage for both the torque and the ledger (below the "
        "speed where their limits are provably ± the effort limit without the curve's division or the brake's "
        "bounds), a sample's delivered torque comes from the next step's first evaluation, and they add their "
        "ledger lines (work, limits, brakes) to the integrated and recorded flows (summed per sample in one pass "
        "by the extension), the commands and the delivered torque to every sample, and the catalog motors' "
        "armature (go2) to the kinetic energies.",
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
