"""Actuators' targets (issue 25), measured: go2 under random actions with and without its actuator model, a stiff
position servo inside the step against the same gains held as a PD controller, and what actuators cost per step.

Writes docs/actuator_study.md (tables; the machine is shared and noisy: the cost ratios are medians of interleaved
rounds, each against its peer in the same run).

1. go2, random actions inside its action space (torques uniform within the effort limits, new every 2 ms), 40
   one-second episodes (seeds 0..39) per setup: free flight (the robot alone: rk4 and semi-implicit Euler) and
   go2_standing on the ground (timestepping), at dt = 1 and 2 ms; without an actuator model (today's ideal torques,
   clipped at the URDF's effort limits) and with the catalog's (actuators = "catalog": Unitree's gear ratios, rotor
   inertia, limits and torque–speed curve, with its overspeed brake, the default, and without it: overspeed =
   "none"; on the ground the brakes' velocity limits are also rows of the contact problem, the default, and the
   same without those rows: [contact] velocity_limits = "brake"). Counts the episodes that did not complete, the
   largest joint speed over its velocity limit, the share of joint samples past the limit and past the brake's band
   (1.1 times the limit), and the longest run of consecutive steps one joint spends past the band.
2. ur5 holding a pose 0.05 rad from its start against gravity with kp = 1e4 N·m/rad, kv = 100 N·m·s/rad on every
   joint (effort limits the URDF's, no velocity limit): position servos inside the step, against a PD with the same
   gains held over each step (control_dt = dt), on rk4 and semi-implicit Euler. A step is stable when the 1 s run
   completes, stays within 0.5 rad of the target and ends within 0.01 rad of it; the ladder runs from 0.1 s down
   by 2 and reports the largest stable step whose next smaller rung is stable too.
3. Cost per step, native kernel where it runs: ur5 (rk4, 1 ms) and go2_standing (timestepping, 1 ms) with the
   catalog's or declared actuators against the same scene without them, under the same torques; go2_standing's
   velocity-limit rows against the same motors without them.

Usage: python scripts/actuator_study.py [--quick] [--out docs/actuator_study.md]
"""

from __future__ import annotations

import argparse
import os
import time
from pathlib import Path

import numpy as np

import multibody_sim as ms
from multibody_sim.scenes import make_scene, shipped_scenes
from multibody_sim.scenes.parse import parse_toml

EPISODES = 40
CONTROL_DT = 2e-3


# ---- 1. go2 under random actions ---------------------------------------------------------------------------------
# The actuator models compared: none, the catalog's (on the ground with its velocity limits as contact rows), the same
# without those rows (ground only: free flight has no contact problem), without brakes (and so without rows).
MODELS = ("none", "catalog", "catalog, brake only", "catalog, no brake")
BAND = 0.1  # the catalog's overspeed band (the default): full braking torque 10 % past the limit


def go2_scene(ground: bool, model: str) -> ms.Scene:
    if ground:
        tables = parse_toml(shipped_scenes()["go2_standing"].read_text(), "go2_standing")
        tables.pop("controller")
        tables.pop("simulation", None)
    else:
        tables = {"robot": {"source": "go2"}}
    if model != "none":
        tables["actuators"] = "catalog"
    if model == "catalog, no brake":
        tables["actuator"] = [{"joints": "*", "overspeed": "none"}]
    if model == "catalog, brake only":
        tables["contact"] = {**tables.get("contact", {}), "velocity_limits": "brake"}
    return make_scene(**tables)


def show_ratio(x: float) -> str:
    """A speed / limit ratio: 3 digits, or its excess over 1 where that is below 1e-3 (the solver's tolerance)."""
    return f"1 + {x - 1:.1e}" if 1.0 < x < 1.001 else f"{x:.3g}"


def longest_run(over: np.ndarray) -> int:
    """The longest run of consecutive True along axis 1 of over (B, N, n), over every row and column."""
    best = 0
    run = np.zeros((over.shape[0], over.shape[2]), dtype=int)
    for k in range(over.shape[1]):
        run = np.where(over[:, k], run + 1, 0)
        best = max(best, int(run.max()))
    return best


