"""Work-precision studies: orders against theory, errors against independent references, the recommendation and
`run --tolerance` against scipy's DOP853, the pilot cache, the bench command's files, messages and signals."""

from __future__ import annotations

import csv
import json
import math
import re
import signal
import subprocess
import sys
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
import pytest
from conftest import joint, link, needs_native, urdf
from PIL import Image
from scipy.integrate import solve_ivp

import multibody_sim as ms
from multibody_sim import bench, native
from multibody_sim.cli import main

PREFIX = "multibody-sim: error: "
Q0_DP = [2.0, 0.5]  # double pendulum: q = 0 is upright; this swings through large angles (a nonlinear motion)
V0_DP = [0.0, 1.0]


# ---- independent references ------------------------------------------------------------------------------
def scipy_reference(robot: ms.Robot, q0: list[float], v0: list[float], duration: float) -> Callable[[float], tuple]:
    """(q, v) at any time in [0, duration] from scipy's DOP853 (rtol = atol = 1e-12) on a fixed-base robot.

    Independent of our integrators and stepping loop: only the forward dynamics (ABA, damping) is shared, and
    on revolute joints q' = v.
    """
    nq = robot.nq

    def rhs(_t: float, y: np.ndarray) -> np.ndarray:
        return np.concatenate([y[nq:], robot.forward_dynamics(y[:nq], y[nq:], np.zeros(robot.nv))])

    sol = solve_ivp(
        rhs, (0.0, duration), np.concatenate([q0, v0]), method="DOP853", rtol=1e-12, atol=1e-12, dense_output=True
    )
    assert sol.success
    return lambda t: (sol.sol(t)[:nq], sol.sol(t)[nq:])


def max_error(model: pin.Model, t: np.ndarray, Q: np.ndarray, V: np.ndarray, reference: Callable) -> float:
    """max over samples of ‖(q ⊖ q_ref, v − v_ref)‖∞, written out with Pinocchio's difference."""
    worst = 0.0
    for ti, q, v in zip(t, Q, V, strict=True):
        q_ref, v_ref = reference(ti)
        worst = max(worst, np.abs(pin.difference(model, q_ref, q)).max(), np.abs(v - v_ref).max())
    return float(worst)


def on_grid(trajectory: ms.Trajectory) -> Callable[[float], tuple]:
    """A trajectory as a reference function of its sample times."""
    return lambda t: (trajectory.q[np.argmin(abs(trajectory.t - t))], trajectory.v[np.argmin(abs(trajectory.t - t))])


# ---- orders ------------------------------------------------------------------------------------------------
# Theory: forward/backward Euler 1, explicit/implicit midpoint 2, RK4 4; the midpoint variational integrator 2.
THEORY = {"euler": 1, "midpoint": 2, "rk4": 4, "implicit_euler": 1, "implicit_midpoint": 2, "variational": 2}


@pytest.fixture(scope="module")
def order_study(robot: Callable[..., ms.Robot]) -> ms.WorkPrecision:
    """Every fixed-step method of THEORY on the damped double pendulum, on steps in the asymptotic range."""
    return ms.work_precision(
        robot("double_pendulum"),
        Q0_DP,
        V0_DP,
        duration=0.2,
        integrators=list(THEORY),
        steps=[0.0025, 0.00125, 0.000625, 0.0003125],
        output_dt=0.1,
        repeats=1,
    )


@pytest.mark.parametrize("name", list(THEORY))
def test_observed_order_matches_theory(order_study: ms.WorkPrecision, name: str) -> None:
    """The slope of log(error) against log(dt) over the finest 3 steps (a 4x range) is the classical order ±0.15."""
    fit = order_study.orders[name]
    assert fit.against == "dt" and fit.points == 3
    assert fit.observed == pytest.approx(THEORY[name], abs=0.15)
    assert fit.theoretical == THEORY[name] and not fit.mismatch


def test_adaptive_effective_order_against_evaluations(robot: Callable[..., ms.Robot]) -> None:
    """Adaptive methods: error ∝ evaluations^-p for an order-p pair's propagated solution (bs32 3, dp54 5), up to
    the steepening a step controller brings (here from p - 0.6 to 1.4 p); an effective order is never flagged."""
    study = ms.work_precision(
        robot("double_pendulum"),
        Q0_DP,
        V0_DP,
        duration=0.5,
        integrators=["bs32", "dp54"],
        tolerances=[10 ** (-k / 2) for k in range(8, 21)],
        repeats=1,
    )
    for name, order in (("bs32", 3), ("dp54", 5)):
        fit = study.orders[name]
        assert fit.against == "evaluations" and fit.points == bench.ADAPTIVE_FIT_POINTS
        assert order - 0.6 < fit.observed < 1.4 * order, (name, fit)
        assert not fit.mismatch


