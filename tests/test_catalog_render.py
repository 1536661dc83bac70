"""Every catalog robot renders: a short run from its default pose exported as HTML (meshcat's page, offline) and
opened in Debian's headless chromium draws the robot. Slow (a page per robot): `bash scripts/test.sh -m slow`."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from test_catalog_robots import STEPS, stable_dt
from test_viz import EMPTY_MAX, Page, _offline, browser, drawn, viz  # noqa: F401  (browser is a fixture)

import multibody_sim as ms

pytestmark = pytest.mark.slow
# Something solid is drawn: 4 times what an empty view shows at most (about 1600 px of the 1024 x 768 view; the
# thin pendulum, framed whole, covers 2500).
RENDERED_MIN = 4 * EMPTY_MAX


@pytest.mark.parametrize("name", sorted(ms.CATALOG))
def test_every_catalog_robot_renders(
    browser: Any,  # noqa: F811  (test_viz's fixture, imported above)
    robot: Callable[..., ms.Robot],
    name: str,
    tmp_path: Path,
) -> None:
    loaded = robot(name)
    q0 = loaded.default_pose()
    dt = stable_dt(loaded, q0)
    trajectory = ms.simulate(loaded, q0, np.zeros(loaded.nv), duration=STEPS * dt, dt=dt)
    html = viz.export_html(trajectory, tmp_path / f"{name}.html")  # the robot reloaded from the metadata
    page = Page(browser, html.as_uri(), _offline, tmp_path)  # waits for the page's "loaded" flag, no errors
    try:
        assert page.blocked == []
        image, region = page.shot(name)
        assert drawn(image, region) > RENDERED_MIN, drawn(image, region)
    finally:
        page.close()
