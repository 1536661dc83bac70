"""The commands that simulate: `run` (one trajectory, optionally chosen by a pilot study for a tolerance, viewed
live) and `bench` (a work-precision study)."""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
from pathlib import Path
from typing import Any

import multibody_sim as ms
from multibody_sim.files import SigtermAsInterrupt, check_output

from .common import (
    EXIT_OK,
    EXIT_SIGINT,
    EXIT_SIGTERM,
    EXIT_SIMULATION_FAILED,
    PROG,
    UsageError,
    check_out,
    configuration_from,
    controller_from_args,
    kept_clause,
    load_system,
    print_note,
    print_text,
    report_error,
    savings_line,
    say,
)
from .view import await_browser, open_viewer, watch

# The API makes adaptive runs name their tolerances; the command line offers these middle-of-the-road ones.
ADAPTIVE_RTOL = 1e-6
ADAPTIVE_ATOL = 1e-8


def _nothing_holds_it_up(robot: Any) -> str:
    """The run header's line for a floating robot run without a scene: it falls, and which scene stands it up."""
    from ..scenes import shipped_scenes
    from ..text import safe_name

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


def cmd_run(args: argparse.Namespace) -> int:
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
    from ..driver import RunSettings, Sink, check_resources
    from ..text import printable, safe_name
    from ..validation import playback_speed, port_number

    playback_speed(args.view_speed, "--view-speed")
    port_number(args.view_port, "--view-port")
    if args.view_forces and not args.view:
        raise UsageError("--view-forces draws contact forces in the --view page: add --view")
    out = check_out(args.out) if args.out else None
    robot = load_system(args)
    scene = robot if isinstance(robot, ms.Scene) else None
    if args.view_forces and getattr(robot, "contact", None) is None:
        raise UsageError(
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
    q0 = declared.pop("q0", robot.default_pose()) if args.q0 is None else configuration_from(robot, args.q0)
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
    controller = controller_from_args(args, robot)
    if controller is None and args.controller is None:
        controller = declared.get("controller")
        if controller is not None:
            args.controller = scene.spec.controller.name  # type: ignore[union-attr]
    _check_run_arguments(robot, method, args.duration, args.dt if args.tolerance is None else None, options)
    if controller is not None:
        options["controller"] = controller
    print_note(args)
    if scene is not None:
        say(scene.describe())
        if args.report_savings:
            say(savings_line(scene))
    if args.tolerance is not None:  # a pilot study chooses the integrator and its step
        choice = _choose_for_tolerance(args, robot, q0, v0, controller, options.get("control_dt"))
        if isinstance(choice, int):  # interrupted during the pilot
            return choice
        method, args.dt = ms.get_integrator(choice.measurement.integrator), choice.measurement.dt
        options.update({k: v for k, v in choice.measurement.simulate_options().items() if k in ("rtol", "atol")})
        if controller is not None and "control_dt" not in options:  # the period the pilot held the controller
            options["control_dt"] = choice.study.settings["control_dt"]
            say(
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
    viewer = open_viewer(robot, args.view_host, args.view_port, args.view_speed, q0) if args.view else None
    with SigtermAsInterrupt(owner=True) as signals:
        try:
            # Printed (and flushed) with the handlers in place, just before stepping: a watcher may signal
            # as soon as it reads this line.
            say(
                f"run: {safe_name(robot.name)} ({base} base, nq {robot.nq}, nv {robot.nv}), integrator {method.name}, "
                f"dt {args.dt:g} s{tolerances}, duration {args.duration:g} s"
                + (f", controller {args.controller}" if controller is not None else "")
                + (f"\n{_nothing_holds_it_up(robot)}" if scene is None and robot.floating_base else "")
            )
            if args.chunk is not None:  # streamed to disk by the loop itself, merged into --out at the end
                if out is None:
                    raise UsageError("--chunk needs --out FILE.npz (the chunks are merged into it)")
                options.update(chunk=args.chunk)
            if out is not None:  # written by simulate however the run ends, signals held off the write
                options.update(out=out)
            if viewer is not None:  # wait for a page, then show the run while it computes, paced to --view-speed
                args._live = await_browser(viewer, args)
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
        say(trajectory.summary() + (f"\n{said}" if said else "") + (f"\nwrote {out}" if out is not None else ""))
        if viewer is not None:
            watch(viewer, trajectory, args)
        return EXIT_OK
    partial = getattr(failure, "trajectory", None)
    kept = kept_clause(failure, out)
    if partial is not None and len(partial):
        describe(partial, "", f"{failure}; {kept}")
        say(partial.summary())
    if viewer is not None:  # a failed run's samples are worth watching; an interrupted one's user wants out
        if isinstance(failure, ms.SimulationError) and partial is not None and len(partial):
            watch(viewer, partial, args)
        else:
            viewer.close()
    if isinstance(failure, ms.SimulationError):
        return report_error(f"{failure}; {kept}", EXIT_SIMULATION_FAILED)
    # The stepping loop cannot tell which signal raised the KeyboardInterrupt; our handler can.
    name = "SIGTERM" if signals.received else "SIGINT"
    where = str(failure) or "interrupted before the first step"
    print_text(f"{PROG}: {name}: {printable(where)}; {kept}", sys.stderr)
    return EXIT_SIGTERM if name == "SIGTERM" else EXIT_SIGINT


def _check_run_arguments(robot: Any, method: Any, duration: Any, dt: Any, options: dict[str, Any]) -> None:
    """What simulate() would refuse, checked before the header is printed (dt None: chosen later, by a pilot).

    The same checks (validation.py), with the same messages, as simulate()'s: bad input prints one line and
    nothing else.
    """
    from ..validation import check_options, positive_number, run_numbers

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
    from ..trajectory import plain_data

    say(json.dumps(plain_data(document), allow_nan=False))


def _choose_for_tolerance(
    args: argparse.Namespace, robot: Any, q0: Any, v0: Any, controller: Any, control_dt: float | None
) -> ms.Choice | int:
    """`run --tolerance`: the pilot study's choice (said before the run), or the exit code if interrupted. The
    pilot runs under the run's controller, at its period."""
    chosen_flags = {"--integrator": args.integrator, "--dt": args.dt, "--rtol": args.rtol, "--atol": args.atol}
    given = [flag for flag, value in {**chosen_flags, "--max-step": args.max_step}.items() if value is not None]
    if given:
        raise UsageError(
            f"--tolerance chooses the integrator and its step or tolerances: drop {', '.join(given)} "
            "(or drop --tolerance and choose them yourself)"
        )
    started: list[bool] = []

    def progress(line: str) -> None:  # one line when a pilot study starts; its measurements stay quiet
        if not started:
            started.append(True)
            horizon = min(args.duration, ms.bench.PILOT_HORIZON)
            say(f"pilot study: every integrator over the first {horizon:g} s (cached for the next run) ...")

    with SigtermAsInterrupt(owner=True) as signals:
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
            name = "SIGTERM" if signals.received else "SIGINT"
            print(f"{PROG}: {name}: interrupted during the pilot study; nothing was simulated", file=sys.stderr)
            return EXIT_SIGTERM if name == "SIGTERM" else EXIT_SIGINT
    if choice.note:
        say(f"note: {choice.note}")
    say(choice.describe())
    return choice


def cmd_bench(args: argparse.Namespace) -> int:
    from ..text import printable, safe_name

    out = _check_out_dir(args.out)
    robot = load_system(args)
    names = None
    if args.integrators is not None:
        names = [name.strip() for name in args.integrators.split(",") if name.strip()]
        if not names:
            raise UsageError("--integrators: name at least one integrator (e.g. --integrators rk4,dp54)")
        for name in names:
            ms.get_integrator(name)  # an unknown name is bad input before any work
    scene_start = isinstance(robot, ms.Scene)  # a scene starts where it declares (its objects' velocities too)
    default_q = robot.q0 if scene_start else robot.default_pose()
    default_v = robot.v0 if scene_start else [0.0] * robot.nv
    q0 = default_q if args.q0 is None else configuration_from(robot, args.q0)
    v0 = default_v if args.v0 is None else robot.check_v(args.v0, "v0")
    controller = controller_from_args(args, robot)
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
            print_note(args)
            say(
                f"bench: {safe_name(robot.name)} ({base} base, nq {robot.nq}, nv {robot.nv}), "
                f"duration {args.duration:g} s"
                + (f", controller {args.controller}" if controller is not None else "")
                + (f" every {control_dt:g} s" if control_dt is not None else "")
            )
        if args.verbose:  # one line per run; the default report is the header and the summary
            say(line)

    failure: ms.BenchInterrupted | None = None
    with SigtermAsInterrupt(owner=True) as signals:
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
        raise UsageError(f"--out {out}: cannot write the tables ({exc.strerror or exc})") from None
    png = written["png"]
    files = [str(written["csv"]), str(written["json"])] + ([str(png)] if isinstance(png, Path) else [])
    say("\n" + result.summary() + f"\nwrote {', '.join(files)}" + ("" if isinstance(png, Path) else f" ({png})"))
    if failure is None:
        return EXIT_OK
    name = "SIGTERM" if signals.received else "SIGINT"
    print_text(f"{PROG}: {name}: {printable(str(failure))}; partial results written to {out}", sys.stderr)
    return EXIT_SIGTERM if name == "SIGTERM" else EXIT_SIGINT


def _check_out_dir(name: str) -> Path:
    """bench --out: a folder (created if missing) we can write in, checked before the study."""
    path = Path(name).expanduser()
    if path.exists() and not path.is_dir():
        raise UsageError(f"--out {name}: is a file, expected a folder for work_precision.csv, .json and .png")
    folder = path.absolute()
    while not folder.exists():
        folder = folder.parent
    if not folder.is_dir() or not os.access(folder, os.W_OK | os.X_OK):
        raise UsageError(f"--out {name}: cannot create files in {folder} (not a writable folder)")
    for suffix in ("csv", "json", "png"):  # the files it will replace must be regular files (or new names)
        file = path / f"work_precision.{suffix}"
        check_output(file, "--out", f"work_precision.{suffix}")
    return path
