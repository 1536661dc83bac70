"""Integrators: registry, tableau checks, observed convergence orders on an arm and floating bases, chart map."""

from __future__ import annotations

import dataclasses
import functools
import re
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import pinocchio as pin
import pytest

import multibody_sim as ms
from multibody_sim.state import ConfigurationSpace

# ---- tableaux built here, not in the package: a new method must be nothing but new coefficients ----------
HEUN = ms.ButcherTableau(a=((0.0, 0.0), (1.0, 0.0)), b=(0.5, 0.5), c=(0.0, 1.0), order=2)
KUTTA3 = ms.ButcherTableau(
    a=((0.0, 0.0, 0.0), (0.5, 0.0, 0.0), (-1.0, 2.0, 0.0)),
    b=(1 / 6, 2 / 3, 1 / 6),
    c=(0.0, 0.5, 1.0),
    order=3,
)
CLASSICAL_RK4 = ms.ButcherTableau(
    a=((0.0, 0.0, 0.0, 0.0), (0.5, 0.0, 0.0, 0.0), (0.0, 0.5, 0.0, 0.0), (0.0, 0.0, 1.0, 0.0)),
    b=(1 / 6, 1 / 3, 1 / 3, 1 / 6),
    c=(0.0, 0.5, 0.5, 1.0),
    order=4,
)


