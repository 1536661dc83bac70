"""Viewing: frames on the configuration manifold, meshes against Pinocchio's own loader, the HTML export and the
live server checked from the pixels in a real browser (Debian's chromium, headless), the playback commands."""

from __future__ import annotations

import hashlib
import importlib.util
import io
import os
import re
import shutil
import socket
import subprocess
import sys
import threading
import time
import urllib.error
import urllib.request
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
import pytest
from PIL import Image
from scipy import ndimage
from scipy.spatial.transform import Rotation, Slerp

import multibody_sim as ms
from multibody_sim.catalog import CATALOG, catalog_urdf
from multibody_sim.cli import main


def _require_viz_extra() -> None:
    """The viz extra (in the test extra) must be there in CI; elsewhere its absence skips this file, visibly."""
    modules = ("meshcat", "trimesh", "collada", "tornado", "umsgpack", "matplotlib")
    missing = [m for m in modules if importlib.util.find_spec(m) is None]
    if missing:
        reason = f"the viz extra is not installed (missing: {', '.join(missing)}; pip install -e '.[test]')"
        if os.environ.get("CI") == "true":
            pytest.fail(reason, pytrace=False)
        pytest.skip(reason, allow_module_level=True)


_require_viz_extra()
viz = pytest.importorskip("multibody_sim.viz")

PREFIX = "multibody-sim: error: "
SHIPPED = Path(__file__).resolve().parents[1] / "models"
# The flags CONTRACTS/FIELD_NOTES name for a headless chromium without a GPU (WebGL through SwiftShader).
# Playwright adds --headless and its own temporary --user-data-dir.
BROWSER_ARGS = [
    "--no-sandbox",
    "--disable-gpu",
    "--enable-unsafe-swiftshader",
    "--disable-background-networking",
    "--no-first-run",
    "--disable-component-update",
    "--disable-sync",
    "--window-size=1024,768",
]
VIEWPORT = {"width": 1024, "height": 768}
TIMEOUT_MS = 90_000  # every browser call is bounded: a hung page fails the test instead of the run
# Pixel checks. The background is meshcat's vertical gradient: a pixel is "drawn" if it differs from its row's
# median by more than COLOR_STEP in some channel. Two erosions drop lines up to 4 px wide (antialiased edges),
# so only solid shapes count. A robot a few hundred pixels tall covers several percent of the 1024x768 view;
# an empty view has nothing solid at all.
COLOR_STEP = 40
DRAWN_MIN = 0.004  # fraction of the view: about 3000 px
EMPTY_MAX = 0.0005
MOVED_MIN = 0.002
HIDE_DECORATIONS = """
  for (const name of ["Grid", "Axes"]) viewer.scene_tree.find([name]).object.visible = false;
  viewer.gui.domElement.style.display = "none";
  viewer.set_dirty();
"""
HIDE_ROBOT = "viewer.scene_tree.find(['meshcat', 'robot']).object.visible = false; viewer.set_dirty();"


# ---- frames on the manifold -------------------------------------------------------------------------------
def _trajectory(t: np.ndarray, q: np.ndarray) -> Any:
    """A stand-in with what resample reads."""

    class Samples:
        pass

    samples = Samples()
    samples.t, samples.q = t, q  # type: ignore[attr-defined]
    return samples


def test_frame_times_every_period_with_the_end() -> None:
    times = viz.frame_times(0.0, 1.0, 30.0)
    assert len(times) == 31 and times[-1] == 1.0
    np.testing.assert_allclose(np.diff(times), 1 / 30, rtol=1e-12)
    times = viz.frame_times(0.5, 1.25, 2.0)  # 0.5, 1.0, then the end, which is off the grid
    np.testing.assert_allclose(times, [0.5, 1.0, 1.25])


def test_resample_revolute_is_linear_and_hits_the_samples(robot: Callable[..., ms.Robot]) -> None:
    ur5 = robot("ur5")
    rng = np.random.default_rng(1)
    t = np.array([0.0, 0.1, 0.25, 0.4])
    q = np.array([ur5.random_configuration(rng) for _ in t])
    times, frames = viz.resample(ur5, _trajectory(t, q), fps=20.0)
    np.testing.assert_allclose(times, np.arange(9) * 0.05)
    expected = np.column_stack([np.interp(times, t, q[:, j]) for j in range(ur5.nq)])  # revolute: linear
    np.testing.assert_allclose(frames, expected, atol=1e-12)
    on_samples = [np.argmin(abs(times - s)) for s in (0.0, 0.25)]
    np.testing.assert_array_equal(frames[on_samples], q[[0, 2]])


def test_resample_free_flyer_rotates_by_slerp(robot: Callable[..., ms.Robot]) -> None:
    free = robot("free_body")
    q0, q1 = free.neutral(), free.neutral()
    q0[3:7] = Rotation.from_rotvec([0.3, -0.2, 0.1]).as_quat()
    q1[:3] = [0.4, -0.1, 0.2]
    q1[3:7] = Rotation.from_rotvec([-1.0, 2.0, 0.5]).as_quat()
    times, frames = viz.resample(free, _trajectory(np.array([0.0, 1.0]), np.array([q0, q1])), fps=10.0)
    slerp = Slerp([0.0, 1.0], Rotation.from_quat([q0[3:7], q1[3:7]]))(times)
    # Rotation part: scipy's slerp, an independent implementation; the quaternion stays unit.
    np.testing.assert_allclose(np.linalg.norm(frames[:, 3:7], axis=1), 1.0, atol=1e-12)
    angle = (Rotation.from_quat(frames[:, 3:7]) * slerp.inv()).magnitude()
    assert angle.max() < 1e-9
    # The free-flyer moves along an SE(3) geodesic: the midpoint is equally far (in the Lie algebra) from both ends.
    mid = frames[5]
    np.testing.assert_allclose(free.difference(q0, mid), free.difference(mid, q1), atol=1e-12)
    # Interpolating the numbers in q would leave the unit sphere: what the manifold interpolation avoids.
    assert abs(np.linalg.norm(0.5 * (q0[3:7] + q1[3:7])) - 1.0) > 0.05


