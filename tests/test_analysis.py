"""Analysis helpers on a trajectory: frame placements and velocities, centre of mass, centroidal momentum, against
forward kinematics by hand, finite differences, per-link sums and conservation laws."""

from __future__ import annotations

import re
from collections.abc import Callable
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pinocchio as pin
import pytest
from conftest import joint, link, urdf

import multibody_sim as ms
from multibody_sim import analysis

# The two-link arm below: links of 1 kg and 0.5 kg (centres 0.5 m and 0.4 m down their links), elbow 1 m below
# the shoulder, and a 0.2 kg tip welded 0.8 m down the lower link; both hinges turn about y.
MASSES = {"upper": 1.0, "lower": 0.5, "tip": 0.2}


def two_link_text() -> str:
    return urdf(
        '<link name="base"/>',
        link("upper", mass=MASSES["upper"], com="0 0 -0.5"),
        link("lower", mass=MASSES["lower"], com="0 0 -0.4"),
        link("tip", mass=MASSES["tip"], com="0 0 0"),
        joint("shoulder", "base", "upper"),
        joint("elbow", "upper", "lower", xyz="0 0 -1"),
        joint("tool", "lower", "tip", kind="fixed", xyz="0 0 -0.8"),
        name="two_link",
    )


@pytest.fixture
def two_link(write_urdf: Callable[..., Path]) -> ms.Robot:
    return ms.load_robot(write_urdf(two_link_text()))


def rot_y(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, 0.0, s], [0.0, 1.0, 0.0], [-s, 0.0, c]])


def down(length: float) -> np.ndarray:
    return np.array([0.0, 0.0, -length])


def states(robot: ms.Robot, n: int, seed: int, speed: float = 1.0) -> SimpleNamespace:
    """A trajectory-like object: n random configurations and velocities."""
    rng = np.random.default_rng(seed)
    return SimpleNamespace(
        q=np.array([robot.random_configuration(rng) for _ in range(n)]), v=speed * rng.normal(size=(n, robot.nv))
    )


def zero_gravity(robot: ms.Robot) -> ms.Robot:
    """A copy of the robot in zero gravity (the cached one stays as it is)."""
    model = pin.Model(robot.model)
    model.gravity = pin.Motion.Zero()
    return ms.Robot(model, name=robot.name, floating_base=robot.floating_base)


# ---- placements ---------------------------------------------------------------------------------------------
def test_placements_are_forward_kinematics_by_hand(two_link):
    traj = states(two_link, 20, seed=0)
    for frame in ("upper", "lower", "tip"):
        placements = analysis.frame_placements(two_link, traj, frame)
        assert placements.shape == (20, 4, 4)
        for (a1, a2), M in zip(traj.q, placements, strict=True):
            elbow = rot_y(a1) @ down(1.0)
            expected = {
                "upper": (rot_y(a1), np.zeros(3)),
                "lower": (rot_y(a1 + a2), elbow),
                "tip": (rot_y(a1 + a2), elbow + rot_y(a1 + a2) @ down(0.8)),
            }[frame]
            np.testing.assert_allclose(M[:3, :3], expected[0], atol=1e-14)
            np.testing.assert_allclose(M[:3, 3], expected[1], atol=1e-14)
            np.testing.assert_array_equal(M[3], [0.0, 0.0, 0.0, 1.0])


def test_the_pendulums_bob_follows_its_angle_along_a_simulated_trajectory(robot):
    pendulum = robot("pendulum")
    traj = ms.simulate(pendulum, [1.0], [0.0], duration=0.5, dt=0.01)
    placements = analysis.frame_placements(pendulum, traj, "bob")
    for angle, M in zip(traj.q[:, 0], placements, strict=True):
        np.testing.assert_allclose(M[:3, :3], rot_y(angle), atol=1e-14)
        np.testing.assert_allclose(M[:3, :3] @ down(1.0), [-np.sin(angle), 0.0, -np.cos(angle)], atol=1e-14)


