"""Watching and sharing motions: a live meshcat viewer, self-contained HTML exports and energy plots.

Imported on demand (`import multibody_sim.viz`), never by `multibody_sim` itself: the simulator does not need
meshcat, trimesh or matplotlib, which come with the `viz` extra (`pip install 'multibody-sim[viz]'`).
"""

from ..recorded import robot_from_trajectory
from ._deps import MissingDependencyError, ViewerWarning
from .export import export_html
from .frames import frame_times, resample
from .notebook import InlineView, inline_view
from .plot import plot_command, plot_png, plot_trajectory
from .scene import MissingVisualsWarning, RobotScene
from .server import ExposedServerWarning, MeshcatServer
from .video import EmptyFrameError, export_video
from .viewer import Viewer

__all__ = [
    "EmptyFrameError",
    "ExposedServerWarning",
    "InlineView",
    "MeshcatServer",
    "MissingDependencyError",
    "MissingVisualsWarning",
    "RobotScene",
    "Viewer",
    "ViewerWarning",
    "export_html",
    "export_video",
    "frame_times",
    "inline_view",
    "plot_command",
    "plot_png",
    "plot_trajectory",
    "resample",
    "robot_from_trajectory",
]
