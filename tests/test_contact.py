"""Contact: the timestepping integrator against closed forms (sliding, resting, bouncing, stacking), its energy
ledger against energies computed independently, and the refusals and defaults of contact scenes."""

from __future__ import annotations

import importlib
import re
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from conftest import contact_steps

import multibody_sim as ms
from multibody_sim.exceptions import InvalidArgumentError, SimulationError
from multibody_sim.integrators.timestepping import SOLVER_COUNTS, TimeStepping
from multibody_sim.kernels import native as native_core
from multibody_sim.scenes import load_scene, make_scene

G = 9.81


def box_scene(*, mu: float = 0.8, velocity: float = 2.0, solver: str = "admm", **extra) -> ms.Scene:
    """A 1 kg box, 0.2 x 0.2 x 0.1 m, resting on the ground at z = 0 (or sliding along x at `velocity`)."""
    return make_scene(
        ground={"friction": mu},
        contact={"solver": solver},
        object=[
            {
                "name": "box",
                "shape": "box",
                "size": [0.2, 0.2, 0.1],
                "mass": 1.0,
                "position": [0.0, 0.0, 0.05],
                "velocity": [velocity, 0, 0, 0, 0, 0],
            }
        ],
        **extra,
    )


def tilted_drop(solver: str = "admm") -> ms.Scene:
    """Two boxes, tilted, dropped onto each other and the ground: landings on redundant corners, a problem that one
    solver iteration does not solve."""
    bottom = {"name": "a", "shape": "box", "size": [0.3, 0.3, 0.1], "mass": 3.0, "position": [0, 0, 0.06],
              "rpy": [0.05, 0.02, 0.0]}  # fmt: skip
    top = {"name": "b", "shape": "box", "size": [0.2, 0.2, 0.1], "mass": 2.0, "position": [0, 0, 0.17],
           "rpy": [0.0, 0.05, 0.1]}  # fmt: skip
    contact = {"pairs": "all", "body_friction": 0.8, "solver": solver}
    return make_scene(ground={"friction": 0.8}, contact=contact, object=[bottom, top])


def run(scene: ms.Scene, duration: float, dt: float, **options) -> ms.Trajectory:
    return ms.simulate(
        scene, scene.q0, scene.v0, duration=duration, dt=dt, integrator="timestepping", progress=False, **options
    )


# ---- closed forms ----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("solver", ["admm", "pgs"])
def test_sliding_box_decelerates_at_mu_g_and_stops_where_coulomb_says(solver):
    """v(t) = v0 - μ g t until it stops at v0/(μg), having slid v0²/(2μg): every step while sliding changes the
    velocity by exactly μ g dt (exact Coulomb cones, no regularization)."""
    mu, v0, dt = 0.8, 2.0, 1e-3
    traj = run(box_scene(mu=mu, velocity=v0, solver=solver), 0.4, dt)
    vx = traj.v[:, 0]
    sliding = np.flatnonzero(vx > mu * G * dt)  # steps that end still sliding
    decelerations = -np.diff(vx)[sliding[:-1]] / dt
    np.testing.assert_allclose(decelerations, mu * G, rtol=1e-6)
    stop = traj.t[np.argmax(vx <= 1e-9)]
    assert abs(stop - v0 / (mu * G)) <= dt
    assert abs(traj.q[-1, 0] - v0**2 / (2 * mu * G)) <= v0 * dt
    assert np.abs(vx[traj.t > stop + dt]).max() < 1e-9  # and stays stopped (stiction)
    assert np.abs(traj.q[:, 2] - 0.05).max() < 1e-9  # never sinks nor lifts


def test_resting_box_drifts_less_than_a_micrometre_in_a_second():
    traj = run(box_scene(velocity=0.0), 1.0, 1e-3)
    drift = np.linalg.norm(traj.q[:, :3] - traj.q[0, :3], axis=1).max()
    assert drift <= 1e-6
    assert traj.stats["solver_unconverged"] == 0


def apex_ratios(traj: ms.Trajectory, radius: float) -> np.ndarray:
    vz, z = traj.v[:, 2], traj.q[:, 2] - radius
    apexes = [z[0]] + [z[i] for i in range(1, len(vz)) if vz[i - 1] > 0 >= vz[i]]
    return np.array(apexes[1:]) / np.array(apexes[:-1])


def test_bouncing_ball_apexes_shrink_by_e_squared():
    """Newton's restitution e = 0.5: each apex is e² = 0.25 of the one before (free flight between bounces)."""
    scene = load_scene("bouncing_ball")
    traj = scene.run(duration=1.6)
    ratios = apex_ratios(traj, 0.05)[:3]  # 1 m -> 0.25 -> 0.0625 -> 0.016
    assert len(ratios) == 3
    np.testing.assert_allclose(ratios, 0.25, rtol=0.03)
    assert np.diff(traj.ledger["contact"].energy).min() >= 0.0


@pytest.mark.slow
def test_bouncing_ball_apexes_within_one_percent_at_a_tenth_of_a_millisecond():
    traj = load_scene("bouncing_ball").run(duration=1.6, dt=1e-4, output_dt=1e-4)
    np.testing.assert_allclose(apex_ratios(traj, 0.05)[:4], 0.25, rtol=0.01)


def test_stack_ground_carries_the_whole_weight_each_step():
    """At rest, the ground's normal impulses over one step sum to the stack's weight × dt."""
    scene = load_scene("box_stack")
    dt = 1e-3
    weight = sum(item.mass for item in scene.spec.objects) * G
    for problem, impulses, v in contact_steps(scene, 20, dt):
        normal = [
            impulses[3 * c + 2] * point.normal[2] for c, point in enumerate(problem.points) if "ground" in point.bodies
        ]
        assert sum(normal) == pytest.approx(weight * dt, rel=1e-9)
    assert np.abs(v).max() < 1e-9


