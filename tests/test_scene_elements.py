"""Scene force elements (springs, damping, regularized friction, wrenches) against independent oracles."""

from __future__ import annotations

import re
import warnings
from collections.abc import Callable

import numpy as np
import pinocchio as pin
import pytest
from conftest import joint, link, urdf
from scipy.optimize import brentq

import multibody_sim as ms
from multibody_sim.exceptions import InvalidArgumentError
from multibody_sim.scenes.elements import ForceElements, Wrench

# A frame near the tip and one mid-chain, per robot, so that wrenches act through long and short chains.
FRAMES = {"ur5": ("tool0", "forearm_link"), "panda": ("panda_hand", "panda_link5"), "solo12": ("FL_FOOT", "HR_KFE")}


def make(robot: ms.Robot, **overrides: object) -> ForceElements:
    """ForceElements on a robot's model, every element off unless given."""
    nv = robot.nv
    kwargs: dict = dict(
        dof_names=robot.dof_names,
        damping=np.zeros(nv),
        friction=np.zeros(nv),
        friction_velocity=1e-3,
        stiffness=np.zeros(nv),
        rest=robot.neutral(),
        wrenches=[],
    )
    kwargs.update(overrides)
    return ForceElements(robot.model, **kwargs)


def random_wrench(
    robot: ms.Robot, frame: str, reference: str, rng: np.random.Generator, scale: Callable[[float], float] | None = None
) -> Wrench:
    extra = {} if scale is None else {"scale": scale}
    return Wrench(
        f"{reference}_{frame}",
        robot.model.getFrameId(frame),
        rng.normal(size=3) * 10.0,
        rng.normal(size=3),
        reference,  # type: ignore[arg-type]
        **extra,
    )


def frame_pose(model: pin.Model, q: np.ndarray, frame_id: int) -> pin.SE3:
    """The frame's placement in the world, by plain forward kinematics (no Jacobian involved)."""
    data = model.createData()
    pin.framesForwardKinematics(model, data, q)
    return data.oMf[frame_id].copy()


def pendulum(write_urdf: Callable[..., object], kind: str = "revolute") -> ms.Robot:
    """One link of 2 kg hanging 0.5 m below a joint about y (revolute, continuous or prismatic)."""
    text = urdf(link("base"), link("arm", mass=2.0, inertia="0.03 0.04 0.05"), joint("j", "base", "arm", kind))
    return ms.load_robot(str(write_urdf(text)), damping=False)


# ---- wrenches -----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("reference", ["world", "local"])
@pytest.mark.parametrize("name", ["ur5", "panda"])
def test_wrench_force_equals_aba_with_external_forces(robot, name: str, reference: str) -> None:
    """aba(q, v, tau + evaluate) == aba(q, v, tau, fext), with fext transformed to the joint frames here by SE(3)
    algebra (Pinocchio's own external-force path, no Jacobian)."""
    rob = robot(name, damping=False)
    model, rng = rob.model, np.random.default_rng(1)
    t = 0.5
    wrenches = [random_wrench(rob, f, reference, rng, scale=lambda t: 1.0 + t * t) for f in FRAMES[name]]
    elements = make(rob, wrenches=wrenches)
    data = model.createData()
    for _ in range(3):
        q, v, tau = rob.random_configuration(rng), rng.normal(size=rob.nv), rng.normal(size=rob.nv)
        pin.forwardKinematics(model, data, q)
        fext = pin.StdVec_Force()
        for _ in range(model.njoints):
            fext.append(pin.Force.Zero())
        for w in wrenches:
            frame = model.frames[w.frame_id]
            i, s = frame.parentJoint, w.scale(t)
            if reference == "local":
                f_joint = frame.placement.act(pin.Force(s * w.force, s * w.torque))
            else:  # the same wrench moved to the world origin, then into the joint frame
                p = frame_pose(model, q, w.frame_id).translation
                f_joint = data.oMi[i].actInv(pin.Force(s * w.force, s * (w.torque + np.cross(p, w.force))))
            fext[i] = fext[i] + f_joint
        expected = pin.aba(model, model.createData(), q, v, tau, fext)
        got = pin.aba(model, model.createData(), q, v, tau + elements.evaluate(q, v, t))
        # Both are the same linear solve with the forces summed in different orders: round-off only.
        np.testing.assert_allclose(got, expected, rtol=1e-9, atol=1e-9 * np.abs(expected).max())