def random_actions(scene: ms.Scene, episodes: int, duration: float) -> np.ndarray:
    """Torques uniform within the effort limits, a new draw every CONTROL_DT; episode b draws from seed b."""
    n = round(duration / CONTROL_DT)
    taus = np.zeros((episodes, n, scene.nv))
    limit = scene.effort_limit[6:]
    for b in range(episodes):
        taus[b, :, 6:] = np.random.default_rng(b).uniform(-limit, limit, size=(n, len(limit)))
    return taus


def go2_episodes(ground: bool, model: str, integrator: str, dt: float, episodes: int) -> dict:
    scene = go2_scene(ground, model)
    taus = random_actions(scene, episodes, 1.0)
    Q0, V0 = np.tile(scene.q0, (episodes, 1)), np.zeros((episodes, scene.nv))
    start = time.perf_counter()
    batch = ms.rollout(
        scene, Q0, V0, duration=1.0, dt=dt, integrator=integrator, taus=taus, control_dt=CONTROL_DT, progress=False
    )
    wall = time.perf_counter() - start
    limits = np.array(scene.model.velocityLimit)[6:]
    speeds = np.abs(batch.v[:, :, 6:])[batch.mask]  # (real samples, 12)
    over = (speeds / limits).max(axis=0)
    failed = batch.status != "completed"
    ran = np.abs(batch.v[:, :, 6:]) * batch.mask[:, :, None]  # samples that ran (0 after a run stopped)
    return {
        "past_limit": float((speeds > limits).mean()),
        "past_band": float((speeds > (1 + BAND) * limits).mean()),
        "longest_past_band": longest_run(ran > (1 + BAND) * limits),
        "failed": int(failed.sum()),
        "statuses": sorted(set(batch.status[failed].tolist())),
        "worst_speed_ratio": float(over.max()),
        "worst_joint": scene.dof_names[6 + int(over.argmax())],
        "kernel": batch.metadata.get("kernel", ""),
        "wall": wall,
    }


# ---- 2. the stiff servo ------------------------------------------------------------------------------------------
KP, KV, OFFSET = 1e4, 100.0, 0.05


def ur5_servo_run(dt: float, integrator: str, inside: bool) -> bool:
    """Whether the 1 s hold is stable at dt (module docstring)."""
    if inside:
        scene = make_scene(
            robot={"source": "ur5"},
            actuator=[{"joints": "*", "kind": "position", "kp": KP, "kv": KV, "velocity_limit": 1e9}],
        )
        target = scene.q0 + OFFSET
        controller = lambda t, q, v: target  # noqa: E731
    else:
        scene = make_scene(robot={"source": "ur5"})
        target = scene.q0 + OFFSET
        reference = ",".join(repr(float(x)) for x in target)
        controller = ms.make_controller("pd", scene, [f"kp={KP}", f"kd={KV}", f"q_ref={reference}"])
    try:
        traj = ms.simulate(
            scene, scene.q0, np.zeros(6), duration=1.0, dt=dt, integrator=integrator, controller=controller,
            output_dt=None, progress=False,
        )  # fmt: skip
    except ms.SimulationError:
        return False
    error = np.abs(traj.q - target)
    return bool(np.isfinite(error).all() and error.max() <= 0.5 and error[-1].max() <= 0.01)


def largest_stable(integrator: str, inside: bool, smallest: float) -> tuple[float | None, int]:
    """The largest rung of 0.1 / 2^k (down to `smallest`) that is stable with its next smaller rung stable too."""
    dt, previous, tried = 0.1, None, 0
    while dt >= smallest:
        tried += 1
        stable = ur5_servo_run(dt, integrator, inside)
        if stable and previous is not None and previous[1]:
            return previous[0], tried
        previous = (dt, stable)
        dt /= 2
    return (previous[0] if previous and previous[1] else None), tried