# ---- velocities: finite differences of the placements along q ⊕ εv ---------------------------------------------
@pytest.mark.parametrize(("name", "frame"), [("ur5", "tool0"), ("solo12", "FL_FOOT"), ("free_body", "box")])
def test_frame_velocities_are_the_time_derivative_of_the_placements(robot, name, frame):
    # Moving along v for a time ε takes q to q ⊕ εv (a floating base included): the linear part must be dp/dt
    # of the frame's origin and the angular part ω with Ṙ = [ω]× R, both in world axes (LOCAL_WORLD_ALIGNED).
    system = robot(name)
    traj = states(system, 5, seed=1, speed=2.0)
    velocities = analysis.frame_velocities(system, traj, frame)
    eps = 1e-5
    for q, v, twist in zip(traj.q, traj.v, velocities, strict=True):
        ahead = analysis.frame_placements(system, SimpleNamespace(q=system.integrate(q, eps * v)), frame)
        behind = analysis.frame_placements(system, SimpleNamespace(q=system.integrate(q, -eps * v)), frame)
        linear = (ahead[:3, 3] - behind[:3, 3]) / (2 * eps)
        angular = pin.log3(ahead[:3, :3] @ behind[:3, :3].T) / (2 * eps)
        scale = 1.0 + np.abs(twist).max()
        # Central differences: O(ε²) ≈ 1e-10 relative, round-off 1e-16/ε ≈ 1e-11.
        np.testing.assert_allclose(twist[:3], linear, atol=1e-7 * scale)
        np.testing.assert_allclose(twist[3:], angular, atol=1e-7 * scale)


# ---- centre of mass -----------------------------------------------------------------------------------------
def test_the_centre_of_mass_is_the_mass_weighted_mean_of_the_links_by_hand(two_link):
    traj = states(two_link, 10, seed=2)
    com = analysis.center_of_mass(two_link, traj)
    assert com.shape == (10, 3)
    total = sum(MASSES.values())
    for (a1, a2), c in zip(traj.q, com, strict=True):
        elbow = rot_y(a1) @ down(1.0)
        centres = {
            "upper": rot_y(a1) @ down(0.5),
            "lower": elbow + rot_y(a1 + a2) @ down(0.4),
            "tip": elbow + rot_y(a1 + a2) @ down(0.8),
        }
        expected = sum(MASSES[name] * centres[name] for name in MASSES) / total
        np.testing.assert_allclose(c, expected, atol=1e-14)


def test_the_centre_of_mass_of_a_legged_robot_from_per_link_data(robot):
    # Σ m_i c_i / Σ m_i with each link's centre placed by its joint's world placement: another Pinocchio path
    # (forward kinematics and the links' inertias) than centerOfMass.
    solo = robot("solo12")
    traj = states(solo, 5, seed=3)
    com = analysis.center_of_mass(solo, traj)
    model, data = solo.model, solo.model.createData()
    for q, c in zip(traj.q, com, strict=True):
        pin.forwardKinematics(model, data, q)
        inertias = model.inertias[1:]
        weighted = sum(body.mass * data.oMi[j + 1].act(body.lever) for j, body in enumerate(inertias))
        np.testing.assert_allclose(c, weighted / sum(body.mass for body in inertias), atol=1e-14)


@pytest.mark.parametrize("name", ["ur5", "solo12"])
def test_the_centre_of_mass_velocity_is_its_time_derivative(robot, name):
    system = robot(name)
    traj = states(system, 5, seed=4, speed=2.0)
    velocity = analysis.center_of_mass_velocity(system, traj)
    eps = 1e-5
    for q, v, vcom in zip(traj.q, traj.v, velocity, strict=True):
        ahead = analysis.center_of_mass(system, SimpleNamespace(q=system.integrate(q, eps * v)))
        behind = analysis.center_of_mass(system, SimpleNamespace(q=system.integrate(q, -eps * v)))
        np.testing.assert_allclose(vcom, (ahead - behind) / (2 * eps), atol=1e-8 * (1.0 + np.abs(vcom).max()))