@pytest.mark.parametrize("reference", ["world", "local"])
@pytest.mark.parametrize(("name", "floating"), [("ur5", False), ("panda", False), ("solo12", True)])
def test_wrench_force_equals_virtual_work(robot, name: str, floating: bool, reference: str) -> None:
    """f · δq equals the wrench's virtual work along δq: force · δp + torque · δθ, with δp and δθ central finite
    differences of the frame's pose along q ⊕ ε δq (tangent space: a free-flyer base on solo12)."""
    rob = robot(name, floating_base=floating, damping=False)
    model, rng = rob.model, np.random.default_rng(2)
    eps = 1e-6
    for frame in FRAMES[name]:
        w = random_wrench(rob, frame, reference, rng)
        elements = make(rob, wrenches=[w])
        q = rob.random_configuration(rng)
        f = elements.evaluate(q, np.zeros(rob.nv), 0.0)
        for _ in range(4):
            dq = rng.normal(size=rob.nv)
            plus = frame_pose(model, pin.integrate(model, q, eps * dq), w.frame_id)
            minus = frame_pose(model, pin.integrate(model, q, -eps * dq), w.frame_id)
            dp = (plus.translation - minus.translation) / (2 * eps)
            if reference == "world":
                dtheta = pin.log3(plus.rotation @ minus.rotation.T) / (2 * eps)  # world axes
                work = w.force @ dp + w.torque @ dtheta
            else:
                R = frame_pose(model, q, w.frame_id).rotation
                dtheta = pin.log3(minus.rotation.T @ plus.rotation) / (2 * eps)  # the frame's axes
                work = w.force @ (R.T @ dp) + w.torque @ dtheta
            # Central differences: O(ε²) truncation (~1e-12 here) and ~1e-16 · |p| / ε ≈ 1e-10 round-off per unit
            # force; 1e-7 relative leaves a wide margin while any wrong axis or sign would be O(1).
            assert f @ dq == pytest.approx(work, rel=1e-7, abs=1e-7 * np.abs(work).max())


# ---- springs --------------------------------------------------------------------------------------------------
def test_spring_on_pendulum_is_hookes_law(write_urdf) -> None:
    """Revolute spring, zero gravity: f = -k x, V = ½ k x², and ABA gives the analytic acceleration -k x / I with
    I = m l² + I_yy about the joint (the parallel-axis theorem)."""
    rob = pendulum(write_urdf)
    model = pin.Model(rob.model)
    model.gravity = pin.Motion.Zero()
    k, rest = 20.0, 0.3
    elements = make(rob, stiffness=np.array([k]), rest=np.array([rest]))
    assert elements.potentials == ["spring:j"] and elements.ledger == []
    inertia = 2.0 * 0.5**2 + 0.04
    for x in (-1.0, -0.2, 0.0, 0.5, 2.5):
        q = np.array([rest + x])
        f = elements.evaluate(q, np.zeros(1), 0.0)
        assert f[0] == pytest.approx(-k * x, abs=1e-12)
        assert elements.potential_energies(q)[0] == pytest.approx(0.5 * k * x * x, abs=1e-12)
        a = pin.aba(model, model.createData(), q, np.zeros(1), f)
        assert a[0] == pytest.approx(-k * x / inertia, rel=1e-12, abs=1e-12)


def test_prismatic_spring(write_urdf) -> None:
    """A prismatic spring pulls back by -k x [N]."""
    rob = pendulum(write_urdf, "prismatic")
    elements = make(rob, stiffness=np.array([150.0]), rest=np.array([0.1]))
    for x in (-0.4, 0.25):
        assert elements.evaluate(np.array([0.1 + x]), np.zeros(1))[0] == pytest.approx(-150.0 * x, abs=1e-12)