# ---- 3. cost -----------------------------------------------------------------------------------------------------
def cost_pair(name: str, plain: ms.Scene, actuated: ms.Scene, integrator: str, commands: np.ndarray,
              steps: int, rounds: int) -> dict:  # fmt: skip
    """CPU µs per step of each scene under the same commands (rollout of one row, every step sampled), medians of
    interleaved rounds, and their ratio."""
    times: dict[str, list[float]] = {"plain": [], "actuated": []}
    kernels = {}
    taus = np.repeat(commands[None, None], steps, axis=1)
    for _ in range(rounds):
        for label, scene in (("plain", plain), ("actuated", actuated)):
            start = time.process_time()
            batch = ms.rollout(scene, scene.q0[None], np.zeros((1, scene.nv)), duration=steps * 1e-3, dt=1e-3,
                               integrator=integrator, taus=taus, progress=False)  # fmt: skip
            times[label].append((time.process_time() - start) / steps * 1e6)
            kernels[label] = batch.metadata.get("kernel", "")
    plain_us, actuated_us = (float(np.median(times[k])) for k in ("plain", "actuated"))
    kernel = kernels["plain"]
    if kernels["actuated"] != kernel:
        kernel = f"{kernel} / {kernels['actuated']}"
    return {"name": name, "plain": plain_us, "actuated": actuated_us, "ratio": actuated_us / plain_us, "kernel": kernel}


def costs(steps: int, rounds: int) -> list[dict]:
    rows = []
    ur5 = make_scene(robot={"source": "ur5"})
    servos = [{"joints": "*", "kind": "position", "kp": 1e3, "kv": 30.0}]
    ur5_servo = make_scene(robot={"source": "ur5"}, actuator=servos)
    ur5_torque = make_scene(robot={"source": "ur5"}, actuator=[{"joints": "*", "rotor_inertia": 1e-4, "gear": 50.0}])
    hold = np.zeros(6)
    rows.append(cost_pair("ur5, rk4: torque actuators (gear, rotor)", ur5, ur5_torque, "rk4", hold, steps, rounds))
    rows.append(cost_pair("ur5, rk4: position servos", ur5, ur5_servo, "rk4", ur5.q0, steps, rounds))
    go2 = go2_scene(ground=True, model="none")
    go2_model = go2_scene(ground=True, model="catalog")
    go2_unbraked = go2_scene(ground=True, model="catalog, no brake")
    rows.append(cost_pair("go2_standing, timestepping: catalog motors", go2, go2_model, "timestepping",
                          np.zeros(go2.nv), steps, rounds))  # fmt: skip
    rows.append(cost_pair("go2_standing, timestepping: catalog motors without brakes", go2, go2_unbraked,
                          "timestepping", np.zeros(go2.nv), steps, rounds))  # fmt: skip
    go2_braked = go2_scene(ground=True, model="catalog, brake only")
    rows.append(cost_pair("go2_standing, timestepping: catalog motors, velocity-limit rows against brakes only",
                          go2_braked, go2_model, "timestepping", np.zeros(go2.nv), steps, rounds))  # fmt: skip
    return rows


