"""Videos of a recorded motion: the HTML export's page filmed frame by frame in headless chromium, then encoded.

Each frame seeks the page's animation to its time and renders it (WebGL through SwiftShader, no GPU needed), so
a video shows exactly what the HTML export shows. MP4 (H.264) goes through imageio-ffmpeg, which bundles ffmpeg;
GIF through Pillow. The browser is the machine's Chromium or Chrome, driven by Playwright (never a download).
"""

from __future__ import annotations

import asyncio
import base64
import io
import os
import shutil
import sys
import tempfile
import threading
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from ..exceptions import InvalidArgumentError, MissingDependencyError
from ..files import atomic_path, check_output
from ..recorded import robot_from_trajectory
from ..robot import Robot
from ..safety import check_allocation
from ..trajectory import Trajectory, check_trajectory
from ..validation import check_flag, check_path, playback_speed
from ._deps import check_viewer_dependencies, require
from .export import page_title, recording_page
from .forces import force_arrows
from .frames import resample
from .scene import CAMERA_VIEWS, RobotScene, check_camera

__all__ = [
    "CAMERA_VIEWS",
    "EmptyFrameError",
    "check_camera",
    "check_video_options",
    "export_video",
    "find_browser",
    "frame_count",
]

VIDEO_FORMATS = (".gif", ".mp4")
BROWSERS = ("chromium", "chromium-browser", "google-chrome", "google-chrome-stable")
FPS_RANGE = {".mp4": (1.0, 120.0), ".gif": (1.0, 50.0)}  # browsers play GIF delays under 20 ms as 100 ms
SIZE_RANGE = (64, 3840)
MAX_VIDEO_FRAMES = 108_000  # an hour at 30 fps; each frame is rendered by a browser (~0.05 s)
# A pixel shows the robot when some channel differs from the empty scene (same camera, robot hidden) by more
# than this; a frame needs at least ROBOT_PIXELS such pixels.
ROBOT_STEP = 24
ROBOT_PIXELS = 12
# The flags for a headless chromium without a GPU (FIELD_NOTES: WebGL through SwiftShader). No sandbox: root (as in
# containers and CI) cannot start chromium with one, and the page is our own file, with every other request refused.
BROWSER_ARGS = (
    "--no-sandbox",
    "--disable-gpu",
    "--enable-unsafe-swiftshader",
    "--disable-background-networking",
    "--no-first-run",
    "--disable-component-update",
    "--disable-sync",
)
TIMEOUT_MS = 120_000  # a hung page fails instead of waiting forever
_RENDER = """(t) => {
  window.multibodySim.seek(t);
  viewer.render();  // synchronous: the drawing buffer holds this frame until the task ends
  return viewer.renderer.domElement.toDataURL("image/png");
}"""


class EmptyFrameError(InvalidArgumentError):
    """A video frame shows no robot (the camera misses it, or its meshes were not drawn)."""