def test_resample_continuous_joint_stays_on_the_circle(robot: Callable[..., ms.Robot]) -> None:
    pendulum = robot("double_pendulum_continuous")
    angles = np.array([[0.2, -3.0], [2.9, 3.0]])  # the second joint crosses pi: the short way round is 0.283 rad
    q = np.array([np.column_stack([np.cos(a), np.sin(a)]).reshape(-1) for a in angles])
    times, frames = viz.resample(pendulum, _trajectory(np.array([0.0, 1.0]), q), fps=4.0)
    wrapped = np.angle(np.exp(1j * (angles[1] - angles[0])))  # shortest signed difference
    for time_, frame in zip(times, frames, strict=True):
        expected = angles[0] + time_ * wrapped
        np.testing.assert_allclose(frame, np.column_stack([np.cos(expected), np.sin(expected)]).reshape(-1), atol=1e-12)


def test_resample_long_trajectory_is_light(robot: Callable[..., ms.Robot], monkeypatch: pytest.MonkeyPatch) -> None:
    """Light: the work scales with the frames, not the samples (at most one interpolation per frame)."""
    pendulum = robot("pendulum")
    t = np.linspace(0.0, 60.0, 600_001)  # 60 s sampled every 0.1 ms
    q = np.sin(t)[:, None]
    interpolations = []
    interpolate = pin.interpolate

    def counted(*args: Any) -> Any:
        interpolations.append(1)
        return interpolate(*args)

    monkeypatch.setattr(pin, "interpolate", counted)
    times, frames = viz.resample(pendulum, _trajectory(t, q), fps=30.0)
    assert frames.shape == (1801, 1)  # 30 frames per second, whatever the sampling
    np.testing.assert_allclose(frames[:, 0], np.sin(times), atol=1e-8)  # linear between 0.1 ms samples
    assert 0 < len(interpolations) <= 1801


def test_resample_refuses_bad_rates(robot: Callable[..., ms.Robot]) -> None:
    pendulum = robot("pendulum")
    samples = _trajectory(np.array([0.0, 1.0]), np.zeros((2, 1)))
    with pytest.raises(ms.InvalidArgumentError, match=re.escape("fps must be a positive number, got 0")):
        viz.resample(pendulum, samples, fps=0)


# ---- the robot of a trajectory ----------------------------------------------------------------------------
def _pendulum_copy(tmp_path: Path) -> Path:
    path = tmp_path / "pendulum.urdf"
    shutil.copy(SHIPPED / "pendulum" / "pendulum.urdf", path)
    return path


def test_robot_from_trajectory_reloads_the_recorded_robot(tmp_path: Path) -> None:
    urdf = _pendulum_copy(tmp_path)
    recorded = ms.load_robot(urdf, damping=False)
    trajectory = ms.simulate(recorded, [0.5], [0.0], duration=0.01, dt=0.005)
    again = viz.robot_from_trajectory(trajectory)
    assert again.source["urdf_sha256"] == hashlib.sha256(urdf.read_bytes()).hexdigest()
    assert again.damping is not None and not np.any(again.damping)
    assert again.nq == recorded.nq


def test_robot_from_trajectory_refuses_a_changed_urdf(tmp_path: Path) -> None:
    urdf = _pendulum_copy(tmp_path)
    trajectory = ms.simulate(ms.load_robot(urdf), [0.5], [0.0], duration=0.01, dt=0.005)
    urdf.write_text(urdf.read_text().replace('<mass value="1.0"/>', '<mass value="2.0"/>'))
    new = hashlib.sha256(urdf.read_bytes()).hexdigest()
    old = trajectory.metadata["robot"]["urdf_sha256"]
    message = (
        f"{urdf}: the URDF changed since the trajectory was recorded (SHA-256 {new[:12]}... instead of "
        f"{old[:12]}...); the motion would be shown on a different robot"
    )
    with pytest.raises(ms.ModelError, match=re.escape(message)):
        viz.robot_from_trajectory(trajectory)


def test_robot_from_trajectory_needs_the_metadata(robot: Callable[..., ms.Robot]) -> None:
    trajectory = ms.simulate(robot("pendulum"), [0.5], [0.0], duration=0.01, dt=0.005)
    trajectory.metadata = {}
    message = "the trajectory does not record how its robot was loaded (metadata 'robot')"
    with pytest.raises(ms.TrajectoryFileError, match=re.escape(message)):
        viz.robot_from_trajectory(trajectory)


