"""Actuators declared in scenes (scenes/actuators.py): tables, the torque laws and limits, reflected rotor inertia, the
implicit servo terms, the ledger, the commands kept as traj.ctrl, and the catalog's published motor data.

Oracles: closed forms of a servo on a free rotor (the pendulum without gravity: I q'' = kp (u - q) - kv q'), the
terminal speed of a motor on its torque–speed curve, M(q) of the plain model plus the reflected inertia (CRBA), and
the ledger's closure (energy_error) converging with dt or exact by construction (the time-stepper).
"""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np
import pytest
from conftest import assert_same_run, assert_same_stepper, both, needs_native, shipped

import multibody_sim as ms
from multibody_sim.exceptions import SceneError
from multibody_sim.integrators import INTEGRATORS
from multibody_sim.scenes import make_scene
from multibody_sim.torques import command_bounds

I_ROTOR = 1.0 + 0.001  # the pendulum's inertia about its hinge: the 1 kg bob 1 m out plus its own [kg·m²]


def rotor(**actuator: object) -> ms.Scene:
    """The shipped pendulum without gravity (a free rotor of inertia I_ROTOR) with one actuator on its hinge (no
    effort or velocity limit unless given: the URDF's are 20 N·m and 20 rad/s)."""
    table = {"joints": "hinge", "effort_limit": 1e9, "velocity_limit": 1e9, **actuator}
    return make_scene(robot={"source": "pendulum"}, gravity=[0, 0, 0], actuator=[table])


def hold(u: float):  # noqa: ANN202 - a controller
    return lambda t, q, v: np.array([u])


# ---- tables ----------------------------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "tables, message",
    [
        ({"actuator": [{"kind": "torque"}]}, "actuator[0].joints: missing"),
        (
            {"actuator": [{"joints": "*", "kind": "servo"}]},
            "actuator[0].kind: must be one of position, torque, velocity",
        ),
        (
            {"actuator": [{"joints": "*", "kind": "torque", "kp": 1.0}]},
            "actuator[0].kp: only for kind position, not torque",
        ),
        (
            {"actuator": [{"joints": "*", "kind": "velocity", "kp": 1.0}]},
            "actuator[0].kp: only for kind position, not velocity",
        ),
        ({"actuator": [{"joints": "*", "gear": 0.0}]}, "actuator[0].gear: must be > 0"),
        ({"actuator": [{"joints": "*", "kp": -1.0}]}, "actuator[0].kp: must be >= 0"),
        (
            {"actuator": [{"joints": "*", "rotr_inertia": 1.0}]},
            "actuator[0]: unknown key 'rotr_inertia' (did you mean 'rotor_inertia'?",
        ),
        ({"actuator": [{"joints": []}]}, "actuator[0].joints: must not be empty"),
        (
            {"actuator": [{"joints": "*", "overspeed": "stop"}]},
            "actuator[0].overspeed: must be one of brake, none, got 'stop'",
        ),
        (
            {"actuator": [{"joints": "*", "overspeed_band": 2.0}]},
            "actuator[0].overspeed_band: must be <= 1 (a fraction of the velocity limit), got 2",
        ),
        ({"actuator": [{"joints": "*", "overspeed_band": 0.0}]}, "actuator[0].overspeed_band: must be > 0"),
        ({"actuators": "published"}, "actuators: must be one of catalog, got 'published'"),
    ],
)
def test_table_mistakes_are_one_line(tables: dict, message: str) -> None:
    with pytest.raises(SceneError) as info:
        make_scene(robot={"source": "pendulum"}, **tables)
    text = str(info.value)
    assert "\n" not in text and text.startswith(f"<scene>: {message}"), text


@pytest.mark.parametrize(
    "tables, message",
    [
        ({"actuator": [{"joints": "knee"}]}, "actuator[0].joints: 'knee' matches no actuated joint (valid: hinge)"),
        (
            {"actuator": [{"joints": "hinge", "kind": "position"}]},
            "actuator[0]: joint 'hinge': a position servo needs kp",
        ),
        (
            {"actuator": [{"joints": "hinge", "kind": "velocity"}]},
            "actuator[0]: joint 'hinge': a velocity servo needs kv > 0",
        ),
        (
            {"actuator": [{"joints": "hinge", "stall_torque": 3.0}]},
            "actuator[0].no_load_speed: missing (the torque–speed curve needs stall_torque and no_load_speed)",
        ),
        (
            {"actuator": [{"joints": "hinge", "kind": "torque"}, {"joints": "hinge", "kp": 1.0}]},
            "actuator[1]: joint 'hinge': kp is only for kind position, and its kind is torque",
        ),
        ({"actuators": "catalog"}, "actuators: the catalog has no published motor data for 'pendulum' (it has: go2)"),
    ],
)
def test_mistakes_found_on_the_model(tables: dict, message: str) -> None:
    with pytest.raises(SceneError, match=f"^{re.escape('<scene>: ' + message)}"):
        make_scene(robot={"source": "pendulum"}, **tables)


