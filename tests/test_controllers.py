"""Built-in controllers, checked against closed-loop analysis, Lyapunov bounds and independent references."""

from __future__ import annotations

import inspect
import math
import re
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
import pytest
from scipy.interpolate import CubicSpline
from scipy.optimize import brentq, root

import multibody_sim as ms
from multibody_sim.cli import main

# A UR5 pose well inside its limits, elbow bent, away from singularities.
UR5_POSE = np.array([0.3, -1.2, 1.4, -0.6, 1.2, 0.5])
CONTROLLER_NAMES = "computed_torque, gravity_compensation, pd, pd_gravity, potential_field"
PD_PARAMETERS = "kd, kp (required), q_ref (required), v_ref"


def exact(message: str) -> str:
    return f"^{re.escape(message)}$"


def window_max(traj: ms.Trajectory, values: np.ndarray, start: float, stop: float) -> float:
    inside = (traj.t >= start) & (traj.t < stop)
    return float(np.abs(values[inside]).max())


# ---- PD and gravity compensation ----------------------------------------------------------------------
def test_pd_gravity_converges_at_the_rate_of_the_linearised_closed_loop(robot):
    """PD + g(q): the error decays to zero, as fast as the slowest eigenvalue of M(q*) ë + Kd ė + Kp e = 0."""
    ur5 = robot("ur5")
    kp = np.array([400.0, 400.0, 200.0, 40.0, 40.0, 10.0])
    controller = ms.PDGravity(ur5, UR5_POSE, kp=kp)
    q0 = UR5_POSE + np.random.default_rng(1).uniform(-0.2, 0.2, 6)
    traj = ms.simulate(ur5, q0, np.zeros(6), duration=3.0, dt=1e-3, controller=controller, output_dt=0.01)
    assert np.all(np.abs(traj.tau) < ur5.effort_limit)  # never saturated: the linear analysis applies
    error = traj.q - UR5_POSE
    assert np.abs(error[-1]).max() < 1e-8 and np.abs(traj.v[-1]).max() < 1e-7  # no steady-state error
    # Linearised at q* with gravity compensated exactly, the Coriolis term (quadratic in v) drops out.
    M = ur5.mass_matrix(UR5_POSE)
    A = np.block(
        [
            [np.zeros((6, 6)), np.eye(6)],
            [-np.linalg.solve(M, np.diag(kp)), -np.linalg.solve(M, np.diag(controller.pd.kd))],
        ]
    )
    slowest = -max(np.linalg.eigvals(A).real)
    # The slowest mode is an oscillating pair: compare maxima over successive one-second windows.
    observed = math.log(window_max(traj, error, 1.0, 2.0) / window_max(traj, error, 2.0, 3.0))
    assert observed == pytest.approx(slowest, rel=0.05)


def test_pd_without_gravity_compensation_leaves_the_static_error_of_gravity(robot):
    """Pure PD settles where Kp (q* - q) = g(q): the exact root, and Kp⁻¹ g(q*) to first order (residual ∝ kp⁻²)."""
    ur5 = robot("ur5")
    base_kp = np.array([2000.0, 2000.0, 1000.0, 200.0, 200.0, 50.0])
    residuals = []
    for scale in (1.0, 2.0):
        kp = scale * base_kp
        traj = ms.simulate(
            ur5, UR5_POSE, np.zeros(6), duration=2.0, dt=1e-3, controller=ms.PD(ur5, UR5_POSE, kp=kp), output_dt=0.1
        )
        assert np.abs(traj.v[-1]).max() < 1e-9  # settled
        static = root(lambda q, kp=kp: kp * (UR5_POSE - q) - ur5.gravity(q), UR5_POSE, tol=1e-14).x
        assert np.abs(traj.q[-1] - static).max() < 1e-10
        error = UR5_POSE - traj.q[-1]
        first_order = ur5.gravity(UR5_POSE) / kp
        assert np.abs(error).max() > 1e-3  # a real sag, not round-off
        residuals.append(np.abs(error - first_order).max())
    assert residuals[0] / residuals[1] == pytest.approx(4.0, rel=0.05)  # second order in 1/kp