# ---- centroidal momentum ------------------------------------------------------------------------------------
def test_a_free_bodys_centroidal_momentum_by_hand_and_conserved(robot):
    # A spinning, drifting box in zero gravity: linear momentum m·R·v_base and angular momentum R·I·ω_base about
    # its centre (its body origin), both constant; RK4 at 1 ms keeps them to ~1e-12 over 1 s of tumbling.
    box = zero_gravity(robot("free_body"))
    rng = np.random.default_rng(5)
    v0 = np.concatenate((rng.normal(size=3), 3.0 * rng.normal(size=3)))
    traj = ms.simulate(box, box.random_configuration(rng), v0, duration=1.0, dt=1e-3)
    momentum = analysis.centroidal_momentum(box, traj)
    inertia = np.diag([0.00833333333333, 0.01666666666667, 0.02166666666667])
    for q, v, h in zip(traj.q[::100], traj.v[::100], momentum[::100], strict=True):
        R = pin.Quaternion(q[3:7]).matrix()
        np.testing.assert_allclose(h[:3], 2.0 * R @ v[:3], atol=1e-12)
        np.testing.assert_allclose(h[3:], R @ inertia @ v[3:], atol=1e-12)
    assert np.abs(momentum - momentum[0]).max() < 1e-9 * np.abs(momentum[0]).max()
    assert np.abs(traj.v[:, 3:] - traj.v[0, 3:]).max() > 0.1  # the body-frame spin changed: it tumbled


def test_joint_torques_cannot_change_a_floating_robots_momentum(robot):
    # In zero gravity, a quadruped flailing its legs under a PD controller (internal torques) keeps its
    # centroidal momentum: what the legs push, the base takes.
    solo = zero_gravity(robot("solo12"))
    rng = np.random.default_rng(6)
    q0 = solo.random_configuration(rng)
    target = solo.random_configuration(rng)[7:]
    v0 = np.concatenate((rng.normal(size=6), 3.0 * rng.normal(size=12)))

    def flail(t, q, v):
        # Gentle gains: Solo's light legs still reach ~20 rad/s, where RK4 at 1 ms is accurate to ~1e-10.
        return np.concatenate((np.zeros(6), 1e-3 * (target - q[7:]) - 1e-4 * v[6:]))

    traj = ms.simulate(solo, q0, v0, duration=0.5, dt=1e-3, controller=flail)
    momentum = analysis.centroidal_momentum(solo, traj)
    assert np.abs(traj.q[:, 7:] - q0[7:]).max() > 0.5  # the legs moved a lot
    assert np.abs(traj.work).max() > 1e-2  # and the torques did work
    assert np.abs(momentum - momentum[0]).max() < 1e-8 * np.abs(momentum[0]).max()


def test_the_linear_momentum_is_the_total_mass_times_the_centre_of_mass_velocity(robot):
    solo = robot("solo12")
    traj = states(solo, 5, seed=7, speed=2.0)
    momentum = analysis.centroidal_momentum(solo, traj)
    vcom = analysis.center_of_mass_velocity(solo, traj)
    np.testing.assert_allclose(momentum[:, :3], solo.total_mass * vcom, atol=1e-12)


# ---- shapes, names and errors -------------------------------------------------------------------------------
def test_batched_trajectories_keep_their_leading_axes(robot):
    ur5 = robot("ur5")
    batch = SimpleNamespace(
        q=np.array([states(ur5, 3, seed=s).q for s in (8, 9)]),
        v=np.array([states(ur5, 3, seed=s).v for s in (8, 9)]),
    )
    assert analysis.frame_placements(ur5, batch, "tool0").shape == (2, 3, 4, 4)
    assert analysis.centroidal_momentum(ur5, batch).shape == (2, 3, 6)
    velocities = analysis.frame_velocities(ur5, batch, "tool0")
    assert velocities.shape == (2, 3, 6)
    second = SimpleNamespace(q=batch.q[1], v=batch.v[1])
    np.testing.assert_array_equal(velocities[1], analysis.frame_velocities(ur5, second, "tool0"))
    single = SimpleNamespace(q=batch.q[0, 0])
    assert analysis.center_of_mass(ur5, single).shape == (3,)


