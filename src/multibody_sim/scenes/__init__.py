"""Scenes: declared physics (locks, springs, friction, forces, payloads, constraints) on a robot.

A scene is a TOML file (``load_scene``) or the same tables in Python (``make_scene``); the resulting Scene is a
Robot wherever one is accepted, and ``Scene.run()`` runs it with its own [simulation] and [controller] settings.
"""

from __future__ import annotations

import dataclasses
import os
from pathlib import Path
from typing import Any

from ..catalog import shipped_models_dir
from ..exceptions import SceneError
from .scene import Scene
from .spec import SceneSpec, parse_scene, read_scene_file

__all__ = ["SCENE_PREFIX", "Scene", "SceneSpec", "load_scene", "make_scene", "scene_from_metadata", "shipped_scenes"]


def shipped_scenes() -> dict[str, Path]:
    """The scenes shipped in models/scenes/, by name (the file's stem): `multibody-sim models` lists them."""
    folder = shipped_models_dir() / "scenes"
    return {path.stem: path for path in sorted(folder.glob("*.toml"))}


SCENE_PREFIX = "scene:"


def load_scene(path: str | os.PathLike[str]) -> Scene:
    """Read a scene file (TOML), or a shipped scene by name, and build its Scene.

    Args:
        path: a scene file, or the name of a shipped scene (`multibody-sim models` lists them), with or
            without ".toml"; a leading "scene:" is allowed (the CLI's way to name a scene explicitly).

    Scene files are untrusted input like URDFs: size-limited, parsed without executing anything, and every key
    checked before anything is built.

    Raises:
        SceneError: the file is missing or malformed, or names something the robot does not have (the
            one-line message names the file, the key and the valid options).
        RobotNotFoundError, ModelError: the robot it names cannot be loaded.
    """
    prefixed = isinstance(path, str) and path.startswith(SCENE_PREFIX)
    if isinstance(path, str):
        path = path.removeprefix(SCENE_PREFIX)
    if isinstance(path, str) and not Path(path).exists():
        shipped = shipped_scenes()
        name = path.removesuffix(".toml")
        if name in shipped:
            return Scene(read_scene_file(shipped[name]))
        if prefixed:
            listed = ", ".join(shipped)
            raise SceneError(
                f"unknown scene '{path}': not a shipped scene nor an existing scene file (shipped: {listed})"
            )
    return Scene(read_scene_file(path))


def make_scene(**tables: Any) -> Scene:
    """Build a Scene from the same tables a scene file holds, as keyword arguments.

    Example::

        make_scene(robot={"source": "panda"}, lock={"panda_finger_joint1": 0.0, "panda_finger_joint2": 0.0},
                   force=[{"frame": "panda_hand", "force": [0, 0, -10], "shape": lambda t: min(t, 1.0)}])

    A force's ``shape`` may also be a Python callable ``t -> scale`` here. Relative URDF paths resolve against the
    working directory.
    """
    return Scene(parse_scene(tables, "<scene>", base_dir=None))


def scene_from_metadata(scene: dict[str, Any]) -> Scene:
    """Rebuild the Scene a trajectory was computed with, from its metadata's ``robot.scene`` entry.

    Raises:
        SceneError: the trajectory was made from a scene built in Python (no TOML text was kept).
    """
    text = scene.get("toml")
    if not isinstance(text, str):
        raise SceneError(
            f"{scene.get('source', '<scene>')}: the trajectory's scene was built in Python: its TOML text is not stored"
        )
    try:
        import tomllib
    except ModuleNotFoundError:  # Python < 3.11
        import tomli as tomllib  # type: ignore[no-redef]
    base_dir = scene.get("base_dir")
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise SceneError(f"{scene.get('source', '<scene>')}: stored scene text is not TOML ({exc})") from None
    spec = parse_scene(data, str(scene.get("source", "<scene>")), base_dir=Path(base_dir) if base_dir else None)
    return Scene(dataclasses.replace(spec, text=text))