@pytest.mark.parametrize("name", ["ur5", "panda"])
@pytest.mark.parametrize("control_dt", [None, 0.01])
def test_gravity_compensation_holds_an_arm_still(robot, name, control_dt):
    arm = robot(name)
    q0 = arm.random_configuration(np.random.default_rng(7))
    options = {} if control_dt is None else {"control_dt": control_dt}
    held = ms.simulate(
        arm, q0, np.zeros(arm.nv), duration=1.0, dt=1e-3, controller=ms.GravityCompensation(arm), **options
    )
    assert np.abs(held.v).max() < 1e-10
    assert np.abs(held.q - q0).max() < 1e-10
    fallen = ms.simulate(arm, q0, np.zeros(arm.nv), duration=0.2, dt=1e-3)
    assert np.abs(fallen.v[-1]).max() > 0.1  # without it the same arm falls


def test_floating_base_controllers_leave_the_base_unactuated(robot):
    solo = robot("solo12")
    q = solo.random_configuration(np.random.default_rng(2))
    v = np.random.default_rng(3).normal(size=solo.nv)
    gravity = ms.GravityCompensation(solo)(0.0, q, v)
    np.testing.assert_array_equal(gravity[:6], 0.0)
    np.testing.assert_allclose(gravity[6:], solo.gravity(q)[6:], rtol=1e-12, atol=1e-12)
    kp = np.arange(1.0, 13.0)  # one gain per actuated joint: nv - 6 = 12
    pd = ms.PD(solo, solo.neutral(), kp=kp, kd=0.5)
    tau = pd(0.0, q, v)
    np.testing.assert_array_equal(tau[:6], 0.0)
    expected = kp * pin.difference(solo.model, q, solo.neutral())[6:] - 0.5 * v[6:]
    np.testing.assert_allclose(tau[6:], expected, rtol=1e-12, atol=1e-12)
    with pytest.raises(ms.InvalidArgumentError, match=exact("kp must be a number or have shape (12,), got (18,)")):
        ms.PD(solo, solo.neutral(), kp=np.ones(18))


# ---- computed torque ----------------------------------------------------------------------------------
CT_TIMES = [0.0, 0.5, 1.0, 1.5]
CT_WAYPOINTS = np.array(
    [
        [0.0, -1.2, 1.4, -0.6, 1.2, 0.5],
        [0.5, -1.0, 1.0, -0.3, 1.0, 0.8],
        [0.8, -1.4, 1.6, -0.9, 1.5, 0.2],
        [0.4, -1.1, 1.2, -0.5, 1.1, 0.6],
    ]
)


def test_computed_torque_error_is_logged_and_shrinks_linearly_with_control_dt(robot):
    """The zero-order hold is the only error source left: first order in control_dt."""
    ur5 = robot("ur5")
    reference = CubicSpline(CT_TIMES, CT_WAYPOINTS, bc_type="clamped")  # revolute joints: the chart is q itself
    periods = [1e-3, 2e-3, 4e-3, 8e-3]
    worst = []
    for period in periods:
        controller = ms.ComputedTorque(ur5, CT_TIMES, CT_WAYPOINTS, kp=100.0)
        traj = ms.simulate(
            ur5, CT_WAYPOINTS[0], np.zeros(6), duration=1.5, dt=1e-3, controller=controller, control_dt=period
        )
        log = controller.tracking_error()
        k = round(period / 1e-3)
        np.testing.assert_allclose(log.t, traj.t[:-1:k], rtol=0, atol=1e-12)  # one row per controller call
        # Recomputed from the trajectory and an independent spline of the same waypoints.
        np.testing.assert_allclose(log.position_error, reference(log.t) - traj.q[:-1:k], rtol=0, atol=1e-12)
        np.testing.assert_allclose(log.velocity_error, reference(log.t, 1) - traj.v[:-1:k], rtol=0, atol=1e-12)
        worst.append(log.max_position_error)
    assert worst[0] < 1e-3  # rad, at a 1 kHz control rate with kp = 100 /s²
    slope = np.polyfit(np.log(periods), np.log(worst), 1)[0]
    assert slope == pytest.approx(1.0, abs=0.1)