def test_a_brake_needs_both_limits() -> None:
    """spring_chain's sliders have no effort or velocity limit: no brake by default, and asking for one says why."""
    scene = make_scene(robot={"source": "spring_chain"}, actuator=[{"joints": "*", "velocity_limit": 1.0}])
    assert {a.overspeed for a in scene.actuators.items} == {"none"}
    message = "actuator[0]: joint 'slider1': overspeed = \"brake\" needs an effort and a velocity limit (declare"
    with pytest.raises(SceneError, match=f"^{re.escape('<scene>: ' + message)}"):
        make_scene(robot={"source": "spring_chain"}, actuator=[{"joints": "*", "overspeed": "brake"}])


def test_a_locked_joint_takes_no_actuator() -> None:
    with pytest.raises(SceneError, match=re.escape("actuator[0].joints: 'panda_finger_joint1' is locked")):
        make_scene(
            robot={"source": "panda"},
            lock={"panda_finger_joint1": 0.0, "panda_finger_joint2": 0.0},
            actuator=[{"joints": "panda_finger_joint1"}],
        )


def test_later_tables_override_key_by_key() -> None:
    """The catalog's motor data, then a servo over it: the gains and kind from the scene, gear and limits kept."""
    scene = make_scene(
        robot={"source": "go2"},
        actuators="catalog",
        actuator=[
            {"joints": "*", "kind": "position", "kp": 20.0, "kv": 0.5},
            {"joints": "FL_*", "kv": 1.0},
        ],
    )
    by_joint = {a.joint: a for a in scene.actuators.items}
    assert len(by_joint) == 12
    fl, fr = by_joint["FL_calf_joint"], by_joint["FR_calf_joint"]
    assert (fl.kind, fl.kp, fl.kv) == ("position", 20.0, 1.0)
    assert (fr.kind, fr.kp, fr.kv) == ("position", 20.0, 0.5)
    assert (fl.gear, fl.effort_limit, fl.velocity_limit) == (12.134, 45.43, 15.70)
    assert fl.sources == ("catalog go2: actuator[1]", "actuator[0]", "actuator[1]")


def test_go2_catalog_reflects_its_rotors() -> None:
    """Armature = gear² × rotor inertia (Unitree's 6.33:1 and the URDF rotors' 1.11842e-4 kg·m²) on every leg joint,
    seen in M(q) against the plain model's (CRBA), and the URDF's limits as the actuators' defaults."""
    plain = make_scene(robot={"source": "go2"})
    scene = make_scene(robot={"source": "go2"}, actuators="catalog")
    q = scene.q0
    added = np.diag(scene.mass_matrix(q) - plain.mass_matrix(q))
    hip = 6.33**2 * 1.11842e-4
    calf = 12.134**2 * 1.11842e-4
    expected = np.array([0.0] * 6 + [hip, hip, calf] * 4)
    np.testing.assert_allclose(added, expected, rtol=1e-12, atol=1e-15)
    off_diagonal = scene.mass_matrix(q) - plain.mass_matrix(q) - np.diag(added)
    assert np.abs(off_diagonal).max() < 1e-15
    np.testing.assert_array_equal(scene.effort_limit[6:], [23.7, 23.7, 45.43] * 4)
    assert "actuator FL_calf_joint: torque, gear 12.134, armature 0.01647, effort 45.43" in scene.describe()


# ---- the torque laws ---------------------------------------------------------------------------------------------
def torque(scene: ms.Scene, q: float, v: float, u: float) -> float:
    return float(scene.actuators.joint_torques(np.array([q]), np.array([v]), np.array([u]))[0])


def test_laws_and_limits_by_hand() -> None:
    position = rotor(kind="position", kp=100.0, kv=2.0, effort_limit=8.0, velocity_limit=50.0)
    assert torque(position, 0.2, 1.5, 0.3) == pytest.approx(100 * 0.1 - 2 * 1.5)  # 7, within 8
    assert torque(position, 0.2, 1.5, 0.5) == 8.0  # 27 clipped at the effort limit
    assert torque(position, 0.2, 1.5, -0.5) == -8.0
    velocity = rotor(kind="velocity", kv=3.0, velocity_limit=20.0)
    assert torque(velocity, 0.0, 1.0, 2.0) == pytest.approx(3.0)
    # the curve: 10 N·m at rest falling to 0 at 20 rad/s while the torque drives the motion; braking: the effort limit
    motor = rotor(kind="torque", effort_limit=8.0, stall_torque=10.0, no_load_speed=20.0, velocity_limit=15.0)
    assert torque(motor, 0.0, 0.0, 9.0) == 8.0  # at rest: min(effort 8, stall 10)
    assert torque(motor, 0.0, 10.0, 9.0) == pytest.approx(5.0)  # 10 (1 - 10/20)
    assert torque(motor, 0.0, -10.0, -9.0) == pytest.approx(-5.0)
    assert torque(motor, 0.0, -10.0, 9.0) == 8.0  # braking: the effort limit only
    assert torque(motor, 0.0, 15.0, 9.0) == 0.0  # at the velocity limit: no driving torque
    assert torque(motor, 0.0, 16.0, -9.0) == -8.0  # beyond it: braking passes
    bounds = command_bounds(position)
    assert (bounds[0][0], bounds[1][0]) == (-3.14159265, 3.14159265)  # a position servo's target: the joint's range
    assert [b[0] for b in command_bounds(velocity)] == [-20.0, 20.0]  # a velocity servo's: ± its velocity limit


