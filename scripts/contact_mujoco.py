"""Contact side by side with MuJoCo: the sliding and resting boxes and a solo12 drop built from the same geometry,
and the cost per step of solo12_standing (the native kernel's step and the Python kernel's) against the sum of
Pinocchio's C++ calls for that step and against mj_step, measured in the same run, and a rollout of it on one and
two threads. Writes docs/contact.md. A benchmark-only dependency (`pip install mujoco`).

    python scripts/contact_mujoco.py [--rounds 7] [--steps 300]
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import time
from pathlib import Path
from typing import Any

import mujoco
import numpy as np
import pinocchio as pin

import multibody_sim as ms

sys.path.insert(0, str(Path(__file__).resolve().parent))
from mujoco_peer import StateMap, mujoco_model  # noqa: E402

G = 9.81
DT = 1e-3


# ---- MuJoCo models from the same geometry -------------------------------------------------------------------
def box_xml(mu: float, velocity: float) -> str:
    """A 1 kg box 0.2 x 0.2 x 0.1 m on a plane, both with friction mu (MuJoCo combines by max), elliptic cones."""
    return f"""
<mujoco>
  <option timestep="{DT}" cone="elliptic" integrator="Euler"/>
  <worldbody>
    <geom type="plane" size="5 5 0.1" friction="{mu} 0.005 0.0001"/>
    <body name="box" pos="0 0 0.05">
      <freejoint/>
      <geom type="box" size="0.1 0.1 0.05" mass="1" friction="{mu} 0.005 0.0001"/>
    </body>
  </worldbody>
</mujoco>"""


def mujoco_box(mu: float, velocity: float, duration: float) -> np.ndarray:
    """MuJoCo's box: samples (t, x, vx, z) at every step."""
    model = mujoco.MjModel.from_xml_string(box_xml(mu, velocity))
    data = mujoco.MjData(model)
    data.qvel[0] = velocity
    rows = [(0.0, data.qpos[0], data.qvel[0], data.qpos[2])]
    for _ in range(round(duration / DT)):
        mujoco.mj_step(model, data)
        rows.append((data.time, data.qpos[0], data.qvel[0], data.qpos[2]))
    return np.array(rows)


def ours_box(mu: float, velocity: float, duration: float) -> np.ndarray:
    scene = ms.make_scene(
        ground={"friction": mu},
        object=[
            {
                "name": "box",
                "shape": "box",
                "size": [0.2, 0.2, 0.1],
                "mass": 1.0,
                "position": [0, 0, 0.05],
                "velocity": [velocity, 0, 0, 0, 0, 0],
            }
        ],
    )
    traj = scene.run(duration=duration, dt=DT, progress=False)
    return np.column_stack([traj.t, traj.q[:, 0], traj.v[:, 0], traj.q[:, 2]])


def sliding_facts(rows: np.ndarray, v0: float) -> dict[str, float]:
    """Deceleration while sliding (mean over the first 0.1 s), stop time, stop distance."""
    t, x, vx = rows[:, 0], rows[:, 1], rows[:, 2]
    early = (t > 0.0) & (t <= 0.1)
    decel = -np.polyfit(t[early], vx[early], 1)[0]
    stopped = np.flatnonzero(vx <= 1e-6)
    stop = t[stopped[0]] if len(stopped) else float("nan")
    return {"deceleration": decel, "stop_time": stop, "distance": x[-1] - x[0], "creep": abs(vx[-1])}