def test_mismatch_is_flagged_on_synthetic_errors() -> None:
    """An "rk4" whose errors fall as dt² (built by hand) is flagged; one that falls as dt⁴ is not."""
    dts = [0.01, 0.005, 0.0025]

    def study(power: int) -> ms.WorkPrecision:
        rows = [
            ms.Measurement("rk4", dt, None, None, "completed", error=1e-2 * (dt / 0.01) ** power, cpu_time=1 / dt)
            for dt in dts
        ]
        reference = bench.Reference("dp54", 1e-12, 1e-12, 1e-13, 1e-13, 1e-14, 100, 0.01)
        return ms.WorkPrecision("synthetic", 1.0, 0.02, [0.0], [0.0], reference, rows, {}, {}, {})

    slow = bench.observed_orders(study(2))["rk4"]
    assert slow.observed == pytest.approx(2.0) and slow.mismatch
    assert slow.note == "fitted on 0.01 s, 0.005 s, 0.0025 s: see the errors"
    good = bench.observed_orders(study(4))["rk4"]
    assert good.observed == pytest.approx(4.0) and not good.mismatch


def test_an_effective_order_is_reported_not_judged() -> None:
    """An adaptive "dp54" whose errors fall as evaluations^-12 (steep, as step controllers make them) is shown in
    the effective-order column and not flagged; a fixed-step method's is in the observed column."""
    tolerances = [10.0**-k for k in range(2, 9)]  # evaluations over a factor 3 (less reads as flat)
    rows = [
        ms.Measurement("dp54", None, tol, tol, "completed", error=tol, evaluations=int(1000 * tol ** (-1 / 12)))
        for tol in tolerances
    ] + [
        ms.Measurement("rk4", dt, None, None, "completed", error=1e-2 * (dt / 0.01) ** 4)
        for dt in (0.01, 0.005, 0.0025)
    ]
    reference = bench.Reference("dop853", 1e-14, 1e-14, 1e-15, 1e-15, 1e-16, 100, 0.01)
    study = ms.WorkPrecision("synthetic", 1.0, 0.02, [0.0], [0.0], reference, rows, {}, {}, {})
    study.orders = bench.observed_orders(study)
    fit = study.orders["dp54"]
    assert fit.against == "evaluations" and fit.observed == pytest.approx(12.0, rel=1e-2) and not fit.mismatch
    header, *lines = study.orders_table().splitlines()
    assert header.split("  ")[:4] == ["integrator", "order", "observed (vs dt)", "effective (vs evaluations)"]
    dp54 = next(line for line in lines if line.startswith("dp54"))
    rk4 = next(line for line in lines if line.startswith("rk4"))
    assert dp54.index("12.0") >= header.index("effective") and "MISMATCH" not in dp54
    assert header.index("observed") <= rk4.index("4.00") < header.index("effective")


def test_the_default_study_does_not_flag_rk4_on_the_double_pendulum(robot: Callable[..., ms.Robot]) -> None:
    """With a dp54 reference at 1e-12 (accurate to ~1e-11 here), RK4's 1 ms run fell within 10x of the reference's
    error, the fit moved to coarser steps and read 4.60: MISMATCH. The DOP853 reference at 1e-14 leaves the fine
    steps usable."""
    arm = robot("double_pendulum")
    study = ms.work_precision(arm, arm.default_pose(), np.zeros(2), duration=1.0, integrators=["rk4"], repeats=1)
    assert (study.reference.integrator, study.reference.rtol) == ("dop853", 1e-14)
    assert study.reference.error < 1e-12
    fit = study.orders["rk4"]
    assert not fit.mismatch and fit.observed == pytest.approx(4.0, abs=bench.ORDER_MISMATCH)  # 4.29 here
    assert 0.001 in [m.dt for m in study.for_integrator("rk4") if not m.below_reference]


# Machado, Oliveira & Fernandes (2009): full-severity simulation matrices in linear RGB.
COLOR_VISION = {
    "protanopia": [[0.152286, 1.052583, -0.204868], [0.114503, 0.786281, 0.099216], [-0.003882, -0.048116, 1.051998]],
    "deuteranopia": [[0.367322, 0.860646, -0.227968], [0.280085, 0.672501, 0.047413], [-0.011820, 0.042940, 0.968881]],
    "tritanopia": [[1.255528, -0.076749, -0.178779], [-0.078411, 0.930809, 0.147602], [0.004733, 0.691367, 0.303900]],
}


def closest_pair_seen_as(colors: list[str], matrix: list[list[float]]) -> float:
    """The smallest distance (sRGB, 0..1) between two of the colours as a viewer with that deficiency sees them."""

    def linear(hex_color: str) -> np.ndarray:
        c = np.array([int(hex_color[i : i + 2], 16) for i in (1, 3, 5)]) / 255
        return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)

    def srgb(c: np.ndarray) -> np.ndarray:
        c = np.clip(c, 0, 1)
        return np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)

    seen = [srgb(np.array(matrix) @ linear(c)) for c in colors]
    return min(float(np.linalg.norm(a - b)) for i, a in enumerate(seen) for b in seen[i + 1 :])


