"""The README runs as written (a README that lies is worse than none): every Python example, its scene file and
every shell command, each checked on what it prints (key lines and figures), not only that it runs.

Commands run in a temporary folder (with `models/` linked in, as in a checkout), in the order of their block,
through `main()` in this process, except `python -m`, the console script of the install line and the serving
commands (see COMMANDS). A few are long as written (a 10,000 s run, a full study, a fresh install); the default
suite runs them shortened (COMMANDS' `short`), and `-m slow` runs them verbatim.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
import shlex
import shutil
import subprocess
import sys
import threading
import time
import urllib.request
import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pytest

import multibody_sim as ms
from multibody_sim.cli import main

ROOT = Path(__file__).resolve().parents[1]
README = ROOT / "README.md"
TEXT = README.read_text()
BLOCKS = re.findall(r"```python\n(.*?)```", TEXT, re.S)
TOML_BLOCKS = re.findall(r"```toml\n(.*?)```", TEXT, re.S)
BASH_BLOCKS = re.findall(r"```bash\n(.*?)```", TEXT, re.S)
FLOAT = r"[-+]?\d+(?:\.\d+)?(?:e[-+]?\d+)?"


# ---- Python examples ------------------------------------------------------------------------------------------
# What each example prints, as regular expressions each matching a line of its output, keyed by a line of code
# that marks the example. Figures are checked against what the example's own setting implies (sample counts from
# durations and steps, sizes from the models), never copied from a run.
PRINTS: dict[str, list[str]] = {
    'robot = ms.load_robot("panda")': [
        r"^9 9 \['panda_joint1', 'panda_joint2', 'panda_joint3'\]$",  # 7 arm joints + 2 fingers
        r"^status: completed$",
        rf"^\(501,\) \(501, 9\) {FLOAT} {FLOAT} {FLOAT}$",  # 0.5 s at 1 ms: 501 samples
    ],
    "except ms.SimulationError as err:": [
        r"^diverged - diverged at t = ",
        rf"^\d+ finite samples kept, up to t = {FLOAT}$",
    ],
    "batch = ms.rollout(ur5, q0s, v0s": [
        r"^<BatchTrajectory 32 elements, up to 31 samples each: 32 completed>$",  # 0.3 s every 10 ms: 31 samples
        r"^\(32, 31, 6\) \['completed' 'completed'\] \[ *\d+ +\d+\]$",
    ],
    "track = ms.ComputedTorque(": [
        rf"^{FLOAT}$",
        r"local minim",
    ],
    "stepper = ms.Stepper(robot": [rf"^0\.05 {FLOAT} {FLOAT} {FLOAT}$"],  # advanced to 0.05 s
    "env = MultibodyEnv(arm": [
        r"^\(12,\) \[150\. 150\. 150\.  28\.  28\.  28\.\]$",  # ur5's URDF efforts
        rf"^t = 1\.00 s, reward {FLOAT}$",  # 50 steps of 20 ms
        r"^\(8, 12\) \(8,\)$",
    ],
    "scene = ms.make_scene(": [r"nq/nv 2/2", rf"^potential {FLOAT} work$"],
    'arm = ms.make_scene(robot={"source": "ur5"}, actuator=': [
        r"^completed True$",
        r"^True \(101, 6\)$",  # 1 s at 10 ms
        r"^\['actuator:elbow_joint', 'actuator:shoulder_lift_joint'\]$",
        r"^  actuator FL_calf_joint: torque, gear 12\.134, armature 0\.01647, effort 45\.43, speed 15\.7, curve",
    ],
    'traj = ms.simulate(arm, q0, np.zeros(arm.nv), duration=1.0, dt=1e-3, integrator="dp54"': [
        r"^\d+ steps, \d+ rejected, 101 samples$",  # 1 s every 10 ms
    ],
    "study = ms.work_precision(": [r"^reference: dop853", r"^rk4 +4 "],
    'box = ms.load_scene("sliding_box")  # 1 kg': [
        rf"^row 3: mass {FLOAT} kg, μ {FLOAT}: slid {FLOAT} m, v0²/\(2μg\) = {FLOAT} m$",
        r"^row 3 re-run alone: True$",
    ],
    'solo = ms.load_robot("solo12")': [
        r"^\('standing', 'straight_standing'\) standing$",
        rf"^{FLOAT}$",
    ],
    'scene = ms.load_scene("sliding_box.toml")': [
        r"^  ground: plane z = 0 m, friction 0\.8, restitution 0$",  # its [ground] table
        r"^status: completed$",
        r"^steps: 400 ",  # 0.4 s at 1 ms
        r"^energy \[J\]: T 2 -> ",  # 1 kg at 2 m/s: 2 J
    ],
    'scene = ms.load_scene("box_sensors.toml")': [
        r"^\(601, 6\) \(601, 3\)$",  # 0.6 s at 1 ms: 601 samples; 6 and 3 components
        # in free fall the IMU reads its bias and noise (0.1 ± 0.02), at rest g + 0.1; the touch sensor m g
        r"^falling: az 0\.\d\d, resting: az 9\.9\d m/s², touch 9\.810 N$",
        r"^\(3001, 1\) 2\.600$",  # 3 s at 1 ms, one joint, held at its target 2.6 rad
    ],
    "df = traj.to_dataframe()": [r"^\s+t\s+q\.root_joint\.z\s+v\.root_joint\.vz\s+q\.FL_KFE\s+total_energy$"],
}


def _marker(block: str) -> str:
    markers = [m for m in PRINTS if m in block]
    assert len(markers) <= 1, f"a README example matches several PRINTS markers: {markers}"
    return markers[0] if markers else ""


def test_readme_has_python_examples() -> None:
    assert len(BLOCKS) >= 2


def test_every_example_that_prints_is_checked() -> None:
    """A new example that prints needs its expected lines here; a marker must still mark an example."""
    unchecked = [b.splitlines()[0] for b in BLOCKS if "print(" in b and not _marker(b)]
    assert unchecked == []
    stale = [m for m in PRINTS if not any(m in b for b in BLOCKS)]
    assert stale == []


@pytest.mark.parametrize("index", range(len(BLOCKS)))
def test_readme_python_example_runs(index: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)  # examples write files into the working directory
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        exec(compile(BLOCKS[index], f"README.md python block {index}", "exec"), {"__name__": "__readme__"})
    _expect_lines(out.getvalue(), PRINTS.get(_marker(BLOCKS[index]), []))


@pytest.mark.parametrize("index", range(len(TOML_BLOCKS)))
def test_readme_scene_example_runs(index: int, tmp_path: Path) -> None:
    """The README's scene file loads and runs as its [simulation] table says."""
    path = tmp_path / "scene.toml"
    path.write_text(TOML_BLOCKS[index])
    scene = ms.load_scene(path)
    traj = scene.run(duration=0.05)
    assert traj.status == "completed" and traj.t[-1] == pytest.approx(0.05)
    if "[[actuator]]" in TOML_BLOCKS[index]:  # the catalog's 12 motors, the calves as servos
        assert len(scene.actuators.items) == 12 and traj.ctrl is not None
        assert [a.kind for a in scene.actuators.items].count("position") == 4
    elif "[randomize]" in TOML_BLOCKS[index]:  # the box's mass and the ground's friction, drawn per row
        assert [table.name for table, _, _ in scene.randomizer.tables] == ["mass", "ground_friction"]
        assert 0.8 <= scene.draw_parameters(0)["mass"]["box"] <= 1.25
    else:
        assert scene.nv == 7 and "force:push" in traj.ledger  # the locks and the force it declares are in force


