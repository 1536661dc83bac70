"""Every number from a user or a file is range-checked before use, in one place (validation.py), for the API and
the command line alike: NaN and infinities, values that underflow to zero or to a subnormal, counts that would
overflow, ports above 65535 and speeds or frame rates outside their ranges each get one line naming the option
and its valid range; never a traceback, never a silently changed value (a port must not wrap modulo 65536).
"""

from __future__ import annotations

import re
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import multibody_sim as ms
from multibody_sim.cli import main

PREFIX = "multibody-sim: error: "
SUBNORMAL = "9.99989e-321"  # how 1e-320 reads back (a subnormal double) in the messages
RANGE_2_53 = "is more than 2**53, the most a run can count exactly"
EPS = f"{sys.float_info.epsilon:g}"


def exact(message: str) -> str:
    return f"^{re.escape(message)}$"


# (command line, the one line it prints)
CLI_CASES = {
    "dt underflows to a subnormal": (
        ["run", "pendulum", "--dt", "1e-320"],
        f"duration / dt = 1 s / {SUBNORMAL} s = inf {RANGE_2_53}: choose a larger dt or a smaller duration",
    ),
    "duration / dt overflows": (
        ["run", "pendulum", "--duration", "1e300", "--dt", "1e-300"],
        f"duration / dt = 1e+300 s / 1e-300 s = inf {RANGE_2_53}: choose a larger dt or a smaller duration",
    ),
    "duration / dt beyond 2**53": (
        ["run", "pendulum", "--duration", "1e7", "--dt", "1e-12"],
        f"duration / dt = 1e+07 s / 1e-12 s = 1e+19 {RANGE_2_53}: choose a larger dt or a smaller duration",
    ),
    "output_dt / dt overflows": (
        ["run", "pendulum", "--dt", "1e-10", "--output-dt", "1e300", "--duration", "0.001"],
        f"output_dt / dt = 1e+300 s / 1e-10 s = inf {RANGE_2_53}: choose a larger dt or a smaller output_dt",
    ),
    "adaptive output_dt underflows": (
        ["run", "pendulum", "--integrator", "dp54", "--output-dt", "1e-320"],
        f"duration / output_dt = 1 s / {SUBNORMAL} s = inf {RANGE_2_53}: choose a larger output_dt or a smaller "
        "duration",
    ),
    "adaptive control_dt underflows": (
        ["run", "pendulum", "--integrator", "dp54", "--control-dt", "1e-320"],
        f"duration / control_dt = 1 s / {SUBNORMAL} s = inf {RANGE_2_53}: choose a larger control_dt or a smaller "
        "duration",
    ),
    "rtol below machine epsilon": (
        ["run", "pendulum", "--integrator", "dp54", "--rtol", "1e-320"],
        f"rtol must be a number from {EPS} to 1 (1 excluded), got {SUBNORMAL}",
    ),
    "rtol of 1 accepts anything": (
        ["run", "pendulum", "--integrator", "dp54", "--rtol", "1"],
        f"rtol must be a number from {EPS} to 1 (1 excluded), got 1",
    ),
    "atol that underflows to zero": (
        ["run", "pendulum", "--integrator", "dp54", "--atol", "1e-400"],
        "atol must be a positive number of units, got 0.0",
    ),
    "a port above 65535 (would wrap to 4464)": (
        ["run", "pendulum", "--view", "--view-port", "70000"],
        "--view-port must be a whole number from 0 to 65535 (0: any free port), got 70000",
    ),
    "a negative port": (
        ["run", "pendulum", "--view-port", "-1"],
        "--view-port must be a whole number from 0 to 65535 (0: any free port), got -1",
    ),
    "a view speed that underflows": (
        ["run", "pendulum", "--view", "--view-speed", "1e-320"],
        f"--view-speed must be a number from 0.001 to 1000 (1 = real time), got {SUBNORMAL}",
    ),
    "a NaN view speed": (
        ["run", "pendulum", "--view-speed", "nan"],
        "--view-speed must be a number from 0.001 to 1000 (1 = real time), got nan",
    ),
    "a chunk size beyond 2**53": (
        ["run", "pendulum", "--out", "{tmp}/run.npz", "--chunk", "99999999999999999999999"],
        "argument --chunk: expected a whole number from 1 to 2**53, got '99999999999999999999999'",
    ),
    "play: a port above 65535": (
        ["play", "{tmp}/none.npz", "--port", "99999"],
        "--port must be a whole number from 0 to 65535 (0: any free port), got 99999",
    ),
    "play: a frame rate of a billion": (
        ["play", "{tmp}/none.npz", "--fps", "1e9"],
        "--fps must be a number from 1 to 1000 frames per second, got 1e+09",
    ),
    "play: an infinite speed": (
        ["play", "{tmp}/none.npz", "--html", "{tmp}/x.html", "--speed", "inf"],
        "--speed must be a number from 0.001 to 1000 (1 = real time), got inf",
    ),
    "bench: a subnormal duration": (
        ["bench", "pendulum", "--integrators", "rk4", "--duration", "1e-320", "--out", "{tmp}"],
        f"duration must be from 1e-06 s (the finest step of the bench's ladder) to 9.007e+09 s (2**53 of those "
        f"steps), got {SUBNORMAL} s",
    ),
    "bench: a duration of 1e300 s": (
        ["bench", "pendulum", "--integrators", "rk4", "--duration", "1e300", "--out", "{tmp}"],
        "duration must be from 1e-06 s (the finest step of the bench's ladder) to 9.007e+09 s (2**53 of those "
        "steps), got 1e+300 s",
    ),
}


