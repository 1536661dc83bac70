"""Stability at the extremes: the linearised system, stiffness ratios, the largest stable step, a tumbling free body,
tiny/huge inertia ratios, divergence, and (slow) energy drift over a million steps.

References, all independent of the code under test: the shipped stiff arm's mass matrix and gravity stiffness
written out from its URDF's constants; central finite differences of forward dynamics through Pinocchio's own
integrate/dIntegrate; the closed-form roots of J θ'' + d θ' + k θ = 0; the stability functions of explicit
Runge–Kutta methods on the negative real axis (|1 + z| ≤ 1 for Euler and RK2's |1 + z + z²/2| ≤ 1 give 2/|λ|,
RK4's interval is 2.7853/|λ|) and on the imaginary axis; the Jacobi-elliptic solution of Euler's equations for
a free rigid body (Landau & Lifshitz, Mechanics §37); conservation laws; scipy's Radau and DOP853 on Pinocchio's
ABA; and the exact invariants of symplectic Euler and RK4 on a linear oscillator.
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from conftest import joint, link, urdf
from scipy.integrate import solve_ivp
from scipy.optimize import brentq
from scipy.special import ellipk

import multibody_sim as ms
from multibody_sim.integrators import Integrator, StepFailure

RobotFactory = Callable[..., ms.Robot]
G = 9.81
RK4_REAL_INTERVAL = 2.785293563405282  # RK4's stability interval on the negative real axis is [-2.7853, 0]
# |R(z)| <= 1 on the negative real axis: Euler |1 + z|, explicit midpoint |1 + z + z²/2| (both [-2, 0]), RK4; the
# stiff arm's fast mode is a velocity mode (v' ≈ λ v), on which semi-implicit Euler's velocity update is explicit
# Euler, so it has Euler's limit.
REAL_INTERVAL = {"euler": 2.0, "semi_implicit_euler": 2.0, "midpoint": 2.0, "rk4": RK4_REAL_INTERVAL}
STIFF_ARM_URDF = Path(__file__).resolve().parents[1] / "models" / "stiff_arm" / "stiff_arm.urdf"


# ---- independent references -------------------------------------------------------------------------------
def stiff_arm_constants() -> dict[str, float]:
    """The two moving links' constants, read from the shipped URDF's text (not through Pinocchio)."""
    root = ET.parse(STIFF_ARM_URDF).getroot()
    links = {e.get("name"): e for e in root.findall("link")}
    joints = {e.get("name"): e for e in root.findall("joint")}

    def inertial(name: str) -> tuple[float, float, float]:
        element = links[name].find("inertial")
        com_z = float(element.find("origin").get("xyz").split()[2])
        return float(element.find("mass").get("value")), -com_z, float(element.find("inertia").get("iyy"))

    m1, c1, i1 = inertial("upper")
    m2, c2, i2 = inertial("tip")
    return {
        "m1": m1, "c1": c1, "i1": i1, "m2": m2, "c2": c2, "i2": i2,
        "l1": -float(joints["elbow"].find("origin").get("xyz").split()[2]),
        "d1": float(joints["shoulder"].find("dynamics").get("damping")),
        "d2": float(joints["elbow"].find("dynamics").get("damping")),
    }  # fmt: skip


def two_link_rates(c: dict[str, float]) -> tuple[float, float]:
    """(fast, slow) decay rates [1/s] of a two-link arm hanging at rest with a light, heavily damped tip.

    Fast: the elbow damping acting through the inverse mass matrix, d2 (M⁻¹)₂₂ = d2 M11 / det M. Slow: gravity
    relaxing the overdamped tip while the upper link follows statically, (K22 - K12²/K11) / d2, the Schur
    complement of the gravity stiffness K. Both to leading order in the tip's smallness (corrections ~1e-5).
    """
    M11 = c["i1"] + c["m1"] * c["c1"] ** 2 + c["i2"] + c["m2"] * (c["l1"] ** 2 + c["c2"] ** 2 + 2 * c["l1"] * c["c2"])
    M12 = c["i2"] + c["m2"] * (c["c2"] ** 2 + c["l1"] * c["c2"])
    M22 = c["i2"] + c["m2"] * c["c2"] ** 2
    K11 = G * (c["m1"] * c["c1"] + c["m2"] * (c["l1"] + c["c2"]))
    K12 = K22 = G * c["m2"] * c["c2"]
    return c["d2"] * M11 / (M11 * M22 - M12**2), (K22 - K12**2 / K11) / c["d2"]


def chart_jacobian_by_finite_differences(
    system: ms.Robot, q: np.ndarray, v: np.ndarray, tau: np.ndarray, eps: float = 1e-6
) -> np.ndarray:
    """Central differences of (ξ', v') = (dIntegrate(q, ξ)⁻¹ v, a(q ⊕ ξ, v)) at ξ = 0, with Pinocchio's own maps."""
    nv = system.nv

    def field(xi: np.ndarray, vel: np.ndarray) -> np.ndarray:
        chart = pin.dIntegrate(system.model, q, xi, pin.ArgumentPosition.ARG1)
        return np.concatenate(
            [np.linalg.solve(chart, vel), system.forward_dynamics(pin.integrate(system.model, q, xi), vel, tau)]
        )

    A = np.empty((2 * nv, 2 * nv))
    for i in range(2 * nv):
        e = np.zeros(2 * nv)
        e[i] = eps
        A[:, i] = (field(e[:nv], v + e[nv:]) - field(-e[:nv], v - e[nv:])) / (2 * eps)
    return A