# ---- meshes -----------------------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["panda", "ur5", "solo12", "pendulum"])
def test_visual_meshes_match_pinocchios_loader(name: str, robot: Callable[..., ms.Robot]) -> None:
    """Our conversion (trimesh, pycollada) and Pinocchio's (coal, assimp) read the same files: same boxes."""
    model = robot(name)
    scene = viz.RobotScene(model)
    path, dirs = catalog_urdf(CATALOG[name])
    reference = pin.buildGeomFromUrdf(
        model.model, str(path), pin.GeometryType.VISUAL, package_dirs=[str(d) for d in dirs]
    )
    assert len(scene.visuals) == reference.ngeoms
    for visual, obj in zip(scene.visuals, reference.geometryObjects, strict=True):
        lo = np.min([p.bounds()[0] for p in visual.parts], axis=0)
        hi = np.max([p.bounds()[1] for p in visual.parts], axis=0)
        shape = obj.geometry
        shape.computeLocalAABB()
        box = shape.aabb_local
        # Meshes: the same vertices read by two libraries. Primitives: our tessellation lies inside the shape.
        tolerance = 1e-4 if obj.meshPath.startswith("/") else 0.02 * float(np.max(box.max_ - box.min_))
        np.testing.assert_allclose(lo, box.min_, atol=tolerance, err_msg=obj.name)
        np.testing.assert_allclose(hi, box.max_, atol=tolerance, err_msg=obj.name)
        np.testing.assert_allclose(visual.placement, obj.placement.homogeneous, atol=1e-12)
        assert visual.joint == obj.parentJoint
        if hasattr(shape, "num_tris"):  # every part of the mesh is there (assimp drops a few degenerate ones)
            triangles = sum(len(p.faces) for p in visual.parts)
            assert shape.num_tris <= triangles <= 1.01 * shape.num_tris, obj.name


def test_mesh_colors_come_from_the_urdf_or_the_files(robot: Callable[..., ms.Robot]) -> None:
    pendulum = viz.RobotScene(robot("pendulum"))
    colors = {tuple(np.round(p.color, 6)) for v in pendulum.visuals for p in v.parts}
    assert colors == {(0.85, 0.3, 0.2, 1.0), (0.6, 0.6, 0.6, 1.0)}  # the URDF's <material> colours
    panda = viz.RobotScene(robot("panda"))  # no <material>: the COLLADA files' colours (white and dark grey)
    shades = {round(float(np.mean(p.color[:3])), 2) for v in panda.visuals for p in v.parts}
    assert min(shades) < 0.3 and max(shades) > 0.85


def test_a_robot_without_visuals_is_drawn_as_a_skeleton(write_urdf: Callable[..., Path]) -> None:
    from conftest import joint, link, urdf

    text = urdf(
        link("base"),
        link("arm"),
        link("forearm"),
        joint("j1", "base", "arm"),
        joint("j2", "arm", "forearm", xyz="0 0 -1"),
    )
    model = ms.load_robot(write_urdf(text))
    note = f"{model.name}: the URDF has no visual geometry; drawing a skeleton of its joints"
    with pytest.warns(viz.MissingVisualsWarning, match=re.escape(note)):
        scene = viz.RobotScene(model)
    assert scene.notes == [note]
    assert scene.joints == [1, 2]
    lo = np.min([p.bounds()[0] for p in scene.visuals[0].parts], axis=0)
    assert lo[2] < -0.9  # the rod from j1 to j2, one metre below


# ---- the server ---------------------------------------------------------------------------------------------
def listening_addresses(port: int) -> set[str]:
    """Addresses with a listening TCP socket on `port`, from the kernel's tables (not from our code)."""
    found = set()
    for table, family in (("/proc/net/tcp", socket.AF_INET), ("/proc/net/tcp6", socket.AF_INET6)):
        if not Path(table).exists():
            continue
        for line in Path(table).read_text().splitlines()[1:]:
            fields = line.split()
            address, port_hex = fields[1].split(":")
            if fields[3] != "0A" or int(port_hex, 16) != port:  # 0A: LISTEN
                continue
            raw = bytes.fromhex(address)
            raw = b"".join(raw[i : i + 4][::-1] for i in range(0, len(raw), 4))  # little-endian words
            found.add(socket.inet_ntop(family, raw))
    return found


def test_server_listens_on_loopback_only() -> None:
    if not Path("/proc/net/tcp").exists():
        pytest.skip("no /proc/net/tcp to read listening sockets from (not Linux)")
    with viz.MeshcatServer(port=0) as server:
        assert server.url == f"http://127.0.0.1:{server.address[1]}/"
        assert listening_addresses(server.address[1]) == {"127.0.0.1"}
        with urllib.request.urlopen(server.url, timeout=10) as response:
            assert response.status == 200 and b"MeshCat.Viewer" in response.read()
        # A page of another site whose name is made to resolve to 127.0.0.1 (DNS rebinding) gets nothing.
        rebound = urllib.request.Request(server.url, headers={"Host": f"attacker.example:{server.address[1]}"})
        with pytest.raises(urllib.error.HTTPError, match="403"):
            urllib.request.urlopen(rebound, timeout=10)
    # The same check sees an exposed server, which warns.
    message = "the viewer listens on '0.0.0.0': other machines that reach this one can open it"
    with pytest.warns(viz.ExposedServerWarning, match=re.escape(message)), viz.MeshcatServer("0.0.0.0", 0) as exposed:
        assert listening_addresses(exposed.address[1]) == {"0.0.0.0"}