def test_continuous_spring_wraps(write_urdf) -> None:
    """On a continuous joint the spring sees the angle wrapped to (-π, π]: rest at 3.0 rad and q at -3.0 rad are
    2π - 6 ≈ 0.283 rad apart, not -6. Checked against the wrap formula and Pinocchio's difference."""
    rob = pendulum(write_urdf, "continuous")
    assert rob.nq == 2
    k, theta_rest = 7.0, 3.0
    rest = np.array([np.cos(theta_rest), np.sin(theta_rest)])
    elements = make(rob, stiffness=np.array([k]), rest=rest)
    for theta in (-3.0, 0.0, 2.0, 3.1, 6.0, -1.5):
        q = np.array([np.cos(theta), np.sin(theta)])
        x = (theta - theta_rest + np.pi) % (2 * np.pi) - np.pi
        assert x == pytest.approx(pin.difference(rob.model, rest, q)[0], abs=1e-12)
        assert elements.evaluate(q, np.zeros(1))[0] == pytest.approx(-k * x, abs=1e-12)
        assert elements.potential_energies(q)[0] == pytest.approx(0.5 * k * x * x, abs=1e-12)
    q = np.array([np.cos(-3.0), np.sin(-3.0)])
    assert elements.spring_displacements(q)[0] == pytest.approx(2 * np.pi - 6.0, abs=1e-12)


def test_spring_displacement_is_pinocchio_difference(write_urdf) -> None:
    """Mixed chain (revolute, continuous, prismatic): each spring's displacement is q ⊖ rest from pin.difference."""
    text = urdf(
        link("a"),
        link("b"),
        link("c"),
        link("d"),
        joint("r", "a", "b"),
        joint("c", "b", "c", "continuous", xyz="0 0 -1", axis="1 0 0"),
        joint("p", "c", "d", "prismatic", xyz="0 0 -1", axis="0 0 1"),
    )
    rob = ms.load_robot(str(write_urdf(text)), damping=False)
    rng = np.random.default_rng(3)
    k = np.array([3.0, 5.0, 11.0])
    for _ in range(5):
        rest, q = rob.random_configuration(rng), rob.random_configuration(rng)
        elements = make(rob, stiffness=k, rest=rest)
        x = pin.difference(rob.model, rest, q)
        np.testing.assert_allclose(elements.spring_displacements(q), x, atol=1e-12)
        np.testing.assert_allclose(elements.evaluate(q, np.zeros(3)), -k * x, atol=1e-12)
        np.testing.assert_allclose(elements.potential_energies(q), 0.5 * k * x * x, atol=1e-12)


# ---- friction -------------------------------------------------------------------------------------------------
def test_friction_power_is_nonnegative_and_analytic(robot) -> None:
    """Friction and damping only take energy out: powers ≥ 0 for velocities from 1e-6 v_s to 1e4 v_s of either
    sign, equal to F_c v tanh(v / v_s) and d v²."""
    rob = robot("panda", damping=False)
    rng = np.random.default_rng(4)
    fc, d, vs = rng.uniform(0.1, 1.0, rob.nv), rng.uniform(0.1, 1.0, rob.nv), 1e-3
    elements = make(rob, friction=fc, damping=d, friction_velocity=vs)
    out = np.empty(len(elements.ledger))
    for _ in range(20):
        v = rng.choice([-1.0, 1.0], rob.nv) * vs * 10.0 ** rng.uniform(-6, 4, rob.nv)
        elements.evaluate(rob.neutral(), v, 0.0)
        elements.powers(v, out)
        assert np.all(out >= 0.0)
        np.testing.assert_allclose(out[: rob.nv], d * v * v, rtol=1e-14)
        np.testing.assert_allclose(out[rob.nv :], fc * v * np.tanh(v / vs), rtol=1e-14)