def tip_arm(write_urdf: Callable[..., Path], scale: float, *, damped: bool = True) -> ms.Robot:
    """A two-link arm whose tip's mass and inertia are `scale` times a 1 kg link's: inertias 1/scale apart."""
    text = urdf(
        '<link name="base"/>',
        link("upper", mass=1.0, com="0 0 -0.5", inertia="0.01 0.01 0.01"),
        link("tip", mass=scale, com="0 0 -0.5", inertia=" ".join([f"{0.01 * scale:.6g}"] * 3)),
        joint("shoulder", "base", "upper", damping=0.05 if damped else None),
        joint("elbow", "upper", "tip", xyz="0 0 -1", damping=0.05 if damped else None),
        name="tip_arm",
    )
    return ms.load_robot(write_urdf(text, f"tip_arm_{scale:g}_{damped}.urdf"))


def rotation(q: np.ndarray) -> np.ndarray:
    """The free-flyer's rotation matrix from its quaternion (x, y, z, w), by Pinocchio's Quaternion class."""
    return pin.Quaternion(q[6], q[3], q[4], q[5]).toRotationMatrix()


# ---- the linearised system -----------------------------------------------------------------------------------
def test_shipped_stiff_arm_has_a_stiffness_ratio_above_1e4():
    arm = ms.load_robot("stiff_arm")
    stiffness = ms.stiffness_ratio(arm, np.zeros(2), np.zeros(2))
    fast, slow = two_link_rates(stiff_arm_constants())
    assert stiffness.ratio >= 1e4
    assert stiffness.decaying == 4  # the hanging equilibrium is asymptotically stable: every mode decays
    # The analytic rates hold to leading order in the tip's smallness; the shoulder's damping and gravity move
    # them by ~1e-5 relative.
    assert stiffness.fastest.real == pytest.approx(-fast, rel=1e-4)
    assert stiffness.slowest.real == pytest.approx(-slow, rel=1e-4)
    assert stiffness.ratio == pytest.approx(fast / slow, rel=2e-4)
    # The same rates from central differences of forward dynamics (no ABA derivatives) at rest.
    numeric = np.linalg.eigvals(chart_jacobian_by_finite_differences(arm, np.zeros(2), np.zeros(2), np.zeros(2)))
    np.testing.assert_allclose(np.sort(numeric.real), np.sort(stiffness.eigenvalues.real), rtol=1e-6, atol=1e-9)
    # Its 2 kg mount keeps the mass matrix of a floating base non-singular (a massless root would not).
    floating = ms.load_robot("stiff_arm", floating_base=True)
    assert np.linalg.eigvalsh(floating.mass_matrix(floating.neutral())).min() > 1e-3


@pytest.mark.parametrize("case", ["stiff_arm", "panda", "ur5", "free_body", "solo12", "planar", "spherical"])
def test_linearization_matches_finite_differences(case, robot):
    """At random states with v ≠ 0, so that the chart term -½ ad_v of free-flyer, planar and spherical joints
    is exercised too; the damped robots (stiff arm, panda) check the damping's share of da/dv."""
    rng = np.random.default_rng(7)
    if case == "planar":  # built in code: the URDF loader's refusal of planar joints is reported separately
        model = pin.Model()
        puck = model.addJoint(0, pin.JointModelPlanar(), pin.SE3.Identity(), "slide")
        model.appendBodyToJoint(
            puck, pin.Inertia(1.0, np.array([0.1, 0.05, 0.0]), np.diag([0.01, 0.02, 0.03])), pin.SE3.Identity()
        )
        hinge = model.addJoint(puck, pin.JointModelRZ(), pin.SE3(np.eye(3), np.array([0.1, 0.0, 0.0])), "hinge")
        model.appendBodyToJoint(
            hinge, pin.Inertia(0.5, np.array([0.2, 0.0, 0.0]), np.diag([0.001, 0.002, 0.002])), pin.SE3.Identity()
        )
        model.damping[:] = [0.2, 0.2, 0.2, 0.1]
        system = ms.Robot(model, name="planar", floating_base=False)
    elif case == "spherical":  # no URDF joint is spherical: build the Pinocchio model in code
        model = pin.Model()
        ball = model.addJoint(0, pin.JointModelSpherical(), pin.SE3.Identity(), "ball")
        model.appendBodyToJoint(
            ball, pin.Inertia(1.0, np.array([0.1, 0.0, -0.5]), np.diag([0.01, 0.02, 0.03])), pin.SE3.Identity()
        )
        system = ms.Robot(model, name="ball", floating_base=False)
    else:
        system = robot(case)
    assert (case in ("free_body", "solo12", "planar", "spherical")) == bool(system.space.curved_blocks)
    q, v = system.random_configuration(rng), rng.normal(size=system.nv)
    tau = np.zeros(system.nv) if system.floating_base else rng.normal(size=system.nv)
    A = ms.linearization(system, q, v, tau)
    numeric = chart_jacobian_by_finite_differences(system, q, v, tau)
    # Central differences at 1e-6: truncation ~1e-12 |f'''|, round-off ~1e-10 |f|; the stiff arm's entries reach 4e4.
    scale = 1.0 + np.max(np.abs(A))
    np.testing.assert_allclose(A, numeric, rtol=0, atol=1e-7 * scale)
    if not system.space.curved_blocks:  # distinct eigenvalues; a free-flyer's repeated ones are ill-conditioned
        eig, eig_numeric = np.linalg.eigvals(A), np.linalg.eigvals(numeric)
        np.testing.assert_allclose(np.sort_complex(eig), np.sort_complex(eig_numeric), rtol=0, atol=1e-6 * scale)
    else:  # the chart term matters: without it the Jacobian is measurably wrong
        flat = A.copy()
        for start, stop in system.space.curved_blocks:
            flat[start:stop, start:stop] = 0.0
        assert np.max(np.abs(flat - numeric)) > 1e3 * 1e-7 * scale