def solo12_mujoco(scene: Any) -> tuple[Any, Any, StateMap]:
    """solo12's URDF in MuJoCo (free joint, no URDF geometry), with the scene's four foot spheres and a plane,
    friction 0.8, elliptic cones, Euler at 1 ms, contact and limits as our scene has them (limits off)."""
    robot = scene.full_robot
    model = mujoco_model(robot)  # for its body names only (contacts are disabled there)
    spec = mujoco.MjSpec.from_string(mujoco_xml_of(robot))
    spec.worldbody.first_body().add_freejoint()
    spec.worldbody.add_geom(type=mujoco.mjtGeom.mjGEOM_PLANE, size=[5, 5, 0.1], friction=[0.8, 0.005, 0.0001])
    for declared in scene.spec.contact.geometry:
        frame = robot.model.frames[robot.model.getFrameId(declared.frame)]
        joint_name = robot.model.names[frame.parentJoint]
        body = spec.body(model.body(model.jnt_bodyid[model.joint(joint_name).id]).name)
        offset = frame.placement * pin.SE3(pin.rpy.rpyToMatrix(*declared.rpy), np.array(declared.position))
        body.add_geom(
            type=mujoco.mjtGeom.mjGEOM_SPHERE,
            size=[declared.shape.radius, 0, 0],
            pos=offset.translation,
            friction=[0.8, 0.005, 0.0001],
            mass=0.0,
        )
    mj = spec.compile()
    mj.opt.timestep = DT
    mj.opt.cone = mujoco.mjtCone.mjCONE_ELLIPTIC
    mj.opt.integrator = mujoco.mjtIntegrator.mjINT_EULER
    mj.dof_damping[:] = 0.0
    mj.dof_armature[:] = 0.0
    mj.dof_frictionloss[:] = 0.0
    mj.opt.disableflags |= int(mujoco.mjtDisableBit.mjDSBL_LIMIT) | int(mujoco.mjtDisableBit.mjDSBL_EQUALITY)
    return mj, mujoco.MjData(mj), StateMap(robot, mj)


def mujoco_xml_of(robot: Any) -> str:
    import xml.etree.ElementTree as ET

    tree = ET.parse(robot.source["urdf_path"])
    for parent in tree.getroot().iter():
        for child in list(parent):
            if child.tag in ("visual", "collision", "transmission", "gazebo"):
                parent.remove(child)
    return ET.tostring(tree.getroot(), encoding="unicode")


def solo12_drop(scene: Any, duration: float) -> tuple[np.ndarray, np.ndarray]:
    """Base height over time, ours and MuJoCo's, both under the scene's PD + gravity compensation."""
    ours = scene.run(duration=duration, dt=DT, progress=False)
    mj, data, states = solo12_mujoco(scene)
    qpos, qvel = states.to_mujoco(scene.q0, scene.v0)
    data.qpos[:], data.qvel[:] = qpos, qvel
    controller = scene.make_controller()
    heights = [data.qpos[2]]
    for _ in range(round(duration / DT)):
        q, v = states.to_pinocchio(data.qpos, data.qvel)
        tau = controller(data.time, q, v)
        for kind, _, iv, _, jv in states.joints:
            if kind != "free":
                data.qfrc_applied[jv] = tau[iv]
        mujoco.mj_step(mj, data)
        heights.append(data.qpos[2])
    return ours.q[:, 2], np.array(heights)


# ---- cost per step ---------------------------------------------------------------------------------------------
def pinocchio_calls(scene: Any, q: np.ndarray, v: np.ndarray, tau: np.ndarray) -> dict[str, Any]:
    """Each Pinocchio C++ call of one timestepping step at (q, v), as closures on fresh workspaces."""
    model, contact = scene.model, scene.contact
    data = model.createData()
    gm = contact.geometry_model
    gd = pin.GeometryData(gm)
    for request in gd.collisionRequests:
        request.enable_contact = True
        request.security_margin = 0.01
    a = pin.aba(model, data, q, v, tau, pin.Convention.WORLD)
    v_free = v + DT * a
    problem = contact.problem(q, v, v_free, DT)
    models, datas = problem.models, problem.datas
    pairs = range(len(gm.collisionPairs))
    pin.updateGeometryPlacements(model, data, gm, gd, q)
    pin.computeCollisions(gm, gd, False)
    pin.crba(model, data, q, pin.Convention.WORLD)
    for cm, cd in zip(models, datas, strict=True):
        cm.calc(model, data, cd)
    chol = pin.ConstraintCholeskyDecomposition(model, data, models, datas)
    settings = ms.integrators.timestepping.admm_settings()
    solver, result = pin.ADMMConstraintSolver(), pin.ADMMSolverResult()
    chol.compute(model, data, models, datas, 1e-12)
    delassus = chol.getDelassusOperatorCholeskyExpression()
    solver.solve(delassus, problem.g, models, datas, settings, result)
    guess = np.array(result.retrieveConstraintImpulses())
    generalized = problem.jacobian.T @ guess

    def solve() -> None:
        result.setConstraintImpulseGuess(guess)
        solver.solve(delassus, problem.g, models, datas, settings, result)

    def patches() -> None:
        for k in pairs:
            pin.computeContactPatch(gm, gd, k)

    def calcs() -> None:
        for cm, cd in zip(models, datas, strict=True):
            cm.calc(model, data, cd)

    def minv() -> None:
        pin.cholesky.decompose(model, data)
        pin.cholesky.solve(model, data, generalized)

    return {
        "aba (v_free)": lambda: pin.aba(model, data, q, v, tau, pin.Convention.WORLD),
        "updateGeometryPlacements": lambda: pin.updateGeometryPlacements(model, data, gm, gd, q),
        "computeCollisions": lambda: pin.computeCollisions(gm, gd, False),
        "computeContactPatch x4": patches,
        "crba (WORLD)": lambda: pin.crba(model, data, q, pin.Convention.WORLD),
        "constraint calc x4": calcs,
        "Delassus Cholesky": lambda: chol.compute(model, data, models, datas, 1e-12),
        "getConstraintsJacobian": lambda: pin.getConstraintsJacobian(model, data, models, datas),
        "ADMM solve (warm)": solve,
        "M^-1 J^T lambda (cholesky)": minv,
        "integrate": lambda: pin.integrate(model, q, DT * v_free),
        "ledger energies x4": lambda: [
            (pin.computeKineticEnergy(model, data, q, v), pin.computePotentialEnergy(model, data)) for _ in range(4)
        ],
    }


