"""Torque policies users pass to simulate(): PD, gravity compensation, computed torque, potential fields.

Every controller here is a callable ``controller(t, q, v) -> tau`` (the contract of
:class:`multibody_sim.simulation.Controller`) built from a :class:`Robot`, so it can use the robot's dynamics.
Stateful ones (computed torque logs its tracking error; the potential field watches for local minima and
draws random pushes) have ``reset()``; all have it, so a caller can reset any controller. A controller also
starts afresh by itself when it is called with a time earlier than its previous call (a new run), so reusing
one across ``simulate`` calls gives the same results as a new one.

Torques are returned unclipped: the stepping loop saturates them at the URDF effort limits (and counts it).

:data:`CONTROLLERS` names the built-ins for the command line; :func:`make_controller` builds one from
``KEY=VALUE`` strings, vectors written as comma-separated numbers (``q_ref=0,-1,1,0,0,0``).
"""

from __future__ import annotations

import difflib
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import pinocchio as pin

from .exceptions import InvalidArgumentError, UnknownNameError
from .robot import Robot, check_system
from .text import name_hint, safe_name
from .validation import check_text

_LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED


# ---- argument checks ---------------------------------------------------------------------------------
def _real_array(value: Any, name: str) -> np.ndarray:
    """value as a finite float array, or InvalidArgumentError naming `name`."""
    try:
        raw = np.asarray(value)
    except ValueError:  # ragged nesting
        raw = None
    if raw is None or raw.dtype.kind not in "iuf":  # a bool is no gain or position
        got = type(value).__name__
        raise InvalidArgumentError(f"{name} must be real numbers, got {got}")
    arr = np.array(raw, dtype=float)
    if not np.all(np.isfinite(arr)):
        raise InvalidArgumentError(f"{name} must be finite, got {arr.tolist()}")
    return arr


def _vector(value: Any, size: int, name: str) -> np.ndarray:
    arr = _real_array(value, name)
    if arr.shape != (size,):
        raise InvalidArgumentError(f"{name} must have shape ({size},), got {arr.shape}")
    return arr


def _gain(value: Any, size: int, name: str) -> np.ndarray:
    """A non-negative gain: one number for every coordinate, or one per coordinate; shape (size,)."""
    arr = _real_array(value, name)
    if arr.shape not in ((), (size,)):
        raise InvalidArgumentError(f"{name} must be a number or have shape ({size},), got {arr.shape}")
    if np.any(arr < 0):
        raise InvalidArgumentError(f"{name} must be >= 0, got {arr.tolist()}")
    return np.broadcast_to(arr, (size,)).copy()


def _positive(value: Any, name: str, *, allow_zero: bool = False) -> float:
    arr = _real_array(value, name)
    if arr.shape != ():
        raise InvalidArgumentError(f"{name} must be a single number, got shape {arr.shape}")
    if arr < 0 or (arr == 0 and not allow_zero):
        raise InvalidArgumentError(f"{name} must be {'>= 0' if allow_zero else '> 0'}, got {float(arr)}")
    return float(arr)


def _n_base(robot: Robot) -> int:
    """Number of unactuated velocity coordinates before the actuated ones (the floating base's 6, else 0)."""
    return 6 if robot.floating_base else 0


def _actuated(robot: Robot) -> slice:
    """The actuated velocity coordinates: after a floating base, before a scene's free objects."""
    check_system(robot, "robot")  # every controller's first look at its robot
    return getattr(robot, "actuated", slice(_n_base(robot), robot.nv))


def _refuse_floating_base(robot: Robot, what: str) -> None:
    check_system(robot, "robot")
    if robot.floating_base:
        raise InvalidArgumentError(
            f"{what} needs every velocity coordinate actuated, but robot '{robot.name}' has a floating base whose 6 "
            "are not (load it with floating_base=False to weld the base)"
        )


class _Stateless:
    """Shared by the controllers that keep nothing between calls."""

    def reset(self) -> None:
        """Nothing to forget: the controller keeps no state between calls."""

    def summary(self) -> str:
        """One line on what the controller saw during the run ("" when there is nothing to say)."""
        return ""


# ---- PD, gravity compensation ---------------------------------------------------------------------------
def _critical_damping(robot: Robot, q: np.ndarray, kp: np.ndarray) -> np.ndarray:
    """kd = 2 sqrt(kp M_jj(q)) on each actuated joint: critical damping of each joint taken alone."""
    M = pin.crba(robot.model, robot.model.createData(), q)
    return 2.0 * np.sqrt(kp * np.diag(M)[_actuated(robot)])


