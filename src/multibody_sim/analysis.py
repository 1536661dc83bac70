"""Analysis of a trajectory, computed on demand from its q and v: frame placements and velocities, centre of mass,
centroidal momentum."""

from __future__ import annotations

import difflib
from typing import Any

import numpy as np
import pinocchio as pin

from .exceptions import InvalidArgumentError, UnknownNameError
from .robot import Robot, check_system

_LOCAL_WORLD_ALIGNED = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED
_LISTED = 12  # frame names an unknown-frame error lists when none is close


def frame_names(robot: Robot) -> list[str]:
    """The names of the robot's frames (links, joints and fixed frames such as tool0), in Pinocchio's order,
    without duplicates."""
    check_system(robot, "robot")
    return list(dict.fromkeys(frame.name for frame in robot.model.frames))


def frame_placements(robot: Robot, traj: Any, frame: str) -> np.ndarray:
    """World placements of a named frame along a trajectory, as homogeneous transforms.

    Args:
        robot: the robot the trajectory belongs to.
        traj: a Trajectory, or anything with a ``q`` array of shape (..., nq) (a BatchTrajectory too).
        frame: a frame name: a link (URDF ``<link>``), a joint or a fixed frame (``frame_names(robot)``
            lists them); a name shared by a link and a joint means the link.

    Returns:
        [[R, p], [0, 1]] with R the frame's orientation and p its origin [m] in the world, shape (..., 4, 4).

    Raises:
        UnknownNameError: no frame has that name (the message lists close matches).
        InvalidArgumentError: traj.q has the wrong shape or non-finite entries.
    """
    check_system(robot, "robot")
    frame_id = _frame_id(robot, frame)
    Q = _configurations(robot, traj)
    model, data = robot.model, robot.data
    out = np.empty((len(Q), 4, 4))
    for i, q in enumerate(Q):
        pin.framesForwardKinematics(model, data, q)
        out[i] = data.oMf[frame_id].homogeneous
    return out.reshape(*_leading(traj.q), 4, 4)


def frame_velocities(robot: Robot, traj: Any, frame: str) -> np.ndarray:
    """Spatial velocity of a named frame along a trajectory, in LOCAL_WORLD_ALIGNED coordinates.

    The linear part is the velocity of the frame's origin in the world [m/s] (the time derivative of p in
    frame_placements) and the angular part the frame's angular velocity ω in world axes [rad/s] (Ṙ = [ω]× R).

    Args:
        robot: the robot the trajectory belongs to.
        traj: a Trajectory, or anything with ``q`` (..., nq) and ``v`` (..., nv) arrays.
        frame: a frame name, as for frame_placements.

    Returns:
        (linear, angular) stacked, shape (..., 6).

    Raises:
        UnknownNameError: no frame has that name (the message lists close matches).
        InvalidArgumentError: traj.q or traj.v has the wrong shape or non-finite entries.
    """
    check_system(robot, "robot")
    frame_id = _frame_id(robot, frame)
    Q, V = _configurations(robot, traj), _velocities(robot, traj)
    model, data = robot.model, robot.data
    out = np.empty((len(Q), 6))
    for i in range(len(Q)):
        pin.forwardKinematics(model, data, Q[i], V[i])
        pin.updateFramePlacement(model, data, frame_id)
        out[i] = pin.getFrameVelocity(model, data, frame_id, _LOCAL_WORLD_ALIGNED).vector
    return out.reshape(*_leading(traj.q), 6)


def center_of_mass(robot: Robot, traj: Any) -> np.ndarray:
    """Position of the robot's centre of mass in the world along a trajectory [m], shape (..., 3).

    Args:
        robot: the robot the trajectory belongs to.
        traj: a Trajectory, or anything with a ``q`` array of shape (..., nq).
    """
    check_system(robot, "robot")
    Q = _configurations(robot, traj)
    model, data = robot.model, robot.data
    out = np.empty((len(Q), 3))
    for i, q in enumerate(Q):
        out[i] = pin.centerOfMass(model, data, q, False)
    return out.reshape(*_leading(traj.q), 3)


