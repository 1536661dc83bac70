"""Scenes: declared physics (locks, springs, friction, forces, payloads, constraints) on a robot.

A scene is a TOML file (``load_scene``) or the same tables in Python (``make_scene``); the resulting Scene is a
Robot wherever one is accepted, and ``Scene.run()`` runs it with its own [simulation] and [controller] settings.
"""

from __future__ import annotations

import contextlib
import dataclasses
import os
import stat
from pathlib import Path
from typing import Any

from ..catalog import (
    CATALOG,
    ROBOT_PREFIX,
    example_robot_data_share,
    folder_list,
    inside_roots,
    shipped_models_dir,
)
from ..exceptions import InvalidArgumentError, ModelError, SceneError
from ..text import printable
from .parse import parse_randomize, parse_scene, parse_toml, read_scene_file
from .scene import Scene
from .spec import SceneSpec

__all__ = ["SCENE_PREFIX", "Scene", "SceneSpec", "load_scene", "make_scene", "scene_from_metadata", "shipped_scenes"]


def shipped_scenes() -> dict[str, Path]:
    """The scenes shipped in models/scenes/, by name (the file's stem): `multibody-sim models` lists them."""
    folder = shipped_models_dir() / "scenes"
    return {path.stem: path for path in sorted(folder.glob("*.toml"))}


SCENE_PREFIX = "scene:"


def load_scene(path: str | os.PathLike[str], *, allowed_roots: list[str | os.PathLike[str]] | None = None) -> Scene:
    """Read a scene file (TOML), or a shipped scene by name, and build its Scene.

    Args:
        path: a scene file, or the name of a shipped scene (`multibody-sim models` lists them), with or
            without ".toml"; a leading "scene:" is allowed (the CLI's way to name a scene explicitly).
        allowed_roots: further folders the scene's robot file and package_dirs may lie in (the CLI's
            `--allow-root`), besides the scene file's own folder and the catalog's folders.

    Scene files are untrusted input like URDFs: size-limited, parsed without executing anything, and every key
    checked before anything is built. A scene from elsewhere cannot widen where files are read from: its robot
    file and its `package_dirs` must lie inside its own folder, the catalog's folders or `allowed_roots` (so
    meshes, and an exported page, come only from there).

    Raises:
        SceneError: the file is missing or malformed, names something the robot does not have, or reaches
            outside the allowed folders (the one-line message names the file, the key and the valid options).
        RobotNotFoundError, ModelError: the robot it names cannot be loaded.
        InvalidArgumentError: allowed_roots is not a list of existing folders.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise SceneError(f"a scene file must be a path, got {type(path).__name__}")
    roots = folder_list("allowed_roots", allowed_roots)
    prefixed = isinstance(path, str) and path.startswith(SCENE_PREFIX)
    if isinstance(path, str):
        path = path.removeprefix(SCENE_PREFIX)
    if isinstance(path, str) and not Path(path).exists():
        shipped = shipped_scenes()
        name = path.removesuffix(".toml")
        if name in shipped:
            path = shipped[name]
        elif prefixed:
            listed = ", ".join(shipped)
            raise SceneError(
                f"unknown scene '{path}': not a shipped scene nor an existing scene file (shipped: {listed})"
            )
    spec = read_scene_file(path)
    check_scene_roots(spec, roots)
    return Scene(dataclasses.replace(spec, allowed_roots=tuple(str(r) for r in roots)))


def scene_roots(spec: SceneSpec, allowed_roots: list[Path]) -> list[Path]:
    """The folders a scene file's robot and package_dirs may lie in: its own folder, the catalog's folders
    (shipped models, example-robot-data) and allowed_roots, symlinks resolved."""
    roots = [spec.base_dir] if spec.base_dir is not None else []
    roots += [shipped_models_dir()]
    with contextlib.suppress(ModelError):  # example-robot-data not installed: its folder allows nothing
        roots.append(example_robot_data_share())
    roots += allowed_roots
    return [Path(os.path.realpath(root)) for root in roots]


def check_scene_roots(spec: SceneSpec, allowed_roots: list[Path]) -> None:
    """SceneError unless the scene's robot file and package_dirs lie inside scene_roots (a catalog name is fine)."""
    if spec.robot is None:  # objects only: no file to read
        return
    roots = scene_roots(spec, allowed_roots)
    paths = (
        []
        if spec.robot.source in CATALOG or spec.robot.source.startswith(ROBOT_PREFIX)
        else [("robot.source", spec.robot.source)]
    )
    paths += [(f"robot.package_dirs[{i}]", d) for i, d in enumerate(spec.robot.package_dirs)]
    for key, value in paths:
        resolved = Path(os.path.realpath(Path(value).expanduser()))
        if not inside_roots(resolved, roots):
            raise SceneError(
                printable(
                    f"{spec.source}: {key}: '{value}' is outside the folders a scene may read from (its own folder "
                    f"and the catalog's: {', '.join(str(r) for r in roots)}); to allow it, pass --allow-root DIR "
                    "(allowed_roots=[DIR] in load_scene)"
                )
            )