def test_every_integrator_has_its_own_colour_blind_safe_colour(tmp_path: Path) -> None:
    colors = [bench.METHOD_COLORS[bench.results._color_index(name)] for name in ms.INTEGRATORS]
    assert len(set(colors)) == len(ms.INTEGRATORS)
    for matrix in COLOR_VISION.values():
        assert closest_pair_seen_as(colors, matrix) > 0.1
    # The check can fail: matplotlib's default cycle has two colours 0.066 apart for a deuteranope.
    tab10 = [
        "#1f77b4",
        "#ff7f0e",
        "#2ca02c",
        "#d62728",
        "#9467bd",
        "#8c564b",
        "#e377c2",
        "#7f7f7f",
        "#bcbd22",
        "#17becf",
    ]
    assert closest_pair_seen_as(tab10, COLOR_VISION["deuteranopia"]) < 0.1
    # The PNG draws each method in its colour (its markers' centres carry it exactly).
    rows = [
        ms.Measurement(name, dt, None, None, "completed", error=dt**k, cpu_time=1 / dt, evaluations=int(4 / dt))
        for k, name in ((1, "euler"), (2, "midpoint"), (4, "rk4"))
        for dt in (0.01, 0.005, 0.0025)
    ]
    reference = bench.Reference("dop853", 1e-14, 1e-14, 1e-15, 1e-15, 1e-16, 100, 0.01)
    study = ms.WorkPrecision("synthetic", 1.0, 0.02, [0.0], [0.0], reference, rows, {}, {}, {})
    study.orders = bench.observed_orders(study)
    png = np.asarray(Image.open(bench.plot_work_precision(study, tmp_path / "wp.png")).convert("RGB")).reshape(-1, 3)
    palette = {tuple(int(c[i : i + 2], 16) for i in (1, 3, 5)) for c in bench.METHOD_COLORS} - {(0, 0, 0)}
    present = palette & set(map(tuple, png))  # black is the axes' colour too: not counted
    drawn = {bench.METHOD_COLORS[bench.results._color_index(name)] for name in ("euler", "midpoint", "rk4")}
    assert {f"#{r:02X}{g:02X}{b:02X}" for r, g, b in present} == drawn


# ---- errors against independent computations -----------------------------------------------------------------
@pytest.mark.parametrize("name", ["double_pendulum", "free_body"])
def test_reported_error_is_the_contract_error(robot: Callable[..., ms.Robot], name: str) -> None:
    """The error in the table equals max over samples of ‖(q ⊖ q_ref, v − v_ref)‖∞ computed here from two
    simulate() runs (the reference: bench's reference integrator at its tolerance, checked 10x tighter); also on a
    spinning floating base."""
    system = robot(name)
    rng = np.random.default_rng(7)
    q0 = system.random_configuration(rng) if name == "free_body" else np.array(Q0_DP)
    v0 = rng.uniform(-2, 2, system.nv) if name == "free_body" else np.array(V0_DP)
    study = ms.work_precision(
        system, q0, v0, duration=0.4, integrators=["rk4", "bs32"], steps=[0.02, 0.01], tolerances=[1e-5], repeats=1
    )
    method, tol = bench.REFERENCE_INTEGRATOR, bench.REFERENCE_TOLERANCE
    ref = ms.simulate(system, q0, v0, duration=0.4, dt=1e-3, integrator=method, rtol=tol, atol=tol, output_dt=0.02)
    check = ms.simulate(
        system, q0, v0, duration=0.4, dt=1e-3, integrator=method, rtol=tol / 10, atol=tol / 10, output_dt=0.02
    )
    assert study.reference.error == max_error(system.model, check.t, ref.q, ref.v, on_grid(check))
    for m in study.measurements:
        run = ms.simulate(system, q0, v0, duration=0.4, output_dt=0.02, **m.simulate_options())
        assert m.error == pytest.approx(max_error(system.model, run.t, run.q, run.v, on_grid(ref)), rel=1e-12)
        assert m.energy_error == pytest.approx(np.abs(run.energy_error).max(), rel=1e-12)
        assert m.evaluations == run.stats["evaluations"] and m.steps == run.stats["steps"]
        assert m.error > 0 and not m.below_reference
    # And the reference itself is as good as it says, against scipy (fixed base only: q' = v there).
    if name == "double_pendulum":
        true = max_error(system.model, ref.t, ref.q, ref.v, scipy_reference(system, Q0_DP, V0_DP, 0.4))
        assert true < 1e-10 and study.reference.error < 1e-10


