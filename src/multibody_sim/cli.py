"""The `multibody-sim` command line: argparse subcommands over the public API, with contract exit codes."""

from __future__ import annotations

import argparse
import contextlib
import difflib
import io
import json
import math
import os
import signal
import sys
import threading
import time
import warnings
from collections.abc import Callable, Iterator, Sequence
from pathlib import Path
from types import FrameType
from typing import Any, NoReturn

import multibody_sim as ms
from multibody_sim.files import check_output, check_unlocked

PROG = "multibody-sim"
COMMANDS = ("run", "models", "inspect", "integrators", "bench", "play", "plot", "export")

# Exit codes (CONTRACTS.md).
EXIT_OK = 0
EXIT_SIMULATION_FAILED = 1
EXIT_BAD_INPUT = 2
EXIT_SIGINT = 128 + signal.SIGINT  # 130
EXIT_SIGTERM = 128 + signal.SIGTERM  # 143
EXIT_SIGPIPE = 141  # what a shell reports for a process that wrote into a closed pipe

# The API makes adaptive runs name their tolerances; the command line offers these middle-of-the-road ones.
ADAPTIVE_RTOL = 1e-6
ADAPTIVE_ATOL = 1e-8

_FLOATING_NOTE = (
    "floating base: q = [x y z qx qy qz qw, joints...] (unit quaternion, scalar last) and "
    "v = [linear, angular (both in the base frame), joints...], so nq = nv + 1 and dq/dt != v"
)


