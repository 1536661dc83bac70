"""Benchmark of batched RK4 rollouts against their Pinocchio floor and MuJoCo.

Writes docs/rollout_cost.md. For each robot, in one run and round-robin (the machine is shared and noisy, so
each figure is a median over rounds in which every variant was timed once, under the same conditions), in CPU
µs per state-step (one state advanced by one step):

- ours: ``simulate`` (one state) and ``rollout`` over a batch of B states (output every step, the default,
  and every 10 steps; and every 10 steps with open-loop torques, whose power the energy ledger integrates),
  RK4, dt = 1 ms, robots loaded with ``damping=False``;
- the Pinocchio floor: 4 × ``pin.aba`` per state in a Python loop, and 4 × ``pin.abaInParallel`` (one thread)
  over the batch, per state: what four ABA calls cost without Python in between;
- MuJoCo on the same URDF (RK4, contacts, limits and equality constraints off, damping and armature zeroed):
  ``mj_step`` in a Python loop and ``mujoco.rollout`` over the same B states on one thread;
- for floating robots, the same robot with its base welded (``floating_base=False``): rollout and floor, so
  that the free-flyer's share (configuration update and chart map) shows.

Ratios are medians of per-round ratios: in each round the floor, rollout and mujoco.rollout run back to back,
so that the load of the moment weighs on all three alike. Then the scaling over the batch size (CPU time) and
over cores (wall time: abaInParallel's threads, MuJoCo's threads and, with Ray installed, the Ray backend on a
local two-CPU instance).

Usage:
    .venv/bin/python scripts/bench_rollout.py [--repeats 9] [--steps 200] [--batch 128] [--no-ray]
"""

from __future__ import annotations

import argparse
import datetime
import math
import os
import statistics
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from multibody_sim import BatchTrajectory, load_robot, make_scene, rollout, simulate

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_step_cost import (  # noqa: E402  (a sibling script: the same MuJoCo model and state map)
    StateMap,
    cpu_name,
    load_average,
    mj_set_state,
    mujoco,
    mujoco_model,
    para,
    table,
)

try:
    from mujoco import rollout as mj_rollout
except ImportError:
    mj_rollout = None

ROBOTS = ("double_pendulum", "ur5", "panda", "solo12", "talos")
SCALING_ROBOTS = ROBOTS  # all five: the target is judged over batch sizes too
BATCHES = (1, 4, 16, 64, 256, 1024)
DT = 1e-3
SEED = 0
V0_SCALE = 0.1  # standard deviation of the Gaussian initial velocities [rad/s, m/s]
TARGET = 1.2  # issue 14's target: batched RK4 per state-step within 1.2 x four ABA calls, output every 10 steps
TARGET_EVERY_STEP = 1.1  # issue 15's (the native kernel): within 1.1 x the floor with output every step
_WORLD = pin.Convention.WORLD
ROOT = Path(__file__).resolve().parent.parent


def median(values: list[float]) -> float:
    return statistics.median(values) if values else math.nan


def fmt(x: float | None, digits: int = 2) -> str:
    if x is None or math.isnan(x):
        return "—"
    return f"{x:.{digits}f}"


def cpu_us(fn: Callable[[], Any], state_steps: int) -> float:
    """CPU µs per state-step of one call of fn."""
    start = time.process_time()
    fn()
    return (time.process_time() - start) / state_steps * 1e6


def wall_us(fn: Callable[[], Any], state_steps: int) -> float:
    start = time.perf_counter()
    fn()
    return (time.perf_counter() - start) / state_steps * 1e6