class PD(_Stateless):
    """PD to a setpoint: ``tau = Kp (q_ref ⊖ q) + Kd (v_ref − v)`` on the actuated joints.

    ``q_ref ⊖ q`` is Pinocchio's difference (the tangent vector from q to q_ref), so continuous joints take the
    short way round. Without gravity compensation the arm settles where ``Kp e = g(q)``: a static error
    ``e ≈ Kp⁻¹ g(q_ref)`` to first order (use :class:`PDGravity` to remove it).

    Args:
        robot: the robot the controller drives.
        q_ref: target configuration, shape (nq,) [rad or m]; a floating base's entries are ignored.
        kp: stiffness [N·m/rad or N/m]: one number, or one per actuated joint (shape (nv,), or (nv − 6,) on a
            floating base).
        kd: damping [N·m·s/rad or N·s/m], same shapes as kp; default ``2 sqrt(kp M_jj(q_ref))``, critical
            damping of each joint taken alone.
        v_ref: target velocity, shape (nv,) [rad/s or m/s]; default zero.

    Attributes:
        q_ref, v_ref, kp, kd: the checked arguments (gains with shape (n_actuated,)).
    """

    def __init__(self, robot: Robot, q_ref: Any, *, kp: Any, kd: Any = None, v_ref: Any = None):
        self.robot = robot
        self._a = _actuated(robot)
        n = self._a.stop - self._a.start
        self.q_ref = robot.check_q(q_ref, "q_ref")
        self.v_ref = np.zeros(robot.nv) if v_ref is None else robot.check_v(v_ref, "v_ref")
        self.kp = _gain(kp, n, "kp")
        self.kd = _critical_damping(robot, self.q_ref, self.kp) if kd is None else _gain(kd, n, "kd")
        self._model = robot.model

    def native_data(self, system: Any) -> dict[str, Any] | None:
        """The controller as the native kernel renders it on `system`'s run (_native.Policy's fields), or None when
        it was not made for that system (another robot, model or actuated range)."""
        if self.robot is not system or self._model is not system.model or self._a != system.actuated:
            return None
        return {"kind": "pd", "q_ref": self.q_ref, "v_ref": self.v_ref, "kp": self.kp, "kd": self.kd}

    def __call__(self, t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Joint torques [N·m or N], shape (nv,), zero on a floating base's 6 entries."""
        a = self._a
        error = pin.difference(self._model, q, self.q_ref)
        tau = np.zeros(self.robot.nv)
        tau[a] = self.kp * error[a] + self.kd * (self.v_ref[a] - v[a])
        return tau


class GravityCompensation(_Stateless):
    """Gravity compensation: ``tau = g(q)`` on the actuated joints, so a fixed-base arm at rest stays at rest.

    On a floating base the joints carry their share of gravity but nothing holds the base up (contact is not
    modelled): the robot still falls.

    Args:
        robot: the robot the controller drives.
    """

    def __init__(self, robot: Robot):
        self.robot = robot
        self._a = _actuated(robot)
        self._model, self._data = robot.model, robot.model.createData()  # its own workspace

    def native_data(self, system: Any) -> dict[str, Any] | None:
        """As PD.native_data: kind "gravity" (no references or gains: zeros of their sizes)."""
        if self.robot is not system or self._model is not system.model or self._a != system.actuated:
            return None
        nv, n = system.nv, self._a.stop - self._a.start
        return {
            "kind": "gravity",
            "q_ref": system.neutral(),
            "v_ref": np.zeros(nv),
            "kp": np.zeros(n),
            "kd": np.zeros(n),
        }

    def __call__(self, t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Joint torques [N·m or N], shape (nv,)."""
        tau = pin.computeGeneralizedGravity(self._model, self._data, q).copy()
        tau[: self._a.start] = 0.0
        tau[self._a.stop :] = 0.0
        return tau


class PDGravity(_Stateless):
    """PD to a setpoint plus gravity compensation: ``tau = Kp (q_ref ⊖ q) + Kd (v_ref − v) + g(q)``.

    With v_ref = 0 and positive gains, a fixed-base robot converges to q_ref with no steady-state error
    (the Takegaki–Arimoto result: ``½ vᵀ M v + ½ eᵀ Kp e`` is a Lyapunov function), as long as the torques stay
    within the effort limits.

    Args:
        robot, q_ref, kp, kd, v_ref: as for :class:`PD`.
    """

    def __init__(self, robot: Robot, q_ref: Any, *, kp: Any, kd: Any = None, v_ref: Any = None):
        self.robot = robot
        self.pd = PD(robot, q_ref, kp=kp, kd=kd, v_ref=v_ref)
        self.gravity = GravityCompensation(robot)

    def native_data(self, system: Any) -> dict[str, Any] | None:
        """As PD.native_data, kind "pd_gravity": its PD's data, when its parts are the built-in ones unchanged."""
        pd, gravity = self.pd, self.gravity
        if type(pd) is not PD or type(gravity) is not GravityCompensation:
            return None
        if "__call__" in vars(pd) or "__call__" in vars(gravity) or self.robot is not system:
            return None
        data = pd.native_data(system)
        if data is None or gravity.native_data(system) is None:
            return None
        return {**data, "kind": "pd_gravity"}

    def __call__(self, t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Joint torques [N·m or N], shape (nv,)."""
        return self.pd(t, q, v) + self.gravity(t, q, v)


# ---- computed torque ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class TrackingLog:
    """The tracking error a :class:`ComputedTorque` controller saw, one row per controller call.

    Attributes:
        t: call times [s], shape (n,).
        position_error: ``q_des(t) ⊖ q`` of the actuated coordinates (a scene's free objects, which the controller
            does not drive, left out), shape (n, nv_actuated) [rad or m].
        velocity_error: ``v_des(t) − v``, likewise [rad/s or m/s].
    """

    t: np.ndarray
    position_error: np.ndarray
    velocity_error: np.ndarray

    @property
    def max_position_error(self) -> float:
        """max over calls and joints of |q_des ⊖ q| [rad or m] (0 for an empty log)."""
        return float(np.abs(self.position_error).max()) if self.position_error.size else 0.0

    @property
    def max_velocity_error(self) -> float:
        """max over calls and joints of |v_des − v| [rad/s or m/s] (0 for an empty log)."""
        return float(np.abs(self.velocity_error).max()) if self.velocity_error.size else 0.0


class ComputedTorque:
    """Computed-torque tracking of a cubic spline through joint waypoints, with the tracking error logged.

    ``tau = M(q) (a_des + Kp e + Kd ė) + C(q, v) v + g(q) + D v`` with ``e = q_des ⊖ q`` and
    ``ė = v_des − v``: with exact dynamics and continuous control the error obeys ``ë + Kd ė + Kp e = 0``,
    so only the zero-order hold (control_dt) and saturation leave an error. The reference is a cubic spline
    (scipy's CubicSpline) through the waypoints in the tangent space of the first one, so continuous joints
    take the short way between consecutive waypoints; before the first time it holds the first waypoint,
    after the last time the last one, at rest. Each call appends (t, e, ė) to a log: :meth:`tracking_error`.

    Args:
        robot: a fixed-base robot whose joints are revolute, prismatic or continuous.
        times: waypoint times [s], shape (n,), n >= 2, strictly increasing.
        waypoints: configurations, shape (n, nq) [rad or m].
        kp: error stiffness [1/s²], a number or shape (nv,); default 100 (10 rad/s).
        kd: error damping [1/s], same shapes; default ``2 sqrt(kp)`` (critical).
        bc_type: spline end conditions: "clamped" (zero velocity at both ends: starts and stops at rest) or
            "natural" (zero acceleration at both ends).

    Raises:
        InvalidArgumentError: a floating base (6 unactuated coordinates: computed torque cannot act on them),
            spherical or planar joints, or bad waypoints.
    """

    def __init__(
        self,
        robot: Robot,
        times: Any,
        waypoints: Any,
        *,
        kp: Any = 100.0,
        kd: Any = None,
        bc_type: str = "clamped",
    ):
        _refuse_floating_base(robot, "computed torque")
        # A scene's free objects (free-flyers after the arm) are not actuated: their coordinates only ride along.
        arm_end = _actuated(robot).stop
        if not all(start >= arm_end for start, _ in robot.space.curved_blocks):
            raise InvalidArgumentError(
                f"computed torque supports revolute, prismatic and continuous joints; robot '{robot.name}' has a "
                "spherical or planar joint"
            )
        if bc_type not in ("clamped", "natural"):
            raise InvalidArgumentError(f"bc_type must be 'clamped' or 'natural', got {bc_type!r}")
        self.robot = robot
        times = _real_array(times, "times")
        if times.ndim != 1 or len(times) < 2:
            raise InvalidArgumentError(f"times must have shape (n,) with n >= 2, got {times.shape}")
        if np.any(np.diff(times) <= 0):
            raise InvalidArgumentError(f"times must be strictly increasing, got {times.tolist()}")
        points = _real_array(waypoints, "waypoints")
        if points.shape != (len(times), robot.nq):
            raise InvalidArgumentError(f"waypoints must have shape ({len(times)}, {robot.nq}), got {points.shape}")
        for i, point in enumerate(points):
            robot.check_q(point, f"waypoints[{i}]")
        self.times, self.waypoints = times, points
        self.kp = _gain(kp, robot.nv, "kp")
        self.kd = 2.0 * np.sqrt(self.kp) if kd is None else _gain(kd, robot.nv, "kd")
        self.bc_type = bc_type
        self._model, self._data = robot.model, robot.model.createData()
        self._origin = points[0]
        # Chart coordinates of each waypoint, accumulated leg by leg (each leg the short way round).
        steps = [pin.difference(self._model, points[i], points[i + 1]) for i in range(len(points) - 1)]
        chart = np.vstack([np.zeros(robot.nv), np.cumsum(steps, axis=0)])
        from scipy.interpolate import CubicSpline  # here: SciPy would slow `import multibody_sim` by a third

        self.spline = CubicSpline(times, chart, axis=0, bc_type=bc_type)
        self._velocity, self._acceleration = self.spline.derivative(1), self.spline.derivative(2)
        self._damping = robot.damping if np.any(robot.damping) else None
        self.reset()

    def reset(self) -> None:
        """Empty the tracking log (a new run)."""
        self._log_t: list[float] = []
        self._log_e: list[np.ndarray] = []
        self._log_de: list[np.ndarray] = []

    def reference(self, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(q_des, v_des, a_des) at time t [s]: shapes (nq,), (nv,), (nv,)."""
        t0, t1 = self.times[0], self.times[-1]
        if t < t0 or t > t1:
            chart = self.spline(min(max(t, t0), t1))
            zero = np.zeros(self.robot.nv)
            return pin.integrate(self._model, self._origin, chart), zero, zero.copy()
        return (
            pin.integrate(self._model, self._origin, self.spline(t)),
            self._velocity(t),
            self._acceleration(t),
        )

    def __call__(self, t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Joint torques [N·m or N], shape (nv,); logs (t, q_des ⊖ q, v_des − v)."""
        if self._log_t and t < self._log_t[-1]:  # time went back: a new run with the same controller
            self.reset()
        q_des, v_des, a_des = self.reference(t)
        error = pin.difference(self._model, q, q_des)
        d_error = v_des - v
        actuated = _actuated(self.robot)  # a scene's free objects only ride along: their "error" is no error
        self._log_t.append(float(t))
        self._log_e.append(error[actuated])
        self._log_de.append(d_error[actuated])
        tau = pin.rnea(self._model, self._data, q, v, a_des + self.kp * error + self.kd * d_error).copy()
        if self._damping is not None:  # the URDF damping takes D v away: give it back
            tau += self._damping * v
        tau[_actuated(self.robot).stop :] = 0.0  # a scene's free objects are not actuated
        return tau

    def tracking_error(self) -> TrackingLog:
        """The log since the last reset, as arrays."""
        actuated = _actuated(self.robot)
        nv = actuated.stop - actuated.start
        return TrackingLog(
            t=np.array(self._log_t),
            position_error=np.array(self._log_e).reshape(-1, nv),
            velocity_error=np.array(self._log_de).reshape(-1, nv),
        )

    def summary(self) -> str:
        """The worst tracking error of the run, in one line."""
        log = self.tracking_error()
        if not len(log.t):
            return "computed torque: not called"
        worst = int(np.argmax(np.abs(log.position_error).max(axis=0)))
        return (
            f"computed torque: max tracking error {log.max_position_error:.3g} "
            f"(in '{safe_name(self.robot.dof_names[_actuated(self.robot)][worst])}'), "
            f"max velocity error {log.max_velocity_error:.3g}, over {len(log.t)} controller calls"
        )


# ---- artificial potential field -------------------------------------------------------------------------
@dataclass(frozen=True)
class LocalMinimum:
    """A stall the potential field detected: far from the goal, slow, and attraction cancelled by repulsion.

    Attributes:
        t: when the stall was confirmed [s].
        position: where, in the field's space, shape (d,).
        push: the random force applied to escape [N] (or [N·m] in joint space), shape (d,); None when escapes
            are off.
    """

    t: float
    position: np.ndarray
    push: np.ndarray | None


@dataclass
class _Watch:
    """The potential field's memory between calls."""

    last_t: float = -math.inf
    stall_since: float | None = None
    reported: bool = False  # this stall has been recorded (escapes off: record it once)
    push: np.ndarray | None = None
    push_until: float = -math.inf
    position: np.ndarray | None = None
    events: list[LocalMinimum] = field(default_factory=list)


class PotentialField:
    """Artificial potential field: attraction to a goal, repulsion from spherical obstacles, local-minimum escape.

    The field lives either on the configuration itself (``frame=None``: q is a point in R^nq, e.g. the
    point_robot's (x, y)) or on the world position of a frame (``frame="tool0"``: an end effector, d = 3).
    With x that point, ``ρ_i = ‖x − c_i‖ − r_i`` the distance to obstacle i's surface and ``d = ‖x − x_goal‖``:

    - attraction: ``U_att = ½ k_attract d²`` up to ``conic_distance``, linear (constant pull
      ``k_attract · conic_distance``) beyond it, so far goals do not command huge forces;
    - repulsion: ``U_rep = Σ_i ½ k_repulse (1/ρ_i − 1/influence)²`` where ``ρ_i < influence``, else 0; it
      grows without bound at the surface, so a robot whose energy is bounded never touches an obstacle.

    The robot follows the negative gradient: ``F = −∇U`` acts on x (mapped to joint torques by the frame's
    position Jacobian, ``tau = Jᵀ F``, taken LOCAL_WORLD_ALIGNED), plus joint damping ``−Kd v`` and, by
    default, gravity compensation ``g(q)``.

    Local minima: where repulsion cancels attraction away from the goal (an obstacle dead ahead on the line of
    symmetry is the classic case) the robot stalls. A stall is declared when, for ``stall_time`` seconds in a
    row, the robot is farther than ``goal_tolerance`` from the goal, slower than ``stall_speed`` and the net
    field force is below ``stall_ratio`` times the attraction alone. With ``escape`` on, a random force of
    magnitude ``escape_force`` (direction uniform on the sphere, from a generator seeded with ``seed``) is added
    for ``escape_time`` seconds. Each stall is recorded in :attr:`local_minima`.

    Args:
        robot: a fixed-base robot; without a frame its configuration must be a plain vector (revolute and
            prismatic joints only).
        goal: target point, shape (d,) [m, or the joints' units without a frame].
        frame: name of a frame (``robot.model.frames``) whose position the field acts on; None: the
            configuration.
        obstacles: spheres (circles in 2-D): each a pair (center (d,), radius), or a row of d + 1 numbers
            (center, then radius) [m].
        k_attract: attraction stiffness [N/m] (in joint space: [N/m] or [N·m/rad²] per the joints' units).
        conic_distance: distance beyond which the attraction stops growing [m].
        k_repulse: repulsion gain [N·m].
        influence: distance from an obstacle's surface beyond which it does not repel [m].
        kd: joint damping [N·s/m or N·m·s/rad], a number or shape (nv,). Default without a frame:
            ``2 sqrt(k_attract M_jj(goal))``, critical damping of each coordinate alone (exact for the point
            robot, whose M is diagonal). With a frame: ``sqrt(k_attract M_jj) max(‖J_j‖, 0.1 m)`` at the neutral
            configuration, J_j the frame Jacobian's column (the joint's lever arm): half of each joint's critical
            damping taken alone, because the joints share the load and the full value overdamps the arm.
        gravity_compensation: add g(q).
        goal_tolerance: distance to the goal that counts as arrived [m].
        stall_speed: speed of x below which the robot may be stalled [m/s].
        stall_ratio: net field force over attraction below which the robot may be stalled.
        stall_time: how long those conditions must last to declare a local minimum [s].
        escape: push the robot out of detected local minima.
        escape_force: size of the random push [N]; default twice the largest attraction,
            ``2 k_attract conic_distance``.
        escape_time: how long each push lasts [s].
        seed: seed of the pushes' random directions (runs are deterministic).

    Raises:
        InvalidArgumentError: a floating base, an unknown frame, bad shapes or values, or a goal or start
            inside an obstacle (the latter when called).
    """

    def __init__(
        self,
        robot: Robot,
        goal: Any,
        *,
        frame: str | None = None,
        obstacles: Sequence[Any] = (),
        k_attract: float = 10.0,
        conic_distance: float = 0.5,
        k_repulse: float = 0.1,
        influence: float = 0.5,
        kd: Any = None,
        gravity_compensation: bool = True,
        goal_tolerance: float = 0.01,
        stall_speed: float = 0.02,
        stall_ratio: float = 0.1,
        stall_time: float = 0.5,
        escape: bool = True,
        escape_force: float | None = None,
        escape_time: float = 1.0,
        seed: int = 0,
    ):
        _refuse_floating_base(robot, "the potential field")
        self.robot = robot
        self._model, self._data = robot.model, robot.model.createData()
        self.frame = frame
        if frame is None:
            if robot.nq != robot.nv or not robot.space.is_flat:
                raise InvalidArgumentError(
                    f"a potential field without a frame acts on q itself, which must be a plain vector (revolute "
                    f"and prismatic joints only); robot '{robot.name}' has nq = {robot.nq}, nv = {robot.nv}: pass "
                    "frame=... for a task-space field"
                )
            self.dimension = robot.nq
            self._frame_id = -1
        else:
            if not isinstance(frame, str) or not self._model.existFrame(frame):
                names = [f.name for f in self._model.frames]
                raise InvalidArgumentError(f"robot '{robot.name}' has no frame {frame!r} ({name_hint(frame, names)})")
            self.dimension = 3
            self._frame_id = self._model.getFrameId(frame)
        d = self.dimension
        goal = _real_array(goal, "goal")
        if goal.shape != (d,):
            space = "a point in space" if frame is not None else "a configuration: pass frame=... for a point in space"
            raise InvalidArgumentError(f"goal must have shape ({d},) ({space}), got {goal.shape}")
        self.goal = goal
        self.obstacle_centers, self.obstacle_radii = _obstacles(obstacles, d)
        self.k_attract = _positive(k_attract, "k_attract")
        self.conic_distance = _positive(conic_distance, "conic_distance")
        self.k_repulse = _positive(k_repulse, "k_repulse", allow_zero=True)
        self.influence = _positive(influence, "influence")
        inside = self._surface_distance(self.goal) <= 0
        if np.any(inside):
            i = int(np.argmax(inside))
            raise InvalidArgumentError(f"goal {self.goal.tolist()} is inside obstacle {i} (distance <= radius)")
        self.kd = self._default_damping() if kd is None else _gain(kd, robot.nv, "kd")
        self.gravity_compensation = bool(gravity_compensation)
        self.goal_tolerance = _positive(goal_tolerance, "goal_tolerance")
        self.stall_speed = _positive(stall_speed, "stall_speed")
        self.stall_ratio = _positive(stall_ratio, "stall_ratio")
        self.stall_time = _positive(stall_time, "stall_time", allow_zero=True)
        self.escape = bool(escape)
        max_pull = self.k_attract * self.conic_distance
        self.escape_force = 2.0 * max_pull if escape_force is None else _positive(escape_force, "escape_force")
        self.escape_time = _positive(escape_time, "escape_time")
        if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
            raise InvalidArgumentError(f"seed must be a whole number, got {seed!r}")
        self.seed = int(seed)
        self.reset()

    # -- the field itself (vectorised, for plots and checks) --
    def _surface_distance(self, x: np.ndarray) -> np.ndarray:
        """ρ_i for each obstacle, shape (..., m)."""
        offsets = np.asarray(x, dtype=float)[..., None, :] - self.obstacle_centers
        return np.linalg.norm(offsets, axis=-1) - self.obstacle_radii

    def potential(self, x: Any) -> np.ndarray:
        """U(x) [J]: shape x.shape[:-1] for points x of shape (..., d); +inf inside an obstacle."""
        x = np.asarray(x, dtype=float)
        d = np.linalg.norm(x - self.goal, axis=-1)
        k, dc = self.k_attract, self.conic_distance
        attract = np.where(d <= dc, 0.5 * k * d**2, k * dc * d - 0.5 * k * dc**2)
        if not len(self.obstacle_radii):
            return attract
        rho = self._surface_distance(x)
        with np.errstate(divide="ignore", invalid="ignore"):
            close = np.where(rho < self.influence, 0.5 * self.k_repulse * (1.0 / rho - 1.0 / self.influence) ** 2, 0.0)
        repulse = np.where(rho > 0, close, np.inf).sum(axis=-1)
        return attract + repulse

    def forces(self, x: Any) -> tuple[np.ndarray, np.ndarray]:
        """(attraction, repulsion) = (−∇U_att, −∇U_rep) at one point x (d,) [N]; each shape (d,).

        Inside an obstacle (or on its surface) the repulsion is taken at a distance of 0.001 influence from the
        surface, so it stays finite and points outwards.
        """
        x = np.asarray(x, dtype=float)
        offset = x - self.goal
        dist = _norm(offset)
        k, dc = self.k_attract, self.conic_distance
        attract = -k * offset if dist <= dc else -(k * dc / dist) * offset
        if not len(self.obstacle_radii):
            return attract, np.zeros(self.dimension)
        away = x - self.obstacle_centers  # (m, d)
        norms = np.sqrt(np.einsum("ij,ij->i", away, away))
        rho = norms - self.obstacle_radii
        near = rho < self.influence
        if not near.any():
            return attract, np.zeros(self.dimension)
        away, norms, rho = away[near], norms[near], np.maximum(rho[near], 1e-3 * self.influence)
        # At an obstacle's very centre any direction is outwards: take the first axis.
        directions = np.where(
            norms[:, None] > 0, away / np.where(norms > 0, norms, 1.0)[:, None], np.eye(1, away.shape[1])
        )
        size = self.k_repulse * (1.0 / rho - 1.0 / self.influence) / rho**2
        return attract, size @ directions

    def position(self, q: Any) -> np.ndarray:
        """The point x(q) the field acts on, shape (d,) [m]: q itself, or the frame's world position."""
        q = self.robot.check_q(q)
        if self._frame_id < 0:
            return q.copy()
        pin.framesForwardKinematics(self._model, self._data, q)
        return self._data.oMf[self._frame_id].translation.copy()

    def _default_damping(self) -> np.ndarray:
        if self._frame_id < 0:
            M = pin.crba(self._model, self._data, self.goal)
            return 2.0 * np.sqrt(self.k_attract * np.diag(M))
        q = self.robot.neutral()
        M = pin.crba(self._model, self._data, q)
        J = pin.computeFrameJacobian(self._model, self._data, q, self._frame_id, _LWA)[:3]
        # 0.1 m: joints that do not move the frame (a wrist roll) still get some damping.
        lever = np.maximum(np.linalg.norm(J, axis=0), 0.1)
        return np.sqrt(self.k_attract * np.diag(M)) * lever

    # -- the controller --
    def reset(self) -> None:
        """Forget the run: no stall, no push, no recorded local minimum; the random generator reseeded."""
        self._rng = np.random.default_rng(self.seed)
        self._watch = _Watch()

    @property
    def local_minima(self) -> list[LocalMinimum]:
        """The local minima detected since the last reset, in order."""
        return list(self._watch.events)

    def __call__(self, t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Joint torques [N·m or N], shape (nv,)."""
        if t < self._watch.last_t:  # time went back: a new run with the same controller
            self.reset()
        watch = self._watch
        watch.last_t = t
        if self._frame_id < 0:
            x, x_dot, J = q, v, None
        else:
            J = pin.computeFrameJacobian(self._model, self._data, q, self._frame_id, _LWA)[:3]
            x = self._data.oMf[self._frame_id].translation.copy()  # updated by computeFrameJacobian
            x_dot = J @ v
        watch.position = np.array(x)
        attract, repulse = self.forces(x)
        force = attract + repulse
        self._watch_for_stall(t, x, x_dot, force, attract)
        if watch.push is not None and t < watch.push_until:
            force = force + watch.push
        tau = force.copy() if J is None else J.T @ force
        tau -= self.kd * v
        if self.gravity_compensation:
            tau += pin.computeGeneralizedGravity(self._model, self._data, q)
        return tau

    def _watch_for_stall(self, t: float, x: Any, x_dot: Any, force: np.ndarray, attract: np.ndarray) -> None:
        watch = self._watch
        if t < watch.push_until:  # being pushed: not a stall
            return
        far = _norm(np.asarray(x) - self.goal) > self.goal_tolerance
        slow = _norm(x_dot) < self.stall_speed
        balanced = _norm(force) < self.stall_ratio * _norm(attract)
        if not (far and slow and balanced):
            watch.stall_since, watch.reported = None, False
            return
        if watch.stall_since is None:
            watch.stall_since = t
        if t - watch.stall_since < self.stall_time or watch.reported:
            return
        push = None
        if self.escape:
            direction = self._rng.normal(size=self.dimension)  # isotropic Gaussian, normalized: uniform direction
            push = self.escape_force * direction / np.linalg.norm(direction)
            watch.push, watch.push_until = push, t + self.escape_time
            watch.stall_since = None
        else:
            watch.reported = True
        watch.events.append(LocalMinimum(t=float(t), position=np.array(x, dtype=float), push=push))

    def summary(self) -> str:
        """Distance to the goal at the last call and the local minima met, in one line."""
        watch = self._watch
        if watch.position is None:
            return "potential field: not called"
        distance = float(np.linalg.norm(watch.position - self.goal))
        arrived = "reached the goal" if distance <= self.goal_tolerance else "short of the goal"
        events = watch.events
        minima = f"{len(events)} local minim{'um' if len(events) == 1 else 'a'} detected"
        if events:
            at = ", ".join(f"{e.t:.3g}" for e in events[:5]) + (", ..." if len(events) > 5 else "")
            minima += f" (t = {at} s){', escaped by random pushes' if self.escape else ''}"
        return f"potential field: {arrived} (distance {distance:.3g}); {minima}"


def _norm(a: np.ndarray) -> float:
    """Euclidean norm of a small vector (np.linalg.norm costs more than the arithmetic here)."""
    return math.sqrt(float(a @ a))


def _obstacles(obstacles: Any, d: int) -> tuple[np.ndarray, np.ndarray]:
    """(centers (m, d), radii (m,)) from pairs (center, radius) or rows of d + 1 numbers."""
    if not isinstance(obstacles, (list, tuple, np.ndarray)):
        raise InvalidArgumentError(
            f"obstacles must be a list of (center, radius) pairs or rows of {d + 1} numbers, "
            f"got {type(obstacles).__name__}"
        )
    centers, radii = [], []
    for i, item in enumerate(obstacles):
        if isinstance(item, tuple) and len(item) == 2 and np.ndim(item[0]) == 1:
            center = _vector(item[0], d, f"obstacles[{i}] center")
            radius = _positive(item[1], f"obstacles[{i}] radius")
        else:
            row = _real_array(item, f"obstacles[{i}]")
            if row.shape != (d + 1,):
                raise InvalidArgumentError(
                    f"obstacles[{i}] must be (center, radius) or {d + 1} numbers (center then radius), "
                    f"got shape {row.shape}"
                )
            center, radius = row[:d], _positive(row[d], f"obstacles[{i}] radius")
        centers.append(center)
        radii.append(radius)
    return np.array(centers, dtype=float).reshape(-1, d), np.array(radii, dtype=float)


# ---- registry for the command line ---------------------------------------------------------------------
_KINDS = {
    "number": "a number",
    "gain": "a number or comma-separated numbers",
    "vector": "comma-separated numbers",
    "rows": "comma-separated numbers (repeat the parameter for several)",
    "text": "a word",
    "flag": "true or false",
    "integer": "a whole number",
}


@dataclass(frozen=True)
class Parameter:
    """One KEY=VALUE parameter of a built-in controller.

    Attributes:
        name: the key.
        kind: how VALUE is read: "number", "gain" (a number or a vector), "vector" (comma-separated numbers),
            "rows" (a vector per occurrence; the key may repeat), "text", "flag" (true/false), "integer".
        help: meaning and units.
        required: whether the controller needs it.
    """

    name: str
    kind: str
    help: str
    required: bool = False

    def parse(self, texts: list[str]) -> Any:
        """The Python value of this parameter's occurrences (several only for "rows")."""
        if self.kind == "rows":
            return [self._numbers(text) for text in texts]
        if len(texts) > 1:
            raise InvalidArgumentError(f"parameter {self.name} given {len(texts)} times (give it once)")
        text = texts[0].strip()
        if self.kind == "text":
            if not text:
                raise InvalidArgumentError(f"parameter {self.name}: empty value")
            return text
        if self.kind == "flag":
            words = {"true": True, "yes": True, "1": True, "false": False, "no": False, "0": False}
            if text.lower() not in words:
                raise InvalidArgumentError(f"parameter {self.name}: '{text}' is not true or false")
            return words[text.lower()]
        if self.kind == "integer":
            try:
                return int(text)
            except ValueError:
                raise InvalidArgumentError(f"parameter {self.name}: '{text}' is not a whole number") from None
        numbers = self._numbers(text)
        if self.kind == "number":
            if numbers.shape != (1,):
                raise InvalidArgumentError(f"parameter {self.name}: expected one number, got {len(numbers)}")
            return float(numbers[0])
        if self.kind == "gain" and numbers.shape == (1,):
            return float(numbers[0])
        return numbers

    def _numbers(self, text: str) -> np.ndarray:
        values = []
        for token in text.split(","):
            try:
                values.append(float(token))
            except ValueError:
                raise InvalidArgumentError(
                    f"parameter {self.name}: '{token.strip()}' is not a number (vectors are comma-separated, "
                    f"e.g. {self.name}=1,2.5,-3)"
                ) from None
        return np.array(values)


@dataclass(frozen=True)
class ControllerSpec:
    """A built-in controller as the command line sees it.

    Attributes:
        name: registry name (``--controller NAME``).
        description: one line.
        factory: ``factory(robot, **parameters) -> controller``.
        parameters: what ``--param KEY=VALUE`` accepts.
    """

    name: str
    description: str
    factory: Callable[..., Any]
    parameters: tuple[Parameter, ...]

    def parameter_list(self) -> str:
        """The parameter names, required ones marked: "kd, kp (required), q_ref (required), v_ref"."""
        return ", ".join(
            p.name + (" (required)" if p.required else "") for p in sorted(self.parameters, key=lambda p: p.name)
        )


def _pd_parameters() -> tuple[Parameter, ...]:
    return (
        Parameter("q_ref", "vector", "target configuration, nq numbers [rad or m]", required=True),
        Parameter("kp", "gain", "stiffness [N·m/rad or N/m]: one number or one per actuated joint", required=True),
        Parameter("kd", "gain", "damping [N·m·s/rad]: one number or one per joint (default: critical per joint)"),
        Parameter("v_ref", "vector", "target velocity, nv numbers [rad/s or m/s] (default: 0)"),
    )


def _computed_torque(robot: Robot, **params: Any) -> ComputedTorque:
    waypoints = params.pop("waypoint")
    if len(waypoints) < 2:
        raise InvalidArgumentError(f"needs at least 2 waypoints (repeat waypoint=...), got {len(waypoints)}")
    for i, point in enumerate(waypoints):
        if len(point) != robot.nq:
            raise InvalidArgumentError(f"waypoint {i} must have nq = {robot.nq} numbers, got {len(point)}")
    times = params.pop("times", None)
    if times is None:  # one second per leg unless told
        times = np.arange(len(waypoints), dtype=float)
    return ComputedTorque(robot, times, np.array(waypoints), **params)


def _potential_field(robot: Robot, **params: Any) -> PotentialField:
    params["obstacles"] = params.pop("obstacle", ())
    return PotentialField(robot, **params)


CONTROLLERS: dict[str, ControllerSpec] = {
    spec.name: spec
    for spec in [
        ControllerSpec("pd", "PD to a setpoint (no gravity compensation)", PD, _pd_parameters()),
        ControllerSpec("gravity_compensation", "hold the robot against gravity: tau = g(q)", GravityCompensation, ()),
        ControllerSpec("pd_gravity", "PD to a setpoint plus gravity compensation", PDGravity, _pd_parameters()),
        ControllerSpec(
            "computed_torque",
            "computed-torque tracking of a cubic spline through waypoints",
            _computed_torque,
            (
                Parameter("waypoint", "rows", "a configuration, nq numbers; repeat for each waypoint", required=True),
                Parameter("times", "vector", "waypoint times [s] (default: 0, 1, 2, ...)"),
                Parameter("kp", "gain", "error stiffness [1/s²] (default: 100)"),
                Parameter("kd", "gain", "error damping [1/s] (default: 2 sqrt(kp))"),
                Parameter("bc_type", "text", "spline ends: clamped (default) or natural"),
            ),
        ),
        ControllerSpec(
            "potential_field",
            "attraction to a goal, repulsion from spheres, local-minimum escape",
            _potential_field,
            (
                Parameter("goal", "vector", "goal point: nq numbers, or x,y,z [m] with frame", required=True),
                Parameter("frame", "text", "frame whose position the field acts on (default: q itself)"),
                Parameter("obstacle", "rows", "a sphere: center then radius [m]; repeat for each obstacle"),
                Parameter("k_attract", "number", "attraction stiffness [N/m] (default: 10)"),
                Parameter("conic_distance", "number", "distance beyond which the pull is constant [m] (default 0.5)"),
                Parameter("k_repulse", "number", "repulsion gain [N·m] (default: 0.1)"),
                Parameter("influence", "number", "reach of the repulsion from a surface [m] (default: 0.5)"),
                Parameter("kd", "gain", "joint damping (default: critical per joint)"),
                Parameter("gravity_compensation", "flag", "add g(q) (default: true)"),
                Parameter("goal_tolerance", "number", "arrival distance [m] (default: 0.01)"),
                Parameter("stall_speed", "number", "speed below which a stall is possible [m/s] (default: 0.02)"),
                Parameter("stall_ratio", "number", "net over attractive force below which ... (default: 0.1)"),
                Parameter("stall_time", "number", "how long a stall lasts before it is declared [s] (default 0.5)"),
                Parameter("escape", "flag", "push out of local minima (default: true)"),
                Parameter(
                    "escape_force", "number", "size of the random push [N] (default: 2 k_attract conic_distance)"
                ),
                Parameter("escape_time", "number", "duration of each push [s] (default: 1)"),
                Parameter("seed", "integer", "seed of the push directions (default: 0)"),
            ),
        ),
    ]
}


def make_controller(name: str, robot: Robot, params: Sequence[str] = ()) -> Any:
    """A built-in controller from its registry name and ``KEY=VALUE`` strings (the command line's way).

    Vectors are comma-separated numbers (``q_ref=0,-1.2,1,0,0,0``); a gain is one number or a vector;
    "rows" parameters (``waypoint``, ``obstacle``) repeat, one vector each.

    Args:
        name: a key of :data:`CONTROLLERS`.
        robot: the robot the controller drives.
        params: ``KEY=VALUE`` strings.

    The controller's ``recipe`` is (name, its ``KEY=VALUE`` strings sorted by key): what it was made from (the
    pilot study of ``run --tolerance`` keys its cache on it).

    Raises:
        UnknownNameError: the name is not a built-in controller (the message lists them).
        InvalidArgumentError: a malformed, unknown, repeated, missing or invalid parameter (the message names
            it and lists the valid ones).
    """
    check_text(name, "name", optional=False)
    check_system(robot, "robot")
    if isinstance(params, (str, bytes)) or not isinstance(params, (list, tuple)):
        raise InvalidArgumentError(f"params must be a list of KEY=VALUE strings, got {type(params).__name__}")
    spec = CONTROLLERS.get(name)
    if spec is None:
        close = difflib.get_close_matches(name, CONTROLLERS, n=1, cutoff=0.5)
        hint = f"did you mean {close[0]}? " if close else ""
        raise UnknownNameError(f"unknown controller '{name}' ({hint}valid: {', '.join(sorted(CONTROLLERS))})")
    by_name = {p.name: p for p in spec.parameters}
    given: dict[str, list[str]] = {}
    for item in params:
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or not key:
            raise InvalidArgumentError(
                f"controller parameter '{item}' is not KEY=VALUE (parameters of {name}: {_listing(spec)})"
            )
        if key not in by_name:
            close = difflib.get_close_matches(key, by_name, n=1, cutoff=0.5)
            hint = f"did you mean {close[0]}? " if close else ""
            raise InvalidArgumentError(
                f"controller '{name}' has no parameter '{key}' ({hint}parameters: {_listing(spec)})"
            )
        given.setdefault(key, []).append(value)
    missing = [p.name for p in spec.parameters if p.required and p.name not in given]
    if missing:
        raise InvalidArgumentError(
            f"controller '{name}' needs {', '.join(f'{m}=...' for m in missing)} (parameters: {_listing(spec)})"
        )
    try:
        values = {key: by_name[key].parse(texts) for key, texts in given.items()}
        controller = spec.factory(robot, **values)
    except InvalidArgumentError as exc:
        raise InvalidArgumentError(f"controller '{name}': {exc}") from None
    # What it was made from, for the caches that key on it (run --tolerance's pilot study): the parameters by name,
    # a repeated one's values in their order (waypoints), each as given.
    controller.recipe = (name, [f"{key}={text}" for key in sorted(given) for text in given[key]])
    return controller


def _listing(spec: ControllerSpec) -> str:
    return spec.parameter_list() or "none"
