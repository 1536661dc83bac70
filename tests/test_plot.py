"""Plots of trajectories: every plotted line is the trajectory's own data, and the PNG is a real picture."""

from __future__ import annotations

import dataclasses
import importlib.util
import os
import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image

import multibody_sim as ms
from multibody_sim.cli import main

if importlib.util.find_spec("matplotlib") is None:  # in the test extra: CI must have it
    reason = "matplotlib is not installed (pip install -e '.[test]')"
    if os.environ.get("CI") == "true":
        pytest.fail(reason, pytrace=False)
    pytest.skip(reason, allow_module_level=True)
viz = pytest.importorskip("multibody_sim.viz")

PREFIX = "multibody-sim: error: "
ENERGY_LINES = {"kinetic T": "kinetic_energy", "potential V": "potential_energy", "total H = T + V": "total_energy"}
LEDGER_LINES = {"work (in)": "work", "dissipated (out)": "dissipated"}


def _lines(axis: object) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    return {line.get_label(): (np.asarray(line.get_xdata()), np.asarray(line.get_ydata())) for line in axis.lines}  # type: ignore[attr-defined]


@pytest.fixture(scope="module")
def panda_run(robot: Callable[..., ms.Robot]) -> ms.Trajectory:
    panda = robot("panda")
    return ms.simulate(panda, panda.neutral(), np.zeros(panda.nv), duration=0.3, dt=1e-3, output_dt=0.01)


def test_energy_panels_plot_the_trajectory_arrays(panda_run: ms.Trajectory, robot: Callable[..., ms.Robot]) -> None:
    fig = viz.plot_trajectory(panda_run, robot=robot("panda"))
    energy, ledger, error, positions = fig.axes
    lines = _lines(energy)
    assert set(lines) == set(ENERGY_LINES)
    for label, field in ENERGY_LINES.items():
        x, y = lines[label]
        np.testing.assert_array_equal(x, panda_run.t)
        np.testing.assert_array_equal(y, getattr(panda_run, field))
    lines = _lines(ledger)  # the totals, then every element of the trajectory's ledger with its kind
    expected = {**LEDGER_LINES, **{f"{name} ({entry.kind})": name for name, entry in panda_run.ledger.items()}}
    assert (
        list(lines)
        == list(expected)
        == ["work (in)", "dissipated (out)", "joint_torques (work)", "joint_damping (dissipated)"]
    )
    for label, field in expected.items():
        x, y = lines[label]
        np.testing.assert_array_equal(x, panda_run.t)
        data = getattr(panda_run, field) if field in LEDGER_LINES.values() else panda_run.ledger[field].energy
        np.testing.assert_array_equal(y, data)
    (x, y), *others = _lines(error).values()
    assert not others
    np.testing.assert_array_equal(x, panda_run.t)
    np.testing.assert_array_equal(y, panda_run.energy_error)
    joints = _lines(positions)
    assert list(joints) == robot("panda").joint_names  # one line per joint, in Pinocchio's order
    for k, (x, y) in enumerate(joints.values()):
        np.testing.assert_array_equal(x, panda_run.t)
        np.testing.assert_array_equal(y, panda_run.q[:, k])  # panda: nq = nv, one coordinate per joint
    assert energy.get_ylabel() == "energy [J]" and positions.get_xlabel() == "time [s]"
    assert error.get_ylabel().startswith("energy_error [") and error.get_ylabel().endswith(" J]")


def test_floating_base_gets_a_base_panel(robot: Callable[..., ms.Robot]) -> None:
    solo = robot("solo12")
    v0 = np.zeros(solo.nv)
    v0[:3] = [0.2, 0.0, 1.0]
    trajectory = ms.simulate(solo, solo.neutral(), v0, duration=0.1, dt=1e-3, output_dt=0.01)
    for given in (solo, None):  # with the robot, or from the trajectory's metadata alone
        fig = viz.plot_trajectory(trajectory, robot=given)
        assert len(fig.axes) == 5
        base = _lines(fig.axes[4])
        assert list(base) == ["base x", "base y", "base z"]
        for k, (_, y) in enumerate(base.values()):
            np.testing.assert_array_equal(y, trajectory.q[:, k])
        joints = _lines(fig.axes[3])
        assert list(joints) == solo.joint_names[1:]  # the root joint is the base panel
        for k, (_, y) in enumerate(joints.values()):
            np.testing.assert_array_equal(y, trajectory.q[:, 7 + k])  # after x y z qx qy qz qw