@dataclass
class Bench:
    """One robot's workload: its batch of states and the timed variants (name -> callable, state-steps)."""

    name: str
    robot: Any
    Q0: np.ndarray
    V0: np.ndarray
    steps: int
    runs: dict[str, list[float]] = field(default_factory=dict)
    mj: tuple[Any, Any, np.ndarray] | None = None  # (model, data, initial states (B, nstate))
    welded: Bench | None = None  # a floating robot with its base welded: rollout and floor only

    @property
    def batch(self) -> int:
        return len(self.Q0)

    def variants(self, full: bool = True) -> dict[str, tuple[Callable[[], Any], int]]:
        """The timed variants, in the order of a round: the floor, rollout (output every 10 steps) and
        mujoco.rollout back to back, the others around them. `full=False`: the floor and rollout only."""
        robot, Q0, V0, steps, B = self.robot, self.Q0, self.V0, self.steps, self.batch
        duration = steps * DT
        model, data = robot.model, robot.data
        pool = pin.ModelPool(model, 1)
        tau = np.zeros((B, robot.nv))
        acc = np.empty((B, robot.nv))
        taus = open_loop_torques(robot, Q0, steps // 10)

        def aba_loop() -> None:
            aba, z = pin.aba, tau[0]
            for b in range(B):
                q, v = Q0[b], V0[b]
                aba(model, data, q, v, z, _WORLD)
                aba(model, data, q, v, z, _WORLD)
                aba(model, data, q, v, z, _WORLD)
                aba(model, data, q, v, z, _WORLD)

        def aba_parallel() -> None:
            for _ in range(4 * steps):
                pin.abaInParallel(1, pool, Q0.T, V0.T, tau.T, acc.T)

        sparse = dict(duration=duration, dt=DT, output_dt=10 * DT, progress=False)
        out: dict[str, tuple[Callable[[], Any], int]] = {
            "aba4_parallel": (aba_parallel, B * steps),
            "rollout_sparse": (lambda: rollout(robot, Q0, V0, **sparse), B * steps),
        }
        if not full:
            return out
        if self.mj is not None and mj_rollout is not None:
            mj_model, mj_data, mj_states = self.mj
            out["mj_rollout"] = (
                lambda: mj_rollout.rollout(mj_model, mj_data, mj_states, nstep=steps),
                B * steps,
            )
        out["rollout"] = (lambda: rollout(robot, Q0, V0, duration=duration, dt=DT, progress=False), B * steps)
        # For the breakdown: samples only at the start and the end, and a one-step call (its fixed cost, spread
        # over the timed run's state-steps as it is in that run).
        out["rollout_bare"] = (
            lambda: rollout(robot, Q0, V0, duration=duration, dt=DT, output_dt=duration, progress=False),
            B * steps,
        )
        out["rollout_call"] = (lambda: rollout(robot, Q0, V0, duration=DT, dt=DT, progress=False), B * steps)
        out["rollout_taus"] = (
            lambda: rollout(robot, Q0, V0, taus=taus, control_dt=10 * DT, **sparse),
            B * steps,
        )
        # One state over ten times the steps, so that simulate()'s fixed per-call cost is amortised as a batch's is.
        out["simulate"] = (lambda: simulate(robot, Q0[0], V0[0], duration=10 * duration, dt=DT), 10 * steps)
        out["aba4"] = (aba_loop, B)
        if self.mj is not None:
            mj_model, mj_data, _ = self.mj
            qpos, qvel = StateMap(robot, mj_model).to_mujoco(Q0[0], V0[0])

            def mj_loop() -> None:
                mj_set_state(mj_model, mj_data, qpos, qvel)
                for _ in range(steps):
                    mujoco.mj_step(mj_model, mj_data)

            out["mj_step"] = (mj_loop, steps)
        return out

    def time_round(self, variants: dict[str, tuple[Callable[[], Any], int]]) -> None:
        for label, (fn, state_steps) in variants.items():
            self.runs.setdefault(label, []).append(cpu_us(fn, state_steps))

    def m(self, label: str) -> float:
        return median(self.runs.get(label, []))

    def ratio(self, num: str, den: str) -> tuple[float, float, float]:
        """(median, first quartile, third quartile) of the per-round ratios num / den."""
        pairs = [a / b for a, b in zip(self.runs.get(num, []), self.runs.get(den, []), strict=False)]
        if not pairs:
            return math.nan, math.nan, math.nan
        if len(pairs) < 2:
            return pairs[0], pairs[0], pairs[0]
        q1, _, q3 = statistics.quantiles(pairs, n=4)
        return statistics.median(pairs), q1, q3


def breakdown(b: Bench) -> dict[str, float]:
    """µs per state-step of what rollout (output every 10 steps) adds to the floor: stepping, samples, fixed;
    medians of the rounds' differences (each round times them back to back)."""
    runs = zip(
        *(b.runs.get(k, []) for k in ("aba4_parallel", "rollout_sparse", "rollout_bare", "rollout_call")), strict=False
    )
    parts: dict[str, list[float]] = {"total": [], "stepping": [], "samples": [], "fixed": []}
    for floor, sparse, bare, call in runs:
        parts["total"].append(sparse - floor)
        parts["stepping"].append(bare - floor - call)
        parts["samples"].append(sparse - bare)
        parts["fixed"].append(call)
    return {k: median(v) for k, v in parts.items()}


def breakdown_row(b: Bench) -> list[str]:
    parts, floor = breakdown(b), b.m("aba4_parallel")
    return [b.name] + [f"{fmt(parts[k])} ({fmt(parts[k] / floor)})" for k in ("total", "stepping", "samples", "fixed")]


def fmt_ratio(r: tuple[float, float, float]) -> str:
    """A median ratio with its interquartile range over the rounds."""
    return f"{fmt(r[0])} ({fmt(r[1])}–{fmt(r[2])})"


def open_loop_torques(robot: Any, Q0: np.ndarray, n_control: int) -> np.ndarray:
    """Open-loop torques (B, n_control, nv) for the column "with torques": random, up to half of each joint's
    gravity torque at the element's initial configuration, so that the motion stays as tame as without them;
    their power enters the energy ledger at every stage."""
    rng = np.random.default_rng(SEED)
    scale = np.abs([robot.gravity(q) for q in Q0])[:, None, :]
    taus = 0.5 * scale * rng.uniform(-1.0, 1.0, (len(Q0), n_control, robot.nv))
    if robot.floating_base:
        taus[:, :, :6] = 0.0
    return np.clip(taus, -robot.effort_limit, robot.effort_limit)


def states(robot: Any, B: int, seed: int = SEED) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    Q0 = np.array([robot.random_configuration(rng) for _ in range(B)])
    return Q0, rng.normal(scale=V0_SCALE, size=(B, robot.nv))


def mujoco_states(robot: Any, model: Any, Q0: np.ndarray, V0: np.ndarray) -> np.ndarray:
    """MuJoCo full-physics states of the batch (B, nstate)."""
    data = mujoco.MjData(model)
    smap = StateMap(robot, model)
    full = mujoco.mjtState.mjSTATE_FULLPHYSICS
    out = np.empty((len(Q0), mujoco.mj_stateSize(model, full)))
    for b in range(len(Q0)):
        mj_set_state(model, data, *smap.to_mujoco(Q0[b], V0[b]))
        mujoco.mj_getState(model, data, out[b], full)
    return out


def make_bench(name: str, B: int, steps: int) -> Bench:
    robot = load_robot(name, damping=False)  # no URDF damping: the MuJoCo peer's is zeroed too
    Q0, V0 = states(robot, B)
    bench = Bench(name, robot, Q0, V0, steps)
    if mujoco is not None:
        model = mujoco_model(robot)
        bench.mj = (model, mujoco.MjData(model), mujoco_states(robot, model, Q0, V0))
    if robot.floating_base:  # the same joints from the same states, the base welded where it starts
        welded = load_robot(name, floating_base=False, damping=False)
        bench.welded = Bench(name + " (base welded)", welded, Q0[:, 7:], V0[:, 6:], steps)
    return bench


def check_same_motion(bench: Bench) -> float:
    """Max |state difference| (MuJoCo coordinates) after the batch's RK4 steps, ours against mujoco.rollout."""
    if bench.mj is None or mj_rollout is None:
        return math.nan
    model, data, states0 = bench.mj
    smap = StateMap(bench.robot, model)
    theirs, _ = mj_rollout.rollout(model, data, states0, nstep=bench.steps)
    ours = rollout(bench.robot, bench.Q0, bench.V0, duration=bench.steps * DT, dt=DT, progress=False)
    worst = 0.0
    for b in range(bench.batch):
        qpos, qvel = smap.to_mujoco(ours.q[b, -1], ours.v[b, -1])
        mj_qpos = theirs[b, -1, 1 : 1 + model.nq].copy()  # FULLPHYSICS: time, qpos, qvel, ...
        mj_qvel = theirs[b, -1, 1 + model.nq : 1 + model.nq + model.nv]
        for kind, _, _, jq, _ in smap.joints:  # q and -q are the same rotation
            if kind == "free" and mj_qpos[jq + 3 : jq + 7] @ qpos[jq + 3 : jq + 7] < 0:
                mj_qpos[jq + 3 : jq + 7] *= -1
        worst = max(worst, float(np.max(np.abs(mj_qpos - qpos))), float(np.max(np.abs(mj_qvel - qvel))))
    return worst


# ---- scaling -----------------------------------------------------------------------------------------------------
def scaling_over_batch(name: str, base_steps: int, repeats: int) -> dict[int, dict[str, float]]:
    """CPU µs per state-step of rollout (output every 10 steps) and mujoco.rollout at each batch size; small
    batches run longer (at least 64 × base_steps state-steps), so the fixed per-call cost weighs alike."""
    robot = load_robot(name, damping=False)
    model = mujoco_model(robot) if mujoco is not None else None
    runs: dict[int, dict[str, list[float]]] = {}
    for _ in range(repeats):
        for B in BATCHES:
            steps = base_steps * max(1, 64 // B)
            Q0, V0 = states(robot, B)
            r = runs.setdefault(B, {})
            r.setdefault("rollout", []).append(
                cpu_us(
                    lambda Q0=Q0, V0=V0, steps=steps: rollout(
                        robot, Q0, V0, duration=steps * DT, dt=DT, output_dt=10 * DT, progress=False
                    ),
                    B * steps,
                )
            )
            pool = pin.ModelPool(robot.model, 1)

            def floor(pool: Any = pool, Q0: np.ndarray = Q0, V0: np.ndarray = V0, steps: int = steps) -> None:
                tau, acc = np.zeros(Q0.shape[0:1] + V0.shape[1:]), np.empty(V0.shape)
                for _ in range(4 * steps):
                    pin.abaInParallel(1, pool, Q0.T, V0.T, tau.T, acc.T)

            r.setdefault("floor", []).append(cpu_us(floor, B * steps))
            r.setdefault("ratio", []).append(r["rollout"][-1] / r["floor"][-1])
            if model is not None and mj_rollout is not None:
                data, mj_states = mujoco.MjData(model), mujoco_states(robot, model, Q0, V0)
                r.setdefault("mj_rollout", []).append(
                    cpu_us(lambda d=data, s=mj_states, n=steps: mj_rollout.rollout(model, d, s, nstep=n), B * steps)
                )
    return {B: {k: median(v) for k, v in r.items()} for B, r in runs.items()}


def scaling_over_cores(name: str, B: int, steps: int, repeats: int) -> dict[str, float]:
    """Wall µs per state-step on 1 and 2 threads: rollout (abaInParallel's threads), abaInParallel alone, and
    mujoco.rollout with one MjData per thread."""
    robot = load_robot(name, damping=False)
    Q0, V0 = states(robot, B)
    tau, acc = np.zeros((B, robot.nv)), np.empty((B, robot.nv))
    pools = {n: pin.ModelPool(robot.model, n) for n in (1, 2)}
    model = mujoco_model(robot) if mujoco is not None else None
    runs: dict[str, list[float]] = {}
    for _ in range(repeats):
        for n in (1, 2):

            def aba(n: int = n) -> None:
                for _ in range(4 * steps):
                    pin.abaInParallel(n, pools[n], Q0.T, V0.T, tau.T, acc.T)

            runs.setdefault(f"aba4_parallel_{n}", []).append(wall_us(aba, B * steps))
            runs.setdefault(f"rollout_{n}", []).append(
                wall_us(
                    lambda n=n: rollout(
                        robot, Q0, V0, duration=steps * DT, dt=DT, output_dt=10 * DT, num_threads=n, progress=False
                    ),
                    B * steps,
                )
            )
            if model is not None and mj_rollout is not None:
                datas = [mujoco.MjData(model) for _ in range(n)]
                mj_states = mujoco_states(robot, model, Q0, V0)
                runs.setdefault(f"mj_rollout_{n}", []).append(
                    wall_us(lambda d=datas, s=mj_states: mj_rollout.rollout(model, d, s, nstep=steps), B * steps)
                )
    return {k: median(v) for k, v in runs.items()}


def ray_scaling(name: str, B: int, steps: int, repeats: int) -> dict[str, float] | None:
    """Wall µs per state-step: local (one thread) against the Ray backend on a local two-CPU instance."""
    # Without cluster support Ray keeps the node on 127.0.0.1 (otherwise it swaps in the machine's address).
    os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
    try:
        import ray
    except ImportError:
        return None
    robot = load_robot(name, damping=False)
    Q0, V0 = states(robot, B)
    run = dict(duration=steps * DT, dt=DT, output_dt=10 * DT, progress=False)
    start = time.perf_counter()
    ray.init(num_cpus=2, include_dashboard=False, _node_ip_address="127.0.0.1", log_to_driver=False)
    startup = time.perf_counter() - start
    out: dict[str, list[float]] = {}
    try:
        rollout(robot, Q0[:4], V0[:4], backend="ray", **run)  # warm the workers (imports, first task)
        for _ in range(repeats):
            out.setdefault("local", []).append(wall_us(lambda: rollout(robot, Q0, V0, **run), B * steps))
            for chunks_per_cpu in (1, 2):
                size = -(-B // (2 * chunks_per_cpu))
                out.setdefault(f"ray_{chunks_per_cpu}", []).append(
                    wall_us(lambda s=size: rollout(robot, Q0, V0, backend="ray", chunk_size=s, **run), B * steps)
                )
    finally:
        ray.shutdown()
    result = {k: median(v) for k, v in out.items()}
    result["startup_s"] = startup
    return result


# ---- scenes: what modelling a scene's physics costs a batch ---------------------------------------------------------
SCENE_TARGETS = {"springs, damping, friction": 1.3, "+ a world force": 2.0, "+ a local wrench": 2.0}  # issue 14's


def scene_variants(name: str, frame: str) -> dict[str, Any]:
    """The bare robot and three scenes on it: springs, viscous damping and Coulomb friction on every joint; the
    same with a world-frame force at `frame` (ramped); the same with a force and torque fixed in `frame` (sine)."""
    robot = load_robot(name, damping=False)
    joints = {
        joint: {"stiffness": 2.0, "rest": 0.1, "damping": 0.05, "friction": 0.02}
        for joint in robot.model.names[1:]
        if robot.model.joints[robot.model.getJointId(joint)].nv == 1
    }
    push = {"name": "push", "frame": frame, "force": [5.0, 0.0, 0.0], "reference": "world", "shape": "ramp"}
    wrench = {
        "name": "wrench",
        "frame": frame,
        "force": [5.0, 0.0, 0.0],
        "torque": [0.0, 0.0, 0.2],
        "reference": "local",
        "shape": "sine",
        "frequency": 2.0,
    }
    source = {"source": name, "damping": False}
    return {
        "bare robot": robot,
        "springs, damping, friction": make_scene(robot=source, joints=joints),
        "+ a world force": make_scene(robot=source, joints=joints, force=[{**push, "ramp_time": 0.1}]),
        "+ a local wrench": make_scene(robot=source, joints=joints, force=[wrench]),
    }


def scene_costs(name: str, frame: str, B: int, steps: int, repeats: int) -> dict[str, tuple[float, float, float]]:
    """Per scene: rollout's CPU µs per state-step (output every 10 steps) and its ratio to the bare robot's, as
    (cost, median ratio, IQR low, IQR high) over interleaved rounds."""
    systems = scene_variants(name, frame)
    robot = systems["bare robot"]
    Q0, V0 = states(robot, B)
    kwargs = dict(duration=steps * DT, dt=DT, output_dt=10 * DT, progress=False)
    runs: dict[str, list[float]] = {label: [] for label in systems}
    for label, system in systems.items():  # untimed: caches and lazy set-up
        done = rollout(system, Q0, V0, **kwargs)
        if not done.completed.all():
            raise SystemExit(f"{name} {label}: elements stopped early")
    for _ in range(repeats):
        for label, system in systems.items():
            runs[label].append(cpu_us(lambda system=system: rollout(system, Q0, V0, **kwargs), B * steps))
    result = {}
    for label in systems:
        ratios = [a / b for a, b in zip(runs[label], runs["bare robot"], strict=True)]
        q1, _, q3 = statistics.quantiles(ratios, n=4) if len(ratios) > 1 else (ratios[0], 0, ratios[0])
        result[label] = (median(runs[label]), statistics.median(ratios), q1, q3)
    return result


def scene_report(name: str, costs: dict[str, tuple[float, float, float, float]], B: int) -> list[str]:
    rows = []
    for label, (cost, ratio, q1, q3) in costs.items():
        target = SCENE_TARGETS.get(label)
        verdict = "" if target is None else (f"≤ {target}: met" if ratio <= target else f"≤ {target}: NOT met")
        rows.append([label, fmt(cost, 1), f"{ratio:.2f} ({q1:.2f}–{q3:.2f})", verdict])
    return [
        f"## Scenes batch ({name}, B = {B})",
        "",
        para(f"""A scene's physics runs elementwise over the batch (one code path for one row and many). rollout
        of {name} with springs, viscous damping and Coulomb friction on every joint, then with a world-frame force
        at the tool added (as a point mass's gravity: one RNEA per row and stage), or instead a force and
        torque fixed in the tool's frame (a frame Jacobian per row and stage), against the bare robot, output
        every 10 steps; CPU µs per state-step, ratios as medians of per-round ratios (IQR in brackets). The
        kernel is the one the run takes (native where eligible)."""),
        "",
        *table(["system", "µs / state-step", "/ bare robot", "target"], rows),
    ]


# ---- the report ----------------------------------------------------------------------------------------------------
def write_report(
    path: Path,
    benches: list[Bench],
    motion: dict[str, float],
    over_batch: dict[str, dict[int, dict[str, float]]],
    over_cores: dict[str, float] | None,
    over_ray: dict[str, float] | None,
    args: argparse.Namespace,
    command: str,
    elapsed: float,
    loads: tuple[float, float],
    scene_lines: list[str],
) -> str:
    B, steps = args.batch, args.steps
    date = datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    mj_version = mujoco.__version__ if mujoco is not None else "not installed"
    lines = [
        "# Cost of batched rollouts",
        "",
        "Generated by `scripts/bench_rollout.py`; do not edit by hand.",
        "",
        f"- Command: `{command}`",
        f"- Date: {date}; the whole run took {elapsed:.0f} s",
        f"- Versions: pin {pin.__version__}, numpy {np.__version__}, mujoco {mj_version}",
        para(f"""- Machine: {cpu_name()}, {os.cpu_count()} cores, shared: the 1-minute load average was
            {loads[0]:.1f} at the start and {loads[1]:.1f} at the end. Every variant is timed once per round,
            round-robin (the floor, rollout and mujoco.rollout back to back), and each figure is the median over
            {args.repeats} rounds of CPU time (wall time where cores are compared); each ratio is the median of
            the rounds' ratios. Absolute figures from a loaded machine run high; the ratios are the robust
            figures."""),
        para(f"""- Workload: RK4, dt = {DT:g} s, {steps} steps, zero torque (but for the column with open-loop
            torques: random, up to half of each joint's gravity torque at the initial state, held for 10 steps), B = {B}
            states
            `robot.random_configuration(np.random.default_rng({SEED}))` with velocities ~ N(0, {V0_SCALE}²);
            robots loaded with `damping=False`. MuJoCo runs the same URDF (contacts, joint limits and equality
            constraints disabled; damping, armature and friction loss zeroed; RK4 at the same dt), from the
            same states."""),
        "",
        "## Per state-step (µs, CPU time, medians)",
        "",
    ]
    head = [
        "robot",
        "nq/nv",
        f"simulate (1 state, {10 * steps} steps)",
        f"rollout B={B}: output every step / every 10 / every 10 with torques",
        "4 × aba, Python loop",
        "4 × abaInParallel (floor)",
        "mj_step loop",
        f"mujoco.rollout B={B}",
    ]
    rows = []
    for b in benches:
        rows.append(
            [
                b.name + (" (floating)" if b.robot.floating_base else ""),
                f"{b.robot.nq}/{b.robot.nv}",
                fmt(b.m("simulate")),
                f"{fmt(b.m('rollout'))} / {fmt(b.m('rollout_sparse'))} / {fmt(b.m('rollout_taus'))}",
                fmt(b.m("aba4")),
                fmt(b.m("aba4_parallel")),
                fmt(b.m("mj_step")),
                fmt(b.m("mj_rollout")),
            ]
        )
    lines += table(head, rows)
    lines += [
        "",
        "## Ratios (medians of per-round ratios, interquartile range in brackets)",
        "",
        para(f"""The targets: batched RK4 within {TARGET}× the floor per state-step with output every 10 steps (the
            first column; issue 14), within {TARGET_EVERY_STEP}× with output every step (the second column; issue
            15, the native kernel), and ahead of mujoco.rollout where the floor allows it (below 1 in the last
            column)."""),
        "",
    ]
    lines += table(
        [
            "robot",
            "rollout / floor (every 10)",
            "every step / floor",
            "every 10 with torques / floor",
            "floor / mujoco.rollout",
            "rollout / mujoco.rollout (every 10)",
        ],
        [
            [
                b.name,
                fmt_ratio(b.ratio("rollout_sparse", "aba4_parallel")),
                fmt_ratio(b.ratio("rollout", "aba4_parallel")),
                fmt_ratio(b.ratio("rollout_taus", "aba4_parallel")),
                fmt_ratio(b.ratio("aba4_parallel", "mj_rollout")),
                fmt_ratio(b.ratio("rollout_sparse", "mj_rollout")),
            ]
            for b in benches
        ],
    )
    lines += [
        "",
        para("""Output every step records a sample per step: the kinetic and potential energy of each state (the
            energy ledger and the blow-up check need them; the native kernel takes the joint placements from the
            next step's first ABA and repeats only the velocity recursion), which MuJoCo's rollout does not
            compute. With torques, the ledger's torque power (a dot product per element and
            stage) is integrated too; without any it is zero and skipped."""),
        "",
        "## Where the rest goes (output every 10 steps; µs per state-step, and as a fraction of the floor)",
        "",
        para(f"""Medians of the rounds' differences: the samples are the difference to a run that records only its
            first and last state; the fixed cost is a one-step call's whole cost (argument checks, set-up, the
            result's assembly, one step and two samples) spread over the {B} × {steps} state-steps of a timed run;
            the stepping is the rest above the floor (stage arithmetic, the loop, and the configuration updates
            and chart map of a floating base). Differences of noisy timings: a few hundredths of the floor
            are within the noise."""),
        "",
    ]
    lines += table(
        ["robot", "rollout − floor", "stepping", "samples (every 10 steps)", "fixed cost per call"],
        [breakdown_row(b) for b in benches],
    )
    lines += [
        "",
        para(f"""Same motion (a check, not a test): after {steps} steps the batch's final states differ from
            mujoco.rollout's by at most""")
        + " "
        + ", ".join(f"{name} {err:.1e}" for name, err in motion.items())
        + " (MuJoCo's coordinates; its RK4 and ours integrate the same equations from the same states).",
    ]
    floating = [b for b in benches if b.welded is not None]
    if floating:
        lines += ["", "## Floating bases: the free-flyer's share", ""]
        lines += table(
            [
                "robot",
                "rollout / floor, floating",
                "rollout / floor, base welded",
                "floating: rollout − floor (µs)",
                "welded: rollout − floor (µs)",
            ],
            [
                [
                    b.name,
                    fmt_ratio(b.ratio("rollout_sparse", "aba4_parallel")),
                    fmt_ratio(b.welded.ratio("rollout_sparse", "aba4_parallel")),
                    fmt(b.m("rollout_sparse") - b.m("aba4_parallel")),
                    fmt(b.welded.m("rollout_sparse") - b.welded.m("aba4_parallel")),
                ]
                for b in floating
                if b.welded is not None
            ],
        )
        lines += [
            "",
            para("""The welded twin runs the same joints from the same states with the base fixed where it starts:
                its configuration update is one addition per joint and its chart map the identity, so the
                difference between the two overheads is the free-flyer's: its part of Pinocchio's integrate (an
                SE(3) exponential and a quaternion product per stage) and the chart map (its series to ad²: two
                6 × 6 products per stage)."""),
        ]
    lines += [
        "",
        "## Scaling over the batch size (µs per state-step, CPU time, output every 10 steps)",
        "",
        para(f"""Batches below 64 run 64 / B times {args.steps} steps, so that every measurement covers at least
            {64 * args.steps} state-steps and the fixed cost of a call (argument checks, the result's
            assembly) weighs alike. The floor (4 × abaInParallel over the same batch) is timed right after each
            rollout, and the ratio is the median of those pairs."""),
        "",
    ]
    for name, rows_by_b in over_batch.items():
        lines += [f"{name}:", ""]
        lines += table(
            ["B", *(str(x) for x in rows_by_b)],
            [
                ["rollout", *(fmt(r.get("rollout")) for r in rows_by_b.values())],
                ["4 × abaInParallel (floor)", *(fmt(r.get("floor")) for r in rows_by_b.values())],
                ["rollout / floor (median of rounds)", *(fmt(r.get("ratio")) for r in rows_by_b.values())],
                ["mujoco.rollout", *(fmt(r.get("mj_rollout")) for r in rows_by_b.values())],
            ],
        )
        lines.append("")
    if over_cores:
        name = args.cores_robot
        lines += [f"## Scaling over cores ({name}, B = {args.cores_batch}, µs per state-step, wall time)", ""]
        lines += table(
            ["", "1 thread", "2 threads", "speed-up"],
            [
                [
                    label,
                    fmt(over_cores.get(f"{key}_1")),
                    fmt(over_cores.get(f"{key}_2")),
                    fmt(over_cores.get(f"{key}_1", math.nan) / over_cores.get(f"{key}_2", math.nan)),
                ]
                for label, key in [
                    ("4 × abaInParallel", "aba4_parallel"),
                    ("rollout (num_threads)", "rollout"),
                    ("mujoco.rollout (one MjData per thread)", "mj_rollout"),
                ]
            ],
        )
    if over_ray:
        lines += [
            "",
            f"## Ray (local instance, 2 CPUs; {args.cores_robot}, B = {args.cores_batch}, wall time)",
            "",
        ]
        lines += table(
            ["", "µs per state-step", "speed-up over local"],
            [
                ["local, 1 thread", fmt(over_ray["local"]), "1.00"],
                ["Ray, 2 chunks (1 per CPU)", fmt(over_ray["ray_1"]), fmt(over_ray["local"] / over_ray["ray_1"])],
                ["Ray, 4 chunks (2 per CPU)", fmt(over_ray["ray_2"]), fmt(over_ray["local"] / over_ray["ray_2"])],
            ],
        )
        lines += [
            "",
            para(f"""Starting the local Ray instance took {over_ray["startup_s"]:.0f} s (not in the figures; the
                workers were warmed by one small rollout first). Each task receives the robot once through
                `ray.put` and returns its chunk's arrays."""),
        ]
    lines += ["", *scene_lines]
    lines += ["", "## Reading", "", *reading(benches, over_cores, over_ray, over_batch), ""]
    text = "\n".join(lines)
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(text, encoding="utf-8")
    return text


def reading(
    benches: list[Bench],
    over_cores: dict[str, float] | None,
    over_ray: dict[str, float] | None,
    over_batch: dict[str, dict[int, dict[str, float]]] | None = None,
) -> list[str]:
    """Paragraphs written from this run's numbers."""
    text = []
    fixed = [b for b in benches if not b.robot.floating_base]
    floating = [b for b in benches if b.robot.floating_base]
    if fixed:
        ratios = ", ".join(f"{b.name} {b.ratio('rollout_sparse', 'aba4_parallel')[0]:.2f}" for b in fixed)
        met = [b.name for b in fixed if b.ratio("rollout_sparse", "aba4_parallel")[0] <= TARGET]
        ahead = [b.name for b in fixed if b.ratio("rollout_sparse", "mj_rollout")[0] < 1.0]
        torques = ", ".join(f"{b.name} {b.ratio('rollout_taus', 'aba4_parallel')[0]:.2f}" for b in fixed)
        worst = max(fixed, key=lambda b: b.ratio("rollout_sparse", "aba4_parallel")[0])
        parts = breakdown(worst)
        floor = worst.m("aba4_parallel")
        text.append(
            para(f"""Fixed bases: a batched RK4 state-step (output every 10 steps) costs {ratios} times four ABA
            calls made by abaInParallel; within the {TARGET}× target: {", ".join(met) if met else "none"}. Ahead of
            mujoco.rollout (same states, one thread): {", ".join(ahead) if ahead else "none"}. With open-loop
            torques, whose power the ledger integrates stage by stage: {torques}. Where the rest goes, on
            {worst.name} (the breakdown table): the stepping {parts["stepping"] / floor:.0%} of the floor (the
            kernel's stage arithmetic, configuration updates and loop beside its ABA passes), the samples
            {parts["samples"] / floor:.0%} (each state's energies and the store's writes) and the fixed cost of the
            call {parts["fixed"] / floor:.0%} (argument checks, the engine's set-up, the result's assembly). Each
            weighs most on the double pendulum, whose ABA is the cheapest, and shrinks with larger batches (the
            scaling table) and sparser output.""")
        )
        if over_batch:
            scaling = "; ".join(
                f"{name} " + ", ".join(f"{fmt(r.get('ratio'))} at B = {b}" for b, r in rows.items() if b >= 64)
                for name, rows in over_batch.items()
            )
            text += ["", para(f"""Over the batch size (rollout / floor, the scaling tables): {scaling}.""")]
    if over_batch:
        verdict = []
        for B in (b for b in BATCHES if b >= 128):
            rows = {name: r[B].get("ratio", math.nan) for name, r in over_batch.items() if B in r}
            if rows:
                over = [f"{name} {ratio:.2f}" for name, ratio in rows.items() if not ratio <= TARGET]
                verdict.append(f"B = {B}: " + ("all within" if not over else "over: " + ", ".join(over)))
        main = [f"{b.name} {b.ratio('rollout_sparse', 'aba4_parallel')[0]:.2f}" for b in benches]
        main_over = [b.name for b in benches if not b.ratio("rollout_sparse", "aba4_parallel")[0] <= TARGET]
        text += [
            "",
            para(f"""The {TARGET}× target by batch size, every robot: B = {benches[0].batch} (the main table):
            {", ".join(main)} ({"all within" if not main_over else "over: " + ", ".join(main_over)});
            {"; ".join(verdict)}. What
            a batch pays per call (checks, the engine's set-up, the result's assembly) is spread over its elements:
            the larger the batch and the dearer the robot's ABA, the closer to the floor."""),
        ]
    every = {b.name: b.ratio("rollout", "aba4_parallel")[0] for b in benches if "rollout" in b.runs}
    if every:
        over_every = [f"{name} ({ratio:.2f})" for name, ratio in every.items() if not ratio <= TARGET_EVERY_STEP]
        within = [name for name, ratio in every.items() if ratio <= TARGET_EVERY_STEP]
        text += [
            "",
            para(f"""Output every step ≤ {TARGET_EVERY_STEP}× the floor (issue 15), B = {benches[0].batch}: met on
            {", ".join(within) or "none"}{"; missed on " + ", ".join(over_every) if over_every else ""}."""),
        ]
    if floating:
        parts = ", ".join(
            f"{b.name}: {b.ratio('rollout_sparse', 'aba4_parallel')[0]:.2f}× the floor and "
            f"{b.ratio('rollout_sparse', 'mj_rollout')[0]:.2f}× mujoco.rollout"
            for b in floating
        )
        welded = ", ".join(
            f"{b.name} {b.welded.ratio('rollout_sparse', 'aba4_parallel')[0]:.2f}" for b in floating if b.welded
        )
        # What the welded twin's overhead on the floating robot's floor would give against MuJoCo.
        estimates = {
            b.name: (
                b.ratio("aba4_parallel", "mj_rollout")[0],
                b.welded.ratio("rollout_sparse", "aba4_parallel")[0] * b.ratio("aba4_parallel", "mj_rollout")[0],
            )
            for b in floating
            if b.welded
        }
        verdicts = "; ".join(
            f"{name}: four ABA passes alone cost {floor:.2f}× a MuJoCo RK4 step here, so about {est:.2f}× "
            + ("mujoco.rollout: just ahead" if est < 1.0 else "mujoco.rollout: still behind")
            for name, (floor, est) in estimates.items()
        )
        text += [
            "",
            para(f"""Floating bases: {parts}. In the native kernel each RK4 stage moves the free-flyer with
            Pinocchio's integrate (an SE(3) exponential and a quaternion product) and maps its stage velocity through
            the inverse chart Jacobian's series to ad² (which keeps RK4 fourth-order; two 6 × 6 products), while
            every revolute joint is one addition. With the base welded the same robots run at {welded} times their
            floor: the difference is the free-flyer's share, and a free update would make {verdicts}. Where four
            ABA passes cost more than MuJoCo's step, being ahead would take cheaper or fewer dynamics evaluations per
            step (an articulated-body pass that reuses the joint kinematics between stages, or a method with fewer
            stages at the same accuracy), not less overhead."""),
        ]
    if over_cores:
        aba_speedup = over_cores["aba4_parallel_1"] / over_cores["aba4_parallel_2"]
        rollout_speedup = over_cores["rollout_1"] / over_cores["rollout_2"]
        mj_speedup = over_cores.get("mj_rollout_1", math.nan) / over_cores.get("mj_rollout_2", math.nan)
        why = (
            """Here the second core was free enough for threads to pay; on this shared 2-core machine other runs
            measured below 1× when other jobs held the cores (a second thread then waits for a core, and
            OpenMP's waiting threads cost more than they give), hence the default num_threads=1."""
            if aba_speedup >= 1.3
            else """On this shared 2-core machine other jobs held the cores (see the load average above), so a
            second thread mostly waited for a core, and OpenMP's waiting threads cost more than they give; hence
            the default num_threads=1."""
        )
        text += [
            "",
            para(f"""Cores: abaInParallel on 2 threads ran {aba_speedup:.2f}× as fast as on 1, and
            rollout(num_threads=2) {rollout_speedup:.2f}× (its stage arithmetic and samples stay on one thread);
            MuJoCo's rollout on two threads {mj_speedup:.2f}×. {why} How far threads pay on an idle multi-core
            machine is not measured here."""),
        ]
    if over_ray:
        text += [
            "",
            para(f"""Ray: on a local two-CPU instance the batch ran {over_ray["local"] / over_ray["ray_2"]:.2f}×
            as fast as locally (4 chunks), with the same results bit for bit (tested). Ray pays off when the
            batch is large enough for its per-task overhead, and beyond one machine."""),
        ]
    return text


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=9, help="rounds; each figure is a median over them")
    parser.add_argument("--steps", type=int, default=200, help="steps per timed batch run")
    parser.add_argument("--batch", type=int, default=128, help="states per batch in the main table")
    parser.add_argument("--robots", default=",".join(ROBOTS), help="comma-separated catalog names")
    parser.add_argument("--scaling-robots", default=",".join(SCALING_ROBOTS))
    parser.add_argument("--cores-robot", default="panda")
    parser.add_argument("--cores-batch", type=int, default=512)
    parser.add_argument("--no-ray", action="store_true", help="skip the Ray measurement")
    parser.add_argument("--scene-robot", default="ur5:tool0", help="ROBOT:FRAME of the scene section")
    parser.add_argument("--scenes-only", action="store_true", help="run only the scene section and print it")
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "rollout_cost.md")
    args = parser.parse_args(argv)
    python = Path(sys.executable)
    python_shown = str(python.relative_to(ROOT)) if python.is_relative_to(ROOT) else "python"
    command = " ".join([python_shown, "scripts/bench_rollout.py", *(sys.argv[1:] if argv is None else argv)])
    if mujoco is not None:  # keep the URDF importer's warnings out of MUJOCO_LOG.TXT in the cwd
        mujoco.set_mju_user_warning(lambda message: None)
    start, load_before = time.perf_counter(), load_average()
    scene_name, scene_frame = args.scene_robot.split(":")
    scenes = scene_costs(scene_name, scene_frame, args.batch, args.steps, args.repeats)
    print("\n".join(scene_report(scene_name, scenes, args.batch)), flush=True)
    if args.scenes_only:
        return 0

    benches = [make_bench(name, args.batch, args.steps) for name in args.robots.split(",")]
    workloads = [(b, b.variants()) for b in benches]
    workloads += [(b.welded, b.welded.variants(full=False)) for b in benches if b.welded is not None]
    for bench, variants in workloads:  # an untimed round: caches, allocators, lazy initialisations
        for label, (fn, _) in variants.items():
            result = fn()
            # A figure per state-step means something only if every state ran every step.
            if isinstance(result, BatchTrajectory) and not result.completed.all():
                raise SystemExit(f"{bench.name} {label}: {int((~result.completed).sum())} elements stopped early")
    for i in range(args.repeats):
        for bench, variants in workloads:
            bench.time_round(variants)
        print(f"round {i + 1}/{args.repeats} done ({time.perf_counter() - start:.0f} s)", flush=True)
    for b, _ in workloads:
        print(
            f"{b.name}: rollout / floor {fmt_ratio(b.ratio('rollout_sparse', 'aba4_parallel'))}, "
            f"rollout / mujoco.rollout {fmt_ratio(b.ratio('rollout_sparse', 'mj_rollout'))}",
            flush=True,
        )
    motion = {b.name: check_same_motion(b) for b in benches}
    over_batch = {
        # as many rounds as the main table: the 1.2x target is judged on these ratios too
        name: scaling_over_batch(name, args.steps, args.repeats)
        for name in args.scaling_robots.split(",")
    }
    print(f"batch scaling done ({time.perf_counter() - start:.0f} s)", flush=True)
    over_cores = scaling_over_cores(args.cores_robot, args.cores_batch, args.steps, max(3, args.repeats // 2))
    print(f"core scaling done ({time.perf_counter() - start:.0f} s)", flush=True)
    over_ray = None if args.no_ray else ray_scaling(args.cores_robot, args.cores_batch, args.steps, 3)
    elapsed = time.perf_counter() - start
    text = write_report(
        args.out,
        benches,
        motion,
        over_batch,
        over_cores,
        over_ray,
        args,
        command,
        elapsed,
        (load_before, load_average()),
        scene_report(scene_name, scenes, args.batch),
    )
    print(text)
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
