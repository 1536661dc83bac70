"""The live viewer: a robot in a local meshcat page, moved by configurations, streamed trajectories or animations."""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np
import pinocchio as pin

from ..robot import Robot, check_system
from ..trajectory import Trajectory
from ..validation import check_flag, frame_rate, playback_speed
from ._deps import check_viewer_dependencies
from .forces import FORCES, ArrowTracks, LiveArrows, arrow_tracks
from .frames import DEFAULT_FPS, resample
from .scene import RobotScene, frame_marker
from .server import DEFAULT_HOST, MeshcatServer


class Viewer:
    """Show a robot with its URDF's visual meshes in a meshcat page served from this machine.

    >>> viewer = Viewer(robot)                 # prints the page's URL (http://127.0.0.1:7000/)
    >>> viewer.display(robot.neutral())        # one configuration
    >>> viewer.play(trajectory, speed=0.5)     # stream a trajectory in (half) real time
    >>> viewer.animate(trajectory)             # or hand it to the page: time slider, play/pause

    Args:
        robot: the robot to show.
        host: address the server binds; 127.0.0.1 (the default) keeps it on this machine. Another address
            warns: other machines could open the page.
        port: TCP port; None takes 7000 or the next free one; 0 lets the system choose.
        announce: print the page's URL.

    Attributes:
        url: the page to open in a browser.
        server: the MeshcatServer.
        scene: the RobotScene (meshes, kinematics, commands).
    """

    def __init__(self, robot: Robot, *, host: str = DEFAULT_HOST, port: int | None = None, announce: bool = True):
        check_system(robot, "robot")
        check_viewer_dependencies()
        self.robot = robot
        self.scene = RobotScene(robot)
        self.server = MeshcatServer(host, port, title=f"{robot.name} - multibody-sim")
        self.url = self.server.url
        self._frame = 0
        self._animated = False
        self._arrows = False  # contact-force arrows are in the page
        for command in self.scene.setup_commands():
            self.server.send(command)
        q0 = robot.neutral()
        self.server.send(self.scene.camera_command(q0[None, :]))
        self._show(q0, None)
        self.server.send({"type": "multibody_sim_ready", "path": ""})
        if announce:
            print(f"meshcat viewer: {self.url}", flush=True)

    def __repr__(self) -> str:
        return f"<Viewer {self.robot.name} at {self.url}>"

    def _repr_html_(self) -> str:
        """In Jupyter, a viewer as a cell's value shows its page (an iframe on its URL)."""
        from .notebook import url_view

        return url_view(self.url).html

    def show(self, *, height: int = 480) -> None:
        """Show this viewer's page as the output of the running Jupyter cell: an iframe on its URL.

        The page is served by this process on 127.0.0.1: the browser showing the notebook must run on the same
        machine (for a notebook on a remote host, show recordings with Trajectory.show(), which needs no server).

        Args:
            height: the output's height [px]; it spans the cell's width.
        """
        from .notebook import display, url_view

        display(url_view(self.url, height=height))

    # ---- showing ----------------------------------------------------------------------------------------
    def display(self, q: Any) -> None:
        """Show the robot at configuration q (shape (nq,))."""
        self._stop_animation()
        self._clear_arrows()
        self._show(self.robot.check_q(q, "q"), None)

    def play(
        self,
        trajectory: Trajectory,
        *,
        speed: float = 1.0,
        fps: float = DEFAULT_FPS,
        frame: bool = True,
        forces: bool = False,
    ) -> int:
        """Stream a trajectory to the page at `speed` times real time; blocks until the end.

        Frames are resampled to `fps` on the configuration manifold; a frame that is already late when the
        next one is due is skipped, so the playback keeps to the clock on a slow machine.

        Args:
            trajectory: a trajectory of this robot.
            speed: playback speed (1 = real time, 0.5 = half speed).
            fps: frames per second sent to the page.
            frame: first aim the camera at the space the motion sweeps.
            forces: draw a contact scene's contact forces as arrows (as the HTML export does: viz/forces.py).

        Returns:
            The number of frames shown.

        Raises:
            InvalidArgumentError: forces=True for a trajectory that records no contacts.
        """
        speed, fps = playback_speed(speed), frame_rate(fps)
        check_flag(forces, "forces")
        times, Q = resample(self.robot, trajectory, fps)
        arrows = self._arrow_tracks(trajectory, times) if forces else None
        if arrows is None:
            self._clear_arrows()
        self._stop_animation()
        if frame:
            self.server.send(self.scene.camera_command(Q))
        start = time.perf_counter()
        shown = 0
        for k, (t, q) in enumerate(zip(times, Q, strict=True)):
            due = start + (t - times[0]) / speed
            now = time.perf_counter()
            if k + 1 < len(times) and now >= start + (times[k + 1] - times[0]) / speed:
                continue  # already late for the next frame: skip this one
            if due > now:
                time.sleep(due - now)
            if arrows is not None:
                for command in arrows.pose_commands(k):
                    self.server.send(command)
            self._show(q, float(t))
            shown += 1
        return shown

    def live(self, *, speed: float = 1.0, fps: float = DEFAULT_FPS, forces: bool = False) -> LiveView:
        """A callback for ``simulate(..., on_sample=viewer.live())`` that shows the run while it is computed.

        It keeps the run to `speed` times real time (it waits when the simulation is ahead of the clock; a
        simulation slower than that is shown as fast as it computes) and sends at most `fps` frames per second.
        Call its ``finish(trajectory)`` after the run to show the last sample. With `forces`, a contact scene's
        contact forces are drawn as arrows as it runs (viz/forces.py LiveArrows: ARROW_LENGTH for the system's
        weight; the run hands each sample's contacts to the callback).
        """
        check_flag(forces, "forces")
        self._stop_animation()
        self._clear_arrows()
        arrows = None
        if forces:
            weight = pin.computeTotalMass(self.robot.model) * float(np.linalg.norm(self.robot.model.gravity.linear))
            arrows = LiveArrows(self.server.send, weight)
            self._arrows = True
        return LiveView(self, playback_speed(speed), 1.0 / frame_rate(fps), arrows)

    def animate(
        self,
        trajectory: Trajectory,
        *,
        fps: float = DEFAULT_FPS,
        speed: float = 1.0,
        play: bool = True,
        loop: bool = True,
        seek: float | None = None,
        frame: bool = True,
        forces: bool = False,
    ) -> None:
        """Hand a trajectory to the page as a meshcat animation, with its time slider and play/pause controls.

        Args:
            trajectory: a trajectory of this robot.
            fps: keyframes per second (resampled on the configuration manifold).
            speed: initial playback speed.
            play: start playing at once.
            loop: repeat the animation.
            seek: with play=False, show this animation time [s].
            frame: first aim the camera at the space the motion sweeps.
            forces: draw a contact scene's contact forces as arrows, animated with the motion (as the HTML
                export does: viz/forces.py).

        Raises:
            InvalidArgumentError: forces=True for a trajectory that records no contacts.
        """
        speed, fps = playback_speed(speed), frame_rate(fps)
        check_flag(forces, "forces")
        times, Q = resample(self.robot, trajectory, fps)
        arrows = self._arrow_tracks(trajectory, times) if forces else None
        if arrows is None:
            self._clear_arrows()
        if frame:
            self.server.send(self.scene.camera_command(Q))
        animation = self.scene.animation_command(times, Q, play=play, loop=loop, speed=speed, seek=seek)
        if arrows is not None:  # one animation for everything: the arrows keep time with the motion
            animation["animations"] += arrows.animations(times)
        self.server.send(animation)
        self._animated = True

    def show_plot(self, plot: Trajectory | bytes) -> None:
        """Show a picture beside the view: PNG bytes, or a trajectory's energies and joints, with a cursor at
        the time the robot shows."""
        if isinstance(plot, Trajectory):
            from .plot import plot_command

            self.server.send(plot_command(plot, robot=self.robot))
        else:
            self.server.send({"type": "multibody_sim_plot", "path": "", "png": bytes(plot)})

    # ---- server -------------------------------------------------------------------------------------------
    def wait_for_browser(self, timeout: float | None = None) -> bool:
        """Block until a page has connected and drawn the scene (True), or `timeout` seconds passed (False)."""
        return self.server.wait_for_client(timeout)

    def close(self) -> None:
        """Stop the server."""
        self.server.close()

    def __enter__(self) -> Viewer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

    def _show(self, q: np.ndarray, t: float | None) -> None:
        for command in self.scene.pose_commands(q):
            self.server.send(command)
        self.server.send(frame_marker(self._frame, t))
        self._frame += 1

    def _arrow_tracks(self, trajectory: Trajectory, times: np.ndarray) -> ArrowTracks:
        """The trajectory's force arrows at the display times, their meshes sent to the page (old ones removed)."""
        tracks = arrow_tracks(trajectory, times)  # raises before anything is sent
        self._clear_arrows()
        for command in tracks.setup_commands() + tracks.pose_commands(0):  # placed before any frame is shown
            self.server.send(command)
        self._arrows = True
        return tracks

    def _clear_arrows(self) -> None:
        """Arrows of an earlier recording would stand still over another motion: remove them."""
        if self._arrows:
            self.server.send({"type": "delete", "path": FORCES})
            self._arrows = False

    def _stop_animation(self) -> None:
        """An animation playing in the page would fight the poses we send: remove it first."""
        if self._animated:
            self.server.send({"type": "set_animation", "path": "", "animations": [], "options": {"play": False}})
            self._animated = False