def test_a_plain_torque_actuator_steps_as_todays_torques_bit_for_bit() -> None:
    """kind torque, gear 1, no rotor, no limits: the command is the torque, exactly as without an actuator."""
    plain = make_scene(robot={"source": "ur5"})
    scene = make_scene(robot={"source": "ur5"}, actuator=[{"joints": "*", "effort_limit": 1e9, "velocity_limit": 1e9}])
    rng = np.random.default_rng(3)
    taus = rng.uniform(-20, 20, size=(1, 50, 6))
    for system in (plain, scene):
        system._run = ms.rollout(  # type: ignore[attr-defined]
            system, plain.q0[None], np.zeros((1, 6)), duration=0.05, dt=1e-3, taus=taus, progress=False
        )
    a, b = plain._run, scene._run  # type: ignore[attr-defined]
    np.testing.assert_array_equal(a.q, b.q)
    np.testing.assert_array_equal(a.v, b.v)
    np.testing.assert_array_equal(a.tau, b.tau)
    np.testing.assert_array_equal(b.ctrl, a.tau)


# ---- dynamics against closed forms -------------------------------------------------------------------------------
def servo_solution(t: np.ndarray, kp: float, kv: float, u: float) -> np.ndarray:
    """q(t) of I q'' = kp (u - q) - kv q' from rest at 0 (underdamped)."""
    wn = math.sqrt(kp / I_ROTOR)
    zeta = kv / (2 * math.sqrt(kp * I_ROTOR))
    wd = wn * math.sqrt(1 - zeta**2)
    return u * (1 - np.exp(-zeta * wn * t) * (np.cos(wd * t) + zeta * wn / wd * np.sin(wd * t)))


def test_position_servo_follows_the_damped_oscillator_at_fourth_order() -> None:
    scene = rotor(kind="position", kp=400.0, kv=4.0)
    errors = []
    for dt in (4e-3, 2e-3, 1e-3):
        traj = scene.run(duration=1.0, dt=dt, integrator="rk4", controller=hold(0.3), q0=[0.0], v0=[0.0])
        errors.append(np.abs(traj.q[:, 0] - servo_solution(traj.t, 400.0, 4.0, 0.3)).max())
    slopes = np.diff(np.log2(errors))
    assert (slopes < -3.7).all(), errors


def test_semi_implicit_euler_takes_a_stiff_servo_at_any_step() -> None:
    """h ω = 10 and h kv / I = 10: the explicit step's bounds (h ω < 2, h kv / I < 2) are far exceeded; with the
    servo terms inside the step it settles at the target as the exact solution does, and converges at first
    order."""
    kp, kv = 1e4, 100.0
    scene = rotor(kind="position", kp=kp, kv=kv)
    h = 10 / math.sqrt(kp / I_ROTOR)
    traj = scene.run(duration=2.0, dt=h, integrator="semi_implicit_euler", controller=hold(0.3), q0=[0.0], v0=[0.0])
    assert traj.status == "completed"
    assert abs(traj.q[-1, 0] - 0.3) < 1e-9
    errors = []
    for dt in (2e-3, 1e-3, 5e-4):
        traj = scene.run(
            duration=0.2, dt=dt, integrator="semi_implicit_euler", controller=hold(0.3), q0=[0.0], v0=[0.0]
        )
        errors.append(np.abs(traj.q[:, 0] - servo_solution(traj.t, kp, kv, 0.3)).max())
    slopes = np.diff(np.log2(errors))
    assert (np.abs(slopes + 1) < 0.15).all(), errors


def test_the_same_stiff_gains_as_a_held_controller_need_a_small_step() -> None:
    """The contrast the servo exists for: kp 1e4 and kv 100 as a PD held over each 100 ms step (on a torque actuator
    limited at 1e9 N·m) oscillate with growing amplitude until that limit holds them, 1e6 rad out."""
    scene = rotor(kind="torque")
    pd = ms.make_controller("pd", scene, ["kp=1e4", "kd=100", "q_ref=0.3"])
    h = 10 / math.sqrt(1e4 / I_ROTOR)
    traj = scene.run(duration=2.0, dt=h, integrator="semi_implicit_euler", controller=pd, q0=[0.0], v0=[0.0])
    assert np.abs(traj.q[-5:, 0] - 0.3).min() > 1e6


def test_a_clipped_servo_stays_stable_at_large_steps() -> None:
    """A stiff servo far from its target saturates; the step frees or clips it where its law lands (revise), so a
    100 ms step still settles on the target (ur5's six joints, effort limits 150 and 28 N·m)."""
    scene = make_scene(robot={"source": "ur5"}, actuator=[{"joints": "*", "kind": "position", "kp": 1e4, "kv": 100.0}])
    target = scene.q0 + 0.3
    for dt in (0.01, 0.1):
        traj = scene.run(duration=2.0, dt=dt, integrator="semi_implicit_euler", controller=lambda t, q, v: target)
        assert traj.status == "completed"
        np.testing.assert_allclose(traj.q[-1], target, atol=0.02)  # gravity's droop: torque / kp ≈ 6 mrad