def cpu_us(fn: Any, n: int) -> float:
    start = time.process_time()
    for _ in range(n):
        fn()
    return (time.process_time() - start) / n * 1e6


def native_run(scene: Any, q: np.ndarray, v: np.ndarray, tau: np.ndarray, steps: int) -> Any:
    """The native kernel's timestepping run of `steps` steps from (q, v) under tau held, sampled at its ends only."""
    duration = steps * DT
    return ms.rollout(scene, q[None], v[None], duration=duration, dt=DT, integrator="timestepping",
                      taus=tau[None, None, :], control_dt=duration, output_dt=duration, progress=False)  # fmt: skip


def step_costs(rounds: int, steps: int) -> dict[str, Any]:
    """CPU-time medians over interleaved rounds: our step on the native kernel and on the Python kernel, each
    Pinocchio call of it, mj_step (4 foot contacts). The native step is the difference of a run of 10·steps and a
    run of `steps` over 9·steps (the run's fixed cost, setting up and two samples, taken out)."""
    scene = ms.load_scene("solo12_standing")
    settled = scene.run(duration=0.3, dt=DT, progress=False)  # standing, four feet in contact
    q, v = settled.q[-1], settled.v[-1]
    tau = settled.tau[-1]
    method = ms.get_integrator("timestepping")
    calls = pinocchio_calls(scene, q, v, tau)
    mj, data, states = solo12_mujoco(scene)
    qpos, qvel = states.to_mujoco(q, v)

    def ours() -> None:
        state = method.init(scene, q, v)
        qq, vv = q, v
        for _ in range(steps):
            attempt = method.attempt(scene, qq, vv, tau, DT, 0.0, state)
            qq, vv, state = attempt.q, attempt.v, attempt.state

    def theirs() -> None:
        data.qpos[:], data.qvel[:] = qpos, qvel
        for kind, _, iv, _, jv in states.joints:
            if kind != "free":
                data.qfrc_applied[jv] = tau[iv]
        for _ in range(steps):
            mujoco.mj_step(mj, data)

    assert native_run(scene, q, v, tau, steps).metadata["kernel"] == "native", "the native kernel is not built"

    def native_step() -> float:
        return (cpu_us(lambda: native_run(scene, q, v, tau, 10 * steps), 1) - cpu_us(
            lambda: native_run(scene, q, v, tau, steps), 1)) / (9 * steps)  # fmt: skip

    samples: dict[str, list[float]] = {"native": [], "ours": [], "mujoco": [], **{name: [] for name in calls}}
    for _ in range(rounds):
        samples["native"].append(native_step())
        samples["ours"].append(cpu_us(ours, 1) / steps)
        for name, fn in calls.items():
            samples[name].append(cpu_us(fn, steps))
        samples["mujoco"].append(cpu_us(theirs, 1) / steps)
    medians = {name: float(np.median(values)) for name, values in samples.items()}
    theirs()  # the contacts MuJoCo holds once standing on its (soft) feet
    medians["mujoco_contacts"] = int(data.ncon)
    return medians