def export_video(
    trajectory: Trajectory,
    path: str | os.PathLike[str],
    *,
    robot: Robot | None = None,
    fps: float = 30.0,
    speed: float = 1.0,
    width: int = 1280,
    height: int = 720,
    camera: str = "default",
    camera_position: Sequence[float] | None = None,
    camera_target: Sequence[float] | None = None,
    progress: bool | None = None,
    browser: str | None = None,
    forces: bool = False,
) -> Path:
    """Film a trajectory into an MP4 or GIF file, rendered headless from the HTML export's page.

    The video lasts (t[-1] - t[0]) / speed seconds: round(that x fps) frames, frame k showing the motion at
    t[0] + k * speed / fps (interpolated on the configuration manifold). The camera stays where it is put.

    Args:
        trajectory: the motion to film.
        path: the file to write (atomically): .mp4 (H.264, yuv420p) or .gif.
        robot: the robot it was recorded on; None loads it from the trajectory's metadata.
        fps: frames per second of the video, 1..120 (GIF: 1..50; its delays are whole 10 ms, spread so that
            the total duration is right). Identical consecutive GIF frames are merged (durations add up).
        speed: playback speed (2 = twice as fast as the simulated time).
        width, height: frame size [px], 64..3840 (even numbers for MP4).
        camera: the direction the camera looks from: default, front, back, left, right or top (x forward, z up),
            at a distance that frames the whole motion.
        camera_position: the camera's position [m], world frame (3,); overrides the direction.
        camera_target: the point it looks at [m] (3,); default: the centre of the space the motion sweeps.
        progress: a progress bar on stderr; None shows it when stderr is a terminal.
        browser: the Chromium or Chrome executable; None looks for chromium, chromium-browser, google-chrome.
        forces: draw a contact scene's contact forces as arrows (see viz/forces.py).

    Returns:
        The path written.

    Raises:
        InvalidArgumentError: unknown extension, fps, size or speed out of range, a bad camera.
        EmptyFrameError: a frame shows no robot (nothing is written).
        MissingDependencyError: no browser, or a package of the viz extra is missing.
    """
    check_trajectory(trajectory, "trajectory")
    check_camera(camera, camera_position, camera_target)
    check_flag(forces, "forces")
    target, fps = check_video_options(path, fps=fps, speed=speed, width=width, height=height)
    suffix = target.suffix.lower()
    count = frame_count(trajectory, fps=fps, speed=speed)
    if suffix == ".gif":  # a GIF is assembled in memory: one palette byte per pixel per frame
        check_allocation(
            count * width * height,
            f"a {width}x{height} GIF of {count} frames would keep them",
            "choose a lower --fps, a smaller size, a higher --speed, or .mp4 (streamed to disk)",
        )
    executable = find_browser(browser)
    check_viewer_dependencies()
    require("playwright.sync_api", "videos")
    require("imageio_ffmpeg" if suffix == ".mp4" else "PIL.Image", "videos")

    robot = robot_from_trajectory(trajectory) if robot is None else robot
    times, Q = resample(robot, trajectory, fps / speed)
    times, Q = times[:count], Q[:count]  # frame k at t0 + k speed / fps: the grid, not the end appended to it
    scene = RobotScene(robot)
    aim = scene.camera_command(Q, view=camera, position=camera_position, target=camera_target, times=times)
    title = page_title(trajectory, robot)
    arrows = force_arrows(trajectory, times) if forces else None
    page = recording_page(robot, times, Q, title=title, play=False, loop=False, camera=aim, scene=scene, arrows=arrows)
    offsets = [float(t - times[0]) for t in times]
    with tempfile.TemporaryDirectory(prefix="multibody-sim-video-") as folder:
        html = Path(folder) / "page.html"
        html.write_text(page, encoding="utf-8")
        show = sys.stderr.isatty() if progress is None else progress
        with (
            atomic_path(target, what="video", suffix=suffix) as partial,  # renamed over target when complete
            _Encoder(partial, suffix, (width, height), fps) as write,
        ):
            _film(executable, html, (width, height), offsets, times, write, show)
    return target


def check_video_options(
    path: str | os.PathLike[str], *, fps: float, speed: float, width: int, height: int, prefix: str = ""
) -> tuple[Path, float]:
    """Check a video's file name and options before any work (export_video calls it; so does `play --video`).

    Args:
        path, fps, speed, width, height: as export_video takes them.
        prefix: put before the option names in messages ("--" for a command line).

    Returns:
        (the path, fps as a float).

    Raises:
        InvalidArgumentError: unknown extension, fps, speed or size out of range.
    """
    target = Path(check_path(path, "path", "a video file (.mp4 or .gif)"))
    suffix = target.suffix.lower()
    label = f"{prefix}video {target}" if prefix else str(target)
    check_output(target, f"{prefix}video", "motion.mp4")  # only a regular file is replaced
    if suffix not in VIDEO_FORMATS:
        raise InvalidArgumentError(
            f"{label}: unknown video format '{target.suffix}' (choose from: {', '.join(VIDEO_FORMATS)})"
        )
    low, high = FPS_RANGE[suffix]
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not (low <= fps <= high):
        raise InvalidArgumentError(
            f"{prefix}fps must be from {low:g} to {high:g} frames per second for {suffix}, got {fps:g}"
            if isinstance(fps, (int, float))
            else f"{prefix}fps must be a number, got {fps!r}"
        )
    playback_speed(speed, f"{prefix}speed")
    for name, value in (("width", width), ("height", height)):
        if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
            raise InvalidArgumentError(f"{prefix}{name} must be a whole number of pixels, got {value!r}")
        if not SIZE_RANGE[0] <= value <= SIZE_RANGE[1]:
            raise InvalidArgumentError(
                f"{prefix}{name} must be from {SIZE_RANGE[0]} to {SIZE_RANGE[1]} pixels, got {value}"
            )
        if suffix == ".mp4" and value % 2:
            raise InvalidArgumentError(
                f"{prefix}{name} must be even for .mp4 (H.264 halves the colour resolution), got {value}"
            )
    return target, float(fps)


