"""What randomised physics costs: a 64-row rollout with the bodies' masses and the friction drawn per row, against the
same rollout with the declared values, per state-step (issue 25's target: at most 1.2 x).

Both rollouts are timed whole (the draws, each row's scene and the native engine's per-row models included), CPU time,
in interleaved rounds (the order alternating), and the medians compared; the machine is shared and noisy, so only the
ratio within one run means anything. The time to draw and build one row's scene (Scene.with_parameters) is measured
apart, and the ratio without it is given too (the rows' own models while stepping). Cases:

- go2_standing (contact, timestepping, its PD + gravity controller natively, 1 s at 1 ms): every body's mass x U(0.9,
  1.1) and the ground's friction U(0.5, 1.0);
- ur5 (rk4, 1 s at 1 ms, a PD natively): every body's mass x U(0.9, 1.1) and each joint's Coulomb friction U(0, 0.5)
  N·m against the arm with a declared 0.25 N·m on each joint (the same friction elements, declared instead of drawn).

Usage: python scripts/bench_randomize.py [--rows 64] [--rounds 7] [--duration 1.0] [--threads 1] [--case ur5]
"""

from __future__ import annotations

import argparse
import statistics
import time
from typing import Any

import numpy as np

import multibody_sim as ms
from multibody_sim.scenes import shipped_scenes
from multibody_sim.scenes.parse import parse_toml

MASSES = {"name": "mass", "bodies": "*", "distribution": "uniform", "scale": [0.9, 1.1]}


def cases() -> dict[str, tuple[ms.Scene, ms.Scene, dict[str, Any], Any]]:
    """name -> (declared scene, randomised scene, rollout settings, the controller made for a scene: a built-in one,
    which the native kernel runs; made for the declared values, as a controller is)."""
    path = shipped_scenes()["go2_standing"]
    go2 = parse_toml(path.read_text(encoding="utf-8"), str(path))
    ground = {"name": "ground_friction", "distribution": "uniform", "value": [0.5, 1.0]}
    go2_plain = ms.make_scene(**go2)
    go2_random = ms.make_scene(**go2, randomize={"seed": 0, "parameter": [MASSES, ground]})
    joints = {name: {"friction": 0.25} for name in ms.load_robot("ur5").joint_names}
    friction = {"name": "friction", "joints": "*", "distribution": "uniform", "value": [0.0, 0.5]}
    ur5_plain = ms.make_scene(robot={"source": "ur5"}, joints=joints)
    ur5_random = ms.make_scene(robot={"source": "ur5"}, joints=joints, randomize={"parameter": [MASSES, friction]})
    return {
        "go2_standing": (go2_plain, go2_random, {"integrator": "timestepping"}, lambda s: s.make_controller()),
        "ur5": (ur5_plain, ur5_random, {"integrator": "rk4"}, lambda s: ms.PD(s, q_ref=s.q0, kp=100.0)),
    }


def per_state_step(system: ms.Scene, control: Any, settings: dict[str, Any], args: Any) -> tuple[float, str]:
    """One rollout of `system` from its initial state, timed whole (CPU): µs per state-step, and its kernel."""
    Q, V = np.tile(system.q0, (args.rows, 1)), np.tile(system.v0, (args.rows, 1))
    controller = control(system)
    start = time.process_time()
    batch = ms.rollout(
        system, Q, V, duration=args.duration, dt=1e-3, controller=controller, num_threads=args.threads,
        progress=False, **settings,
    )  # fmt: skip
    spent = time.process_time() - start
    assert batch.completed.all(), batch.summary()
    return spent / int(np.sum(batch.stats["steps"])) * 1e6, batch.metadata["kernel"]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, default=64)
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--duration", type=float, default=1.0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--case", choices=("go2_standing", "ur5"), help="one case only (default: both)")
    args = parser.parse_args()
    for name, (plain, random, settings, control) in cases().items():
        if args.case is not None and name != args.case:
            continue
        per_state_step(plain, control, settings, args), per_state_step(random, control, settings, args)  # warm
        times: dict[str, list[float]] = {"declared": [], "randomised": []}
        kernels = set()
        for r in range(args.rounds):
            order = ("declared", "randomised") if r % 2 == 0 else ("randomised", "declared")
            for which in order:
                us, kernel = per_state_step(plain if which == "declared" else random, control, settings, args)
                times[which].append(us)
                kernels.add(kernel)
        start = time.process_time()
        for b in range(args.rows):
            random.with_parameters(random.draw_parameters(b))
        setup = (time.process_time() - start) / args.rows * 1e3
        declared, randomised = statistics.median(times["declared"]), statistics.median(times["randomised"])
        steps = args.rows * round(args.duration / 1e-3)
        stepping = randomised - setup * 1e3 * args.rows / steps  # the rows' scenes' building taken out
        print(
            f"{name}: {args.rows} rows x {args.duration:g} s, {', '.join(sorted(kernels))} kernel: declared "
            f"{declared:.3f} us per state-step, randomised {randomised:.3f} (medians of {args.rounds}); ratio "
            f"{randomised / declared:.3f}; drawing and building one row's scene: {setup:.2f} ms; without that "
            f"building: {stepping:.3f} us, ratio {stepping / declared:.3f}"
        )


if __name__ == "__main__":
    main()
