"""The command line's arguments: one argparse subparser per command, errors as one line (exit 2), `--version`."""

from __future__ import annotations

import argparse
import difflib
from typing import Any, NoReturn

import multibody_sim as ms

from .common import COMMANDS, PROG, UsageError
from .info import cmd_inspect, cmd_integrators, cmd_models
from .run import ADAPTIVE_ATOL, ADAPTIVE_RTOL, cmd_bench, cmd_run
from .view import cmd_export, cmd_play, cmd_plot


class _Parser(argparse.ArgumentParser):
    """An ArgumentParser whose errors are one line and exit 2, with no usage dump.

    Raising instead of exiting lets main() return the code (tests call main() in-process).
    """

    def error(self, message: str) -> NoReturn:
        raise UsageError(message)


class _VersionAction(argparse.Action):
    """--version: the package version, then the kernel line, printed as is (argparse's action rewraps lines)."""

    def __call__(self, parser: argparse.ArgumentParser, *args: Any) -> NoReturn:
        from .. import native

        print(f"{PROG} {_version()}\nkernel: {native.kernel()}")
        parser.exit()


class _ControllerNames:
    """The built-in controllers' names, looked up when a help text shows them: building the parser (and
    `--help`) does not import the controllers, hence Pinocchio."""

    def __str__(self) -> str:
        return ", ".join(ms.CONTROLLERS)


def parse_arguments(argv: list[str]) -> argparse.Namespace:
    # argparse words the "no command" and "unknown command" errors differently across Python versions and
    # offers no close match: check the command name ourselves.
    if not argv:
        raise UsageError(f"no command given (choose from: {', '.join(COMMANDS)}; see {PROG} --help)")
    if not argv[0].startswith("-") and argv[0] not in COMMANDS:
        close = difflib.get_close_matches(argv[0], COMMANDS, n=1, cutoff=0.5)
        hint = f"did you mean {close[0]}? " if close else ""
        raise UsageError(f"unknown command '{argv[0]}' ({hint}choose from: {', '.join(COMMANDS)})")
    return build_parser().parse_args(argv)


def build_parser() -> _Parser:
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
    add_controller_options(run, "apply a built-in controller: %(names)s (default: the scene's, else no torque)")
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
    run.set_defaults(handler=cmd_run)

    models = commands.add_parser(
        "models",
        help="list the robot catalog",
        description="List the catalog robots: name, nq, nv, natural base, description.",
    )
    models.set_defaults(handler=cmd_models)

    inspect = commands.add_parser(
        "inspect",
        parents=[robot_options],
        help="show a robot's joints, bodies and source",
        description="Show a robot's joints (type, limits, effort limit, damping), body masses, sizes and source.",
    )
    inspect.set_defaults(handler=cmd_inspect)

    integrators = commands.add_parser(
        "integrators",
        help="list the integration methods",
        description="List the integration methods with their order and properties.",
    )
    integrators.set_defaults(handler=cmd_integrators)

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
    add_controller_options(
        bench, "measure the motion under a built-in controller: %(names)s (default: the scene's, else no torque)"
    )
    bench.add_argument("--verbose", action="store_true", help="print a line for every run as it is measured")
    bench.set_defaults(handler=cmd_bench)
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
    play.set_defaults(handler=cmd_play)

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
    plot.set_defaults(handler=cmd_plot)

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
    export.set_defaults(handler=cmd_export)


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


def add_controller_options(parser: argparse.ArgumentParser, text: str) -> None:
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


def _positive_int(text: str) -> int:
    from ..validation import positive_count

    try:
        return positive_count(int(text), "N")
    except ValueError:  # not a whole number, or out of range (InvalidArgumentError is a ValueError)
        raise argparse.ArgumentTypeError(f"expected a whole number from 1 to 2**53, got '{text}'") from None
