"""Contact scenes in the viewer: the ground, the objects and the declared collision shapes are drawn, and the
objects move as recorded (an HTML export, opened in Debian's chromium as the viewer's own tests do)."""

from __future__ import annotations

import dataclasses
import re
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
import pytest
from test_viz import HIDE_ROBOT, Page, _offline, _seek_shots, browser, check_drawn_and_moving, check_empty, moved

import multibody_sim as ms
from multibody_sim import viz
from multibody_sim.exceptions import InvalidArgumentError
from multibody_sim.viz.scene import ROOT, RobotScene

__all__ = ["browser"]  # the fixture, shared with test_viz


def test_a_contact_scene_draws_its_ground_objects_and_collision_shapes() -> None:
    pytest.importorskip("trimesh")
    scene = ms.load_scene("panda_push")
    drawn = RobotScene(scene)
    paths = [v.path for v in drawn.visuals]
    assert any(path.startswith(f"{ROOT}/box/contact_") for path in paths)  # the object, on its own body
    assert any("contact_" in path and "panda_hand" in path for path in paths)  # the sphere between the fingers
    assert [f.path for f in drawn.fixtures] == [f"{ROOT}/ground/000"]  # the ground, welded to the world
    top = drawn.fixtures[0].placement[2, 3] + max(p.bounds()[1][2] for p in drawn.fixtures[0].parts)
    assert top == pytest.approx(0.0, abs=1e-9)  # its top face is the plane z = 0
    objects_only = RobotScene(ms.load_scene("box_stack"))
    assert objects_only.notes == []  # no robot: nothing missing, no skeleton
    assert len(objects_only.visuals) == 3 and len(objects_only.fixtures) == 1


def test_html_export_of_a_sliding_box_draws_and_moves(browser: Any, tmp_path: Path) -> None:
    scene = ms.load_scene("sliding_box")
    trajectory = scene.run(output_dt=0.01, progress=False)
    html = viz.export_html(trajectory, tmp_path / "box.html")  # the scene rebuilt from the trajectory's metadata
    page = Page(browser, html.as_uri() + "#t=0.1", _offline, tmp_path)
    try:
        assert page.blocked == []
        x = page.page.evaluate("viewer.scene_tree.find(['meshcat', 'robot', 'box']).object.position.x")
        times, frames = viz.resample(scene, trajectory, 30.0)
        assert x == pytest.approx(np.interp(0.1, times, frames[:, 0]), abs=1e-3)
        assert x > 0.1  # it slid: the check can tell
        ground = page.page.evaluate("viewer.scene_tree.find(['meshcat', 'robot', 'ground']).object.children.length")
        assert ground == 1
        check_drawn_and_moving(_seek_shots(page, (0.0, 0.25), "box"))
        page.page.evaluate(HIDE_ROBOT)
        check_empty(_seek_shots(page, (0.0, 0.25), "box_empty"))
    finally:
        page.close()


def check_arrows(
    page: Page, trajectory: ms.Trajectory, t: float, *, sliding: bool = True, largest: float | None = None
) -> None:
    """The page shows one arrow per contact point of the sample on display at t, along its force (friction back,
    the normal force up: the direction (−μ, 0, 1) while the box slides), a force of `largest` (default: the largest
    of the run) ARROW_LENGTH long; and hiding the arrows changes the picture (they are drawn, not only placed)."""
    from multibody_sim.viz.forces import ARROW_LENGTH

    i = int(np.searchsorted(trajectory.t, t + 1e-9, side="right") - 1)
    shown = trajectory.contacts.at(i)
    assert len(shown.sample) == 4
    dt = trajectory.metadata["options"]["dt"]
    forces = shown.impulse / dt
    if largest is None:
        largest = np.linalg.norm(trajectory.contacts.impulse, axis=1).max() / dt
    for k in range(4):
        node = f"viewer.scene_tree.find(['meshcat', 'forces', '{k}']).object"
        position = page.page.evaluate(f"{node}.position.toArray()")
        length = page.page.evaluate(f"{node}.scale.z")
        x, y, z, w = page.page.evaluate(f"{node}.quaternion.toArray()")
        axis = pin.Quaternion(w, x, y, z).matrix()[:, 2]  # where the arrow's +z points
        np.testing.assert_allclose(position, shown.point[k], atol=1e-3)  # the box moves 2 cm per frame
        assert length == pytest.approx(ARROW_LENGTH * np.linalg.norm(forces[k]) / largest, rel=1e-3)
        direction = forces[k] / np.linalg.norm(forces[k])
        np.testing.assert_allclose(axis, direction, atol=1e-6)
        if sliding:
            np.testing.assert_allclose(direction, np.array([-0.8, 0.0, 1.0]) / np.hypot(0.8, 1.0), atol=1e-6)
    with_arrows = page.shot(f"arrows_t{t:g}")
    page.page.evaluate("viewer.scene_tree.find(['meshcat', 'forces']).object.visible = false; viewer.set_dirty();")
    without = page.shot(f"no_arrows_t{t:g}")
    page.page.evaluate("viewer.scene_tree.find(['meshcat', 'forces']).object.visible = true; viewer.set_dirty();")
    assert moved(with_arrows[0], without[0], with_arrows[1]) > ARROWS_MIN