# ---- the browser ------------------------------------------------------------------------------------------
def _unavailable(reason: str) -> None:
    if os.environ.get("CI") == "true":  # CI installs the browser: its absence is a failure there
        pytest.fail(reason)
    pytest.skip(reason)


@pytest.fixture(scope="module")
def browser() -> Iterator[Any]:
    """Debian's chromium, headless, driven by Playwright (which never downloads a browser of its own here)."""
    chromium = shutil.which("chromium")
    if chromium is None:
        _unavailable("Debian's chromium is not installed (scripts/test.sh installs it with apt-get when root)")
    try:
        from playwright.sync_api import sync_playwright
    except ImportError:
        _unavailable("playwright is not installed (pip install -e '.[test]')")
    with sync_playwright() as playwright:
        instance = playwright.chromium.launch(executable_path=chromium, args=BROWSER_ARGS, timeout=TIMEOUT_MS)
        try:
            yield instance
        finally:
            instance.close()


class Page:
    """A browser tab on one of our pages, which may reach only `allowed` URLs (everything else is aborted)."""

    def __init__(self, browser: Any, url: str, allowed: Callable[[str], bool], folder: Path):
        self.page = browser.new_page(viewport=VIEWPORT)
        self.page.set_default_timeout(TIMEOUT_MS)
        self.requests: list[str] = []
        self.blocked: list[str] = []
        self.folder = folder

        def route(r: Any) -> None:
            self.requests.append(r.request.url)
            if allowed(r.request.url):
                r.continue_()
            else:
                self.blocked.append(r.request.url)
                r.abort()

        self.page.route("**/*", route)
        self.page.goto(url)
        self.page.wait_for_function("window.multibodySim && window.multibodySim.loaded")
        assert self.page.evaluate("window.multibodySim.errors") == []
        self.page.evaluate(HIDE_DECORATIONS)  # grid, axes, controls: only the robot may differ from the background

    def shot(self, name: str) -> tuple[np.ndarray, tuple[int, int, int, int]]:
        """(screenshot as an (h, w, 3) array, view region x0, y0, x1, y1) once a frame has been drawn."""
        self.page.evaluate("window.multibodySim.rendered()")
        path = self.folder / f"{name}.png"
        self.page.screenshot(path=str(path))
        rect = self.page.evaluate(
            "(() => { const r = viewer.renderer.domElement.getBoundingClientRect(); "
            "return [r.left, r.top, r.right, r.bottom]; })()"
        )
        region = tuple(int(round(v)) for v in rect)
        return np.asarray(Image.open(path).convert("RGB"), dtype=int), region  # type: ignore[return-value]

    def close(self) -> None:
        self.page.close()


def drawn(image: np.ndarray, region: tuple[int, int, int, int]) -> float:
    """Fraction of the view covered by solid shapes that are not the background."""
    x0, y0, x1, y1 = region
    view = image[y0:y1, x0:x1]
    background = np.median(view, axis=1, keepdims=True)  # the gradient is constant along a row
    mask = ndimage.binary_erosion(np.abs(view - background).max(axis=2) > COLOR_STEP, iterations=2)
    return float(mask.mean())


def moved(a: np.ndarray, b: np.ndarray, region: tuple[int, int, int, int]) -> float:
    """Fraction of the view whose colour changed between two screenshots (solid areas only)."""
    x0, y0, x1, y1 = region
    change = np.abs(a[y0:y1, x0:x1] - b[y0:y1, x0:x1]).max(axis=2) > COLOR_STEP
    return float(ndimage.binary_erosion(change, iterations=1).mean())


def check_drawn_and_moving(shots: list[tuple[np.ndarray, tuple[int, int, int, int]]]) -> None:
    (first, region), (second, _) = shots
    assert drawn(first, region) > DRAWN_MIN and drawn(second, region) > DRAWN_MIN, (
        drawn(first, region),
        drawn(second, region),
    )
    assert moved(first, second, region) > MOVED_MIN, moved(first, second, region)


def check_empty(shots: list[tuple[np.ndarray, tuple[int, int, int, int]]]) -> None:
    """The same checks on the same page with the robot hidden: they fail, so they can."""
    (first, region), (second, _) = shots
    assert drawn(first, region) < EMPTY_MAX and drawn(second, region) < EMPTY_MAX
    assert moved(first, second, region) < EMPTY_MAX


def _offline(url: str) -> bool:
    return url.startswith(("file:", "data:", "blob:"))


def _seek_shots(page: Page, times: tuple[float, float], label: str) -> list[tuple[np.ndarray, Any]]:
    shots = []
    for t in times:
        page.page.evaluate(f"window.multibodySim.seek({t})")
        shots.append(page.shot(f"{label}_t{t:g}"))
    return shots