def test_motor_reaches_the_no_load_speed_of_its_curve() -> None:
    """Full command on a free rotor: I v' = stall (1 - v / w0), v(t) = w0 (1 - exp(-stall t / (I w0)))."""
    stall, w0 = 5.0, 4.0
    scene = rotor(kind="torque", stall_torque=stall, no_load_speed=w0, effort_limit=100.0, velocity_limit=100.0)
    traj = scene.run(duration=3.0, dt=1e-3, integrator="rk4", controller=hold(50.0), q0=[0.0], v0=[0.0])
    exact = w0 * (1 - np.exp(-stall * traj.t / (I_ROTOR * w0)))
    np.testing.assert_allclose(traj.v[:, 0], exact, atol=1e-9)
    np.testing.assert_allclose(traj.tau[:, 0], stall * (1 - traj.v[:, 0] / w0), atol=1e-12)  # delivered, not 50
    np.testing.assert_array_equal(traj.ctrl[:, 0], 50.0)


def test_no_driving_torque_past_the_velocity_limit() -> None:
    """Full torque on a free rotor without the brake: it stops accelerating at the velocity limit (one step past it at
    most). With the brake (the default) the drive ramps down to the limit instead: test_semi_implicit_brake_..."""
    scene = rotor(kind="torque", effort_limit=10.0, velocity_limit=3.0, overspeed="none")
    dt = 1e-3
    traj = scene.run(duration=1.0, dt=dt, integrator="semi_implicit_euler", controller=hold(10.0), q0=[0.0], v0=[0.0])
    assert 3.0 <= traj.v[-1, 0] <= 3.0 + dt * 10.0 / I_ROTOR
    assert traj.v[:, 0].max() <= 3.0 + dt * 10.0 / I_ROTOR


# ---- the overspeed brake -----------------------------------------------------------------------------------------
EFFORT, V_MAX, BAND = 10.0, 3.0, 0.1
K_BRAKE = EFFORT / (BAND * V_MAX)  # the brake's gain [N·m·s/rad]: full effort 10 % past the limit


def spun(load: float = 4.0, **actuator: object) -> ms.Scene:
    """The free rotor with a torque actuator (effort 10 N·m, velocity limit 3 rad/s) and a constant external torque
    `load` [N·m] about its hinge (a [[force]] on the bob)."""
    table = {"joints": "hinge", "kind": "torque", "effort_limit": EFFORT, "velocity_limit": V_MAX, **actuator}
    force = [{"name": "load", "frame": "bob", "torque": [0.0, load, 0.0]}]
    return make_scene(robot={"source": "pendulum"}, gravity=[0, 0, 0], actuator=[table], force=force)


def test_overspeed_brake_by_hand() -> None:
    """The brake is a velocity servo toward ± the limit bounding the available torque, within ± the effort limit."""
    scene = spun()
    assert scene.actuators.items[0].brake_gain == pytest.approx(K_BRAKE)
    assert torque(scene, 0.0, 2.9, 5.0) == pytest.approx(K_BRAKE * 0.1)  # below the limit: the drive ramps down
    assert torque(scene, 0.0, 2.0, 5.0) == 5.0  # far below: the command
    assert torque(scene, 0.0, 3.06, 5.0) == pytest.approx(-K_BRAKE * 0.06)  # past it: braking whatever the command
    assert torque(scene, 0.0, 3.06, -1.0) == pytest.approx(-K_BRAKE * 0.06)  # a weaker braking command: the brake's
    assert torque(scene, 0.0, 3.06, -8.0) == -8.0  # a stronger one passes
    assert torque(scene, 0.0, 3.5, 5.0) == -EFFORT  # beyond the band: the effort limit
    assert torque(scene, 0.0, -3.06, -5.0) == pytest.approx(K_BRAKE * 0.06)  # the same on the other side
    assert torque(scene, 0.0, -3.0 * V_MAX, 10.0) == EFFORT  # braking is never cut
    off = spun(overspeed="none")
    assert torque(off, 0.0, 3.06, 5.0) == 0.0 and torque(off, 0.0, 2.9, 5.0) == 5.0  # no drive past it, no brake
    assert [name for name, _ in off.actuators.ledger] == ["actuator:hinge", "actuator_limit:hinge"]
    assert scene.actuators.ledger[-1] == ("actuator_overspeed:hinge", "dissipated")


def overspeed_solution(t: np.ndarray, load: float) -> np.ndarray:
    """v(t) of the rotor from rest under the load, command 0: I v' = load up to the limit (at t1), then
    I v' = load − k (v − v_max) (within the band): v → v_max + load / k."""
    t1 = V_MAX * I_ROTOR / load
    steady = V_MAX + load / K_BRAKE
    after = steady + (V_MAX - steady) * np.exp(-K_BRAKE * (t - t1) / I_ROTOR)
    return np.where(t < t1, load * t / I_ROTOR, after)


