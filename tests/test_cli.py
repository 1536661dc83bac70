"""The command line: output checked against the URDF files and the Python API, exit codes, signals."""

from __future__ import annotations

import hashlib
import io
import re
import shutil
import signal
import subprocess
import sys
import threading
import xml.etree.ElementTree as ET
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import joint, link, urdf

import multibody_sim as ms
from multibody_sim import cli
from multibody_sim.catalog import CATALOG, catalog_urdf
from multibody_sim.cli import main

PREFIX = "multibody-sim: error: "


def _console_script() -> Path:
    """The installed console script (the venv's bin folder, else PATH)."""
    beside = Path(sys.executable).with_name("multibody-sim")
    if beside.is_file():
        return beside
    found = shutil.which("multibody-sim")
    if found is None:
        pytest.fail("the multibody-sim console script is not installed (pip install -e .)")
    return Path(found)


def run_cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess[str]:
    """Run the real console script in a child process."""
    return subprocess.run([str(_console_script()), *args], capture_output=True, text=True, timeout=120, cwd=cwd)


# A shell may start background jobs with SIGINT ignored, and an ignored signal stays ignored across exec:
# Python then never turns SIGINT into KeyboardInterrupt. A real Ctrl-C reaches a foreground process with the
# default disposition, so the child restores it and execs the console script (preexec_fn is unsafe with threads).
_WITH_DEFAULT_SIGINT = [
    sys.executable,
    "-c",
    "import os, signal, sys; signal.signal(signal.SIGINT, signal.SIG_DFL); os.execv(sys.argv[1], sys.argv[1:])",
]


