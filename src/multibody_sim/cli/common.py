"""What the commands share: exit codes, one-line errors, printing names from files safely, and the robot or scene a
command names."""

from __future__ import annotations

import argparse
import io
import math
import os
import signal
import sys
from pathlib import Path
from typing import Any

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


class UsageError(Exception):
    """Bad command-line input, reported as one line and exit code 2."""


def is_scene(args: argparse.Namespace) -> bool:
    """Whether a command's ROBOT_OR_URDF names a scene: a .toml file, a shipped scene's name or scene:NAME.

    A name that is both a shipped scene and a catalog robot (four_bar, spring_chain) takes the scene, and leaves
    a note (args.note) that the command prints on stderr once its arguments are accepted; robot:NAME takes the
    robot.
    """
    from ..catalog import ROBOT_PREFIX
    from ..scenes import SCENE_PREFIX, shipped_scenes

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


def print_note(args: argparse.Namespace) -> None:
    """The note is_scene left, on stderr: printed once bad input can no longer be the next line."""
    note = getattr(args, "note", None)
    if note:
        print_text(note, sys.stderr)
        args.note = None


def load_system(args: argparse.Namespace) -> Any:
    if is_scene(args):
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
            raise UsageError(f"{', '.join(given)}: a scene declares its robot: set this in its [robot] table")
        # --allow-root is the user's own say: a scene from elsewhere reads only its folder and the catalog's
        return ms.load_scene(args.robot, allowed_roots=args.allow_root or None)
    if args.report_savings:
        raise UsageError("--report-savings applies to scene files (.toml): a robot alone has nothing to save")
    return ms.load_robot(
        args.robot,
        floating_base=args.floating_base,
        damping=not args.no_damping,
        package_dirs=args.package_dir or None,
        allowed_roots=args.allow_root or None,
        srdf=args.srdf,
    )


def configuration_from(robot: Any, words: list[str]) -> Any:
    """--q0: one named pose (robot.pose) or nq numbers."""
    numbers = []
    for word in words:
        try:
            numbers.append(float(word))
        except ValueError:
            if len(words) == 1:
                return robot.pose(word)  # an unknown name lists the valid ones
            poses = f"one pose name ({', '.join(robot.poses)}) or " if robot.poses else ""
            raise UsageError(f"--q0: '{word}' is not a number (give {poses}{robot.nq} numbers)") from None
    return robot.check_q(numbers, "q0")


def controller_from_args(args: argparse.Namespace, robot: Any) -> Any:
    """The --controller with its --param values, or None (bad names and values are bad input)."""
    if args.controller is None:
        if args.param:
            raise UsageError(f"--param needs --controller NAME (valid: {', '.join(sorted(ms.CONTROLLERS))})")
        return None
    return ms.make_controller(args.controller, robot, args.param)


def savings_line(scene: Any) -> str:
    measured = ms.bench.measure_savings(scene)
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


def check_output_file(name: str, option: str, example: str) -> Path:
    """An output must be a regular file (or a new name) in a writable folder, before the work that produces it
    (files.check_output: directories, FIFOs, sockets and devices are refused; a symbolic link is written through)."""
    check_output(name, option, example)
    return Path(name).expanduser()


def report_error(message: str, code: int = EXIT_BAD_INPUT) -> int:
    """Print one line on stderr and return the exit code."""
    from ..text import printable

    # Names in messages may come from untrusted files: control characters and line breaks escaped visibly.
    print(f"{PROG}: error: {printable(message)}", file=sys.stderr)
    return code


def check_out(name: str) -> Path:
    """--out must be writable, and not being written by another run, before a possibly long run, not after it."""
    path = check_output_file(name, "--out", "run.npz")
    check_unlocked(path, "--out")
    return path


def kept_clause(failure: BaseException, out: Path | None) -> str:
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


def print_text(text: str = "", file: Any = None) -> None:
    """Print the program's text: its own line breaks kept, every other unprintable character escaped (names in it
    come from files: safe_name escapes them where they are inserted, this is the last defence)."""
    from ..text import terminal_text

    print(terminal_text(text), file=file or sys.stdout, flush=True)


def say(text: str) -> None:
    """Print a run's progress; a reader that left (`| head`) must not cost the run or its file."""
    try:
        print_text(text)
    except BrokenPipeError:
        discard_stdout()


def discard_stdout() -> None:
    """Point stdout at /dev/null so that the interpreter's final flush does not fail again."""
    try:
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, sys.stdout.fileno())
    except (OSError, ValueError, AttributeError, io.UnsupportedOperation):
        pass  # not a real file (tests capture stdout): nothing will be flushed to a closed pipe