def test_computed_torque_reference_wraps_continuous_joints(robot):
    """Waypoints in (cos, sin) are reached; each leg takes the short way; the velocity is the position's derivative."""
    arm = robot("double_pendulum_continuous")
    angles = np.array([[0.0, 0.0], [2.5, -1.0], [5.0, -2.0], [7.0, 1.0]])  # the first joint turns more than once
    waypoints = np.column_stack(
        [np.cos(angles[:, 0]), np.sin(angles[:, 0]), np.cos(angles[:, 1]), np.sin(angles[:, 1])]
    )
    controller = ms.ComputedTorque(arm, [0.0, 1.0, 2.0, 3.0], waypoints)
    for t, point in zip([0.0, 1.0, 2.0, 3.0], waypoints, strict=True):
        np.testing.assert_allclose(controller.reference(t)[0], point, atol=1e-12)
    unwrapped = CubicSpline([0.0, 1.0, 2.0, 3.0], angles, bc_type="clamped")
    for t in np.linspace(0.05, 2.95, 7):
        q, v, a = controller.reference(t)
        np.testing.assert_allclose(q, pin.integrate(arm.model, waypoints[0], unwrapped(t)), atol=1e-12)
        h = 1e-6
        fd = pin.difference(arm.model, controller.reference(t - h)[0], controller.reference(t + h)[0]) / (2 * h)
        np.testing.assert_allclose(v, fd, atol=1e-6)
        np.testing.assert_allclose(a, unwrapped(t, 2), atol=1e-9)
    _, v_end, a_end = controller.reference(4.0)  # after the last waypoint: held at rest
    assert not v_end.any() and not a_end.any()


def test_computed_torque_log_restarts_with_a_new_run(robot):
    ur5 = robot("ur5")
    controller = ms.ComputedTorque(ur5, CT_TIMES, CT_WAYPOINTS)
    first = ms.simulate(ur5, CT_WAYPOINTS[0], np.zeros(6), duration=0.2, dt=1e-3, controller=controller)
    log_first = controller.tracking_error()
    again = ms.simulate(ur5, CT_WAYPOINTS[0], np.zeros(6), duration=0.2, dt=1e-3, controller=controller)
    log_again = controller.tracking_error()
    assert len(log_again.t) == len(log_first.t) == 200
    np.testing.assert_array_equal(log_again.position_error, log_first.position_error)
    np.testing.assert_array_equal(again.q, first.q)
    controller.reset()
    assert controller.tracking_error().t.shape == (0,)
    assert controller.tracking_error().position_error.shape == (0, 6)


def test_computed_torque_refuses_a_floating_base(robot):
    solo = robot("solo12")
    message = (
        "computed torque needs every velocity coordinate actuated, but robot 'solo12' has a floating base whose 6 "
        "are not (load it with floating_base=False to weld the base)"
    )
    with pytest.raises(ms.InvalidArgumentError, match=exact(message)):
        ms.ComputedTorque(solo, [0.0, 1.0], [solo.neutral(), solo.neutral()])