# ---- the ledger ------------------------------------------------------------------------------------------------
def test_contact_work_of_a_step_is_the_kinetic_energy_the_impulses_change():
    """W = ½ λᵀJ(v⁺ + v_free) = T(q, v⁺) − T(q, v_free), with v_free from the scene's own forward dynamics and T
    from its kinetic energy: the ledger's contact entries (dissipated, minus the corrections' work) are −W."""
    scene = box_scene(velocity=1.0)
    q = scene.q0.copy()
    q[2] -= 1e-4  # a little penetration, so the correction's work is not zero
    v = scene.v0.copy()
    v[2] = -0.3  # landing while sliding
    dt = 1e-3
    tau = np.zeros(scene.nv)
    attempt = TimeStepping().attempt(scene, q, v, tau, dt, 0.0, None)
    v_free = v + dt * scene.forward_dynamics(q, v, tau)
    work = scene.kinetic_energy(q, attempt.v) - scene.kinetic_energy(q, v_free)
    names = [name for name, _ in scene.ledger_elements]
    flows = dict(zip(names, attempt.flows, strict=True))
    assert flows["penetration_correction"] > 0.0
    assert flows["contact"] > 0.0
    assert flows["penetration_correction"] + flows["restitution"] - flows["contact"] == pytest.approx(
        work, rel=1e-12, abs=1e-15
    )


@pytest.mark.parametrize("name", ["talos_standing", "go2_standing", "box_stack"])
def test_the_ledgers_kinetic_energy_from_crbas_mass_matrix_is_pinocchios_kinetic_energy(name):
    """The ledger's T at the step's start, ½ vᵀ (M − diag(raised)) v from the contact problem's CRBA
    (ContactModel.kinetic_energy), equals computeKineticEnergy's sum over the bodies after forwardKinematics
    (another Pinocchio algorithm) on the model's own armature, on random states: with the model's armature, with
    armature, and under a step's servo terms on M's diagonal (the armature raised, by a servo's size and far more)."""
    scene = load_scene(name)
    contact, model = scene.contact, scene.contact.model
    reference = model.createData()
    rng = np.random.default_rng(7)
    cases = [(model.armature.copy(), None), (rng.uniform(0.0, 0.5, model.nv), None)]
    cases += [(rng.uniform(0.0, 0.05, model.nv), size * rng.uniform(0.0, 1.0, model.nv)) for size in (1e-3, 1.0, 1e2)]
    for own, raised in cases:
        for _ in range(5):
            q = pin.randomConfiguration(model, -np.ones(model.nq), np.ones(model.nq))
            v = rng.normal(0.0, 2.0, model.nv)
            model.armature = own if raised is None else own + raised
            pin.crba(model, contact.data, q, pin.Convention.WORLD)  # as ContactModel.problem does
            model.armature = own
            expected = pin.computeKineticEnergy(model, reference, q, v)
            assert expected > 0.0
            tolerance = 1e-14 if raised is None else 1e-14 * (1.0 + raised.max())
            assert contact.kinetic_energy(v, raised) == pytest.approx(expected, rel=tolerance)


def test_no_other_ledger_element_is_named_contact():
    scene = load_scene("box_stack")
    names = [name for name, _ in scene.ledger_elements]
    assert [name for name in names if "contact" in name] == ["contact"]
    assert dict(scene.ledger_elements)["contact"] == "dissipated"


def test_timestep_error_is_the_free_fall_error_of_semi_implicit_euler():
    """In free fall a semi-implicit Euler step loses exactly ½ m g² dt² (its own formula books that)."""
    scene = make_scene(object=[{"name": "ball", "shape": "sphere", "radius": 0.1, "mass": 2.0, "position": [0, 0, 5]}])
    dt = 1e-3
    traj = run(scene, 0.1, dt)
    per_step = np.diff(traj.ledger["timestep_error"].energy)
    np.testing.assert_allclose(per_step, -0.5 * 2.0 * G**2 * dt**2, rtol=1e-6)
    assert np.abs(traj.energy_error).max() <= 1e-12 * 2.0 * G * 5


# ---- solver failures -------------------------------------------------------------------------------------------
def test_unconverged_steps_are_counted_and_more_than_one_percent_fails_the_run():
    """A solver stopped at its cap continues with its best impulses; past 1 % of the steps the run fails, with its
    samples."""
    scene = tilted_drop()
    capped = TimeStepping(max_iterations=1)
    with pytest.raises(SimulationError) as info:
        ms.simulate(scene, scene.q0, scene.v0, duration=0.05, dt=1e-3, integrator=capped, progress=False)
    error = info.value
    assert error.status == "solver_failed"
    traj = error.trajectory
    assert traj.t[-1] == pytest.approx(0.05)
    assert 0.01 * traj.stats["steps"] < traj.stats["solver_unconverged"] <= traj.stats["steps"]
    assert re.match(r"solver_failed: the contact solver did not converge on \d+ of 50 steps", str(error))


def test_a_failed_pgs_run_suggests_admm():
    """A run that fails on PGS (the Gauss–Seidel sweeps first; here capped at one iteration on two tilted boxes
    landing) says that the default is another way out; the same capped run on the default does not name itself."""
    messages = {}
    for solver in ("pgs", "admm"):
        scene = tilted_drop(solver)
        with pytest.raises(SimulationError) as info:
            ms.simulate(scene, scene.q0, scene.v0, duration=0.05, dt=1e-3, integrator=TimeStepping(max_iterations=1))
        assert info.value.status == "solver_failed"
        messages[solver] = str(info.value)
    hint = ' or [contact] solver = "admm" (the default: it converges more reliably than PGS on many or redundant '
    hint += "contact rows)"
    assert messages["pgs"].endswith("try a smaller dt" + hint)
    assert messages["admm"].endswith("try a smaller dt")