def test_continuous_joints_are_plotted_as_angles(robot: Callable[..., ms.Robot]) -> None:
    pendulum = robot("double_pendulum_continuous")
    q0 = np.array([np.cos(3.0), np.sin(3.0), 1.0, 0.0])  # near the top: it swings through +-pi
    trajectory = ms.simulate(pendulum, q0, [4.0, 0.0], duration=1.0, dt=1e-3, output_dt=0.01)
    joints = _lines(viz.plot_trajectory(trajectory, robot=pendulum).axes[3])
    for k, (_, angle) in enumerate(joints.values()):
        cos, sin = trajectory.q[:, 2 * k], trajectory.q[:, 2 * k + 1]
        np.testing.assert_allclose(np.cos(angle), cos, atol=1e-12)
        np.testing.assert_allclose(np.sin(angle), sin, atol=1e-12)
        assert np.abs(np.diff(angle)).max() < 1.0  # unwrapped: no jump of 2 pi where it passes the top
    assert np.ptp(list(joints.values())[0]) > np.pi  # it did pass the top


def test_png_is_a_real_picture(panda_run: ms.Trajectory, tmp_path: Path) -> None:
    path = tmp_path / "plots" / "panda.png"
    viz.plot_trajectory(panda_run, path, dpi=100)
    image = Image.open(path)
    assert image.format == "PNG"
    assert image.size == (900, 1020)  # 9 in x (4 panels x 2.4 in + 0.6 in) at 100 dpi
    pixels = np.asarray(image.convert("RGB")).reshape(-1, 3).astype(np.int64)
    packed, counts = np.unique(pixels @ [65536, 256, 1], return_counts=True)
    solid = np.column_stack([packed // 65536, packed // 256 % 256, packed % 256])[counts >= 40]
    # solid: line colours, text, grid, background, not just antialiasing blends
    assert len(solid) >= 8
    assert (pixels.min(axis=1) < 200).mean() > 0.02  # ink on more than 2 % of the picture
    for color in ([31, 119, 180], [255, 127, 14], [44, 160, 44], [214, 39, 40]):  # matplotlib's first colours
        assert np.any(np.all(np.abs(solid.astype(int) - color) <= 2, axis=1)), color


def test_cli_plot_writes_beside_the_trajectory(
    panda_run: ms.Trajectory, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = panda_run.save(tmp_path / "run.npz")
    assert main(["plot", str(run)]) == 0
    assert capsys.readouterr().out == f"wrote {tmp_path / 'run.png'}\n"
    assert Image.open(tmp_path / "run.png").size[0] > 500
    out = tmp_path / "elsewhere" / "energy.png"
    assert main(["plot", str(run), "--out", str(out)]) == 0
    assert out.is_file()


def test_cli_plot_refuses_a_folder_as_output(
    panda_run: ms.Trajectory, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    run = panda_run.save(tmp_path / "run.npz")
    assert main(["plot", str(run), "--out", str(tmp_path)]) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err == f"{PREFIX}--out {tmp_path}: is a directory, expected a file name such as plot.png\n"


def test_cli_plot_without_matplotlib(
    panda_run: ms.Trajectory, tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    run = panda_run.save(tmp_path / "run.npz")
    monkeypatch.setitem(sys.modules, "matplotlib.figure", None)  # what the import sees when it is not installed
    assert main(["plot", str(run)]) == 2
    captured = capsys.readouterr()
    message = "plots need the 'matplotlib' package, which is not installed (pip install 'multibody-sim[viz]')"
    assert (captured.out, captured.err) == ("", f"{PREFIX}{message}\n")
    assert not (tmp_path / "run.png").exists()


# ---- legibility: legends, ledger curves, axis offsets ---------------------------------------------------------
def _laid_out(fig: Any) -> Any:
    """The figure drawn by Agg (final constrained layout), and its renderer for the boxes of what it drew."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    return canvas.get_renderer()


def _check_legends_clear(fig: Any) -> None:
    """Every legend lies inside the figure and covers no panel, no other legend and no title."""
    renderer = _laid_out(fig)
    figure_box = fig.bbox
    legends = [axis.get_legend() for axis in fig.axes if axis.get_legend() is not None]
    assert len(legends) == len(fig.axes)
    boxes = [legend.get_window_extent(renderer) for legend in legends]
    title = fig._suptitle.get_window_extent(renderer)
    for k, box in enumerate(boxes):
        assert (
            figure_box.x0 <= box.x0 and box.x1 <= figure_box.x1 and figure_box.y0 <= box.y0 and box.y1 <= figure_box.y1
        )
        assert not any(box.overlaps(axis.bbox) for axis in fig.axes)
        assert not any(box.overlaps(other) for j, other in enumerate(boxes) if j != k)
        assert not box.overlaps(title)


def test_legend_of_many_joints_sits_beside_the_panel_in_columns(robot: Callable[..., ms.Robot]) -> None:
    talos = robot("talos")
    run = ms.simulate(talos, talos.neutral(), np.zeros(talos.nv), duration=0.02, dt=1e-3, output_dt=0.005)
    fig = viz.plot_trajectory(run, robot=talos)
    positions = fig.axes[3]
    legend = positions.get_legend()
    names = talos.joint_names[1:]
    assert len(names) > 30
    assert [text.get_text() for text in legend.get_texts()] == names  # every joint named, none dropped
    assert legend._ncols >= 3  # 14 rows at most per column
    looks = {(line.get_color(), line.get_linestyle()) for line in positions.get_lines()}
    assert len(looks) == len(names)  # colour and dash tell every line apart
    _check_legends_clear(fig)


def test_ledger_curves_that_coincide_stay_distinguishable(
    panda_run: ms.Trajectory, robot: Callable[..., ms.Robot]
) -> None:
    fig = viz.plot_trajectory(panda_run, robot=robot("panda"))
    lines = fig.axes[1].get_lines()
    looks = [(line.get_color(), line.get_linestyle(), line.get_marker()) for line in lines]
    assert len(set(looks)) == len(lines) == 4
    n = len(panda_run.t)

    def marks(line: Any) -> set[int]:
        if line.get_marker() in ("None", None, ""):
            return set()
        start, step = line.get_markevery()
        return set(range(start, n, step))

    by_label = {line.get_label(): line for line in lines}
    # Undriven panda: the torques' work is zero throughout, and the damping element is all that dissipates:
    # each element lies exactly on a total, and must still show.
    pairs = [("work (in)", "joint_torques (work)"), ("dissipated (out)", "joint_damping (dissipated)")]
    for total, element in pairs:
        np.testing.assert_array_equal(by_label[total].get_ydata(), by_label[element].get_ydata())
        assert by_label[total].get_linestyle() != by_label[element].get_linestyle()
        assert marks(by_label[element]) and not marks(by_label[total])
    assert not marks(by_label["joint_torques (work)"]) & marks(by_label["joint_damping (dissipated)"])
    _check_legends_clear(fig)


LABEL = re.compile(r"^(?P<name>.*?)(?: - (?P<offset>\S+))? \[(?:1e(?P<order>-?\d+) )?(?P<unit>[^\]]*)\]$")


def test_axis_offsets_are_written_into_the_labels(robot: Callable[..., ms.Robot]) -> None:
    """A base far from the origin that wobbles by micrometres, and a tiny energy_error: matplotlib would print an
    offset and a power of ten above those axes, where titles go; the labels carry them instead, and the ticks
    read true."""
    solo = robot("solo12")
    run = ms.simulate(solo, solo.neutral(), np.zeros(solo.nv), duration=0.3, dt=1e-3, output_dt=0.01)
    wobble = 1e-6 * np.sin(20 * run.t)
    q = run.q.copy()
    q[:, :3] = np.column_stack([1000.0 + wobble, 1000.0 - wobble, 1000.0 + 0.5 * wobble])
    run = dataclasses.replace(run, q=q, energy_error=3e-9 * np.cos(20 * run.t))
    fig = viz.plot_trajectory(run, robot=solo, title="a title that spans much of the width of the whole figure")
    renderer = _laid_out(fig)
    error, base = fig.axes[2], fig.axes[4]
    assert error.get_ylabel() == "energy_error [1e-9 J]"
    assert base.get_ylabel() == "base position - 1000 [1e-6 m]"
    for axis in fig.axes:
        offset = axis.yaxis.get_offset_text()
        assert not (offset.get_visible() and offset.get_text())  # nothing printed above any axis
        match = LABEL.match(axis.get_ylabel())
        assert match, axis.get_ylabel()
        shift = float(match["offset"] or 0.0)
        scale = 10.0 ** int(match["order"] or 0)
        for tick, text in zip(axis.get_yticks(), axis.get_yticklabels(), strict=True):
            if text.get_text():  # the label's value, read as the axis label says, is where the tick is
                value = float(text.get_text().replace("\u2212", "-")) * scale + shift
                assert value == pytest.approx(tick, rel=1e-12, abs=1e-6 * scale)
    title = fig._suptitle.get_window_extent(renderer)
    for axis in fig.axes:
        texts = [axis.yaxis.label, *axis.get_yticklabels()]
        assert not any(title.overlaps(text.get_window_extent(renderer)) for text in texts if text.get_text())
        assert not title.overlaps(axis.bbox)


def test_joints_selects_the_lines_and_the_base_panel(robot: Callable[..., ms.Robot]) -> None:
    ur5 = robot("ur5")
    run = ms.simulate(ur5, ur5.neutral(), np.zeros(ur5.nv), duration=0.05, dt=1e-3, output_dt=0.01)
    fig = viz.plot_trajectory(run, robot=ur5, joints=["elbow_joint", "shoulder_pan_joint"])
    joints = _lines(fig.axes[3])
    assert list(joints) == ["shoulder_pan_joint", "elbow_joint"]  # in the robot's order
    np.testing.assert_array_equal(joints["elbow_joint"][1], run.q[:, ur5.joint_names.index("elbow_joint")])
    solo = robot("solo12")
    run = ms.simulate(solo, solo.neutral(), np.zeros(solo.nv), duration=0.02, dt=1e-3, output_dt=0.01)
    for given in (solo, None):
        fig = viz.plot_trajectory(run, robot=given, joints=["root_joint"])  # only the base: no joint panel
        assert len(fig.axes) == 4 and list(_lines(fig.axes[3])) == ["base x", "base y", "base z"]
        fig = viz.plot_trajectory(run, robot=given, joints=["FL_KFE"])  # a joint only: no base panel
        assert len(fig.axes) == 4 and list(_lines(fig.axes[3])) == ["FL_KFE"]


def test_unknown_joint_names_close_matches(
    robot: Callable[..., ms.Robot], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    ur5 = robot("ur5")
    run = ms.simulate(ur5, ur5.neutral(), np.zeros(ur5.nv), duration=0.02, dt=1e-3)
    with pytest.raises(ms.UnknownNameError, match=re.escape("unknown joint 'elbw' (did you mean elbow_joint?)")):
        viz.plot_trajectory(run, robot=ur5, joints=["elbw"])
    path = run.save(tmp_path / "ur5.npz")
    cases = {
        "shoulder_pan_joint,elbw": "--joints: unknown joint 'elbw' (did you mean elbow_joint?)",
        "xyz": "--joints: unknown joint 'xyz' (joints: shoulder_pan_joint, shoulder_lift_joint, elbow_joint, "
        "wrist_1_joint, wrist_2_joint, wrist_3_joint)",
        ",": "--joints: no joint names given (comma-separated names, e.g. --joints elbow_joint,wrist_1_joint)",
    }
    for given, message in cases.items():
        assert main(["plot", str(path), "--joints", given]) == 2
        assert capsys.readouterr() == ("", f"{PREFIX}{message}\n")
    assert not (tmp_path / "ur5.png").exists()
    assert main(["plot", str(path), "--joints", "wrist_1_joint, elbow_joint"]) == 0
    assert capsys.readouterr().out == f"wrote {tmp_path / 'ur5.png'}\n"