def test_computed_torque_argument_errors(robot):
    ur5 = robot("ur5")
    with pytest.raises(ms.InvalidArgumentError, match=exact("times must be strictly increasing, got [0.0, 1.0, 1.0]")):
        ms.ComputedTorque(ur5, [0.0, 1.0, 1.0], CT_WAYPOINTS[:3])
    with pytest.raises(ms.InvalidArgumentError, match=exact("waypoints must have shape (3, 6), got (4, 6)")):
        ms.ComputedTorque(ur5, [0.0, 1.0, 2.0], CT_WAYPOINTS)
    with pytest.raises(ms.InvalidArgumentError, match=exact("bc_type must be 'clamped' or 'natural', got 'cubic'")):
        ms.ComputedTorque(ur5, CT_TIMES, CT_WAYPOINTS, bc_type="cubic")


# ---- potential field on the point robot ---------------------------------------------------------------
def point_robot_field(robot, obstacles, **options: Any) -> tuple[ms.Robot, ms.PotentialField]:
    puck = robot("point_robot")
    return puck, ms.PotentialField(puck, [2.0, 0.0], obstacles=obstacles, **options)


def surface_distance(points: np.ndarray, center: Any, radius: float) -> np.ndarray:
    return np.linalg.norm(points - np.asarray(center), axis=1) - radius


def test_point_robot_model(robot):
    """The shipped point robot: identity mass matrix, no gravity load, 20 N effort limits."""
    puck = robot("point_robot")
    q = puck.random_configuration(np.random.default_rng(0))
    np.testing.assert_allclose(puck.mass_matrix(q), np.eye(2), atol=1e-15)
    np.testing.assert_allclose(puck.gravity(q), 0.0, atol=1e-15)
    np.testing.assert_array_equal(puck.effort_limit, [20.0, 20.0])


def test_potential_field_forces_are_the_negative_gradient(robot):
    """forces() against central differences of potential(), in the quadratic, conic and repulsive zones."""
    _, field = point_robot_field(robot, [((0.0, 0.1), 0.5), ([1.0, -0.8], 0.3)])
    rng = np.random.default_rng(4)
    points = [np.array([1.9, 0.05]), np.array([-2.0, 0.3]), np.array([0.0, 0.75]), np.array([0.7, -0.4])]
    points += list(rng.uniform(-2.5, 2.5, (20, 2)))
    checked = 0
    for x in points:
        if np.isinf(field.potential(x)):
            continue
        attract, repulse = field.forces(x)
        h = 1e-6
        gradient = [(field.potential(x + h * e) - field.potential(x - h * e)) / (2 * h) for e in np.eye(2)]
        np.testing.assert_allclose(attract + repulse, -np.array(gradient), rtol=1e-6, atol=1e-6)
        checked += 1
    assert checked >= 20
    assert np.isinf(field.potential([0.0, 0.2]))  # inside an obstacle


def test_potential_field_goes_around_an_obstacle_within_its_lyapunov_bound(robot):
    """E = ½ vᵀ M v + U(x) never increases (the robot follows −∇U with damping), so U_rep ≤ U(x0) bounds the
    approach: the robot never gets closer to the surface than ρ* with ½ k_rep (1/ρ* − 1/ρ0)² = U(x0)."""
    center, radius = (0.0, 0.1), 0.5
    puck, field = point_robot_field(robot, [(center, radius)])
    traj = ms.simulate(puck, [-2.0, 0.0], [0.0, 0.0], duration=12.0, dt=5e-3, controller=field)
    assert np.linalg.norm(traj.q[-1] - [2.0, 0.0]) < field.goal_tolerance
    assert field.local_minima == []
    energy = 0.5 * np.sum(traj.v**2, axis=1) + field.potential(traj.q)  # M = identity
    assert np.diff(energy).max() <= 1e-9 * energy[0]
    rho_star = 1.0 / (1.0 / field.influence + math.sqrt(2.0 * energy[0] / field.k_repulse))
    closest = surface_distance(traj.q, center, radius).min()
    assert rho_star < closest < field.influence  # repelled, never inside
    assert traj.q[:, 1].min() < -0.5  # it went round below (the obstacle leans up)