# ---- the report --------------------------------------------------------------------------------------------------
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="8 episodes, a short cost run (a smoke test)")
    parser.add_argument("--out", type=Path, default=Path("docs/actuator_study.md"))
    args = parser.parse_args()
    episodes = 8 if args.quick else EPISODES
    lines = [
        "# Actuators: measured targets",
        "",
        f"Generated by `.venv/bin/python scripts/{Path(__file__).name}`; do not edit by hand. The model and the "
        "go2 data's sources: docs/actuators.md.",
        "",
        f"## 1. go2 under random actions ({episodes} one-second episodes per row)",
        "",
        "Torques uniform within the effort limits, a new draw every 2 ms, episode b from seed b; the same draws "
        "with and without the actuator model. *catalog*: Unitree's motors with their overspeed brake (the default; "
        f"full braking torque {100 * BAND:g} % past the limit) and, on the ground, their velocity limits as "
        "constraints of the time-stepper's contact problem (the default; docs/actuators.md); *catalog, brake only*: "
        '(ground) the same without those constraints, `[contact] velocity_limits = "brake"`; *catalog, no brake*: '
        'the same with `overspeed = "none"` (no brake, no constraint). *speed / limit*: the largest joint speed over '
        "its velocity limit (URDF: 30.1 rad/s hip and thigh, "
        "15.7 rad/s calf) in any sample of any episode that ran; *past limit*, *past band*: the share of joint "
        f"samples (every step is sampled) faster than the limit, and than {1 + BAND:g} times it; *longest past band*: "
        "the most consecutive steps one joint spent faster than that.",
        "",
        "| setup | integrator | dt | actuator model | did not complete | speed / limit (joint) | past limit | "
        "past band | longest past band [steps] | kernel |",
        "|---|---|---:|---|---:|---|---:|---:|---:|---|",
    ]
    worst: dict = {}  # per (ground, model): the largest speed / limit, the longest run past the band
    for ground, integrator in ((False, "rk4"), (False, "semi_implicit_euler"), (True, "timestepping")):
        for dt in (1e-3, 2e-3):
            for model in MODELS:
                if model == "catalog, brake only" and not ground:
                    continue
                r = go2_episodes(ground, model, integrator, dt, episodes)
                ratio, run = worst.get((ground, model), (0.0, 0))
                worst[ground, model] = (max(ratio, r["worst_speed_ratio"]), max(run, r["longest_past_band"]))
                failed = f"{r['failed']} of {episodes}" + (f" ({', '.join(r['statuses'])})" if r["failed"] else "")
                lines.append(
                    f"| {'go2_standing (ground)' if ground else 'free flight'} | {integrator} | {dt * 1e3:g} ms | "
                    f"{model} | {failed} | {show_ratio(r['worst_speed_ratio'])} ({r['worst_joint']}) | "
                    f"{100 * r['past_limit']:.2g} % | {100 * r['past_band']:.2g} % | {r['longest_past_band']} | "
                    f"{r['kernel']} |"
                )
                print(lines[-1], flush=True)
    flight, ground_ = worst[False, "catalog"], worst[True, "catalog"]
    old_flight, old_ground = worst[False, "catalog, no brake"], worst[True, "catalog, no brake"]
    braked = worst[True, "catalog, brake only"]
    lines += [
        "",
        "Reading: with the catalog's model no episode fails at 1 or 2 ms on any setup; without it, semi-implicit "
        "Euler diverges in free flight (the legs' small inertias under 23.7 and 45.43 N·m) and every setup spins "
        "joints to tens of times their rated speed. The drive never drives a joint past its velocity limit; past it, "
        "the overspeed brake acts against the motion whatever the command, rising to the full effort limit "
        f"{100 * BAND:g} % past it. In free flight (the other joints' motion carries a joint on) it holds the "
        f"joints within {flight[0]:.3g} times their limits (without the brake: {old_flight[0]:.3g}), "
        + (f"with at most {flight[1]} consecutive steps past the band" if flight[1] else "never past the band")
        + ". On the ground the feet's impacts change joint speeds within a step by impulses that no finite torque "
        f"can stop in that step: with the brake alone joints reach {braked[0]:.3g} times their limits, and the "
        f"brake brings them back within the band in at most {braked[1]} steps (without the brake: "
        f"{old_ground[0]:.3g} times, up to {old_ground[1]} steps past the band). With the velocity limits as "
        "constraints of the contact problem, solved with the impacts, every joint sample stays within "
        f"{show_ratio(ground_[0])} times its limit (the solver's tolerance is 1e-9 of the step's velocity scale), "
        "never past the band; *past limit* counts those samples within the tolerance.",
        "",
        "## 2. A stiff position servo inside the step, against the same gains held as a PD",
        "",
        f"ur5 holding its start pose + {OFFSET} rad on every joint against gravity, kp = {KP:g} N·m/rad and "
        f'kv = {KV:g} N·m·s/rad, the URDF\'s effort limits (150 and 28 N·m), for 1 s. *Servo*: `kind = "position"` '
        "actuators (evaluated at every stage; semi-implicit Euler takes kv and kp inside the step). *Held PD*: the "
        "built-in `pd` controller with the same gains, called at every step and held over it. Stable: the run "
        "completes, stays within 0.5 rad of the target and ends within 0.01 rad; the largest such step of 0.1 s / 2^k "
        "whose next smaller rung is stable too.",
        "",
        "| integrator | servo: largest stable dt | held PD: largest stable dt | ratio |",
        "|---|---:|---:|---:|",
    ]
    smallest = 1e-4 if args.quick else 1e-6
    ladder = {}
    for integrator in ("rk4", "semi_implicit_euler"):
        servo, _ = largest_stable(integrator, True, smallest)
        held, _ = largest_stable(integrator, False, smallest)
        ladder[integrator] = (servo, held)
        ratio = f"{servo / held:.3g}" if servo and held else "—"
        show = lambda x: f"{x:.3g} s" if x else f"< {smallest:g} s"  # noqa: E731
        lines.append(f"| {integrator} | {show(servo)} | {show(held)} | {ratio} |")
        print(lines[-1], flush=True)
    lines += [
        "",
        "Reading: with the servo's kv and kp inside the step, semi-implicit Euler holds the pose at steps up to "
        f"{ladder['semi_implicit_euler'][0] or 0:.3g} s (the ladder's top, 0.1 s, is a cap, not a limit); the same "
        f"gains held as a PD need {ladder['semi_implicit_euler'][1] or 0:.3g} s. RK4 has no implicit terms: it "
        "evaluates the servo at every stage, so the stiff servo mode (kv over the wrist's small inertia) bounds its "
        f"step ({ladder['rk4'][0] or 0:.3g} s) as any stiff force does, against {ladder['rk4'][1] or 0:.3g} s for "
        "the held PD, whose gains act once per step on the state sampled at its start.",
    ]
    steps, rounds = (200, 3) if args.quick else (2000, 7)
    lines += [
        "",
        "## 3. Cost per step",
        "",
        f"CPU µs per step (medians of {rounds} interleaved rounds of {steps} steps at 1 ms, one row, every step "
        "sampled), each scene against its peer (the same scene without actuators; for the velocity-limit rows, the "
        "same motors without them), under the same commands.",
        "",
        "| scene | peer [µs] | scene [µs] | ratio | kernels |",
        "|---|---:|---:|---:|---|",
    ]
    load = os.getloadavg()[0]
    for r in costs(steps, rounds):
        lines.append(f"| {r['name']} | {r['plain']:.2f} | {r['actuated']:.2f} | {r['ratio']:.3f} | {r['kernel']} |")
        print(lines[-1], flush=True)
    lines += [
        "",
        f"Reading: measured with the machine's load average at {load:.1f} (shared; repeated runs differ by a few "
        "percent). On ur5 the actuators are evaluated at every RK4 stage with their ledger lines (the URDF's limits "
        "give each an overspeed brake and its line). On go2_standing under zero commands the actuators change the "
        "motion itself (the legs fold under the robot's weight: with the catalog's motors and brakes at joint speeds "
        "up to 16 rad/s, without a model up to 135 rad/s, without the brakes 46 rad/s, over 2 s at 1 ms), and with it "
        "the contact problems the steps solve: that ratio compares different motions, not an overhead. The "
        "velocity-limit rows' row is the same motors with and without the rows, under the same zero commands: the "
        "calves fold at up to their limit, so rows join some steps and there hold the calves at it, which changes "
        "the motion a little too; where no joint comes within 2 % of its limit "
        "the rows add no row and no solve (tests/test_velocity_limits.py: the same problems, solver iterations "
        "and samples bit for bit as without them).",
    ]
    args.out.write_text("\n".join(lines) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