@pytest.mark.parametrize("load", [0.1, 0.5, 0.9, -0.7])
def test_friction_creep_velocity(write_urdf, load: float) -> None:
    """Under a constant load τ = load · F_c the regularized friction balances it at the documented creep velocity
    v_s · atanh(τ / F_c): found here as the root of τ + f(v) with a bracketing solver."""
    rob = pendulum(write_urdf)
    fc, vs = 0.3, 2e-3
    elements = make(rob, friction=np.array([fc]), friction_velocity=vs)
    q, tau = rob.neutral(), load * fc
    root = brentq(lambda v: tau + elements.evaluate(q, np.array([v]))[0], -50 * vs, 50 * vs, xtol=1e-15, rtol=1e-14)
    assert root == pytest.approx(vs * np.arctanh(load), rel=1e-10)


@pytest.mark.parametrize(("method", "limit"), [("euler", 2.0), ("rk4", 2.785)])
def test_friction_step_limit_of_explicit_methods(write_urdf, method: str, limit: float) -> None:
    """The documented stiffness: near rest, friction relaxes the velocity with T_f = m v_s / F_c (m = 1 / M⁻¹ of
    the joint), and explicit Euler / RK4 are stable for h < 2 T_f / 2.785 T_f (their real stability intervals).
    Integrating v' = aba(q, v, f(v)) by hand from v = 0.1 v_s: 5 % below the limit the velocity dies out, 5 % above
    it grows until the tanh saturates."""
    rob = pendulum(write_urdf)
    model = pin.Model(rob.model)
    model.gravity = pin.Motion.Zero()
    data = model.createData()
    fc, vs = 0.3, 1e-3
    elements = make(rob, friction=np.array([fc]), friction_velocity=vs)
    q = rob.neutral()
    m = 1.0 / pin.computeMinverse(model, data, q)[0, 0]
    time_constant = m * vs / fc

    def accel(v: np.ndarray) -> np.ndarray:
        return pin.aba(model, data, q, v, elements.evaluate(q, v))

    def final_speed(h: float) -> float:
        v = np.array([0.1 * vs])
        for _ in range(300):
            if method == "euler":
                v = v + h * accel(v)
            else:
                k1 = accel(v)
                k2 = accel(v + 0.5 * h * k1)
                k3 = accel(v + 0.5 * h * k2)
                k4 = accel(v + h * k3)
                v = v + h / 6 * (k1 + 2 * k2 + 2 * k3 + k4)
        return abs(v[0])

    assert final_speed(0.95 * limit * time_constant) < 1e-6 * vs
    assert final_speed(1.05 * limit * time_constant) > 0.1 * vs


def test_friction_jacobian_far_from_rest(write_urdf) -> None:
    """df/dv = -F_c sech²(v / v_s) / v_s stays finite and warning-free at |v| ≫ v_s (cosh² would overflow beyond
    355 v_s), and matches the textbook formula where that one is still representable."""
    rob = pendulum(write_urdf)
    fc, vs = 0.3, 1e-3
    elements = make(rob, friction=np.array([fc]), friction_velocity=vs)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        for v in (1e4 * vs, -1e6 * vs):
            assert elements.jacobians(rob.neutral(), np.array([v]))[1][0, 0] == pytest.approx(0.0, abs=1e-300)
    for u in (0.0, 0.3, -2.0, 20.0, 300.0):
        got = elements.jacobians(rob.neutral(), np.array([u * vs]))[1][0, 0]
        assert got == pytest.approx(-fc / vs / np.cosh(u) ** 2, rel=1e-12)


# ---- Jacobians ------------------------------------------------------------------------------------------------
def jacobian_case(rob: ms.Robot, rng: np.random.Generator, first: int, name: str) -> ForceElements:
    """Springs, dampers, friction and both kinds of time-scaled wrenches on the dofs after index `first`."""
    nv = rob.nv
    stiffness, damping, friction = np.zeros(nv), np.zeros(nv), np.zeros(nv)
    stiffness[[first + 1, first + 3]] = 20.0, 30.0
    damping[[first, first + 2]] = 0.5
    friction[[first + 3, first + 4]] = 0.3
    wrenches = [
        random_wrench(rob, FRAMES[name][0], "world", rng, scale=lambda t: np.sin(3.0 * t)),
        random_wrench(rob, FRAMES[name][1], "local", rng, scale=lambda t: 1.0 + t),
    ]
    return make(
        rob,
        stiffness=stiffness,
        damping=damping,
        friction=friction,
        friction_velocity=0.05,
        rest=rob.random_configuration(rng),
        wrenches=wrenches,
    )