def make_scene(**tables: Any) -> Scene:
    """Build a Scene from the same tables a scene file holds, as keyword arguments.

    Example::

        make_scene(robot={"source": "panda"}, lock={"panda_finger_joint1": 0.0, "panda_finger_joint2": 0.0},
                   force=[{"frame": "panda_hand", "force": [0, 0, -10], "shape": lambda t: min(t, 1.0)}])

    A force's ``shape`` may also be a Python callable ``t -> scale`` here. Relative URDF paths resolve against the
    working directory.
    """
    return Scene(parse_scene(tables, "<scene>", base_dir=None))


def scene_from_metadata(scene: dict[str, Any], *, allowed_roots: list[str | os.PathLike[str]] | None = None) -> Scene:
    """Rebuild the Scene a trajectory was computed with, from its metadata's ``robot.scene`` entry.

    A trajectory may come from a stranger: the scene's robot file and package_dirs must lie in the catalog's
    folders, or in the scene's recorded folder while that folder still holds the recorded scene file unchanged, as
    for load_scene; the folders allowed when it was recorded are not trusted from the file, only `allowed_roots`
    (the CLI's `play --allow-root`).

    Raises:
        SceneError: the trajectory was made from a scene built in Python (no TOML text was kept), or its scene
            reaches outside the allowed folders.
    """
    if not isinstance(scene, dict):
        raise SceneError(f"scene must be the metadata's robot.scene entry (a dict), got {type(scene).__name__}")
    text = scene.get("toml")
    if not isinstance(text, str):
        raise SceneError(
            f"{scene.get('source', '<scene>')}: the trajectory's scene was built in Python: its TOML text is not stored"
        )
    base_dir = scene.get("base_dir")
    source = printable(str(scene.get("source", "<scene>")))
    data = parse_toml(text, f"{source} (the trajectory's stored scene text)")
    spec = parse_scene(data, source, base_dir=Path(base_dir) if base_dir else None)
    roots = folder_list("allowed_roots", allowed_roots)
    # The recorded folder is the file's say: trusted only while it holds the recorded scene file, unchanged (then
    # the user has that scene; a stranger's trajectory cannot name a folder of theirs as the scene's).
    trusted = spec if _recorded_scene_file(scene, text) else dataclasses.replace(spec, base_dir=None)
    check_scene_roots(trusted, roots)
    return Scene(dataclasses.replace(spec, text=text, allowed_roots=tuple(str(r) for r in roots)))


def _recorded_scene_file(scene: dict[str, Any], text: str) -> bool:
    """Whether the recorded base_dir holds the recorded scene file with the recorded text."""
    base_dir, source = scene.get("base_dir"), scene.get("source")
    if not isinstance(base_dir, str) or not isinstance(source, str) or not base_dir:
        return False
    path = Path(base_dir) / Path(source).name
    try:
        # Both from the file: looked at before it is opened (a FIFO would block the open, a device could act on it).
        if not stat.S_ISREG(os.stat(path).st_mode):
            return False
        fd = os.open(path, os.O_RDONLY | getattr(os, "O_NONBLOCK", 0))
        with os.fdopen(fd, "rb") as stream:
            return stat.S_ISREG(os.fstat(fd).st_mode) and stream.read(len(text.encode()) + 1) == text.encode()
    except OSError:
        return False


def randomized_scene(system: Any, randomize: Any, where: str) -> tuple[Any, Any]:
    """What a batch or an environment draws its rows' or episodes' parameters from (rollout's and the gym
    environments' `randomize`): (the system to run, its Randomizer or None).

    Args:
        system: a Robot or a Scene.
        randomize: None (the scene's own [randomize] table, if it has one), False (nothing drawn), or a dict in the
            [randomize] table's form: the scene with it in place of its own.
        where: the caller's name, for messages ("rollout").

    Raises:
        InvalidArgumentError: randomize is none of those, or names what the scene does not have (one line).
    """
    if randomize is None or randomize is False:
        return system, getattr(system, "randomizer", None) if randomize is None else None
    if not isinstance(system, Scene):
        raise InvalidArgumentError(
            f"randomize draws a scene's parameters: the system must be a Scene (load_scene, make_scene), got a "
            f"{type(system).__name__}"
        )
    if not isinstance(randomize, dict):
        raise InvalidArgumentError(
            "randomize must be None (the scene's own [randomize]), False (none) or a dict in the [randomize] "
            f"table's form ({{'seed': 0, 'parameter': [{{...}}]}}), got {type(randomize).__name__}"
        )
    try:
        spec = parse_randomize(randomize, where)
        scene = Scene(dataclasses.replace(system.spec, randomize=spec, parameters=None), robot=system.full_robot)
    except SceneError as exc:
        raise InvalidArgumentError(str(exc)) from None
    return scene, scene.randomizer