def equilibrium_on_the_axis(field: ms.PotentialField, radius: float) -> float:
    """x < 0 on the symmetry line where the capped pull k dc balances the repulsion k_rep (1/ρ − 1/ρ0)/ρ²."""
    pull = field.k_attract * field.conic_distance

    def balance(rho: float) -> float:
        return field.k_repulse * (1.0 / rho - 1.0 / field.influence) / rho**2 - pull

    rho = brentq(balance, 1e-3, field.influence * (1 - 1e-9), xtol=1e-15)
    return -(radius + rho)


def test_symmetric_obstacle_traps_the_field_and_the_stall_is_detected(robot):
    puck, field = point_robot_field(robot, [((0.0, 0.0), 0.5)], escape=False)
    traj = ms.simulate(puck, [-2.0, 0.0], [0.0, 0.0], duration=8.0, dt=5e-3, controller=field)
    x_eq = equilibrium_on_the_axis(field, 0.5)
    assert x_eq + 2.0 > field.conic_distance and 2.0 - x_eq > field.conic_distance  # in the constant-pull zone
    np.testing.assert_allclose(traj.q[-1], [x_eq, 0.0], atol=1e-4)  # stuck, 2.7 m short of the goal
    assert not traj.q[:, 1].any()  # symmetry is never broken by itself
    [stall] = field.local_minima  # detected once, not at every call
    np.testing.assert_allclose(stall.position, [x_eq, 0.0], atol=0.02)
    assert stall.push is None and field.stall_time <= stall.t < 5.0
    assert field.summary().startswith("potential field: short of the goal (distance 2.72); 1 local minimum detected")


def test_random_push_escapes_the_local_minimum_deterministically(robot):
    center, radius = (0.0, 0.0), 0.5
    puck, field = point_robot_field(robot, [(center, radius)], seed=0)
    traj = ms.simulate(puck, [-2.0, 0.0], [0.0, 0.0], duration=12.0, dt=5e-3, controller=field)
    assert np.linalg.norm(traj.q[-1] - [2.0, 0.0]) < field.goal_tolerance
    assert surface_distance(traj.q, center, radius).min() > 0.05
    events = field.local_minima
    assert len(events) >= 1 and all(e.push is not None for e in events)
    assert np.linalg.norm(events[0].push) == pytest.approx(field.escape_force, rel=1e-12)
    assert events[0].position[0] == pytest.approx(equilibrium_on_the_axis(field, radius), abs=0.02)
    # The same controller reused (it starts afresh when time goes back) and a new one with the same seed agree
    # bitwise; another seed pushes another way.
    for again in (field, ms.PotentialField(puck, [2.0, 0.0], obstacles=[(center, radius)], seed=0)):
        repeat = ms.simulate(puck, [-2.0, 0.0], [0.0, 0.0], duration=12.0, dt=5e-3, controller=again)
        np.testing.assert_array_equal(repeat.q, traj.q)
    other = ms.PotentialField(puck, [2.0, 0.0], obstacles=[(center, radius)], seed=1)
    ms.simulate(puck, [-2.0, 0.0], [0.0, 0.0], duration=4.0, dt=5e-3, controller=other)
    assert not np.array_equal(other.local_minima[0].push, events[0].push)


# ---- potential field on an arm's end effector --------------------------------------------------------
UR5_START = np.array([0.0, -1.2, 1.4, -0.6, 1.2, 0.5])


def ur5_task(robot) -> tuple[ms.Robot, np.ndarray, np.ndarray, np.ndarray]:
    """(ur5, tool0 at the start, goal, obstacle centre) for the end-effector field."""
    ur5 = robot("ur5")
    data = ur5.model.createData()
    pin.framesForwardKinematics(ur5.model, data, UR5_START)
    start = data.oMf[ur5.model.getFrameId("tool0")].translation.copy()
    goal = start + np.array([-0.3, 0.35, 0.15])
    return ur5, start, goal, (start + goal) / 2 + np.array([0.05, 0.0, 0.0])


