"""Videos: filmed frame by frame in headless Debian chromium from the HTML export's page, read back with imageio
and Pillow: frame count and duration as asked, frames that change where and when the robot moves, and only
there, an empty view refused."""

from __future__ import annotations

import dataclasses
import importlib.util
import os
import re
import shutil
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from PIL import Image

import multibody_sim as ms
from multibody_sim.cli import main


def _require(modules: tuple[str, ...], what: str) -> None:
    """In the test extra, so CI must have them; elsewhere their absence skips this file, visibly."""
    missing = [m for m in modules if importlib.util.find_spec(m) is None]
    if missing:
        reason = f"{what} is not installed (missing: {', '.join(missing)}; pip install -e '.[test]')"
        if os.environ.get("CI") == "true":
            pytest.fail(reason, pytrace=False)
        pytest.skip(reason, allow_module_level=True)


_require(("meshcat", "trimesh", "umsgpack", "imageio_ffmpeg", "playwright"), "the viz extra")
_require(("imageio",), "imageio (reads the videos back)")
import imageio.v3 as iio  # noqa: E402

from multibody_sim import viz  # noqa: E402
from multibody_sim.viz import video  # noqa: E402

PREFIX = "multibody-sim: error: "
SIZE = (320, 240)
STEP = 24  # a pixel changed when a channel moved by more than this (H.264 and palette noise stay far below)
MOVED_MIN = 40  # pixels: the bob alone (10 cm across, 5 px 3 m away at 320x240) where it was and where it went


def _film_available() -> None:
    if shutil.which("chromium") is None:
        reason = "Debian's chromium is not installed (scripts/test.sh installs it with apt-get when root)"
        if os.environ.get("CI") == "true":
            pytest.fail(reason)
        pytest.skip(reason)


@pytest.fixture(scope="module")
def still_then_swinging(tmp_path_factory: pytest.TempPathFactory) -> tuple[ms.Trajectory, Path]:
    """The pendulum held at 0.5 rad until t = 0.45 s, then turning at -3 rad/s until 1 s: (trajectory, its file)."""
    pendulum = ms.load_robot("pendulum")
    run = ms.simulate(pendulum, [0.5], [0.0], duration=1.0, dt=1e-3, output_dt=0.01)
    angle = 0.5 - 3.0 * np.clip(run.t - 0.45, 0.0, None)
    run = dataclasses.replace(run, q=angle[:, None])
    return run, run.save(tmp_path_factory.mktemp("video") / "pendulum.npz")