class _UsageError(Exception):
    """Bad command-line input, reported as one line and exit code 2."""


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line and exit 2, with no usage dump.

    Raising instead of exiting lets main() return the code (tests call main() in-process).
    """

    def error(self, message: str) -> NoReturn:
        raise _UsageError(message)


class _VersionAction(argparse.Action):
    """--version: the package version, then the kernel line, printed as is (argparse's action rewraps lines)."""

    def __call__(self, parser: argparse.ArgumentParser, *args: Any) -> NoReturn:
        from . import native

        print(f"{PROG} {_version()}\nkernel: {native.kernel()}")
        parser.exit()


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line.

    Args:
        argv: the arguments after the program name; None reads sys.argv[1:].

    Returns:
        The exit code: 0 success, 1 the simulation failed, 2 bad input, 130 / 143 interrupted by
        SIGINT / SIGTERM.
    """
    _tolerate_unencodable_output()
    argv = list(sys.argv[1:] if argv is None else argv)
    try:
        args = _parse(argv)
    except _UsageError as exc:
        return _error(str(exc))
    except SystemExit as exc:  # --help and --version exit through argparse
        return exc.code if isinstance(exc.code, int) else EXIT_OK
    bad_input = (
        ms.InvalidArgumentError,
        ms.UnknownNameError,
        ms.ModelError,
        ms.TrajectoryFileError,
        ms.MissingDependencyError,
        _UsageError,
    )
    try:
        return int(args.handler(args))
    except bad_input as exc:
        return _error(str(exc))
    except ms.MultibodySimError as exc:  # not bad input and not caught by the command: a failure
        return _error(str(exc), EXIT_SIMULATION_FAILED)
    except KeyboardInterrupt:  # Ctrl-C outside the stepping loop (loading, writing): nothing to keep
        print(f"{PROG}: interrupted", file=sys.stderr)
        return EXIT_SIGINT
    except BrokenPipeError:  # the reader of a listing left (`multibody-sim models | head`): stop quietly
        _discard_stdout()
        return EXIT_SIGPIPE


# ---- arguments ---------------------------------------------------------------------------------------
class _ControllerNames:
    """The built-in controllers' names, looked up when a help text shows them: building the parser (and
    `--help`) does not import the controllers, hence Pinocchio."""

    def __str__(self) -> str:
        return ", ".join(ms.CONTROLLERS)


def _parse(argv: list[str]) -> argparse.Namespace:
    # argparse words the "no command" and "unknown command" errors differently across Python versions and
    # offers no close match: check the command name ourselves.
    if not argv:
        raise _UsageError(f"no command given (choose from: {', '.join(COMMANDS)}; see {PROG} --help)")
    if not argv[0].startswith("-") and argv[0] not in COMMANDS:
        close = difflib.get_close_matches(argv[0], COMMANDS, n=1, cutoff=0.5)
        hint = f"did you mean {close[0]}? " if close else ""
        raise _UsageError(f"unknown command '{argv[0]}' ({hint}choose from: {', '.join(COMMANDS)})")
    return _build_parser().parse_args(argv)


def _build_parser() -> _Parser:
    parser = _Parser(
        prog=PROG,
        description="Simulate URDF robots on Pinocchio with swappable integrators and an energy ledger.",
        epilog="Exit codes: 0 success, 1 the simulation failed (partial samples written to --out), "
        "2 bad input, 130 / 143 interrupted by SIGINT / SIGTERM (partial samples written to --out).",
    )
    parser.add_argument(
        "--version",
        action=_VersionAction,
        nargs=0,
        help="show the version and which stepping kernel runs (native C++, or Python and why), then exit",
    )
    commands = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)

    robot_options = _Parser(add_help=False)
    robot_options.add_argument(
        "robot",
        metavar="ROBOT_OR_URDF",
        help=f"a catalog name (`{PROG} models` lists them), a URDF file, or a scene file (.toml) declaring the "
        "robot and the physics in play",
    )
    robot_options.add_argument(
        "--report-savings",
        action="store_true",
        help="for a scene: measure (a short side benchmark) the time per RK4 step of the scene against its full "
        "robot model",
    )
    base = robot_options.add_mutually_exclusive_group()
    base.add_argument(
        "--floating-base",
        dest="floating_base",
        action="store_const",
        const=True,
        default=None,
        help="add a free-flyer root joint (default: the catalog's natural base; fixed for files)",
    )
    base.add_argument(
        "--fixed-base", dest="floating_base", action="store_const", const=False, help="weld the root link to the world"
    )
    robot_options.add_argument(
        "--no-damping", action="store_true", help="ignore the URDF's joint viscous damping (default: apply it)"
    )
    robot_options.add_argument(
        "--package-dir",
        metavar="DIR",
        action="append",  # one folder per flag: a list would swallow a ROBOT_OR_URDF written after it
        default=[],
        help="folder that package://NAME/... URIs resolve against (repeat the option for several)",
    )
    robot_options.add_argument(
        "--srdf",
        metavar="FILE",
        help="an SRDF whose <group_state>s are the robot's named poses, for --q0 NAME (catalog robots come with "
        "example-robot-data's)",
    )
    robot_options.add_argument(
        "--allow-root",
        metavar="DIR",
        action="append",
        default=[],
        help="a further folder mesh paths may resolve into, besides the URDF's folder and the package "
        "folders; for a scene file, a further folder its robot file and package_dirs may lie in, besides its own "
        "folder and the catalog's (repeat the option for several)",
    )

    run = commands.add_parser(
        "run",
        parents=[robot_options],
        help="simulate a robot and print a summary",
        description="Simulate ROBOT_OR_URDF from (q0, v0) with no applied torque (or a built-in controller's) "
        "and print the run's summary.",
    )
    run.add_argument(
        "--integrator",
        metavar="NAME",
        default=None,
        help=f"integration method (default: rk4; `{PROG} integrators` lists them)",
    )
    run.add_argument(
        "--dt",
        metavar="S",
        type=float,
        default=None,
        help="integration step [s]; an adaptive integrator's first trial step (default: 0.001)",
    )
    run.add_argument(
        "--duration", metavar="S", type=float, default=None, help="simulated time [s] (default: the scene's, or 1)"
    )
    run.add_argument(
        "--q0",
        metavar="V",
        nargs="+",
        help="initial configuration: a named pose (`inspect ROBOT` lists them, e.g. standing) or nq space-separated "
        "numbers (a floating base's quaternion is x y z w); default: the robot's default pose (its SRDF's reference "
        "pose, else the neutral configuration)",
    )
    run.add_argument(
        "--v0", metavar="V", type=float, nargs="+", help="initial velocity, nv space-separated numbers (default: zeros)"
    )
    run.add_argument(
        "--rtol",
        metavar="TOL",
        type=float,
        help=f"relative error tolerance of adaptive integrators (default: {ADAPTIVE_RTOL:g})",
    )
    run.add_argument(
        "--atol",
        metavar="TOL",
        type=float,
        help=f"absolute error tolerance of adaptive integrators (default: {ADAPTIVE_ATOL:g})",
    )
    run.add_argument(
        "--max-step", metavar="S", type=float, help="largest step of adaptive integrators [s] (default: no limit)"
    )
    run.add_argument(
        "--output-dt",
        metavar="S",
        type=float,
        help="sampling period of the output [s], a multiple of dt (default: every step)",
    )
    run.add_argument(
        "--control-dt", metavar="S", type=float, help="controller period [s], a multiple of dt (default: every step)"
    )
    _add_controller_options(run, "apply a built-in controller: %(names)s (default: the scene's, else no torque)")
    run.add_argument(
        "--out",
        metavar="FILE.npz",
        help="write the trajectory here (also the partial one if the run fails or is interrupted)",
    )
    run.add_argument(
        "--chunk",
        metavar="N",
        type=_positive_int,
        help="stream samples to FILE.npz.parts/ every N samples and merge them into --out at the end or on an "
        "early stop: memory stays bounded on long runs",
    )
    run.add_argument(
        "--json",
        action="store_true",
        help="print the run's summary as one JSON document on stdout (the header and notes go to stderr)",
    )
    run.add_argument(
        "--tolerance",
        metavar="TOL",
        type=float,
        help="choose the cheapest integrator and step whose error max |(q ⊖ q_ref, v − v_ref)|∞ stays within TOL "
        "over the first min(duration, 1 s), from a pilot study cached per robot and initial state (not with "
        "--integrator, --dt, --rtol, --atol or --max-step)",
    )
    view = run.add_argument_group("watching the run (needs the viz extra: pip install 'multibody-sim[viz]')")
    view.add_argument(
        "--view",
        action="store_true",
        help="watch the run live in a meshcat page served on 127.0.0.1: the URL is printed and the run starts "
        "when a browser opens it; after the run the page keeps the recording until Ctrl-C when run from a "
        "terminal (otherwise the viewer closes at the end and says so)",
    )
    view.add_argument(
        "--view-speed", metavar="X", type=float, default=1.0, help="playback speed, 1 = real time (default: 1)"
    )
    view.add_argument("--view-plot", action="store_true", help="show the energy plot beside the view")
    view.add_argument(
        "--view-forces",
        action="store_true",
        help="draw a contact scene's contact forces as arrows: as the run computes (20 cm for the system's weight) "
        "and in the recording left in the page after it (20 cm for the largest force)",
    )
    _add_server_options(view, prefix="--view-")
    run.set_defaults(handler=_cmd_run)

    models = commands.add_parser(
        "models",
        help="list the robot catalog",
        description="List the catalog robots: name, nq, nv, natural base, description.",
    )
    models.set_defaults(handler=_cmd_models)

    inspect = commands.add_parser(
        "inspect",
        parents=[robot_options],
        help="show a robot's joints, bodies and source",
        description="Show a robot's joints (type, limits, effort limit, damping), body masses, sizes and source.",
    )
    inspect.set_defaults(handler=_cmd_inspect)

    integrators = commands.add_parser(
        "integrators",
        help="list the integration methods",
        description="List the integration methods with their order and properties.",
    )
    integrators.set_defaults(handler=_cmd_integrators)

    bench = commands.add_parser(
        "bench",
        parents=[robot_options],
        help="measure error against cost for every integrator and recommend one",
        description="Run each integrator over a ladder of steps (fixed-step) or tolerances (adaptive) from (q0, v0) "
        "under the scene's controller or --controller (else with no applied torque); measure the error against a "
        "dop853 reference (checked by refining it; a contact scene's is timestepping at a much smaller step), the "
        "energy error and the cost; print observed against theoretical orders and the cheapest integrator for a few "
        "accuracies; write DIR/work_precision.csv, .json and .png.",
    )
    bench.add_argument(
        "--integrators",
        metavar="A,B,...",
        help="comma-separated integrators to measure (default: every one that accepts the robot)",
    )
    bench.add_argument(
        "--duration", metavar="S", type=float, default=1.0, help="simulated time of every run [s] (default: 1)"
    )
    bench.add_argument(
        "--q0",
        metavar="V",
        nargs="+",
        help="initial configuration: a named pose or nq numbers (default: the robot's default pose)",
    )
    bench.add_argument("--v0", metavar="V", type=float, nargs="+", help="initial velocity, nv numbers (default: zeros)")
    bench.add_argument(
        "--out", metavar="DIR", default=".", help="folder for work_precision.{csv,json,png} (default: the current one)"
    )
    _add_controller_options(
        bench, "measure the motion under a built-in controller: %(names)s (default: the scene's, else no torque)"
    )
    bench.add_argument("--verbose", action="store_true", help="print a line for every run as it is measured")
    bench.set_defaults(handler=_cmd_bench)
    _add_view_commands(commands)
    return parser


def _add_view_commands(commands: Any) -> None:
    play = commands.add_parser(
        "play",
        help="replay a saved trajectory in meshcat, live or as one HTML file",
        description="Replay TRAJ.npz on the robot it was recorded on (loaded again from the trajectory's "
        "metadata; refused if its URDF changed since) as a meshcat animation with a time slider: served on "
        "127.0.0.1 until Ctrl-C, or written with --html as one self-contained file that opens from disk, "
        "offline. Needs the viz extra (pip install 'multibody-sim[viz]').",
    )
    play.add_argument("trajectory", metavar="TRAJ.npz", help="a trajectory written by `run --out`")
    play.add_argument("--html", metavar="OUT.html", help="write one self-contained HTML file instead of serving")
    play.add_argument(
        "--fps", metavar="N", type=float, default=30.0, help="frames per second of the animation (default: 30)"
    )
    play.add_argument(
        "--speed", metavar="X", type=float, default=1.0, help="initial playback speed, 1 = real time (default: 1)"
    )
    play.add_argument("--plot", action="store_true", help="show the energy and joint-position plot beside the view")
    play.add_argument(
        "--allow-root",
        metavar="DIR",
        action="append",
        default=[],
        help="a folder the trajectory's robot may read meshes from besides its URDF's folder and the catalog's, "
        "when its metadata names one (a trajectory from elsewhere cannot widen them itself; repeat for several)",
    )
    play.add_argument(
        "--forces",
        action="store_true",
        help="draw a contact scene's contact forces as arrows (served, --html or --video; the largest force is "
        "20 cm long)",
    )
    _add_server_options(play, prefix="--")
    video = play.add_argument_group(
        "video (rendered headless in Chromium or Chrome from the same page; --fps and --speed apply)"
    )
    video.add_argument(
        "--video",
        metavar="OUT.mp4",
        help="write a video instead of serving: .mp4 (H.264) or .gif, frames at --fps, lasting duration / --speed",
    )
    video.add_argument("--width", metavar="PX", type=int, default=1280, help="frame width in pixels (default: 1280)")
    video.add_argument("--height", metavar="PX", type=int, default=720, help="frame height in pixels (default: 720)")
    video.add_argument(
        "--camera",
        metavar="VIEW",
        default="default",
        help="the direction the camera looks from: default, front, back, left, right, top (x forward, z up)",
    )
    video.add_argument(
        "--camera-position", metavar="M", type=float, nargs=3, help="the camera's position x y z [m] (world frame)"
    )
    video.add_argument(
        "--camera-target",
        metavar="M",
        type=float,
        nargs=3,
        help="the point the camera looks at, x y z [m] (default: the centre of the space the motion sweeps)",
    )
    play.set_defaults(handler=_cmd_play)

    plot = commands.add_parser(
        "plot",
        help="plot a saved trajectory's energies and joint positions",
        description="Plot kinetic, potential and total energy, work, dissipated and energy_error against time, "
        "and the joint positions, into a PNG. Needs matplotlib (pip install 'multibody-sim[viz]').",
    )
    plot.add_argument("trajectory", metavar="TRAJ.npz", help="a trajectory written by `run --out`")
    plot.add_argument("--out", metavar="PLOT.png", help="the PNG to write (default: TRAJ.png beside the trajectory)")
    plot.add_argument(
        "--joints",
        metavar="NAMES",
        help="plot only these joints, comma-separated (a floating base's root joint is the base panel)",
    )
    plot.set_defaults(handler=_cmd_plot)

    export = commands.add_parser(
        "export",
        help="write a saved trajectory as a table (CSV, Parquet) for pandas, spreadsheets and others",
        description="Write TRAJ.npz as a table, one row per sample, with named columns: t, q.<coordinate> (a "
        "floating base's root_joint.x .y .z .qx .qy .qz .qw), v.<dof>, tau.<dof>, kinetic_energy, potential_energy, "
        "total_energy, work, dissipated, energy_error, ledger.<element> and a scene's constraint records. Needs "
        "pandas, and pyarrow for Parquet (pip install 'multibody-sim[dataframe]').",
    )
    export.add_argument(
        "trajectory", metavar="TRAJ.npz", help="a trajectory written by `run --out` (or a chunked run's parts)"
    )
    export.add_argument("--csv", metavar="OUT.csv", help="write a CSV file (a header line of column names)")
    export.add_argument("--parquet", metavar="OUT.parquet", help="write a Parquet file (float64 columns)")
    export.set_defaults(handler=_cmd_export)


def _add_server_options(group: Any, prefix: str) -> None:
    group.add_argument(
        f"{prefix}host",
        metavar="ADDR",
        default="127.0.0.1",
        help="address the viewer listens on (default: 127.0.0.1, this machine only; another address warns)",
    )
    group.add_argument(
        f"{prefix}port", metavar="N", type=int, help="port of the viewer (default: 7000 or the next free one)"
    )


def _version() -> str:
    import importlib.metadata  # here: `--help` and every command need not pay for it

    try:
        return importlib.metadata.version("multibody-sim")
    except importlib.metadata.PackageNotFoundError:
        return "unknown"


# ---- commands ----------------------------------------------------------------------------------------
def _is_scene(args: argparse.Namespace) -> bool:
    """Whether a command's ROBOT_OR_URDF names a scene: a .toml file, a shipped scene's name or scene:NAME.

    A name that is both a shipped scene and a catalog robot (four_bar, spring_chain) takes the scene, and leaves
    a note (args.note) that the command prints on stderr once its arguments are accepted; robot:NAME takes the
    robot.
    """
    from .catalog import ROBOT_PREFIX
    from .scenes import SCENE_PREFIX, shipped_scenes

    source = args.robot
    if source.startswith((SCENE_PREFIX, ROBOT_PREFIX)):
        return bool(source.startswith(SCENE_PREFIX))
    scene = source.endswith(".toml") or source in shipped_scenes()
    if scene and source in ms.CATALOG:
        args.note = (
            f"{PROG}: note: '{source}' names both a shipped scene and a catalog robot: taking the scene "
            f"({ROBOT_PREFIX}{source} for the robot alone)"
        )
    return scene


def _nothing_holds_it_up(robot: Any) -> str:
    """The run header's line for a floating robot run without a scene: it falls, and which scene stands it up."""
    from .safety import safe_name
    from .scenes import shipped_scenes

    standing = [name for name in shipped_scenes() if name.startswith(f"{robot.name}_") and "stand" in name]
    cure = (
        f"run the shipped scene {standing[0]} to stand it on the ground"
        if standing
        else "declare [ground] and [[contact.geometry]] in a scene to stand it on the ground"
    )
    return (
        f"note: nothing holds {safe_name(robot.name)} up: without a scene there is no ground or contact, so its "
        f"floating base falls; {cure}"
    )