@pytest.mark.parametrize("damping", [0.0, 0.3, 30.0])
def test_one_dof_eigenvalues_are_the_roots_of_the_damped_pendulum(write_urdf, damping):
    """J θ'' + d θ' + m g l θ = 0 with J = m l² + I_yy: λ = (-d ± √(d² - 4 J m g l)) / (2 J)."""
    m, ell, iyy = 2.0, 0.7, 0.003
    text = urdf(
        '<link name="base"/>',
        link("bob", mass=m, com=f"0 0 {-ell}", inertia=f"{iyy} {iyy} {iyy}"),
        joint("hinge", "base", "bob", damping=damping),
    )
    pendulum = ms.load_robot(write_urdf(text))
    J, k = m * ell**2 + iyy, m * G * ell
    roots = np.roots([J, damping, k]).astype(complex)
    stiffness = ms.stiffness_ratio(pendulum, [0.0], [0.0])
    np.testing.assert_allclose(np.sort_complex(stiffness.eigenvalues), np.sort_complex(roots), rtol=1e-10)
    assert stiffness.spectral_radius == pytest.approx(np.max(np.abs(roots)), rel=1e-10)
    if damping == 0.0:  # undamped: oscillatory, not stiff; no decaying mode, no ratio
        assert stiffness.decaying == 0 and math.isnan(stiffness.ratio)
        assert stiffness.fastest is None and stiffness.slowest is None
    elif damping**2 < 4 * J * k:  # a decaying complex pair: one decay rate, ratio 1
        assert stiffness.decaying == 2 and stiffness.ratio == pytest.approx(1.0, rel=1e-12)
    else:  # overdamped: two real rates
        fast, slow = sorted(np.abs(roots.real), reverse=True)
        assert stiffness.ratio == pytest.approx(fast / slow, rel=1e-9)
        assert stiffness.fastest.real == pytest.approx(-fast, rel=1e-10)


def test_neutral_and_growing_modes_are_not_decaying():
    """A free body in space is all neutral modes; the upright double pendulum (q = 0) has growing ones."""
    body = ms.load_robot("free_body")
    body.model.gravity.linear = np.zeros(3)  # a freshly loaded copy: the cached catalog robot keeps its gravity
    at_rest = ms.stiffness_ratio(body, body.neutral(), np.zeros(6))
    assert at_rest.decaying == 0 and math.isnan(at_rest.ratio) and at_rest.spectral_radius == 0.0
    upright = ms.load_robot("double_pendulum", damping=False)
    stiffness = ms.stiffness_ratio(upright, [0.0, 0.0], [0.0, 0.0])
    # Undamped and conservative: eigenvalues come in pairs ±λ (two real saddle pairs at the top).
    eig = stiffness.eigenvalues
    np.testing.assert_allclose(np.sort(eig.real), -np.sort(eig.real)[::-1], atol=1e-9 * stiffness.spectral_radius)
    assert np.sum(eig.real > 0) == 2 and stiffness.decaying == 2


def test_stiffness_arguments_are_checked(robot):
    arm = robot("stiff_arm")
    with pytest.raises(ms.InvalidArgumentError, match=re.escape("v must have shape (2,), got (3,)")):
        ms.linearization(arm, [0.0, 0.0], [0.0, 0.0, 0.0])
    with pytest.raises(ms.InvalidArgumentError, match=re.escape("decay_tolerance must be a positive number, got 0")):
        ms.stiffness_ratio(arm, [0.0, 0.0], [0.0, 0.0], decay_tolerance=0)