ARROWS_MIN = 0.002  # fraction of the view the four arrows cover at least (about 1500 px; they cover ~0.01)


def test_html_export_draws_contact_forces_as_arrows(browser: Any, tmp_path: Path) -> None:
    """With forces=True each contact point of the sample shown carries an arrow along its force."""
    scene = ms.load_scene("sliding_box")
    trajectory = scene.run(duration=0.2, output_dt=0.01, progress=False)
    html = viz.export_html(trajectory, tmp_path / "forces.html", forces=True)
    page = Page(browser, html.as_uri() + "#t=0.1", _offline, tmp_path)
    try:
        check_arrows(page, trajectory, 0.1)
        check_drawn_and_moving(_seek_shots(page, (0.05, 0.15), "forces"))
    finally:
        page.close()


def test_live_viewer_draws_the_ground_and_contact_forces_as_arrows(browser: Any, tmp_path: Path) -> None:
    """The meshcat server's page: the ground; the arrows animated with the recording (animate) and moved frame by
    frame when it is streamed (play); a later motion without forces removes them."""
    scene = ms.load_scene("sliding_box")
    trajectory = scene.run(duration=0.2, output_dt=0.01, progress=False)
    with viz.Viewer(scene, port=0, announce=False) as viewer:
        viewer.animate(trajectory, play=False, seek=0.1, forces=True)  # kept by the server for the page to come
        origin = f"http://127.0.0.1:{viewer.server.address[1]}/"
        page = Page(browser, viewer.url, lambda url: url.startswith(origin), tmp_path)
        try:
            assert page.blocked == []
            ground = "viewer.scene_tree.find(['meshcat', 'robot', 'ground']).object.children.length"
            assert page.page.evaluate(ground) == 1
            check_arrows(page, trajectory, 0.1)
            viewer.play(trajectory, speed=2.0, forces=True)  # streamed: the last frame shows the last sample
            page.page.wait_for_function(f"window.multibodySim.frame >= {viewer._frame - 1}")
            check_arrows(page, trajectory, 0.2)
            viewer.play(trajectory, speed=4.0)  # no forces asked: the arrows are gone
            page.page.wait_for_function(f"window.multibodySim.frame >= {viewer._frame - 1}")
            assert page.page.evaluate("viewer.scene_tree.find(['meshcat', 'forces']).object.children.length") == 0
        finally:
            page.close()
        with pytest.raises(InvalidArgumentError, match="^the trajectory records no contacts"):
            viewer.animate(dataclasses.replace(trajectory, contacts=None), forces=True)


def test_a_live_run_draws_its_contact_forces_as_it_computes(browser: Any, tmp_path: Path) -> None:
    """Viewer.live(forces=True) as a run's on_sample: the arrows follow the run as it computes (mid-run, the
    sample on display), an arrow ARROW_LENGTH long for the box's weight (the run's largest force is not known
    yet); without forces the callback takes no contacts and no arrow is drawn."""
    scene = ms.load_scene("sliding_box")
    weight = 1.0 * 9.81  # the sliding box: 1 kg (its scene file), standard gravity
    assert pin.computeTotalMass(scene.model) == pytest.approx(1.0)
    with viz.Viewer(scene, port=0, announce=False) as viewer:
        origin = f"http://127.0.0.1:{viewer.server.address[1]}/"
        page = Page(browser, viewer.url, lambda url: url.startswith(origin), tmp_path)
        try:
            from multibody_sim.viz.forces import ARROW_LENGTH

            live = viewer.live(forces=True)
            handed: list[np.ndarray] = []
            seen: list[tuple[float, list[float], float]] = []

            def contacts(rows: np.ndarray | None, dt: float) -> None:
                handed.append(rows)
                live.contacts(rows, dt)

            def watched(t: float, q: np.ndarray, v: np.ndarray) -> None:
                before = live.shown
                live(t, q, v)
                if not seen and live.shown != before and t >= 0.05:  # mid-run: the frame just sent, with its arrows
                    page.page.wait_for_function(f"window.multibodySim.frame >= {viewer._frame - 1}")
                    node = "viewer.scene_tree.find(['meshcat', 'forces', '0']).object"
                    seen.append(
                        (t, page.page.evaluate(f"{node}.position.toArray()"), page.page.evaluate(f"{node}.scale.z"))
                    )

            watched.wants_contacts = True  # type: ignore[attr-defined]  # hand the contacts on to the live view
            watched.contacts = contacts  # type: ignore[attr-defined]
            trajectory = ms.simulate(
                scene, scene.q0, scene.v0, duration=0.1, dt=1e-3, integrator="timestepping", on_sample=watched
            )
            assert len(handed) == len(trajectory.t) and handed[0] is None  # sample 0 has no step behind it
            t, position, length = seen[0]
            i = int(np.flatnonzero(trajectory.t == t)[0])
            first = trajectory.contacts.at(i)
            np.testing.assert_allclose(position, first.point[0], atol=1e-9)
            assert length == pytest.approx(ARROW_LENGTH * np.linalg.norm(first.impulse[0]) / 1e-3 / weight, rel=1e-6)
            live.finish(trajectory)
            page.page.wait_for_function(f"window.multibodySim.frame >= {viewer._frame - 1}")
            check_arrows(page, trajectory, 0.1, largest=weight)
            plain = viewer.live()
            assert not plain.wants_contacts
            ms.simulate(scene, scene.q0, scene.v0, duration=0.02, dt=1e-3, integrator="timestepping", on_sample=plain)
            page.page.wait_for_function(f"window.multibodySim.frame >= {viewer._frame - 1}")
            assert page.page.evaluate("viewer.scene_tree.find(['meshcat', 'forces']).object.children.length") == 0
        finally:
            page.close()


