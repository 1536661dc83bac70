"""What the command line prints where: `python -m`, `run --json`, checks before the header, robot or scene names."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

import multibody_sim as ms
from multibody_sim.cli import main

PREFIX = "multibody-sim: error: "


def call(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    """main(args) in this process: (exit code, stdout, stderr)."""
    code = main(list(args))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def console(*args: str, module: bool = False, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    """The console script (or `python -m multibody_sim`) in a child process."""
    script = Path(sys.executable).with_name("multibody-sim")
    command = [sys.executable, "-m", "multibody_sim"] if module else [str(script)]
    return subprocess.run([*command, *args], capture_output=True, text=True, timeout=120, cwd=cwd)


# ---- python -m multibody_sim -------------------------------------------------------------------------
def test_python_dash_m_is_the_console_script() -> None:
    for args in (["--help"], ["integrators"], ["run", "pendulum", "--duration", "0.05", "--q0", "1"]):
        script, module = console(*args), console(*args, module=True)
        assert module.returncode == script.returncode == 0
        if args[0] == "run":  # wall times differ; everything else is the same
            strip = [line for line in module.stdout.splitlines() if "wall time" not in line]
            assert strip == [line for line in script.stdout.splitlines() if "wall time" not in line]
            assert "status: completed" in module.stdout
        else:
            assert module.stdout == script.stdout
            assert module.stdout.startswith("usage: multibody-sim") or "rk4" in module.stdout
    bad = console("run", "ur5", "--dt", "-1", module=True)
    assert (bad.returncode, bad.stdout) == (2, "")
    assert bad.stderr == PREFIX + "dt must be a positive number of seconds, got -1.0\n"


# ---- run --json ------------------------------------------------------------------------------------------
def test_run_json_prints_one_document_matching_the_api(tmp_path: Path) -> None:
    out = tmp_path / "run.npz"
    args = ["run", "double_pendulum", "--q0", "2", "0.5", "--v0", "0", "1", "--duration", "0.3", "--dt", "0.01"]
    result = console(*args, "--integrator", "midpoint", "--out", str(out), "--json", module=True)
    assert result.returncode == 0
    document = json.loads(result.stdout)  # exactly one JSON document: anything else on stdout fails here
    assert result.stdout.count("\n") == 1
    # The header and the human summary went to stderr.
    err = result.stderr.splitlines()
    assert err[0] == "run: double_pendulum (fixed base, nq 2, nv 2), integrator midpoint, dt 0.01 s, duration 0.3 s"
    assert "status: completed" in err and err[-1] == f"wrote {out}"
    # The document describes the run and holds the same numbers as the Python API's run.
    robot = ms.load_robot("double_pendulum")
    api = ms.simulate(robot, [2.0, 0.5], [0.0, 1.0], duration=0.3, dt=0.01, integrator="midpoint")
    assert document["robot"] == {
        "name": "double_pendulum",
        "source": "double_pendulum",
        "base": "fixed",
        "nq": 2,
        "nv": 2,
    }
    assert (document["integrator"], document["dt"], document["duration"]) == ("midpoint", 0.01, 0.3)
    assert document["q0"] == [2.0, 0.5] and document["v0"] == [0.0, 1.0]
    assert document["out"] == str(out) and document["error"] is None and document["controller"] is None
    summary = document["summary"]
    assert summary["status"] == "completed" and summary["samples"] == len(api.t) == 31
    assert summary["stats"]["steps"] == 30 and summary["stats"]["evaluations"] == 60
    np.testing.assert_allclose(summary["energy"]["total"], api.total_energy[[0, -1]], rtol=1e-12)
    np.testing.assert_allclose(summary["energy"]["kinetic"], api.kinetic_energy[[0, -1]], rtol=1e-12)
    assert summary["dissipated"] == pytest.approx(api.dissipated[-1], rel=1e-12)
    assert summary["max_abs_energy_error"] == pytest.approx(np.abs(api.energy_error).max(), rel=1e-12)
    assert summary["ledger"]["joint_damping"]["kind"] == "dissipated"
    assert summary["limit_violations"] == {
        "count": 0,
        "samples": 0,
        "worst_joint": None,
        "worst_excess": 0.0,
        "worst_time": None,
    }
    saved = ms.Trajectory.load(out)
    np.testing.assert_array_equal(saved.q[-1], api.q[-1])


def test_run_json_of_a_failed_run_still_prints_the_partial_summary(capsys: pytest.CaptureFixture[str]) -> None:
    diverging = ["run", "double_pendulum", "--integrator", "euler", "--dt", "0.5", "--duration", "50"]
    code, stdout, stderr = call(capsys, *diverging, "--v0", "30", "30", "--json")
    assert code == 1
    document = json.loads(stdout)
    assert document["summary"]["status"] == "diverged"
    assert document["error"].startswith("diverged at t = ")
    assert stderr.splitlines()[-1] == PREFIX + document["error"]
    assert document["summary"]["real_time_factor"] is None or document["summary"]["real_time_factor"] > 0


def test_run_json_with_a_controller_reports_what_it_saw(capsys: pytest.CaptureFixture[str]) -> None:
    code, stdout, stderr = call(
        capsys,
        "run",
        "point_robot",
        "--controller",
        "potential_field",
        "--param",
        "goal=1,0",
        "--q0",
        "0",
        "0",
        "--duration",
        "0.2",
        "--json",
    )
    assert code == 0
    document = json.loads(stdout)
    assert document["controller"] == "potential_field"
    assert document["controller_report"] and document["controller_report"] in stderr
    assert document["summary"]["stats"]["controller_calls"] == 200


def test_run_json_with_bad_input_prints_nothing_on_stdout(capsys: pytest.CaptureFixture[str]) -> None:
    code, stdout, stderr = call(capsys, "run", "ur5", "--q0", "1", "--json")
    assert (code, stdout) == (2, "")
    assert stderr == PREFIX + "q0 must have shape (6,), got (1,)\n"


# ---- arguments are checked before the header ---------------------------------------------------------------
BEFORE_HEADER = {
    "negative dt": (["run", "ur5", "--dt", "-1"], "dt must be a positive number of seconds, got -1.0"),
    "zero duration": (["run", "ur5", "--duration", "0"], "duration must be a positive number of seconds, got 0.0"),
    "output_dt": (
        ["run", "ur5", "--output-dt", "0.0015"],
        "output_dt must be a whole multiple of dt = 0.001 s, got 0.0015 s",
    ),
    "control_dt": (
        ["run", "ur5", "--dt", "0.01", "--control-dt", "0.015"],
        "control_dt must be a whole multiple of dt = 0.01 s, got 0.015 s",
    ),
    "negative rtol": (
        ["run", "ur5", "--integrator", "dp54", "--rtol", "-1"],
        "rtol must be a positive number of units, got -1.0",
    ),
    "fixed-step option": (
        ["run", "ur5", "--max-step", "0.1"],
        "option 'max_step' does not apply to the fixed-step integrator 'rk4' (it applies to the adaptive "
        "integrators: bs32, dop853, dp54)",
    ),
    "refused robot": (
        ["run", "solo12", "--integrator", "variational"],
        "integrator 'variational' does not support floating bases yet (robot 'solo12' has one); use rk4, dp54 or "
        "another explicit integrator",
    ),
}


@pytest.mark.parametrize("case", BEFORE_HEADER)
def test_bad_run_arguments_print_one_line_and_no_header(case: str, capsys: pytest.CaptureFixture[str]) -> None:
    argv, message = BEFORE_HEADER[case]
    code, stdout, stderr = call(capsys, *argv)
    assert (code, stdout, stderr) == (2, "", PREFIX + message + "\n")


def test_bad_dt_through_the_console_script_prints_one_line() -> None:
    result = console("run", "ur5", "--dt", "-1")
    assert (result.returncode, result.stdout) == (2, "")
    assert result.stderr == PREFIX + "dt must be a positive number of seconds, got -1.0\n"


def test_the_checks_agree_with_simulate() -> None:
    """The CLI's early checks say what simulate() itself says."""
    ur5 = ms.load_robot("ur5")
    q, v = np.zeros(6), np.zeros(6)
    with pytest.raises(ms.InvalidArgumentError) as caught:
        ms.simulate(ur5, q, v, duration=1.0, dt=-1.0)
    assert str(caught.value) == BEFORE_HEADER["negative dt"][1]
    with pytest.raises(ms.InvalidArgumentError) as caught:
        ms.simulate(ur5, q, v, duration=1.0, dt=0.01, control_dt=0.015)
    assert str(caught.value) == BEFORE_HEADER["control_dt"][1]