# ---- the largest stable step: analytic limits on the stiff arm ----------------------------------------------
# The fast mode's limits (2/|λ| ≈ 4.8e-5 s, 2.785/|λ| ≈ 6.7e-5 s) fall 15 to 20 % from the nearest rungs of the
# ladder 0.02 s / √2^k, so each rung is clearly stable (|R(hλ)| < 0.9) or clearly unstable (|R(hλ)| > 1.3: a
# round-off seed grows past the blow-up check within the 0.2 s horizon's ~4000 steps).
STIFF_Q0, STIFF_HORIZON = [0.5, 0.0], 0.2


@pytest.mark.parametrize("name", sorted(REAL_INTERVAL))
def test_largest_stable_dt_brackets_the_analytic_limit_of_explicit_methods(name, robot):
    arm = robot("stiff_arm")
    fast, _ = two_link_rates(stiff_arm_constants())
    limit = REAL_INTERVAL[name] / fast
    result = ms.largest_stable_dt(arm, name, STIFF_Q0, [0.0, 0.0], horizon=STIFF_HORIZON)
    assert result.integrator == name and result.confirmed and not result.notes
    assert limit / 2**0.5 < result.largest_stable_dt <= limit
    # The ladder: geometric from a tenth of the horizon, unstable (diverged) above the answer, stable at the answer
    # and the rung below it, where it stops.
    dts = [rung.dt for rung in result.rungs]
    np.testing.assert_allclose(dts, STIFF_HORIZON / 10 / 2 ** (np.arange(len(dts)) / 2), rtol=1e-12)
    assert [rung.stable for rung in result.rungs] == [False] * (len(dts) - 2) + [True, True]
    assert all(rung.status == "diverged" and rung.reached < STIFF_HORIZON for rung in result.rungs[:-2])
    assert all(rung.status == "completed" and rung.reached == STIFF_HORIZON for rung in result.rungs[-2:])
    assert result.largest_stable_dt == result.rungs[-2].dt
    assert len(result.table().splitlines()) == 2 + len(dts)


@pytest.mark.parametrize("name", ["implicit_euler", "implicit_midpoint", "variational"])
def test_a_stable_methods_are_stable_up_to_the_cap(name, robot):
    """|hλ| ≈ 830 at the cap (h = horizon/10): A-stability keeps the fast mode bounded at any step."""
    arm = robot("stiff_arm")
    result = ms.largest_stable_dt(arm, name, STIFF_Q0, [0.0, 0.0], horizon=STIFF_HORIZON)
    assert result.largest_stable_dt == STIFF_HORIZON / 10 and result.confirmed
    assert len(result.rungs) == 2 and all(rung.status == "completed" for rung in result.rungs)


def test_the_energy_bound_decides_on_a_conservative_oscillator(robot):
    """Explicit Euler multiplies a linear oscillator's energy by exactly 1 + (ωh)² per step, so the rungs whose
    energy error exceeds the bound are known in advance: the ladder must classify each one the same way."""
    pendulum = robot("pendulum")
    omega = math.sqrt(G * 1.0 / (1.0 + 0.001))  # m g l / (m l² + I_yy) from the URDF
    theta0, horizon = 0.01, 2.0  # small: the nonlinearity changes the energy growth by ~θ0²/8 ~ 1e-5 relative
    energy0 = 1.0 * G * 1.0 * (1 - math.cos(theta0))
    bound = 0.1 * energy0

    def energy_error(h: float) -> float:  # the last step is shortened to land on the horizon
        n = math.ceil(horizon / h - 1e-9)
        last = horizon - (n - 1) * h
        return energy0 * ((1 + (omega * h) ** 2) ** (n - 1) * (1 + (omega * last) ** 2) - 1)

    result = ms.largest_stable_dt(pendulum, "euler", [theta0], [0.0], horizon=horizon, energy_bound=bound)
    assert result.energy_bound == bound
    for rung in result.rungs:
        assert rung.status == "completed"
        assert rung.max_energy_error == pytest.approx(energy_error(rung.dt), rel=1e-3)
        if abs(energy_error(rung.dt) / bound - 1) > 0.01:
            assert rung.stable == (energy_error(rung.dt) <= bound), rung
    threshold = brentq(lambda h: energy_error(h) - bound, 1e-4, 0.05)
    assert threshold / 2**0.5 < result.largest_stable_dt <= threshold
    assert "max |energy_error| <= " in result.criterion and "(given)" in result.criterion


class _UnstableAt(Integrator):
    """Explicit Euler that fails (StepFailure) at given step sizes: a ladder made non-monotone on purpose."""

    name = "unstable_at"
    order = 1
    description = "test double"
    evaluations_per_step = 1

    def __init__(self, unstable_dts: list[float]):
        self.unstable_dts = unstable_dts

    def step(self, system, q, v, tau, dt, t=0.0):
        if any(math.isclose(dt, bad, rel_tol=1e-9) for bad in self.unstable_dts):
            raise StepFailure("on the unstable list", status="newton_failed")
        return ms.INTEGRATORS["euler"].step(system, q, v, tau, dt, t)