@pytest.mark.parametrize(("name", "floating"), [("panda", False), ("solo12", True)])
def test_jacobians_match_finite_differences(robot, name: str, floating: bool) -> None:
    """jacobians() equals central differences of evaluate(): in q along tangent directions (q ⊕ ε e_j, a
    free-flyer base on solo12), in v directly. The wrench part is not small: it is checked, not hidden."""
    rob = robot(name, floating_base=floating, damping=False)
    rng = np.random.default_rng(5)
    elements = jacobian_case(rob, rng, 6 if floating else 0, name)
    q, t = rob.random_configuration(rng), 0.4
    v = rng.normal(size=rob.nv) * 0.05  # friction velocities within a few v_s, where its curvature is largest
    df_dq, df_dv = elements.jacobians(q, v, t)
    eps, nv = 1e-6, rob.nv
    fd_q, fd_v = np.zeros((nv, nv)), np.zeros((nv, nv))
    for j in range(nv):
        e = np.zeros(nv)
        e[j] = eps
        plus = elements.evaluate(pin.integrate(rob.model, q, e), v, t)
        minus = elements.evaluate(pin.integrate(rob.model, q, -e), v, t)
        fd_q[:, j] = (plus - minus) / (2 * eps)
        fd_v[:, j] = (elements.evaluate(q, v + e, t) - elements.evaluate(q, v - e, t)) / (2 * eps)
    # Truncation ε² f'''/6: at most ~1e-9 for friction (F_c / v_s³ ≈ 2400 with v_s = 0.05) and the kinematics;
    # round-off 1e-16 |f| / ε ≈ 1e-8 for |f| ≲ 50. 1e-6 leaves a margin of ~100 over both.
    np.testing.assert_allclose(df_dq, fd_q, atol=1e-6)
    np.testing.assert_allclose(df_dv, fd_v, atol=1e-6)
    springs = np.zeros((nv, nv))
    springs[elements._sprung, elements._sprung] = -np.array([20.0, 30.0])
    assert np.abs(df_dq - springs).max() > 1.0  # the wrenches' q-dependence is really exercised


# ---- powers and bookkeeping -----------------------------------------------------------------------------------
def test_powers_match_each_elements_force_times_velocity(robot) -> None:
    """Each ledger power equals (that element's generalized force, from a ForceElements holding it alone) · v,
    negated for dissipated elements; and the total force · v is the work minus the dissipation plus the springs'."""
    rob = robot("panda", damping=False)
    rng = np.random.default_rng(6)
    nv, t = rob.nv, 0.7
    damping, friction, stiffness = np.zeros(nv), np.zeros(nv), np.zeros(nv)
    damping[[0, 4]] = 0.2, 0.7
    friction[[1, 4, 6]] = 0.3, 0.1, 0.5
    stiffness[[2, 5]] = 15.0, 25.0
    wrenches = [
        random_wrench(rob, "panda_hand", "world", rng, scale=lambda t: np.cos(t)),
        random_wrench(rob, "panda_link5", "local", rng),
    ]
    common = dict(friction_velocity=0.01, rest=rob.random_configuration(rng))
    elements = make(rob, damping=damping, friction=friction, stiffness=stiffness, wrenches=wrenches, **common)
    assert elements.ledger == [
        ("damping:panda_joint1", "dissipated"),
        ("damping:panda_joint5", "dissipated"),
        ("friction:panda_joint2", "dissipated"),
        ("friction:panda_joint5", "dissipated"),
        ("friction:panda_joint7", "dissipated"),
        (f"force:{wrenches[0].name}", "work"),
        (f"force:{wrenches[1].name}", "work"),
    ]
    assert elements.potentials == ["spring:panda_joint3", "spring:panda_joint6"]

    def alone(kind: str, index: int) -> ForceElements:
        if kind == "force":
            return make(rob, wrenches=[wrenches[index]], **common)
        values = np.zeros(nv)
        values[index] = {"damping": damping, "friction": friction, "stiffness": stiffness}[kind][index]
        return make(rob, **{kind: values}, **common)

    parts = [("damping", 0), ("damping", 4), ("friction", 1), ("friction", 4), ("friction", 6)]
    parts += [("force", 0), ("force", 1)]
    out = np.empty(len(elements.ledger))
    for _ in range(3):
        q, v = rob.random_configuration(rng), rng.normal(size=nv) * 0.05
        total = elements.evaluate(q, v, t).copy()
        elements.powers(v, out)
        expected = [(1.0 if kind == "force" else -1.0) * alone(kind, i).evaluate(q, v, t) @ v for kind, i in parts]
        np.testing.assert_allclose(out, expected, rtol=1e-12, atol=1e-14)
        spring_power = sum(alone("stiffness", i).evaluate(q, v, t) @ v for i in (2, 5))
        balance = out[5:].sum() - out[:5].sum() + spring_power
        assert total @ v == pytest.approx(balance, rel=1e-12, abs=1e-13)


