"""Trajectories as tables: column names as documented, values equal to the arrays, CSV and Parquet round trips."""

from __future__ import annotations

import csv as csv_module
import dataclasses
import importlib.util
import json
import os
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest
from conftest import joint, link, urdf

import multibody_sim as ms
from multibody_sim import tables
from multibody_sim.cli import main
from multibody_sim.integrators.cone_solver import TOLERANCE
from multibody_sim.trajectory import write_chunk

for _module in ("pandas", "pyarrow"):
    if importlib.util.find_spec(_module) is None:  # in the test extra: CI must have them
        _reason = f"{_module} is not installed (pip install -e '.[test]')"
        if os.environ.get("CI") == "true":
            pytest.fail(_reason, pytrace=False)
        pytest.skip(_reason, allow_module_level=True)
import pandas as pd  # noqa: E402
import pyarrow.parquet as pq  # noqa: E402

PREFIX = "multibody-sim: error: "
ENERGIES = ["kinetic_energy", "potential_energy", "total_energy", "work", "dissipated", "energy_error"]


def _run(system: ms.Robot, duration: float = 0.05) -> ms.Trajectory:
    rng = np.random.default_rng(3)
    v0 = rng.normal(size=system.nv)
    return ms.simulate(system, system.neutral(), v0, duration=duration, dt=1e-3, output_dt=0.01)


def _check_values(frame: pd.DataFrame, run: ms.Trajectory, q_columns: list[str], dof_columns: list[str]) -> None:
    """Every column holds the trajectory's own array, bit for bit."""
    np.testing.assert_array_equal(frame["t"].to_numpy(), run.t)
    np.testing.assert_array_equal(frame[q_columns].to_numpy(), run.q)
    np.testing.assert_array_equal(frame[[f"v.{d}" for d in dof_columns]].to_numpy(), run.v)
    np.testing.assert_array_equal(frame[[f"tau.{d}" for d in dof_columns]].to_numpy(), run.tau)
    for name in ENERGIES:
        np.testing.assert_array_equal(frame[name].to_numpy(), getattr(run, name))
    for name, entry in run.ledger.items():
        np.testing.assert_array_equal(frame[f"ledger.{name}"].to_numpy(), entry.energy)


def test_fixed_base_columns_are_joint_names(robot: Callable[..., ms.Robot]) -> None:
    panda = robot("panda")
    run = _run(panda)
    q_columns = [f"q.{name}" for name in panda.joint_names]  # one coordinate per joint
    expected = ["t", *q_columns, *(f"v.{d}" for d in panda.dof_names), *(f"tau.{d}" for d in panda.dof_names)]
    expected += [*ENERGIES, "ledger.joint_torques", "ledger.joint_damping"]
    for frame in (run.to_dataframe(), run.to_dataframe(robot=panda)):  # names from the metadata, or the robot
        assert list(frame.columns) == expected
        assert len(frame) == len(run.t) and all(frame.dtypes == np.float64)
        _check_values(frame, run, q_columns, panda.dof_names)
    assert frame.attrs == {
        "robot": "panda",
        "integrator": "rk4",
        "status": "completed",
        "ledger_kinds": {"joint_torques": "work", "joint_damping": "dissipated"},
    }


def test_floating_base_coordinates_are_named(robot: Callable[..., ms.Robot]) -> None:
    solo = robot("solo12")
    run = _run(solo)
    q_columns = [f"q.root_joint.{c}" for c in ("x", "y", "z", "qx", "qy", "qz", "qw")]
    q_columns += [f"q.{name}" for name in solo.joint_names[1:]]
    v_names = [f"root_joint.{c}" for c in ("vx", "vy", "vz", "wx", "wy", "wz")] + solo.joint_names[1:]
    assert solo.dof_names == v_names
    for frame in (run.to_dataframe(), run.to_dataframe(robot=solo)):
        assert list(frame.columns[: 1 + solo.nq + 2 * solo.nv]) == [
            "t",
            *q_columns,
            *(f"v.{d}" for d in v_names),
            *(f"tau.{d}" for d in v_names),
        ]
        _check_values(frame, run, q_columns, v_names)
    np.testing.assert_allclose(np.linalg.norm(frame[q_columns[3:7]].to_numpy(), axis=1), 1.0, atol=1e-12)