def test_a_loose_reference_is_detected(robot: Callable[..., ms.Robot]) -> None:
    """A reference at rtol 1e-4: its refinement check estimates its true error (against scipy) within 3x, and the
    runs more accurate than it can tell are flagged, left out of the fit and never recommended for less."""
    system = robot("double_pendulum")
    study = ms.work_precision(
        system,
        Q0_DP,
        V0_DP,
        duration=0.5,
        integrators=["rk4"],
        steps=[0.02, 0.01, 0.005, 0.0025, 0.00125],
        reference_tolerance=1e-4,
        repeats=1,
    )
    r = study.reference
    true = max_error(system.model, r.t, r.q, r.v, scipy_reference(system, Q0_DP, V0_DP, 0.5))
    assert true > 1e-6  # it is loose indeed
    assert 1 / 3 < r.error / true < 3
    flagged = [m for m in study.measurements if m.below_reference]
    assert flagged and all(m.error < bench.REFERENCE_MARGIN * r.error for m in flagged)
    assert all(not m.below_reference for m in study.measurements if m.error >= bench.REFERENCE_MARGIN * r.error)
    # The ladder stops at the first run it cannot tell from the reference: finer ones would measure nothing.
    assert study.measurements[-1] is flagged[0] and len(flagged) == 1
    assert study.orders["rk4"].points <= len(study.measurements) - 1
    assert ms.recommend(study, r.error / 2) is None  # nothing can be certified below the reference's own error


# ---- the recommendation --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def menu(robot: Callable[..., ms.Robot]) -> ms.WorkPrecision:
    """Five integrators on the double pendulum over 0.5 s (the recommendation tests choose among these)."""
    return ms.work_precision(
        robot("double_pendulum"),
        Q0_DP,
        V0_DP,
        duration=0.5,
        integrators=["euler", "midpoint", "rk4", "dp54", "implicit_midpoint"],
        steps=[0.02, 0.01, 0.005, 0.002, 0.001],
        tolerances=[1e-3, 1e-4, 1e-5, 1e-6, 1e-7, 1e-8],
        repeats=1,
    )


@pytest.fixture(scope="module")
def independent(menu: ms.WorkPrecision, robot: Callable[..., ms.Robot]) -> dict[int, float]:
    """Each completed configuration of `menu` re-run with simulate() and measured against scipy's DOP853."""
    system = robot("double_pendulum")
    exact = scipy_reference(system, Q0_DP, V0_DP, 0.5)
    errors = {}
    for m in menu.measurements:
        if m.completed:
            run = ms.simulate(system, Q0_DP, V0_DP, duration=0.5, output_dt=menu.output_dt, **m.simulate_options())
            errors[id(m)] = max_error(system.model, run.t, run.q, run.v, exact)
    return errors


@pytest.mark.parametrize("tolerance", [1e-2, 1e-4, 1e-6])
def test_recommendation_meets_the_tolerance_and_is_the_cheapest(
    menu: ms.WorkPrecision, independent: dict[int, float], tolerance: float
) -> None:
    """Re-run independently, the recommended configuration's error against scipy is within the tolerance; and
    no measured configuration that (by the same independent check) meets it costs less CPU time."""
    chosen = ms.recommend(menu, tolerance)
    assert chosen is not None
    assert independent[id(chosen)] <= tolerance
    # Configurations within 1 % of the tolerance are too close to call either way: left out of the comparison.
    meeting = [m for m in menu.measurements if m.completed and independent[id(m)] <= 0.99 * tolerance]
    assert meeting and all(chosen.cpu_time <= m.cpu_time for m in meeting)
    by_evaluations = ms.recommend(menu, tolerance, cost="evaluations")
    assert all(by_evaluations.evaluations <= m.evaluations for m in meeting)


def test_recommend_refuses_bad_arguments(menu: ms.WorkPrecision) -> None:
    with pytest.raises(ms.InvalidArgumentError, match=re.escape("tolerance must be a positive number, got 0")):
        ms.recommend(menu, 0)
    with pytest.raises(
        ms.InvalidArgumentError,
        match=re.escape("cost must be one of 'cpu_time', 'wall_time', 'evaluations', got 'money'"),
    ):
        ms.recommend(menu, 1e-3, cost="money")


# ---- failures are recorded, not raised ---------------------------------------------------------------------
STIFF = urdf(
    link("base", mass=2.0, com="0 0 0.05"),
    link("upper", mass=1.0),
    link("tip", mass=0.01, inertia="0.0001 0.0001 0.0001"),
    joint("shoulder", "base", "upper", damping=0.05),
    joint("elbow", "upper", "tip", xyz="0 0 -1", damping=100.0),
    name="stiff",
)


