"""The commands that show a saved trajectory: `play` (meshcat, live, HTML or video), `plot` (PNG) and `export`
(CSV, Parquet); and the viewer that `run --view` shares with `play`."""

from __future__ import annotations

import argparse
import contextlib
import sys
import time
import warnings
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import multibody_sim as ms

from .common import EXIT_OK, PROG, UsageError, check_output_file, print_text, say


def cmd_play(args: argparse.Namespace) -> int:
    from ..text import safe_name
    from ..validation import frame_rate, playback_speed, port_number

    viz = viz_module()
    html = check_output_file(args.html, "--html", "view.html") if args.html else None
    if not args.video:  # a video's frame rate has its own range per format (checked with the video's options)
        frame_rate(args.fps, "--fps")
    playback_speed(args.speed, "--speed")
    port_number(args.port, "--port")
    video = _check_video(args) if args.video else None
    trajectory = ms.Trajectory.load(args.trajectory)
    if args.forces and trajectory.contacts is None:
        raise UsageError(
            f"--forces: {args.trajectory} records no contacts (forces are drawn for runs of scenes with contact)"
        )
    try:
        robot = viz.robot_from_trajectory(trajectory, allowed_roots=args.allow_root or None)
        if video is not None:
            _write_video(viz, trajectory, robot, video, args)
        if html is not None:
            started = time.perf_counter()
            try:
                with viewer_warnings(viz):
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
                raise UsageError(f"--html {html}: cannot write the page ({exc.strerror or exc})") from None
            size = html.stat().st_size / 1e6
            say(f"wrote {html} ({size:.1f} MB in {time.perf_counter() - started:.1f} s): opens from disk, offline")
        if video is not None or html is not None:
            return EXIT_OK
        viewer = open_viewer(robot, args.host, args.port, args.speed)
        try:
            viewer.animate(trajectory, fps=args.fps, speed=args.speed, forces=args.forces)
            if args.plot:
                viewer.show_plot(trajectory)
            say(
                f"play: {safe_name(robot.name)}, {len(trajectory)} samples, "
                f"t = {trajectory.t[0]:g}..{trajectory.t[-1]:g} s"
            )
            say(f"view: open {viewer.url} in a browser (time slider under Open Controls > Animations); Ctrl-C to quit")
            _wait_for_interrupt()
        finally:
            viewer.close()
    except viz.MissingDependencyError as exc:
        raise UsageError(str(exc)) from None
    return EXIT_OK


def _check_video(args: argparse.Namespace) -> Path:
    """play --video: the file name, options and browser are checked before the trajectory is read."""
    from ..viz import video

    path = check_output_file(args.video, "--video", "motion.mp4")
    video.check_video_options(path, fps=args.fps, speed=args.speed, width=args.width, height=args.height, prefix="--")
    video.check_camera(args.camera, args.camera_position, args.camera_target, prefix="--")
    video.find_browser()
    return path


def _write_video(viz: Any, trajectory: Any, robot: Any, path: Path, args: argparse.Namespace) -> None:
    started = time.perf_counter()
    try:
        with viewer_warnings(viz):
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
        raise UsageError(f"--video {path}: cannot write the video ({exc.strerror or exc})") from None
    frames = viz.video.frame_count(trajectory, fps=args.fps, speed=args.speed)
    size = path.stat().st_size / 1e6
    say(
        f"wrote {path} ({frames} frames at {args.fps:g} fps, {frames / args.fps:.2f} s; {size:.1f} MB in "
        f"{time.perf_counter() - started:.1f} s)"
    )