@pytest.mark.parametrize("case", sorted(CLI_CASES))
def test_a_bad_number_on_the_command_line_is_one_line(
    case: str, tmp_path: Path, capfd: pytest.CaptureFixture[str]
) -> None:
    argv, message = CLI_CASES[case]
    capfd.readouterr()
    code = main([word.replace("{tmp}", str(tmp_path)) for word in argv])
    out, err = capfd.readouterr()
    assert (code, out, err) == (2, "", f"{PREFIX}{message}\n")


def pendulum() -> ms.Robot:
    return ms.load_robot("pendulum")


def adaptive(**options: Any) -> dict[str, Any]:
    return {"integrator": "dp54", "rtol": 1e-6, "atol": 1e-8, **options}


def trajectory_with_times(tmp_path: Path, t: list[float]) -> Path:
    """A saved pendulum run whose sample times were rewritten (a forged or damaged file)."""
    run = ms.simulate(pendulum(), [0.1], [0.0], duration=0.003, dt=1e-3)
    run.t = np.array(t)
    return run.save(tmp_path / "forged.npz")


# (the call, the error it raises, the exact message; "{tmp}" is the test's folder)
API_CASES: dict[str, tuple[Callable[[Path], object], type[Exception], str]] = {
    "simulate: dt underflows": (
        lambda tmp: ms.simulate(pendulum(), [0.0], [0.0], duration=1.0, dt=1e-320),
        ms.InvalidArgumentError,
        f"duration / dt = 1 s / {SUBNORMAL} s = inf {RANGE_2_53}: choose a larger dt or a smaller duration",
    ),
    "simulate: adaptive output_dt underflows": (
        lambda tmp: ms.simulate(pendulum(), [0.0], [0.0], duration=1.0, dt=1e-3, **adaptive(output_dt=1e-320)),
        ms.InvalidArgumentError,
        f"duration / output_dt = 1 s / {SUBNORMAL} s = inf {RANGE_2_53}: choose a larger output_dt or a smaller "
        "duration",
    ),
    "simulate: max_step underflows": (
        lambda tmp: ms.simulate(pendulum(), [0.0], [0.0], duration=1.0, dt=1e-3, **adaptive(max_step=1e-320)),
        ms.InvalidArgumentError,
        f"duration / max_step = 1 s / {SUBNORMAL} s = inf {RANGE_2_53}: choose a larger max_step or a smaller duration",
    ),
    "simulate: rtol of 2": (
        lambda tmp: ms.simulate(pendulum(), [0.0], [0.0], duration=1.0, dt=1e-3, **adaptive(rtol=2.0)),
        ms.InvalidArgumentError,
        f"rtol must be a number from {EPS} to 1 (1 excluded), got 2",
    ),
    "simulate: chunk beyond 2**53": (
        lambda tmp: ms.simulate(pendulum(), [0.0], [0.0], duration=1.0, dt=1e-3, out=tmp / "r.npz", chunk=2**60),
        ms.InvalidArgumentError,
        f"chunk must be at most 2**53 = {2**53}, got {2**60}",
    ),
    "rollout: duration / dt overflows": (
        lambda tmp: ms.rollout(pendulum(), [[0.0]], [[0.0]], duration=1e300, dt=1e-300),
        ms.InvalidArgumentError,
        f"duration / dt = 1e+300 s / 1e-300 s = inf {RANGE_2_53}: choose a larger dt or a smaller duration",
    ),
    "Stepper: control_dt / dt overflows": (
        lambda tmp: ms.Stepper(pendulum(), dt=1e-10, control_dt=1e300),
        ms.InvalidArgumentError,
        f"control_dt / dt = 1e+300 s / 1e-10 s = inf {RANGE_2_53}: choose a larger dt or a smaller control_dt",
    ),
    "Stepper: advancing 1e300 s in steps of 1e-10 s": (
        lambda tmp: ms.Stepper(pendulum(), dt=1e-10).advance_to(1e300),
        ms.InvalidArgumentError,
        f"(t - current time) / control_dt = 1e+300 s / 1e-10 s = inf {RANGE_2_53}: choose a larger control_dt "
        "or a smaller (t - current time)",
    ),
    "trajectory file: a NaN sample time": (
        lambda tmp: ms.Trajectory.load(trajectory_with_times(tmp, [0.0, 0.001, float("nan"), 0.003])),
        ms.TrajectoryFileError,
        "{tmp}/forged.npz: sample times: t must hold finite times, got nan at index 2",
    ),
    "trajectory file: times that go back": (
        lambda tmp: ms.Trajectory.load(trajectory_with_times(tmp, [0.0, 0.002, 0.001, 0.003])),
        ms.TrajectoryFileError,
        "{tmp}/forged.npz: sample times: t must be strictly increasing, got 0.002 then 0.001 at indices 1 and 2",
    ),
    "trajectory file: a repeated sample time": (
        lambda tmp: ms.Trajectory.load(trajectory_with_times(tmp, [0.0, 0.001, 0.001, 0.003])),
        ms.TrajectoryFileError,
        "{tmp}/forged.npz: sample times: t must be strictly increasing, got 0.001 then 0.001 at indices 1 and 2",
    ),
}