# ---- names that are both a robot and a scene ---------------------------------------------------------------
BOTH = ("four_bar", "spring_chain")


def test_the_names_that_are_both_a_robot_and_a_scene() -> None:
    from multibody_sim.scenes import shipped_scenes

    assert set(ms.CATALOG) & set(shipped_scenes()) == set(BOTH)


@pytest.mark.parametrize("name", BOTH)
def test_a_bare_shared_name_runs_the_scene_and_says_so(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    code, stdout, stderr = call(capsys, "run", name, "--duration", "0.01")
    assert code == 0
    assert stdout.startswith(f"scene '{name}': robot {name}")
    assert stderr == (
        f"multibody-sim: note: '{name}' names both a shipped scene and a catalog robot: taking the scene "
        f"(robot:{name} for the robot alone)\n"
    )
    # scene:NAME is the same run, without the note.
    code, explicit, stderr = call(capsys, "run", f"scene:{name}", "--duration", "0.01")
    assert (code, stderr) == (0, "")
    assert explicit.splitlines()[:3] == stdout.splitlines()[:3]


@pytest.mark.parametrize("name", BOTH)
def test_robot_prefix_runs_the_robot_alone(name: str, capsys: pytest.CaptureFixture[str]) -> None:
    robot = ms.load_robot(name)
    code, stdout, stderr = call(capsys, "run", f"robot:{name}", "--duration", "0.01")
    assert (code, stderr) == (0, "")
    base = "floating" if robot.floating_base else "fixed"
    assert stdout.splitlines()[0] == (
        f"run: {name} ({base} base, nq {robot.nq}, nv {robot.nv}), integrator rk4, dt 0.001 s, duration 0.01 s"
    )
    assert "scene" not in stdout


@pytest.mark.parametrize("name", BOTH)
def test_the_api_takes_the_same_prefixes(name: str) -> None:
    robot, prefixed = ms.load_robot(name), ms.load_robot(f"robot:{name}")
    assert type(robot) is type(prefixed) is ms.Robot
    assert prefixed.nq == robot.nq and prefixed.source["load_robot"]["source"] == name  # metadata as before
    scene, explicit = ms.load_scene(name), ms.load_scene(f"scene:{name}")
    assert isinstance(scene, ms.Scene) and isinstance(explicit, ms.Scene)
    assert explicit.spec.text == scene.spec.text


def test_unknown_prefixed_names_list_the_valid_ones(capsys: pytest.CaptureFixture[str]) -> None:
    from multibody_sim.scenes import shipped_scenes

    code, _, stderr = call(capsys, "run", "scene:ur5")
    assert code == 2
    assert stderr == (
        f"{PREFIX}unknown scene 'ur5': not a shipped scene nor an existing scene file (shipped: "
        f"{', '.join(shipped_scenes())})\n"
    )
    code, _, stderr = call(capsys, "run", "robot:ur55")
    assert code == 2 and stderr.startswith(f"{PREFIX}unknown robot 'ur55': not a catalog name")


def test_models_marks_the_names_that_are_both(capsys: pytest.CaptureFixture[str]) -> None:
    code, stdout, _ = call(capsys, "models")
    assert code == 0
    assert stdout.splitlines()[-1] == (
        "four_bar, spring_chain: both a robot and a scene; run, inspect and bench take the scene "
        "(robot:four_bar for the robot alone)"
    )