def test_continuous_joints_are_cos_and_sin(robot: Callable[..., ms.Robot]) -> None:
    pendulum = robot("double_pendulum_continuous")
    run = _run(pendulum)
    q_columns = [f"q.{name}.{part}" for name in pendulum.joint_names for part in ("cos", "sin")]
    for frame in (run.to_dataframe(), run.to_dataframe(robot=pendulum)):
        assert list(frame.columns[1:5]) == q_columns
        _check_values(frame, run, q_columns, pendulum.dof_names)
        angle = np.arctan2(frame[q_columns[1]], frame[q_columns[0]])
        np.testing.assert_allclose(np.cos(angle), run.q[:, 0], atol=1e-15)


def test_mixed_continuous_and_revolute_joints_load_the_robot(write_urdf: Callable[..., Path]) -> None:
    """Names alone cannot tell which one-dof joint has two coordinates: the robot is loaded from the metadata."""
    text = urdf(
        link("base"),
        link("a"),
        link("b"),
        joint("hinge", "base", "a"),
        joint("wheel", "a", "b", kind="continuous", xyz="0 0 -1"),
    )
    arm = ms.load_robot(write_urdf(text))
    run = _run(arm)
    frame = run.to_dataframe()
    assert list(frame.columns[1:4]) == ["q.hinge", "q.wheel.cos", "q.wheel.sin"]
    _check_values(frame, run, ["q.hinge", "q.wheel.cos", "q.wheel.sin"], ["hinge", "wheel"])


def test_scene_constraints_and_ledger_elements_are_columns() -> None:
    scene = ms.load_scene(Path(__file__).resolve().parents[1] / "models" / "scenes" / "four_bar.toml")
    run = scene.run(duration=0.02)
    frame = run.to_dataframe()
    assert [c for c in frame.columns if c.startswith("ledger.")] == [f"ledger.{name}" for name in run.ledger]
    (name, record), *_ = run.constraints.items()
    force = [f"constraint.{name}.force[{k}]" for k in range(record.force.shape[1])]
    assert list(frame.columns[-len(force) - 2 :]) == [
        *force,
        f"constraint.{name}.drift",
        f"constraint.{name}.velocity_drift",
    ]
    np.testing.assert_array_equal(frame[force].to_numpy(), record.force)
    np.testing.assert_array_equal(frame[f"constraint.{name}.drift"].to_numpy(), record.drift)
    np.testing.assert_array_equal(frame[f"constraint.{name}.velocity_drift"].to_numpy(), record.velocity_drift)


def test_without_metadata_columns_are_indexed(robot: Callable[..., ms.Robot]) -> None:
    run = dataclasses.replace(_run(robot("ur5")), metadata={})
    frame = run.to_dataframe()
    assert list(frame.columns[:3]) == ["t", "q[0]", "q[1]"] and "v[5]" in frame and "tau[0]" in frame


@pytest.mark.parametrize("block", [7, 100_000])  # several blocks per file, and one
def test_csv_and_parquet_read_back_exactly(
    robot: Callable[..., ms.Robot], tmp_path: Path, monkeypatch: pytest.MonkeyPatch, block: int
) -> None:
    monkeypatch.setattr(tables, "_BLOCK_ROWS", block)
    run = _run(robot("solo12"), duration=0.2)
    expected = run.to_dataframe()
    csv = tables.write_table(run, tmp_path / "run.csv")
    back = pd.read_csv(csv)
    pd.testing.assert_frame_equal(back, expected, check_exact=True, check_like=False)
    with csv.open(newline="") as f:  # read without pandas too: Python's own float() gets every bit back
        header, *rows = list(csv_module.reader(f))
    assert header == list(expected.columns) and len(rows) == len(run.t)
    np.testing.assert_array_equal(np.array([[float(x) for x in row] for row in rows]), expected.to_numpy())
    parquet = tables.write_table(run, tmp_path / "run.parquet")
    pd.testing.assert_frame_equal(pd.read_parquet(parquet), expected, check_exact=True)
    header = json.loads(pq.read_schema(parquet).metadata[b"multibody_sim"])
    assert header["robot"] == "solo12" and header["metadata"]["robot"]["dof_names"] == robot("solo12").dof_names