# ---- scenes, objects and refusals ------------------------------------------------------------------------------
def test_other_integrators_refuse_contact_scenes_naming_timestepping():
    scene = box_scene()
    with pytest.raises(InvalidArgumentError) as info:
        ms.simulate(scene, scene.q0, scene.v0, duration=0.01, dt=1e-3, integrator="rk4")
    assert str(info.value) == (
        "integrator 'rk4' cannot step scene 'objects-scene': it has contact ([ground], [contact] or [[object]]), "
        "which only integrator 'timestepping' steps"
    )


def test_without_contact_timestepping_is_semi_implicit_euler():
    robot = ms.load_robot("double_pendulum")
    q0, v0 = np.array([0.3, -0.2]), np.array([0.1, 0.5])
    ours = ms.simulate(robot, q0, v0, duration=0.05, dt=1e-3, integrator="timestepping", progress=False)
    theirs = ms.simulate(robot, q0, v0, duration=0.05, dt=1e-3, integrator="semi_implicit_euler", progress=False)
    np.testing.assert_array_equal(ours.q, theirs.q)
    np.testing.assert_array_equal(ours.v, theirs.v)


def test_a_contact_scene_without_an_integrator_uses_timestepping():
    assert box_scene().simulation_settings()["integrator"] == "timestepping"
    assert load_scene("sliding_box").simulation_settings()["integrator"] == "timestepping"


def test_objects_join_the_state_after_the_robot_with_world_velocities():
    """q: position and scalar-last quaternion; v: Pinocchio's body-frame velocity, from the TOML's world frame."""
    rpy, linear, angular = [0.3, -0.2, 1.1], [1.0, 2.0, 3.0], [0.5, -0.4, 0.2]
    scene = make_scene(
        robot={"source": "double_pendulum"},
        object=[
            {
                "name": "cube",
                "shape": "box",
                "size": [0.1, 0.2, 0.3],
                "mass": 2.0,
                "position": [1, 2, 3],
                "rpy": rpy,
                "velocity": [*linear, *angular],
            }
        ],
    )
    assert scene.nq == 2 + 7 and scene.nv == 2 + 6
    assert scene.dof_names[2:] == [f"cube.{c}" for c in ("vx", "vy", "vz", "wx", "wy", "wz")]
    q, v = scene.q0, scene.v0
    np.testing.assert_allclose(q[2:5], [1, 2, 3])
    rotation = pin.Quaternion(q[8], *q[5:8]).matrix()  # (w, x, y, z) constructor, scalar-last storage
    np.testing.assert_allclose(rotation, pin.rpy.rpyToMatrix(*rpy), atol=1e-15)
    data = scene.model.createData()
    pin.forwardKinematics(scene.model, data, q, v)
    joint = scene.model.getJointId("cube")
    world = pin.getVelocity(scene.model, data, joint, pin.LOCAL_WORLD_ALIGNED)
    np.testing.assert_allclose(world.linear, linear, atol=1e-14)
    np.testing.assert_allclose(world.angular, angular, atol=1e-14)
    # Uniform density: a box's inertia from its shape.
    inertia = scene.model.inertias[joint]
    assert inertia.mass == 2.0
    np.testing.assert_allclose(
        np.diag(inertia.inertia), 2.0 / 12 * np.array([0.2**2 + 0.3**2, 0.1**2 + 0.3**2, 0.1**2 + 0.2**2])
    )
    tau = np.zeros(scene.nv)
    tau[5] = 1.0
    with pytest.raises(InvalidArgumentError, match=re.escape("tau[2:8] acts on the scene's free objects")):
        scene.check_tau(tau)


def test_describe_says_what_is_modelled():
    text = load_scene("box_stack").describe()
    assert "contact pairs: ground-bottom, ground-middle, ground-top, bottom-middle, bottom-top, middle-top" in text
    assert "contact solver: semismooth Newton, ADMM after 20 Newton iterations" in text
    assert "position limits: reported, not enforced" in text
    assert "joint dry friction: regularized" in text
    assert "force elements: none" in text


# ---- robots: limits, exact joint friction, feet ------------------------------------------------------------------
def test_a_joint_driven_into_its_limit_stops_there():
    """panda_limits drives joint 4 towards −0.5 rad, past its upper limit (−0.0698 rad), with up to its full
    effort: enforced as a unilateral constraint, the limit is violated by at most 1e-6 rad at any sample."""
    scene = load_scene("panda_limits")
    traj = scene.run()
    upper = scene.upper_limit[3]
    assert traj.q[-1, 3] == pytest.approx(upper, abs=1e-3)  # it did reach the limit
    outside = np.maximum(traj.q - scene.upper_limit, scene.lower_limit - traj.q)  # every joint is limited
    assert outside.max() <= 1e-6
    assert traj.stats["saturated_dofs"].get("panda_joint4", 0) > 0  # pushed as hard as it could
    # Only an excursion beyond the enforcement's 1e-9 slop is reported as a violation.
    assert traj.limit_violations.count == int((outside > 1e-9).sum())
    text = scene.describe()
    assert "position limits: enforced as unilateral constraints (9 joints)" in text


def friction_scene(F: float) -> ms.Scene:
    """The double pendulum without gravity or damping, dry friction F on its first joint, exact."""
    return make_scene(
        robot={"source": "double_pendulum", "damping": False},
        gravity=[0.0, 0.0, 0.0],
        joints={"joint1": {"friction": F}},
        contact={"friction": "exact"},
    )