def test_divergence_and_refusal_are_statuses(write_urdf: Callable[..., Path], robot: Callable[..., ms.Robot]) -> None:
    """Explicit Euler on the stiff elbow (decay rate ≈ 100 / 2.6e-3 ≈ 4e4 /s: stable only for dt < 2/λ ≈ 5e-5 s)
    diverges at 10 ms and is recorded as such while implicit Euler completes; variational refuses a floating base
    (recorded when no integrator set is named, an error when it is named)."""
    stiff = ms.load_robot(write_urdf(STIFF))
    study = ms.work_precision(
        stiff, [0.3, 0.0], [0.0, 0.0], duration=0.2, integrators=["euler", "implicit_euler"], steps=[0.01], repeats=1
    )
    (euler,) = study.for_integrator("euler")
    (implicit,) = study.for_integrator("implicit_euler")
    assert euler.status == "diverged" and math.isnan(euler.error) and euler.message.startswith("diverged at t = ")
    assert implicit.completed and implicit.error < 0.1
    assert "diverged at dt 0.01 s" in study.orders_table()

    body = robot("free_body")
    study = ms.work_precision(
        body, body.neutral(), np.ones(6), duration=0.05, steps=[0.01], tolerances=[1e-4], repeats=1, output_dt=0.05
    )
    (refused,) = study.for_integrator("variational")
    with pytest.raises(ms.InvalidArgumentError) as expected:
        ms.INTEGRATORS["variational"].check_system(body)
    assert refused.status == "refused" and refused.message == str(expected.value).split(";")[0]
    assert {m.integrator for m in study.measurements if m.completed} == set(ms.INTEGRATORS) - {"variational"}
    with pytest.raises(ms.InvalidArgumentError, match=re.escape(str(expected.value))):
        ms.work_precision(body, body.neutral(), np.ones(6), duration=0.05, integrators=["variational"])