def test_end_effector_field_torques_are_the_gradient_through_the_kinematics(robot):
    """tau = Jᵀ(−∇U) equals −∂U(x(q))/∂q by finite differences of the forward kinematics (no damping, no g)."""
    ur5, _, goal, center = ur5_task(robot)
    field = ms.PotentialField(
        ur5, goal, frame="tool0", obstacles=[(center, 0.08)], influence=0.3, kd=0.0, gravity_compensation=False
    )
    rng = np.random.default_rng(5)
    for q in [UR5_START, UR5_START + rng.uniform(-0.3, 0.3, 6)]:
        tau = field(0.0, q, np.zeros(6))
        h = 1e-6

        def energy(dq: np.ndarray, q: np.ndarray = q) -> float:
            return float(field.potential(field.position(pin.integrate(ur5.model, q, dq))))

        gradient = np.array([(energy(h * e) - energy(-h * e)) / (2 * h) for e in np.eye(6)])
        np.testing.assert_allclose(tau, -gradient, rtol=1e-6, atol=1e-6)


def test_end_effector_reaches_the_goal_around_an_obstacle(robot):
    ur5, start, goal, center = ur5_task(robot)
    field = ms.PotentialField(
        ur5,
        goal,
        frame="tool0",
        obstacles=[(center, 0.08)],
        k_attract=100.0,
        conic_distance=0.3,
        k_repulse=0.01,
        influence=0.1,
    )
    traj = ms.simulate(ur5, UR5_START, np.zeros(6), duration=5.0, dt=4e-3, controller=field, output_dt=0.02)
    path = np.array([field.position(q) for q in traj.q])
    np.testing.assert_allclose(path[0], start, atol=1e-12)
    assert np.linalg.norm(path[-1] - goal) < field.goal_tolerance
    assert surface_distance(path, center, 0.08).min() > 0.0
    assert field.local_minima == []


# ---- registry and command line -----------------------------------------------------------------------
MINIMAL_PARAMETERS = {
    "pd": ["kp=100", "q_ref=0.3,-1.2,1.4,-0.6,1.2,0.5"],
    "gravity_compensation": [],
    "pd_gravity": ["kp=100", "q_ref=0.3,-1.2,1.4,-0.6,1.2,0.5"],
    "computed_torque": ["waypoint=0,-1.2,1.4,-0.6,1.2,0.5", "waypoint=0.5,-1,1,-0.3,1,0.8"],
    "potential_field": ["goal=0.4,0.3,0.5", "frame=tool0", "obstacle=0.5,0.2,0.4,0.05"],
}


def test_every_registered_controller_is_exercised_here():
    assert sorted(ms.CONTROLLERS) == sorted(MINIMAL_PARAMETERS) == CONTROLLER_NAMES.split(", ")


@pytest.mark.parametrize("name", sorted(ms.CONTROLLERS))
def test_registry_builds_each_controller_and_matches_its_keywords(robot, name):
    ur5 = robot("ur5")
    controller = ms.make_controller(name, ur5, MINIMAL_PARAMETERS[name])
    tau = controller(0.0, UR5_POSE, np.zeros(6))
    assert tau.shape == (6,) and np.all(np.isfinite(tau))
    controller.reset()
    spec = ms.CONTROLLERS[name]
    factory = {"computed_torque": ms.ComputedTorque, "potential_field": ms.PotentialField}.get(name, spec.factory)
    keywords = set(inspect.signature(factory).parameters) - {"self", "robot"}
    renamed = {"waypoint": "waypoints", "obstacle": "obstacles"}  # one occurrence per row on the command line
    assert {renamed.get(p.name, p.name) for p in spec.parameters} == keywords