@pytest.mark.parametrize("case", sorted(API_CASES))
def test_a_bad_number_in_the_api_is_one_error(case: str, tmp_path: Path) -> None:
    call, error, message = API_CASES[case]
    with pytest.raises(error, match=exact(message.replace("{tmp}", str(tmp_path)))):
        call(tmp_path)


VIEWER_CASES = {
    "a port above 65535": (
        {"port": 70000},
        "port must be a whole number from 0 to 65535 (0: any free port), got 70000",
    ),
    "a port as a float": (
        {"port": 7000.0},
        "port must be a whole number from 0 to 65535 (0: any free port), got 7000.0",
    ),
    "a port as a string": (
        {"port": "7000"},
        "port must be a whole number from 0 to 65535 (0: any free port), got '7000'",
    ),
    "a host that is not a string": ({"host": 127}, "host must be an address such as '127.0.0.1', got int"),
}


@pytest.mark.parametrize("case", sorted(VIEWER_CASES))
def test_the_viewer_server_refuses_bad_ports(case: str) -> None:
    pytest.importorskip("tornado")
    from multibody_sim.viz import MeshcatServer

    options, message = VIEWER_CASES[case]
    with pytest.raises(ms.InvalidArgumentError, match=exact(message)):
        MeshcatServer(**options)


def test_playback_numbers_are_checked_before_any_work(tmp_path: Path) -> None:
    pytest.importorskip("meshcat")
    import multibody_sim.viz as viz

    run = ms.simulate(pendulum(), [0.1], [0.0], duration=0.01, dt=1e-3)
    with pytest.raises(
        ms.InvalidArgumentError, match=exact("fps must be a number from 1 to 1000 frames per second, got 1e+09")
    ):
        viz.export_html(run, tmp_path / "x.html", fps=1e9)
    with pytest.raises(
        ms.InvalidArgumentError, match=exact("speed must be a number from 0.001 to 1000 (1 = real time), got 1e-09")
    ):
        viz.inline_view(run, speed=1e-9)
    assert not (tmp_path / "x.html").exists()


def test_values_inside_the_ranges_still_run(tmp_path: Path) -> None:
    """The edges of the ranges are accepted: the checks refuse only what cannot be meant."""
    robot = pendulum()
    run = ms.simulate(robot, [0.1], [0.0], duration=0.01, dt=1e-3, **adaptive(rtol=sys.float_info.epsilon * 1e6))
    assert run.status == "completed"
    assert ms.Stepper(robot, dt=1e-3).advance_to(0.01).t == pytest.approx(0.01)
    loaded = ms.Trajectory.load(run.save(tmp_path / "run.npz"))
    assert np.array_equal(loaded.t, run.t)
