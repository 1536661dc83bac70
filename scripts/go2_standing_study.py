"""Why go2_standing moved while held by PD + gravity compensation, and what holds it still (docs/contact.md).

Runs go2_standing for 6 s (timestepping, 1 ms) with its controller's damping kd at the PD default (critical for
each joint alone: 2 sqrt(kp M_jj)) and at 5 and 10, at half the step, and with PGS; then at kp 100, 200 and 400
(kd 5) for the sag. Prints where the base comes to rest, when it is within 0.1 mm of that, how far it moves in the
last half of the scene's 1 s, the contacts' tangential / normal force ratio (μ = 0.8: the feet stick) and the sag
from touchdown.

Usage: python scripts/go2_standing_study.py
"""

from __future__ import annotations

import numpy as np

import multibody_sim as ms
from multibody_sim.controllers import PDGravity


def run(scene: ms.Scene, *, kp: float, kd: float | None, dt: float = 1e-3) -> ms.Trajectory:
    controller = PDGravity(scene, scene.make_controller().pd.q_ref, kp=kp, kd=kd)
    return ms.simulate(
        scene, scene.q0, scene.v0, duration=6.0, dt=dt, integrator="timestepping", controller=controller,
        output_dt=0.01, progress=False,
    )  # fmt: skip


def describe(label: str, traj: ms.Trajectory, touchdown: float) -> None:
    base = traj.q[:, :3]
    rest = base[-1]
    away = np.linalg.norm(base - rest, axis=1)
    settled = traj.t[np.flatnonzero(away > 1e-4)[-1] + 1]
    half = np.linalg.norm(base[100] - base[50])  # from 0.5 s to 1 s
    last = traj.contacts.at(len(traj) - 1)
    carrying = np.linalg.norm(last.impulse, axis=1) > 0
    ratio = np.linalg.norm(last.impulse[carrying, :2], axis=1) / last.impulse[carrying, 2]
    print(
        f"{label:26s} rest x {rest[0] * 1e3:+7.3f} mm, sag {(touchdown - rest[2]) * 1e3:6.3f} mm; within 0.1 mm of "
        f"rest after {settled:4.2f} s; moved {half * 1e3:6.3f} mm from 0.5 to 1 s; |f_t|/f_n {ratio.max():.3f}; "
        f"{traj.stats['solver_unconverged']} unconverged, {traj.stats['saturated_controls']} saturated"
    )


def main() -> None:
    scene = ms.load_scene("go2_standing")
    touchdown = scene.q0[2] - min(point.gap for point in scene.contact.detect(scene.q0))
    describe("kp 100, kd default", run(scene, kp=100.0, kd=None), touchdown)
    describe("kp 100, kd default, dt/2", run(scene, kp=100.0, kd=None, dt=5e-4), touchdown)
    scene.contact.solver = "pgs"
    describe("kp 100, kd default, PGS", run(scene, kp=100.0, kd=None), touchdown)
    scene.contact.solver = "admm"
    for kd in (5.0, 10.0):
        describe(f"kp 100, kd {kd:g}", run(scene, kp=100.0, kd=kd), touchdown)
    for kp in (200.0, 400.0):
        describe(f"kp {kp:g}, kd 5", run(scene, kp=kp, kd=5.0), touchdown)


if __name__ == "__main__":
    main()