def _print_note(args: argparse.Namespace) -> None:
    """The note _is_scene left, on stderr: printed once bad input can no longer be the next line."""
    note = getattr(args, "note", None)
    if note:
        _print(note, sys.stderr)
        args.note = None


def _load(args: argparse.Namespace) -> Any:
    if _is_scene(args):
        given = [
            flag
            for flag, value in (
                ("--floating-base/--fixed-base", args.floating_base is not None),
                ("--no-damping", args.no_damping),
                ("--package-dir", args.package_dir),
                ("--srdf", args.srdf),
            )
            if value
        ]
        if given:
            raise _UsageError(f"{', '.join(given)}: a scene declares its robot: set this in its [robot] table")
        # --allow-root is the user's own say: a scene from elsewhere reads only its folder and the catalog's
        return ms.load_scene(args.robot, allowed_roots=args.allow_root or None)
    if args.report_savings:
        raise _UsageError("--report-savings applies to scene files (.toml): a robot alone has nothing to save")
    return ms.load_robot(
        args.robot,
        floating_base=args.floating_base,
        damping=not args.no_damping,
        package_dirs=args.package_dir or None,
        allowed_roots=args.allow_root or None,
        srdf=args.srdf,
    )


def _cmd_run(args: argparse.Namespace) -> int:
    """`run`; with --json, everything it says goes to stderr and stdout gets one JSON document (the summary)."""
    if not args.json:
        return _run(args, None)
    document: dict[str, Any] = {}
    with contextlib.redirect_stdout(sys.stderr):
        code = _run(args, document)
    if document:  # none when the arguments were refused: the error line says why
        _print_json(document)
    return code


