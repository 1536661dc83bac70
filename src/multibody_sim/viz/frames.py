"""From a saved trajectory to display frames: resampling to a display rate (the robot it was recorded on comes from
recorded.robot_from_trajectory)."""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pinocchio as pin

from ..exceptions import InvalidArgumentError
from ..robot import Robot, check_system
from ..safety import check_allocation
from ..trajectory import Trajectory
from ..validation import finite_number, positive_number

DEFAULT_FPS = 30.0


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
