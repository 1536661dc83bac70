"""The robot (or scene) a saved trajectory was recorded on, loaded again from its metadata, as untrusted input: only
from the folders the user allows."""

from __future__ import annotations

import contextlib
import os
from pathlib import Path
from typing import Any

from .catalog import CATALOG, example_robot_data_share, folder_list, inside_roots, load_robot, shipped_models_dir
from .exceptions import ModelError, TrajectoryFileError
from .robot import Robot
from .text import printable
from .trajectory import Trajectory, check_trajectory


def robot_from_trajectory(
    trajectory: Trajectory, *, allowed_roots: list[str | os.PathLike[str]] | None = None
) -> Robot:
    """Load the robot a trajectory was recorded on, from its metadata (load_robot arguments, URDF SHA-256).

    A trajectory may come from a stranger: the package folders and allowed roots its metadata records are used only
    inside the URDF's folder and the catalog's, or inside `allowed_roots` (the CLI's `play --allow-root`); a scene's
    as load_scene allows them. Meshes, and pages exported from them, come only from there.

    Raises:
        TrajectoryFileError: the trajectory does not record how its robot was loaded.
        ModelError: the URDF cannot be found, its SHA-256 differs from the recorded one (the file changed), or the
            metadata names a folder outside the allowed ones.
    """
    check_trajectory(trajectory, "trajectory")
    extra = folder_list("allowed_roots", allowed_roots)
    info = trajectory.metadata.get("robot")
    arguments = info.get("load_robot") if isinstance(info, dict) else None
    objects_only = isinstance(info, dict) and isinstance(info.get("scene"), dict) and info.get("source") is None
    if not objects_only and (
        not isinstance(info, dict) or not isinstance(arguments, dict) or not arguments.get("source")
    ):
        raise TrajectoryFileError("the trajectory does not record how its robot was loaded (metadata 'robot')")
    assert isinstance(info, dict)
    if isinstance(info.get("scene"), dict):  # a scene's reduced / modified model: rebuild the scene itself
        from .scenes import scene_from_metadata

        robot: Robot = scene_from_metadata(info["scene"], allowed_roots=list(allowed_roots or []))
        return _checked(robot, info, trajectory)
    if not isinstance(arguments, dict):  # objects only: handled above
        raise TrajectoryFileError("the trajectory does not record how its robot was loaded (metadata 'robot')")
    source = str(arguments["source"])
    urdf_path = info.get("urdf_path")
    # A catalog name loads the catalog's URDF; a file loads the recorded absolute path, so that replaying does
    # not depend on the folder the command runs in.
    if source not in CATALOG and urdf_path:
        source = str(urdf_path)
    recorded = _recorded_folders(arguments, urdf_path if source not in CATALOG else None, extra)
    options: dict[str, Any] = {"package_dirs": recorded["package_dirs"] or None}
    if recorded["allowed_roots"] or extra:  # recorded only when given
        options["allowed_roots"] = recorded["allowed_roots"] + [str(root) for root in extra]
    try:
        robot = load_robot(
            source,
            floating_base=arguments.get("floating_base"),
            damping=bool(arguments.get("damping", True)),
            **options,
        )
    except ModelError as exc:
        raise ModelError(f"cannot load the trajectory's robot: {exc}") from None
    return _checked(robot, info, trajectory)


def _recorded_folders(arguments: dict[str, Any], urdf_path: Any, extra: list[Path]) -> dict[str, list[str]]:
    """The metadata's package_dirs and allowed_roots, each of which must lie in the URDF's folder, the catalog's
    folders or `extra` (the user's allowed roots): a stranger's trajectory cannot widen where meshes are read."""
    roots = [shipped_models_dir()]
    with contextlib.suppress(ModelError):  # example-robot-data not installed: its folder allows nothing
        roots.append(example_robot_data_share())
    if isinstance(urdf_path, str) and urdf_path:
        roots.append(Path(urdf_path).parent)
    trusted = [Path(os.path.realpath(root)) for root in [*roots, *extra]]
    found: dict[str, list[str]] = {}
    for key in ("package_dirs", "allowed_roots"):
        folders = arguments.get(key) or []
        if not isinstance(folders, list) or not all(isinstance(f, str) for f in folders):
            raise TrajectoryFileError(f"the trajectory's metadata has a malformed robot.load_robot.{key}")
        for folder in folders:
            resolved = Path(os.path.realpath(Path(folder).expanduser()))
            if not inside_roots(resolved, trusted):
                raise ModelError(
                    printable(
                        f"cannot load the trajectory's robot: its metadata names the folder '{folder}' ({key}), "
                        f"outside the URDF's folder and the catalog's ({', '.join(str(r) for r in trusted)}); to allow "
                        f"it, pass --allow-root {folder} (allowed_roots=[{folder!r}])"
                    )
                )
        found[key] = list(folders)
    return found


def _checked(robot: Robot, info: dict[str, Any], trajectory: Trajectory) -> Robot:
    """The robot, if its URDF is the one recorded and its nq fits the trajectory's."""
    recorded = info.get("urdf_sha256")
    actual = robot.source.get("urdf_sha256")
    if recorded and actual != recorded:
        raise ModelError(
            f"{robot.source.get('urdf_path')}: the URDF changed since the trajectory was recorded "
            f"(SHA-256 {str(actual)[:12]}... instead of {str(recorded)[:12]}...); "
            "the motion would be shown on a different robot"
        )
    if trajectory.q.ndim != 2 or trajectory.q.shape[1] != robot.nq:
        raise TrajectoryFileError(
            f"the trajectory's configurations have shape {trajectory.q.shape}, but {robot.name} has nq = {robot.nq}"
        )
    return robot