def _changed(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    return np.abs(a.astype(int) - b.astype(int)).max(axis=2) > STEP


def _project(points: np.ndarray, position: np.ndarray, target: np.ndarray) -> np.ndarray:
    """Pixel coordinates (x right, y down) of world points seen by meshcat's camera (75 deg vertical field of
    view, z up) at `position` looking at `target`, in a SIZE frame: an independent pinhole model."""
    forward = (target - position) / np.linalg.norm(target - position)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    relative = points - position
    depth = relative @ forward
    focal = 1.0 / np.tan(np.radians(75.0) / 2)
    x = relative @ right / depth * focal * SIZE[1] / SIZE[0]
    y = relative @ up / depth * focal
    return np.column_stack([(x + 1) / 2 * SIZE[0], (1 - y) / 2 * SIZE[1]])


def _distance_to_segment(pixels: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    along = np.clip((pixels - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
    return np.linalg.norm(pixels - (a + along[:, None] * (b - a)), axis=1)


def test_mp4_has_the_frames_asked_and_changes_only_where_and_when_the_robot_moves(
    still_then_swinging: tuple[ms.Trajectory, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _film_available()
    run, path = still_then_swinging
    out = tmp_path / "films" / "pendulum.mp4"
    position, target = np.array([0.0, -3.0, -0.5]), np.array([0.0, 0.0, -0.5])  # facing the swing's plane
    camera = ["--camera-position", *map(str, position), "--camera-target", *map(str, target)]
    code = main(["play", str(path), "--video", str(out), "--fps", "10", "--width", "320", "--height", "240", *camera])
    captured = capsys.readouterr()
    assert (code, captured.err) == (0, "")  # no progress bar: stderr is not a terminal here
    pattern = rf"wrote {re.escape(str(out))} \(10 frames at 10 fps, 1\.00 s; \d+\.\d MB in \d+\.\d s\)\n"
    assert re.fullmatch(pattern, captured.out), captured.out
    meta = iio.immeta(out, plugin="FFMPEG")
    assert (meta["codec"], meta["fps"], meta["duration"], meta["size"]) == ("h264", 10.0, 1.0, SIZE)
    frames = iio.imread(out, plugin="FFMPEG")
    assert frames.shape == (10, SIZE[1], SIZE[0], 3)  # 1 s at 10 fps: frames at t = 0, 0.1, ..., 0.9
    changes = [_changed(a, b) for a, b in zip(frames[:-1], frames[1:], strict=True)]
    counts = [int(change.sum()) for change in changes]
    assert max(counts[:4]) == 0, counts  # t = 0 .. 0.4: held still, the frames are the same
    assert min(counts[4:]) > MOVED_MIN, counts  # from 0.4 to 0.9 s it swings: every frame differs
    # Where: what changes between two frames lies along the rod, hinge to bob, in one of them, as a pinhole
    # camera at the same place sees it (the bob's radius is 2.6 px there); the grid, the axes, the sky do not.
    pendulum = ms.load_robot("pendulum")
    hinge = _project(np.zeros((1, 3)), position, target)[0]
    times = np.arange(10) * 0.1
    bobs = []
    for angle in np.interp(times, run.t, run.q[:, 0]):
        pin.forwardKinematics(pendulum.model, pendulum.data, np.array([angle]))
        bobs.append(pendulum.data.oMi[1].act(np.array([0.0, 0.0, -1.0])))
    bob_pixels = _project(np.array(bobs), position, target)
    for k in range(4, 9):
        ys, xs = np.nonzero(changes[k])
        pixels = np.column_stack([xs, ys]) + 0.5
        near = np.minimum(
            _distance_to_segment(pixels, hinge, bob_pixels[k]), _distance_to_segment(pixels, hinge, bob_pixels[k + 1])
        )
        assert near.max() < 6.0, (k, near.max())
        for bob in bob_pixels[k : k + 2]:  # and the bob did change where it was and where it went
            assert np.linalg.norm(pixels - bob, axis=1).min() < 3.0


def test_gif_keeps_the_duration_at_a_speed_and_merges_still_frames(
    still_then_swinging: tuple[ms.Trajectory, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _film_available()
    run, _ = still_then_swinging
    out = viz.export_video(
        run, tmp_path / "fast.gif", fps=10, speed=2.0, width=320, height=240, camera="front", progress=True
    )
    # 1 s at twice the speed: 0.5 s, 5 frames showing t = 0, 0.2, 0.4 (held still: one frame of 300 ms), 0.6, 0.8.
    image = Image.open(out)
    durations = []
    for k in range(image.n_frames):
        image.seek(k)
        durations.append(image.info["duration"])
    assert durations == [300, 100, 100]
    frames = iio.imread(out, index=None)
    assert frames.shape[:3] == (3, SIZE[1], SIZE[0])
    assert _changed(frames[0][..., :3], frames[1][..., :3]).sum() > MOVED_MIN
    assert capsys.readouterr().err.count("| 0/5 [") == 1  # one progress bar, counting the 5 frames filmed


def test_a_view_without_the_robot_is_an_error_not_a_blank_video(
    still_then_swinging: tuple[ms.Trajectory, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    _film_available()
    _, run = still_then_swinging
    out = tmp_path / "away.mp4"
    looking_away = ["--camera-position", "3", "0", "0.5", "--camera-target", "6", "0", "0.5"]
    code = main(
        ["play", str(run), "--video", str(out), "--fps", "5", "--width", "160", "--height", "120", *looking_away]
    )
    assert code == 2
    assert capsys.readouterr() == (
        "",
        f"{PREFIX}frame 0 (t = 0 s) shows no robot (0 pixels differ from the empty scene): the camera does not see "
        "it (check the camera position and target) or its meshes were not drawn; no video written\n",
    )
    assert list(tmp_path.iterdir()) == []  # not even a partial file


@pytest.mark.parametrize(
    ("options", "message"),
    [
        (["--video", "{d}/x.avi"], "--video {d}/x.avi: unknown video format '.avi' (choose from: .gif, .mp4)"),
        (["--video", "{d}/x.mp4", "--fps", "500"], "--fps must be from 1 to 120 frames per second for .mp4, got 500"),
        (["--video", "{d}/x.gif", "--fps", "60"], "--fps must be from 1 to 50 frames per second for .gif, got 60"),
        (["--video", "{d}/x.mp4", "--fps", "0"], "--fps must be from 1 to 120 frames per second for .mp4, got 0"),
        (
            ["--video", "{d}/x.mp4", "--speed", "-2"],
            "--speed must be a number from 0.001 to 1000 (1 = real time), got -2",
        ),
        (["--video", "{d}/x.mp4", "--width", "20"], "--width must be from 64 to 3840 pixels, got 20"),
        (
            ["--video", "{d}/x.mp4", "--height", "241"],
            "--height must be even for .mp4 (H.264 halves the colour resolution), got 241",
        ),
        (
            ["--video", "{d}/x.gif", "--camera", "under"],
            "--camera: unknown view 'under' (choose from: default, front, back, left, right, top)",
        ),
        (
            ["--video", "{d}/x.gif", "--camera-position", "1", "nan", "0"],
            "--camera-position must be 3 finite numbers (x y z in metres), got [1.0, nan, 0.0]",
        ),
        (
            ["--video", "{d}/x.gif", "--camera-target", "inf", "0", "0"],
            "--camera-target must be 3 finite numbers (x y z in metres), got [inf, 0.0, 0.0]",
        ),
        (
            ["--video", "{d}/x.mp4", "--camera-position", "1", "2", "3", "--camera-target", "1", "2", "3"],
            "--camera-position and --camera-target coincide: the camera would look nowhere",
        ),
        (["--video", "{d}"], "--video {d}: is a directory, expected a file name such as motion.mp4"),
    ],
)
def test_bad_video_options_are_one_line_before_any_work(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], options: list[str], message: str
) -> None:
    missing = tmp_path / "missing.npz"  # never read: the options are refused first
    code = main(["play", str(missing), *(o.format(d=tmp_path) for o in options)])
    assert (code, capsys.readouterr()) == (2, ("", f"{PREFIX}{message.format(d=tmp_path)}\n"))
    assert list(tmp_path.iterdir()) == []


def test_video_without_a_browser_says_what_to_install(
    still_then_swinging: tuple[ms.Trajectory, Path],
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    run, path = still_then_swinging
    monkeypatch.setenv("PATH", str(tmp_path))  # no chromium, chromium-browser or google-chrome here
    message = (
        "videos need a Chromium or Chrome browser: none of chromium, chromium-browser, google-chrome, "
        "google-chrome-stable is on PATH (Debian, Ubuntu: apt install chromium)"
    )
    assert main(["play", str(path), "--video", str(tmp_path / "x.mp4")]) == 2
    assert capsys.readouterr() == ("", f"{PREFIX}{message}\n")
    with pytest.raises(ms.MissingDependencyError, match=re.escape(message)):
        viz.export_video(run, tmp_path / "x.gif")
    assert list(tmp_path.iterdir()) == []


def test_gif_delays_are_whole_centiseconds_adding_up_to_the_duration() -> None:
    for count, fps in ((10, 10.0), (90, 30.0), (7, 24.0), (1, 1.0), (1000, 29.97)):
        delays = video.gif_delays(count, fps)
        assert len(delays) == count and all(d % 10 == 0 and d > 0 for d in delays)
        assert abs(sum(delays) - 1000 * count / fps) <= 5.0
        assert max(abs(d - 1000 / fps) for d in delays) < 10.0  # each as close to 1/fps as centiseconds allow


def test_frame_count_follows_duration_fps_and_speed(still_then_swinging: tuple[ms.Trajectory, Path]) -> None:
    run, _ = still_then_swinging
    assert video.frame_count(run, fps=30) == 30
    assert video.frame_count(run, fps=30, speed=0.5) == 60
    assert video.frame_count(run, fps=24, speed=4) == 6
    short = dataclasses.replace(run, t=run.t[:1], q=run.q[:1])
    assert video.frame_count(short, fps=30) == 1  # a single sample is a one-frame video


def test_camera_views_and_fixed_positions() -> None:
    scene = viz.RobotScene(ms.load_robot("pendulum"))
    Q = np.array([[0.5], [-0.5]])
    fixed = scene.camera_command(Q, position=[2.0, 1.0, 0.5], target=[0.0, 0.0, -0.5])
    assert (fixed["position"], fixed["target"]) == ([2.0, 1.0, 0.5], [0.0, 0.0, -0.5])
    framed = scene.camera_command(Q)
    for view, (azimuth, elevation) in video.CAMERA_VIEWS.items():
        command = scene.camera_command(Q, view=view)
        assert command["target"] == framed["target"]  # every view looks at the centre of the swept space
        offset = np.subtract(command["position"], command["target"])
        direction = offset / np.linalg.norm(offset)
        a, e = np.radians([azimuth, elevation])
        np.testing.assert_allclose(direction, [np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], atol=1e-12)
    assert scene.camera_command(Q, view="front")["position"][0] > framed["target"][0]  # front: on the +x side
    with pytest.raises(ms.InvalidArgumentError, match=re.escape("the camera target must be 3 finite numbers")):
        scene.camera_command(Q, target=[0.0, np.nan, 1.0])
    with pytest.raises(ms.InvalidArgumentError, match="the camera position and target coincide"):
        scene.camera_command(Q, position=[1.0, 1.0, 1.0], target=[1.0, 1.0, 1.0])
    with pytest.raises(ms.UnknownNameError, match=re.escape("unknown camera view 'under' (choose from: default,")):
        scene.camera_command(Q, view="under")