def test_an_isolated_stable_rung_is_not_the_answer(robot):
    pendulum = robot("pendulum")
    rung = [0.1 / 2 ** (k / 2) for k in range(8)]
    method = _UnstableAt([rung[0], rung[2], rung[3], rung[6]])  # rung 1 stable alone, rungs 4 and 5 a pair
    result = ms.largest_stable_dt(pendulum, method, [0.01], [0.0], horizon=1.0, energy_bound=1.0)
    assert result.largest_stable_dt == pytest.approx(rung[4], rel=1e-12) and result.confirmed
    assert [r.stable for r in result.rungs] == [False, True, False, False, True, True]
    assert [r.status for r in result.rungs] == ["newton_failed", "completed", "newton_failed", "newton_failed"] + [
        "completed"
    ] * 2
    assert result.notes == (
        f"isolated stable rung at dt = {rung[1]:.4g} s (the next smaller step, {rung[2]:.4g} s, is unstable: "
        "newton_failed at t = 0 s); stability is not monotone in dt here",
    )


def test_a_stable_last_rung_before_max_steps_is_an_unconfirmed_answer(robot):
    rung = [0.1 / 2 ** (k / 2) for k in range(5)]
    method = _UnstableAt(rung[:3])
    # Rung 3 takes ceil(1 / 0.0354) = 29 steps, rung 4 would take 40: the ladder stops before it.
    result = ms.largest_stable_dt(robot("pendulum"), method, [0.01], [0.0], horizon=1.0, energy_bound=1.0, max_steps=35)
    assert [r.stable for r in result.rungs] == [False, False, False, True]
    assert result.largest_stable_dt == pytest.approx(rung[3], rel=1e-12) and not result.confirmed
    assert result.notes == (f"ladder stopped at dt = {rung[4]:.4g} s: a run would take more than max_steps = 35 steps",)


def test_the_ladder_stops_at_max_steps(robot):
    arm = robot("stiff_arm")
    result = ms.largest_stable_dt(arm, "euler", STIFF_Q0, [0.0, 0.0], horizon=STIFF_HORIZON, max_steps=1000)
    # Euler needs dt < 4.8e-5 s, i.e. more than 4000 steps: no rung within 1000 steps is stable.
    assert result.largest_stable_dt is None and not result.confirmed
    assert all(STIFF_HORIZON / r.dt <= 1000 for r in result.rungs) and not any(r.stable for r in result.rungs)
    next_dt = result.rungs[-1].dt / 2**0.5
    assert result.notes == (
        f"ladder stopped at dt = {next_dt:.4g} s: a run would take more than max_steps = 1000 steps",
    )


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        (
            {"integrator": "dp54"},
            "integrator 'dp54' is adaptive: it chooses its own steps, so it has no largest stable dt "
            "(largest_stable_dt applies to fixed-step integrators)",
        ),
        ({"horizon": -1.0}, "horizon must be a positive number, got -1.0"),
        ({"dt_max": 2.0}, "dt_max must be at most the horizon (1 s), got 2 s"),
        ({"ratio": 1.0}, "ratio must be greater than 1, got 1"),
        ({"energy_bound": 0.0}, "energy_bound must be a positive number, got 0.0"),
        ({"max_steps": 0}, "max_steps must be a positive integer, got 0"),
        ({"q0": [0.0, 0.0]}, "q0 must have shape (1,), got (2,)"),
    ],
)
def test_ladder_arguments_are_checked(kwargs, message, robot):
    arguments = {"integrator": "rk4", "q0": [0.1], "horizon": 1.0, **kwargs}
    with pytest.raises(ms.InvalidArgumentError, match=f"^{re.escape(message)}$"):
        ms.largest_stable_dt(robot("pendulum"), arguments.pop("integrator"), arguments.pop("q0"), [0.0], **arguments)


# ---- a free rigid body spinning near its intermediate axis ----------------------------------------------------
SPIN = np.array([1e-3, 20.0, 1e-3])  # body-frame angular velocity [rad/s]: 20 rad/s about y, the middle axis


@pytest.fixture(scope="module")
def body_in_space() -> ms.Robot:
    body = ms.load_robot("free_body")  # a fresh copy: the session's cached free_body keeps its gravity
    body.model.gravity.linear = np.zeros(3)
    return body