def test_play_forces_serves_the_arrows_and_the_commands_refuse_runs_without_contact(
    browser: Any, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, tmp_path: Path
) -> None:
    """`play RUN.npz --forces` serves the arrows (checked in the page it serves, while it waits for Ctrl-C);
    --forces and --view-forces on a run without contact, or --view-forces without --view, are refused in one
    line."""
    import multibody_sim.cli as cli

    scene = ms.load_scene("sliding_box")
    trajectory = scene.run(duration=0.2, output_dt=0.01, progress=False)
    run = trajectory.save(tmp_path / "box.npz")
    seen: list[bool] = []

    def ctrl_c(seconds: float) -> None:  # the command waits in time.sleep: the page is checked there
        port = int(re.search(r"view: open http://127\.0\.0\.1:(\d+)/", capsys.readouterr().out).group(1))  # type: ignore[union-attr]
        origin = f"http://127.0.0.1:{port}/"
        page = Page(browser, origin, lambda url: url.startswith(origin), tmp_path)
        try:
            page.page.evaluate("window.multibodySim.seek(0.1)")
            check_arrows(page, trajectory, 0.1)
            seen.append(True)
        finally:
            page.close()
        raise KeyboardInterrupt

    monkeypatch.setattr(cli.view.time, "sleep", ctrl_c)
    assert cli.main(["play", str(run), "--port", "0", "--forces"]) == 0
    assert seen == [True]
    monkeypatch.undo()

    pendulum = ms.simulate(ms.load_robot("pendulum"), [1.0], [0.0], duration=0.01, dt=1e-3)
    plain = pendulum.save(tmp_path / "pendulum.npz")
    prefix = "multibody-sim: error: "
    for argv, message in [
        (
            ["play", str(plain), "--forces", "--html", str(tmp_path / "p.html")],
            f"--forces: {plain} records no contacts (forces are drawn for runs of scenes with contact)",
        ),
        (["run", "sliding_box", "--view-forces"], "--view-forces draws contact forces in the --view page: add --view"),
        (
            ["run", "pendulum", "--view", "--view-forces"],
            "--view-forces draws contact forces, and this run has no contact (run a scene with [ground], [contact] "
            "or [[object]], e.g. sliding_box)",
        ),
    ]:
        assert cli.main(argv) == 2
        captured = capsys.readouterr()
        assert (captured.out, captured.err) == ("", prefix + message + "\n")


def test_a_video_draws_the_forces_when_asked(browser: Any, tmp_path: Path) -> None:
    """The same frame filmed with and without forces=True differs by the arrows (sample 0 has no contact yet: the
    frame at 0.1 s is compared)."""
    from PIL import Image

    trajectory = ms.load_scene("sliding_box").run(duration=0.2, output_dt=0.01, progress=False)
    last = []
    for forces in (False, True):
        out = viz.export_video(
            trajectory, tmp_path / f"box_{forces}.gif", fps=10, width=320, height=240, progress=False, forces=forces
        )
        image = Image.open(out)
        assert image.n_frames == 2  # t = 0 and 0.1 s
        image.seek(1)
        last.append(np.asarray(image.convert("RGB"), dtype=int))
    changed = np.abs(last[1] - last[0]).max(axis=2) > 40
    assert changed.sum() > 100  # the four arrows: ~0.01 of the view, ~800 px at 320x240