def _run(args: argparse.Namespace, document: dict[str, Any] | None) -> int:
    """The run command; fills `document` (when given) with the run's description and summary as data."""
    from .driver import RunSettings, Sink, check_resources
    from .safety import printable, safe_name
    from .validation import playback_speed, port_number

    playback_speed(args.view_speed, "--view-speed")
    port_number(args.view_port, "--view-port")
    if args.view_forces and not args.view:
        raise _UsageError("--view-forces draws contact forces in the --view page: add --view")
    out = _check_out(args.out) if args.out else None
    robot = _load(args)
    scene = robot if isinstance(robot, ms.Scene) else None
    if args.view_forces and getattr(robot, "contact", None) is None:
        raise _UsageError(
            "--view-forces draws contact forces, and this run has no contact (run a scene with [ground], [contact] "
            "or [[object]], e.g. sliding_box)"
        )
    # A scene's own settings, which the command line's flags override.
    declared = scene.simulation_settings() if scene is not None else {}
    if args.tolerance is not None:  # the pilot study chooses the method and its step, not the scene
        for name in ("integrator", "dt", "rtol", "atol", "max_step"):
            declared.pop(name, None)
    method = ms.get_integrator(args.integrator or declared.pop("integrator", "rk4"))
    args.dt = declared.pop("dt", None) if args.dt is None else args.dt
    args.duration = declared.pop("duration", 1.0) if args.duration is None else args.duration
    # Checked before the header so that a wrong vector is the only thing printed.
    q0 = declared.pop("q0", robot.default_pose()) if args.q0 is None else _configuration(robot, args.q0)
    v0 = declared.pop("v0", [0.0] * robot.nv) if args.v0 is None else robot.check_v(args.v0, "v0")
    names = ("rtol", "atol", "max_step", "output_dt", "control_dt")
    options = {name: getattr(args, name) for name in names if getattr(args, name) is not None}
    if scene is not None:
        for name in names:
            if (
                name not in options
                and name in declared
                and (method.adaptive or name not in ("rtol", "atol", "max_step"))
            ):
                options[name] = declared[name]
    controller = _controller(args, robot)
    if controller is None and args.controller is None:
        controller = declared.get("controller")
        if controller is not None:
            args.controller = scene.spec.controller.name  # type: ignore[union-attr]
    _check_run_arguments(robot, method, args.duration, args.dt if args.tolerance is None else None, options)
    if controller is not None:
        options["controller"] = controller
    _print_note(args)
    if scene is not None:
        _say(scene.describe())
        if args.report_savings:
            _say(_savings(scene))
    if args.tolerance is not None:  # a pilot study chooses the integrator and its step
        choice = _choose_for_tolerance(args, robot, q0, v0, controller, options.get("control_dt"))
        if isinstance(choice, int):  # interrupted during the pilot
            return choice
        method, args.dt = ms.get_integrator(choice.measurement.integrator), choice.measurement.dt
        options.update({k: v for k, v in choice.measurement.simulate_options().items() if k in ("rtol", "atol")})
        if controller is not None and "control_dt" not in options:  # the period the pilot held the controller
            options["control_dt"] = choice.study.settings["control_dt"]
            _say(
                f"note: the controller is held for {options['control_dt']:g} s, as in the pilot study (called at every "
                "step, it would make the motion depend on the steps); --control-dt sets another period"
            )
    args.dt = 1e-3 if args.dt is None else args.dt  # the --dt default
    tolerances = ""
    if method.adaptive:
        options.setdefault("rtol", ADAPTIVE_RTOL)
        options.setdefault("atol", ADAPTIVE_ATOL)
        tolerances = f", rtol {options['rtol']:g}, atol {options['atol']:g}"
    checked = {k: v for k, v in options.items() if k != "controller"}
    _check_run_arguments(robot, method, args.duration, args.dt, checked)
    # What the run could not hold or write (memory, chunk buffers, the file-size limit): refused before the header.
    check_resources(robot, RunSettings.check(method, args.duration, args.dt, checked), Sink(out, args.chunk))
    base = "floating" if robot.floating_base else "fixed"
    viewer = _open_viewer(robot, args.view_host, args.view_port, args.view_speed, q0) if args.view else None
    with _SigtermAsInterrupt() as signals:
        try:
            # Printed (and flushed) with the handlers in place, just before stepping: a watcher may signal
            # as soon as it reads this line.
            _say(
                f"run: {safe_name(robot.name)} ({base} base, nq {robot.nq}, nv {robot.nv}), integrator {method.name}, "
                f"dt {args.dt:g} s{tolerances}, duration {args.duration:g} s"
                + (f", controller {args.controller}" if controller is not None else "")
                + (f"\n{_nothing_holds_it_up(robot)}" if scene is None and robot.floating_base else "")
            )
            if args.chunk is not None:  # streamed to disk by the loop itself, merged into --out at the end
                if out is None:
                    raise _UsageError("--chunk needs --out FILE.npz (the chunks are merged into it)")
                options.update(chunk=args.chunk)
            if out is not None:  # written by simulate however the run ends, signals held off the write
                options.update(out=out)
            if viewer is not None:  # wait for a page, then show the run while it computes, paced to --view-speed
                args._live = _await_browser(viewer, args)
                options.update(on_sample=args._live)
            trajectory = ms.simulate(robot, q0, v0, duration=args.duration, dt=args.dt, integrator=method, **options)
        except ms.SimulationError as exc:
            failure: BaseException | None = exc
        except KeyboardInterrupt as exc:  # SimulationInterrupted, or a signal before the first step
            failure = exc
        else:
            failure = None

    def describe(trajectory: Any, report: str, error: str | None) -> None:
        if document is not None:
            document.update(
                robot={"name": robot.name, "source": args.robot, "base": base, "nq": robot.nq, "nv": robot.nv},
                scene=scene is not None,
                integrator=method.name,
                dt=args.dt,
                duration=args.duration,
                options={k: v for k, v in options.items() if isinstance(v, (int, float))},
                controller=args.controller if controller is not None else None,
                q0=q0,
                v0=v0,
                out=str(out) if out is not None else None,
                summary=trajectory.summary_data(),
                controller_report=report or None,
                error=error,
            )

    if failure is None:
        said = getattr(controller, "summary", lambda: "")()  # what the controller saw (tracking error, minima)
        describe(trajectory, said, None)
        _say(trajectory.summary() + (f"\n{said}" if said else "") + (f"\nwrote {out}" if out is not None else ""))
        if viewer is not None:
            _watch(viewer, trajectory, args)
        return EXIT_OK
    partial = getattr(failure, "trajectory", None)
    kept = _kept(failure, out)
    if partial is not None and len(partial):
        describe(partial, "", f"{failure}; {kept}")
        _say(partial.summary())
    if viewer is not None:  # a failed run's samples are worth watching; an interrupted one's user wants out
        if isinstance(failure, ms.SimulationError) and partial is not None and len(partial):
            _watch(viewer, partial, args)
        else:
            viewer.close()
    if isinstance(failure, ms.SimulationError):
        return _error(f"{failure}; {kept}", EXIT_SIMULATION_FAILED)
    # The stepping loop cannot tell which signal raised the KeyboardInterrupt; our handler can.
    name = signals.received or "SIGINT"
    where = str(failure) or "interrupted before the first step"
    _print(f"{PROG}: {name}: {printable(where)}; {kept}", sys.stderr)
    return EXIT_SIGTERM if name == "SIGTERM" else EXIT_SIGINT


