"""Plots of trajectories: every plotted line is the trajectory's own data, and the PNG is a real picture."""

from __future__ import annotations

import importlib.util
import os
import sys
from collections.abc import Callable
from pathlib import Path

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
ENERGY_LINES = {
    "kinetic T": "kinetic_energy",
    "potential V": "potential_energy",
    "total H = T + V": "total_energy",
    "work (in)": "work",
    "dissipated (out)": "dissipated",
}


def _lines(axis: object) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    return {line.get_label(): (np.asarray(line.get_xdata()), np.asarray(line.get_ydata())) for line in axis.lines}  # type: ignore[attr-defined]


@pytest.fixture(scope="module")
def panda_run(robot: Callable[..., ms.Robot]) -> ms.Trajectory:
    panda = robot("panda")
    return ms.simulate(panda, panda.neutral(), np.zeros(panda.nv), duration=0.3, dt=1e-3, output_dt=0.01)


def test_energy_panels_plot_the_trajectory_arrays(panda_run: ms.Trajectory, robot: Callable[..., ms.Robot]) -> None:
    fig = viz.plot_trajectory(panda_run, robot=robot("panda"))
    energy, error, positions = fig.axes
    lines = _lines(energy)
    assert set(lines) == set(ENERGY_LINES)
    for label, field in ENERGY_LINES.items():
        x, y = lines[label]
        np.testing.assert_array_equal(x, panda_run.t)
        np.testing.assert_array_equal(y, getattr(panda_run, field))
    (x, y), *others = _lines(error).values()
    assert not others
    np.testing.assert_array_equal(x, panda_run.t)
    np.testing.assert_array_equal(y, panda_run.energy_error)
    joints = _lines(positions)
    assert list(joints) == robot("panda").joint_names  # one line per joint, in Pinocchio's order
    for k, (x, y) in enumerate(joints.values()):
        np.testing.assert_array_equal(x, panda_run.t)
        np.testing.assert_array_equal(y, panda_run.q[:, k])  # panda: nq = nv, one coordinate per joint
    assert (energy.get_ylabel(), error.get_ylabel()) == ("energy [J]", "energy_error [J]")
    assert positions.get_xlabel() == "time [s]"


def test_floating_base_gets_a_base_panel(robot: Callable[..., ms.Robot]) -> None:
    solo = robot("solo12")
    v0 = np.zeros(solo.nv)
    v0[:3] = [0.2, 0.0, 1.0]
    trajectory = ms.simulate(solo, solo.neutral(), v0, duration=0.1, dt=1e-3, output_dt=0.01)
    for given in (solo, None):  # with the robot, or from the trajectory's metadata alone
        fig = viz.plot_trajectory(trajectory, robot=given)
        assert len(fig.axes) == 4
        base = _lines(fig.axes[3])
        assert list(base) == ["base x", "base y", "base z"]
        for k, (_, y) in enumerate(base.values()):
            np.testing.assert_array_equal(y, trajectory.q[:, k])
        joints = _lines(fig.axes[2])
        assert list(joints) == solo.joint_names[1:]  # the root joint is the base panel
        for k, (_, y) in enumerate(joints.values()):
            np.testing.assert_array_equal(y, trajectory.q[:, 7 + k])  # after x y z qx qy qz qw


def test_continuous_joints_are_plotted_as_angles(robot: Callable[..., ms.Robot]) -> None:
    pendulum = robot("double_pendulum_continuous")
    q0 = np.array([np.cos(3.0), np.sin(3.0), 1.0, 0.0])  # near the top: it swings through +-pi
    trajectory = ms.simulate(pendulum, q0, [4.0, 0.0], duration=1.0, dt=1e-3, output_dt=0.01)
    joints = _lines(viz.plot_trajectory(trajectory, robot=pendulum).axes[2])
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
    assert image.size == (900, 780)  # 9 in x (3 panels x 2.4 in + 0.6 in) at 100 dpi
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