def _expect_lines(output: str, patterns: list[str]) -> None:
    lines = output.splitlines()
    for pattern in patterns:
        assert any(re.search(pattern, line) for line in lines), f"no line matches {pattern!r} in:\n{output}"


# ---- shell commands --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class Command:
    """How a README command is run and checked.

    Attributes:
        lines: regular expressions, each matching a line of its output (stdout and stderr).
        code: its exit code.
        short: (old, new) substitutions for the default suite; the verbatim command runs with `-m slow`.
        how: "cli" (main() here), "python -m" (a subprocess), "install" (the quick start's install line), "ci"
            (the test command), "serve" (play's server, interrupted) or "view" (run --view, watched in chromium).
        check: a function of the folder it ran in, for the files it wrote.
    """

    lines: tuple[str, ...] = ()
    code: int = 0
    short: tuple[tuple[str, str], ...] = ()
    how: str = "cli"
    check: Any = None


def _npz_samples(name: str, n: int) -> Any:
    def check(folder: Path) -> None:
        assert len(ms.Trajectory.load(folder / name)) == n

    return check


def _free_fall(folder: Path) -> None:
    """The free body falls for 1 s from rest: T = m g² t² / 2 with the mass from its URDF, as V falls by as much."""
    urdf = ET.parse(ROOT / "models/free_body/free_body.urdf").getroot()
    mass = sum(float(m.get("value")) for m in urdf.iter("mass"))
    traj = ms.Trajectory.load(folder / "free_body.npz")
    assert traj.kinetic_energy[-1] == pytest.approx(mass * 9.81**2 / 2, rel=1e-9)