def test_html_export_of_an_arm_draws_and_moves(
    browser: Any, capsys: pytest.CaptureFixture[str], robot: Callable[..., ms.Robot], tmp_path: Path
) -> None:
    panda = robot("panda")
    trajectory = ms.simulate(panda, panda.neutral(), np.zeros(panda.nv), duration=2.0, dt=1e-3, output_dt=0.01)
    trajectory.save(tmp_path / "panda.npz")
    html = tmp_path / "panda.html"
    code = main(["play", str(tmp_path / "panda.npz"), "--html", str(html), "--plot"])
    out = capsys.readouterr().out
    assert code == 0 and out.startswith(f"wrote {html} (")
    text = html.read_text()
    assert "<script src=" not in text and "<link" not in text  # one file: everything inline
    page = Page(browser, html.as_uri(), _offline, tmp_path)
    try:
        assert page.blocked == [] and page.requests == [html.as_uri()]  # no network, not even a favicon
        assert page.page.evaluate("window.multibodySim.duration") == pytest.approx(2.0, abs=1e-6)
        plot = page.page.evaluate("document.getElementById('plot-image').naturalWidth")
        assert plot > 500  # the energy plot, decoded, beside the view
        check_drawn_and_moving(_seek_shots(page, (0.2, 1.5), "panda"))
        # The cursor over the plot marks the time shown (1.5 s), where matplotlib itself puts t = 1.5.
        figure = viz.plot_trajectory(trajectory, robot=panda)
        figure.savefig(io.BytesIO(), format="png")  # lays the figure out
        expected = figure.axes[0].transData.transform((1.5, 0.0))[0] / (figure.get_figwidth() * figure.dpi)
        cursor = page.page.evaluate(
            "(() => { const c = document.getElementById('plot-cursor').getBoundingClientRect();"
            " const i = document.getElementById('plot-image').getBoundingClientRect();"
            " return (c.left + c.width / 2 - i.left) / i.width; })()"
        )
        assert cursor == pytest.approx(expected, abs=0.004)  # within 2 px of 500
        page.page.evaluate(HIDE_ROBOT)
        check_empty(_seek_shots(page, (0.2, 1.5), "panda_empty"))
    finally:
        page.close()


def test_html_export_of_a_floating_legged_robot_draws_and_moves(
    browser: Any, robot: Callable[..., ms.Robot], tmp_path: Path
) -> None:
    solo = robot("solo12")
    v0 = np.zeros(solo.nv)
    v0[2], v0[3:6], v0[6:] = 3.0, [0.5, 1.0, 0.3], 2.0  # thrown up, spinning, legs swinging
    trajectory = ms.simulate(solo, solo.neutral(), v0, duration=0.6, dt=1e-3, output_dt=0.01)
    html = viz.export_html(trajectory, tmp_path / "solo12.html")  # the robot reloaded from the metadata
    page = Page(browser, html.as_uri() + "#t=0.5", _offline, tmp_path)  # opens paused at 0.5 s
    try:
        assert page.blocked == []
        # The page shows the recorded motion: the base's height at 0.5 s, read from the scene the page drew.
        height = page.page.evaluate("viewer.scene_tree.find(['meshcat', 'robot', 'root_joint']).object.position.z")
        times, frames = viz.resample(solo, trajectory, 30.0)
        assert height == pytest.approx(np.interp(0.5, times, frames[:, 2]), abs=1e-3)
        assert abs(height - frames[0, 2]) > 0.1  # far from where it started: the check can tell
        check_drawn_and_moving(_seek_shots(page, (0.1, 0.5), "solo12"))
        page.page.evaluate(HIDE_ROBOT)
        check_empty(_seek_shots(page, (0.1, 0.5), "solo12_empty"))
    finally:
        page.close()


def test_live_server_page_draws_and_moves(browser: Any, robot: Callable[..., ms.Robot], tmp_path: Path) -> None:
    ur5 = robot("ur5")
    with viz.Viewer(ur5, port=0, announce=False) as viewer:
        port = viewer.server.address[1]
        if Path("/proc/net/tcp").exists():
            assert listening_addresses(port) == {"127.0.0.1"}
        origin = f"http://127.0.0.1:{port}/"
        page = Page(browser, viewer.url, lambda url: url.startswith(origin), tmp_path)
        try:
            assert page.blocked == []

            def show(q: np.ndarray, name: str) -> tuple[np.ndarray, Any]:
                viewer.display(q)
                page.page.wait_for_function(f"window.multibodySim.frame >= {viewer._frame - 1}")
                return page.shot(name)

            poses = (ur5.neutral(), np.array([0.0, -1.2, 1.5, 0.0, 0.5, 0.0]))
            check_drawn_and_moving([show(q, f"live{k}") for k, q in enumerate(poses)])
            page.page.evaluate(HIDE_ROBOT)
            check_empty([show(q, f"live_empty{k}") for k, q in enumerate(poses)])
        finally:
            page.close()


# ---- notebooks ---------------------------------------------------------------------------------------------
NOTEBOOK_CELLS = (
    "import numpy as np\nimport multibody_sim as ms\nfrom multibody_sim import viz\n"
    "robot = ms.load_robot('free_body')\nv0 = np.array([0.0, 0.0, 1.0, 3.0, 1.0, 0.0])\n"
    "traj = ms.simulate(robot, robot.neutral(), v0, duration=0.2, dt=1e-3, output_dt=0.01)",
    "traj.show(height=400)",
    "viewer = viz.Viewer(robot, port=0, announce=False)\nviewer.show(height=400)",
)


def _notebook_frame(page: Any, index: int, tmp_path: Path) -> tuple[np.ndarray, tuple[int, int, int, int]]:
    """The index-th iframe of the page once its viewer has drawn everything: (screenshot, whole-image region)."""
    handle = page.locator("iframe").nth(index)
    frame = handle.element_handle().content_frame()
    frame.wait_for_function("window.multibodySim && window.multibodySim.loaded", timeout=TIMEOUT_MS)
    assert frame.evaluate("window.multibodySim.errors") == []
    frame.evaluate("window.multibodySim.seek(0.1)")  # a recording stops playing (and drawing every frame)
    frame.evaluate(HIDE_DECORATIONS)
    frame.evaluate("window.multibodySim.rendered()")
    path = tmp_path / f"cell{index}.png"
    handle.screenshot(path=str(path), timeout=TIMEOUT_MS)
    image = np.asarray(Image.open(path).convert("RGB"), dtype=int)
    return image, (0, 0, image.shape[1], image.shape[0])