class LiveView:
    """The on_sample callback of a live view (see Viewer.live).

    Attributes:
        wants_contacts: the run hands it each sample's contacts (``contacts(rows, dt)``, just before the sample)
            when it draws force arrows.
    """

    def __init__(self, viewer: Viewer, speed: float, period: float, arrows: LiveArrows | None = None):
        self.viewer, self.speed, self.period = viewer, speed, period
        self.start: float | None = None
        self.shown = -math.inf  # time of the latest frame sent
        self.arrows = arrows
        self.wants_contacts = arrows is not None

    def contacts(self, rows: np.ndarray | None, dt: float) -> None:
        """The next sample's contacts: (k, 11) rows as Trajectory.contacts holds them, or None; dt the step [s]."""
        if self.arrows is not None:
            self.arrows.contacts(rows, dt)

    def __call__(self, t: float, q: np.ndarray, v: np.ndarray) -> None:
        now = time.perf_counter()
        if self.start is None:
            self.start = now - t / self.speed
        due = self.start + t / self.speed
        if due > now:  # ahead of the clock: wait, so the run plays at `speed`
            time.sleep(due - now)
        if t - self.shown >= self.period * self.speed:
            if self.arrows is not None:
                self.arrows.draw()
            self.viewer._show(np.asarray(q), t)
            self.shown = t

    def finish(self, trajectory: Trajectory) -> None:
        """Show the run's last sample if the frame rate skipped it."""
        if len(trajectory) and trajectory.t[-1] > self.shown:
            if self.arrows is not None:  # it holds the last sample's contacts
                self.arrows.draw()
            self.viewer._show(np.asarray(trajectory.q[-1]), float(trajectory.t[-1]))
            self.shown = float(trajectory.t[-1])