def _json_run(folder: Path) -> None:
    document = json.loads((folder / "run.json").read_text())
    assert document["robot"]["name"] == "pendulum" and document["summary"]["status"] == "completed"
    assert document["duration"] == 0.5 and document["summary"]["stats"]["steps"] == 500


def _csv_and_parquet(folder: Path) -> None:
    header = (folder / "ur5.csv").read_text().splitlines()[0].split(",")
    assert header[:2] == ["t", "q.shoulder_pan_joint"] and len(header) == 26
    assert (folder / "ur5.parquet").read_bytes()[:4] == b"PAR1"


def _png(name: str) -> Any:
    def check(folder: Path) -> None:
        assert (folder / name).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    return check


def _html(folder: Path) -> None:
    page = (folder / "ur5.html").read_text()
    assert "<title>ur5 (rk4) - multibody-sim</title>" in page


def _video(folder: Path) -> None:
    imageio = pytest.importorskip("imageio.v3")
    frames = imageio.imread(folder / "ur5.mp4", plugin="pyav" if _has("av") else None)
    duration = ms.Trajectory.load(folder / "ur5.npz").t[-1]
    assert len(frames) == round(duration * 30)  # duration / speed x fps


def _has(module: str) -> bool:
    import importlib.util

    return importlib.util.find_spec(module) is not None


def _study(folder: str, orders: dict[str, float]) -> Any:
    def check(cwd: Path) -> None:
        study = ms.WorkPrecision.from_json(cwd / folder / "work_precision.json")
        for name, order in orders.items():  # the methods' theoretical orders
            assert abs(study.orders[name].observed - order) < 0.4, (name, study.orders[name])

    return check


