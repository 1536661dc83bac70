"""From a saved trajectory to display frames: the robot it was recorded on, and resampling to a display rate."""

from __future__ import annotations

import contextlib
import math
import os
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from ..catalog import (
    CATALOG,
    example_robot_data_share,
    folder_list,
    inside_roots,
    load_robot,
    shipped_models_dir,
)
from ..exceptions import InvalidArgumentError, ModelError, TrajectoryFileError
from ..robot import Robot
from ..safety import check_allocation
from ..text import printable
from ..trajectory import Trajectory
from ..validation import check_system, check_trajectory, finite_number, positive_number

DEFAULT_FPS = 30.0


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
        from ..scenes import scene_from_metadata

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


def frame_times(t_start: float, t_end: float, fps: float, frame_bytes: int = 8) -> np.ndarray:
    """Display times from t_start to t_end at `fps` frames per second, the end included.

    Args:
        frame_bytes: what the caller will keep per frame [bytes]; the frames must fit in usable_memory().
    """
    t_start, t_end = finite_number(t_start, "t_start"), finite_number(t_end, "t_end")
    fps = positive_number(fps, "fps", None)
    frames = (t_end - t_start) * fps  # Python floats: a span that overflows is inf, refused below
    frames = math.floor(frames + 1e-9) if math.isfinite(frames) else frames
    check_allocation(
        (frames + 2) * frame_bytes,
        f"{t_end - t_start:g} s at {fps:g} frames per second would keep {frames + 2:.3g} frames",
        "choose a lower frame rate (fps), or play a shorter trajectory",
    )
    count = int(frames)
    times = t_start + np.arange(count + 1) / fps
    if t_end - times[-1] > 1e-9 / fps:
        times = np.append(times, t_end)
    return times


def resample(robot: Robot, trajectory: Trajectory | Any, fps: float = DEFAULT_FPS) -> tuple[np.ndarray, np.ndarray]:
    """Frames of a trajectory at a display rate, interpolated on the configuration manifold.

    Between two samples, q moves along Pinocchio's geodesic (`pin.interpolate`): a free-flyer's quaternion
    stays a unit quaternion (spherical interpolation) and a continuous joint's (cos, sin) stays on the circle,
    where interpolating the numbers in q would not.

    Args:
        robot: the robot the trajectory was recorded on.
        trajectory: anything with `t` (shape (n,), non-decreasing) and `q` (shape (n, nq)).
        fps: frames per second of the result (> 0).

    Returns:
        (times, Q): times [s] of shape (m,) from t[0] to t[-1] every 1/fps (the end included) and the
        configurations at those times, shape (m, nq).
    """
    check_system(robot, "robot")
    positive_number(fps, "fps", None)
    if not (hasattr(trajectory, "t") and hasattr(trajectory, "q")):
        raise InvalidArgumentError(
            f"trajectory must be a Trajectory (or have t and q arrays), got {type(trajectory).__name__}"
        )
    t = np.asarray(trajectory.t, dtype=float)
    Q = np.asarray(trajectory.q, dtype=float)
    if t.ndim != 1 or len(t) == 0 or Q.shape != (len(t), robot.nq):
        raise InvalidArgumentError(
            f"trajectory must have t of shape (n,) and q of shape (n, {robot.nq}), got {t.shape} and {Q.shape}"
        )
    if np.any(np.diff(t) < 0):
        raise InvalidArgumentError("trajectory times must be non-decreasing")
    times = frame_times(float(t[0]), float(t[-1]), float(fps), frame_bytes=8 * (robot.nq + 2))
    if len(t) == 1:
        return times[:1], Q[:1].copy()
    segment = np.clip(np.searchsorted(t, times, side="right") - 1, 0, len(t) - 2)
    frames = np.empty((len(times), robot.nq))
    model = robot.model
    for k, (time, i) in enumerate(zip(times, segment, strict=True)):
        span = t[i + 1] - t[i]
        alpha = 0.0 if span <= 0 else min(max((time - t[i]) / span, 0.0), 1.0)
        if alpha == 0.0:
            frames[k] = Q[i]
        elif alpha == 1.0:
            frames[k] = Q[i + 1]
        else:
            frames[k] = pin.interpolate(model, Q[i], Q[i + 1], alpha)
    return times, frames
