"""Contact scenes in the viewer: the ground, the objects and the declared collision shapes are drawn, and the
objects move as recorded (an HTML export, opened in Debian's chromium as the viewer's own tests do)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
import pytest
from test_viz import HIDE_ROBOT, Page, _offline, _seek_shots, browser, check_drawn_and_moving, check_empty

import multibody_sim as ms
from multibody_sim import viz
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


def test_html_export_draws_contact_forces_as_arrows(browser: Any, tmp_path: Path) -> None:
    """With forces=True each contact point of the sample shown carries an arrow along its force (friction back,
    the normal force up: the direction (−μ, 0, 1)), the largest force of the run ARROW_LENGTH long."""
    from multibody_sim.viz.forces import ARROW_LENGTH

    scene = ms.load_scene("sliding_box")
    trajectory = scene.run(duration=0.2, output_dt=0.01, progress=False)
    html = viz.export_html(trajectory, tmp_path / "forces.html", forces=True)
    page = Page(browser, html.as_uri() + "#t=0.1", _offline, tmp_path)
    try:
        i = int(np.searchsorted(trajectory.t, 0.1, side="right") - 1)
        shown = trajectory.contacts.at(i)
        assert len(shown.sample) == 4
        forces = shown.impulse / trajectory.metadata["options"]["dt"]
        largest = np.linalg.norm(trajectory.contacts.impulse, axis=1).max() / trajectory.metadata["options"]["dt"]
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
            np.testing.assert_allclose(direction, np.array([-0.8, 0.0, 1.0]) / np.hypot(0.8, 1.0), atol=1e-6)
        check_drawn_and_moving(_seek_shots(page, (0.05, 0.15), "forces"))
    finally:
        page.close()