def test_a_notebook_shows_a_recording_offline_and_the_live_viewer(browser: Any, tmp_path: Path) -> None:
    """A real notebook executed headless by nbclient in an ipykernel; its outputs, put in a page as a notebook
    front end does, open in chromium: the recording with no network at all, the live viewer from its server."""
    missing = [m for m in ("nbformat", "nbclient", "ipykernel") if importlib.util.find_spec(m) is None]
    if missing:
        _unavailable(f"the notebook test needs {', '.join(missing)} (pip install -e '.[test]')")
    import nbclient
    import nbformat

    notebook = nbformat.v4.new_notebook()
    film = tmp_path / "from_the_kernel.gif"  # Playwright's synchronous API inside the kernel's event loop
    video = f"viz.export_video(traj, {str(film)!r}, fps=10, width=160, height=120)"
    notebook.cells = [nbformat.v4.new_code_cell(source) for source in (*NOTEBOOK_CELLS, video)]
    client = nbclient.NotebookClient(notebook, timeout=120, kernel_name="python3")
    with client.setup_kernel():  # the kernel, and the viewer's server in it, live until the checks are done
        for index, cell in enumerate(notebook.cells):
            client.execute_cell(cell, index)
        recording, live = (notebook.cells[k].outputs for k in (1, 2))
        assert Image.open(film).n_frames == 2  # 0.2 s at 10 fps: two frames, the box moving between them
        assert [o["output_type"] for o in recording] == ["display_data"] == [o["output_type"] for o in live]
        inline, served = recording[0]["data"]["text/html"], live[0]["data"]["text/html"]
        assert inline.startswith('<iframe srcdoc="&lt;!DOCTYPE html&gt;') and "<script" not in inline
        assert recording[0]["data"]["text/plain"].startswith("<InlineView free_body, t = 0..0.2 s, ")
        url = re.search(r'src="(http://127\.0\.0\.1:\d+/)"', served).group(1)  # type: ignore[union-attr]
        front_end = tmp_path / "notebook.html"
        front_end.write_text(f"<!DOCTYPE html><html><body>{inline}<hr>{served}</body></html>")
        page = browser.new_page(viewport={"width": 900, "height": 900})
        page.set_default_timeout(TIMEOUT_MS)
        requests: list[str] = []

        def route(r: Any) -> None:
            requests.append(r.request.url)
            r.continue_() if r.request.url.startswith((front_end.as_uri(), url)) else r.abort()

        page.route("**/*", route)
        try:
            page.goto(front_end.as_uri())
            shots = [_notebook_frame(page, index, tmp_path) for index in (0, 1)]
            offline = [r for r in requests if not r.startswith(url)]
            assert offline == [front_end.as_uri()]  # the recording fetched nothing: it is all in the srcdoc
            for image, region in shots:
                assert drawn(image, region) > DRAWN_MIN, drawn(image, region)
            for index in (0, 1):  # the same check on the same frames with the robot hidden: it can fail
                page.locator("iframe").nth(index).element_handle().content_frame().evaluate(HIDE_ROBOT)
                image, region = _notebook_frame(page, index, tmp_path)
                assert drawn(image, region) < EMPTY_MAX
        finally:
            page.close()


def test_show_outside_a_notebook_says_where_it_works(robot: Callable[..., ms.Robot]) -> None:
    pendulum = robot("pendulum")
    trajectory = ms.simulate(pendulum, [0.5], [0.0], duration=0.1, dt=0.01)
    message = (
        "show() displays inline in a Jupyter notebook, and none is running; elsewhere write a page with "
        "multibody_sim.viz.export_html(trajectory, 'motion.html') or run `multibody-sim play`"
    )
    with pytest.raises(ms.MissingDependencyError) as caught:
        trajectory.show()
    assert str(caught.value) == message
    with pytest.raises(
        ms.InvalidArgumentError, match=re.escape("height must be a number of pixels of at least 100, got 20")
    ):
        viz.inline_view(trajectory, robot=pendulum, height=20)
    view = viz.inline_view(trajectory, robot=pendulum, height=250)
    assert view._repr_html_().endswith('style="width: 100%; height: 250px; border: 0" allowfullscreen></iframe>')
    with viz.Viewer(pendulum, port=0, announce=False) as viewer:
        assert viewer._repr_html_() == (
            f'<iframe src="{viewer.url}" title="multibody-sim viewer" style="width: 100%; height: 480px; border: 0" '
            "allowfullscreen></iframe>"
        )