def test_registry_values_reach_the_controller(robot):
    ur5 = robot("ur5")
    pd = ms.make_controller("pd", ur5, ["kp=1,2,3,4,5,6", "kd=0.5", "q_ref=0.3,-1.2,1.4,-0.6,1.2,0.5"])
    np.testing.assert_array_equal(pd.kp, [1, 2, 3, 4, 5, 6])
    np.testing.assert_array_equal(pd.kd, [0.5] * 6)
    puck = robot("point_robot")
    field = ms.make_controller(
        "potential_field", puck, ["goal=2,0", "obstacle=0,0,0.5", "obstacle=1, 1, 0.25", "escape=false", "seed=3"]
    )
    np.testing.assert_array_equal(field.obstacle_centers, [[0, 0], [1, 1]])
    np.testing.assert_array_equal(field.obstacle_radii, [0.5, 0.25])
    assert field.escape is False and field.seed == 3


def test_cli_runs_pd_gravity_on_ur5(capsys, tmp_path: Path):
    out = tmp_path / "pd.npz"
    argv = ["run", "ur5", "--controller", "pd_gravity", "--param", "kp=400,400,200,40,40,10"]
    argv += ["--param", "q_ref=0.3,-1.2,1.4,-0.6,1.2,0.5", "--q0", "0.2", "-1.1", "1.3", "-0.5", "1.1", "0.4"]
    argv += ["--duration", "3", "--output-dt", "0.1", "--out", str(out)]
    assert main(argv) == 0
    lines = capsys.readouterr().out.splitlines()
    assert (
        lines[0] == "run: ur5 (fixed base, nq 6, nv 6), integrator rk4, dt 0.001 s, duration 3 s, controller pd_gravity"
    )
    traj = ms.Trajectory.load(out)
    np.testing.assert_allclose(traj.q[-1], UR5_POSE, atol=1e-7)
    assert traj.metadata["controller"] == "PDGravity"


def test_cli_prints_what_the_controller_saw(capsys):
    argv = [
        "run",
        "point_robot",
        "--controller",
        "potential_field",
        "--param",
        "goal=2,0",
        "--param",
        "obstacle=0,0,0.5",
    ]
    argv += ["--q0", "-2", "0", "--duration", "12", "--dt", "0.005", "--output-dt", "1"]
    assert main(argv) == 0
    last = capsys.readouterr().out.splitlines()[-1]
    assert re.fullmatch(
        r"potential field: reached the goal \(distance [0-9.e-]+\); 1 local minimum detected \(t = 3\.3\d* s\), "
        r"escaped by random pushes",
        last,
    ), last