def test_export_command_writes_both_formats(
    robot: Callable[..., ms.Robot], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = _run(robot("panda"))
    path = run.save(tmp_path / "run.npz")
    csv, parquet = tmp_path / "out" / "run.csv", tmp_path / "run.parquet"
    assert main(["export", str(path), "--csv", str(csv), "--parquet", str(parquet)]) == 0
    columns = 1 + 3 * 9 + 6 + 2
    assert capsys.readouterr() == (
        f"wrote {csv} (6 rows x {columns} columns, 0.0 MB)\nwrote {parquet} (6 rows x {columns} columns, 0.0 MB)\n",
        "",
    )
    expected = run.to_dataframe()
    pd.testing.assert_frame_equal(pd.read_csv(csv), expected, check_exact=True)
    pd.testing.assert_frame_equal(pd.read_parquet(parquet), expected, check_exact=True)


def test_export_reads_the_parts_of_a_chunked_run(
    robot: Callable[..., ms.Robot], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A chunked run stopped before merging leaves run.npz.parts/: export reads it as one trajectory."""
    run = _run(robot("ur5"), duration=0.2)
    out = tmp_path / "run.npz"
    out.with_name("run.npz.parts").mkdir()
    for index, rows in enumerate((slice(0, 8), slice(8, 16), slice(16, None))):
        piece = dataclasses.replace(
            run,
            **{name: getattr(run, name)[rows] for name in ("t", "q", "v", "tau", *ENERGIES)},
            ledger={name: dataclasses.replace(entry, energy=entry.energy[rows]) for name, entry in run.ledger.items()},
        )
        write_chunk(piece, out, index, run_id="one-run", first_sample=rows.start)  # as a chunked run writes them
    for given in (out, out.with_name("run.npz.parts")):  # the file's name, or the folder
        csv = tmp_path / "parts.csv"
        assert main(["export", str(given), "--csv", str(csv)]) == 0
        assert capsys.readouterr().out.startswith(f"wrote {csv} (21 rows x ")
        back = pd.read_csv(csv)
        pd.testing.assert_frame_equal(back, run.to_dataframe(), check_exact=True)


def test_missing_pandas_is_one_line(
    robot: Callable[..., ms.Robot], tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    run = _run(robot("ur5"))
    path = run.save(tmp_path / "run.npz")
    monkeypatch.setitem(sys.modules, "pyarrow.parquet", None)  # what the import sees when it is not installed
    message = (
        "Parquet files need the 'pyarrow' package, which is not installed (pip install 'multibody-sim[dataframe]')"
    )
    assert main(["export", str(path), "--parquet", str(tmp_path / "x.parquet")]) == 2
    assert capsys.readouterr() == ("", f"{PREFIX}{message}\n")
    monkeypatch.setitem(sys.modules, "pandas", None)
    with pytest.raises(ms.MissingDependencyError) as caught:
        run.to_dataframe()
    assert str(caught.value) == (
        "dataframes need the 'pandas' package, which is not installed (pip install 'multibody-sim[dataframe]')"
    )
    assert main(["export", str(path), "--csv", str(tmp_path / "x.csv")]) == 2
    assert capsys.readouterr() == (
        "",
        f"{PREFIX}CSV and Parquet files need the 'pandas' package, which is not installed "
        "(pip install 'multibody-sim[dataframe]')\n",
    )
    assert not (tmp_path / "x.csv").exists() and not (tmp_path / "x.parquet").exists()


def test_bad_table_requests(robot: Callable[..., ms.Robot], tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    run = _run(robot("ur5"))
    with pytest.raises(ms.InvalidArgumentError) as caught:
        tables.write_table(run, tmp_path / "run.xlsx")
    assert (
        str(caught.value) == f"{tmp_path / 'run.xlsx'}: unknown table extension '.xlsx' (choose from: .csv, .parquet)"
    )
    with pytest.raises(ms.InvalidArgumentError, match="has nq = 9 and nv = 9, the trajectory 6 and 6"):
        run.to_dataframe(robot=robot("panda"))
    path = run.save(tmp_path / "run.npz")
    cases = {
        (): "export: nothing to write (give --csv OUT.csv and/or --parquet OUT.parquet)",
        ("--csv", str(tmp_path)): f"--csv {tmp_path}: is a directory, expected a file name such as table.csv",
    }
    for extra, message in cases.items():
        assert main(["export", str(path), *extra]) == 2
        assert capsys.readouterr() == ("", f"{PREFIX}{message}\n")
    assert main(["export", str(tmp_path / "missing.npz"), "--csv", str(tmp_path / "x.csv")]) == 2
    assert capsys.readouterr().err == f"{PREFIX}{tmp_path / 'missing.npz'}: no such trajectory file\n"


# ---- contacts (issue 27) -------------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def stack() -> tuple[ms.Scene, ms.Trajectory]:
    """box_stack resting for 0.0205 s: the last step is shortened to 0.5 ms."""
    scene = ms.load_scene("box_stack")
    return scene, scene.run(duration=0.0205)


def test_contact_columns_carry_the_weights_a_resting_stack_holds(stack: tuple[ms.Scene, ms.Trajectory]) -> None:
    """Each body's normal force is the weight resting on it plus the weight it rests with (statics, independent of
    the solver), its tangential force zero; the counts are its contact points; at every sample, the last one (over a
    shortened step) included."""
    scene, run = stack
    frame = run.to_dataframe()
    bodies = run.contacts.bodies
    assert bodies == ["ground", "bottom", "middle", "top"]
    columns = [f"contact.{b}.{part}" for b in bodies for part in ("normal", "tangential", "count")]
    assert list(frame.columns[-len(columns) - 1 :]) == [*columns, "contact.count"]
    g = float(np.linalg.norm(scene.model.gravity.linear))
    mass = {name: scene.model.inertias[scene.model.getJointId(name)].mass for name in bodies[1:]}
    above = {"bottom": mass["middle"] + mass["top"], "middle": mass["top"], "top": 0.0}
    later = frame.iloc[1:]  # sample 0 has no contacts: no step has ended there
    total = sum(mass.values()) * g
    # To the solver's tolerance: each step's constraint velocities are within TOLERANCE of g dt of their solution, so
    # a box's momentum may change by up to that on either side of a step (~2 TOLERANCE of its weight x dt).
    rtol = 2 * TOLERANCE
    np.testing.assert_allclose(later["contact.ground.normal"], total, rtol=rtol)
    for body in bodies[1:]:  # what rests on it, and its own weight with that, on what is below
        np.testing.assert_allclose(later[f"contact.{body}.normal"], (2 * above[body] + mass[body]) * g, rtol=rtol)
        # At rest on exactly vertical normals (narrow_phase.box_box): no friction, to the solver's tolerance.
        assert later[f"contact.{body}.tangential"].max() < 1e-9 * later[f"contact.{body}.normal"].min()
    counts = {"ground": 4, "bottom": 8, "middle": 8, "top": 4}  # the face-to-face patches: four corners each
    for body, count in counts.items():
        assert (later[f"contact.{body}.count"] == count).all()
    assert (later["contact.count"] == 12).all() and (frame.iloc[0, -len(columns) - 1 :] == 0).all()
    assert run.t[-1] - run.t[-2] == pytest.approx(5e-4)


def test_contact_columns_of_a_sliding_box_follow_coulomb(tmp_path: Path) -> None:
    """The sliding box, while it slides: tangential = mu normal = mu m g."""
    scene = ms.load_scene("sliding_box")
    run = scene.run(duration=0.1)
    frame = run.to_dataframe()
    m, g, mu = 1.0, float(np.linalg.norm(scene.model.gravity.linear)), 0.8
    sliding = frame.iloc[5:]  # it slides at 2 m/s for 0.25 s
    np.testing.assert_allclose(sliding["contact.box.normal"], m * g, rtol=1e-7)  # the solve's accuracy: ~3e-9
    np.testing.assert_allclose(sliding["contact.box.tangential"], mu * m * g, rtol=1e-7)
    np.testing.assert_array_equal(sliding["contact.ground.tangential"], sliding["contact.box.tangential"])


def test_contacts_in_long_form_add_up_to_the_columns(stack: tuple[ms.Scene, ms.Trajectory]) -> None:
    _, run = stack
    wide = run.to_dataframe()
    long = run.contacts_dataframe()
    assert len(long) == len(run.contacts.sample)
    assert list(long.columns[:4]) == ["t", "sample", "body1", "body2"]
    np.testing.assert_array_equal(long[["force.x", "force.y", "force.z"]].to_numpy(), run.contact_forces())
    # The last sample's step was half as long: its impulses are half, its forces the same. Each pair's (what statics
    # fixes) to the solver's tolerance (a box's momentum may change by TOLERANCE of g h on either side of a step: up to
    # 3 TOLERANCE of the half step's impulses, 2 of the one before); each point's to 1e-4 only: a
    # patch's four corners share its load in a statically indeterminate way (the diagonal mode, +-+- at the
    # corners: no force, no moment), which round-off against the solver's regularization sets, here to ~1e-5.
    last = long[long["sample"] == len(run.t) - 1]
    before = long[long["sample"] == len(run.t) - 2]
    pairs = ["body1", "body2"]
    last_sums, before_sums = last.groupby(pairs)["impulse.z"].sum(), before.groupby(pairs)["impulse.z"].sum()
    assert len(last_sums) == 3
    np.testing.assert_allclose(last_sums.to_numpy(), before_sums.to_numpy() / 2, rtol=5 * TOLERANCE)
    np.testing.assert_allclose(last["impulse.z"].to_numpy(), before["impulse.z"].to_numpy() / 2, rtol=1e-4)
    np.testing.assert_allclose(last["normal_force"].to_numpy(), before["normal_force"].to_numpy(), rtol=1e-4)
    for body in run.contacts.bodies:
        touching = long[(long["body1"] == body) | (long["body2"] == body)]
        sums = touching.groupby("sample")["normal_force"].sum().reindex(range(len(run.t)), fill_value=0.0)
        np.testing.assert_allclose(sums.to_numpy(), wide[f"contact.{body}.normal"].to_numpy(), rtol=1e-12)
    no_contact = _run(ms.load_robot("pendulum"))
    with pytest.raises(ms.InvalidArgumentError, match=r"^the trajectory records no contacts"):
        no_contact.contacts_dataframe()


@pytest.mark.parametrize("block", [7, 50_000])
def test_contact_columns_in_csv_and_parquet(
    stack: tuple[ms.Scene, ms.Trajectory],
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    block: int,
) -> None:
    """export --csv/--parquet of a saved contact run, written in blocks of 7 rows or in one: the dataframe's bits."""
    monkeypatch.setattr(tables, "_BLOCK_ROWS", block)
    _, run = stack
    path = run.save(tmp_path / "stack.npz")
    csv, parquet = tmp_path / "stack.csv", tmp_path / "stack.parquet"
    assert main(["export", str(path), "--csv", str(csv), "--parquet", str(parquet)]) == 0
    capsys.readouterr()
    expected = run.to_dataframe()
    assert "contact.count" in expected.columns
    pd.testing.assert_frame_equal(pd.read_csv(csv), expected, check_exact=True)
    pd.testing.assert_frame_equal(pd.read_parquet(parquet), expected, check_exact=True)