def test_run_view_streams_the_run_in_real_time(
    browser: Any, capsys: pytest.CaptureFixture[str], tmp_path: Path
) -> None:
    with socket.socket() as probe:  # a free port for --view-port (the command prints it too)
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
    argv = ["run", "double_pendulum", "--duration", "1", "--q0", "2", "0", "--view", "--view-port", str(port)]
    argv += ["--view-speed", "0.5", "--out", str(tmp_path / "run.npz")]
    result: list[int] = []
    thread = threading.Thread(target=lambda: result.append(main(argv)), daemon=True)
    thread.start()
    deadline = time.monotonic() + 60
    while not listening_addresses(port) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert listening_addresses(port) == {"127.0.0.1"}
    page = Page(browser, f"http://127.0.0.1:{port}/", lambda url: url.startswith(f"http://127.0.0.1:{port}/"), tmp_path)
    try:
        page.page.wait_for_function("window.multibodySim.time === 1")  # the last frame
        received = page.page.evaluate("window.multibodySim.received")  # [page clock, frame time] per frame
        thread.join(timeout=30)
    finally:
        page.close()
    assert result == [0]
    out = capsys.readouterr().out
    assert f"view: http://127.0.0.1:{port}/" in out.splitlines()
    clock, shown = np.array([r for r in received if r[1] is not None]).T
    assert np.all(np.diff(shown) > 0)  # frames in order, time never running backwards
    assert shown[-1] == 1.0 and len(shown) >= 10  # 30 fps over 2 s, some skipped only if the machine lags
    # --view-speed 0.5: half a simulated second per second (the pacing itself is tested without a browser: a
    # busy page receives frames in bursts).
    rate = (shown[-1] - shown[0]) / (clock[-1] - clock[0])
    assert 0.3 < rate < 0.75, [(round(c, 3), t) for c, t in received]


def _paced(viewer: Any, monkeypatch: pytest.MonkeyPatch, send_cost: float) -> list[tuple[float, float]]:
    """(wall clock, frame time) of every frame marker the viewer sends; each send costs `send_cost` seconds."""
    sent: list[tuple[float, float]] = []
    send = viewer.server.send

    def recording(command: dict[str, Any]) -> None:
        if command["type"] == "multibody_sim_frame":
            time.sleep(send_cost)
            sent.append((time.perf_counter(), command["time"]))
        send(command)

    monkeypatch.setattr(viewer.server, "send", recording)
    return sent


@pytest.mark.parametrize(("speed", "send_cost"), [(2.0, 0.0), (1.0, 0.06)])
def test_play_keeps_to_the_clock(
    speed: float, send_cost: float, robot: Callable[..., ms.Robot], monkeypatch: pytest.MonkeyPatch
) -> None:
    """Frames go out at their time / speed, never early; when sending is slower than the frame rate (60 ms for
    33 ms frames), frames are skipped and the playback still ends on time."""
    pendulum = robot("pendulum")
    trajectory = ms.simulate(pendulum, [1.0], [0.0], duration=1.0, dt=1e-3)
    with viz.Viewer(pendulum, port=0, announce=False) as viewer:
        sent = _paced(viewer, monkeypatch, send_cost)
        started = time.perf_counter()
        shown = viewer.play(trajectory, speed=speed, fps=30.0)
    wall, times = np.array(sent).T
    assert shown == len(sent) and times[-1] == 1.0 and np.all(np.diff(times) > 0)
    due = started + times / speed
    assert np.all(wall - send_cost >= due - 2e-3)  # never ahead of the clock
    assert wall[-1] - started == pytest.approx(1.0 / speed + send_cost, abs=0.15)  # ends on time
    if send_cost:
        assert len(sent) < 0.75 * 31  # frames were skipped to keep up
    else:
        assert len(sent) == 31


# ---- commands -----------------------------------------------------------------------------------------------
def call(capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str, str]:
    code = main(list(args))
    captured = capsys.readouterr()
    return code, captured.out, captured.err


@pytest.fixture
def pendulum_run(tmp_path: Path) -> tuple[Path, Path]:
    """(trajectory file, its URDF): a pendulum from a URDF copied into the test's folder."""
    urdf = _pendulum_copy(tmp_path)
    trajectory = ms.simulate(ms.load_robot(urdf), [0.5], [0.0], duration=0.5, dt=0.01)
    return trajectory.save(tmp_path / "run.npz"), urdf


def test_play_html_writes_one_file(
    capsys: pytest.CaptureFixture[str], pendulum_run: tuple[Path, Path], tmp_path: Path
) -> None:
    run, _ = pendulum_run
    html = tmp_path / "out" / "pendulum.html"
    code, out, err = call(capsys, "play", str(run), "--html", str(html), "--fps", "10")
    assert (code, err) == (0, "")
    assert re.fullmatch(rf"wrote {re.escape(str(html))} \(\d+\.\d MB in \d+\.\d s\): opens from disk, offline\n", out)
    assert html.stat().st_size < 2_000_000  # the viewer's JavaScript and two primitives


@pytest.mark.parametrize(
    ("make", "message"),
    [
        (lambda d: d / "missing.npz", "{path}: no such trajectory file"),
        (
            lambda d: (d / "notes.npz", (d / "notes.npz").write_text("not a trajectory"))[0],
            "{path}: not a trajectory file (not an .npz archive)",
        ),
    ],
)
@pytest.mark.parametrize("command", [["play"], ["play", "--html", "x.html"], ["plot"]])
def test_commands_refuse_bad_files(
    capsys: pytest.CaptureFixture[str], tmp_path: Path, make: Callable[[Path], Path], message: str, command: list[str]
) -> None:
    path = make(tmp_path)
    argv = [command[0], str(path), *command[1:]]
    if "--html" in argv:
        argv[-1] = str(tmp_path / "x.html")
    code, out, err = call(capsys, *argv)
    assert (code, out) == (2, "")
    assert err == PREFIX + message.format(path=path) + "\n"