def _configuration(robot: Any, words: list[str]) -> Any:
    """--q0: one named pose (robot.pose) or nq numbers."""
    numbers = []
    for word in words:
        try:
            numbers.append(float(word))
        except ValueError:
            if len(words) == 1:
                return robot.pose(word)  # an unknown name lists the valid ones
            poses = f"one pose name ({', '.join(robot.poses)}) or " if robot.poses else ""
            raise _UsageError(f"--q0: '{word}' is not a number (give {poses}{robot.nq} numbers)") from None
    return robot.check_q(numbers, "q0")


def _check_run_arguments(robot: Any, method: Any, duration: Any, dt: Any, options: dict[str, Any]) -> None:
    """What simulate() would refuse, checked before the header is printed (dt None: chosen later, by a pilot).

    The same checks (validation.py), with the same messages, as simulate()'s: bad input prints one line and
    nothing else.
    """
    from .validation import check_options, positive_number, run_numbers

    positive_number(duration, "duration")
    if dt is None:
        return
    if method.adaptive:  # the command line's default tolerances, unless given
        options = {"rtol": ADAPTIVE_RTOL, "atol": ADAPTIVE_ATOL, **options}
    check_options(method, options)
    run_numbers(method.adaptive, duration, dt, options)
    method.check_system(robot)


def _print_json(document: dict[str, Any]) -> None:
    """One JSON document on stdout (no NaN or Infinity: JSON has none; they are null)."""
    from .trajectory import plain_data

    _say(json.dumps(plain_data(document), allow_nan=False))


def _controller(args: argparse.Namespace, robot: Any) -> Any:
    """The --controller with its --param values, or None (bad names and values are bad input)."""
    if args.controller is None:
        if args.param:
            raise _UsageError(f"--param needs --controller NAME (valid: {', '.join(sorted(ms.CONTROLLERS))})")
        return None
    return ms.make_controller(args.controller, robot, args.param)


def _choose_for_tolerance(
    args: argparse.Namespace, robot: Any, q0: Any, v0: Any, controller: Any, control_dt: float | None
) -> ms.Choice | int:
    """`run --tolerance`: the pilot study's choice (said before the run), or the exit code if interrupted. The
    pilot runs under the run's controller, at its period."""
    chosen_flags = {"--integrator": args.integrator, "--dt": args.dt, "--rtol": args.rtol, "--atol": args.atol}
    given = [flag for flag, value in {**chosen_flags, "--max-step": args.max_step}.items() if value is not None]
    if given:
        raise _UsageError(
            f"--tolerance chooses the integrator and its step or tolerances: drop {', '.join(given)} "
            "(or drop --tolerance and choose them yourself)"
        )
    started: list[bool] = []

    def progress(line: str) -> None:  # one line when a pilot study starts; its measurements stay quiet
        if not started:
            started.append(True)
            horizon = min(args.duration, ms.bench.PILOT_HORIZON)
            _say(f"pilot study: every integrator over the first {horizon:g} s (cached for the next run) ...")

    with _SigtermAsInterrupt() as signals:
        try:
            choice = ms.choose_integrator(
                robot,
                q0,
                v0,
                tolerance=args.tolerance,
                duration=args.duration,
                progress=progress,
                controller=controller,
                control_dt=control_dt,
            )
        except KeyboardInterrupt:
            name = signals.received or "SIGINT"
            print(f"{PROG}: {name}: interrupted during the pilot study; nothing was simulated", file=sys.stderr)
            return EXIT_SIGTERM if name == "SIGTERM" else EXIT_SIGINT
    if choice.note:
        _say(f"note: {choice.note}")
    _say(choice.describe())
    return choice


def _add_controller_options(parser: argparse.ArgumentParser, text: str) -> None:
    """--controller NAME and its repeated --param KEY=VALUE (run, bench)."""
    controller = parser.add_argument("--controller", metavar="NAME", help=text)
    controller.names = _ControllerNames()  # type: ignore[attr-defined]  # read by argparse's %(names)s
    parser.add_argument(
        "--param",
        metavar="KEY=VALUE",
        action="append",
        default=[],
        help="a --controller parameter; vectors are comma-separated (q_ref=0,-1,1,0,0,0); repeat for each",
    )


def _cmd_bench(args: argparse.Namespace) -> int:
    from .safety import printable, safe_name

    out = _check_out_dir(args.out)
    robot = _load(args)
    names = None
    if args.integrators is not None:
        names = [name.strip() for name in args.integrators.split(",") if name.strip()]
        if not names:
            raise _UsageError("--integrators: name at least one integrator (e.g. --integrators rk4,dp54)")
        for name in names:
            ms.get_integrator(name)  # an unknown name is bad input before any work
    scene_start = isinstance(robot, ms.Scene)  # a scene starts where it declares (its objects' velocities too)
    default_q = robot.q0 if scene_start else robot.default_pose()
    default_v = robot.v0 if scene_start else [0.0] * robot.nv
    q0 = default_q if args.q0 is None else _configuration(robot, args.q0)
    v0 = default_v if args.v0 is None else robot.check_v(args.v0, "v0")
    controller = _controller(args, robot)
    declared = robot.simulation_settings() if scene_start else {}
    if controller is None:  # the scene's own controller, at its declared period
        controller = declared.get("controller")
        if controller is not None:
            args.controller = robot.spec.controller.name
    control_dt = declared.get("control_dt", ms.bench.CONTROL_DT) if controller is not None else None
    base = "floating" if robot.floating_base else "fixed"
    started: list[bool] = []

    def progress(line: str) -> None:  # the header waits for the study's checks: bad input prints nothing else
        if not started:
            started.append(True)
            _print_note(args)
            _say(
                f"bench: {safe_name(robot.name)} ({base} base, nq {robot.nq}, nv {robot.nv}), "
                f"duration {args.duration:g} s"
                + (f", controller {args.controller}" if controller is not None else "")
                + (f" every {control_dt:g} s" if control_dt is not None else "")
            )
        if args.verbose:  # one line per run; the default report is the header and the summary
            _say(line)

    failure: ms.BenchInterrupted | None = None
    with _SigtermAsInterrupt() as signals:
        try:
            result = ms.work_precision(
                robot,
                q0,
                v0,
                duration=args.duration,
                integrators=names,
                progress=progress,
                controller=controller,
                control_dt=control_dt,
            )
        except ms.BenchInterrupted as exc:
            result, failure = exc.result, exc
    try:
        written = result.write(out)
    except OSError as exc:
        raise _UsageError(f"--out {out}: cannot write the tables ({exc.strerror or exc})") from None
    png = written["png"]
    files = [str(written["csv"]), str(written["json"])] + ([str(png)] if isinstance(png, Path) else [])
    _say("\n" + result.summary() + f"\nwrote {', '.join(files)}" + ("" if isinstance(png, Path) else f" ({png})"))
    if failure is None:
        return EXIT_OK
    name = signals.received or "SIGINT"
    _print(f"{PROG}: {name}: {printable(str(failure))}; partial results written to {out}", sys.stderr)
    return EXIT_SIGTERM if name == "SIGTERM" else EXIT_SIGINT