def thread_costs(rounds: int, B: int = 8, duration: float = 0.3) -> dict[str, float]:
    """Wall- and CPU-time medians over interleaved rounds of a native rollout of solo12_standing (B rows from
    perturbed standing poses, the scene's PD + gravity compensation) on one and on two threads [ms]."""
    scene = ms.load_scene("solo12_standing")
    rng = np.random.default_rng(0)
    Q0 = np.array([scene.space.integrate(scene.q0, 0.02 * rng.normal(size=scene.nv)) for _ in range(B)])
    V0 = np.zeros((B, scene.nv))
    controller = scene.make_controller()
    samples: dict[str, list[float]] = {"wall 1": [], "wall 2": [], "cpu 1": [], "cpu 2": []}
    for _ in range(rounds):
        for threads in (1, 2):
            wall, cpu = time.perf_counter(), time.process_time()
            batch = ms.rollout(scene, Q0, V0, duration=duration, dt=DT, integrator="timestepping",
                               controller=controller, num_threads=threads, progress=False)  # fmt: skip
            samples[f"wall {threads}"].append((time.perf_counter() - wall) * 1e3)
            samples[f"cpu {threads}"].append((time.process_time() - cpu) * 1e3)
            assert batch.metadata["kernel"] == "native"
    return {name: float(np.median(values)) for name, values in samples.items()}