def test_play_draws_a_skeleton_when_a_mesh_is_missing(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    text = (SHIPPED / "pendulum" / "pendulum.urdf").read_text()
    text = text.replace('<sphere radius="0.05"/>', '<mesh filename="meshes/bob.stl"/>')  # no such file
    urdf = tmp_path / "pendulum.urdf"
    urdf.write_text(text)
    run = ms.simulate(ms.load_robot(urdf), [0.5], [0.0], duration=0.1, dt=0.01).save(tmp_path / "run.npz")
    html = tmp_path / "run.html"
    code, out, err = call(capsys, "play", str(run), "--html", str(html))
    assert code == 0 and html.is_file()
    assert err == (
        f"multibody-sim: warning: {urdf}: Pinocchio cannot build the visual model (Mesh meshes/bob.stl could not "
        "be found.); drawing a skeleton\n"
    )


def test_play_refuses_a_changed_urdf(
    capsys: pytest.CaptureFixture[str], pendulum_run: tuple[Path, Path], tmp_path: Path
) -> None:
    run, urdf = pendulum_run
    old = hashlib.sha256(urdf.read_bytes()).hexdigest()
    urdf.write_text(urdf.read_text().replace('radius="0.05"', 'radius="0.08"'))
    new = hashlib.sha256(urdf.read_bytes()).hexdigest()
    code, out, err = call(capsys, "play", str(run), "--html", str(tmp_path / "x.html"))
    assert (code, out) == (2, "")
    assert err == (
        f"{PREFIX}{urdf}: the URDF changed since the trajectory was recorded (SHA-256 {new[:12]}... instead of "
        f"{old[:12]}...); the motion would be shown on a different robot\n"
    )
    assert not (tmp_path / "x.html").exists()


def test_play_without_meshcat_says_what_to_install(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, pendulum_run: tuple[Path, Path], tmp_path: Path
) -> None:
    run, _ = pendulum_run
    monkeypatch.setitem(sys.modules, "meshcat", None)  # what `import meshcat` sees when it is not installed
    expected = (
        f"{PREFIX}the meshcat viewer needs the 'meshcat' package, which is not installed "
        "(pip install 'multibody-sim[viz]')\n"
    )
    for argv in (["play", str(run)], ["play", str(run), "--html", str(tmp_path / "x.html")]):
        code, out, err = call(capsys, *argv)
        assert (code, out, err) == (2, "", expected)
    code, out, err = call(capsys, "run", "pendulum", "--duration", "0.01", "--view")
    assert (code, out, err) == (2, "", expected)  # refused before simulating


def test_run_view_refuses_a_bad_speed(capsys: pytest.CaptureFixture[str]) -> None:
    code, out, err = call(capsys, "run", "pendulum", "--view", "--view-speed", "-1")
    assert (code, out, err) == (
        2,
        "",
        f"{PREFIX}--view-speed must be a number from 0.001 to 1000 (1 = real time), got -1\n",
    )


def test_play_serves_until_interrupted(
    capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, pendulum_run: tuple[Path, Path]
) -> None:
    """`play` without --html serves the page on 127.0.0.1 until Ctrl-C, which closes it with exit code 0."""
    import multibody_sim.cli as cli

    seen: dict[str, Any] = {}

    def ctrl_c(seconds: float) -> None:  # the command waits in time.sleep: the user presses Ctrl-C there
        out = capsys.readouterr().out
        seen["out"] = out
        port = int(re.search(r"view: open http://127\.0\.0\.1:(\d+)/ in a browser", out).group(1))  # type: ignore[union-attr]
        seen["port"] = port
        seen["listening"] = listening_addresses(port)
        with urllib.request.urlopen(f"http://127.0.0.1:{port}/", timeout=10) as response:
            seen["page"] = response.read().decode()
        raise KeyboardInterrupt

    monkeypatch.setattr(cli.view.time, "sleep", ctrl_c)
    run, _ = pendulum_run
    code = main(["play", str(run), "--port", "0"])
    assert code == 0
    assert "play: pendulum, 51 samples, t = 0..0.5 s" in seen["out"]
    assert "<title>pendulum - multibody-sim</title>" in seen["page"]
    if Path("/proc/net/tcp").exists():
        assert seen["listening"] == {"127.0.0.1"}
        assert listening_addresses(seen["port"]) == set()  # closed on the way out


def test_a_warning_shown_again_while_warnings_are_recorded_is_shown_once():
    """The command line records the viewer's warnings and shows the others again as Python would: it does so once
    recording has ended. Shown while still recording, each was recorded again, into the list being read, until
    memory ran out (an overflow warning from a camera near 1e308). In a child process with 3 GiB of address space."""
    code = (
        "import resource, warnings\n"
        "resource.setrlimit(resource.RLIMIT_AS, (3 * 2**30, 3 * 2**30))\n"
        "from multibody_sim import cli, viz\n"
        "with cli.view.viewer_warnings(viz):\n"
        "    warnings.warn('overflow here', RuntimeWarning)\n"
        "print('done')\n"
    )
    result = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert (result.returncode, result.stdout) == (0, "done\n"), result.stderr[-2000:]
    assert result.stderr.count("RuntimeWarning: overflow here") == 1, result.stderr[-2000:]