def test_a_load_past_the_limit_settles_where_the_brake_holds_it() -> None:
    """A load below the effort limit spins the rotor past its limit: the brake holds it at v_max + load / k (closed
    form, both phases), on RK4 and at the fixed point of semi-implicit Euler; the brake's line books the work it
    takes out, ∫ k (v − v_max) v dt of the closed form (quadrature), and the ledger closes."""
    from scipy.integrate import quad

    load = V_MAX * I_ROTOR / 0.75  # the limit reached at t = 0.75 s, on the step grid (RK4 keeps its order)
    scene = spun(load)
    u = hold(0.0)
    traj = scene.run(duration=3.0, dt=1e-3, integrator="rk4", controller=u, q0=[0.0], v0=[0.0])
    np.testing.assert_allclose(traj.v[:, 0], overspeed_solution(traj.t, load), rtol=0, atol=1e-9)
    t1 = V_MAX * I_ROTOR / load
    taken, _ = quad(lambda t: K_BRAKE * (overspeed_solution(t, load) - V_MAX) * overspeed_solution(t, load), t1, 3.0)
    assert traj.ledger["actuator_overspeed:hinge"].energy[-1] == pytest.approx(taken, rel=1e-6)
    np.testing.assert_allclose(-traj.tau[:, 0], np.maximum(0.0, K_BRAKE * (traj.v[:, 0] - V_MAX)), atol=1e-12)
    assert abs(traj.energy_error[-1]) < 1e-8 * taken
    assert np.abs(traj.ledger["actuator_limit:hinge"].energy).max() == 0.0  # the command (0) was never cut
    for dt in (1e-3, 0.05):  # h k / I = 1.7 and 83: the brake inside the step
        traj = scene.run(duration=3.0, dt=dt, integrator="semi_implicit_euler", controller=u, q0=[0.0], v0=[0.0])
        np.testing.assert_allclose(traj.v[-20:, 0], V_MAX + load / K_BRAKE, rtol=0, atol=1e-10)


def test_a_joint_far_past_its_limit_is_braked_at_the_effort_limit() -> None:
    """Started far past its limit (an impact's aftermath), no load: the brake decelerates at the effort limit to
    the band's edge (1 + band) v_max, then decays to the limit with time constant I / k (closed form)."""
    scene = spun(0.0)
    edge = (1 + BAND) * V_MAX
    t_edge = 0.5  # on the step grid (RK4 keeps its order)
    v0 = edge + t_edge * EFFORT / I_ROTOR  # 2.77 times the limit
    traj = scene.run(duration=1.0, dt=1e-3, integrator="rk4", controller=hold(5.0), q0=[0.0], v0=[v0])
    exact = np.where(
        traj.t < t_edge,
        v0 - EFFORT * traj.t / I_ROTOR,
        V_MAX + (edge - V_MAX) * np.exp(-K_BRAKE * (traj.t - t_edge) / I_ROTOR),
    )
    np.testing.assert_allclose(traj.v[:, 0], exact, rtol=0, atol=1e-8)


def test_semi_implicit_brake_against_a_drive_at_large_steps() -> None:
    """Full command (10 N·m) with no load: the drive ramps to 0 at the limit; with a narrow band (h k / I = 33)
    semi-implicit Euler and the time-stepper land on the limit without chattering, where the drive held over the step
    would overshoot."""
    scene = spun(0.0, overspeed_band=0.01)
    k = EFFORT / (0.01 * V_MAX)
    for integrator in ("semi_implicit_euler", "timestepping"):
        traj = scene.run(duration=5.0, dt=0.1, integrator=integrator, controller=hold(EFFORT), q0=[0.0], v0=[0.0])
        assert traj.status == "completed"
        np.testing.assert_allclose(traj.v[-20:, 0], V_MAX, rtol=0, atol=1e-12)
        assert traj.v[:, 0].max() <= V_MAX + 1e-12
    assert k * 0.1 / I_ROTOR > 30


def test_linearize_refuses_a_semi_implicit_brake_where_it_binds() -> None:
    scene = spun(0.0)
    with pytest.raises(ms.InvalidArgumentError, match="takes the overspeed brake of hinge implicitly at this state"):
        ms.linearize(scene, [0.0], [3.1], [0.0], dt=1e-3, integrator="semi_implicit_euler")
    ms.linearize(scene, [0.0], [1.0], [0.0], dt=1e-3, integrator="semi_implicit_euler")  # far below: no brake
    dv = scene.actuators.jacobians(np.zeros(1), np.array([3.1]), np.zeros(1))[1]
    assert dv[0, 0] == pytest.approx(-K_BRAKE)


# ---- the ledger --------------------------------------------------------------------------------------------------
def test_ledger_lines_net_to_the_delivered_work() -> None:
    """Semi-implicit Euler books h τ(q⁺, v⁺) · v⁺ per step: the actuator line minus its limit line is the sum of the
    trajectory's delivered tau · v over the samples after the first (a held command), to round-off."""
    scene = rotor(
        kind="position", kp=50.0, kv=1.0, effort_limit=3.0, stall_torque=6.0, no_load_speed=5.0, velocity_limit=4.0
    )
    dt = 1e-3
    traj = scene.run(duration=1.0, dt=dt, integrator="semi_implicit_euler", controller=hold(1.0), q0=[0.0], v0=[0.0])
    lines = traj.ledger["actuator:hinge"].energy - traj.ledger["actuator_limit:hinge"].energy
    lines -= traj.ledger["actuator_overspeed:hinge"].energy
    delivered = np.cumsum(dt * traj.tau[1:, 0] * traj.v[1:, 0])
    np.testing.assert_allclose(lines[1:], delivered, rtol=1e-10, atol=1e-12)
    assert traj.ledger["actuator_limit:hinge"].energy[-1] > 0.1  # the limits cut a driving torque here