@pytest.mark.parametrize(
    ("v", "tau", "sticks"),
    [
        ([0.0, 0.0], [0.3, 0.0], True),
        ([0.0, 0.0], [-0.49, 0.0], True),
        ([0.0, 0.0], [0.8, 0.0], False),
        ([0.0, 0.0], [-0.49, 0.2], False),  # joint 2's torque loads joint 1 through M: it slips
        ([0.5, 0.2], [0.1, 0.0], False),
        ([-0.5, 0.2], [0.1, -0.3], True),  # the arm's own dynamics nearly stop joint 1: friction does the rest
    ],
)
def test_exact_joint_friction_sticks_below_its_bound_and_slips_with_coulomb_force(v, tau, sticks):
    """One step of dry friction F on joint 1 is a one-dimensional complementarity problem with a closed form:
    with v_free = v + dt M⁻¹(τ − C v) and w = (M⁻¹)₁₁, the impulse that stops the joint is p = −v_free[0] / w; if
    |p| ≤ F dt the joint sticks (v⁺ = v_free + M⁻¹ e₁ p), else it slips with the full Coulomb torque:
    v⁺ = v + dt M⁻¹(τ − C v − F sign(v⁺) e₁). The time-stepper agrees to 1e-9."""
    F, dt = 0.5, 1e-3
    scene = friction_scene(F)
    q, v, tau = np.array([0.3, -0.2]), np.array(v), np.array(tau)
    step = TimeStepping().attempt(scene, q, v, tau, dt, 0.0, None)
    M, h = scene.mass_matrix(q), scene.nonlinear_effects(q, v)
    e1 = np.array([1.0, 0.0])
    v_free = v + dt * np.linalg.solve(M, tau - h)
    column = np.linalg.solve(M, e1)
    stop = -v_free[0] / column[0]
    assert (abs(stop) <= F * dt) == sticks
    if sticks:
        expected = v_free + column * stop
        assert abs(step.v[0]) <= 1e-9
    else:
        expected = v + dt * np.linalg.solve(M, tau - h - F * np.sign(v_free[0]) * e1)
        assert np.sign(expected[0]) == np.sign(v_free[0])
    np.testing.assert_allclose(step.v, expected, rtol=0, atol=1e-9)
    assert "joint dry friction: exact (a constraint: stiction), on 1 joints" in scene.describe()


def test_solo12_stands_on_its_four_foot_spheres():
    scene = load_scene("solo12_standing")
    traj = scene.run(duration=0.5)
    assert np.abs(traj.q[:, 2] - traj.q[0, 2]).max() < 0.02  # dropped 3 mm, sags under its PD, never falls
    assert np.abs(traj.q[:, :2] - traj.q[0, :2]).max() < 1e-4  # its feet do not slide
    assert np.abs(traj.energy_error).max() <= 1e-9 * scene.total_mass * G
    assert np.diff(traj.ledger["contact"].energy).min() >= 0.0


def test_contact_with_mimic_joints_is_refused_naming_what_pinocchio_lacks():
    """Pinocchio 4.1's ConstraintCholeskyDecomposition raises on a model with a mimic joint ("This algorithm does
    not support Joint Mimic type in the model"): the scene says so, and what to drop, in one line."""
    with pytest.raises(ms.SceneError) as caught:
        make_scene(robot={"source": "panda", "mimic": True}, ground={})
    assert str(caught.value) == (
        "<scene>: contact: contact and mimic joints cannot be combined: Pinocchio 4.1's constraint Cholesky (the "
        "contact solver's Delassus operator) does not support mimic joints (drop robot.mimic, making the followers "
        "independent joints, or drop [ground], [contact] and [[object]])"
    )
    plain = make_scene(robot={"source": "panda"}, ground={})  # the same robot, its fingers independent: accepted
    assert plain.contact is not None and plain.nv == 9


