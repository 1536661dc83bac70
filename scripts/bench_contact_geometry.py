"""What the URDF's collision meshes cost per contact step against declared foot spheres (docs/contact.md).

solo12 held by PD + gravity compensation at its standing pose (solo12_standing's controller) on the ground,
timestepping at 1 ms, from the same start (its standing pose, 3 mm above the ground on its spheres), with its URDF's
collision geometry (17 meshes as their convex hulls; robot_geometry = "urdf") and with four declared foot spheres
(solo12_standing's). Each is a CPU-time median over interleaved rounds in one process (2 cores shared: the ratio,
not absolute times, is the result). Each run takes the kernel it would take (mesh hulls: Python; spheres: native
when built); MULTIBODY_SIM_NATIVE=0 compares both on the Python kernel.

Usage: [MULTIBODY_SIM_NATIVE=0] python scripts/bench_contact_geometry.py [--steps 300] [--repeats 7]
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

import multibody_sim as ms

Q_REF = [0.0, 0.0, 0.235, 0.0, 0.0, 0.0, 1.0, 0.1, 0.8, -1.6, -0.1, 0.8, -1.6, 0.1, -0.8, 1.6, -0.1, -0.8, 1.6]
FEET = ("FL_FOOT", "FR_FOOT", "HL_FOOT", "HR_FOOT")


def scene(geometry: str) -> ms.Scene:
    """solo12 on the ground under PD + gravity compensation; geometry "urdf" or "spheres"."""
    controller = {"name": "pd_gravity", "kp": 20.0, "q_ref": Q_REF}
    contact = {"robot_geometry": "urdf"}
    if geometry == "spheres":
        contact = {"geometry": [{"frame": f, "shape": "sphere", "radius": 0.016} for f in FEET]}
    return ms.make_scene(robot={"source": "solo12"}, ground={"friction": 0.8}, contact=contact, controller=controller)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--repeats", type=int, default=7)
    args = parser.parse_args()
    scenes = {name: scene(name) for name in ("urdf", "spheres")}
    q0 = np.array(Q_REF)
    times: dict[str, list[float]] = {name: [] for name in scenes}
    unconverged: dict[str, int] = {name: 0 for name in scenes}
    kernels: dict[str, str] = {}
    for _ in range(args.repeats):
        for name, s in scenes.items():
            controller = s.make_controller()
            start = time.process_time()
            traj = ms.simulate(
                s, q0, np.zeros(s.nv), duration=args.steps * 1e-3, dt=1e-3, integrator="timestepping",
                controller=controller, output_dt=args.steps * 1e-3, progress=False,
            )  # fmt: skip
            times[name].append((time.process_time() - start) / args.steps * 1e6)
            unconverged[name] = max(unconverged[name], int(traj.stats.get("solver_unconverged", 0)))
            kernels[name] = str(traj.metadata.get("kernel"))
    print(f"solo12 standing, {args.steps} steps of 1 ms, CPU-time medians of {args.repeats} interleaved rounds")
    for name in scenes:
        median = statistics.median(times[name])
        print(
            f"  {name:8s} {median:8.1f} µs/step  kernel {kernels[name]}  "
            f"(max unconverged steps per run: {unconverged[name]})"
        )
    print(f"  urdf / spheres: {statistics.median(times['urdf']) / statistics.median(times['spheres']):.2f}x")


if __name__ == "__main__":
    main()