def half_tumble_period(inertia: np.ndarray, omega: np.ndarray) -> float:
    """Time between successive sign changes of the intermediate-axis rate: 2K(k)/s (Landau & Lifshitz §37).

    For I1 < I2 < I3 and M² > 2 E I2 (here: the spin favours the largest axis slightly), ω2 = A sn(s t, k) with
    s² = (I3 - I2)(M² - 2E I1) / (I1 I2 I3) and k² = (I2 - I1)(2E I3 - M²) / ((I3 - I2)(M² - 2E I1)).
    """
    i1, i2, i3 = inertia
    two_e, m2 = omega @ (inertia * omega), np.sum((inertia * omega) ** 2)
    assert i1 < i2 < i3 and m2 > two_e * i2
    s = math.sqrt((i3 - i2) * (m2 - two_e * i1) / (i1 * i2 * i3))
    k2 = (i2 - i1) * (two_e * i3 - m2) / ((i3 - i2) * (m2 - two_e * i1))
    return 2 * ellipk(k2) / s


def sign_changes(t: np.ndarray, x: np.ndarray) -> np.ndarray:
    """Times where x changes sign, by linear interpolation between samples."""
    i = np.flatnonzero(np.sign(x[1:]) != np.sign(x[:-1]))
    return t[i] - x[i] * (t[i + 1] - t[i]) / (x[i + 1] - x[i])


def momentum_drift(body: ms.Robot, traj: ms.Trajectory) -> float:
    """max ‖L(t) - L(0)‖ / ‖L(0)‖ of the world-frame angular momentum R I ω (the centre of mass is at rest)."""
    inertia = body.model.inertias[1].inertia
    L = np.array([rotation(q) @ inertia @ v[3:] for q, v in zip(traj.q, traj.v, strict=True)])
    return float(np.max(np.linalg.norm(L - L[0], axis=1)) / np.linalg.norm(L[0]))


@pytest.mark.parametrize(
    ("name", "options"), [("rk4", {"dt": 1e-3}), ("dp54", {"dt": 1e-3, "rtol": 1e-10, "atol": 1e-10})]
)
def test_free_body_tumbles_with_the_elliptic_period_and_conserves_energy_and_momentum(body_in_space, name, options):
    body = body_in_space
    inertia = np.diag(body.model.inertias[1].inertia)
    assert np.allclose(body.model.inertias[1].inertia, np.diag(inertia))  # principal axes = body axes
    v0 = np.concatenate([np.zeros(3), SPIN])
    traj = ms.simulate(body, body.neutral(), v0, duration=5.0, integrator=name, **options)
    half = half_tumble_period(inertia, SPIN)  # 2.38 s: two sign reversals within 5 s
    crossings = sign_changes(traj.t, traj.v[:, 4])
    assert len(crossings) == 2 and traj.v[:, 4].min() < -0.999 * SPIN[1]  # it flips over completely
    # The period is ~ln(1/ε)/s: a relative state error δ shifts it by ~δ/(s ln(1/ε)); both runs keep δ < 1e-6.
    assert crossings[1] - crossings[0] == pytest.approx(half, rel=1e-5)
    energy = traj.total_energy
    # RK4's local error is ~(ωh)⁵/120 ≈ 3e-11 relative per step at ωh = 0.02, and only the ~300 steps of each
    # flip (where the body-frame rates change fast) contribute much: ~1e-8 at worst if they all added up. dp54
    # holds each step's error to 1e-10 over ~1000 steps. The same reasoning bounds the momentum's drift.
    assert np.max(np.abs(energy - energy[0])) < 1e-8 * energy[0]
    assert momentum_drift(body, traj) < 1e-7


def test_rk4_energy_and_momentum_errors_shrink_at_fourth_order_on_the_tumbling_body(body_in_space):
    body = body_in_space
    v0 = np.concatenate([np.zeros(3), SPIN])
    errors = []
    for dt in (2e-3, 1e-3):
        traj = ms.simulate(body, body.neutral(), v0, duration=3.0, dt=dt, integrator="rk4")
        errors.append((traj.max_abs_energy_error, momentum_drift(body, traj)))
    (e1, l1), (e2, l2) = errors
    assert e1 / e2 > 2**4 * 0.7 and l1 / l2 > 2**4 * 0.7  # order 4 (ratio 16), with room for the pre-asymptotics


def test_implicit_midpoint_keeps_the_free_bodys_energy_at_any_step(body_in_space):
    """Without gravity the body-frame velocity obeys v' = f(v) with f quadratic and M constant: the midpoint
    rule conserves every quadratic invariant of such a flow exactly, so kinetic energy and |body momentum| are
    off only by what Newton leaves: at most 1e-10 (1 + |x|∞) ≈ 2e-9 rad/s on the midpoint velocity per step, i.e.
    ~2e-10 of the energy; even if all 1000 steps added up that is 2e-7, while a second-order method that does
    not conserve them errs by O((ωh)²) = O(4e-2) at ωh = 0.2. The world-frame momentum's direction (which depends
    on how q is advanced) is off at second order."""
    body = body_in_space
    v0 = np.concatenate([np.zeros(3), SPIN])
    inertia = body.model.inertias[1].inertia
    drifts = []
    for dt in (1e-2, 5e-3):
        traj = ms.simulate(body, body.neutral(), v0, duration=5.0, dt=dt, integrator="implicit_midpoint")
        energy = traj.total_energy
        assert np.max(np.abs(energy - energy[0])) < 3e-7 * energy[0]
        body_momentum = np.linalg.norm(traj.v[:, 3:] @ inertia, axis=1)
        assert np.max(np.abs(body_momentum - body_momentum[0])) < 3e-7 * body_momentum[0]
        assert traj.v[:, 4].min() < -0.99 * SPIN[1]  # it still tumbles
        drifts.append(momentum_drift(body, traj))
    assert drifts[0] / drifts[1] == pytest.approx(4.0, rel=0.1)  # order 2