def test_energy_error_closes_and_converges_with_limits() -> None:
    """ur5 with stiff clipped servos and curves: energy_error falls with dt (RK4) and stays a small part of the work."""
    scene = make_scene(
        robot={"source": "ur5"},
        actuator=[
            {"joints": "*", "kind": "position", "kp": 2e3, "kv": 20.0, "velocity_limit": 1e3},
            {"joints": "wrist_*", "stall_torque": 40.0, "no_load_speed": 4.0},
        ],
    )
    target = scene.q0 + 0.2
    errors = []
    for dt in (4e-4, 2e-4, 1e-4):
        traj = scene.run(duration=0.3, dt=dt, integrator="rk4", controller=lambda t, q, v: target)
        errors.append(abs(traj.energy_error[-1]))
        scale = np.abs(traj.ledger["actuator:shoulder_lift_joint"].energy).max()
    assert errors[2] < errors[0] / 4 and errors[2] < 1e-4 * scale, errors


def test_the_time_stepper_ledger_closes_with_implicit_servos() -> None:
    """go2 standing on its feet under position servos at 2 ms: every step raises the armature for the velocity update
    and the contact problem; the ledger still closes to round-off (the time-stepper's books are exact)."""
    tables = shipped("go2_standing")
    q_ref = tables.pop("controller")["q_ref"][7:]
    scene = make_scene(**tables, actuators="catalog", actuator=[{"joints": "*", "kind": "position", "kp": 60, "kv": 2}])
    u = np.zeros(scene.nv)
    u[6:] = q_ref
    traj = scene.run(duration=0.5, dt=2e-3, controller=lambda t, q, v: u)
    assert traj.status == "completed"
    assert np.abs(traj.energy_error).max() < 1e-10  # (booking only the raised-armature contact work: 0.27 J)
    assert abs(traj.q[-1, 2] - traj.q[0, 2]) < 0.05  # it stands


# ---- records and entry points ------------------------------------------------------------------------------------
def test_ctrl_is_kept_saved_and_rolled_out(tmp_path) -> None:
    scene = rotor(kind="position", kp=10.0, kv=1.0, effort_limit=2.0)
    traj = scene.run(duration=0.1, dt=1e-3, integrator="rk4", controller=hold(1.0), q0=[0.0], v0=[0.0])
    assert traj.ctrl.shape == traj.tau.shape and (traj.ctrl == 1.0).all()
    assert traj.tau[0, 0] == 2.0  # 10 rad of error × 10 clipped at 2
    loaded = ms.Trajectory.load(traj.save(tmp_path / "servo.npz"))
    np.testing.assert_array_equal(loaded.ctrl, traj.ctrl)
    np.testing.assert_array_equal(loaded.tau, traj.tau)
    taus = np.full((2, 100, 1), 1.0)
    taus[1] = 0.5
    batch = ms.rollout(scene, np.zeros((2, 1)), np.zeros((2, 1)), duration=0.1, dt=1e-3, taus=taus, progress=False)
    np.testing.assert_array_equal(batch.ctrl[:, :, 0], taus[:, :1, 0].repeat(101, axis=1))
    element = batch.element(0)
    np.testing.assert_array_equal(element.q, traj.q)
    np.testing.assert_array_equal(element.tau, traj.tau)


def test_stepper_gives_simulates_samples() -> None:
    scene = rotor(kind="velocity", kv=2.0, effort_limit=3.0)
    traj = scene.run(duration=0.05, dt=1e-3, integrator="semi_implicit_euler", controller=hold(2.0), q0=[0.0], v0=[0.0])
    stepper = ms.Stepper(scene, dt=1e-3, integrator="semi_implicit_euler", q0=[0.0], v0=[0.0])
    for _ in range(50):
        stepper.step(np.array([2.0]))
    np.testing.assert_array_equal(stepper.q, traj.q[-1])
    np.testing.assert_array_equal(stepper.v, traj.v[-1])


def test_implicit_euler_runs_on_the_actuators_derivatives() -> None:
    """Newton needs d(torque)/d(q, v): checked against central differences, then a stiff servo at a large step."""
    scene = rotor(kind="position", kp=1e4, kv=100.0, effort_limit=1e3)
    q, v, u = np.array([0.1]), np.array([0.5]), np.array([0.2])
    dq, dv, du = scene.actuators.jacobians(q, v, u)
    eps = 1e-6
    fd_q = (torque(scene, 0.1 + eps, 0.5, 0.2) - torque(scene, 0.1 - eps, 0.5, 0.2)) / (2 * eps)
    fd_v = (torque(scene, 0.1, 0.5 + eps, 0.2) - torque(scene, 0.1, 0.5 - eps, 0.2)) / (2 * eps)
    fd_u = (torque(scene, 0.1, 0.5, 0.2 + eps) - torque(scene, 0.1, 0.5, 0.2 - eps)) / (2 * eps)
    np.testing.assert_allclose([dq[0, 0], dv[0, 0], du[0, 0]], [fd_q, fd_v, fd_u], rtol=1e-6)
    traj = scene.run(duration=1.0, dt=0.05, integrator="implicit_euler", controller=hold(0.3), q0=[0.0], v0=[0.0])
    assert abs(traj.q[-1, 0] - 0.3) < 1e-3