def frame_count(trajectory: Trajectory, *, fps: float, speed: float = 1.0) -> int:
    """How many frames export_video writes: round((t[-1] - t[0]) / speed x fps), at least 1.

    Raises:
        InvalidArgumentError: more than MAX_VIDEO_FRAMES (or a span that overflows).
    """
    span = float(trajectory.t[-1]) - float(trajectory.t[0])  # Python floats: an overflow is inf, refused below
    frames = span / speed * fps
    if not frames <= MAX_VIDEO_FRAMES:
        raise InvalidArgumentError(
            f"a video of {span:.6g} s of motion at speed {speed:g} and {fps:g} frames per second would have "
            f"{frames:.3g} frames, more than the {MAX_VIDEO_FRAMES} a video may (an hour at 30 fps): choose a higher "
            "speed, a lower fps, or film part of the trajectory"
        )
    return max(1, round(frames))


def find_browser(browser: str | None = None) -> str:
    """The Chromium or Chrome to film with: `browser` if given, else the first of BROWSERS on PATH."""
    if browser is not None:
        found = shutil.which(browser)
        if found is None:
            raise MissingDependencyError(f"videos need a Chromium or Chrome browser; '{browser}' is not one")
        return found
    for name in BROWSERS:
        found = shutil.which(name)
        if found is not None:
            return found
    raise MissingDependencyError(
        f"videos need a Chromium or Chrome browser: none of {', '.join(BROWSERS)} is on PATH "
        "(Debian, Ubuntu: apt install chromium)"
    )


def _film(
    executable: str,
    html: Path,
    size: tuple[int, int],
    offsets: list[float],
    times: np.ndarray,
    write: Callable[[np.ndarray], None],
    progress: bool,
) -> None:
    """Open the page in headless chromium and hand every frame to `write`, checking each shows the robot."""

    def run() -> None:
        from playwright.sync_api import sync_playwright
        from tqdm import tqdm

        with sync_playwright() as playwright:
            browser = playwright.chromium.launch(
                executable_path=executable, args=list(BROWSER_ARGS), timeout=TIMEOUT_MS
            )
            try:
                page = browser.new_page(viewport={"width": size[0], "height": size[1]}, device_scale_factor=1)
                page.set_default_timeout(TIMEOUT_MS)
                # Offline: the page is one file; anything else it asked for would be a bug, so refuse it.
                page.route("**/*", lambda r: r.continue_() if r.request.url.startswith("file:") else r.abort())
                page.goto(html.as_uri())
                page.wait_for_function(
                    "window.multibodySim && (window.multibodySim.loaded || window.multibodySim.errors.length)"
                )
                errors = page.evaluate("window.multibodySim.errors")
                if errors:
                    raise InvalidArgumentError(f"the page could not show the recording: {errors[0].splitlines()[0]}")
                page.evaluate("viewer.scene_tree.find(['meshcat', 'robot']).object.visible = false")
                empty = _decode(page.evaluate(_RENDER, offsets[0]), size)
                page.evaluate("viewer.scene_tree.find(['meshcat', 'robot']).object.visible = true")
                bar = tqdm(
                    total=len(offsets), unit="frame", desc="video", disable=not progress, leave=False, file=sys.stderr
                )
                with bar:
                    for k, offset in enumerate(offsets):
                        frame = _decode(page.evaluate(_RENDER, offset), size)
                        shown = int((np.abs(frame.astype(np.int16) - empty).max(axis=2) > ROBOT_STEP).sum())
                        if shown < ROBOT_PIXELS:
                            raise EmptyFrameError(
                                f"frame {k} (t = {times[k]:.6g} s) shows no robot ({shown} pixels differ from the "
                                "empty scene): the camera does not see it (check the camera position and target) "
                                "or its meshes were not drawn; no video written"
                            )
                        write(frame)
                        bar.update(1)
            finally:
                browser.close()

    try:
        asyncio.get_running_loop()
    except RuntimeError:  # no event loop here: Playwright's synchronous API may run in this thread
        run()
        return
    # Inside an event loop (a Jupyter kernel) the synchronous API refuses to run: give it a thread of its own.
    failure: list[BaseException] = []

    def guarded() -> None:
        try:
            run()
        except BaseException as exc:  # re-raised in the caller's thread
            failure.append(exc)

    worker = threading.Thread(target=guarded, name="multibody-sim-video")
    worker.start()
    worker.join()
    if failure:
        raise failure[0]


