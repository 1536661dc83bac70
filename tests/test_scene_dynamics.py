"""Scenes at run time: the physics a scene declares, as simulate() integrates it, and the paths users take to it.

Each test checks against a reference computed independently of the code under test: the analytic eigenfrequencies
of a fixed-free spring chain and RK4's exact amplification of each mode, the closed-form driven harmonic oscillator
(convergence orders of every fixed-step integrator), the regularized friction's closed-form creep and sliding
acceleration, wrench power from Pinocchio's frame velocities integrated by Simpson's rule, constraint forces from a
KKT system solved with numpy, RK4 error estimates from the dynamics' finite-difference Jacobian, frame positions
from Pinocchio's kinematics, and the viewer's mesh placements against the full robot's kinematics and the URDF text.
"""

from __future__ import annotations

import base64
import functools
import importlib.util
import math
import os
import re
import struct
import subprocess
import sys
import xml.etree.ElementTree as ET
import zlib
from collections.abc import Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
import pytest

import multibody_sim as ms
from multibody_sim.catalog import CATALOG, catalog_urdf
from multibody_sim.scenes import shipped_scenes

if sys.version_info >= (3, 11):
    import tomllib
else:  # pragma: no cover - Python 3.10
    import tomli as tomllib

SCENES = shipped_scenes()
LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
RK4_REAL_LIMIT = 2.785  # RK4's stability interval on the negative real axis is (-2.785, 0)
PREFIX = "multibody-sim: error: "


# ---- helpers -------------------------------------------------------------------------------------------------
def scene_tables(name: str) -> dict[str, Any]:
    """A shipped scene's tables, as make_scene takes them (the TOML parsed with the standard library)."""
    return tomllib.loads(SCENES[name].read_text(encoding="utf-8"))


@functools.cache
def shipped_run(name: str) -> tuple[ms.Scene, ms.Trajectory]:
    """(scene, trajectory) of a shipped scene run as it declares itself (full duration), computed once per session."""
    scene = ms.load_scene(SCENES[name])
    return scene, scene.run(progress=False)


def energy_scale(traj: ms.Trajectory) -> float:
    """The energy a run moves around [J]: max T + range of V + max |work| + max dissipated.

    (Not |V|: Pinocchio's potential has an arbitrary zero, e.g. a panda's 90 J at its height.)
    """
    return float(
        traj.kinetic_energy.max()
        + np.ptp(traj.potential_energy)
        + np.abs(traj.work).max()
        + np.abs(traj.dissipated).max()
    )


def fd_jacobian(scene: ms.Scene, q: np.ndarray, v: np.ndarray, t: float) -> np.ndarray:
    """The open-loop state matrix d(ξ', v')/d(ξ, v) at (q, v, t) by central differences in the tangent space.

    Open loop (tau = 0): simulate() holds a controller's torque over each step, so it adds no stiffness inside a step.
    The dynamics are evaluated at time t, as the integrators' stages evaluate them (time-dependent wrenches).
    """
    nv = scene.nv

    def rate(dx: np.ndarray) -> np.ndarray:
        qq, vv = scene.integrate(q, dx[:nv]), v + dx[nv:]
        return np.concatenate([vv, scene.unchecked_forward_dynamics(qq, vv, np.zeros(nv), t)])

    eps = 1e-6
    columns = []
    for i in range(2 * nv):
        dx = np.zeros(2 * nv)
        dx[i] = eps
        columns.append((rate(dx) - rate(-dx)) / (2 * eps))
    return np.array(columns).T


def eigenvalues_along(scene: ms.Scene, traj: ms.Trajectory, count: int = 11) -> np.ndarray:
    """Eigenvalues of the open-loop Jacobian at `count` samples spread over the run."""
    picks = np.linspace(0, len(traj.t) - 1, count).round().astype(int)
    return np.concatenate([np.linalg.eigvals(fd_jacobian(scene, traj.q[i], traj.v[i], traj.t[i])) for i in picks])


def xml_attribute(element: ET.Element, path: str, name: str) -> str:
    """The attribute `name` of the sub-element at `path` (which the files here always have)."""
    found = element.find(path)
    value = None if found is None else found.get(name)
    assert value is not None, f"no {path}/@{name} in <{element.tag} name={element.get('name')!r}>"
    return value


def urdf_mass(source: str, link: str) -> float:
    """A link's mass read from the catalog URDF's text (not from Pinocchio)."""
    root = ET.parse(catalog_urdf(CATALOG[source])[0]).getroot()
    element = next(e for e in root.findall("link") if e.get("name") == link)
    return float(xml_attribute(element, "inertial/mass", "value"))


def order_slope(steps: list[float], errors: list[float]) -> float:
    """Slope of log(error) against log(step): the observed convergence order."""
    return float(np.polyfit(np.log(steps), np.log(errors), 1)[0])