@pytest.mark.parametrize("name", ["euler", "semi_implicit_euler"])
def test_euler_and_semi_implicit_euler_gain_exactly_half_h_squared_a_m_a_per_step(body_in_space, name):
    """With no gravity a = a(v) and M is constant in the body frame, so both methods take v+ = v + h a(v), and
    T+ - T = h vᵀ M a + ½ h² aᵀ M a = ½ h² aᵀ M a > 0 (vᵀ M a = -vᵀ C v = 0): the energy rises at every step,
    by an amount computed here from each sample with Pinocchio's CRBA and ABA."""
    body = body_in_space
    v0 = np.concatenate([np.zeros(3), SPIN])
    h = 1e-3
    traj = ms.simulate(body, body.neutral(), v0, duration=5.0, dt=h, integrator=name)
    M = body.mass_matrix(traj.q[0])
    np.testing.assert_allclose(body.mass_matrix(traj.q[-1]), M, atol=1e-15)
    accelerations = np.array(
        [body.forward_dynamics(q, v, np.zeros(6)) for q, v in zip(traj.q[:-1], traj.v[:-1], strict=True)]
    )
    predicted = 0.5 * h**2 * np.einsum("ni,ij,nj->n", accelerations, M, accelerations)
    gained = np.diff(traj.total_energy)
    np.testing.assert_allclose(gained, predicted, rtol=1e-6, atol=1e-14 * traj.total_energy[0])
    assert np.all(gained > 0)
    drift = traj.total_energy[-1] / traj.total_energy[0] - 1
    assert drift > 1e-2  # not a round-off effect: a few per cent over one tumble
    assert momentum_drift(body, traj) > 1e-3


# ---- tiny/huge inertia ratios -------------------------------------------------------------------------------------
def test_stiffness_ratio_grows_as_the_inverse_square_of_the_tips_inertia(write_urdf):
    """Tip inertia s times the upper link's (mass too): the elbow damping's rate grows as 1/s and gravity's pull
    on the overdamped tip shrinks as s, so the ratio scales as 1/s² (1e4 between s = 1e-4 and 1e-6)."""
    ratios = {}
    for scale in (1e-4, 1e-6):
        arm = tip_arm(write_urdf, scale)
        stiffness = ms.stiffness_ratio(arm, [0.0, 0.0], [0.0, 0.0])
        constants = {"m1": 1.0, "c1": 0.5, "i1": 0.01, "m2": scale, "c2": 0.5, "i2": 0.01 * scale, "l1": 1.0}
        fast, slow = two_link_rates({**constants, "d1": 0.05, "d2": 0.05})
        assert stiffness.fastest.real == pytest.approx(-fast, rel=1e-4)
        assert stiffness.slowest.real == pytest.approx(-slow, rel=1e-3)
        ratios[scale] = stiffness.ratio
    assert ratios[1e-6] > 1e9
    assert ratios[1e-6] / ratios[1e-4] == pytest.approx(1e4, rel=2e-3)


def pinocchio_reference(system: ms.Robot, q0: np.ndarray, horizon: float, method: str) -> np.ndarray:
    """(q, v) at the horizon by scipy on Pinocchio's ABA with the damping torque -D v: no multibody_sim stepping."""
    model, data, damping = system.model, system.model.createData(), system.damping
    nv = system.nv

    def field(_t: float, y: np.ndarray) -> np.ndarray:
        return np.concatenate([y[nv:], pin.aba(model, data, y[:nv], y[nv:], -damping * y[nv:])])

    solution = solve_ivp(
        field, (0.0, horizon), np.concatenate([q0, np.zeros(nv)]), method=method, rtol=1e-12, atol=1e-13
    )
    assert solution.success
    return solution.y[:, -1]