def center_of_mass_velocity(robot: Robot, traj: Any) -> np.ndarray:
    """Velocity of the robot's centre of mass in the world along a trajectory [m/s], shape (..., 3).

    Args:
        robot: the robot the trajectory belongs to.
        traj: a Trajectory, or anything with ``q`` (..., nq) and ``v`` (..., nv) arrays.
    """
    check_system(robot, "robot")
    Q, V = _configurations(robot, traj), _velocities(robot, traj)
    model, data = robot.model, robot.data
    out = np.empty((len(Q), 3))
    for i in range(len(Q)):
        pin.centerOfMass(model, data, Q[i], V[i], False)
        out[i] = data.vcom[0]
    return out.reshape(*_leading(traj.q), 3)


def centroidal_momentum(robot: Robot, traj: Any) -> np.ndarray:
    """The robot's centroidal momentum along a trajectory: its total momentum about the centre of mass, in world
    axes, shape (..., 6).

    The first three entries are the linear momentum [kg·m/s] (total mass × centre-of-mass velocity), the last
    three the angular momentum about the centre of mass [kg·m²/s]. Both are conserved when no external force
    acts (a floating robot in zero gravity, joint torques and damping being internal).

    Args:
        robot: the robot the trajectory belongs to.
        traj: a Trajectory, or anything with ``q`` (..., nq) and ``v`` (..., nv) arrays.
    """
    check_system(robot, "robot")
    Q, V = _configurations(robot, traj), _velocities(robot, traj)
    model, data = robot.model, robot.data
    out = np.empty((len(Q), 6))
    for i in range(len(Q)):
        out[i] = pin.computeCentroidalMomentum(model, data, Q[i], V[i]).vector
    return out.reshape(*_leading(traj.q), 6)


# ---- checks ---------------------------------------------------------------------------------------------------
def _frame_id(robot: Robot, name: Any) -> int:
    if not isinstance(name, str):
        raise InvalidArgumentError(f"frame must be a frame name (a string), got {type(name).__name__}")
    model = robot.model
    matches = [i for i, frame in enumerate(model.frames) if frame.name == name]
    if not matches:
        names = frame_names(robot)
        close = difflib.get_close_matches(name, names, n=5, cutoff=0.5)
        if close:
            hint = f"did you mean {', '.join(close)}?"
        else:
            shown = names if len(names) <= _LISTED else [*names[:_LISTED], "..."]
            hint = f"its {len(names)} frames: {', '.join(shown)}; multibody_sim.analysis.frame_names(robot) lists them"
        raise UnknownNameError(f"robot '{robot.name}' has no frame '{name}' ({hint})")
    bodies = [i for i in matches if model.frames[i].type == pin.FrameType.BODY]
    return (bodies or matches)[0]


def _configurations(robot: Robot, traj: Any) -> np.ndarray:
    """traj.q as a (n, nq) float array, checked (shape, finiteness, unit quaternions)."""
    Q = _stack(traj, "q", robot.nq)
    for i, q in enumerate(Q):
        if not robot.space.is_normalized(q):
            raise InvalidArgumentError(
                f"traj.q[{i}] is not a valid configuration: its quaternion / (cos, sin) entries must have unit norm"
            )
    return Q


def _velocities(robot: Robot, traj: Any) -> np.ndarray:
    V = _stack(traj, "v", robot.nv)
    if np.shape(traj.v)[:-1] != np.shape(traj.q)[:-1]:
        raise InvalidArgumentError(
            f"traj.v must have one row per row of traj.q: shapes {np.shape(traj.q)} and {np.shape(traj.v)}"
        )
    return V


def _stack(traj: Any, field: str, size: int) -> np.ndarray:
    if not hasattr(traj, field):
        raise InvalidArgumentError(
            f"traj must be a Trajectory (or have a '{field}' array), got {type(traj).__name__} without '{field}'"
        )
    values = np.asarray(getattr(traj, field))
    if values.dtype.kind not in "biuf" or values.ndim < 1 or values.shape[-1] != size:
        raise InvalidArgumentError(
            f"traj.{field} must be an array of shape (..., {size}), got shape {values.shape} dtype {values.dtype}"
        )
    flat = np.asarray(values, dtype=float).reshape(-1, size)
    if not np.isfinite(flat).all():
        row = int(np.argmax(~np.isfinite(flat).all(axis=1)))
        raise InvalidArgumentError(f"traj.{field} must be finite, got non-finite entries in row {row}")
    return flat


def _leading(values: Any) -> tuple[int, ...]:
    return tuple(np.shape(values)[:-1])
