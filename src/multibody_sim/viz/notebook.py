"""Jupyter cell outputs: a recorded motion inline (the HTML export's page in an iframe) and the live viewer's page."""

from __future__ import annotations

import html
import math
from typing import Any

from ..exceptions import InvalidArgumentError, MissingDependencyError
from ..recorded import robot_from_trajectory
from ..robot import Robot, check_system
from ..trajectory import Trajectory, check_trajectory
from ..validation import check_flag, frame_rate, playback_speed
from ._deps import check_viewer_dependencies
from .export import page_title, recording_page
from .frames import DEFAULT_FPS, resample

DEFAULT_HEIGHT = 480  # [px]


class InlineView:
    """HTML that Jupyter shows as a cell output (`_repr_html_`): an iframe of a viewer page.

    Attributes:
        html: the iframe's markup.
    """

    def __init__(self, markup: str, description: str):
        self.html = markup
        self._description = description

    def _repr_html_(self) -> str:
        return self.html

    def __repr__(self) -> str:
        return f"<InlineView {self._description}>"


def inline_view(
    trajectory: Trajectory,
    *,
    robot: Robot | None = None,
    fps: float = DEFAULT_FPS,
    speed: float = 1.0,
    height: int = DEFAULT_HEIGHT,
    plot: bool = False,
) -> InlineView:
    """A recorded motion as a notebook cell output, offline: the HTML export's page inside an iframe's srcdoc.

    The page holds the viewer's JavaScript, the meshes and the animation, so the output needs no server and no
    network, and stays in the saved notebook (a notebook reopened later shows it once trusted).

    Args:
        trajectory: the motion to show.
        robot: the robot it was recorded on; None loads it from the trajectory's metadata.
        fps: keyframes per second (the output grows with fps x duration).
        speed: initial playback speed.
        height: the output's height [px]; it spans the cell's width.
        plot: show the energy and joint-position plot beside the view.
    """
    check_trajectory(trajectory, "trajectory")
    if robot is not None:
        check_system(robot, "robot")
    fps, speed = frame_rate(fps), playback_speed(speed)
    check_flag(plot, "plot")
    check_viewer_dependencies()
    height = _height(height)
    robot = robot_from_trajectory(trajectory) if robot is None else robot
    times, Q = resample(robot, trajectory, fps)
    extra = []
    if plot:
        from .plot import plot_command

        extra.append(plot_command(trajectory, robot=robot))
    page = recording_page(robot, times, Q, title=page_title(trajectory, robot), speed=speed, extra=extra)
    markup = (
        f'<iframe srcdoc="{html.escape(page, quote=True)}" title="{html.escape(page_title(trajectory, robot))}" '
        f'style="width: 100%; height: {height}px; border: 0" allowfullscreen></iframe>'
    )
    return InlineView(markup, f"{robot.name}, t = {times[0]:g}..{times[-1]:g} s, {len(page) / 1e6:.1f} MB")


def url_view(url: str, *, height: int = DEFAULT_HEIGHT) -> InlineView:
    """A live viewer's page (served at `url`) as a notebook cell output: an iframe pointing at it."""
    height = _height(height)
    markup = (
        f'<iframe src="{html.escape(url, quote=True)}" title="multibody-sim viewer" '
        f'style="width: 100%; height: {height}px; border: 0" allowfullscreen></iframe>'
    )
    return InlineView(markup, url)


def display(view: InlineView) -> None:
    """Show a view as the output of the running Jupyter cell.

    Raises:
        MissingDependencyError: not inside IPython (a notebook or console).
    """
    try:
        from IPython import get_ipython
        from IPython.display import display as show
    except ImportError:
        get_ipython = None
    if get_ipython is None or get_ipython() is None:
        raise MissingDependencyError(
            "show() displays inline in a Jupyter notebook, and none is running; elsewhere write a page with "
            "multibody_sim.viz.export_html(trajectory, 'motion.html') or run `multibody-sim play`"
        )
    show(view)


def _height(height: Any) -> int:
    if isinstance(height, bool) or not isinstance(height, (int, float)) or not math.isfinite(height) or height < 100:
        raise InvalidArgumentError(f"height must be a number of pixels of at least 100, got {height!r}")
    return int(height)