def _check_out_dir(name: str) -> Path:
    """bench --out: a folder (created if missing) we can write in, checked before the study."""
    path = Path(name).expanduser()
    if path.exists() and not path.is_dir():
        raise _UsageError(f"--out {name}: is a file, expected a folder for work_precision.csv, .json and .png")
    folder = path.absolute()
    while not folder.exists():
        folder = folder.parent
    if not folder.is_dir() or not os.access(folder, os.W_OK | os.X_OK):
        raise _UsageError(f"--out {name}: cannot create files in {folder} (not a writable folder)")
    for suffix in ("csv", "json", "png"):  # the files it will replace must be regular files (or new names)
        file = path / f"work_precision.{suffix}"
        check_output(file, "--out", f"work_precision.{suffix}")
    return path


def _cmd_models(args: argparse.Namespace) -> int:
    rows = ms.catalog_table()
    _print(
        _table(
            ["name", "nq", "nv", "base", "poses", "description"],
            [[r["name"], r["nq"], r["nv"], r["base"], _poses_cell(r), r["description"]] for r in rows],
        )
    )
    _print(
        "\nposes: the SRDF's named poses (run ROBOT --q0 NAME); * marks the default pose, where runs start; "
        "- none: runs start from the neutral configuration"
    )
    from .scenes import shipped_scenes
    from .scenes.spec import read_scene_file

    scenes = shipped_scenes()
    if scenes:
        _print(f"\nscenes (run one with `{PROG} run NAME`; the files are in {next(iter(scenes.values())).parent}):")
        scene_rows = [[name, read_scene_file(path).description] for name, path in scenes.items()]
        _print(_table(["name", "description"], scene_rows, indent=2))
    both = sorted(set(scenes) & set(ms.CATALOG))
    if both:
        _print(
            f"\n{', '.join(both)}: both a robot and a scene; run, inspect and bench take the scene "
            f"(robot:{both[0]} for the robot alone)"
        )
    return EXIT_OK


def _poses_cell(row: dict[str, Any]) -> str:
    """A robot's poses for `models`: the default first, starred."""
    poses = sorted(row["poses"], key=lambda name: name != row["default_pose"])
    return ",".join(f"{name}*" if name == row["default_pose"] else name for name in poses) or "-"


def _savings(scene: Any) -> str:
    measured = scene.measure_savings()
    if math.isnan(measured["full_us"]):  # objects only: no robot to compare with
        return (
            f"cost ({measured['integrator']}, CPU-time medians of 5 x 200 steps): scene {measured['scene_us']:.1f} "
            "µs/step (objects only: no robot model to compare with)"
        )
    return (
        f"savings ({'RK4' if measured['integrator'] == 'rk4' else measured['integrator']}, CPU-time medians of 5 x "
        f"200 steps): scene {measured['scene_us']:.1f} "
        f"µs/step, full robot "
        f"model {measured['full_us']:.1f} µs/step: {measured['ratio']:.2f}x the full model's cost"
    )


def _cmd_inspect(args: argparse.Namespace) -> int:
    from .safety import safe_name

    robot = _load(args)
    _print_note(args)
    if isinstance(robot, ms.Scene):
        _print(robot.describe())
        _print(_savings(robot))
        _print()
    model = robot.model
    entry = ms.CATALOG.get(args.robot)
    lines = [safe_name(robot.name) + (f": {entry.description}" if entry is not None else "")]
    source = robot.source
    derived = {"sdf": " (SDF, converted to URDF)"}.get(source.get("derivation", ""), "")
    if source.get("derivation", "").startswith("prune:"):
        derived = f" (without the subtree below {safe_name(source['derivation'].removeprefix('prune:'))})"
    lines += [f"URDF: {safe_name(source.get('urdf_path'))}{derived}", f"sha256: {source.get('urdf_sha256')}"]
    base = "floating (free-flyer root joint)" if robot.floating_base else "fixed (root link welded to the world)"
    lines += [f"base: {base}", f"nq: {robot.nq}  nv: {robot.nv}"]
    if robot.poses:
        named = ", ".join(safe_name(p) + (" (default)" if p == robot.default_pose_name else "") for p in robot.poses)
        lines.append(f"poses: {named} (from {safe_name(source.get('srdf_path'))})")
    elif not isinstance(robot, ms.Scene):
        lines.append("poses: none (runs start from the neutral configuration)")
    if isinstance(robot, ms.Scene):
        lines.append("start: the scene's initial state ([initial], else the robot's default pose; objects as declared)")
    welded = float(model.inertias[0].mass)
    lines.append(
        f"total mass: {robot.total_mass:.6g} kg"
        + (f" (moving bodies; {welded:.6g} kg welded to the world not counted)" if welded > 0 else "")
    )
    if robot.floating_base:
        lines.append(_FLOATING_NOTE)

    joint_rows = []
    for jid in range(1, model.njoints):
        joint = model.joints[jid]
        if joint.nv == 0:
            continue
        iq, iv = joint.idx_q, joint.idx_v
        kind = _joint_kind(joint.shortname())
        unit = "m" if kind == "prismatic" else "rad"
        if joint.nq == 1 and math.isfinite(robot.lower_limit[iq]):
            limits = f"[{robot.lower_limit[iq]:.6g}, {robot.upper_limit[iq]:.6g}] {unit}"
        else:
            limits = "none"
        if robot.floating_base and iv < 6:
            effort = "unactuated"
        elif joint.nv == 1 and math.isfinite(robot.effort_limit[iv]):
            effort = f"{robot.effort_limit[iv]:.6g} {'N' if kind == 'prismatic' else 'N·m'}"
        else:
            effort = "none"
        damping = ", ".join(f"{d:.6g}" for d in robot.damping[iv : iv + joint.nv])
        joint_rows.append([model.names[jid], kind, limits, effort, damping])
    lines += [
        "",
        "joints (Pinocchio order):",
        _table(["name", "type", "position limits", "effort limit", "damping"], joint_rows, indent=2),
    ]

    # Pinocchio merges links joined by fixed joints into one body per joint; list the links in each.
    links: dict[int, list[str]] = {}
    for frame in model.frames:
        if frame.type.name == "BODY":
            links.setdefault(frame.parentJoint, []).append(frame.name)
    body_rows = []
    for jid in range(model.njoints):
        mass = float(model.inertias[jid].mass)
        if jid == 0 and mass == 0.0:
            continue
        moved_by = "(welded to the world)" if jid == 0 else model.names[jid]
        body_rows.append([moved_by, f"{mass:.6g}", ", ".join(links.get(jid, []))])
    lines += [
        "",
        "bodies (links joined by fixed joints are merged):",
        _table(["moved by joint", "mass [kg]", "links"], body_rows, indent=2),
    ]
    _print("\n".join(lines))
    return EXIT_OK


def _cmd_integrators(args: argparse.Namespace) -> int:
    rows, notes = [], []
    for name, method in ms.INTEGRATORS.items():
        properties = {"adaptive": method.adaptive, "implicit": method.implicit, "symplectic": method.symplectic}
        flags = [flag for flag, on in {**properties, "A-stable": method.a_stable}.items() if on]
        # Newton's iterations vary, so an implicit method's count is typical, not exact.
        evaluations = f"~{method.evaluations_per_step}" if method.implicit else method.evaluations_per_step
        rows.append([name, method.order, evaluations, ", ".join(flags) or "-", method.description])
        if method.notes:
            notes.append(f"  {name}: {method.notes}")
    _print(_table(["name", "order", "evaluations/step", "flags", "description"], rows))
    if notes:
        _print("\nnotes:\n" + "\n".join(notes))
    return EXIT_OK