# ---- files ------------------------------------------------------------------------------------------------------
def test_tables_and_picture_round_trip(order_study: ms.WorkPrecision, tmp_path: Path) -> None:
    """CSV rows are the measurements (floats exact through repr); the JSON reads back to the same study; the PNG
    is a PNG."""
    written = order_study.write(tmp_path)
    with open(written["csv"], newline="") as f:
        rows = list(csv.DictReader(f))
    assert len(rows) == len(order_study.measurements)
    by_key = {(m.integrator, m.dt): m for m in order_study.measurements}
    for row in rows:
        m = by_key[(row["integrator"], float(row["dt"]))]
        assert float(row["error"]) == m.error and int(row["evaluations"]) == m.evaluations
        assert row["status"] == "completed" and row["rtol"] == ""
    again = ms.WorkPrecision.from_json(written["json"])
    assert again.to_dict() == order_study.to_dict()
    assert json.loads(Path(written["json"]).read_text())["complete"] is True
    assert Path(written["png"]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


# ---- run --tolerance and its cache ---------------------------------------------------------------------------
CHOICE = re.compile(
    r"^tolerance (?P<tol>\S+) over the first (?P<horizon>\S+) s: chose (?P<integrator>\w+), (?P<settings>.+?) "
    r"\((?P<cached>cached )?pilot study: error (?P<error>\S+) \+ reference"
)


def call(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    code = main(list(args))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def test_run_tolerance_chooses_says_so_and_meets_it(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, robot: Callable
) -> None:
    """`run --tolerance 1e-5` says what it chose before running it; every sample of the run within the pilot
    horizon is within 1e-5 of scipy's DOP853; a second call takes its choice from the cache."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    args = ["run", "double_pendulum", "--q0", "2", "0.5", "--v0", "0", "1", "--duration", "1.5", "--tolerance", "1e-5"]
    code, out, err = call(capsys, *args, "--out", str(tmp_path / "a.npz"))
    assert (code, err) == (0, "")
    lines = out.splitlines()
    assert lines[0] == "pilot study: every integrator over the first 1 s (cached for the next run) ..."
    said = CHOICE.match(lines[1])
    assert said and said["tol"] == "1e-05" and said["horizon"] == "1" and not said["cached"]
    assert float(said["error"]) <= 1e-5
    assert lines[2].startswith(f"run: double_pendulum (fixed base, nq 2, nv 2), integrator {said['integrator']}, ")
    traj = ms.Trajectory.load(tmp_path / "a.npz")
    assert traj.metadata["integrator"] == said["integrator"] and traj.t[-1] == 1.5
    system = robot("double_pendulum")
    exact = scipy_reference(system, [2.0, 0.5], [0.0, 1.0], 1.0)
    within = traj.t <= 1.0 + 1e-12
    assert max_error(system.model, traj.t[within], traj.q[within], traj.v[within], exact) <= 1e-5

    code, out2, err = call(capsys, *args)
    again = CHOICE.match(out2.splitlines()[0])
    assert (code, err) == (0, "") and again and again["cached"]
    assert (again["integrator"], again["settings"], again["error"]) == (
        said["integrator"],
        said["settings"],
        said["error"],
    )


def count_studies(monkeypatch: pytest.MonkeyPatch) -> list[int]:
    """A list that gains an entry each time choose_integrator runs a study (rather than reading its cache)."""
    studies: list[int] = []
    work_precision = bench.work_precision

    def counted(*args: Any, **kw: Any) -> Any:
        studies.append(1)
        return work_precision(*args, **kw)

    monkeypatch.setattr(bench.pilot, "work_precision", counted)  # where choose_integrator finds it
    return studies


def test_pilot_cache_is_read_and_a_corrupt_entry_is_rebuilt(
    tmp_path: Path, robot: Callable, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The second choose_integrator call reads the cache (no study is run again, same choice); a corrupted cache
    file is ignored, said so, rebuilt as a valid entry, and used by the next call."""
    system = robot("double_pendulum")
    kwargs = {"tolerance": 1e-4, "duration": 0.2, "cache_dir": tmp_path, "integrators": ["midpoint", "rk4", "dp54"]}
    studies = count_studies(monkeypatch)
    first = ms.choose_integrator(system, Q0_DP, V0_DP, **kwargs)
    second = ms.choose_integrator(system, Q0_DP, V0_DP, **kwargs)
    assert not first.cached and second.cached and second.cache_path == first.cache_path
    assert len(studies) == 1  # the second call ran no study
    assert second.measurement == first.measurement

    first.cache_path.write_text('{"format": "multibody-sim work-precision", "truncated')
    rebuilt = ms.choose_integrator(system, Q0_DP, V0_DP, **kwargs)
    assert not rebuilt.cached and rebuilt.note.startswith("ignored an unreadable pilot cache entry (")
    assert rebuilt.note.endswith("; rebuilt it")
    assert json.loads(first.cache_path.read_text())["complete"] is True
    assert ms.choose_integrator(system, Q0_DP, V0_DP, **kwargs).cached
    # A different initial state is a different entry.
    other = ms.choose_integrator(system, [2.0, 0.4], V0_DP, **{**kwargs, "tolerance": 1e-2})
    assert not other.cached and other.cache_path != first.cache_path


@needs_native
def test_the_pilot_measures_on_the_kernel_the_run_takes_and_caches_each_apart(
    tmp_path: Path, robot: Callable, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A pilot measured on the Python kernel (MULTIBODY_SIM_NATIVE=0) does not answer for a native run, nor the
    reverse: each kernel has its own cache entry, and each study's runs say which kernel ran them."""
    system = robot("double_pendulum")
    kwargs = {"tolerance": 1e-3, "duration": 0.1, "cache_dir": tmp_path, "integrators": ["rk4", "dp54"]}
    monkeypatch.setenv(native.ENV, "0")
    python = ms.choose_integrator(system, Q0_DP, V0_DP, **kwargs)
    monkeypatch.setenv(native.ENV, "1")
    compiled = ms.choose_integrator(system, Q0_DP, V0_DP, **kwargs)
    assert not python.cached and not compiled.cached and compiled.cache_path != python.cache_path
    assert {m.kernel for m in python.study.measurements} == {"python (row)"}
    assert {m.kernel for m in compiled.study.measurements} == {"native"}
    assert " s CPU on the native kernel; cheapest of " in compiled.describe()
    assert " s CPU on the python (row) kernel; cheapest of " in python.describe()
    monkeypatch.setenv(native.ENV, "0")
    again = ms.choose_integrator(system, Q0_DP, V0_DP, **kwargs)
    assert again.cached and again.cache_path == python.cache_path
    said = "kernel measured (the one each run takes): python (row) for rk4, dp54 (not native: MULTIBODY_SIM_NATIVE=0)"
    assert said in again.study.summary().splitlines()
    assert "kernel measured (the one each run takes): native for rk4, dp54" in compiled.study.summary().splitlines()


def test_the_pilot_runs_under_the_controller_and_keys_its_cache_on_it(
    tmp_path: Path, robot: Callable, monkeypatch: pytest.MonkeyPatch
) -> None:
    """Under gravity compensation from rest the double pendulum does not move (M q̈ = g - g = 0), so the pilot's
    reference stays at q0 while the unforced one falls; a built-in controller is cached under its recipe (another
    gain is another entry), and a controller of the user's own is measured but not cached."""
    system = robot("double_pendulum")
    q0 = [0.7, -0.4]
    kwargs = {"tolerance": 1e-4, "duration": 0.2, "cache_dir": tmp_path, "integrators": ["rk4", "dp54"]}
    studies = count_studies(monkeypatch)
    held = ms.make_controller("gravity_compensation", system)
    still = ms.choose_integrator(system, q0, [0.0, 0.0], controller=held, **kwargs)
    assert np.abs(np.asarray(still.study.reference.q) - q0).max() < 1e-12
    assert still.study.settings["controller"] == "GravityCompensation"
    free = ms.choose_integrator(system, q0, [0.0, 0.0], **kwargs)
    assert np.abs(np.asarray(free.study.reference.q) - q0).max() > 1e-2  # it falls
    assert free.cache_path != still.cache_path
    assert ms.choose_integrator(system, q0, [0.0, 0.0], controller=held, **kwargs).cached
    assert len(studies) == 2
    pd = {gain: ms.make_controller("pd", system, ["q_ref=0.7,-0.4", f"kp={gain}"]) for gain in (5, 50)}
    first = ms.choose_integrator(system, q0, [0.0, 0.0], controller=pd[5], **kwargs)
    other = ms.choose_integrator(system, q0, [0.0, 0.0], controller=pd[50], **kwargs)
    assert not other.cached and other.cache_path != first.cache_path and len(studies) == 4

    def own(t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        return np.zeros(2)

    mine = ms.choose_integrator(system, q0, [0.0, 0.0], controller=own, **kwargs)
    again = ms.choose_integrator(system, q0, [0.0, 0.0], controller=own, **kwargs)
    assert not again.cached and len(studies) == 6
    assert mine.note == "the pilot study is not cached: a controller of your own has no description to key the cache on"


def test_bench_and_run_tolerance_take_the_scene_controller(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A scene with a [controller] is benchmarked and piloted under it (the motion the run makes), and says so."""
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "cache"))
    scene = ms.load_scene("panda_push")
    name = scene.spec.controller.name
    code, out, err = call(
        capsys, "bench", "panda_push", "--duration", "0.04", "--integrators", "timestepping", "--out", str(tmp_path)
    )
    assert (code, err) == (0, "")
    header = [line for line in out.splitlines() if line.startswith("bench: panda_push")]
    assert header and header[0].endswith(f", duration 0.04 s, controller {name} every 0.001 s")
    assert " under its controller (" in out
    study = ms.WorkPrecision.from_json(tmp_path / "work_precision.json")
    assert study.settings["controller"] is not None
    code, out, err = call(capsys, "run", "panda_push", "--duration", "0.04", "--tolerance", "1e-2")
    assert (code, err) == (0, ""), err
    assert any(CHOICE.match(line) for line in out.splitlines())


def test_an_unreferenced_motion_is_said_to_be_one() -> None:
    """A study whose reference did not converge says so instead of calling the motion too simple."""
    base = {
        "integrator": "timestepping",
        "rtol": math.nan,
        "atol": math.nan,
        "check_rtol": math.nan,
        "check_atol": math.nan,
        "evaluations": 10,
        "wall_time": 0.1,
        "dt": 2e-5,
        "check_dt": 1e-5,
        "t": np.zeros(1),
        "q": np.zeros((1, 1)),
        "v": np.zeros((1, 1)),
    }
    for error, said in ((46.0, "note: the reference did not converge"), (1e-9, "note: every run is as accurate")):
        study = ms.WorkPrecision(
            system="x",
            duration=1.0,
            output_dt=0.02,
            q0=[0.0],
            v0=[0.0],
            reference=bench.Reference(error=error, **base),
            measurements=[
                bench.Measurement(
                    "timestepping", 1e-3, None, None, bench.STATUS_COMPLETED, error=error / 100, below_reference=True
                )
            ],
            orders={},
            settings={},
            metadata={},
            complete=True,
        )
        assert said in study.summary()


def test_an_unreachable_tolerance_is_a_clear_error(tmp_path: Path, robot: Callable) -> None:
    with pytest.raises(ms.InvalidArgumentError) as raised:
        ms.choose_integrator(
            robot("double_pendulum"),
            Q0_DP,
            V0_DP,
            tolerance=1e-14,
            duration=0.1,
            integrators=["rk4"],
            cache_dir=tmp_path,
        )
    assert re.fullmatch(
        r"no integrator met tolerance 1e-14 over the first 0\.1 s in the pilot study \(the most accurate was rk4, "
        r"dt \S+ s: \S+; the reference is accurate to ~\S+\): ask for a looser tolerance",
        str(raised.value),
    ), str(raised.value)


# ---- the bench command ------------------------------------------------------------------------------------------
def test_bench_prints_orders_and_recommendations_and_writes_files(
    capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    code, out, err = call(
        capsys,
        "bench",
        "double_pendulum",
        "--q0",
        "2",
        "0.5",
        "--integrators",
        "rk4,dp54",
        "--duration",
        "0.1",
        "--out",
        str(tmp_path / "wp"),
    )
    assert (code, err) == (0, "")
    saved = ms.WorkPrecision.from_json(tmp_path / "wp" / "work_precision.json")
    assert set(saved.integrators()) == {"rk4", "dp54"} and saved.complete
    assert saved.orders_table() in out  # the table printed is the saved study's
    for row in saved.orders_table().splitlines()[1:]:
        name, order, observed = row.split()[:3]
        assert int(order) == ms.INTEGRATORS[name].order
    assert "recommended (least CPU time" in out
    # The default report is concise: the header, the study's summary and the files; --verbose adds a line per run.
    assert out.startswith("bench: double_pendulum (fixed base, nq 2, nv 2), duration 0.1 s\n\nwork-precision study")
    assert " evals" not in out
    code, verbose, _ = call(
        capsys, "bench", "double_pendulum", "--q0", "2", "0.5", "--integrators", "rk4", "--duration", "0.1",
        "--out", str(tmp_path / "v"), "--verbose",
    )  # fmt: skip
    runs = ms.WorkPrecision.from_json(tmp_path / "v" / "work_precision.json").for_integrator("rk4")
    assert code == 0 and sum(line.endswith(" evals") for line in verbose.splitlines()) == len(runs)
    for tol in (1e-2, 1e-4, 1e-6, 1e-8):
        rec = ms.recommend(saved, tol)
        assert re.search(rf"^  {tol:.0e}  +{rec.integrator} +{re.escape(rec.settings())} ", out, re.M) if rec else True
    assert (tmp_path / "wp" / "work_precision.csv").is_file() and (tmp_path / "wp" / "work_precision.png").is_file()


def _bad_inputs(tmp: Path) -> list[tuple[list[str], str]]:
    a_file = tmp / "a_file"
    a_file.write_text("")
    body = ms.load_robot("solo12")
    try:
        ms.INTEGRATORS["variational"].check_system(body)
    except ms.InvalidArgumentError as exc:
        refusal = str(exc)
    valid = ", ".join(sorted(ms.INTEGRATORS))
    dp = ["double_pendulum"]
    tol = ["run", *dp, "--tolerance", "1e-6"]
    chooses = "--tolerance chooses the integrator and its step or tolerances: drop {} (or drop --tolerance and choose "
    chooses += "them yourself)"
    return [
        (["bench", *dp, "--integrators", "rk4,rk5"], f"unknown integrator 'rk5' (did you mean rk4? valid: {valid})"),
        (
            ["bench", *dp, "--integrators", ","],
            "--integrators: name at least one integrator (e.g. --integrators rk4,dp54)",
        ),
        (["bench", *dp, "--duration", "0"], "duration must be a positive number of seconds, got 0.0"),
        (["bench", *dp, "--q0", "1"], "q0 must have shape (2,), got (1,)"),
        (
            ["bench", *dp, "--out", str(a_file)],
            f"--out {a_file}: is a file, expected a folder for work_precision.csv, .json and .png",
        ),
        (["bench", "solo12", "--integrators", "variational"], refusal),
        ([*tol, "--integrator", "rk4"], chooses.format("--integrator")),
        ([*tol, "--dt", "0.01", "--rtol", "1e-3"], chooses.format("--dt, --rtol")),
        (["run", *dp, "--tolerance", "-1"], "tolerance must be a positive number, got -1.0"),
        (
            ["bench", *dp, "--param", "kp=1"],
            f"--param needs --controller NAME (valid: {', '.join(sorted(ms.CONTROLLERS))})",
        ),
        (
            ["bench", *dp, "--controller", "pd"],
            "controller 'pd' needs q_ref=..., kp=... (parameters: kd, kp (required), q_ref (required), v_ref)",
        ),
    ]


def test_bad_input_is_one_exact_line_and_exit_2(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    for argv, message in _bad_inputs(tmp_path):
        code, out, err = call(capsys, *argv)
        assert (code, out, err) == (2, "", PREFIX + message + "\n"), argv


# ---- signals -----------------------------------------------------------------------------------------------------
def _interrupt_bench(sig: signal.Signals, out: Path) -> subprocess.CompletedProcess[str]:
    """Start a bench far too long to finish, signal it once it measures, and collect what it says."""
    script = Path(sys.executable).with_name("multibody-sim")
    # A shell may start background jobs with SIGINT ignored; restore the default as a real Ctrl-C would find it.
    reset = "import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); os.execv(sys.argv[1], sys.argv[1:])"
    args = [sys.executable, "-c", reset, str(script), "bench", "double_pendulum", "--duration", "2", "--verbose"]
    args += ["--out", str(out)]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    watchdog = threading.Timer(90.0, proc.kill)
    watchdog.start()
    try:
        assert proc.stdout is not None
        header = "".join(proc.stdout.readline() for _ in range(3))  # header, "measuring ...", "reference: ..."
        proc.send_signal(sig)  # the handlers are in place, and the reference is done: measurements are under way
        stdout, stderr = proc.communicate(timeout=90)
    finally:
        watchdog.cancel()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return subprocess.CompletedProcess(args, proc.returncode, header + stdout, stderr)


def test_signals_stop_the_bench_and_keep_the_measurements(tmp_path: Path) -> None:
    """SIGINT / SIGTERM: exit 130 / 143, one line on stderr, the partial study written (complete: false)."""
    results: dict[str, subprocess.CompletedProcess[str]] = {}
    threads = [
        threading.Thread(target=lambda s=s: results.__setitem__(s.name, _interrupt_bench(s, tmp_path / s.name)))
        for s in (signal.SIGINT, signal.SIGTERM)
    ]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for sig, code in ((signal.SIGINT, 130), (signal.SIGTERM, 143)):
        done = results[sig.name]
        assert done.returncode == code, done.stderr
        expected = f"bench: double_pendulum (fixed base, nq 2, nv 2), duration 2 s\nmeasuring {len(ms.INTEGRATORS)} "
        assert done.stdout.startswith(expected)
        (line,) = done.stderr.splitlines()
        assert re.fullmatch(
            rf"multibody-sim: {sig.name}: interrupted after \d+ measurements; partial results written to "
            + re.escape(str(tmp_path / sig.name)),
            line,
        )
        saved = ms.WorkPrecision.from_json(tmp_path / sig.name / "work_precision.json")
        assert saved.complete is False and saved.reference is not None
        assert "(INTERRUPTED: partial results)" in done.stdout