def _decode(data_url: str, size: tuple[int, int]) -> np.ndarray:
    """A canvas's PNG data URL as an (height, width, 3) uint8 array."""
    image_module = require("PIL.Image", "videos")
    image = image_module.open(io.BytesIO(base64.b64decode(data_url.split(",", 1)[1]))).convert("RGB")
    if image.size != size:
        raise InvalidArgumentError(
            f"the browser drew {image.size[0]}x{image.size[1]} pixels instead of {size[0]}x{size[1]}"
        )
    return np.asarray(image)


class _Encoder:
    """Context manager giving write(frame) for one video file; the file is complete when it exits cleanly."""

    def __init__(self, path: Path, suffix: str, size: tuple[int, int], fps: float):
        self.path, self.suffix, self.size, self.fps = path, suffix, size, fps
        self.frames: list[Any] = []
        self.writer: Any = None

    def __enter__(self) -> Callable[[np.ndarray], None]:
        if self.suffix == ".mp4":
            imageio_ffmpeg = require("imageio_ffmpeg", "videos")
            self.writer = imageio_ffmpeg.write_frames(
                str(self.path),
                self.size,
                fps=self.fps,
                codec="libx264",
                quality=8,
                macro_block_size=2,  # H.264 in yuv420p needs even sizes, which export_video checked
                ffmpeg_log_level="error",
            )
            self.writer.send(None)
            return lambda frame: self.writer.send(np.ascontiguousarray(frame))
        image_module = require("PIL.Image", "videos")

        palette: list[Any] = []

        def add(frame: np.ndarray) -> None:
            image = image_module.fromarray(frame)
            if not palette:  # one palette, the first frame's, for all: what does not move keeps its colours
                palette.append(image.quantize(colors=255, dither=image_module.Dither.NONE))
            self.frames.append(image.quantize(palette=palette[0], dither=image_module.Dither.NONE))

        return add

    def __exit__(self, kind: type[BaseException] | None, *exc: object) -> None:
        if self.suffix == ".mp4":
            if self.writer is not None:
                self.writer.close()
            return
        if kind is not None or not self.frames:
            return
        first, *rest = self.frames
        delays = gif_delays(len(self.frames), self.fps)
        first.save(self.path, format="GIF", save_all=True, append_images=rest, duration=delays, loop=0)


def gif_delays(count: int, fps: float) -> list[int]:
    """Each GIF frame's delay [ms]: whole centiseconds (the format's unit), the rounding spread so that frame k
    ends at round(100 (k + 1) / fps) cs: the total is count / fps to within 5 ms however long the video."""
    ends = [round(100 * (k + 1) / fps) for k in range(count)]
    return [10 * (end - start) for start, end in zip([0, *ends[:-1]], ends, strict=True)]