BAD_CONTROLLER_INPUT = [
    (
        ["--controller", "pdgrav"],
        f"unknown controller 'pdgrav' (did you mean pd_gravity? valid: {CONTROLLER_NAMES})",
    ),
    (
        ["--controller", "pd_gravity", "--param", "kpp=1"],
        f"controller 'pd_gravity' has no parameter 'kpp' (did you mean kp? parameters: {PD_PARAMETERS})",
    ),
    (
        ["--controller", "pd_gravity", "--param", "kp=1"],
        f"controller 'pd_gravity' needs q_ref=... (parameters: {PD_PARAMETERS})",
    ),
    (
        ["--controller", "pd_gravity", "--param", "kp", "--param", "q_ref=0,0,0,0,0,0"],
        f"controller parameter 'kp' is not KEY=VALUE (parameters of pd_gravity: {PD_PARAMETERS})",
    ),
    (
        ["--controller", "pd", "--param", "kp=abc", "--param", "q_ref=0,0,0,0,0,0"],
        "controller 'pd': parameter kp: 'abc' is not a number (vectors are comma-separated, e.g. kp=1,2.5,-3)",
    ),
    (
        ["--controller", "pd", "--param", "kp=1", "--param", "q_ref=0 0 0 0 0 0"],
        "controller 'pd': parameter q_ref: '0 0 0 0 0 0' is not a number (vectors are comma-separated, "
        "e.g. q_ref=1,2.5,-3)",
    ),
    (
        ["--controller", "pd_gravity", "--param", "kp=1,2", "--param", "q_ref=0,0,0,0,0,0"],
        "controller 'pd_gravity': kp must be a number or have shape (6,), got (2,)",
    ),
    (
        ["--controller", "pd_gravity", "--param", "kp=-1", "--param", "q_ref=0,0,0,0,0,0"],
        "controller 'pd_gravity': kp must be >= 0, got -1.0",
    ),
    (
        ["--controller", "pd_gravity", "--param", "kp=1", "--param", "q_ref=0,0,0,0,0"],
        "controller 'pd_gravity': q_ref must have shape (6,), got (5,)",
    ),
    (
        ["--controller", "pd_gravity", "--param", "kp=1", "--param", "kp=2", "--param", "q_ref=0,0,0,0,0,0"],
        "controller 'pd_gravity': parameter kp given 2 times (give it once)",
    ),
    (
        ["--param", "kp=1"],
        f"--param needs --controller NAME (valid: {CONTROLLER_NAMES})",
    ),
    (
        ["--controller", "computed_torque", "--param", "waypoint=0,0,0,0,0,0"],
        "controller 'computed_torque': needs at least 2 waypoints (repeat waypoint=...), got 1",
    ),
    (
        ["--controller", "computed_torque", "--param", "waypoint=0,0,0,0,0,0", "--param", "waypoint=1,1,1,1,1"],
        "controller 'computed_torque': waypoint 1 must have nq = 6 numbers, got 5",
    ),
    (
        ["--controller", "potential_field", "--param", "goal=0.4,0.3,0.5"],
        "controller 'potential_field': goal must have shape (6,) (a configuration: pass frame=... for a point in "
        "space), got (3,)",
    ),
    (
        ["--controller", "potential_field", "--param", "goal=0.4,0.3,0.5", "--param", "escape=maybe"],
        "controller 'potential_field': parameter escape: 'maybe' is not true or false",
    ),
]


@pytest.mark.parametrize(("extra", "message"), BAD_CONTROLLER_INPUT)
def test_cli_bad_controller_input_is_one_exact_line_and_exit_2(capsys, extra, message):
    assert main(["run", "ur5", "--duration", "0.01", *extra]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err == f"multibody-sim: error: {message}\n"


def test_potential_field_without_a_frame_needs_plain_coordinates(robot):
    arm = robot("double_pendulum_continuous")
    message = (
        "a potential field without a frame acts on q itself, which must be a plain vector (revolute and prismatic "
        "joints only); robot 'double_pendulum_continuous' has nq = 4, nv = 2: pass frame=... for a task-space field"
    )
    with pytest.raises(ms.InvalidArgumentError, match=exact(message)):
        ms.PotentialField(arm, [0.0, 0.0, 0.0, 0.0])
    puck = robot("point_robot")
    with pytest.raises(
        ms.InvalidArgumentError, match=exact("goal [0.0, 0.0] is inside obstacle 0 (distance <= radius)")
    ):
        ms.PotentialField(puck, [0.0, 0.0], obstacles=[((0.1, 0.0), 0.5)])
    message = (
        "the potential field needs every velocity coordinate actuated, but robot 'solo12' has a floating base whose 6 "
        "are not (load it with floating_base=False to weld the base)"
    )
    with pytest.raises(ms.InvalidArgumentError, match=exact(message)):
        ms.PotentialField(robot("solo12"), [0.0, 0.0, 0.0], frame="base_link")


def test_cli_unknown_frame_lists_close_matches(capsys):
    argv = ["run", "ur5", "--controller", "potential_field", "--param", "goal=0.4,0.3,0.5", "--param", "frame=tool1"]
    assert main(argv) == 2
    err = capsys.readouterr().err
    assert err == (
        "multibody-sim: error: controller 'potential_field': robot 'ur5' has no frame 'tool1' (did you mean 'tool0'?)\n"
    )