@pytest.mark.parametrize(
    ("damped", "methods"),
    [
        # Undamped: a mass matrix with condition number 1e6, but not stiff (the tip swings at its own pendulum
        # frequency whatever its mass): every method keeps its order at ordinary steps.
        (False, {"rk4": 4, "semi_implicit_euler": 1, "implicit_midpoint": 2, "variational": 2}),
        # Damped: stiffness ratio 2e9, fast rate 2e5 /s; the A-stable methods keep their order at |hλ| = 400..3000.
        (True, {"implicit_euler": 1, "implicit_midpoint": 2}),
    ],
)
def test_methods_converge_with_inertias_1e6_apart(write_urdf, damped, methods):
    arm = tip_arm(write_urdf, 1e-6, damped=damped)
    q0, horizon = np.array([0.5, -0.3]), 0.5
    reference = pinocchio_reference(arm, q0, horizon, "Radau" if damped else "DOP853")
    steps = [2.0**-k for k in range(6, 10)]
    for name, order in methods.items():
        errors = []
        for dt in steps:
            traj = ms.simulate(arm, q0, np.zeros(2), duration=horizon, dt=dt, integrator=name)
            errors.append(np.max(np.abs(np.concatenate([traj.q[-1], traj.v[-1]]) - reference)))
        slope = np.polyfit(np.log(steps), np.log(errors), 1)[0]
        assert slope == pytest.approx(order, abs=0.15), (name, errors)
        assert errors[-1] < 2e-2  # and the finest step is accurate in absolute terms (the swing is ~1 rad)


# ---- divergence ----------------------------------------------------------------------------------------------------
def test_a_diverging_run_grows_at_the_analytic_rate_keeps_finite_samples_and_names_the_cure(robot):
    """Explicit Euler at h = 2.5/|λ| multiplies the fast mode by 1 + hλ = -1.5 per step."""
    arm = robot("stiff_arm")
    fast, _ = two_link_rates(stiff_arm_constants())
    dt = 2.5 / fast
    with pytest.raises(ms.SimulationError) as caught:
        ms.simulate(arm, STIFF_Q0, [0.0, 0.0], duration=STIFF_HORIZON, dt=dt, integrator="euler")
    error = caught.value
    traj = error.trajectory
    assert error.status == traj.status == "diverged"
    assert all(np.isfinite(getattr(traj, f)).all() for f in ("t", "q", "v", "total_energy", "energy_error"))
    assert traj.t[-1] < STIFF_HORIZON and len(traj) == traj.stats["steps"] + 1
    # The elbow rate, dominated by the fast mode once it has grown, flips sign and grows by 1.5 every step.
    tail = traj.v[-20:, 1]
    assert np.all(np.sign(tail[1:]) == -np.sign(tail[:-1]))
    np.testing.assert_allclose(np.abs(tail[1:] / tail[:-1]), 1.5, rtol=1e-3)
    message = str(error)
    steps = len(traj) - 1
    assert message.startswith(f"diverged at t = {traj.t[-1]:.6g} s (step {steps}): ")
    cure = re.search(r"; try a smaller dt \(now (\S+) s\), or an implicit integrator \(([^)]*)\)$", message)
    assert cure, message
    assert float(cure.group(1)) == pytest.approx(dt, rel=1e-5)
    suggested = cure.group(2).split(", ")
    assert {"implicit_euler", "implicit_midpoint"} <= set(suggested)
    assert all(ms.INTEGRATORS[name].a_stable for name in suggested)


# ---- a million steps -------------------------------------------------------------------------------------------------
@pytest.mark.slow
def test_a_million_steps_energy_drift_matches_the_linear_theory(robot):
    """On the pendulum at small amplitude (ωh = 0.157), over 1e6 steps (5e4 s, ~1.2e5 periods):

    - RK4's energy decays as |R(iωh)|^(2n), R(z) = 1 + z + z²/2 + z³/6 + z⁴/24 (a secular drift: -2 % here);
    - semi-implicit Euler conserves p² + x² - ωh x p exactly (x = ωθ, p = θ'), so E/E0 stays within
      [1/(1 + ωh/2), 1/(1 - ωh/2)] forever and drifts not at all.
    The nonlinearity at θ0 = 0.01 rad changes both by ~θ0²/8 ~ 1e-5 relative.
    """
    pendulum = robot("pendulum")
    omega = math.sqrt(G * 1.0 / (1.0 + 0.001))
    h, n, theta0 = 0.05, 1_000_000, 0.01
    y = omega * h
    rest = pendulum.potential_energy([0.0])
    rk4 = ms.simulate(pendulum, [theta0], [0.0], duration=n * h, dt=h, integrator="rk4", output_dt=1000 * h)
    energy = rk4.total_energy - rest
    steps = np.rint(rk4.t / h)
    gain = abs(1 + 1j * y - y**2 / 2 - 1j * y**3 / 6 + y**4 / 24) ** 2
    np.testing.assert_allclose(energy / energy[0], gain**steps, rtol=1e-4)
    assert energy[-1] / energy[0] < 0.99
    symplectic = ms.simulate(
        pendulum, [theta0], [0.0], duration=n * h, dt=h, integrator="semi_implicit_euler", output_dt=7 * h
    )
    ratio = (symplectic.total_energy - rest) / (symplectic.total_energy[0] - rest)
    low, high = 1 / (1 + y / 2), 1 / (1 - y / 2)
    assert np.all((ratio > low * (1 - 1e-3)) & (ratio < high * (1 + 1e-3)))
    last = ratio[-len(ratio) // 10 :]  # the band is still swept at the end: no drift either way
    assert last.max() > high * (1 - 1e-3) and last.min() < low * (1 + 1e-3)