def cmd_plot(args: argparse.Namespace) -> int:
    viz = viz_module()
    out = check_output_file(args.out or str(Path(args.trajectory).with_suffix(".png")), "--out", "plot.png")
    joints = [name.strip() for name in args.joints.split(",") if name.strip()] if args.joints is not None else None
    if joints is not None and not joints:
        raise UsageError(
            "--joints: no joint names given (comma-separated names, e.g. --joints elbow_joint,wrist_1_joint)"
        )
    trajectory = ms.Trajectory.load(args.trajectory)
    try:
        viz.plot_trajectory(trajectory, out, joints=joints)
    except viz.MissingDependencyError as exc:
        raise UsageError(str(exc)) from None
    except ms.UnknownNameError as exc:
        raise UsageError(f"--joints: {exc}") from None
    except OSError as exc:
        raise UsageError(f"--out {out}: cannot write the plot ({exc.strerror or exc})") from None
    say(f"wrote {out}")
    return EXIT_OK


def cmd_export(args: argparse.Namespace) -> int:
    from .. import tables

    outputs = [
        (option, name, kind)
        for option, name, kind in (("--csv", args.csv, "csv"), ("--parquet", args.parquet, "parquet"))
        if name
    ]
    if not outputs:
        raise UsageError("export: nothing to write (give --csv OUT.csv and/or --parquet OUT.parquet)")
    targets = []
    for option, name, kind in outputs:
        path = check_output_file(name, option, f"table.{kind}")
        tables.check_table_format(path, kind)
        targets.append((option, path, kind))
    trajectory = ms.Trajectory.load(args.trajectory, mmap=True)  # a long run's arrays stay on disk
    for option, path, kind in targets:
        try:
            tables.write_table(trajectory, path, format=kind)
        except OSError as exc:
            raise UsageError(f"{option} {path}: cannot write the table ({exc.strerror or exc})") from None
        columns = len(tables.column_names(trajectory))
        say(f"wrote {path} ({len(trajectory)} rows x {columns} columns, {path.stat().st_size / 1e6:.1f} MB)")
    return EXIT_OK


def viz_module() -> Any:
    """multibody_sim.viz, imported only by the commands that view or plot (it is not needed to simulate)."""
    import multibody_sim.viz as viz

    return viz


def open_viewer(robot: Any, host: str, port: int | None, speed: float, q0: Any = None) -> Any:
    """Start the meshcat viewer before the work (bad options and missing packages fail first), showing q0."""
    viz = viz_module()
    try:
        with viewer_warnings(viz):
            viewer = viz.Viewer(robot, host=host, port=port, announce=False)
        if q0 is not None:  # a page opened while the run computes shows where it starts
            viewer.display(q0)
    except viz.MissingDependencyError as exc:
        raise UsageError(str(exc)) from None
    except OSError as exc:
        raise UsageError(f"the viewer cannot listen: {exc}") from None
    say(f"view: {viewer.url}")
    return viewer


@contextlib.contextmanager
def viewer_warnings(viz: Any) -> Iterator[None]:
    """The viewer's warnings (exposed server, missing meshes) as one line each on stderr."""
    from ..text import printable

    caught: list[warnings.WarningMessage] = []
    try:
        with warnings.catch_warnings(record=True) as recording:
            warnings.simplefilter("always", viz.ViewerWarning)
            caught = recording
            yield
    finally:  # recording has ended: a warning shown again is shown, not recorded into the list being read
        for warning in caught:
            if issubclass(warning.category, viz.ViewerWarning):
                print_text(f"{PROG}: warning: {printable(str(warning.message))}", sys.stderr)
            else:  # someone else's: shown as Python would have
                warnings.showwarning(warning.message, warning.category, warning.filename, warning.lineno)


def await_browser(viewer: Any, args: argparse.Namespace) -> Any:
    """`run --view`: wait until a page is open, then return the live callback that streams the run to it."""
    say(f"view: open {viewer.url} in a browser to watch the run; Ctrl-C to quit")
    while not viewer.wait_for_browser(timeout=0.5):
        pass
    return viewer.live(speed=args.view_speed, forces=args.view_forces)


def watch(viewer: Any, trajectory: Any, args: argparse.Namespace) -> None:
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
            say("view: played; the page keeps the recording (time slider under Open Controls); Ctrl-C to quit")
            _wait_for_interrupt()
        else:
            say(
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