def _cmd_play(args: argparse.Namespace) -> int:
    from .safety import safe_name
    from .validation import frame_rate, playback_speed, port_number

    viz = _viz()
    html = _check_output(args.html, "--html", "view.html") if args.html else None
    if not args.video:  # a video's frame rate has its own range per format (checked with the video's options)
        frame_rate(args.fps, "--fps")
    playback_speed(args.speed, "--speed")
    port_number(args.port, "--port")
    video = _check_video(args) if args.video else None
    trajectory = ms.Trajectory.load(args.trajectory)
    if args.forces and trajectory.contacts is None:
        raise _UsageError(
            f"--forces: {args.trajectory} records no contacts (forces are drawn for runs of scenes with contact)"
        )
    try:
        robot = viz.robot_from_trajectory(trajectory, allowed_roots=args.allow_root or None)
        if video is not None:
            _write_video(viz, trajectory, robot, video, args)
        if html is not None:
            started = time.perf_counter()
            try:
                with _viewer_warnings(viz):
                    viz.export_html(
                        trajectory,
                        html,
                        robot=robot,
                        fps=args.fps,
                        speed=args.speed,
                        plot=args.plot,
                        forces=args.forces,
                    )
            except OSError as exc:
                raise _UsageError(f"--html {html}: cannot write the page ({exc.strerror or exc})") from None
            size = html.stat().st_size / 1e6
            _say(f"wrote {html} ({size:.1f} MB in {time.perf_counter() - started:.1f} s): opens from disk, offline")
        if video is not None or html is not None:
            return EXIT_OK
        viewer = _open_viewer(robot, args.host, args.port, args.speed)
        try:
            viewer.animate(trajectory, fps=args.fps, speed=args.speed, forces=args.forces)
            if args.plot:
                viewer.show_plot(trajectory)
            _say(
                f"play: {safe_name(robot.name)}, {len(trajectory)} samples, "
                f"t = {trajectory.t[0]:g}..{trajectory.t[-1]:g} s"
            )
            _say(f"view: open {viewer.url} in a browser (time slider under Open Controls > Animations); Ctrl-C to quit")
            _wait_for_interrupt()
        finally:
            viewer.close()
    except viz.MissingDependencyError as exc:
        raise _UsageError(str(exc)) from None
    return EXIT_OK


def _check_video(args: argparse.Namespace) -> Path:
    """play --video: the file name, options and browser are checked before the trajectory is read."""
    from .viz import video

    path = _check_output(args.video, "--video", "motion.mp4")
    video.check_video_options(path, fps=args.fps, speed=args.speed, width=args.width, height=args.height, prefix="--")
    video.check_camera(args.camera, args.camera_position, args.camera_target, prefix="--")
    video.find_browser()
    return path


def _write_video(viz: Any, trajectory: Any, robot: Any, path: Path, args: argparse.Namespace) -> None:
    started = time.perf_counter()
    try:
        with _viewer_warnings(viz):
            viz.export_video(
                trajectory,
                path,
                robot=robot,
                fps=args.fps,
                speed=args.speed,
                width=args.width,
                height=args.height,
                camera=args.camera,
                camera_position=args.camera_position,
                camera_target=args.camera_target,
                forces=args.forces,
            )
    except OSError as exc:
        raise _UsageError(f"--video {path}: cannot write the video ({exc.strerror or exc})") from None
    frames = viz.video.frame_count(trajectory, fps=args.fps, speed=args.speed)
    size = path.stat().st_size / 1e6
    _say(
        f"wrote {path} ({frames} frames at {args.fps:g} fps, {frames / args.fps:.2f} s; {size:.1f} MB in "
        f"{time.perf_counter() - started:.1f} s)"
    )


def _cmd_plot(args: argparse.Namespace) -> int:
    viz = _viz()
    out = _check_output(args.out or str(Path(args.trajectory).with_suffix(".png")), "--out", "plot.png")
    joints = [name.strip() for name in args.joints.split(",") if name.strip()] if args.joints is not None else None
    if joints is not None and not joints:
        raise _UsageError(
            "--joints: no joint names given (comma-separated names, e.g. --joints elbow_joint,wrist_1_joint)"
        )
    trajectory = ms.Trajectory.load(args.trajectory)
    try:
        viz.plot_trajectory(trajectory, out, joints=joints)
    except viz.MissingDependencyError as exc:
        raise _UsageError(str(exc)) from None
    except ms.UnknownNameError as exc:
        raise _UsageError(f"--joints: {exc}") from None
    except OSError as exc:
        raise _UsageError(f"--out {out}: cannot write the plot ({exc.strerror or exc})") from None
    _say(f"wrote {out}")
    return EXIT_OK


def _cmd_export(args: argparse.Namespace) -> int:
    from . import tables

    outputs = [
        (option, name, kind)
        for option, name, kind in (("--csv", args.csv, "csv"), ("--parquet", args.parquet, "parquet"))
        if name
    ]
    if not outputs:
        raise _UsageError("export: nothing to write (give --csv OUT.csv and/or --parquet OUT.parquet)")
    targets = []
    for option, name, kind in outputs:
        path = _check_output(name, option, f"table.{kind}")
        tables.check_table_format(path, kind)
        targets.append((option, path, kind))
    trajectory = ms.Trajectory.load(args.trajectory, mmap=True)  # a long run's arrays stay on disk
    for option, path, kind in targets:
        try:
            tables.write_table(trajectory, path, format=kind)
        except OSError as exc:
            raise _UsageError(f"{option} {path}: cannot write the table ({exc.strerror or exc})") from None
        columns = len(tables.column_names(trajectory))
        _say(f"wrote {path} ({len(trajectory)} rows x {columns} columns, {path.stat().st_size / 1e6:.1f} MB)")
    return EXIT_OK


# ---- viewing -----------------------------------------------------------------------------------------
def _viz() -> Any:
    """multibody_sim.viz, imported only by the commands that view or plot (it is not needed to simulate)."""
    import multibody_sim.viz as viz

    return viz


def _open_viewer(robot: Any, host: str, port: int | None, speed: float, q0: Any = None) -> Any:
    """Start the meshcat viewer before the work (bad options and missing packages fail first), showing q0."""
    viz = _viz()
    try:
        with _viewer_warnings(viz):
            viewer = viz.Viewer(robot, host=host, port=port, announce=False)
        if q0 is not None:  # a page opened while the run computes shows where it starts
            viewer.display(q0)
    except viz.MissingDependencyError as exc:
        raise _UsageError(str(exc)) from None
    except OSError as exc:
        raise _UsageError(f"the viewer cannot listen: {exc}") from None
    _say(f"view: {viewer.url}")
    return viewer


@contextlib.contextmanager
def _viewer_warnings(viz: Any) -> Iterator[None]:
    """The viewer's warnings (exposed server, missing meshes) as one line each on stderr."""
    from .safety import printable

    caught: list[warnings.WarningMessage] = []
    try:
        with warnings.catch_warnings(record=True) as recording:
            warnings.simplefilter("always", viz.ViewerWarning)
            caught = recording
            yield
    finally:  # recording has ended: a warning shown again is shown, not recorded into the list being read
        for warning in caught:
            if issubclass(warning.category, viz.ViewerWarning):
                _print(f"{PROG}: warning: {printable(str(warning.message))}", sys.stderr)
            else:  # someone else's: shown as Python would have
                warnings.showwarning(warning.message, warning.category, warning.filename, warning.lineno)