SOLO_V0 = "0 0 0 0.5 0 0 3 -3 3 -3 3 -3 3 -3 3 -3 3 -3"
COMMANDS: dict[str, Command] = {
    # Quick start
    "python3 -m venv .venv && .venv/bin/pip install -q . && "
    ".venv/bin/multibody-sim run ur5 --duration 2 --out ur5.npz": (
        Command(
            lines=(
                r"^run: ur5 \(fixed base, nq 6, nv 6\), integrator rk4, dt 0\.001 s, duration 2 s$",
                r"^status: completed$",
                r"^steps: 2000 ",
                r"^wrote ur5\.npz$",
            ),
            how="install",
            check=_npz_samples("ur5.npz", 2001),
        )
    ),
    "bash scripts/test.sh": Command(how="ci"),
    # Controllers
    "multibody-sim run ur5 --controller pd_gravity --param kp=400,400,200,40,40,10 "
    "--param q_ref=0.3,-1.2,1.4,-0.6,1.2,0.5 --duration 3": Command(
        lines=(r"duration 3 s, controller pd_gravity$", r"^status: completed$", r"^steps: 3000 ")
    ),
    "multibody-sim run point_robot --controller potential_field --param goal=2,0 --param obstacle=0,0,0.5 "
    "--q0 -2 0 --duration 10": Command(
        lines=(r"^status: completed$", r"^potential field: reached the goal \(distance \d\.\d+e-0[5-9]\)")
    ),
    "multibody-sim run ur5 --controller computed_torque --param waypoint=0,-1.2,1.4,-0.6,1.2,0.5 "
    "--param waypoint=0.5,-1,1,-0.3,1,0.8 --q0 0 -1.2 1.4 -0.6 1.2 0.5": Command(
        lines=(r"^status: completed$", r"^computed torque: max tracking error \d\.\d+e-0[4-9] ")
    ),
    # Command line
    "multibody-sim models": Command(
        lines=(
            r"^ur5 +6 +6 +fixed ",
            r"^solo12 +19 +18 +floating +standing\*,straight_standing ",
            r"^ +double_pendulum_spring_friction ",  # the shipped scenes
        )
    ),
    "multibody-sim inspect panda": Command(
        lines=(  # the panda URDF's own limits
            r"^nq: 9  nv: 9$",
            r"^ +panda_joint1 +revolute +\[-2\.8973, 2\.8973\] rad +2\.175 rad/s +87 N·m ",
            r"^ +panda_joint7 +revolute +\[-2\.8973, 2\.8973\] rad +2\.61 rad/s +12 N·m ",
            r"^ +panda_finger_joint1 +prismatic +\[0, 0\.04\] m +0\.2 m/s +100 N ",
        )
    ),
    "multibody-sim integrators": Command(lines=(r"^rk4 +4 +4 ", r"^dop853 +8 +13 +adaptive ")),
    "multibody-sim run ur5 --integrator rk4 --dt 1e-3 --duration 2 --q0 0 -1 1 0 0 0 --out ur5.npz": Command(
        lines=(r"^status: completed$", r"^wrote ur5\.npz$"), check=_npz_samples("ur5.npz", 2001)
    ),
    "multibody-sim run models/free_body/free_body.urdf --floating-base --out free_body.npz": Command(
        lines=(r"^run: free_body \(floating base, nq 7, nv 6\)", r"^status: completed$"), check=_free_fall
    ),
    "multibody-sim run pendulum --q0 1 --duration 10000 --output-dt 0.01 --chunk 100000 --out long.npz": Command(
        lines=(r"^status: completed$",),
        short=(("--duration 10000", "--duration 3"), ("--chunk 100000", "--chunk 100")),
        check=lambda folder: None,  # the sample count depends on the duration: checked in _run_block
    ),
    "multibody-sim run pendulum --q0 1 --duration 0.5 --json > run.json": Command(check=_json_run),
    "python -m multibody_sim run pendulum --q0 1 --duration 0.5": Command(
        lines=(r"^status: completed$", r"^steps: 500 "), how="python -m"
    ),
    # Scenes
    "multibody-sim run double_pendulum_spring_friction": Command(
        lines=(r"^status: completed$", r"^ledger \[J\]: work 0, dissipated \d")
    ),
    "multibody-sim run my_scene.toml --duration 5 --out run.npz": Command(
        lines=(r"^run: my_scene \(fixed base, nq 7, nv 7\)", r"^status: completed$"),  # 9 dof, 2 fingers locked
        short=(("--duration 5", "--duration 0.5"),),
    ),
    "multibody-sim run talos_upper_body --report-savings": Command(
        lines=(
            r"^savings \(RK4, CPU-time medians .*\): scene \d.* µs/step, full robot model \d.* µs/step",
            r"^status: completed$",
        )
    ),
    "multibody-sim inspect talos_upper_body": Command(lines=(r"model nq/nv 32/32 -> 20/20",)),  # 12 leg joints
    # Viewing
    "multibody-sim run ur5 --duration 3 --out ur5.npz --view": Command(
        lines=(r"^view: http://127\.0\.0\.1:\d+/", r"^status: completed$"),
        short=(("--duration 3", "--duration 0.5"),),
        how="view",
    ),
    "multibody-sim play ur5.npz": Command(lines=(r"^play: ur5, ",), how="serve"),
    "multibody-sim play ur5.npz --html ur5.html --plot": Command(
        lines=(r"^wrote ur5\.html \(.* MB in .* s\): opens from disk, offline$",), check=_html
    ),
    "multibody-sim play ur5.npz --video ur5.mp4 --fps 30": Command(lines=(r"^wrote ur5\.mp4",), check=_video),
    "multibody-sim plot ur5.npz --out ur5.png": Command(lines=(r"^wrote ur5\.png$",), check=_png("ur5.png")),
    "multibody-sim plot ur5.npz --joints shoulder_pan_joint,elbow_joint": Command(
        lines=(r"^wrote ur5\.png$",), check=_png("ur5.png")
    ),
    # Speed and accuracy
    "multibody-sim bench ur5 --duration 1 --out bench/": Command(
        lines=(r"^reference: dop853 rtol 1e-14", r"^wrote bench/work_precision\.csv"),
        short=(("--duration 1", "--duration 0.2 --integrators midpoint,rk4,dp54"),),  # every one: 13 s of CPU
        check=_study("bench", {"rk4": 4.0, "midpoint": 2.0}),
    ),
    "multibody-sim bench solo12 --integrators rk4,dp54,implicit_midpoint --q0 standing "
    f"--v0 {SOLO_V0} --duration 0.5": Command(
        lines=(r"^bench: solo12 \(floating base, nq 19, nv 18\), duration 0\.5 s$", r"^rk4 +4 +\d\.\d\d "),
        check=_study(".", {"rk4": 4.0, "implicit_midpoint": 2.0}),
    ),
    "multibody-sim run ur5 --duration 5 --tolerance 1e-6 --out ur5.npz": Command(
        lines=(r"^tolerance 1e-06 over the first 1 s: chose \w+", r"^status: completed$")
    ),
    # Catalog
    "multibody-sim run solo12 --q0 straight_standing --duration 0.5": Command(
        lines=(r"^run: solo12 \(floating base, nq 19, nv 18\)", r"^status: completed$")
    ),
    "multibody-sim inspect talos": Command(lines=(r"^poses: half_sitting \(default\)",)),
    # Tables
    "multibody-sim export ur5.npz --csv ur5.csv --parquet ur5.parquet": Command(
        lines=(r"^wrote ur5\.csv \(2001 rows x 26 columns", r"^wrote ur5\.parquet \(2001 rows x 26 columns"),
        check=_csv_and_parquet,
    ),
}
# Files a block reads that an earlier block wrote: the command that makes them, run first.
PRELUDE = {"multibody-sim export ur5.npz": "multibody-sim run ur5 --duration 2 --out ur5.npz"}
SLOW = [line for line, command in COMMANDS.items() if command.short or command.how == "install"]