# ---- the report --------------------------------------------------------------------------------------------------
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--steps", type=int, default=300)
    parser.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "docs" / "contact.md"))
    args = parser.parse_args()
    mu, v0 = 0.8, 2.0
    runs = (("ours", ours_box(mu, v0, 0.5)), ("mujoco", mujoco_box(mu, v0, 0.5)))
    slide = {name: sliding_facts(rows, v0) for name, rows in runs}
    rest = {"ours": ours_box(mu, 0.0, 1.0), "mujoco": mujoco_box(mu, 0.0, 1.0)}
    solo = ms.load_scene("solo12_standing")
    ours_z, mj_z = solo12_drop(solo, 1.0)
    costs = step_costs(args.rounds, args.steps)
    threads = thread_costs(args.rounds)
    pin_sum = sum(costs[name] for name in costs if name not in ("native", "ours", "mujoco", "mujoco_contacts"))
    pin_solver = pin_sum - costs["ledger energies x4"]
    print(costs, flush=True)
    lines = [
        "# Contact: our time-stepper beside MuJoCo",
        "",
        "Generated by `python scripts/contact_mujoco.py` "
        f"(rounds {args.rounds}, {args.steps} steps each; pin {pin.__version__}, mujoco {mujoco.__version__}, "
        f"Python {platform.python_version()}, load average {os.getloadavg()[0]:.1f} at the end on a shared "
        "2-core machine). MuJoCo models are built from the same geometry: the same box, the same URDF with the "
        "scene's four foot spheres, friction 0.8 on every geom (MuJoCo combines by max), elliptic cones, Euler at "
        "1 ms, joint limits off as in our scene.",
        "",
        "## A box sliding at 2 m/s, μ = 0.8 (closed form: μg = 7.848 m/s², stops at 0.2548 s after 0.2548 m)",
        "",
        "| | deceleration [m/s²] | relative to μg | stop time [s] | distance [m] | speed at 0.5 s [m/s] |",
        "|---|---|---|---|---|---|",
    ]
    for name, facts in slide.items():
        lines.append(
            f"| {name} | {facts['deceleration']:.5f} | {facts['deceleration'] / (mu * G) - 1:+.2e} | "
            f"{facts['stop_time']:.4f} | {facts['distance']:.5f} | {facts['creep']:.2e} |"
        )
    lines += [
        "",
        "## A box resting on the ground for 1 s",
        "",
        "| | drift of its centre [m] | height change [m] |",
        "|---|---|---|",
    ]
    for name, rows in rest.items():
        drift = float(np.abs(rows[:, 1] - rows[0, 1]).max())
        sink = float(rows[-1, 3] - rows[0, 3])
        lines.append(f"| {name} | {drift:.2e} | {sink:+.2e} |")
    lines += [
        "",
        "## solo12 dropped onto four foot spheres, held by the scene's PD + gravity compensation",
        "",
        "| t [s] | base height, ours [m] | MuJoCo [m] |",
        "|---|---|---|",
    ]
    for t in (0.0, 0.01, 0.05, 0.1, 0.3, 0.6, 1.0):
        i = round(t / DT)
        lines.append(f"| {t:g} | {ours_z[i]:.5f} | {mj_z[i]:.5f} |")
    lines += [
        "",
        "## Cost per step, solo12_standing (4 foot contacts), CPU-time medians over interleaved rounds",
        "",
        "| what | µs per step |",
        "|---|---|",
        f"| **our timestepping step, native kernel** (`src/native/contact.cpp`) | **{costs['native']:.1f}** |",
        f"| our timestepping step, Python kernel (`TimeStepping.attempt`) | {costs['ours']:.1f} |",
        *(
            f"| Pinocchio: {name} | {costs[name]:.2f} |"
            for name in costs
            if name not in ("native", "ours", "mujoco", "mujoco_contacts")
        ),
        f"| **sum of Pinocchio's calls** | **{pin_sum:.1f}** ({pin_solver:.1f} without the ledger's energies) |",
        f"| MuJoCo `mj_step` ({costs['mujoco_contacts']} contacts) | {costs['mujoco']:.1f} |",
        "",
        f"Ratios: the native step / Pinocchio's calls = **{costs['native'] / pin_sum:.2f}** (the issue's target: "
        f"≤ 1.3); the native step / mj_step = {costs['native'] / costs['mujoco']:.1f}; the Python kernel's step / "
        f"Pinocchio's calls = {costs['ours'] / pin_sum:.2f}; Pinocchio's calls / mj_step = "
        f"{pin_sum / costs['mujoco']:.2f} ({pin_solver / costs['mujoco']:.2f} without the ledger's energies). Each "
        "Pinocchio call is timed alone through its Python binding (a few tenths of a µs of binding overhead each) on "
        "a state standing on four feet; the native step is a run of that state under its torque held (the "
        "difference of a 10·steps and a steps run, per step), with the contact models, datas, Cholesky storage and "
        "solver kept across steps. Both kernels' steps are the same arithmetic bit for bit "
        "(tests/test_native_contact.py).",
        "",
        f"## A rollout of solo12_standing, {8} rows, 0.3 s, on one and two threads (native kernel, medians)",
        "",
        "| threads | wall time [ms] | CPU time [ms] |",
        "|---|---|---|",
        f"| 1 | {threads['wall 1']:.1f} | {threads['cpu 1']:.1f} |",
        f"| 2 | {threads['wall 2']:.1f} | {threads['cpu 2']:.1f} |",
        "",
        f"Two threads take {threads['wall 2'] / threads['wall 1']:.2f}x the wall time of one (rows split across the "
        "threads once per run, each row with its own warm start; the machine's two cores are shared with other "
        "work, so the wall times are noisy).",
        "",
        "## Differences",
        "",
        "- Friction: ours is exact Coulomb (a cone constraint on impulses): the box decelerates at μg to the "
        "solver's tolerance and stops dead. MuJoCo's contact is soft (a regularized, compliant constraint): its "
        "deceleration is below μg and its box creeps, as the tables show.",
        "- Resting: ours holds a box still to round-off (speculative contacts, no penetration); MuJoCo's soft "
        "contact lets it sink into the ground until the constraint's spring carries the weight.",
        "- The solo12 drop: both settle on their feet; heights differ by MuJoCo's penetration and by the joints' "
        "sag under the same PD gains.",
    ]
    lines += ["", MEASURED_APART.strip("\n")]
    Path(args.out).write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