def test_frame_names_lists_links_joints_and_fixed_frames_once(robot):
    names = analysis.frame_names(robot("ur5"))
    assert {"tool0", "wrist_3_link", "elbow_joint", "base_link"} <= set(names)
    assert len(names) == len(set(names))


def exact(message: str) -> str:
    return f"^{re.escape(message)}$"


def test_an_unknown_frame_lists_close_matches_or_the_frames(robot):
    ur5 = robot("ur5")
    traj = states(ur5, 1, seed=0)
    with pytest.raises(ms.UnknownNameError, match=exact("robot 'ur5' has no frame 'tool' (did you mean tool0?)")):
        analysis.frame_placements(ur5, traj, "tool")
    with pytest.raises(
        ms.UnknownNameError,
        match=exact(
            "robot 'ur5' has no frame 'shoulder' (did you mean shoulder_link, shoulder_pan_joint, shoulder_lift_joint?)"
        ),
    ):
        analysis.frame_velocities(ur5, traj, "shoulder")
    with pytest.raises(
        ms.UnknownNameError,
        match=exact(
            "robot 'ur5' has no frame 'xyz' (its 22 frames: universe, world, world_joint, base_link, "
            "base_link-base_fixed_joint, base, shoulder_pan_joint, shoulder_link, shoulder_lift_joint, upper_arm_link, "
            "elbow_joint, forearm_link, ...; multibody_sim.analysis.frame_names(robot) lists them)"
        ),
    ):
        analysis.frame_placements(ur5, traj, "xyz")
    assert issubclass(ms.UnknownNameError, LookupError)


def test_bad_trajectories_are_refused(robot):
    ur5 = robot("ur5")
    with pytest.raises(
        ms.InvalidArgumentError,
        match=exact("traj.q must be an array of shape (..., 6), got shape (4, 7) dtype float64"),
    ):
        analysis.center_of_mass(ur5, SimpleNamespace(q=np.zeros((4, 7))))
    with pytest.raises(
        ms.InvalidArgumentError,
        match=exact("traj must be a Trajectory (or have a 'v' array), got SimpleNamespace without 'v'"),
    ):
        analysis.centroidal_momentum(ur5, SimpleNamespace(q=np.zeros((4, 6))))
    with pytest.raises(
        ms.InvalidArgumentError,
        match=exact("traj.v must have one row per row of traj.q: shapes (4, 6) and (3, 6)"),
    ):
        analysis.frame_velocities(ur5, SimpleNamespace(q=np.zeros((4, 6)), v=np.zeros((3, 6))), "tool0")
    bad = np.zeros((2, 6))
    bad[1, 2] = np.nan
    with pytest.raises(ms.InvalidArgumentError, match=exact("traj.q must be finite, got non-finite entries in row 1")):
        analysis.frame_placements(ur5, SimpleNamespace(q=bad), "tool0")
    solo = robot("solo12")
    with pytest.raises(
        ms.InvalidArgumentError,
        match=exact("traj.q[0] is not a valid configuration: its quaternion / (cos, sin) entries must have unit norm"),
    ):
        analysis.center_of_mass(solo, SimpleNamespace(q=np.zeros((1, 19))))
    with pytest.raises(ms.InvalidArgumentError, match=exact("frame must be a frame name (a string), got int")):
        analysis.frame_placements(ur5, SimpleNamespace(q=np.zeros((1, 6))), 3)