def interrupt_run(sig: signal.Signals, out: Path) -> subprocess.CompletedProcess[str]:
    """Start a run far too long to finish, signal it once it is stepping, and collect what it says."""
    # 3600 s of ur5 takes minutes: the run is surely still stepping when the signal arrives.
    script = str(_console_script())
    run = ["run", "ur5", "--duration", "3600", "--output-dt", "0.1", "--out", str(out)]
    args = [*_WITH_DEFAULT_SIGINT, script, *run]
    proc = subprocess.Popen(args, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    watchdog = threading.Timer(90.0, proc.kill)  # never hang the test run
    watchdog.start()
    try:
        assert proc.stdout is not None
        header = proc.stdout.readline()  # printed just before the first step, with the handlers in place
        threading.Event().wait(2.0)  # let it take some steps, even on a busy machine
        proc.send_signal(sig)
        stdout, stderr = proc.communicate(timeout=90)
    finally:
        watchdog.cancel()
        if proc.poll() is None:
            proc.kill()
            proc.wait()
    return subprocess.CompletedProcess(args, proc.returncode, header + stdout, stderr)


class ConsoleRuns:
    """Console-script runs started together: each child spends about a second importing the package, so
    running them side by side keeps this file within its time budget.

    Attributes:
        work: a folder for the runs' files.
    """

    def __init__(self, work: Path) -> None:
        self.work = work
        self._pool = ThreadPoolExecutor(max_workers=4)
        self._jobs: dict[str, Future[subprocess.CompletedProcess[str]]] = {}

    def start(self, key: str, job: Callable[..., subprocess.CompletedProcess[str]], *args: Any, **kw: Any) -> None:
        self._jobs[key] = self._pool.submit(job, *args, **kw)

    def __getitem__(self, key: str) -> subprocess.CompletedProcess[str]:
        return self._jobs[key].result(timeout=240)

    def close(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)


def call(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    """main(args) in this process: (exit code, stdout, stderr)."""
    code = main(list(args))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


def assert_one_line(stderr: str) -> str:
    """stderr is exactly one line and no traceback; returns it."""
    assert "Traceback" not in stderr
    lines = stderr.splitlines()
    assert len(lines) == 1, stderr
    return lines[0]


def urdf_joints(path: Path) -> dict[str, ET.Element]:
    """The URDF's movable joints by name, read with the standard library (independent of Pinocchio)."""
    root = ET.parse(path).getroot()
    # Direct children only: <transmission> and <gazebo> blocks hold <joint> elements of their own.
    return {j.get("name"): j for j in root.findall("joint") if j.get("type") != "fixed"}


def urdf_link_masses(path: Path) -> tuple[dict[str, float], str]:
    """({link: mass}, root link name) read from the URDF."""
    root = ET.parse(path).getroot()
    masses = {}
    for element in root.findall("link"):
        mass = element.find("inertial/mass")
        masses[element.get("name")] = float(mass.get("value")) if mass is not None else 0.0
    children = {j.find("child").get("link") for j in root.findall("joint")}
    (root_link,) = set(masses) - children
    return masses, root_link


def table_rows(text: str, header_start: str) -> list[list[str]]:
    """Rows of the table whose header line starts with header_start (columns are 2+ spaces apart)."""
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.strip().startswith(header_start))
    rows = []
    for line in lines[start + 1 :]:
        if not line.strip():
            break
        rows.append(re.split(r"\s{2,}", line.strip()))
    return rows


# ---- shared fixtures: input files, and every console-script run started at once ---------------------------
@pytest.fixture(scope="module")
def inputs(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A folder with a malformed URDF (and no missing.urdf)."""
    folder = tmp_path_factory.mktemp("inputs")
    (folder / "broken.urdf").write_text('<?xml version="1.0"?><robot name="x"><link name="a"></robot>')
    return folder


@pytest.fixture(scope="module")
def console(inputs: Path, tmp_path_factory: pytest.TempPathFactory) -> Iterator[ConsoleRuns]:
    """Every console-script run of this file, started together; tests wait for the one they check."""
    work = tmp_path_factory.mktemp("console")
    runs = ConsoleRuns(work)
    for sig in (signal.SIGINT, signal.SIGTERM):  # first: they mostly wait
        runs.start(sig.name, interrupt_run, sig, work / f"{sig.name}.npz")
    for name in ("happy", "diverging"):
        (work / name).mkdir()
    runs.start("happy", run_cli, "run", "ur5", "--duration", "0.2", "--out", "F.npz", cwd=work / "happy")
    runs.start("diverging", run_cli, *DIVERGING, "--out", "F.npz", cwd=work / "diverging")
    runs.start("models", run_cli, "models")
    runs.start("inspect panda", run_cli, "inspect", "panda")
    runs.start("integrators", run_cli, "integrators")
    for case in CONSOLE_BAD_INPUT:
        runs.start(case, run_cli, *BAD_INPUT[case](inputs)[0], cwd=inputs)
    yield runs
    runs.close()


# ---- run: the CLI passes every argument to the API ----------------------------------------------------
def test_run_matches_the_python_api(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """Every run option reaches simulate(): the saved file equals the API's result for the same arguments."""
    out = tmp_path / "dp.npz"
    argv = "run double_pendulum --integrator midpoint --dt 0.01 --duration 0.5 --q0 3.0 -0.2 --v0 0 1.5 --no-damping"
    argv += " --output-dt 0.05 --control-dt 0.02"
    code, stdout, stderr = call(capsys, *argv.split(), "--out", str(out))
    assert (code, stderr) == (0, "")
    robot = ms.load_robot("double_pendulum", damping=False)
    expected = ms.simulate(
        robot, [3.0, -0.2], [0.0, 1.5], duration=0.5, dt=0.01, integrator="midpoint", output_dt=0.05, control_dt=0.02
    )
    saved = ms.Trajectory.load(out)
    for name in ("t", "q", "v", "tau", "kinetic_energy", "potential_energy", "dissipated", "energy_error"):
        np.testing.assert_array_equal(getattr(saved, name), getattr(expected, name), err_msg=name)
    # output_dt = 0.05 over 0.5 s: 11 samples; the options are recorded as given.
    assert len(saved) == 11
    assert saved.metadata["options"] == {"dt": 0.01, "duration": 0.5, "output_dt": 0.05, "control_dt": 0.02}
    assert saved.metadata["integrator"] == "midpoint" and saved.metadata["robot"]["damping"] is False
    lines = stdout.splitlines()
    assert lines[0] == "run: double_pendulum (fixed base, nq 2, nv 2), integrator midpoint, dt 0.01 s, duration 0.5 s"
    # The printed summary is the saved trajectory's (wall time included: stats are saved with it).
    assert "\n".join(lines[1:-1]) == saved.summary()
    assert lines[-1] == f"wrote {out}"


def test_run_defaults(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """Defaults: rk4, dt 1e-3, duration 1 s, q0 the neutral configuration, v0 zero, damping on, every step."""
    out = tmp_path / "pendulum.npz"
    code, stdout, _ = call(capsys, "run", "pendulum", "--out", str(out))
    assert code == 0
    saved = ms.Trajectory.load(out)
    assert saved.metadata["integrator"] == "rk4"
    assert saved.metadata["options"] == {"dt": 1e-3, "duration": 1.0}
    assert len(saved) == 1001 and saved.t[-1] == 1.0  # 1 s / 1 ms steps, every step sampled
    np.testing.assert_array_equal(saved.q[0], [0.0])  # a single revolute joint: neutral is angle 0
    np.testing.assert_array_equal(saved.v[0], [0.0])
    assert saved.metadata["robot"]["damping"] is True
    assert stdout.startswith("run: pendulum (fixed base, nq 1, nv 1), integrator rk4, dt 0.001 s, duration 1 s\n")


def test_run_adaptive_tolerances(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """Adaptive methods get the documented default tolerances, or the given ones, and --max-step."""
    adaptive = sorted(name for name, method in ms.INTEGRATORS.items() if method.adaptive)
    if not adaptive:
        pytest.skip("no adaptive integrator registered")
    robot = ms.load_robot("ur5")
    for args, options in (
        ([], {"rtol": 1e-6, "atol": 1e-8}),
        (["--rtol", "1e-4", "--atol", "1e-7", "--max-step", "0.02"], {"rtol": 1e-4, "atol": 1e-7, "max_step": 0.02}),
    ):
        out = tmp_path / "adaptive.npz"
        argv = ["run", "ur5", "--integrator", adaptive[0], "--duration", "0.3", "--output-dt", "0.05", *args]
        code, stdout, _ = call(capsys, *argv, "--out", str(out))
        assert code == 0
        q0, v0 = robot.neutral(), np.zeros(6)
        expected = ms.simulate(robot, q0, v0, duration=0.3, dt=1e-3, integrator=adaptive[0], output_dt=0.05, **options)
        saved = ms.Trajectory.load(out)
        np.testing.assert_array_equal(saved.t, expected.t)
        np.testing.assert_array_equal(saved.q, expected.q)
        assert saved.metadata["options"] == {"dt": 1e-3, "duration": 0.3, "output_dt": 0.05, **options}
        assert f"rtol {options['rtol']:g}, atol {options['atol']:g}" in stdout.splitlines()[0]


def test_run_damping_flag(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """The double pendulum's URDF declares damping 0.05: it dissipates D v² > 0 unless --no-damping."""
    damping = {
        name: float(j.find("dynamics").get("damping"))
        for name, j in urdf_joints(catalog_urdf(CATALOG["double_pendulum"])[0]).items()
    }
    assert damping == {"joint1": 0.05, "joint2": 0.05}
    files = {}
    for flag in ([], ["--no-damping"]):
        out = files[bool(flag)] = tmp_path / f"dp{len(flag)}.npz"
        argv = ["run", "double_pendulum", "--duration", "0.2", "--v0", "1", "-1", *flag, "--out", str(out)]
        assert call(capsys, *argv)[0] == 0
    damped, free = ms.Trajectory.load(files[False]), ms.Trajectory.load(files[True])
    # Dissipated energy is ∫ D |v|² dt: the trapezoid rule on the 1 ms samples agrees to O(dt²).
    power = 0.05 * np.sum(damped.v**2, axis=1)
    assert power[0] == pytest.approx(0.1)  # v0 = (1, -1)
    trapezoid = float(np.sum((power[1:] + power[:-1]) / 2 * np.diff(damped.t)))
    assert damped.dissipated[-1] == pytest.approx(trapezoid, rel=1e-3)
    np.testing.assert_array_equal(free.dissipated, 0.0)


def test_run_base_flags(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    """--floating-base adds a free-flyer (nq + 7, nv + 6) to an arm; --fixed-base removes it from solo12."""
    n_ur5 = len(urdf_joints(catalog_urdf(CATALOG["ur5"])[0]))
    n_solo = len(urdf_joints(catalog_urdf(CATALOG["solo12"])[0]))
    assert (n_ur5, n_solo) == (6, 12)  # all revolute: one coordinate each
    cases = (("ur5", "--floating-base", n_ur5 + 7, n_ur5 + 6), ("solo12", "--fixed-base", n_solo, n_solo))
    for name, flag, nq, nv in cases:
        out = tmp_path / f"{name}.npz"
        code, stdout, _ = call(capsys, "run", name, flag, "--duration", "0.01", "--out", str(out))
        assert code == 0
        saved = ms.Trajectory.load(out)
        assert saved.q.shape == (11, nq) and saved.v.shape == (11, nv)
        assert saved.metadata["robot"]["floating_base"] is (flag == "--floating-base")
        base = "floating" if flag == "--floating-base" else "fixed"
        assert stdout.splitlines()[0].startswith(f"run: {name} ({base} base, nq {nq}, nv {nv})")


def test_run_package_dir_reaches_load_robot(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, write_urdf: Callable[..., Path]
) -> None:
    """A URDF path with --package-dir (given twice): both folders are recorded as load_robot's arguments."""
    path = write_urdf(urdf(link("base"), link("arm"), joint("j", "base", "arm")))
    dirs = [tmp_path / "share_a", tmp_path / "share_b"]
    for d in dirs:
        d.mkdir()
    out = tmp_path / "arm.npz"
    package_dirs = ["--package-dir", str(dirs[0]), "--package-dir", str(dirs[1])]
    code, stdout, _ = call(capsys, "run", str(path), *package_dirs, "--duration", "0.01", "--out", str(out))
    assert code == 0
    robot_meta = ms.Trajectory.load(out).metadata["robot"]
    assert robot_meta["load_robot"]["package_dirs"] == [str(d) for d in dirs]
    assert robot_meta["urdf_sha256"] == hashlib.sha256(path.read_bytes()).hexdigest()
    assert stdout.startswith("run: robot (fixed base, nq 1, nv 1)")  # a file's robot is named after its stem


def test_run_happy_path_console_script(console: ConsoleRuns) -> None:
    """The installed script: `run ur5 --duration 0.2 --out F.npz` writes a complete, documented trajectory."""
    result = console["happy"]
    assert (result.returncode, result.stderr) == (0, "")
    saved = ms.Trajectory.load(console.work / "happy" / "F.npz")
    assert saved.status == "completed"
    assert len(saved) == 201 and saved.t[0] == 0.0 and saved.t[-1] == 0.2  # 0.2 s of 1 ms steps
    np.testing.assert_allclose(np.diff(saved.t), 1e-3, rtol=1e-9)
    np.testing.assert_array_equal(saved.q[0], np.zeros(6))  # six revolute joints: neutral is all zeros
    np.testing.assert_array_equal(saved.v[0], np.zeros(6))
    np.testing.assert_array_equal(saved.tau, 0.0)  # no controller: no torque
    meta = saved.metadata
    assert meta["integrator"] == "rk4" and meta["options"] == {"dt": 1e-3, "duration": 0.2}
    assert meta["robot"]["name"] == "ur5"
    assert meta["robot"]["load_robot"] == {"source": "ur5", "floating_base": None, "damping": True, "package_dirs": []}
    urdf_path = catalog_urdf(CATALOG["ur5"])[0]
    assert meta["robot"]["urdf_sha256"] == hashlib.sha256(urdf_path.read_bytes()).hexdigest()
    assert meta["versions"]["pin"] not in ("", "not installed")
    # ur5 declares no damping and no torque acts: H is conserved; RK4's error at 1 ms is far below 1 µJ.
    np.testing.assert_array_equal(saved.dissipated, 0.0)
    assert np.max(np.abs(saved.total_energy - saved.total_energy[0])) < 1e-6
    lines = result.stdout.splitlines()
    assert lines[0] == "run: ur5 (fixed base, nq 6, nv 6), integrator rk4, dt 0.001 s, duration 0.2 s"
    assert "\n".join(lines[1:-1]) == saved.summary() and lines[-1] == "wrote F.npz"


class _ClosedPipe(io.StringIO):
    def write(self, text: str) -> int:
        raise BrokenPipeError(32, "Broken pipe")


def test_closed_stdout(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    """A reader that left (`| head`): a run still completes and writes its file; a listing ends with 141
    (128 + SIGPIPE), as shells report for tools that write into a closed pipe. No traceback either way."""
    monkeypatch.setattr(sys, "stdout", _ClosedPipe())
    out = tmp_path / "p.npz"
    assert main(["run", "pendulum", "--duration", "0.1", "--out", str(out)]) == 0
    assert len(ms.Trajectory.load(out)) == 101  # 0.1 s of 1 ms steps
    assert main(["integrators"]) == 128 + signal.SIGPIPE


# ---- models, inspect, integrators --------------------------------------------------------------------
def test_models_lists_the_catalog_with_sizes_from_the_urdfs(capsys: pytest.CaptureFixture[str]) -> None:
    from test_catalog import expected_sizes  # counted from the files, pruned and locked joints taken out

    code, stdout, stderr = call(capsys, "models")
    assert (code, stderr) == (0, "")
    rows = table_rows(stdout, "name")
    assert [r[0] for r in rows] == list(CATALOG)
    for name, nq, nv, base, poses, description in rows:
        assert (int(nq), int(nv)) == expected_sizes(name, CATALOG[name].floating_base), name
        assert base == ("floating" if CATALOG[name].floating_base else "fixed")
        robot = ms.load_robot(name)
        assert set(poses.replace("*", "").split(",")) == (set(robot.poses) or {"-"})
        assert description == CATALOG[name].description


def test_models_console_script(console: ConsoleRuns) -> None:
    result = console["models"]
    assert (result.returncode, result.stderr) == (0, "")
    robots, _, rest = result.stdout.partition("\n\n")  # the catalog, a note on its poses, the shipped scenes
    note, _, scenes = rest.partition("\n\n")
    assert note.startswith("poses: the SRDF's named poses")
    header, *rows = robots.splitlines()
    assert header.split() == ["name", "nq", "nv", "base", "poses", "description"]
    assert {r.split()[0] for r in rows} == set(CATALOG)
    assert scenes.startswith("scenes (run one with")
    ur5 = next(r for r in rows if r.split()[0] == "ur5")
    assert ur5.split()[1:4] == ["6", "6", "fixed"]


def test_inspect_panda_console_script(console: ConsoleRuns) -> None:
    """Joints, position and velocity limits, efforts, damping and masses as the URDF file declares them (read with
    ElementTree)."""
    result = console["inspect panda"]
    assert (result.returncode, result.stderr) == (0, "")
    out = result.stdout
    path = catalog_urdf(CATALOG["panda"])[0]
    assert f"URDF: {path}" in out.splitlines()
    assert f"sha256: {hashlib.sha256(path.read_bytes()).hexdigest()}" in out.splitlines()
    assert "nq: 9  nv: 9" in out and "base: fixed" in out
    joints = urdf_joints(path)
    rows = table_rows(out, "name")
    assert [r[0] for r in rows] == list(joints)  # panda's file lists its chain in kinematic order
    for name, kind, limits, velocity, effort, damping in rows:
        declared = joints[name]
        limit = declared.find("limit")
        unit = "m" if declared.get("type") == "prismatic" else "rad"
        assert kind == declared.get("type")
        assert limits == f"[{float(limit.get('lower')):g}, {float(limit.get('upper')):g}] {unit}"
        assert velocity == f"{float(limit.get('velocity')):g} {unit}/s"
        assert effort == f"{float(limit.get('effort')):g} {'N' if unit == 'm' else 'N·m'}"
        assert float(damping) == float(declared.find("dynamics").get("damping"))
    # Total mass: every link except the root, which is welded to the world.
    masses, root_link = urdf_link_masses(path)
    moving = sum(masses.values()) - masses[root_link]
    total = float(re.search(r"^total mass: (\S+) kg", out, re.M).group(1))
    assert total == pytest.approx(moving, rel=1e-5)  # printed with 6 significant digits
    # Each merged body weighs the sum of the URDF links it lists.
    for moved_by, mass, links in table_rows(out, "moved by joint"):
        assert float(mass) == pytest.approx(sum(masses[n] for n in links.split(", ")), rel=1e-5), moved_by
    assert "(welded to the world)" in [r[0] for r in table_rows(out, "moved by joint")]
    assert "dq/dt != v" not in out


def test_inspect_zero_limits_mean_none_and_floating_note(capsys: pytest.CaptureFixture[str]) -> None:
    """The double pendulum declares limits and effort 0 (meaning "none"); solo12 gets the q̇ ≠ v note."""
    path = catalog_urdf(CATALOG["double_pendulum"])[0]
    for declared in urdf_joints(path).values():
        assert (declared.find("limit").get("lower"), declared.find("limit").get("upper")) == ("0", "0")
    code, out, _ = call(capsys, "inspect", "double_pendulum")
    assert code == 0
    assert [r[:5] for r in table_rows(out, "name")] == [
        ["joint1", "revolute", "none", "none", "none"],
        ["joint2", "revolute", "none", "none", "none"],
    ]
    code, out, _ = call(capsys, "inspect", "solo12", "--no-damping")
    assert code == 0
    assert "nq: 19  nv: 18" in out and "dq/dt != v" in out and "base: floating" in out
    rows = table_rows(out, "name")
    assert rows[0][:5] == ["root_joint", "floating", "none", "unactuated", "unactuated"]
    assert all(float(d) == 0.0 for r in rows for d in r[5].split(", "))  # --no-damping reached load_robot


def test_inspect_a_scene_says_runs_start_from_its_initial_state(capsys: pytest.CaptureFixture[str]) -> None:
    """A scene of objects has no poses, yet its runs start where it places them (not from neutral): inspect says
    so, and the state a run starts from is the declared one."""
    code, out, _ = call(capsys, "inspect", "box_stack")
    assert code == 0 and "neutral" not in out
    assert "start: the scene's initial state ([initial], else the robot's default pose; objects as declared)" in out
    scene = ms.load_scene("box_stack")
    assert scene.run(duration=0.001, progress=False).q[0][2] == pytest.approx(0.05)  # the bottom box's declared z


@pytest.mark.parametrize("mode", ["in-process", "console script"])
def test_integrators_lists_the_registry(capsys: pytest.CaptureFixture[str], mode: str, request: Any) -> None:
    if mode == "in-process":
        code, out, err = call(capsys, "integrators")
    else:
        result = request.getfixturevalue("console")["integrators"]
        code, out, err = result.returncode, result.stdout, result.stderr
    assert (code, err) == (0, "")
    rows = {r[0]: r for r in table_rows(out, "name")}
    assert list(rows) == list(ms.INTEGRATORS)
    # Classical orders and stage counts (Hairer, Nørsett & Wanner, Solving ODEs I, ch. II; Bogacki & Shampine
    # 1989; Dormand & Prince 1980): the names the catalog of methods has always meant.
    known = {
        "euler": (1, 1),
        "semi_implicit_euler": (1, 1),
        "midpoint": (2, 2),
        "rk4": (4, 4),
        "bs32": (3, 4),
        "dp54": (5, 7),
    }
    for name, (order, stages) in known.items():
        if name in rows:
            assert rows[name][1:3] == [str(order), str(stages)], name
    assert rows.get("implicit_euler", ["", "1"])[1] == "1" and rows.get("implicit_midpoint", ["", "2"])[1] == "2"
    for name, method in ms.INTEGRATORS.items():
        properties = {"adaptive": method.adaptive, "implicit": method.implicit, "symplectic": method.symplectic}
        flags = [flag for flag, on in {**properties, "A-stable": method.a_stable}.items() if on]
        assert rows[name][3] == (", ".join(flags) or "-")
        assert rows[name][4] == method.description
        if method.notes:
            assert f"  {name}: {method.notes}" in out.splitlines()


def test_help_and_version(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, _ = call(capsys, "--help")
    assert code == 0 and all(c in out for c in ("run", "models", "inspect", "integrators"))
    code, out, _ = call(capsys, "run", "--help")
    assert code == 0 and "default: rk4" in out and "default: 0.001" in out and "default: 1)" in out
    code, out, _ = call(capsys, "--version")
    lines = out.splitlines()
    assert code == 0 and lines[0] == f"multibody-sim {ms.__version__}"
    assert len(lines) == 2 and lines[1].startswith(("kernel: native (C++, Pinocchio ", "kernel: python (")), lines


# ---- bad input: one line, exit 2 ---------------------------------------------------------------------
def _api_message(call_api: Callable[[], object]) -> str:
    """The message of the MultibodySimError the API raises for the same input."""
    with pytest.raises(ms.MultibodySimError) as info:
        call_api()
    return str(info.value)


BAD_INPUT: dict[str, Callable[[Path], tuple[list[str], str]]] = {
    # Each case: tmp_path -> (argv, the exact stderr line).
    "unknown robot": lambda tmp: (["run", "urr5"], _api_message(lambda: ms.load_robot("urr5"))),
    "missing URDF": lambda tmp: (
        ["run", str(tmp / "missing.urdf")],
        _api_message(lambda: ms.load_robot(tmp / "missing.urdf")),
    ),
    "malformed URDF": lambda tmp: (
        ["inspect", str(tmp / "broken.urdf")],
        _api_message(lambda: ms.load_robot(tmp / "broken.urdf")),
    ),
    "unknown integrator": lambda tmp: (
        ["run", "pendulum", "--integrator", "rk5"],
        _api_message(lambda: ms.get_integrator("rk5")),
    ),
    "negative dt": lambda tmp: (
        ["run", "pendulum", "--dt", "-0.01"],
        _api_message(lambda: ms.simulate(ms.load_robot("pendulum"), [0.0], [0.0], duration=1.0, dt=-0.01)),
    ),
    "non-number dt": lambda tmp: (["run", "pendulum", "--dt", "fast"], "argument --dt: invalid float value: 'fast'"),
    "wrong q0 length": lambda tmp: (["run", "ur5", "--q0", "0.1", "0.2"], "q0 must have shape (6,), got (2,)"),
    "output-dt not a multiple of dt": lambda tmp: (
        ["run", "pendulum", "--output-dt", "0.0015"],
        _api_message(
            lambda: ms.simulate(ms.load_robot("pendulum"), [0.0], [0.0], duration=1.0, dt=1e-3, output_dt=0.0015)
        ),
    ),
    "both base flags": lambda tmp: (
        ["run", "ur5", "--floating-base", "--fixed-base"],
        "argument --fixed-base: not allowed with argument --floating-base",
    ),
    "missing robot argument": lambda tmp: (["run"], "the following arguments are required: ROBOT_OR_URDF"),
    "unknown subcommand": lambda tmp: (
        ["rnu", "ur5"],
        f"unknown command 'rnu' (did you mean run? choose from: {', '.join(cli.COMMANDS)})",
    ),
    "no subcommand": lambda tmp: (
        [],
        f"no command given (choose from: {', '.join(cli.COMMANDS)}; see multibody-sim --help)",
    ),
    "out is a directory": lambda tmp: (
        ["run", "pendulum", "--out", str(tmp)],
        f"--out {tmp}: is a directory, expected a file name such as run.npz",
    ),
}


# Every bad-input path also through the real console script, except the CLI's own --out check (in-process
# covers it; each child costs a second of imports).
CONSOLE_BAD_INPUT = [case for case in BAD_INPUT if case != "out is a directory"]


@pytest.mark.parametrize(
    ("case", "mode"),
    [(case, "in-process") for case in BAD_INPUT] + [(case, "console script") for case in CONSOLE_BAD_INPUT],
)
def test_bad_input_is_one_line_and_exit_2(
    case: str, mode: str, inputs: Path, capsys: pytest.CaptureFixture[str], request: Any
) -> None:
    argv, message = BAD_INPUT[case](inputs)
    if mode == "in-process":
        code, _, err = call(capsys, *argv)
    else:
        result = request.getfixturevalue("console")[case]
        code, err = result.returncode, result.stderr
    assert code == 2
    assert assert_one_line(err) == PREFIX + message


def test_bad_input_messages_name_the_valid_options(inputs: Path) -> None:
    """The API-derived lines above say what to do: close matches, valid names, the expected shape."""
    lines = {case: BAD_INPUT[case](inputs)[1] for case in BAD_INPUT}
    assert "did you mean ur5" in lines["unknown robot"] and "multibody-sim models" in lines["unknown robot"]
    assert lines["missing URDF"] == f"{inputs / 'missing.urdf'}: URDF file not found"
    assert lines["malformed URDF"].startswith(f"{inputs / 'broken.urdf'}: malformed XML")
    assert all(name in lines["unknown integrator"] for name in ms.INTEGRATORS)
    assert "dt" in lines["negative dt"] and "-0.01" in lines["negative dt"]
    assert "output_dt" in lines["output-dt not a multiple of dt"] and "0.001" in lines["output-dt not a multiple of dt"]


# ---- failures and interruptions ----------------------------------------------------------------------
DIVERGING = ["run", "double_pendulum", "--integrator", "euler", "--dt", "0.5", "--duration", "50", "--v0", "30", "30"]


def _check_diverged(code: int, stderr: str, out: Path, shown: str | None = None) -> None:
    """Exit 1; one line naming the time and a joint; the file holds the finite samples up to that time."""
    assert code == 1
    line = assert_one_line(stderr)
    assert line.startswith(PREFIX + "diverged at t = ")
    assert line.endswith(f"written to {shown or out}")
    assert re.search(r"'(joint1|joint2)'", line)  # the double pendulum's joints
    t_stop = float(re.search(r"at t = (\S+) s", line).group(1))
    saved = ms.Trajectory.load(out)
    assert saved.status == "diverged"
    assert saved.t[-1] == pytest.approx(t_stop, rel=1e-6) and t_stop < 50.0  # the message prints 6 digits
    assert f"({len(saved)} samples, t = 0..{saved.t[-1]:g} s)" in line
    for name in ("t", "q", "v", "tau", "total_energy", "energy_error"):
        assert np.all(np.isfinite(getattr(saved, name))), name
    np.testing.assert_allclose(np.diff(saved.t), 0.5)  # every 0.5 s step up to the stop


def test_diverging_run_in_process(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    out = tmp_path / "div.npz"
    code, stdout, stderr = call(capsys, *DIVERGING, "--out", str(out))
    _check_diverged(code, stderr, out)
    assert "status: diverged" in stdout  # the partial run's summary


def test_diverging_run_console_script(console: ConsoleRuns) -> None:
    result = console["diverging"]
    _check_diverged(result.returncode, result.stderr, console.work / "diverging" / "F.npz", "F.npz")


def test_diverging_run_without_out_says_nothing_was_saved(capsys: pytest.CaptureFixture[str]) -> None:
    code, _, stderr = call(capsys, *DIVERGING)
    assert code == 1
    assert assert_one_line(stderr).endswith("not saved (pass --out FILE.npz to keep it)")


@pytest.mark.parametrize(("sig", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_signal_stops_the_run_and_keeps_the_samples(sig: signal.Signals, code: int, console: ConsoleRuns) -> None:
    """SIGINT and SIGTERM: exit 130 / 143, one line saying where it stopped, the samples so far on disk."""
    result = console[sig.name]
    out = console.work / f"{sig.name}.npz"
    assert result.stdout.startswith("run: ur5 ")
    assert result.returncode == code
    line = assert_one_line(result.stderr)
    assert line.startswith(f"multibody-sim: {sig.name}: interrupted at t = ")
    assert line.endswith(f"written to {out}")
    saved = ms.Trajectory.load(out)
    assert saved.status == "interrupted"
    assert saved.t[-1] > 0
    t_stop = float(re.search(r"at t = (\S+) s", line).group(1))
    assert saved.t[-1] == pytest.approx(t_stop, rel=1e-6)  # the message prints 6 digits
    assert f"({len(saved)} samples, t = 0..{saved.t[-1]:g} s)" in line
    # Samples every 0.1 s, then the state where it stopped.
    np.testing.assert_allclose(np.diff(saved.t[:-1]), 0.1, rtol=1e-9)
    assert 0 < saved.t[-1] - saved.t[-2] <= 0.1 + 1e-9
    assert np.all(np.isfinite(saved.q)) and np.all(np.isfinite(saved.v))
    assert "status: interrupted" in result.stdout
