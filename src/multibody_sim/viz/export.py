"""One self-contained HTML file of a recorded motion: viewer, meshes, animation (and the plot), no server needed."""

from __future__ import annotations

import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..files import check_output, write_atomically
from ..recorded import robot_from_trajectory
from ..robot import Robot, check_system
from ..trajectory import Trajectory, check_trajectory
from ..validation import check_flag, check_path, check_text, frame_rate, playback_speed
from ._deps import check_viewer_dependencies, meshcat_viewer_js
from .frames import DEFAULT_FPS, resample
from .page import standalone_page
from .scene import RobotScene, pack


def export_html(
    trajectory: Trajectory,
    path: str | os.PathLike[str],
    *,
    robot: Robot | None = None,
    fps: float = DEFAULT_FPS,
    speed: float = 1.0,
    loop: bool = True,
    plot: bool = False,
    title: str | None = None,
    forces: bool = False,
) -> Path:
    """Write a trajectory as one HTML file that plays it in meshcat's viewer, offline, from disk.

    The file holds meshcat's viewer JavaScript (from the meshcat package), the robot's visual meshes and the
    motion as a meshcat animation (time slider, play/pause, speed), resampled to `fps` on the configuration
    manifold; nothing is fetched from a network. Commands are applied in a fixed order and
    `window.multibodySim.loaded` turns true when all are.

    Args:
        trajectory: the motion to show.
        path: the .html file to write (atomically).
        robot: the robot it was recorded on; None loads it from the trajectory's metadata (checking that the
            URDF's SHA-256 still matches).
        fps: keyframes per second.
        speed: initial playback speed (1 = real time).
        loop: repeat the animation.
        plot: show the energy and joint-position plot beside the view.
        title: the page title (default: the robot's name and the integrator).
        forces: draw the contact forces as arrows (a contact scene's run: see viz/forces.py).

    Returns:
        The path written.
    """
    check_trajectory(trajectory, "trajectory")
    check_path(path, "path", "an HTML file")
    if robot is not None:
        check_system(robot, "robot")
    fps, speed = frame_rate(fps), playback_speed(speed)
    check_flag(loop, "loop")
    check_flag(plot, "plot")
    check_text(title, "title")
    check_output(path, "out", "view.html")  # before the work: only a regular file is replaced
    check_viewer_dependencies()
    robot = robot_from_trajectory(trajectory) if robot is None else robot
    times, Q = resample(robot, trajectory, fps)
    extra: list[dict[str, Any]] = []
    if plot:
        from .plot import plot_command

        extra.append(plot_command(trajectory, robot=robot))
    arrows = None
    if forces:
        from .forces import force_arrows

        arrows = force_arrows(trajectory, times)
    page = recording_page(
        robot,
        times,
        Q,
        title=title or page_title(trajectory, robot),
        loop=loop,
        speed=speed,
        extra=extra,
        arrows=arrows,
    )
    target = Path(path)
    write_atomically(target, lambda f: f.write(page.encode("utf-8")))
    return target


def recording_page(
    robot: Robot,
    times: np.ndarray,
    Q: np.ndarray,
    *,
    title: str,
    play: bool = True,
    loop: bool = True,
    speed: float = 1.0,
    seek: float | None = None,
    camera: dict[str, Any] | None = None,
    extra: Sequence[dict[str, Any]] = (),
    scene: RobotScene | None = None,
    arrows: tuple[list[dict[str, Any]], list[dict[str, Any]]] | None = None,
) -> str:
    """The self-contained page of a recording (what export_html writes, notebooks embed and videos film).

    Args:
        robot: the robot shown.
        times: keyframe times [s], shape (n,); Q: the configurations there, shape (n, nq).
        title: the page title.
        play, loop, speed, seek: the animation's start (see RobotScene.animation_command).
        camera: a camera command (RobotScene.camera_command); None frames the whole motion.
        extra: commands applied after the animation (the plot beside the view).
        scene: the robot's RobotScene if already built (it loads the meshes).
        arrows: (setup commands, animation entries) of contact-force arrows (viz.forces.force_arrows), or None.
    """
    scene = RobotScene(robot) if scene is None else scene
    commands: list[dict[str, Any]] = scene.setup_commands()
    commands.append(scene.camera_command(Q, times=times) if camera is None else camera)
    commands += scene.pose_commands(Q[0])
    animation = scene.animation_command(times, Q, play=play, loop=loop, speed=speed, seek=seek)
    if arrows is not None:  # one animation for everything: the arrows keep time with the motion
        commands += arrows[0]
        animation["animations"] += arrows[1]
    commands.append(animation)
    commands += extra
    commands.append({"type": "multibody_sim_ready", "path": ""})
    return standalone_page(title, meshcat_viewer_js().read_text(encoding="utf-8"), [pack(c) for c in commands])


def page_title(trajectory: Trajectory, robot: Robot) -> str:
    """The robot's name and the integrator: "panda (rk4) - multibody-sim"."""
    integrator = trajectory.metadata.get("integrator")
    return f"{robot.name}" + (f" ({integrator})" if integrator else "") + " - multibody-sim"