def test_curve_derivative_where_the_curve_binds() -> None:
    scene = rotor(kind="torque", stall_torque=10.0, no_load_speed=20.0, effort_limit=8.0)
    _, dv, du = scene.actuators.jacobians(np.array([0.0]), np.array([10.0]), np.array([9.0]))
    assert dv[0, 0] == pytest.approx(-10.0 / 20.0) and du[0, 0] == 0.0


def test_gym_actions_are_the_commands() -> None:
    pytest.importorskip("gymnasium")
    from multibody_sim.gym import MultibodyEnv

    scene = make_scene(robot={"source": "ur5"}, actuator=[{"joints": "*", "kind": "position", "kp": 100.0, "kv": 5.0}])
    env = MultibodyEnv(scene, reward=lambda q, v, tau: 0.0)
    np.testing.assert_array_equal(env.action_space.low, scene.lower_limit)
    np.testing.assert_array_equal(env.action_space.high, scene.upper_limit)


def test_linearize_refuses_semi_implicit_servos_in_one_line() -> None:
    scene = rotor(kind="position", kp=10.0, kv=1.0)
    with pytest.raises(ms.InvalidArgumentError, match="takes the scene's servo terms implicitly"):
        ms.linearize(scene, [0.0], [0.0], [0.1], dt=1e-3, integrator="semi_implicit_euler")
    assert INTEGRATORS["rk4"].jacobians(scene, np.zeros(1), np.zeros(1), np.array([0.1]), 1e-3, 0.0) is not None


# ---- the native kernel: its rendering (src/native/scene.cpp, the engine's steps) bit for bit ------------------------


def go2_on_ground(**actuator: object) -> ms.Scene:
    tables = shipped("go2_standing", drop=("controller", "simulation"))
    return make_scene(**tables, actuators="catalog", actuator=[{"joints": "*", **actuator}] if actuator else [])


def native_cases() -> dict[str, tuple[ms.Scene, str, float]]:
    """(scene, integrator, dt): servos on a fixed arm (explicit and with implicit terms), the catalog's motors on a
    falling and a standing go2 (curves, limits, contact), servos on the ground, actuators with springs and friction."""
    ur5_servos = [
        {"joints": "*", "kind": "position", "kp": 1e4, "kv": 100.0},
        {"joints": "wrist_*", "kind": "velocity", "kv": 5.0},
    ]
    return {
        "ur5 servos, rk4": (make_scene(robot={"source": "ur5"}, actuator=ur5_servos), "rk4", 1e-4),
        "ur5 servos, semi-implicit, revised": (
            make_scene(robot={"source": "ur5"}, actuator=ur5_servos),
            "semi_implicit_euler",
            0.02,
        ),
        "go2 motors, free flight": (make_scene(robot={"source": "go2"}, actuators="catalog"), "rk4", 1e-3),
        "go2 motors on the ground": (go2_on_ground(), "timestepping", 1e-3),
        "go2 servos on the ground": (go2_on_ground(kind="position", kp=60.0, kv=2.0), "timestepping", 2e-3),
        "a loaded rotor on its brake, semi-implicit, revised": (
            spun(4.0, overspeed_band=0.01),
            "semi_implicit_euler",
            0.02,
        ),
        "ur5 motors with springs and friction": (
            make_scene(
                robot={"source": "ur5"},
                joints={"elbow_joint": {"stiffness": 3.0, "friction": 0.1}},
                actuator=[
                    {"joints": "*", "gear": 50.0, "rotor_inertia": 2e-5, "stall_torque": 40.0, "no_load_speed": 3.0}
                ],
            ),
            "rk4",
            1e-3,
        ),
    }