class NaiveLieRungeKutta(ms.Integrator):
    """The tempting but wrong Lie-group RK: stages ``integrate(q_n, dt Σ a_ij v_j)``, v_j stage velocities.

    Summing velocities that live at different base points ignores the chart Jacobian, which is the identity
    only on commutative joints. Kept here as the negative control the convergence test must catch.
    """

    def __init__(self, tableau: ms.ButcherTableau):
        self.name = f"naive_lie_rk{tableau.order}"
        self.order = tableau.order
        self.description = "explicit RK summing stage velocities at different base points (no chart)"
        self.evaluations_per_step = tableau.stages
        self.tableau = tableau

    def step(
        self, system: ms.Robot, q: np.ndarray, v: np.ndarray, tau: np.ndarray, dt: float, t: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        a, b = self.tableau.a, self.tableau.b
        velocities: list[np.ndarray] = []
        accelerations: list[np.ndarray] = []
        powers: list[np.ndarray] = []
        for i in range(len(b)):
            dq = dt * sum((a[i][j] * velocities[j] for j in range(i)), np.zeros(system.nv))
            v_stage = v + dt * sum((a[i][j] * accelerations[j] for j in range(i)), np.zeros(system.nv))
            q_stage = system.space.integrate(q, dq)
            velocities.append(v_stage)
            accelerations.append(system.unchecked_forward_dynamics(q_stage, v_stage, tau))
            powers.append(system.ledger_power(q_stage, v_stage, tau))
        q_next = system.space.integrate(q, dt * sum(b_j * x for b_j, x in zip(b, velocities, strict=True)))
        v_next = v + dt * sum(b_j * x for b_j, x in zip(b, accelerations, strict=True))
        return q_next, v_next, dt * sum(b_j * x for b_j, x in zip(b, powers, strict=True))


# ---- registry ------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", sorted(ms.INTEGRATORS))
def test_every_registered_name_resolves(name: str) -> None:
    method = ms.get_integrator(name)
    assert method is ms.INTEGRATORS[name]
    assert isinstance(method, ms.Integrator)
    assert method.name == name
    assert method.order >= 1 and method.evaluations_per_step >= 1
    assert ms.get_integrator(method) is method  # objects pass through untouched


@pytest.mark.parametrize(
    ("name", "hint"),
    [("nonsense", ""), ("rk_4", "did you mean rk4? "), ("midpiont", "did you mean midpoint? ")],
)
def test_unknown_integrator_lists_the_valid_names(name: str, hint: str) -> None:
    valid = ", ".join(sorted(ms.INTEGRATORS))
    message = f"unknown integrator '{name}' ({hint}valid: {valid})"
    with pytest.raises(ms.UnknownIntegratorError, match=f"^{re.escape(message)}$") as info:
        ms.get_integrator(name)
    assert isinstance(info.value, LookupError) and isinstance(info.value, ms.MultibodySimError)
    for registered in ms.INTEGRATORS:  # the message names every valid choice
        assert registered in str(info.value)


def test_simulate_rejects_an_unknown_integrator_name(robot: Callable[..., ms.Robot]) -> None:
    pendulum = robot("pendulum")
    message = f"unknown integrator 'leapfrog' (valid: {', '.join(sorted(ms.INTEGRATORS))})"
    with pytest.raises(LookupError, match=f"^{re.escape(message)}$"):
        ms.simulate(pendulum, [0.1], [0.0], duration=0.1, dt=0.01, integrator="leapfrog")


def test_integrator_of_the_wrong_type_is_a_value_error() -> None:
    with pytest.raises(ValueError, match=f"^{re.escape('integrator must be a name or an Integrator, got int')}$"):
        ms.get_integrator(4)  # type: ignore[arg-type]


# ---- tableau validation and order conditions -----------------------------------------------------------
@pytest.mark.parametrize(
    ("a", "b", "c", "order", "message"),
    [
        pytest.param(
            ((0.0, 0.0), (0.5, 0.0)),
            (0.4, 0.5),
            (0.0, 0.5),
            1,
            "tableau weights b must sum to 1, got 0.9",
            id="weights-sum",
        ),
        pytest.param(
            ((0.0, 0.0), (0.5, 0.0)),
            (0.0, 1.0),
            (0.0, 0.6),
            2,
            "tableau rows of a must sum to c",
            id="row-sums",
        ),
        pytest.param(
            ((0.0, 0.5), (0.5, 0.0)),
            (0.5, 0.5),
            (0.5, 0.5),
            1,
            "an explicit tableau's a must be strictly lower-triangular",
            id="upper-entry",
        ),
        pytest.param(
            ((0.5, 0.0), (0.5, 0.0)),
            (0.5, 0.5),
            (0.5, 0.5),
            1,
            "an explicit tableau's a must be strictly lower-triangular",
            id="diagonal-entry",
        ),
        pytest.param(
            ((0.0, 0.0), (0.5, 0.0)),
            (0.0, 0.0, 1.0),
            (0.0, 0.5),
            1,
            "tableau shapes disagree: a (2, 2), b (3,), c (2,)",
            id="shapes",
        ),
        pytest.param(((0.0,),), (1.0,), (0.0,), 0, "tableau order must be >= 1, got 0", id="order"),
    ],
)
def test_tableau_validation_rejects_bad_coefficients(
    a: tuple[tuple[float, ...], ...], b: tuple[float, ...], c: tuple[float, ...], order: int, message: str
) -> None:
    with pytest.raises(ValueError, match=f"^{re.escape(message)}$"):
        ms.ButcherTableau(a=a, b=b, c=c, order=order)


def test_tableau_is_immutable() -> None:
    with pytest.raises(dataclasses.FrozenInstanceError):
        HEUN.order = 3  # type: ignore[misc]


def _order_conditions(tableau: ms.ButcherTableau, b: np.ndarray | None = None) -> dict[int, list[float]]:
    """Residuals of Butcher's order conditions (one per rooted tree, 1/γ on the right), grouped by order.

    `b` replaces the tableau's weights (for an embedded solution).
    """
    a, c = np.array(tableau.a), np.array(tableau.c)
    b = np.array(tableau.b) if b is None else b
    ac = a @ c
    return {
        1: [b.sum() - 1.0],
        2: [b @ c - 1 / 2],
        3: [b @ c**2 - 1 / 3, b @ ac - 1 / 6],
        4: [b @ c**3 - 1 / 4, b @ (c * ac) - 1 / 8, b @ a @ c**2 - 1 / 12, b @ a @ ac - 1 / 24],
        5: [
            b @ c**4 - 1 / 5,
            b @ (c**2 * ac) - 1 / 10,
            b @ (c * (a @ c**2)) - 1 / 15,
            b @ (c * (a @ ac)) - 1 / 30,
            b @ ac**2 - 1 / 20,
            b @ a @ c**3 - 1 / 20,
            b @ a @ (c * ac) - 1 / 40,
            b @ a @ a @ c**2 - 1 / 60,
            b @ a @ a @ ac - 1 / 120,
        ],
    }


def _check_order(tableau: ms.ButcherTableau, order: int, b: np.ndarray | None = None) -> None:
    """Conditions up to `order` hold (checked up to 5); if order < 5, one of order + 1 fails."""
    conditions = _order_conditions(tableau, b)
    for p in range(1, min(order, 5) + 1):
        assert np.allclose(conditions[p], 0.0, atol=1e-14), f"order-{p} condition violated"
    if order < 5:
        # Well above round-off; not large: Dormand-Prince tuned its 4th-order weights' residuals to ~1e-3.
        assert np.max(np.abs(conditions[order + 1])) > 1e-6, f"the tableau is of order > {order}"


def _registered_and_test_tableaux() -> list[tuple[str, ms.ButcherTableau]]:
    found = [(name, m.tableau) for name, m in ms.INTEGRATORS.items() if isinstance(m, ms.ExplicitRungeKutta)]
    return found + [("heun", HEUN), ("kutta3", KUTTA3), ("classical_rk4", CLASSICAL_RK4)]


@pytest.mark.parametrize(("name", "tableau"), _registered_and_test_tableaux(), ids=lambda x: str(x)[:20])
def test_tableau_order_is_what_the_order_conditions_say(name: str, tableau: ms.ButcherTableau) -> None:
    """The declared order (and an embedded pair's lower order) against Butcher's conditions, not on trust."""
    _check_order(tableau, tableau.order)
    b_hat = getattr(tableau, "b_hat", ())
    if b_hat:
        _check_order(tableau, tableau.embedded_order, np.array(b_hat))


# ---- observed convergence order --------------------------------------------------------------------------
@dataclass(frozen=True)
class ConvergenceCase:
    """A robot, an initial state and step ladders on which every method is in its asymptotic regime.

    Attributes:
        name: catalog robot.
        floating_base: load_robot's floating_base.
        duration: simulated time [s].
        spin: magnitude of the random initial base angular velocity [rad/s] (floating bases).
        seed: seed of the random initial state.
        ref_exponent: the reference is RK4 at dt = 2^-ref_exponent s, Richardson-checked against 2^-(ref-1).
        ladders: exponents k (dt = 2^-k s) per order; a method uses that of the largest order <= its own.
    """

    name: str
    floating_base: bool | None
    duration: float
    spin: float
    seed: int
    ref_exponent: int
    ladders: dict[int, tuple[int, ...]]

    def ladder(self, order: int) -> tuple[int, ...]:
        return self.ladders[max(p for p in self.ladders if p <= order)]


# Ladders were chosen from the error sequence over dt = 2^-5 .. 2^-13 s: coarse steps are pre-asymptotic from
# a random state (ur5's RK4 slopes run 2.9, 3.2, 3.7 above 2^-8 s), the finest ones approach the reference's
# error. On solo12 the RK4 ladder is deliberately at dt <= 2^-9 s: the order loss of naive Lie-group stages
# only shows there. Not every random solo12 state reaches Euler's asymptotic regime by 2^-13 s (legs whipped
# by the spin, Euler pumping energy into them): the seed is one that does, so the test stays under a second.
CASES = {
    "ur5": ConvergenceCase(
        "ur5",
        None,
        0.5,
        0.0,
        20240611,
        14,
        {1: (10, 11, 12, 13), 2: (9, 10, 11, 12), 4: (8, 9, 10, 11), 5: (7, 8, 9, 10)},
    ),
    "solo12": ConvergenceCase(
        "solo12",
        True,
        0.5,
        8.0,
        3,
        14,
        {1: (10, 11, 12, 13), 2: (10, 11, 12, 13), 4: (9, 10, 11, 12), 5: (7, 8, 9, 10)},
    ),
    "free_body": ConvergenceCase(
        "free_body", True, 0.5, 5.0, 20240611, 12, {1: (7, 8, 9, 10), 2: (6, 7, 8, 9), 4: (6, 7, 8, 9), 5: (5, 6, 7, 8)}
    ),
}
ORDER_TOLERANCE = 0.3  # a half-order slip (e.g. 4 -> 3.5) is a real loss; fits over 4 points scatter ~0.1


def _initial_state(robot: ms.Robot, case: ConvergenceCase) -> tuple[np.ndarray, np.ndarray]:
    """A random configuration, velocities in [-1, 1]; a floating base spins at case.spin about a random axis."""
    rng = np.random.default_rng(case.seed)
    q0 = robot.random_configuration(rng)
    v0 = rng.uniform(-1.0, 1.0, robot.nv)
    if robot.floating_base:
        axis = rng.normal(size=3)
        v0[3:6] = case.spin * axis / np.linalg.norm(axis)
    return q0, v0


def _state_error(robot: ms.Robot, q: np.ndarray, v: np.ndarray, q_ref: np.ndarray, v_ref: np.ndarray) -> float:
    """max(‖q ⊖ q_ref‖∞, ‖v − v_ref‖∞): the error in the tangent space, never a difference of quaternions."""
    return max(float(np.abs(robot.space.difference(q_ref, q)).max()), float(np.abs(v - v_ref).max()))


@functools.cache
def _reference(case_name: str) -> tuple[np.ndarray, np.ndarray, float]:
    """(q_ref, v_ref, error estimate) at the final time, by RK4 at a much finer step than any ladder."""
    case = CASES[case_name]
    robot = ms.load_robot(case.name, floating_base=case.floating_base)
    q0, v0 = _initial_state(robot, case)
    fine = ms.simulate(robot, q0, v0, duration=case.duration, dt=2.0**-case.ref_exponent, output_dt=case.duration)
    coarse = ms.simulate(
        robot, q0, v0, duration=case.duration, dt=2.0 ** -(case.ref_exponent - 1), output_dt=case.duration
    )
    # Richardson: for an order-4 method the fine run's error is ~1/15 of the fine-coarse gap.
    estimate = _state_error(robot, coarse.q[-1], coarse.v[-1], fine.q[-1], fine.v[-1]) / 15
    return fine.q[-1], fine.v[-1], estimate


def _observed_order(case_name: str, integrator: ms.Integrator) -> tuple[float, list[float]]:
    """Least-squares slope of log(error) against log(dt) over the case's ladder for the method's order."""
    case = CASES[case_name]
    robot = ms.load_robot(case.name, floating_base=case.floating_base)
    q0, v0 = _initial_state(robot, case)
    q_ref, v_ref, ref_error = _reference(case_name)
    # Points within 30x of the reference's error (which would bend the slope by > 0.05) or near round-off
    # say nothing about the method's order.
    floor = max(30 * ref_error, 1e-11)
    dts, errors = [], []
    for k in case.ladder(integrator.order):
        dt = 2.0**-k
        traj = ms.simulate(robot, q0, v0, duration=case.duration, dt=dt, integrator=integrator, output_dt=case.duration)
        assert traj.t[-1] == case.duration
        error = _state_error(robot, traj.q[-1], traj.v[-1], q_ref, v_ref)
        if error > floor:
            dts.append(dt)
            errors.append(error)
    assert len(errors) >= 3, f"{integrator.name} on {case_name}: ladder lost in round-off ({errors}); move it"
    slope = float(np.polyfit(np.log(dts), np.log(errors), 1)[0])
    return slope, errors


@pytest.mark.parametrize("case_name", sorted(CASES))
# dop853 (order 8) reaches round-off on these ladders before its asymptotic range: tests/test_adaptive.py checks
# its order on a coarse ladder of its own.
@pytest.mark.parametrize("name", sorted(n for n, m in ms.INTEGRATORS.items() if m.order <= 5))
def test_observed_order_matches_declared_order(name: str, case_name: str) -> None:
    """Every registered method converges at its declared order on an arm and on floating bases.

    Adaptive pairs are run at fixed steps with their propagating weights b (their order is that of b).
    """
    method = ms.INTEGRATORS[name]
    if method.adaptive:
        # dt is only its first trial step: test the formula it propagates, at fixed steps, instead.
        if not isinstance(method, ms.ExplicitRungeKutta):
            pytest.skip("adaptive and not a Runge-Kutta pair: no fixed-step formula to test")
        method = ms.ExplicitRungeKutta(f"{name}_fixed_step", method.tableau, f"{name} without step control")
    case = CASES[case_name]
    try:  # a method may declare systems it cannot integrate (e.g. a fixed-base-only method)
        method.check_system(ms.load_robot(case.name, floating_base=case.floating_base))
    except ms.InvalidArgumentError as exc:
        pytest.skip(f"{name} refuses {case_name}: {exc}")
    slope, errors = _observed_order(case_name, method)
    assert abs(slope - method.order) < ORDER_TOLERANCE, (
        f"{method.name} on {case_name}: observed order {slope:.2f}, declared {method.order}; errors {errors}"
    )


@pytest.mark.parametrize(("case_name", "expected"), [("ur5", 4), ("solo12", 2), ("free_body", 2)])
def test_naive_lie_group_stages_lose_rk4_order_on_a_floating_base(case_name: str, expected: int) -> None:
    """The negative control: the ladder that passes RK4 catches stages built without the chart map.

    On the arm every joint is commutative, so naive stages are exact and keep order 4; on a free-flyer
    they drop to order 2, which proves the convergence test above would see that bug.
    """
    naive = NaiveLieRungeKutta(CLASSICAL_RK4)
    slope, errors = _observed_order(case_name, naive)
    assert abs(slope - expected) < ORDER_TOLERANCE, f"naive RK4 on {case_name}: order {slope:.2f}, {errors}"


@pytest.mark.parametrize("case_name", ["ur5", "free_body"])
@pytest.mark.parametrize(("label", "tableau"), [("heun", HEUN), ("kutta3", KUTTA3)])
def test_a_new_tableau_is_a_new_method(label: str, tableau: ms.ButcherTableau, case_name: str) -> None:
    """A tableau defined outside the package runs through simulate() and shows its order, chart included."""
    method = ms.ExplicitRungeKutta(label, tableau, f"{label} (built in a test)")
    assert method.order == tableau.order and method.evaluations_per_step == tableau.stages
    slope, errors = _observed_order(case_name, method)
    assert abs(slope - tableau.order) < ORDER_TOLERANCE, f"{label} on {case_name}: {slope:.2f}, {errors}"
    robot = ms.load_robot(CASES[case_name].name, floating_base=CASES[case_name].floating_base)
    traj = ms.simulate(robot, *_initial_state(robot, CASES[case_name]), duration=0.01, dt=0.001, integrator=method)
    assert traj.metadata["integrator"] == label
    assert traj.stats["evaluations"] == traj.stats["steps"] * tableau.stages


def test_reference_is_far_more_accurate_than_the_ladders() -> None:
    """Guard the guard: each reference's Richardson error is tiny against the smallest error fitted."""
    for case_name, case in CASES.items():
        _, _, ref_error = _reference(case_name)
        assert ref_error < 1e-9, f"{case_name}: reference error {ref_error:.2e}"
        assert case.ref_exponent >= max(max(k) for k in case.ladders.values()) + 1


# ---- the chart map ---------------------------------------------------------------------------------------
CHART_ROBOTS = [
    ("free_body", True),
    ("solo12", True),
    ("ur5", None),
    ("double_pendulum_continuous", None),
    ("solo12", False),
]


@pytest.mark.parametrize(("name", "floating_base"), CHART_ROBOTS)
def test_chart_velocity_is_the_inverse_chart_jacobian_up_to_its_truncation(
    robot: Callable[..., ms.Robot], name: str, floating_base: bool | None
) -> None:
    """d/ds integrate(q_base, xi + s·xi') at s = 0, by central differences in the tangent space, equals v."""
    space = robot(name, floating_base=floating_base).space
    assert isinstance(space, ConfigurationSpace)
    rng = np.random.default_rng(7)
    q_base = robot(name, floating_base=floating_base).random_configuration(rng)
    xi = rng.uniform(-0.2, 0.2, space.nv)  # rotations up to ~0.35 rad: the series after A⁶ drops ~1e-10
    v = rng.normal(size=space.nv)
    xi_dot = space.chart_velocity(xi, v, 6)
    q = space.integrate(q_base, xi)
    eps = 1e-6
    forward = space.difference(q, space.integrate(q_base, xi + eps * xi_dot))
    backward = space.difference(q, space.integrate(q_base, xi - eps * xi_dot))
    # Central difference: truncation O(eps²) ~ 1e-12, cancellation ~ 1e-16 / eps ~ 1e-10.
    np.testing.assert_allclose((forward - backward) / (2 * eps), v, atol=1e-8)
    if space.is_flat:
        np.testing.assert_array_equal(xi_dot, v)
    else:
        # The map has teeth here: using v itself as the chart rate misses by O(|xi|·|v|).
        assert np.abs(space.chart_velocity(xi, v, 0) - v).max() == 0.0
        assert np.abs(xi_dot - v).max() > 0.01


def _lie_group_chain() -> pin.Model:
    """A free-flyer, a spherical and a planar joint side by side: the three non-commutative joints."""
    model = pin.Model()
    for joint in (pin.JointModelFreeFlyer(), pin.JointModelSpherical(), pin.JointModelPlanar()):
        model.addJoint(0, joint, pin.SE3.Identity(), joint.shortname())
    return model


def _ad(kind: str, x: Any) -> Any:
    """The Lie algebra's ad matrix of x, written out by hand: se(3) with x = (linear, angular), so(3), and se(2)
    with x = (vx, vy, ω). Works on floats and on mpmath numbers."""

    def skew(a: Any) -> list[list[Any]]:
        return [[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]]

    if kind == "so3":
        return skew(x)
    if kind == "se2":
        return [[0, -x[2], x[1]], [x[2], 0, -x[0]], [0, 0, 0]]
    rho, phi = skew(x[:3]), skew(x[3:])
    zero = [[0, 0, 0]] * 3
    return [phi[r] + rho[r] for r in range(3)] + [zero[r] + phi[r] for r in range(3)]


def test_chart_generators_are_the_lie_algebras_ad() -> None:
    # The generators are found numerically from Pinocchio's chart Jacobian and rounded: they must be exactly the
    # ad matrices of se(3), so(3) and se(2), written out independently above.
    space = ConfigurationSpace(_lie_group_chain())
    assert space.curved_blocks == [(0, 6), (6, 9), (9, 12)]
    rng = np.random.default_rng(3)
    for (start, stop), G, kind in zip(space.curved_blocks, space.chart_generators, ("se3", "so3", "se2"), strict=True):
        x = rng.normal(size=stop - start)
        np.testing.assert_array_equal((x @ G).reshape(stop - start, -1), np.array(_ad(kind, x), dtype=float))


def test_truncated_chart_map_drops_exactly_the_next_power_of_the_rotation() -> None:
    # Against J(ξ)⁻¹ v with 40 digits (J = Σ_k (-ad_ξ)^k / (k+1)!, the right Jacobian of exp, solved in mpmath):
    # truncated after A^K the map misses by O(|ξ|^K') with K' the next power whose coefficient is non-zero
    # (b_3 = b_5 = 0), so halving ξ divides the error by 2^K'. And at |ξ| ~ 1e-4 rad, where Pinocchio's own
    # Jexp6 loses up to 8 digits, RK4's map (K = 2) is exact to round-off.
    import mpmath

    space = ConfigurationSpace(_lie_group_chain())
    rng = np.random.default_rng(5)
    direction = rng.normal(size=space.nv)
    v = rng.normal(size=space.nv)

    def exact(xi: np.ndarray) -> np.ndarray:
        out = v.copy()
        with mpmath.workdps(40):
            for (start, stop), kind in zip(space.curved_blocks, ("se3", "so3", "se2"), strict=True):
                ad = mpmath.matrix(_ad(kind, [mpmath.mpf(float(c)) for c in xi[start:stop]]))
                J, term, k = mpmath.zeros(stop - start), mpmath.eye(stop - start), 1
                while mpmath.mnorm(term, 1) > mpmath.mpf(10) ** -45:
                    J += term
                    term, k = term * (-ad) / (k + 1), k + 1
                solution = mpmath.lu_solve(J, mpmath.matrix([float(c) for c in v[start:stop]]))
                out[start:stop] = [float(c) for c in solution]
        return out

    for terms, dropped in ((1, 2), (2, 4), (4, 6), (6, 8)):
        errors = []
        for size in (0.4, 0.2):
            xi = direction * size
            errors.append(np.abs(space.chart_velocity(xi, v, terms) - exact(xi)).max())
        assert abs(np.log2(errors[0] / errors[1]) - dropped) < 0.3, (terms, errors)
    xi = direction * 1e-4
    np.testing.assert_allclose(space.chart_velocity(xi, v, 2), exact(xi), rtol=0, atol=4e-16 * np.abs(v).max())


CURVATURE_CASES = [(name, None, entry.floating_base) for name, entry in sorted(ms.CATALOG.items())] + [
    ("solo12", False, False),  # a legged robot welded to the world is flat
    ("ur5", True, True),  # an arm on a free-flyer is not
]


@pytest.mark.parametrize(("name", "floating_base", "floating"), CURVATURE_CASES)
def test_curved_blocks_are_exactly_the_free_flyer(
    robot: Callable[..., ms.Robot], name: str, floating_base: bool | None, floating: bool
) -> None:
    """Revolute, prismatic and continuous joints commute; only the free-flyer's SE(3) block needs the chart."""
    space = robot(name, floating_base=floating_base).space
    assert space.curved_blocks == ([(0, 6)] if floating else [])
    assert space.is_flat is (not floating)