def test_go2_standing_comes_to_rest_and_sags_as_its_pd_springs_carry_its_weight():
    """go2_standing holds still by the end of its run (its base moves < 0.1 mm over the last half second), and the
    sag from where its feet touch is the PD springs' (floating-base gravity compensation leaves the trunk's weight
    to them): Hooke's law, so doubling kp halves it."""
    from multibody_sim.controllers import PDGravity

    scene = load_scene("go2_standing")
    traj = scene.run(progress=False)
    assert np.linalg.norm(traj.q[-1, :3] - traj.q[len(traj) // 2, :3]) < 1e-4
    touchdown = scene.q0[2] - min(point.gap for point in scene.contact.detect(scene.q0))
    q_ref = scene.make_controller().pd.q_ref
    sags = []
    for kp in (100.0, 200.0):
        controller = PDGravity(scene, q_ref, kp=kp, kd=5.0)
        rest = ms.simulate(
            scene,
            scene.q0,
            scene.v0,
            duration=4.0,
            dt=1e-3,
            integrator="timestepping",
            controller=controller,
            output_dt=0.1,
        )
        assert np.abs(rest.v[-1]).max() < 1e-5  # at rest
        sags.append(touchdown - rest.q[-1, 2])
    assert sags[0] > 5e-3  # millimetres: what the first run's base settles by
    assert sags[0] / sags[1] == pytest.approx(2.0, rel=0.05)


def test_run_solo12_without_a_scene_says_nothing_holds_it_up(capsys):
    from multibody_sim.cli import main

    assert main(["run", "solo12", "--duration", "0.002"]) == 0
    out = capsys.readouterr().out
    assert (
        "note: nothing holds solo12 up: without a scene there is no ground or contact, so its floating base falls; "
        "run the shipped scene solo12_standing to stand it on the ground"
    ) in out


def test_bench_measures_a_contact_scene_against_timestepping_at_a_much_smaller_step():
    """A non-smooth system has no higher-order reference: the study says so and measures timestepping against
    itself at CONTACT_REFERENCE_DT, where its first order shows."""
    from multibody_sim import bench

    scene = load_scene("sliding_box")
    study = ms.work_precision(
        scene, scene.q0, scene.v0, duration=0.1, output_dt=0.02, steps=[0.02, 0.01, 0.005, 0.0025], repeats=1
    )
    reference = study.reference
    assert reference is not None
    assert (reference.integrator, reference.dt, reference.check_dt) == (
        "timestepping",
        bench.CONTACT_REFERENCE_DT,
        bench.CONTACT_REFERENCE_DT / 2,
    )
    assert {m.integrator for m in study.measurements if m.completed} == {"timestepping"}
    refused = {m.integrator for m in study.measurements if m.status == bench.STATUS_REFUSED}
    assert refused == set(ms.INTEGRATORS) - {"timestepping"}
    assert study.orders["timestepping"].observed == pytest.approx(1.0, abs=0.2)
    assert "the reference is the same integrator at a much smaller step" in study.summary()


# ---- the trajectory's contacts -------------------------------------------------------------------------------------
def test_the_trajectory_records_each_samples_contacts_compactly(tmp_path):
    """Sample i holds the contacts of the step that ended there: while the box slides, its four points' impulses
    sum to (−μ m g dt, 0, m g dt) in world axes, Coulomb's closed form; the record survives save/load and a
    chunked run (sample indices from the run's start)."""
    mu, dt = 0.8, 1e-3
    scene = box_scene(mu=mu)
    traj = run(scene, 0.2, dt)
    contacts = traj.contacts
    assert contacts is not None and contacts.bodies == ["ground", "box"]
    assert len(contacts.at(0).sample) == 0  # no step ended at the first sample
    for i in (1, 50, 200):
        shown = contacts.at(i)
        assert len(shown.sample) == 4 and (shown.pair == [0, 1]).all()
        np.testing.assert_allclose(shown.impulse.sum(axis=0), [-mu * G * dt, 0.0, G * dt], rtol=1e-6, atol=1e-15)
        np.testing.assert_allclose(shown.normal, np.tile([0.0, 0.0, 1.0], (4, 1)), atol=1e-12)
        np.testing.assert_allclose(shown.point[:, 2], 0.0, atol=1e-9)  # on the ground
        assert abs(shown.point[:, 0].mean() - traj.q[i - 1, 0]) < 1e-9  # under the box where the step started
    loaded = ms.Trajectory.load(traj.save(tmp_path / "box.npz"))
    run(scene, 0.2, dt, out=tmp_path / "chunked.npz", chunk=37)  # six chunk files, merged at the end
    chunked = ms.Trajectory.load(tmp_path / "chunked.npz")
    for other in (loaded, chunked):
        assert other.contacts is not None and other.contacts.bodies == contacts.bodies
        for part in ("sample", "pair", "point", "normal", "impulse"):
            np.testing.assert_array_equal(getattr(other.contacts, part), getattr(contacts, part))
    robot_run = ms.simulate(
        ms.load_robot("double_pendulum"), [0.1, 0.2], [0, 0], duration=0.01, dt=1e-3, progress=False
    )
    assert robot_run.contacts is None


def test_a_rollout_of_a_contact_scene_steps_each_row_as_simulate_does():
    """Rows of a rollout carry their own solver state (warm start, landings): each equals its own simulate(),
    its contacts included (per element, as Trajectory.contacts), also when batches are joined (Ray's chunks)."""
    rollout_module = importlib.import_module("multibody_sim.rollout")  # the module (the package exports the function)
    mu, dt = 0.8, 1e-3
    scene = box_scene(mu=mu)
    speeds = np.array([0.5, 1.0, 2.0])
    V0 = np.tile(scene.v0, (3, 1))
    V0[:, 0] = speeds
    batch = ms.rollout(scene, np.tile(scene.q0, (3, 1)), V0, duration=0.3, dt=dt, integrator="timestepping")
    assert list(batch.status) == ["completed"] * 3 and len(batch.contacts) == 3
    halves = [
        ms.rollout(scene, np.tile(scene.q0, (k, 1)), V0[rows], duration=0.3, dt=dt, integrator="timestepping")
        for k, rows in ((1, [0]), (2, [1, 2]))
    ]
    joined = rollout_module._concatenate(halves)
    for b in range(3):
        alone = run(box_scene(mu=mu, velocity=speeds[b]), 0.3, dt)
        for element in (batch.element(b), joined.element(b)):
            np.testing.assert_array_equal(element.q, alone.q)
            solver = {k: v for k, v in alone.stats.items() if k.startswith("solver_")}
            assert len(solver) == len(SOLVER_COUNTS) and solver["solver_steps"] > 0  # kept per element
            assert {k: element.stats[k] for k in solver} == solver
            assert element.contacts is not None and element.contacts.bodies == alone.contacts.bodies
            for part in ("sample", "pair", "point", "normal", "impulse"):
                np.testing.assert_array_equal(getattr(element.contacts, part), getattr(alone.contacts, part))
        # Independently of simulate(): while it slides, the four points' impulses sum to Coulomb's (−μ m g dt, 0,
        # m g dt); once it sticks, to (0, 0, m g dt).
        contacts, vx = batch.contacts[b], batch.v[b, :, 0]
        for i in (1, int(np.argmax(vx <= 1e-9)) + 5):
            sliding = vx[i] > 1e-9
            expected = [-mu * G * dt if sliding else 0.0, 0.0, G * dt]
            np.testing.assert_allclose(contacts.at(i).impulse.sum(axis=0), expected, rtol=1e-6, atol=1e-12)
    np.testing.assert_allclose(batch.q[:, -1, 0], speeds**2 / (2 * mu * G), atol=2.0 * dt)
    pendulum = ms.load_robot("double_pendulum")
    no_contact = ms.rollout(pendulum, [[0.1, 0.2]] * 2, [[0.0, 0.0]] * 2, duration=0.01, dt=1e-3, progress=False)
    assert no_contact.contacts == [None, None] and no_contact.element(1).contacts is None
    assert "solver_steps" not in no_contact.stats and "solver_steps" not in no_contact.element(1).stats
    totals = {k: int(batch.stats[k].sum()) for k in ("solver_steps", "solver_iterations", "solver_unconverged")}
    said = f"contact solver: {totals['solver_steps']} steps with constraints, {totals['solver_iterations']} iterations"
    assert said in batch.summary()


# ---- the URDF's collision geometry ------------------------------------------------------------------------------
SOLO_LEGS = {  # solo12's knees bent as in solo12_standing: locked, the robot is one rigid body on four feet
    f"{leg}_{joint}": value
    for leg, sign in (("FL", 1.0), ("FR", 1.0), ("HL", -1.0), ("HR", -1.0))
    for joint, value in (("HAA", 0.0), ("HFE", 0.8 * sign), ("KFE", -1.6 * sign))
}


def lowest_collision_vertex(scene: ms.Scene, q: np.ndarray) -> float:
    """min world z over every vertex of the URDF's collision meshes at q, independently of coal and of the contact
    code: the URDF read by yourdfpy, the STL files by trimesh, the links placed by Pinocchio's kinematics."""
    import trimesh
    import yourdfpy

    from multibody_sim.catalog import resolve_mesh_uri

    urdf_path = Path(scene.source["urdf_path"])
    urdf = yourdfpy.URDF.load(str(urdf_path), load_meshes=False, build_scene_graph=False)
    roots = [urdf_path.parents[3]]  # example-robot-data's share folder: package://example-robot-data/...
    model, data = scene.model, scene.model.createData()
    pin.framesForwardKinematics(model, data, q)
    lowest = np.inf
    for link in urdf.robot.links:
        for collision in link.collisions:
            mesh = collision.geometry.mesh
            path = resolve_mesh_uri(mesh.filename, urdf_path, package_dirs=roots)
            vertices = np.asarray(trimesh.load(path, force="mesh").vertices) * (
                1.0 if mesh.scale is None else mesh.scale
            )
            origin = np.eye(4) if collision.origin is None else collision.origin
            placement = data.oMf[model.getFrameId(link.name)].homogeneous @ origin
            lowest = min(lowest, float((vertices @ placement[:3, :3].T + placement[:3, 3])[:, 2].min()))
    return lowest


def test_a_robot_without_declared_geometry_rests_on_its_urdf_collision_meshes():
    """solo12 (legs locked: one rigid body) dropped 1.1 cm onto [ground] with no [[contact.geometry]]: it lands on its
    URDF collision meshes' convex hulls and comes to rest with its lowest collision vertex on the plane, to the
    penetration slop (1 nm)."""
    from multibody_sim.scenes.contact import PENETRATION_SLOP

    scene = make_scene(robot={"source": "solo12"}, ground={"friction": 0.8}, lock=SOLO_LEGS)
    start = scene.q0.copy()
    start[2] += 0.011 - lowest_collision_vertex(scene, start)  # its lowest vertex 1.1 cm above the ground
    text = scene.describe()
    assert "robot collision geometry (the URDF's): 17 shapes on 17 links, 17 of them meshes" in text
    assert native_core._scene_reason(scene) is None  # hulls run natively (their vertices against the ground)
    traj = ms.simulate(scene, start, scene.v0, duration=0.5, dt=1e-3, integrator="timestepping", progress=False)
    assert traj.stats["solver_unconverged"] <= 5  # of 500 steps (the landing's), well within the 1 % allowed
    assert np.abs(traj.v[-1]).max() < 1e-9  # at rest
    assert abs(lowest_collision_vertex(scene, traj.q[-1])) <= PENETRATION_SLOP
    assert traj.q[:, 2].min() > start[2] - 0.011 - 1e-9  # never below where the vertex meets the plane
    last = traj.contacts.at(len(traj) - 1)
    carrying = last.pair[np.linalg.norm(last.impulse, axis=1) > 0.0, 1]  # (the lower legs are speculative rows)
    assert {traj.contacts.bodies[j] for j in carrying} == {"FL_FOOT", "FR_FOOT", "HL_FOOT", "HR_FOOT"}


def test_a_standing_robot_holds_on_its_urdf_meshes_and_declared_geometry_replaces_them_per_body():
    """solo12 held by PD + gravity compensation on its URDF collision meshes stands (the solver converges on every
    step); a declared sphere replaces the URDF's meshes on the body it is on (every link of that joint) only."""
    controller = {"name": "pd_gravity", "kp": 20.0, "q_ref": [0.0, 0.0, 0.235, 0.0, 0.0, 0.0, 1.0]}
    controller["q_ref"] += [0.1, 0.8, -1.6, -0.1, 0.8, -1.6, 0.1, -0.8, 1.6, -0.1, -0.8, 1.6]
    scene = make_scene(robot={"source": "solo12"}, ground={"friction": 0.8}, controller=controller)
    traj = scene.run(duration=0.3, progress=False)
    assert traj.stats["solver_unconverged"] == 0
    assert traj.q[:, 2].min() > 0.2  # it stands: the base stays up
    sphere = {"frame": "FL_FOOT", "shape": "sphere", "radius": 0.016}
    mixed = make_scene(robot={"source": "solo12"}, ground={}, contact={"robot_geometry": "urdf", "geometry": [sphere]})
    knee = mixed.model.frames[mixed.model.getFrameId("FL_FOOT")].parentJoint
    on_knee = [g for g in mixed.contact.geometries if g.joint == knee]
    assert [(g.body, g.kind, g.from_urdf) for g in on_knee] == [("FL_FOOT", "sphere", False)]
    assert sum(g.from_urdf for g in mixed.contact.geometries) == 17 - 2  # FL_LOWER_LEG's and FL_FOOT's replaced
    declared_only = make_scene(robot={"source": "solo12"}, ground={}, contact={"geometry": [sphere]})
    assert not any(g.from_urdf for g in declared_only.contact.geometries)  # the default once geometry is declared


def test_a_robot_without_collision_geometry_is_told_so():
    text = make_scene(robot={"source": "solo12"}, ground={}, contact={"robot_geometry": "declared"}).describe()
    assert (
        'robot collision geometry: none (robot_geometry = "declared" and no [[contact.geometry]]): the robot passes '
        'through everything; declare [[contact.geometry]] (spheres on feet, boxes on soles) or robot_geometry = "urdf"'
    ) in text
    assert "contact pairs: none" in text
    no_ground = make_scene(robot={"source": "panda"}, contact={"limits": "enforce"})  # nothing to touch: no meshes
    assert 'robot collision geometry: none (nothing to touch: no [ground], and contact.pairs is "ground")' in (
        no_ground.describe()
    )
    mjcf = Path(__file__).parent / "data" / "mjcf" / "floating_arm.xml"  # its geoms: box, capsule, sphere, cylinder
    assert "robot collision geometry (the MJCF's): 4 shapes on 4 links, 0 of them meshes" in (
        make_scene(robot={"source": str(mjcf)}, ground={}).describe()
    )
    with pytest.raises(ms.SceneError, match=re.escape("contact.robot_geometry: needs a robot")):
        make_scene(
            ground={}, contact={"robot_geometry": "urdf"}, object=[{"shape": "sphere", "radius": 0.1, "mass": 1.0}]
        )
    with pytest.raises(ms.SceneError, match=re.escape("contact.robot_geometry: must be one of declared, urdf, got")):
        make_scene(robot={"source": "solo12"}, ground={}, contact={"robot_geometry": "meshes"})


def test_a_patch_keeps_its_deepest_point_and_the_farthest_from_those_kept():
    """Of 24 points on a circle, flat, one 0.1 mm deeper: MAX_PATCH_POINTS kept, the deepest and then each farthest
    from those kept (the quarter points); points above PATCH_DEPTH and near-duplicates are not kept."""
    from multibody_sim.scenes import narrow_phase as narrow

    angles = np.linspace(0.0, 2 * np.pi, 24, endpoint=False)
    ring = [
        narrow.Candidate(k, np.array([np.cos(a), np.sin(a), 0.0]), np.array([np.cos(a), np.sin(a), -1e-4 * (k == 3)]),
                         -1e-4 * (k == 3))
        for k, a in enumerate(angles)
    ]  # fmt: skip
    kept = narrow.select(ring, np.array([0.0, 0.0, 1.0]), narrow.MIN_PATCH_SPACING)
    assert len(kept) == narrow.MAX_PATCH_POINTS == 4
    np.testing.assert_allclose(sorted(np.degrees(angles[[c.feature for c in kept]])), [45, 135, 225, 315])
    high = [narrow.Candidate(0, np.zeros(3), np.zeros(3), 0.0), narrow.Candidate(1, np.ones(3), np.ones(3), 0.002)]
    assert [c.feature for c in narrow.select(high, np.array([0.0, 0.0, 1.0]), 0.0)] == [0]
    twins = [narrow.Candidate(k, np.full(3, 1e-3 * k), np.full(3, 1e-3 * k), 0.0) for k in range(3)]
    assert [c.feature for c in narrow.select(twins, np.array([0.0, 0.0, 1.0]), 0.01)] == [0]


def test_stepper_steps_a_contact_scene_as_simulate_does():
    """Stepper's control intervals restart the solver state as jumps: the time-stepper keeps its warm start there,
    and the samples equal simulate()'s bit for bit."""
    scene = load_scene("solo12_standing")
    controller = scene.make_controller()
    stepper = ms.Stepper(scene, dt=1e-3, integrator="timestepping", q0=scene.q0, v0=scene.v0)
    for _ in range(100):
        stepper.step(controller(stepper.t, stepper.q, stepper.v))
    traj = scene.run(duration=0.1, progress=False)
    np.testing.assert_array_equal(stepper.q, traj.q[-1])
    np.testing.assert_array_equal(stepper.v, traj.v[-1])
    solver = {k: v for k, v in traj.stats.items() if k.startswith("solver_")}
    assert solver["solver_steps"] == 100 and {k: stepper.stats[k] for k in solver} == solver


def test_a_misspelt_body_in_contact_pairs_gets_a_did_you_mean() -> None:
    """A contact pair naming a body the scene's geometry lacks names the closest ones, not every body."""
    box = {"name": "box", "shape": "box", "size": [0.1, 0.1, 0.05], "mass": 0.2, "position": [0.0, 0.0, 0.5]}
    with pytest.raises(ms.SceneError) as caught:
        make_scene(robot={"source": "solo12"}, ground={"friction": 0.8}, object=[box],
                   contact={"pairs": [["ground", "base_lnk"]]})  # fmt: skip
    message = str(caught.value)
    assert message.endswith("contact.pairs[0][1]: unknown body 'base_lnk' (did you mean 'base_link'?)"), message
    assert "FL_FOOT" not in message  # solo12's other bodies are not listed


def test_contact_chunks_read_as_the_last_write_of_each_sample() -> None:
    """recording's contact chunks (an engine call's samples at once) against a plain dict of samples: a sample written
    again (with or without contacts) holds its last write, truncation keeps samples below n, and the record lists
    the samples in order with each sample's rows as written."""
    from multibody_sim.recording import SampleStore, contacts_at, kept_contacts

    rng = np.random.default_rng(7)
    store = SampleStore(1, 1, 1, 0, 0, 4)
    expected: dict[int, np.ndarray] = {}
    for _ in range(60):
        samples = rng.choice(25, size=rng.integers(1, 5), replace=False)
        parts = [rng.normal(size=(rng.integers(0, 3), 11)) for _ in samples]
        if rng.random() < 0.5:  # one chunk for several samples, as the native engine appends them
            sample = np.concatenate([np.full(len(p), s) for s, p in zip(samples, parts)]).astype(np.int64)
            rows = np.concatenate(parts).reshape(-1, 11)
            store.contacts.setdefault(0, []).append((samples.astype(np.int64), sample, rows))
        else:  # one sample at a time, as the Python kernel writes them
            for s, p in zip(samples, parts):
                store.write_contacts(int(s), 0, p)
        for s, p in zip(samples, parts):
            expected[int(s)] = p
        if rng.random() < 0.1:
            n = int(rng.integers(5, 25))
            store.truncate(0, n)
            expected = {s: p for s, p in expected.items() if s < n}
    for n in (0, 7, 25):
        sample, rows = kept_contacts(store.contacts[0], n)
        keys = sorted(s for s, p in expected.items() if s < n and len(p))
        want = np.concatenate([expected[s] for s in keys]).reshape(-1, 11) if keys else np.zeros((0, 11))
        np.testing.assert_array_equal(rows, want)
        np.testing.assert_array_equal(sample, np.repeat(keys, [len(expected[s]) for s in keys]).astype(np.int64))
    for s in range(30):
        held = contacts_at(store.contacts[0], s)
        if s in expected and len(expected[s]):
            np.testing.assert_array_equal(held, expected[s])
        else:
            assert held is None


def test_contact_chunks_in_order_read_as_written() -> None:
    """Chunks in sample order with no sample written twice (a native run's) read as their rows concatenated, and a
    truncation below their end drops the later samples' rows."""
    from multibody_sim.recording import kept_contacts

    rng = np.random.default_rng(8)
    chunks, parts = [], []
    for first in (0, 3, 9):
        written = np.arange(first, first + 3, dtype=np.int64)
        counts = rng.integers(0, 4, size=3)
        rows = rng.normal(size=(int(counts.sum()), 11))
        chunks.append((written, np.repeat(written, counts), rows))
        parts.append((np.repeat(written, counts), rows))
    sample, rows = kept_contacts(chunks, 12)
    np.testing.assert_array_equal(sample, np.concatenate([s for s, _ in parts]))
    np.testing.assert_array_equal(rows, np.concatenate([r for _, r in parts]))
    sample, rows = kept_contacts(chunks, 4)
    everything = np.concatenate([s for s, _ in parts])
    np.testing.assert_array_equal(sample, everything[everything < 4])
    np.testing.assert_array_equal(rows, np.concatenate([r for _, r in parts])[everything < 4])


def test_contacts_record_holds_the_kept_rows_columns() -> None:
    """SampleStore.contacts_record copies each column block of the kept rows once, from the chunks themselves when
    they are in order: its arrays are kept_contacts' columns (pairs as int64), C-contiguous, for chunks in order, a
    sample written again, chunks out of order and truncations; and it owns its memory (not a view of a chunk)."""
    from multibody_sim.recording import SampleStore, kept_contacts

    system = make_scene(robot={"source": "double_pendulum"}, ground={})
    rng = np.random.default_rng(9)
    in_order = [
        (np.arange(a, a + 3), np.repeat(np.arange(a, a + 3), [2, 0, 1]), rng.normal(size=(3, 11))) for a in (0, 3, 6)
    ]
    again = in_order + [(np.array([4]), np.array([4, 4]), rng.normal(size=(2, 11)))]  # sample 4 written again
    reversed_ = in_order[::-1]
    unwritten = [(np.array([0, 1]), np.array([1, 2]), rng.normal(size=(2, 11)))]  # a row of a sample not written
    for chunks in (in_order, again, reversed_, unwritten):
        for chunk in chunks:
            chunk[2][:, :2] = rng.integers(0, 3, size=(len(chunk[2]), 2)) + 0.0
        for n in (9, 5, 1):
            store = SampleStore(1, 1, 1, 0, 0, 4)
            store.contacts[0] = list(chunks)
            record = store.contacts_record(0, n, system)
            sample, rows = kept_contacts(chunks, n)
            if not len(sample):
                assert len(record.sample) == 0
                continue
            np.testing.assert_array_equal(record.sample, sample)
            assert record.pair.dtype == np.int64
            np.testing.assert_array_equal(record.pair, rows[:, :2].astype(np.int64))
            for part, (lo, hi) in zip(
                (record.point, record.normal, record.impulse), ((2, 5), (5, 8), (8, 11)), strict=True
            ):
                np.testing.assert_array_equal(part, rows[:, lo:hi])
                assert part.flags.c_contiguous and not any(np.shares_memory(part, c[2]) for c in chunks)