@needs_native
@pytest.mark.parametrize("case", list(native_cases()))
def test_native_kernel_renders_actuators_bit_for_bit(case: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """rollout with random commands around their bounds (new every 2 ms or step), natively and on the Python kernel:
    every sample, ledger line, the delivered torques and the commands, the counts (revisions included)."""
    scene, integrator, dt = native_cases()[case]
    low, high = command_bounds(scene)
    low, high = np.maximum(low, -50.0), np.minimum(high, 50.0)
    B, duration, control_dt = 3, 0.1, max(dt, 2e-3)
    n = round(duration / control_dt)
    rng = np.random.default_rng(7)
    taus = rng.uniform(low, high, size=(B, n, scene.nv)) * 1.2  # some beyond the bounds: clipped, counted
    taus[:, :, : scene.actuated.start] = 0.0
    Q0, V0 = np.tile(scene.q0, (B, 1)), np.zeros((B, scene.nv))

    def run():  # noqa: ANN202
        return ms.rollout(scene, Q0, V0, duration=duration, dt=dt, integrator=integrator, taus=taus,
                          control_dt=control_dt, progress=False)  # fmt: skip

    fast, slow = both(run, monkeypatch)
    assert fast.metadata["kernel"] == "native" and slow.metadata["kernel"] != "native"
    for b in range(B):
        assert_same_run(fast.element(b), slow.element(b))
        np.testing.assert_array_equal(fast.element(b).ctrl, slow.element(b).ctrl)
    assert fast.stats["saturated_controls"].sum() > 0


@needs_native
def test_native_stepper_and_controllers_with_actuators(monkeypatch: pytest.MonkeyPatch) -> None:
    """A built-in PD on torque actuators (commands computed inside the engine, clipped at the actuators' bounds) and a
    Stepper with servos, on both kernels."""
    scene = make_scene(robot={"source": "ur5"}, actuator=[{"joints": "*", "stall_torque": 100.0, "no_load_speed": 2.0}])
    pd = ms.make_controller("pd", scene, ["kp=400", "kd=20", "q_ref=0.3,-1,1,0,0.2,0"])

    def run():  # noqa: ANN202
        return ms.simulate(scene, scene.q0, np.zeros(6), duration=0.3, dt=1e-3, controller=pd, control_dt=2e-3)

    fast, slow = both(run, monkeypatch)
    assert fast.metadata["kernel"] == "native"
    assert_same_run(fast, slow)
    servos = rotor(kind="position", kp=1e4, kv=100.0, effort_limit=30.0)

    def step():  # noqa: ANN202
        stepper = ms.Stepper(servos, dt=0.01, integrator="semi_implicit_euler", q0=[0.0], v0=[0.0])
        for k in range(30):
            stepper.step(np.array([0.3 if k < 15 else -0.2]))
        return stepper

    assert_same_stepper(*both(step, monkeypatch))


def assert_rendered(scene: ms.Scene, rendered: Any, q: np.ndarray, v: np.ndarray, u: np.ndarray) -> None:
    """The native actuators (_native.SceneActuators) give Actuators' torques and ledger powers at (q, v) under u, bit
    for bit."""
    torques, flows = rendered.evaluate(q, v, u)
    expected = np.empty(len(scene.actuators.ledger))
    scene.actuators.powers(q, v, u, expected)
    np.testing.assert_array_equal(torques, scene.actuators.joint_torques(q, v, u))
    np.testing.assert_array_equal(flows, expected)


@needs_native
def test_native_arithmetic_of_the_actuators() -> None:
    """_native.SceneActuators.evaluate against Actuators.joint_torques and powers at random states and commands."""
    from multibody_sim.kernels.native import _scene_actuators

    scene = make_scene(
        robot={"source": "go2"},
        actuators="catalog",
        actuator=[
            {"joints": "*_calf_joint", "kind": "position", "kp": 40.0, "kv": 1.0},
            {"joints": "FL_hip_joint", "kind": "velocity", "kv": 2.0},
        ],
    )
    rendered = _scene_actuators(scene.actuators, ms.native.load_model(scene.model))
    rng = np.random.default_rng(1)
    for _ in range(200):
        q = scene.random_configuration(rng)
        v = rng.normal(0.0, 20.0, scene.nv)
        u = rng.normal(0.0, 30.0, scene.nv)
        u[:6] = 0.0
        assert_rendered(scene, rendered, q, v, u)


@needs_native
def test_native_actuators_at_the_edges_of_their_shortcuts() -> None:
    """_native.SceneActuators takes shortcuts below speeds where the limits provably are ± the effort limit (half the
    curve's knee, the velocity limit, half the brake's start): at and beside those speeds, the knee, the brake's start
    and band and the no-load speed, under laws at and beside the effort limits, the same torques and ledger powers
    as Actuators.joint_torques and powers."""
    from multibody_sim.kernels.native import _scene_actuators

    scene = make_scene(
        robot={"source": "go2"},
        actuators="catalog",
        actuator=[
            {"joints": "FL_calf_joint", "kind": "position", "kp": 40.0, "kv": 1.0},
            {"joints": "FR_hip_joint", "kind": "velocity", "kv": 2.0},
            {"joints": "RL_hip_joint", "overspeed": "none"},
            # a curve too close to its effort limit to shortcut
            {"joints": "RR_hip_joint", "stall_torque": 23.7 * 1.0005, "no_load_speed": 30.0},
        ],
    )
    rendered = _scene_actuators(scene.actuators, ms.native.load_model(scene.model))
    items = scene.actuators.items
    edges = []
    for a in items:
        marks = [a.velocity_limit, a.no_load_speed, a.no_load_speed * (1.0 - a.effort_limit / a.stall_torque)]
        if a.brake_gain > 0.0:
            start = a.velocity_limit - a.effort_limit / a.brake_gain
            marks += [start, (1.0 + a.overspeed_band) * a.velocity_limit]
        marks += [0.5 * x for x in marks]
        near = [y for x in marks if np.isfinite(x) for y in (np.nextafter(x, 0.0), x, np.nextafter(x, np.inf))]
        near += [x * (1.0 + d) for x in marks if np.isfinite(x) for d in (-1e-9, 1e-9)]
        edges.append(np.array([0.0, *near, *(-y for y in near)]))
    rng = np.random.default_rng(3)
    q0 = scene.q0
    for _ in range(3000):
        v = np.zeros(scene.nv)
        u = np.zeros(scene.nv)
        for a, speeds in zip(items, edges, strict=True):
            v[a.dof] = speeds[rng.integers(len(speeds))]
            target = a.effort_limit * rng.choice([-1.0, 1.0]) * (1.0 + rng.choice([-1e-12, 0.0, 1e-12, 0.3, -0.3]))
            if a.kind == "torque":
                u[a.dof] = target
            elif a.kind == "velocity":
                u[a.dof] = target / a.kv + v[a.dof]
            else:
                u[a.dof] = (target + a.kv * v[a.dof]) / a.kp + q0[a.iq]
        assert_rendered(scene, rendered, q0, v, u)