def simpson_cumulative(t: np.ndarray, power: np.ndarray, breaks: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """∫ power dt from t[0] by composite Simpson on a uniform grid, restarted at each break (a kink or jump of the
    integrand), at every second sample from each break.

    Returns:
        (indices, cumulative integral at those indices).
    """
    h = t[1] - t[0]
    cuts = sorted({0, len(t) - 1, *(int(round((b - t[0]) / h)) for b in breaks if t[0] < b < t[-1])})
    indices, values, total = [0], [0.0], 0.0
    for a, b in zip(cuts[:-1], cuts[1:], strict=True):
        assert (b - a) % 2 == 0, f"Simpson's rule needs an even number of intervals between breaks, got {b - a}"
        for k in range(a + 2, b + 1, 2):
            total += h / 3 * (power[k - 2] + 4 * power[k - 1] + power[k])
            indices.append(k)
            values.append(total)
    return np.array(indices), np.array(values)


def wrench_scale(shape: str, spec: dict[str, Any], t: np.ndarray) -> np.ndarray:
    """The documented time shapes of a [[force]], written out here: constant, step, ramp, sine."""
    start = spec.get("start", 0.0)
    on = t >= start
    if shape == "constant":
        return np.ones_like(t)
    if shape == "step":
        return on * 1.0
    if shape == "ramp":
        return np.clip((t - start) / spec.get("ramp_time", 1.0), 0.0, 1.0)
    return np.where(on, np.sin(2 * np.pi * spec.get("frequency", 1.0) * (t - start) + spec.get("phase", 0.0)), 0.0)


def rk4_amplification(z: complex) -> complex:
    """RK4's stability function R(z) = 1 + z + z²/2 + z³/6 + z⁴/24."""
    return 1 + z + z**2 / 2 + z**3 / 6 + z**4 / 24


# ---- springs: the fixed-free chain ---------------------------------------------------------------------------
def undamped_spring_chain(**changes: Any) -> tuple[ms.Scene, float, float, int]:
    """The shipped spring_chain scene with its damping switched off (make_scene), and (k, m, N) from the files."""
    tables = scene_tables("spring_chain")
    stiffness = {settings["stiffness"] for settings in tables["joints"].values()}
    for settings in tables["joints"].values():
        settings["damping"] = 0.0
    tables.update(changes)
    (k,) = stiffness  # one spring constant for the whole chain
    n = len(tables["joints"])
    return ms.make_scene(**tables), k, urdf_mass("spring_chain", "cart1"), n


def chain_frequencies(k: float, m: float, n: int) -> np.ndarray:
    """Fixed-free chain of n masses m and springs k: ω_j = 2 √(k/m) sin((2j−1)π / (2(2n+1))), j = 1..n."""
    j = np.arange(1, n + 1)
    return 2 * np.sqrt(k / m) * np.sin((2 * j - 1) * np.pi / (2 * (2 * n + 1)))


def chain_matrices(k: float, m: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """(M, K) in the joints' coordinates (each cart relative to the previous one), built by hand.

    Cart i sits at x_i = Σ_{j≤i} q_j (plus constants), so T = ½ m |L v|² with L lower-triangular ones, and each
    spring stretches by its own joint's q: V = ½ k |q|².
    """
    lower = np.tril(np.ones((n, n)))
    return m * lower.T @ lower, k * np.eye(n)


def rk4_energy_drift(M: np.ndarray, K: np.ndarray, displacement: np.ndarray, h: float, steps: np.ndarray) -> np.ndarray:
    """RK4's energy error on M x'' + K x = 0 from rest at `displacement`, after each number of steps.

    Each mode's energy is multiplied by |R(iω_j h)|² per step, exactly: in scaled modal coordinates (ω η, η') a
    mode's RK4 map is a normal matrix, so it scales the energy by |R|² whatever the phase. The error after n steps
    is Σ_j E_j (|R(iω_j h)|^(2n) − 1), E_j the modal energies of the start.
    """
    chol = np.linalg.cholesky(M)
    omega2, modes = np.linalg.eigh(np.linalg.solve(chol, np.linalg.solve(chol, K).T))
    shapes = np.linalg.solve(chol.T, modes)  # M-orthonormal mode shapes
    modal_energy = 0.5 * omega2 * (shapes.T @ M @ displacement) ** 2
    gain = np.abs(rk4_amplification(1j * np.sqrt(omega2)[None, :] * h)) ** (2 * steps[:, None])
    return ((gain - 1) * modal_energy).sum(axis=1)


def test_spring_chain_linearization_has_the_analytic_chain_frequencies() -> None:
    scene, k, m, n = undamped_spring_chain()
    omega = chain_frequencies(k, m, n)
    q, v = np.zeros(n), np.zeros(n)
    # The continuous system: eigenvalues ±iω_j, nothing real (no damping left).
    lam = np.linalg.eigvals(ms.linearization(scene, q, v))
    np.testing.assert_allclose(np.abs(lam.real), 0.0, atol=1e-9 * omega.max())
    np.testing.assert_allclose(np.sort(lam.imag[lam.imag > 0]), omega, rtol=1e-10)
    # One RK4 step of h: its eigenvalues are RK4's amplification R(±iω_j h) exactly (a linear system), which agrees
    # with the exact flow exp(±iω_j h) to RK4's local error, |θ|^5/120 at θ = ω_j h.
    h = 1e-3
    mu = np.linalg.eigvals(ms.linearize(scene, q, v, np.zeros(n), h, integrator="rk4").A)
    for w in omega:
        for z in (1j * w * h, -1j * w * h):
            nearest = mu[np.argmin(np.abs(mu - rk4_amplification(z)))]
            assert abs(nearest - rk4_amplification(z)) < 1e-12
            assert abs(nearest - np.exp(z)) < 1.05 * abs(z) ** 5 / 120
            assert abs(nearest - np.exp(z)) > 0.5 * abs(z) ** 5 / 120  # RK4's own error, not another method's
    # Implicit midpoint: the Cayley map (1 + iθ/2)/(1 − iθ/2), on the unit circle: no amplitude error at any step.
    h = 2e-3
    mu = np.linalg.eigvals(ms.linearize(scene, q, v, np.zeros(n), h, integrator="implicit_midpoint").A)
    np.testing.assert_allclose(np.abs(mu), 1.0, atol=1e-9)
    expected = np.concatenate([(1 + 0.5j * omega * h) / (1 - 0.5j * omega * h)] * 2)
    expected[n:] = expected[n:].conj()
    for value in expected:
        assert np.abs(mu - value).min() < 1e-9


def test_spring_ledger_entries_are_the_springs_stored_energy_and_rk4_drifts_as_predicted() -> None:
    scene, k, m, n = undamped_spring_chain()
    h, duration = 1e-3, 1.0
    traj = ms.simulate(scene, scene.q0, scene.v0, duration=duration, dt=h, integrator="rk4", output_dt=0.01)
    assert traj.status == "completed"
    # Each spring's ledger entry (kind "potential") is ½ k q_j² of the trajectory's own q.
    stored = 0.5 * k * traj.q**2
    for j in range(n):
        entry = traj.ledger[f"spring:slider{j + 1}"]
        assert entry.kind == "potential"
        np.testing.assert_allclose(entry.energy, stored[:, j], rtol=1e-13, atol=1e-300)
    # V is the springs' energy (gravity is off), and T is ½ vᵀ M v with M built by hand.
    M, K = chain_matrices(k, m, n)
    np.testing.assert_allclose(traj.potential_energy, stored.sum(axis=1), rtol=1e-13)
    np.testing.assert_allclose(traj.kinetic_energy, 0.5 * np.einsum("ti,ij,tj->t", traj.v, M, traj.v), rtol=1e-12)
    # RK4 on this linear system multiplies each mode's energy by |R(iω_j h)|² per step, exactly.
    predicted = rk4_energy_drift(M, K, scene.q0, h, np.round(traj.t / h))
    assert abs(predicted[-1]) > 1e-8 * traj.total_energy[0]  # a drift worth comparing
    np.testing.assert_allclose(traj.energy_error, predicted, rtol=1e-6, atol=1e-14 * traj.total_energy[0])


def test_spring_chain_potential_adds_springs_and_gravity() -> None:
    """With gravity along the chain, V = Σ ½ k q_j² + Σ_i m g x_i, cart i at x_i = 0.3 i + Σ_{j≤i} q_j."""
    g = 9.81
    scene, k, m, n = undamped_spring_chain(gravity=[-g, 0.0, 0.0])
    traj = ms.simulate(scene, scene.q0, scene.v0, duration=0.05, dt=1e-3, output_dt=0.01)
    positions = 0.3 * np.arange(1, n + 1) + np.cumsum(traj.q, axis=1)  # URDF: carts 0.3 m apart at q = 0
    expected = 0.5 * k * (traj.q**2).sum(axis=1) + m * g * positions.sum(axis=1)
    np.testing.assert_allclose(traj.potential_energy, expected, rtol=1e-12)
    springs = sum(traj.ledger[f"spring:slider{j + 1}"].energy for j in range(n))
    np.testing.assert_allclose(springs, 0.5 * k * (traj.q**2).sum(axis=1), rtol=1e-13)
    # Gravity only moves the equilibrium, to K q* = −∂V_g/∂q (∂V_g/∂q_j = m g (number of carts from j on)): the
    # energy error is RK4's modal drift about q*.
    M, K = chain_matrices(k, m, n)
    equilibrium = np.linalg.solve(K, -m * g * np.arange(n, 0, -1.0))
    predicted = rk4_energy_drift(M, K, scene.q0 - equilibrium, 1e-3, np.round(traj.t / 1e-3))
    np.testing.assert_allclose(traj.energy_error, predicted, rtol=1e-6, atol=1e-14 * energy_scale(traj))


def test_shipped_spring_chain_conserves_energy_with_implicit_midpoint() -> None:
    """Implicit midpoint conserves every quadratic invariant of a linear system; the damping ledger's midpoint rule
    integrates d v_mid² exactly as the step removes it: only Newton's tolerance and round-off remain."""
    scene, traj = shipped_run("spring_chain")
    assert traj.metadata["integrator"] == "implicit_midpoint"
    assert traj.dissipated[-1] > 0.1 * traj.total_energy[0]  # the shipped chain is damped: the ledger has work to do
    assert np.abs(traj.energy_error).max() < 1e-10 * energy_scale(traj)


# ---- time-dependent forces: the driven harmonic oscillator ---------------------------------------------------
K_DRIVEN, F0, FREQ, PHASE = 100.0, 2.0, 3.0, 0.4
X0, V0 = 0.02, -0.1


@functools.cache
def driven_oscillator() -> tuple[ms.Scene, float]:
    """point_robot's puck (1 kg, M = I) on a spring along x, driven by F0 sin(2π f t + φ) along x; and its mass."""
    scene = ms.make_scene(
        robot={"source": "point_robot"},
        joints={"x": {"stiffness": K_DRIVEN}},
        force=[
            {
                "name": "drive",
                "frame": "puck",
                "force": [F0, 0.0, 0.0],
                "shape": "sine",
                "frequency": FREQ,
                "phase": PHASE,
            }
        ],
    )
    return scene, urdf_mass("point_robot", "puck")


def driven_exact(t: np.ndarray, m: float) -> tuple[np.ndarray, np.ndarray]:
    """m x'' + k x = F0 sin(Ω t + φ), x(0) = X0, x'(0) = V0: homogeneous part plus the particular solution."""
    w, big = math.sqrt(K_DRIVEN / m), 2 * math.pi * FREQ
    p = F0 / (m * (w * w - big * big))
    a = X0 - p * math.sin(PHASE)
    b = (V0 - p * big * math.cos(PHASE)) / w
    x = a * np.cos(w * t) + b * np.sin(w * t) + p * np.sin(big * t + PHASE)
    v = -a * w * np.sin(w * t) + b * w * np.cos(w * t) + p * big * np.cos(big * t + PHASE)
    return x, v


def driven_error(traj: ms.Trajectory, m: float) -> float:
    """max over samples of |x − x_exact| and |v − v_exact| / ω (both in metres); y must stay at rest."""
    assert not traj.q[:, 1].any() and not traj.v[:, 1].any()
    x, v = driven_exact(traj.t, m)
    return float(max(np.abs(traj.q[:, 0] - x).max(), np.abs(traj.v[:, 0] - v).max() / math.sqrt(K_DRIVEN / m)))


# Step ladders in the asymptotic range of each method, above round-off: errors from ~1e-4 down to ~1e-8.
@pytest.mark.parametrize(
    ("integrator", "order", "steps"),
    [
        ("rk4", 4, [1 / 25, 1 / 50, 1 / 100, 1 / 200]),
        ("midpoint", 2, [1 / 100, 1 / 200, 1 / 400, 1 / 800]),
        ("euler", 1, [1 / 400, 1 / 800, 1 / 1600, 1 / 3200]),
        ("semi_implicit_euler", 1, [1 / 400, 1 / 800, 1 / 1600, 1 / 3200]),
        ("implicit_midpoint", 2, [1 / 100, 1 / 200, 1 / 400, 1 / 800]),
    ],
)
def test_driven_oscillator_converges_at_each_methods_order(integrator: str, order: int, steps: list[float]) -> None:
    """A force evaluated only at step starts would cap every method at order 1: the stages must see their times."""
    scene, m = driven_oscillator()
    errors = [
        driven_error(
            ms.simulate(scene, [X0, 0.0], [V0, 0.0], duration=1.0, dt=h, integrator=integrator, output_dt=0.2), m
        )
        for h in steps
    ]
    assert abs(order_slope(steps, errors) - order) < 0.15, errors


# Where each method evaluates the dynamics within a step, as fractions of the step (its Butcher nodes c; implicit
# midpoint at the midpoint; semi-implicit Euler at the start).
STAGE_NODES = {
    "euler": {0.0},
    "semi_implicit_euler": {0.0},
    "midpoint": {0.0, 0.5},
    "rk4": {0.0, 0.5, 1.0},
    "implicit_midpoint": {0.5},
}


@pytest.mark.parametrize("integrator", sorted(STAGE_NODES))
def test_time_dependent_forces_are_evaluated_at_the_stage_times(integrator: str) -> None:
    """A callable shape (the API's form of a [[force]] shape) records the times it is asked for: t_n + c_i h."""
    asked: list[float] = []

    def shape(t: float) -> float:
        asked.append(t)
        return math.sin(2 * math.pi * FREQ * t)

    scene = ms.make_scene(
        robot={"source": "point_robot"},
        joints={"x": {"stiffness": K_DRIVEN}},
        force=[{"name": "drive", "frame": "puck", "force": [F0, 0.0, 0.0], "shape": shape}],
    )
    h = 1 / 64  # a power of two: the stage times' fractions of the step are exact
    ms.simulate(scene, [X0, 0.0], [V0, 0.0], duration=4 * h, dt=h, integrator=integrator)
    offsets = np.array(asked) / h - np.floor(np.array(asked) / h)  # position within the step, in [0, 1)
    seen = set(np.round(offsets, 12)) - {0.0}  # step starts are also asked at the samples (ledger, records)
    assert seen == STAGE_NODES[integrator] - {0.0, 1.0}


def test_driven_oscillator_dp54_meets_its_tolerance() -> None:
    """Each accepted step's local error is at most atol + rtol |y|; on this neutrally stable oscillator errors add up
    at most linearly, so the global error stays below (number of steps) x (atol + rtol max |y|)."""
    scene, m = driven_oscillator()
    errors = []
    for tol in (1e-8, 1e-10):
        traj = ms.simulate(
            scene, [X0, 0.0], [V0, 0.0], duration=1.0, dt=1e-2, integrator="dp54", rtol=tol, atol=tol, output_dt=0.01
        )
        size = max(np.abs(traj.q).max(), np.abs(traj.v).max())
        errors.append(driven_error(traj, m))
        assert errors[-1] < traj.stats["steps"] * (tol + tol * size)
    assert errors[1] < errors[0] / 10  # tighter tolerance, smaller error: the control is doing the work


def test_a_wrench_on_a_one_dof_scene() -> None:
    """The single slider of the brief (spring_chain with four joints locked, nv = 1) with a spring and a sine force."""
    lock = {f"slider{i}": 0.0 for i in range(1, 5)}
    force = [{"name": "drive", "frame": "cart5", "force": [F0, 0.0, 0.0], "shape": "sine", "frequency": FREQ}]
    scene = ms.make_scene(
        robot={"source": "spring_chain"},
        gravity=[0, 0, 0],
        lock=lock,
        joints={"slider5": {"stiffness": K_DRIVEN}},
        force=force,
    )
    assert scene.nv == 1
    m = urdf_mass("spring_chain", "cart5")
    # From rest at the spring's rest position: x = p (sin Ω t − (Ω/ω) sin ω t), p = F0 / (m (ω² − Ω²)).
    traj = ms.simulate(scene, [0.0], [0.0], duration=0.5, dt=1e-3, output_dt=0.01)
    w, big = math.sqrt(K_DRIVEN / m), 2 * math.pi * FREQ
    p = F0 / (m * (w * w - big * big))
    exact = -p * big / w * np.sin(w * traj.t) + p * np.sin(big * traj.t)
    np.testing.assert_allclose(traj.q[:, 0], exact, atol=1e-9)


# ---- friction ------------------------------------------------------------------------------------------------
def friction_scene(friction: float, velocity: float, push: float) -> ms.Scene:
    """point_robot's 1 kg puck with Coulomb friction on x and a constant world force along x (gravity does no work
    on the horizontal table)."""
    return ms.make_scene(
        robot={"source": "point_robot"},
        friction_velocity=velocity,
        joints={"x": {"friction": friction}},
        force=[{"name": "push", "frame": "puck", "force": [push, 0.0, 0.0]}],
    )


def test_friction_below_breakaway_creeps_at_the_regularized_velocity() -> None:
    fc, vs, push = 1.0, 0.01, 0.5
    scene = friction_scene(fc, vs, push)
    m = urdf_mass("point_robot", "puck")
    # Near the creep velocity the friction is a damper of slope fc (1 − (push/fc)²)/vs: time constant 13 ms, so
    # 0.3 s is 22 time constants (e^-22 ~ 3e-10 of the start left); RK4 keeps an autonomous ODE's equilibria exactly.
    traj = ms.simulate(scene, [0.0, 0.0], [0.0, 0.0], duration=0.3, dt=1e-3, output_dt=1e-3)
    creep = vs * math.atanh(push / fc)
    assert traj.v[-1, 0] == pytest.approx(creep, rel=1e-7)
    assert not traj.v[:, 1].any()
    # The friction's ledger entry is the dissipated energy ∫ fc v tanh(v/vs) dt: never decreasing, and equal to
    # Simpson's rule over the samples.
    friction = traj.ledger["friction:x"]
    assert friction.kind == "dissipated"
    assert np.diff(friction.energy).min() >= -1e-15
    power = fc * traj.v[:, 0] * np.tanh(traj.v[:, 0] / vs)
    index, integral = simpson_cumulative(traj.t, power, [])
    # Simpson's error here is dominated by the start, where v' jumps from 0 and tanh(v/vs) bends on a 10 ms scale.
    np.testing.assert_allclose(friction.energy[index], integral, rtol=1e-6, atol=1e-10)
    # The push's work is push · x; the balance is T = work − dissipated.
    np.testing.assert_allclose(traj.ledger["force:push"].energy, push * traj.q[:, 0], rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(traj.kinetic_energy, 0.5 * m * traj.v[:, 0] ** 2, rtol=1e-12)
    # RK4's accuracy on the fastest mode, the friction's slope λ = fc/(m vs) = 100 /s (see the every-scene test).
    rate = fc / (m * vs)
    assert np.abs(traj.energy_error).max() < energy_scale(traj) * 0.3 * rate * (1e-3 * rate) ** 4 / 60


def test_friction_above_breakaway_slides_at_the_net_acceleration() -> None:
    fc, vs, push = 1.0, 0.01, 2.0
    m = urdf_mass("point_robot", "puck")
    traj = ms.simulate(friction_scene(fc, vs, push), [0.0, 0.0], [0.0, 0.0], duration=0.5, dt=1e-3, output_dt=0.01)
    # Once v ≫ vs, tanh(v/vs) = 1 to round-off and the puck accelerates uniformly at (push − fc)/m.
    assert traj.v[-11, 0] > 30 * vs
    acceleration = (traj.v[-1, 0] - traj.v[-11, 0]) / (traj.t[-1] - traj.t[-11])
    assert acceleration == pytest.approx((push - fc) / m, rel=1e-9)
    assert np.diff(traj.ledger["friction:x"].energy).min() >= 0.0
    assert traj.dissipated[-1] == pytest.approx(traj.ledger["friction:x"].energy[-1])


def test_stiff_friction_needs_an_implicit_method() -> None:
    """vs = 1e-6 m/s: the friction's slope fc/(m vs) = 1e6 /s puts h|λ| = 1000 at h = 1 ms, far outside RK4's
    stability interval (2.785). The tanh saturates, so RK4 does not blow up but settles on a wrong state; implicit
    Euler's fixed point is the exact steady state, which it reaches (its own decay factor is 1/(1 + h|λ|))."""
    fc, vs, push = 1.0, 1e-6, 0.5
    scene = friction_scene(fc, vs, push)
    m = urdf_mass("point_robot", "puck")
    assert 1e-3 * fc / (m * vs) > 100 * RK4_REAL_LIMIT
    creep = vs * math.atanh(push / fc)
    implicit = ms.simulate(scene, [0.0, 0.0], [0.0, 0.0], duration=0.2, dt=1e-3, integrator="implicit_euler")
    assert implicit.v[-1, 0] == pytest.approx(creep, rel=1e-6)
    try:
        explicit = ms.simulate(scene, [0.0, 0.0], [0.0, 0.0], duration=0.2, dt=1e-3, integrator="rk4")
    except ms.SimulationError as exc:  # diverging would show the same thing
        assert exc.status == "diverged"
    else:
        assert abs(explicit.v[-1, 0] - creep) > 10 * creep  # measured: 1.7e-4 m/s, 300 times the creep


# ---- external wrenches: the ledger's work against frame velocities ---------------------------------------------
@pytest.mark.parametrize("name", ["free_body_torqued", "ur5_ceiling_push"])
def test_wrench_work_is_the_integral_of_the_frame_power(name: str) -> None:
    """force:<name> = ∫ w(t) · V_frame dt, with V_frame Pinocchio's frame velocity in the wrench's convention (world:
    world-aligned axes at the frame's origin; local: the frame's own axes), integrated by Simpson's rule over a
    1 ms output grid restarted at the shapes' kinks and jumps."""
    scene = ms.load_scene(SCENES[name])
    traj = scene.run(progress=False, output_dt=1e-3)
    model, data = scene.model, scene.model.createData()
    forces = scene_tables(name)["force"]
    assert {f.get("reference", "world") for f in forces} == {"world", "local"}
    for spec in forces:
        frame = model.getFrameId(spec["frame"])
        reference = LWA if spec.get("reference", "world") == "world" else pin.ReferenceFrame.LOCAL
        wrench = np.concatenate([spec.get("force", [0.0, 0.0, 0.0]), spec.get("torque", [0.0, 0.0, 0.0])])
        power = np.empty(len(traj.t))
        for i, (q, v) in enumerate(zip(traj.q, traj.v, strict=True)):
            pin.forwardKinematics(model, data, q, v)
            power[i] = wrench @ pin.getFrameVelocity(model, data, frame, reference).vector
        shape = spec.get("shape", "constant")
        power *= wrench_scale(shape, spec, traj.t)
        breaks = [spec.get("start", 0.0)] + ([spec["start"] + spec["ramp_time"]] if shape == "ramp" else [])
        index, work = simpson_cumulative(traj.t, power, breaks)
        entry = traj.ledger[f"force:{spec['name']}"]
        assert entry.kind == "work"
        assert np.abs(work).max() > 0.01  # each wrench does real work in these scenes
        # Simpson's and RK4's quadratures agree to O(h^4); a step's jump costs RK4 one stage's weight (h/6) of the
        # power at the switch, zero here (the free box does not move along the thrust before it starts).
        np.testing.assert_allclose(entry.energy[index], work, rtol=0, atol=1e-7 * np.abs(work).max())


# ---- constraints: the four-bar linkage and the pinned ur5 ------------------------------------------------------
def rk4_state_error(scene: ms.Scene, traj: ms.Trajectory, dt: float) -> tuple[float, float]:
    """(ω, T ω (hω)^4 / 120): the fastest rate of the dynamics along the run and RK4's relative global error scale.

    RK4's local error on y' = λy is |hλ|^5/120 of the state; over T/h steps that adds up to T|λ|(h|λ|)^4/120.
    """
    omega = float(np.abs(eigenvalues_along(scene, traj)).max())
    duration = float(traj.t[-1] - traj.t[0])
    return omega, duration * omega * (dt * omega) ** 4 / 120


def kkt_constraint_forces(scene: ms.Scene, q: np.ndarray, v: np.ndarray) -> np.ndarray:
    """The four-bar's loop force from M a + h = Jᵀ λ and J a + J̇ v = 0 solved with numpy, in the plane (y, z).

    J is the difference of the two pins' world-aligned Jacobians (force on the coupler, the first frame's body);
    the out-of-plane row (x) is identically satisfied and dropped; the Baumgarte terms act on a drift of ~1e-9 m
    (10 ⋅ 1e-9 m/s² against g) and are left out.
    """
    model, data = scene.model, scene.model.createData()
    tip1, tip2 = model.getFrameId("coupler_tip"), model.getFrameId("rocker_tip")
    pin.forwardKinematics(model, data, q, v, np.zeros(scene.nv))
    pin.computeJointJacobians(model, data, q)
    J = (pin.getFrameJacobian(model, data, tip1, LWA) - pin.getFrameJacobian(model, data, tip2, LWA))[1:3]
    gamma = (
        pin.getFrameClassicalAcceleration(model, data, tip1, LWA).linear
        - pin.getFrameClassicalAcceleration(model, data, tip2, LWA).linear
    )[1:3]
    M = pin.crba(model, data, q)
    M = np.triu(M) + np.triu(M, 1).T
    bias = pin.nonLinearEffects(model, data, q, v)
    kkt = np.block([[M, -J.T], [J, np.zeros((2, 2))]])
    solution = np.linalg.solve(kkt, np.concatenate([-bias, -gamma]))
    return solution[scene.nv :]


def test_four_bar_closes_its_loop_and_conserves_energy() -> None:
    scene, traj = shipped_run("four_bar")
    assert traj.status == "completed" and scene.nv == 3
    dt = traj.metadata["options"]["dt"]
    record = traj.constraints["loop"]
    n = len(traj.t)
    assert record.force.shape == (n, 3) and record.drift.shape == (n,) and record.velocity_drift.shape == (n,)
    # The exact motion keeps the pins together, so every bit of drift is integration error: at most the pins' lever
    # arms (crank + coupler, coupler, rocker: a + b + c = 0.75 m, read from the URDF below) times RK4's global error
    # in the angles, T ω (hω)^4/120 relative; ω from the dynamics' Jacobian. Baumgarte only pulls it back further.
    omega, relative = rk4_state_error(scene, traj, dt)
    root = ET.parse(catalog_urdf(CATALOG["four_bar"])[0]).getroot()
    arms = sum(
        float(xml_attribute(j, "origin", "xyz").split()[1])
        for j in root.findall("joint")
        if j.get("name") in ("coupler_joint", "coupler_tip_joint", "rocker_tip_joint")
    )
    swing = np.ptp(traj.q, axis=0).max()  # the angles' range [rad]
    assert omega * dt < 0.1 and 0.7 < arms < 0.8
    assert record.drift.max() < arms * swing * relative
    # The pins also coincide when checked with Pinocchio's kinematics at the samples (the record is no fiction).
    data = scene.model.createData()
    gaps = []
    for q in traj.q:
        pin.framesForwardKinematics(scene.model, data, q)
        gaps.append(
            np.linalg.norm(
                data.oMf[scene.model.getFrameId("coupler_tip")].translation
                - data.oMf[scene.model.getFrameId("rocker_tip")].translation
            )
        )
    np.testing.assert_allclose(record.drift, gaps, rtol=1e-6, atol=1e-15)
    # No damping: H is conserved to RK4's accuracy, energy (quadratic in the state) off by at most twice the state's
    # relative error; and halving the step divides the error by ~16.
    scale = energy_scale(traj)
    assert np.abs(traj.energy_error).max() < 2 * relative * scale
    # The constraint's work λ · (J v) vanishes on the constraint manifold (J v = 0): what the ledger reports is RK4's
    # quadrature of it over stages slightly off the manifold, integration error of the same order as the energy's.
    work = traj.ledger["constraint:loop"]
    assert work.kind == "work"
    assert np.abs(work.energy).max() < 2 * relative * scale
    # Halving the step divides all three by ~16 (RK4's order 4): they are integration error, nothing else.
    coarse = scene.run(progress=False, dt=2 * dt)
    ratios = [
        np.abs(coarse.energy_error).max() / np.abs(traj.energy_error).max(),
        coarse.constraints["loop"].drift.max() / record.drift.max(),
        np.abs(coarse.ledger["constraint:loop"].energy).max() / np.abs(work.energy).max(),
    ]
    assert min(ratios) > 2**3.5, ratios


def test_four_bar_constraint_forces_match_the_kkt_system() -> None:
    scene, traj = shipped_run("four_bar")
    record = traj.constraints["loop"]
    # The recorded multipliers are the KKT solution at each sample; the out-of-plane row carries nothing.
    for i in np.linspace(0, len(traj.t) - 1, 9).round().astype(int):
        expected = kkt_constraint_forces(scene, traj.q[i], traj.v[i])
        np.testing.assert_allclose(record.force[i, 1:], expected, rtol=1e-6, atol=1e-6 * np.abs(expected).max())
        assert abs(record.force[i, 0]) < 1e-8 * np.abs(expected).max()


def integrators_that_run(scene: ms.Scene) -> list[str]:
    """Every registered integrator that actually integrates the scene for a few steps."""
    able = []
    for name, method in sorted(ms.INTEGRATORS.items()):
        options = {"rtol": 1e-6, "atol": 1e-6} if method.adaptive else {}
        try:
            ms.simulate(scene, scene.q0, scene.v0, duration=3e-3, dt=1e-3, integrator=name, **options)
        except ms.InvalidArgumentError:
            continue
        able.append(name)
    return able


@pytest.mark.parametrize("integrator", ["implicit_euler", "variational"])
def test_integrators_without_constraints_refuse_the_four_bar(integrator: str) -> None:
    scene = ms.load_scene(SCENES["four_bar"])
    able = integrators_that_run(scene)
    assert "rk4" in able and integrator not in able
    message = (
        f"integrator '{integrator}' needs the dynamics' analytic derivatives, which scene 'four_bar' does not "
        f"provide (it has constraints: loop); use one of: {', '.join(able)}"
    )
    with pytest.raises(ms.InvalidArgumentError, match=re.escape(message)):
        ms.simulate(scene, scene.q0, scene.v0, duration=0.01, dt=1e-3, integrator=integrator)


def test_ur5_pinned_tool_stays_at_its_anchor() -> None:
    scene, traj = shipped_run("ur5_pinned_tool")
    data = scene.model.createData()
    tool = scene.model.getFrameId("tool0")
    pin.framesForwardKinematics(scene.model, data, traj.q[0])
    anchor = data.oMf[tool].translation.copy()  # no position given: the anchor is where the tool starts
    distances = []
    for q in traj.q:
        pin.framesForwardKinematics(scene.model, data, q)
        distances.append(np.linalg.norm(data.oMf[tool].translation - anchor))
    # As for the four-bar: any drift is RK4's error in the angles (relative T ω (hω)^4/120) times the arm's reach
    # from the base to the tool (under 1.2 m for a UR5) times the angles' range.
    _, relative = rk4_state_error(scene, traj, traj.metadata["options"]["dt"])
    bound = 1.2 * np.ptp(traj.q, axis=0).max() * relative
    assert np.ptp(traj.q, axis=0).max() > 0.5  # the arm does swing about the pin
    assert max(distances) < bound
    np.testing.assert_allclose(traj.constraints["pin"].drift, distances, rtol=1e-6, atol=1e-15)


# ---- every shipped scene -------------------------------------------------------------------------------------
# max |energy_error| of each shipped scene, relative to its energy scale (max T + range of V + max |work| + max
# dissipated). Explicit RK4 (every scene but one): a mode y' = λy takes a local error |hλ|^5/120 of the state per
# step, T|λ|(h|λ|)^4/120 over the run; the energy, quadratic in the state, is off by at most twice that:
#     bound = E T ω (hω)^4 / 60,   ω = max |λ| of the open-loop Jacobian at 11 samples of the run
# (open loop: the controllers' torques are held over each step and add no stiffness inside one). That presumes
# every mode inside RK4's stability region, which is asserted. Exceptions, by scene:
# - spring_chain runs implicit midpoint on a linear system: it conserves every quadratic invariant, and its
#   ledger's midpoint rule takes out exactly the damper's d v_mid² per step: Newton's tolerance and round-off only.
# - double_pendulum_spring_friction: its largest |λ| (~1.5e3 /s) is the regularized friction's slope near v = 0,
#   a real, decaying mode (h|λ| = 1.5 < 2.785): its errors die out instead of adding up over the run, so ω there is
#   the fastest oscillation, max |Im λ| (~54 /s).
# A floor of 1e-11 E covers round-off over a few thousand steps.
EXACT_QUADRATIC = {"spring_chain": 1e-10}
OSCILLATION_ONLY = {"double_pendulum_spring_friction"}


@pytest.mark.parametrize("name", sorted(SCENES))
def test_every_shipped_scene_runs_at_integrator_accuracy_and_round_trips(name: str, tmp_path: Path) -> None:
    scene, traj = shipped_run(name)
    assert traj.status == "completed"
    settings = scene.simulation_settings()
    assert traj.t[-1] == pytest.approx(settings["duration"])
    scale = energy_scale(traj)
    error = np.abs(traj.energy_error).max()
    if name in EXACT_QUADRATIC:
        bound = EXACT_QUADRATIC[name] * scale
    elif settings["integrator"] == "timestepping":
        # Contact scenes: every ledger term of the time-stepper has its own formula (the contact's from its
        # impulses, the step's own error from energies), so the ledger closes to round-off; the contact never
        # puts energy in.
        bound = 1e-9 * scale
        assert np.diff(traj.ledger["contact"].energy).min() >= -1e-12 * scale
    else:
        assert settings["integrator"] == "rk4", f"{name}: reason out a bound for {settings['integrator']}"
        lam = eigenvalues_along(scene, traj)
        h = settings["dt"]
        assert h * np.abs(lam).max() < RK4_REAL_LIMIT, f"{name}: a mode outside RK4's stability region"
        omega = np.abs(lam.imag).max() if name in OSCILLATION_ONLY else np.abs(lam).max()
        bound = scale * max(settings["duration"] * omega * (h * omega) ** 4 / 60, 1e-11)
    assert error < bound, f"{name}: max |energy_error| {error:.3g} J, bound {bound:.3g} J"
    # Save and load: every array, the ledger with its kinds, the constraint records, the scene's text.
    loaded = ms.Trajectory.load(traj.save(tmp_path / f"{name}.npz"))
    for field in ("t", "q", "v", "tau", "kinetic_energy", "potential_energy", "energy_error", "work", "dissipated"):
        np.testing.assert_array_equal(getattr(loaded, field), getattr(traj, field))
    assert {k: e.kind for k, e in loaded.ledger.items()} == {k: e.kind for k, e in traj.ledger.items()}
    for key, entry in traj.ledger.items():
        np.testing.assert_array_equal(loaded.ledger[key].energy, entry.energy)
    declared = [c.get("name", f"constraint{i}") for i, c in enumerate(scene_tables(name).get("constraint", []))]
    assert list(loaded.constraints) == list(traj.constraints) == declared
    for key, record in traj.constraints.items():
        for part in ("force", "drift", "velocity_drift"):
            np.testing.assert_array_equal(getattr(loaded.constraints[key], part), getattr(record, part))
    assert loaded.metadata["robot"]["scene"]["toml"] == SCENES[name].read_text(encoding="utf-8")
    assert loaded.status == "completed"


# ---- the command line ----------------------------------------------------------------------------------------
REPO = Path(__file__).resolve().parents[1]


def console_script() -> Path:
    """The installed multibody-sim console script (beside this Python, as pip install -e . puts it)."""
    script = Path(sys.executable).with_name("multibody-sim")
    if not script.is_file():
        pytest.fail("the multibody-sim console script is not installed (pip install -e .)")
    return script


def cli(*args: str, cwd: Path = REPO) -> subprocess.CompletedProcess[str]:
    return subprocess.run([str(console_script()), *args], capture_output=True, text=True, timeout=120, cwd=cwd)


@pytest.fixture(scope="module")
def cli_runs(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    """Every console run of this file, started side by side (each child spends ~1 s importing the package)."""
    work = tmp_path_factory.mktemp("cli")
    bad = work / "bad.toml"
    bad.write_text('gravty = [0.0, 0.0, -9.81]\n[robot]\nsource = "pendulum"\n', encoding="utf-8")
    jobs = {
        "run": ("run", "models/scenes/four_bar.toml", "--duration", "0.1", "--out", str(work / "f.npz")),
        "bad": ("run", str(bad)),
        "savings": ("run", "talos_upper_body", "--report-savings", "--duration", "0.01"),
        "inspect": ("inspect", "panda_payload"),
        "fixed_base": ("run", "four_bar", "--fixed-base"),
        "models": ("models",),
    }
    with ThreadPoolExecutor(max_workers=3) as pool:
        futures: dict[str, Future[subprocess.CompletedProcess[str]]] = {
            key: pool.submit(cli, *args) for key, args in jobs.items()
        }
        yield {"work": work, "bad_file": bad, **{key: future.result(timeout=240) for key, future in futures.items()}}


def test_cli_runs_a_scene_file_and_says_what_it_modelled(cli_runs: dict[str, Any]) -> None:
    done = cli_runs["run"]
    assert (done.returncode, done.stderr) == (0, "")
    scene = ms.load_scene(REPO / "models" / "scenes" / "four_bar.toml")
    assert done.stdout.startswith(scene.describe() + "\n")
    assert "run: four_bar (fixed base, nq 3, nv 3), integrator rk4, dt 0.001 s, duration 0.1 s\n" in done.stdout
    traj = ms.Trajectory.load(cli_runs["work"] / "f.npz")
    assert traj.status == "completed" and traj.t[-1] == pytest.approx(0.1)
    assert traj.constraints["loop"].force.shape == (len(traj.t), 3)
    assert traj.metadata["robot"]["scene"]["toml"] == SCENES["four_bar"].read_text(encoding="utf-8")


def test_cli_refuses_a_bad_scene_file_in_one_line(cli_runs: dict[str, Any]) -> None:
    done = cli_runs["bad"]
    with pytest.raises(ms.SceneError) as caught:  # the message the API gives for the same file
        ms.load_scene(cli_runs["bad_file"])
    assert "gravty" in str(caught.value) and "\n" not in str(caught.value)
    assert (done.returncode, done.stdout) == (2, "")
    assert done.stderr == PREFIX + str(caught.value) + "\n"  # one line, no traceback


SAVINGS = re.compile(
    r"savings \(RK4, CPU-time medians of 5 x 200 steps\): scene (\d+\.\d) µs/step, full robot model (\d+\.\d) "
    r"µs/step: (\d+\.\d\d)x the full model's cost"
)


@pytest.mark.parametrize("key", ["savings", "inspect"])
def test_cli_reports_the_savings_measurement(cli_runs: dict[str, Any], key: str) -> None:
    done = cli_runs[key]
    assert (done.returncode, done.stderr) == (0, "")
    (line,) = [line for line in done.stdout.splitlines() if line.startswith("savings")]
    match = SAVINGS.fullmatch(line)
    assert match, line
    scene_us, full_us, ratio = (float(x) for x in match.groups())
    assert scene_us > 0 and full_us > 0
    # The ratio is the two medians' quotient (each printed to 0.05 µs, the ratio to 0.005).
    low, high = (scene_us - 0.05) / (full_us + 0.05), (scene_us + 0.05) / (full_us - 0.05)
    assert low - 0.005 <= ratio <= high + 0.005
    name = "talos_upper_body" if key == "savings" else "panda_payload"
    assert done.stdout.startswith(ms.load_scene(name).describe() + "\n")


def test_cli_refuses_base_flags_with_a_scene(cli_runs: dict[str, Any]) -> None:
    done = cli_runs["fixed_base"]
    assert (done.returncode, done.stdout) == (2, "")
    assert done.stderr == (
        PREFIX + "--floating-base/--fixed-base: a scene declares its robot: set this in its [robot] table\n"
    )


def test_cli_models_lists_the_shipped_scenes(cli_runs: dict[str, Any]) -> None:
    done = cli_runs["models"]
    assert (done.returncode, done.stderr) == (0, "")
    rows = done.stdout.split("\nscenes (", 1)[1].splitlines()
    for name in SCENES:
        description = scene_tables(name)["description"]
        assert any(re.fullmatch(rf"\s+{re.escape(name)}\s+{re.escape(description)}", row) for row in rows), name


# ---- the viewer path -----------------------------------------------------------------------------------------
def require_viewer() -> Any:
    """multibody_sim.viz with its extra; in CI a missing extra fails, elsewhere it skips with the reason."""
    missing = [m for m in ("meshcat", "umsgpack", "trimesh", "scipy") if importlib.util.find_spec(m) is None]
    if missing:
        reason = f"the viz extra is not installed (missing: {', '.join(missing)})"
        if os.environ.get("CI") == "true":
            pytest.fail(reason, pytrace=False)
        pytest.skip(reason)
    import multibody_sim.viz as viz

    return viz


@pytest.mark.parametrize("name", ["four_bar", "talos_upper_body"])
def test_robot_from_a_saved_scene_trajectory_is_the_scene(name: str, tmp_path: Path) -> None:
    require_viewer()
    from multibody_sim.recorded import robot_from_trajectory

    scene = ms.load_scene(SCENES[name])
    traj = scene.run(progress=False, duration=0.02)
    loaded = ms.Trajectory.load(traj.save(tmp_path / "run.npz"))
    rebuilt = robot_from_trajectory(loaded)
    assert isinstance(rebuilt, ms.Scene)
    assert rebuilt.nq == loaded.q.shape[1] == scene.nq and rebuilt.full_nq == scene.full_nq
    assert rebuilt.describe() == scene.describe()
    for q, v in zip(loaded.q[::5], loaded.v[::5], strict=True):  # the same dynamics, not merely the same sizes
        np.testing.assert_array_equal(
            rebuilt.forward_dynamics(q, v, np.zeros(scene.nv)), scene.forward_dynamics(q, v, np.zeros(scene.nv))
        )


def page_commands(html: Path) -> list[dict[str, Any]]:
    """The viewer commands embedded in an exported page: base64 of zlib of length-prefixed msgpack."""
    import umsgpack

    found = re.search(r'id="multibody-sim-commands">([^<]*)</script>', html.read_text(encoding="utf-8"))
    assert found, "no embedded commands"
    raw = zlib.decompress(base64.b64decode(found.group(1)))
    commands, i = [], 0
    while i < len(raw):
        (size,) = struct.unpack_from("<I", raw, i)
        commands.append(umsgpack.unpackb(raw[i + 4 : i + 4 + size], allow_invalid_utf8=True))
        i += 4 + size
    return commands


def visual_origins(urdf: Path) -> dict[str, np.ndarray]:
    """Each <visual>'s origin in its link, by Pinocchio's geometry name "<link>_<k>", read from the URDF text."""
    origins = {}
    for element in ET.parse(urdf).getroot().findall("link"):
        for k, visual in enumerate(element.findall("visual")):
            origin = visual.find("origin")
            xyz = [float(x) for x in (origin.get("xyz", "0 0 0") if origin is not None else "0 0 0").split()]
            rpy = [float(x) for x in (origin.get("rpy", "0 0 0") if origin is not None else "0 0 0").split()]
            origins[f"{element.get('name')}_{k}"] = pin.SE3(pin.rpy.rpyToMatrix(*rpy), np.array(xyz)).homogeneous
    return origins


@pytest.mark.parametrize("name", ["talos_upper_body", "ur5_ceiling_push"])
def test_exported_page_draws_locked_links_and_the_base_pose_where_the_full_robot_has_them(
    name: str, tmp_path: Path
) -> None:
    """Every mesh of the page at the scene's first and last frames sits where the FULL robot's kinematics puts it,
    with the locked joints at their [lock] values and the root welded at the scene's [robot] position and rpy."""
    viz = require_viewer()
    scene = ms.load_scene(SCENES[name])
    traj = ms.Trajectory.load(scene.run(progress=False, duration=0.05).save(tmp_path / "run.npz"))
    html = viz.export_html(traj, tmp_path / "page.html", fps=20)  # the scene rebuilt from the file's metadata
    commands = page_commands(html)
    assert commands[-1]["type"] == "multibody_sim_ready"

    tables = scene_tables(name)
    robot = tables["robot"]
    pose = pin.SE3(
        pin.rpy.rpyToMatrix(*robot.get("rpy", [0.0, 0.0, 0.0])), np.array(robot.get("position", [0.0, 0.0, 0.0]))
    ).homogeneous
    full = ms.load_robot(robot["source"], floating_base=False)
    lock = tables.get("lock", {})

    def full_kinematics(q: np.ndarray) -> pin.Data:
        """The full model's kinematics: scene joints at q, locked joints at their lock values (by joint name)."""
        q_full = pin.neutral(full.model)
        for jid in range(1, full.model.njoints):
            joint, joint_name = full.model.joints[jid], full.model.names[jid]
            if joint_name in lock:
                q_full[joint.idx_q] = lock[joint_name]
            else:
                mine = scene.model.joints[scene.model.getJointId(joint_name)]
                q_full[joint.idx_q : joint.idx_q + joint.nq] = q[mine.idx_q : mine.idx_q + mine.nq]
        data = full.model.createData()
        pin.framesForwardKinematics(full.model, data, q_full)
        return data

    def matrix(command: dict[str, Any]) -> np.ndarray:
        return np.array(command["matrix"], dtype=float).reshape(4, 4).T  # meshcat's column-major 4x4

    transforms = [c for c in commands if c["type"] == "set_transform"]
    geometry = {c["path"]: matrix(c) for c in transforms if c["path"].count("/") == 4}  # /meshcat/robot/body/geom
    bodies = {c["path"]: matrix(c) for c in transforms if c["path"].count("/") == 3}
    origins = visual_origins(Path(full.source["urdf_path"]))
    assert len(geometry) == len(origins)  # every <visual> of the URDF is drawn, the locked links' too
    data = full_kinematics(traj.q[0])
    for path, placement in geometry.items():
        body, node = path.rsplit("/", 1)
        visual = node.split("_", 1)[1]  # "<index>_<link>_<k>"
        link = full.model.getFrameId(visual.rsplit("_", 1)[0])
        expected = pose @ data.oMf[link].homogeneous @ origins[visual]
        np.testing.assert_allclose(bodies[body] @ placement, expected, atol=2e-6)  # float32 on the page
    # The animation's last keys: each moving body at the full robot's pose for the trajectory's last q.
    (animation,) = [c for c in commands if c["type"] == "set_animation"]
    data = full_kinematics(traj.q[-1])
    assert {a["path"] for a in animation["animations"]} == {p for p in bodies if not p.endswith("/universe")}
    for track_set in animation["animations"]:
        joint_name = track_set["path"].rsplit("/", 1)[1]
        position = next(t for t in track_set["clip"]["tracks"] if t["name"] == ".position")["keys"][-1]["value"]
        expected = pose @ data.oMi[full.model.getJointId(joint_name)].homogeneous
        np.testing.assert_allclose(position, expected[:3, 3], atol=2e-6)


def test_linearize_takes_time_dependent_forces_at_the_stage_times() -> None:
    """ur5_ceiling_push's ramp and sine forces: linearize(..., t=1 s) equals central finite differences of one RK4
    step started at t = 1 s (and differs from the t = 0 linearization, so the test has teeth)."""
    scene = ms.load_scene("ur5_ceiling_push")
    q, v, tau, h, t = scene.q0, np.full(scene.nv, 0.3), np.zeros(scene.nv), 1e-2, 1.0
    method = ms.get_integrator("rk4")

    def step(dx: np.ndarray) -> np.ndarray:
        q1, v1, _ = method.step(scene, scene.space.integrate(q, dx[: scene.nv]), v + dx[scene.nv :], tau, h, t)
        return np.concatenate((q1, v1))

    base = step(np.zeros(2 * scene.nv))
    eps = 1e-6
    columns = []
    for e in np.eye(2 * scene.nv):
        plus, minus = step(eps * e), step(-eps * e)
        dq = scene.space.difference(minus[: scene.nq], plus[: scene.nq]) / (2 * eps)
        columns.append(np.concatenate((dq, (plus[scene.nq :] - minus[scene.nq :]) / (2 * eps))))
    finite_differences = np.column_stack(columns)
    assert base.shape == (2 * scene.nv,)
    A_t = ms.linearize(scene, q, v, tau, h, t=t).A
    A_0 = ms.linearize(scene, q, v, tau, h).A
    scale = np.abs(finite_differences).max()
    assert np.abs(A_t - finite_differences).max() < 1e-7 * scale
    assert np.abs(A_0 - finite_differences).max() > 1e-5 * scale


def test_a_stepper_on_a_time_dependent_scene_is_simulate_bitwise() -> None:
    """Stepper passes each step's start time too: 1000 RK4 steps of ur5_ceiling_push (ramp and sine forces) land
    exactly where simulate() does."""
    scene = ms.load_scene("ur5_ceiling_push")
    stepper = ms.Stepper(scene, dt=1e-3, q0=scene.q0, v0=scene.v0)
    for _ in range(1000):
        t, q, v = stepper.step(np.zeros(scene.nv))
    traj = ms.simulate(scene, scene.q0, scene.v0, duration=1.0, dt=1e-3, progress=False)
    assert t == traj.t[-1]
    np.testing.assert_array_equal(q, traj.q[-1])
    np.testing.assert_array_equal(v, traj.v[-1])