def test_evaluate_into_out_and_fresh_arrays(robot) -> None:
    """evaluate(out=) writes into and returns out; without it each call returns a new array (no aliasing)."""
    rob = robot("panda", damping=False)
    rng = np.random.default_rng(7)
    elements = jacobian_case(rob, rng, 0, "panda")
    q1, q2, v = rob.random_configuration(rng), rob.random_configuration(rng), rng.normal(size=rob.nv)
    a, b = elements.evaluate(q1, v, 0.1), elements.evaluate(q2, v, 0.1)
    assert a is not b and not np.allclose(a, b)
    out = np.full(rob.nv, np.nan)
    assert elements.evaluate(q1, v, 0.1, out) is out
    np.testing.assert_array_equal(out, a)


def test_flags(robot) -> None:
    """empty: no element at all; time_dependent: any wrench."""
    rob = robot("ur5", damping=False)
    nothing = make(rob)
    assert nothing.empty and not nothing.time_dependent and nothing.ledger == [] and nothing.potentials == []
    np.testing.assert_array_equal(nothing.evaluate(rob.neutral(), np.ones(rob.nv)), np.zeros(rob.nv))
    sprung = make(rob, stiffness=np.r_[1.0, np.zeros(rob.nv - 1)])
    assert not sprung.empty and not sprung.time_dependent
    pushed = make(rob, wrenches=[random_wrench(rob, "tool0", "world", np.random.default_rng(8))])
    assert not pushed.empty and pushed.time_dependent


# ---- errors ---------------------------------------------------------------------------------------------------
def test_joint_elements_only_on_one_dof_joints(robot) -> None:
    rob = robot("solo12", floating_base=True, damping=False)
    stiffness = np.zeros(rob.nv)
    stiffness[3] = 1.0
    message = (
        "stiffness on 'root_joint.wx': joint elements apply to 1-dof joints (revolute, prismatic, continuous) only"
    )
    with pytest.raises(InvalidArgumentError, match=re.escape(message)):
        make(rob, stiffness=stiffness)


def test_bad_arguments(robot) -> None:
    rob = robot("ur5", damping=False)
    with pytest.raises(InvalidArgumentError, match=re.escape("damping must be finite and >= 0, got [-1.0, 0.0")):
        make(rob, damping=np.r_[-1.0, np.zeros(rob.nv - 1)])
    with pytest.raises(InvalidArgumentError, match=re.escape("friction must have shape (6,), got (5,)")):
        make(rob, friction=np.zeros(5))
    with pytest.raises(InvalidArgumentError, match=re.escape("friction_velocity must be > 0, got 0.0")):
        make(rob, friction_velocity=0.0)
    with pytest.raises(InvalidArgumentError, match=re.escape("wrench 'w': reference must be one of local, world")):
        Wrench("w", 1, np.zeros(3), np.zeros(3), "body")  # type: ignore[arg-type]
    with pytest.raises(InvalidArgumentError, match=re.escape("wrench 'w': frame_id 999 out of range [0, ")):
        make(rob, wrenches=[Wrench("w", 999, np.zeros(3))])
