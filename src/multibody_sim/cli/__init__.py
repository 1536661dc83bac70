"""The `multibody-sim` command line: argparse subcommands over the public API, with contract exit codes.

parser.py builds the parser; the commands live in run.py (run, bench), info.py (models, inspect, integrators) and
view.py (play, plot, export); common.py holds what they share (exit codes, output, loading the robot or scene).
"""

from __future__ import annotations

import sys
from collections.abc import Callable, Sequence

import multibody_sim as ms

from .common import (
    COMMANDS,
    EXIT_OK,
    EXIT_SIGINT,
    EXIT_SIGPIPE,
    EXIT_SIMULATION_FAILED,
    PROG,
    UsageError,
    discard_stdout,
    report_error,
)
from .parser import parse_arguments


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
        args = parse_arguments(argv)
    except UsageError as exc:
        return report_error(str(exc))
    except SystemExit as exc:  # --help and --version exit through argparse
        return exc.code if isinstance(exc.code, int) else EXIT_OK
    bad_input = (
        ms.InvalidArgumentError,
        ms.UnknownNameError,
        ms.ModelError,
        ms.TrajectoryFileError,
        ms.MissingDependencyError,
        UsageError,
    )
    try:
        return int(args.handler(args))
    except bad_input as exc:
        return report_error(str(exc))
    except ms.MultibodySimError as exc:  # not bad input and not caught by the command: a failure
        return report_error(str(exc), EXIT_SIMULATION_FAILED)
    except KeyboardInterrupt:  # Ctrl-C outside the stepping loop (loading, writing): nothing to keep
        print(f"{PROG}: interrupted", file=sys.stderr)
        return EXIT_SIGINT
    except BrokenPipeError:  # the reader of a listing left (`multibody-sim models | head`): stop quietly
        discard_stdout()
        return EXIT_SIGPIPE


def _tolerate_unencodable_output() -> None:
    """Print descriptions with non-ASCII characters (Runge–Kutta) even on a non-UTF-8 terminal."""
    reconfigure: Callable[..., None] | None = getattr(sys.stdout, "reconfigure", None)
    if reconfigure is not None:
        reconfigure(errors="replace")


__all__ = ["COMMANDS", "main"]