# Sections measured by other commands (named in them), kept in the page when it is regenerated.
MEASURED_APART = """
## The URDF's collision geometry (robot_geometry = "urdf")

Measured apart from MuJoCo (not regenerated by this script; commands given). A robot without declared
`[[contact.geometry]]` collides with its URDF's collision shapes: Pinocchio's `buildGeomFromUrdf` with the loader's
package folders, meshes as their convex hulls (coal's qhull hull: `buildConvexRepresentation` would take an STL's own
triangles as the hull, and their unshared vertices left coal's support search on a local vertex: a solo12 foot sank
28 µm), contact patches of at most 8 points none closer than 1 cm (a hull's facet on the ground gives up to 8
points within a few millimetres, nearly equal rows on which ADMM stalled: solo12 standing on its meshes had 38
unconverged steps of 1000 at 4.3 ms per step without the spacing, none at 0.9 ms with it).

- Rest height: solo12 with its legs locked (one rigid body), dropped 1.1 cm on its meshes, comes to rest with the
  lowest vertex of its collision meshes (read by trimesh, placed by Pinocchio's kinematics) at -1e-14 m, within
  the 1 nm penetration slop (`tests/test_contact.py`).
- Cost, `python scripts/bench_contact_geometry.py --steps 300 --repeats 7` (solo12 standing under the scene's PD +
  gravity compensation, timestepping at 1 ms, CPU-time medians of interleaved rounds, load average 7.6-8.7; both
  converged on every step). Both on the Python kernel (`MULTIBODY_SIM_NATIVE=0`): URDF meshes 765-814 µs per step,
  four declared foot spheres 206-217 µs: 3.5-4.0x over two runs (17 hulls against the ground instead of 4 spheres:
  more pairs to test, 8 contact points at rest instead of 4, the lower legs' speculative rows, more solver
  iterations). By default the spheres run on the native kernel (36.6 µs) while mesh hulls stay on the Python
  kernel (771 µs): 21x.
- Limit: a robot that collapses onto many links at once (solo12, go2 or talos dropped without a controller: 30-100
  points on 10-40 links) leaves ADMM at residuals of 1e-9..1e-7 on 2-5 % of the steps, above the 1e-12 tolerance,
  and the run ends "solver_failed" (partial samples kept; it does not pass through the ground). Hold the robot with
  a controller, declare geometry (spheres on feet), or use a smaller dt.

## go2_standing: why it moved while held, and what holds it still

`MULTIBODY_SIM_NATIVE=0 python scripts/go2_standing_study.py` (6 s runs, timestepping at 1 ms; not regenerated by
this script). The base was not drifting: it was settling, slowly, towards a rest that is not the reference pose.

| controller | rest x [mm] | sag from touchdown [mm] | within 0.1 mm of rest after | moved, 0.5 to 1 s [mm] |
|---|---|---|---|---|
| kp 100, kd default (1.4-3.2) | -7.807 | 8.037 | 2.84 s | 2.850 |
| the same at dt/2 | -7.799 | 8.034 | 2.84 s | 2.840 |
| the same with PGS | -7.807 | 8.037 | 2.84 s | 2.850 |
| kp 100, kd 5 (the scene now) | -7.814 | 7.949 | 1.36 s | 0.049 |
| kp 100, kd 10 (48 torques saturated) | +5.394 | 7.777 | 0.76 s | 0.668 |
| kp 200, kd 5 | -3.478 | 3.919 | 1.10 s | 0.509 |
| kp 400, kd 5 | -1.692 | 2.002 | 0.89 s | 0.017 |

- Not the contact numerics: halving the step moves the rest by 8 µm, PGS and ADMM agree, the solver converged on
  every step, the feet stick (tangential / normal force 0.33 < μ = 0.8; their contact points move only as the
  spheres roll) and the normal forces sum to the weight to 3e-7 at rest, where |v| falls to 1e-8 m/s by 10 s.
- The sag is the controller's: gravity compensation on a floating base holds each leg's own weight, but the trunk's
  (on the unactuated base coordinates) reaches the joints only through the contact forces, so the PD springs carry
  it: the sag halves as kp doubles (8.0, 3.9, 2.0 mm at kp 100, 200, 400: Hooke's law; tested).
- The slow settling was the damping: the PD's default kd is critical for each joint alone on a fixed base
  (2 sqrt(kp M_jj)), but in stance the joints carry the 15 kg trunk, an underdamped 0.6 s mode that was still
  moving the base by 2.9 mm in the last half of the scene's 1 s. The scene now sets kd = 5: within 0.1 mm of rest
  by 1.4 s, 0.05 mm of motion in the last half second, no torque saturated (kd 10 saturates the knees).
- Where it comes to rest along x depends on the landing: four sticking feet make the stance statically
  indeterminate (the legs' springs hold the feet apart with 0.33 of the normal force), so the horizontal rest
  differs with the transient (kd 5: -7.8 mm, kd 10: +5.4 mm); solo12_standing, lighter, settles in 0.2 s at 2 µm.
  A rest at the reference pose needs a controller that distributes the weight over the feet (contact-aware
  inverse dynamics), which the built-in controllers are not.
"""


if __name__ == "__main__":
    main()