def _await_browser(viewer: Any, args: argparse.Namespace) -> Any:
    """`run --view`: wait until a page is open, then return the live callback that streams the run to it."""
    _say(f"view: open {viewer.url} in a browser to watch the run; Ctrl-C to quit")
    while not viewer.wait_for_browser(timeout=0.5):
        pass
    return viewer.live(speed=args.view_speed, forces=args.view_forces)


def _watch(viewer: Any, trajectory: Any, args: argparse.Namespace) -> None:
    """`run --view`, after the run (streamed live as it computed): leave its animation in the page."""
    try:
        if args.view_plot:
            viewer.show_plot(trajectory)
        live = getattr(args, "_live", None)
        if live is not None:
            live.finish(trajectory)
        duration = float(trajectory.t[-1] - trajectory.t[0])
        viewer.animate(
            trajectory, play=False, seek=duration, speed=args.view_speed, frame=False, forces=args.view_forces
        )
        if _interactive():  # someone at a terminal may still want the page; a script wants the exit
            _say("view: played; the page keeps the recording (time slider under Open Controls); Ctrl-C to quit")
            _wait_for_interrupt()
        else:
            _say(
                "view: played; the viewer closes now, as stdin is not a terminal (run from a terminal to keep the "
                "page open until Ctrl-C)"
            )
    except KeyboardInterrupt:
        pass  # the run is complete and saved: closing the viewer is the normal way out
    finally:
        viewer.close()


def _interactive() -> bool:
    try:
        return bool(sys.stdin is not None and sys.stdin.isatty())
    except (AttributeError, OSError, ValueError):  # closed or replaced stdin
        return False


def _wait_for_interrupt() -> None:
    """Serve until Ctrl-C (returns normally then: it is how one closes a viewer)."""
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        pass


def _check_output(name: str, option: str, example: str) -> Path:
    """An output must be a regular file (or a new name) in a writable folder, before the work that produces it
    (files.check_output: directories, FIFOs, sockets and devices are refused; a symbolic link is written through)."""
    check_output(name, option, example)
    return Path(name).expanduser()


# ---- helpers -----------------------------------------------------------------------------------------
def _error(message: str, code: int = EXIT_BAD_INPUT) -> int:
    """Print one line on stderr and return the exit code."""
    from .safety import printable

    # Names in messages may come from untrusted files: control characters and line breaks escaped visibly.
    print(f"{PROG}: error: {printable(message)}", file=sys.stderr)
    return code


def _positive_int(text: str) -> int:
    from .validation import positive_count

    try:
        return positive_count(int(text), "N")
    except ValueError:  # not a whole number, or out of range (InvalidArgumentError is a ValueError)
        raise argparse.ArgumentTypeError(f"expected a whole number from 1 to 2**53, got '{text}'") from None


def _check_out(name: str) -> Path:
    """--out must be writable, and not being written by another run, before a possibly long run, not after it."""
    path = _check_output(name, "--out", "run.npz")
    check_unlocked(path, "--out")
    return path


def _kept(failure: BaseException, out: Path | None) -> str:
    """The clause that says what a failed or interrupted run kept, and where (simulate wrote it: `.saved_to`)."""
    trajectory = getattr(failure, "trajectory", None)
    if trajectory is None or not len(trajectory):
        return "no samples to keep"
    span = f"partial trajectory ({len(trajectory)} samples, t = {trajectory.t[0]:g}..{trajectory.t[-1]:g} s)"
    if out is None:
        return f"{span} not saved (pass --out FILE.npz to keep it)"
    saved_to = getattr(failure, "saved_to", None)
    if saved_to is None:
        return f"{span} not written to {out}: lost when this command exits"
    if saved_to.is_dir():  # a chunked run whose parts could not be merged
        return f"{span} kept in {saved_to} (`multibody-sim plot`, `export` and Trajectory.load read the folder)"
    return f"{span} written to {out}"


class _SigtermAsInterrupt:
    """While active, SIGTERM raises KeyboardInterrupt, so a `kill` takes Ctrl-C's path and keeps the samples.

    Attributes:
        received: "SIGTERM" once the handler ran, else None.
    """

    def __init__(self) -> None:
        self.received: str | None = None
        self._previous: Any = None
        # Python only lets the main thread install handlers; elsewhere SIGTERM keeps its default.
        self._active = threading.current_thread() is threading.main_thread()

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        self.received = "SIGTERM"
        raise KeyboardInterrupt

    def __enter__(self) -> _SigtermAsInterrupt:
        if self._active:
            self._previous = signal.signal(signal.SIGTERM, self._handle)
        return self

    def __exit__(self, *exc: object) -> None:
        if self._active:  # None: the previous handler was not installed from Python; restore the default
            signal.signal(signal.SIGTERM, signal.SIG_DFL if self._previous is None else self._previous)


def _joint_kind(shortname: str) -> str:
    """The URDF word for a Pinocchio joint model (JointModelRZ -> revolute, JointModelRUBX -> continuous)."""
    short = shortname.removeprefix("JointModel")
    if short.startswith("RUB") or short.startswith("RevoluteUnbounded"):
        return "continuous"
    if short in ("RX", "RY", "RZ") or short.startswith("Revolute"):
        return "revolute"
    if short in ("PX", "PY", "PZ") or short.startswith("Prismatic"):
        return "prismatic"
    return {"FreeFlyer": "floating", "Planar": "planar", "Spherical": "spherical"}.get(short, short)


def _table(headers: list[str], rows: list[list[Any]], indent: int = 0) -> str:
    """Left-aligned columns separated by two spaces."""
    from .safety import safe_name

    cells = [[safe_name(c) for c in row] for row in [headers, *rows]]  # names from files: one line each
    widths = [max(len(row[i]) for row in cells) for i in range(len(headers))]
    pad = " " * indent
    return "\n".join(pad + "  ".join(c.ljust(w) for c, w in zip(row, widths, strict=True)).rstrip() for row in cells)


def _print(text: str = "", file: Any = None) -> None:
    """Print the program's text: its own line breaks kept, every other unprintable character escaped (names in it
    come from files: safe_name escapes them where they are inserted, this is the last defence)."""
    from .safety import terminal_text

    print(terminal_text(text), file=file or sys.stdout, flush=True)


def _say(text: str) -> None:
    """Print a run's progress; a reader that left (`| head`) must not cost the run or its file."""
    try:
        _print(text)
    except BrokenPipeError:
        _discard_stdout()


def _discard_stdout() -> None:
    """Point stdout at /dev/null so that the interpreter's final flush does not fail again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError, io.UnsupportedOperation):
        pass  # not a real file (tests capture stdout): nothing will be flushed to a closed pipe


def _tolerate_unencodable_output() -> None:
    """Print descriptions with non-ASCII characters (Runge–Kutta) even on a non-UTF-8 terminal."""
    reconfigure: Callable[..., None] | None = getattr(sys.stdout, "reconfigure", None)
    if reconfigure is not None:
        reconfigure(errors="replace")


if __name__ == "__main__":
    sys.exit(main())
