"""Progress bars for long runs: on a terminal (or when asked), never in scripts and logs."""

from __future__ import annotations

import numpy as np
import pytest

import multibody_sim as ms


def test_progress_bar_when_asked(robot, capsys: pytest.CaptureFixture[str]) -> None:
    pendulum = robot("pendulum")
    traj = ms.simulate(pendulum, [1.0], [0.0], duration=2.0, dt=1e-3, output_dt=0.01, progress=True)
    err = capsys.readouterr().err
    assert "simulate:" in err and "t = 2/2 s" in err  # the bar reached the duration
    assert traj.t[-1] == 2.0


def test_no_progress_bar_off_a_terminal(robot, capsys: pytest.CaptureFixture[str]) -> None:
    pendulum = robot("pendulum")
    seen: list[float] = []
    ms.simulate(pendulum, [1.0], [0.0], duration=2.0, dt=1e-3, output_dt=0.5, on_sample=lambda t, q, v: seen.append(t))
    assert capsys.readouterr().err == ""  # stderr is not a terminal under pytest: silent by default
    np.testing.assert_allclose(seen, [0.0, 0.5, 1.0, 1.5, 2.0])  # on_sample sees every sample as it is computed


def test_progress_and_on_sample_together(robot, capsys: pytest.CaptureFixture[str]) -> None:
    pendulum = robot("pendulum")
    seen: list[float] = []
    ms.simulate(
        pendulum,
        [1.0],
        [0.0],
        duration=1.0,
        dt=1e-3,
        output_dt=0.25,
        progress=True,
        on_sample=lambda t, q, v: seen.append(t),
    )
    assert seen == [0.0, 0.25, 0.5, 0.75, 1.0]
    assert "t = 1/1 s" in capsys.readouterr().err


def test_on_sample_must_be_callable(robot) -> None:
    with pytest.raises(ms.InvalidArgumentError, match="on_sample must be callable as on_sample\\(t, q, v\\), got int"):
        ms.simulate(robot("pendulum"), [1.0], [0.0], duration=0.1, dt=1e-2, on_sample=3)
