"""Contact scenes in the viewer: the ground, the objects and the declared collision shapes are drawn, and the
objects move as recorded (an HTML export, opened in Debian's chromium as the viewer's own tests do)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
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