def readme_commands(block: str) -> list[str]:
    """The command lines of a bash block, without their trailing comments."""
    lines = (re.sub(r"\s+#\s.*$", "", line).strip() for line in block.splitlines())
    return [line for line in lines if line and not line.startswith("#")]


def test_every_readme_command_is_tested() -> None:
    commands = {line for block in BASH_BLOCKS for line in readme_commands(block)}
    assert sorted(commands - set(COMMANDS)) == []  # a new README command needs its entry in COMMANDS
    assert sorted(set(COMMANDS) - commands) == []  # and an entry whose command left the README goes


def test_the_test_command_is_what_ci_runs() -> None:
    """The quick start's second command is the whole test run, and .ci/run calls exactly it (CONTRACTS)."""
    quick_start = readme_commands(BASH_BLOCKS[0])
    assert quick_start[1] == "bash scripts/test.sh"
    ci = [line for line in (ROOT / ".ci/run").read_text().splitlines() if line and not line.startswith("#")]
    assert ci[-1] == "bash scripts/test.sh"


@pytest.mark.parametrize("index", range(len(BASH_BLOCKS)))
def test_readme_commands_run(
    index: int, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    _run_block(readme_commands(BASH_BLOCKS[index]), tmp_path, monkeypatch, capsys, verbatim=False)


@pytest.mark.slow
@pytest.mark.parametrize("line", SLOW, ids=[line.split(" && ")[-1] for line in SLOW])
def test_long_readme_commands_run_verbatim(
    line: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    block = next(b for b in map(readme_commands, BASH_BLOCKS) if line in b)
    _run_block(block[: block.index(line) + 1], tmp_path, monkeypatch, capsys, verbatim=True)


def _run_block(
    lines: list[str],
    folder: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    *,
    verbatim: bool,
) -> None:
    """Run a block's commands in order in `folder`, a checkout's stand-in, and check each."""
    (folder / "models").symlink_to(ROOT / "models")  # paths as in a checkout
    (folder / "my_scene.toml").write_text(TOML_BLOCKS[0])  # "the scene above, saved as my_scene.toml"
    monkeypatch.chdir(folder)
    monkeypatch.setenv("XDG_CACHE_HOME", str(folder / "cache"))  # run --tolerance's pilot starts afresh
    for prefix, needed in PRELUDE.items():
        if any(line.startswith(prefix) for line in lines):
            assert main(shlex.split(needed)[1:]) == 0
    capsys.readouterr()
    for line in lines:
        command = COMMANDS[line]
        run = line
        if not verbatim:
            for old, new in command.short:
                assert old in run
                run = run.replace(old, new)
        code, output = _execute(run, command, folder, monkeypatch, capsys, verbatim)
        assert code == command.code, f"{run}\n{output}"
        _expect_lines(output, list(command.lines))
        if command.check is not None:
            command.check(folder)
        if "--out long.npz" in run:  # sampled every 10 ms over its duration
            duration = float(re.search(r"--duration (\S+)", run).group(1))  # type: ignore[union-attr]
            assert len(ms.Trajectory.load(folder / "long.npz")) == round(duration / 0.01) + 1


def _execute(
    line: str,
    command: Command,
    folder: Path,
    monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
    verbatim: bool,
) -> tuple[int, str]:
    """Run one command as `command.how` says: (exit code, its output)."""
    if command.how == "ci":
        return 0, ""  # the whole suite: what CI runs (test_the_test_command_is_what_ci_runs)
    if command.how == "install":
        if verbatim:  # a fresh venv in a copy of the checkout: pip builds and installs the package
            checkout = folder / "checkout"
            shutil.copytree(ROOT, checkout, ignore=shutil.ignore_patterns(".venv", "build", ".git", "*.npz"))
            lock = os.environ.get("MULTIBODY_SIM_BUILD_LOCK")  # as scripts/test.sh: one C++ build at a time
            shell = f"flock {shlex.quote(lock)} bash -c {shlex.quote(line)}" if lock else line
            done = subprocess.run(shell, shell=True, cwd=checkout, capture_output=True, text=True, timeout=3600)
            shutil.copy(checkout / "ur5.npz", folder / "ur5.npz")
            return done.returncode, done.stdout + done.stderr
        # The line's last command, through this environment's installed console script.
        script = Path(sys.executable).with_name("multibody-sim")
        argv = [str(script), *shlex.split(line.split("&&")[-1])[1:]]
        done = subprocess.run(argv, cwd=folder, capture_output=True, text=True, timeout=600)
        return done.returncode, done.stdout + done.stderr
    if command.how == "python -m":
        argv = [sys.executable, *shlex.split(line)[1:]]
        done = subprocess.run(argv, cwd=folder, capture_output=True, text=True, timeout=600)
        return done.returncode, done.stdout + done.stderr
    tokens = shlex.split(line)
    assert tokens[0] == "multibody-sim"
    argv, target = tokens[1:], None
    if ">" in argv:  # a shell redirect of stdout into a file
        at = argv.index(">")
        argv, target = argv[:at], argv[at + 1]
    if command.how == "serve":
        return _serve(argv, monkeypatch, capsys)
    if command.how == "view":
        return _view(argv, capsys)
    code = main(argv)
    captured = capsys.readouterr()
    if target is not None:
        (folder / target).write_text(captured.out)
        return code, captured.err
    return code, captured.out + captured.err


def _serve(argv: list[str], monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    """`play` serves until Ctrl-C: the page is fetched where the command waits, then Ctrl-C is pressed there."""
    import multibody_sim.cli as cli

    seen: dict[str, str] = {}

    def ctrl_c(seconds: float) -> None:
        seen["out"] = capsys.readouterr().out
        url = re.search(r"http://127\.0\.0\.1:\d+/", seen["out"]).group(0)  # type: ignore[union-attr]
        with urllib.request.urlopen(url, timeout=10) as response:
            seen["page"] = response.read().decode()
        raise KeyboardInterrupt

    with monkeypatch.context() as patch:
        patch.setattr(cli.view.time, "sleep", ctrl_c)
        code = main(argv)
    assert "<title>ur5 - multibody-sim</title>" in seen["page"]
    return code, seen["out"] + capsys.readouterr().out


def _view(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    """`run --view` streams once a page has drawn the robot: a headless chromium opens the printed address and
    watches the run to its last frame."""
    chromium = shutil.which("chromium")
    if chromium is None:
        _unavailable("Debian's chromium is not installed (scripts/test.sh installs it with apt-get when root)")
    playwright_api = pytest.importorskip("playwright.sync_api")
    result: list[int] = []
    thread = threading.Thread(target=lambda: result.append(main(argv)), daemon=True)
    thread.start()
    printed = ""
    deadline = time.monotonic() + 120
    while "view: http" not in printed and time.monotonic() < deadline:
        time.sleep(0.1)
        printed += capsys.readouterr().out
    url = re.search(r"http://127\.0\.0\.1:\d+/", printed).group(0)  # type: ignore[union-attr]
    duration = float(argv[argv.index("--duration") + 1])
    args = ["--no-sandbox", "--disable-gpu", "--enable-unsafe-swiftshader", "--no-first-run"]
    with playwright_api.sync_playwright() as playwright:
        browser = playwright.chromium.launch(executable_path=chromium, args=args, timeout=90_000)
        try:
            page = browser.new_page()
            page.goto(url, timeout=90_000)
            page.wait_for_function(f"window.multibodySim && window.multibodySim.time === {duration}", timeout=90_000)
        finally:
            browser.close()
    thread.join(timeout=60)
    captured = capsys.readouterr()
    return (result[0] if result else -1), printed + captured.out + captured.err


def _unavailable(reason: str) -> None:
    if os.environ.get("CI") == "true":  # CI installs the browser: its absence is a failure there
        pytest.fail(reason)
    pytest.skip(reason)
