"""Robot: dynamics terms and energies of one Pinocchio model (pure maths, no stepping, no files)."""

from __future__ import annotations

import difflib
from typing import Any

import numpy as np
import pinocchio as pin

from .exceptions import InvalidArgumentError, UnknownNameError
from .ordered import ordered_dot
from .state import ConfigurationSpace

_WORLD = pin.Convention.WORLD
_UNBOUNDED = 1e300  # Pinocchio writes ±DBL_MAX for "no limit"
# A coordinate counts as outside its limits only beyond LIMIT_TOLERANCE_ULPS machine epsilons (a few units in the
# last place) of the limit's scale max(|lower|, |upper|, 1): round-off in the dynamics moves a coordinate resting
# on a limit by ~1e-19 (panda's fingers at 0 m), which is no violation. 8 eps is 1.8e-15 rad or m.
LIMIT_TOLERANCE_ULPS = 8


class Robot:
    """A rigid multibody system loaded from a URDF: M(q), C(q, v), g(q), energies and forward dynamics.

    Equations of motion: ``M(q) v' + C(q, v) v + g(q) = tau - D v`` with D the joint viscous damping
    (diagonal, from the URDF's ``<dynamics damping>``; zero when loaded with ``damping=False``).
    For a floating base, q = [x y z qx qy qz qw, joints...] and v = [linear, angular (base frame),
    joints...], so q' != v; the first 6 entries of tau act on the unactuated base and must be zero.

    Build one with :func:`multibody_sim.load_robot`.

    Attributes:
        name: catalog name or URDF file stem.
        model, data: the underlying Pinocchio objects, for experts.
        nq, nv: configuration and velocity sizes.
        joint_names: movable joints in velocity order (a floating base's root joint first).
        dof_names: one name per velocity coordinate, length nv.
        floating_base: whether the root is a free-flyer joint.
        damping: joint viscous damping coefficients D [N·m·s/rad or N·s/m], shape (nv,).
        effort_limit: |tau| bounds [N·m or N], shape (nv,); inf where the URDF gives none (or 0).
        velocity_limit: |v| bounds the URDF declares [rad/s or m/s], shape (nv,); inf where it gives none (or 0).
            Shown by `inspect`; a scene's [[actuator]]s take them as their defaults.
        lower_limit, upper_limit: position limits, shape (nq,); ±inf where there is none.
        limit_tolerance: how far past a limit a coordinate may lie before it counts as a violation (round-off),
            shape (nq,): LIMIT_TOLERANCE_ULPS x machine epsilon x max(|lower|, |upper|, 1); inf where there is no limit.
        limit_drift: how fast the tolerance grows with time [rad/s or m/s], shape (nq,): zero for a robot; a contact
            scene's coordinates whose velocity its contact solve holds (enforced limits, exact joint friction) drift
            by up to the solve's accuracy every second (scenes.contact.HELD_DRIFT_RATE).
        space: the configuration manifold (integrate, difference).
        source: how the robot was loaded (the full load_robot arguments, URDF path and SHA-256).
        poses: names of the named poses (pose(name) gives one); default_pose_name: the one default_pose() returns,
            or None (neutral()).
    """

    def __init__(
        self,
        model: pin.Model,
        *,
        name: str,
        floating_base: bool,
        damping: bool = True,
        always_damped: bool = False,
        source: dict[str, Any] | None = None,
        poses: dict[str, np.ndarray] | None = None,
        default_pose: str | None = None,
        space: ConfigurationSpace | None = None,
    ):
        self.model = model
        self.data = model.createData()
        self.name = name
        self.floating_base = floating_base
        self.source = dict(source or {})
        # the configuration space depends on the joints only: a model of the same joints may lend its own
        self.space = ConfigurationSpace(model) if space is None else space
        self.nq = model.nq
        self.nv = model.nv
        self.joint_names = [model.names[i] for i in range(1, model.njoints) if model.joints[i].nv > 0]
        self.dof_names = _dof_names(model)
        self.damping = np.array(model.damping, dtype=float) if damping else np.zeros(self.nv)
        if floating_base:
            self.damping[:6] = 0.0
        # The term -D v and its ledger line joint_damping: where D has a nonzero entry, or always (always_damped: a
        # scene whose [randomize] draws damping has that line in every row, D = 0 or not).
        self._damped = always_damped or bool(np.any(self.damping))
        self.effort_limit = _effort_limits(model, floating_base)
        self.velocity_limit = _effort_limits(model, floating_base, "velocityLimit")
        self.lower_limit, self.upper_limit = _position_limits(model)
        self._limited = np.isfinite(self.lower_limit)
        scale = np.maximum(np.maximum(np.abs(self.lower_limit), np.abs(self.upper_limit)), 1.0)
        self.limit_tolerance = np.where(self._limited, LIMIT_TOLERANCE_ULPS * np.finfo(float).eps * scale, np.inf)
        self.limit_drift = np.zeros(self.nq)
        self._n_base = 6 if floating_base else 0
        # The actuated velocity coordinates: all but a floating base's 6 (a scene's free objects are left out too).
        self.actuated = slice(self._n_base, self.nv)
        self.total_mass = float(pin.computeTotalMass(model))
        self._poses = {name: self.check_q(q, f"pose '{name}'").copy() for name, q in (poses or {}).items()}
        if default_pose is not None and default_pose not in self._poses:
            raise InvalidArgumentError(f"default_pose '{default_pose}' is not one of the poses ({self._valid_poses()})")
        self.default_pose_name = default_pose

    def __repr__(self) -> str:
        base = "floating" if self.floating_base else "fixed"
        return f"Robot({self.name!r}, nq={self.nq}, nv={self.nv}, base={base})"

    # ---- configurations ------------------------------------------------------------------------------
    def neutral(self) -> np.ndarray:
        """The neutral configuration (zero joint angles, identity base orientation), shape (nq,)."""
        return pin.neutral(self.model)

    @property
    def poses(self) -> tuple[str, ...]:
        """The names of the robot's named poses (its SRDF's `<group_state>`s), in file order; () without one."""
        return tuple(self._poses)

    def pose(self, name: str) -> np.ndarray:
        """The named pose `name` (one of `poses`), shape (nq,); a fresh copy.

        Raises:
            UnknownNameError: no pose of that name (the message lists the valid ones).
        """
        if not isinstance(name, str):
            raise InvalidArgumentError(f"name must be a pose name (a string), got {type(name).__name__}")
        if name not in self._poses and not self._poses:
            raise UnknownNameError(
                f"unknown pose '{name}': {self.name} has no named poses (they come from an SRDF: srdf=FILE in "
                "load_robot, --srdf FILE on the command line)"
            )
        if name not in self._poses:
            close = difflib.get_close_matches(str(name), self._poses, n=1, cutoff=0.6)
            hint = f"did you mean {close[0]}? " if close else ""
            raise UnknownNameError(f"unknown pose '{name}' for {self.name} ({hint}valid: {self._valid_poses()})")
        return self._poses[name].copy()

    def default_pose(self) -> np.ndarray:
        """Where runs start by default, shape (nq,): the SRDF's everyday pose (`default_pose_name`: the catalog's
        reference pose, else "default", "standing" or "half_sitting" when the SRDF has one), else neutral()."""
        if self.default_pose_name is None:
            return self.neutral()
        return self._poses[self.default_pose_name].copy()

    def _valid_poses(self) -> str:
        return ", ".join(self._poses) if self._poses else "none"

    def random_configuration(self, rng: np.random.Generator | int | None = None) -> np.ndarray:
        """A random configuration, shape (nq,).

        Uniform within finite joint limits and in [-pi, pi] where there is none; a uniformly random unit
        quaternion for spherical joints and the floating base, whose position is uniform in [-1, 1]^3 m.
        """
        if not (rng is None or isinstance(rng, np.random.Generator) or type(rng) is int or isinstance(rng, np.integer)):
            raise InvalidArgumentError(f"rng must be a numpy Generator, a whole-number seed or None, got {rng!r}")
        rng = np.random.default_rng(rng)
        q = self.neutral()
        for joint in self.model.joints[1:]:
            i, nq, nv = joint.idx_q, joint.nq, joint.nv
            if nq == nv:  # plain coordinates (revolute, prismatic, translation, spherical-ZYX, ...)
                lo = np.where(np.isfinite(self.lower_limit[i : i + nq]), self.lower_limit[i : i + nq], -np.pi)
                hi = np.where(np.isfinite(self.upper_limit[i : i + nq]), self.upper_limit[i : i + nq], np.pi)
                q[i : i + nq] = rng.uniform(lo, hi)
            elif (nq, nv) == (2, 1):  # continuous joint: (cos, sin)
                angle = rng.uniform(-np.pi, np.pi)
                q[i : i + 2] = np.cos(angle), np.sin(angle)
            elif (nq, nv) == (4, 3) and joint.shortname() == "JointModelPlanar":
                angle = rng.uniform(-np.pi, np.pi)
                q[i : i + 4] = *rng.uniform(-1.0, 1.0, 2), np.cos(angle), np.sin(angle)
            elif (nq, nv) == (4, 3):  # spherical: unit quaternion (x, y, z, w)
                q[i : i + 4] = _random_unit_quaternion(rng)
            elif (nq, nv) == (7, 6):  # free-flyer: position then unit quaternion
                q[i : i + 3] = rng.uniform(-1.0, 1.0, 3)
                q[i + 3 : i + 7] = _random_unit_quaternion(rng)
            else:
                raise InvalidArgumentError(f"random_configuration: unsupported joint type {joint.shortname()}")
        return q

    def integrate(self, q: Any, dv: Any) -> np.ndarray:
        """q ⊕ dv on the configuration manifold, shape (nq,)."""
        return self.space.integrate(self.check_q(q), self.check_v(dv, "dv"))

    def difference(self, q0: Any, q1: Any) -> np.ndarray:
        """q1 ⊖ q0 in the tangent space, shape (nv,)."""
        return self.space.difference(self.check_q(q0, "q0"), self.check_q(q1, "q1"))

    # ---- dynamics terms ------------------------------------------------------------------------------
    def mass_matrix(self, q: Any) -> np.ndarray:
        """Joint-space inertia matrix M(q) [kg·m², kg], shape (nv, nv), symmetric positive definite."""
        M = pin.crba(self.model, self.data, self.check_q(q))
        return np.triu(M) + np.triu(M, 1).T

    def coriolis_matrix(self, q: Any, v: Any) -> np.ndarray:
        """Coriolis matrix C(q, v), shape (nv, nv): C v is the Coriolis/centrifugal term, Ṁ - 2C is skew."""
        return pin.computeCoriolisMatrix(self.model, self.data, self.check_q(q), self.check_v(v)).copy()

    def gravity(self, q: Any) -> np.ndarray:
        """Generalized gravity g(q) [N·m, N], shape (nv,)."""
        return pin.computeGeneralizedGravity(self.model, self.data, self.check_q(q)).copy()

    def nonlinear_effects(self, q: Any, v: Any) -> np.ndarray:
        """C(q, v) v + g(q), shape (nv,) (without damping)."""
        return pin.nonLinearEffects(self.model, self.data, self.check_q(q), self.check_v(v)).copy()

    def forward_dynamics(self, q: Any, v: Any, tau: Any) -> np.ndarray:
        """Accelerations v' = M^-1 (tau - D v - C v - g), shape (nv,), by the articulated-body algorithm."""
        return self.unchecked_forward_dynamics(self.check_q(q), self.check_v(v), self.check_tau(tau))

    def inverse_dynamics(self, q: Any, v: Any, a: Any) -> np.ndarray:
        """Torques tau = M a + C v + g + D v that produce accelerations a, shape (nv,), by RNEA.

        For a floating base the first 6 entries are the wrench the base would need (not an actuator's).
        """
        q, v, a = self.check_q(q), self.check_v(v), self.check_v(a, "a")
        tau = pin.rnea(self.model, self.data, q, v, a).copy()
        return tau + self.damping * v if self._damped else tau

    def unchecked_forward_dynamics(self, q: np.ndarray, v: np.ndarray, tau: np.ndarray, t: float = 0.0) -> np.ndarray:
        """forward_dynamics without argument checks: the stepping loop's hot path (a robot's dynamics ignore t)."""
        if self._damped:
            tau = tau - self.damping * v
        return pin.aba(self.model, self.data, q, v, tau, _WORLD)

    def unchecked_dynamics_derivatives(
        self, q: np.ndarray, v: np.ndarray, tau: np.ndarray, t: float = 0.0
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Analytic partial derivatives of forward dynamics (damping included), from Pinocchio's ABA derivatives.

        Returns:
            (da_dq, da_dv, da_dtau), each shape (nv, nv); da_dq is taken in the tangent space at q (a variation
            dq moves q to q ⊕ dq), and da_dtau = M(q)^-1.
        """
        if self._damped:
            tau = tau - self.damping * v
        da_dq, da_dv, da_dtau = pin.computeABADerivatives(self.model, self.data, q, v, tau)
        da_dq, da_dv, da_dtau = da_dq.copy(), da_dv.copy(), da_dtau.copy()
        if self._damped:
            da_dv -= da_dtau * self.damping  # a depends on v through tau - D v as well
        return da_dq, da_dv, da_dtau

    # ---- energies ------------------------------------------------------------------------------------
    def kinetic_energy(self, q: Any, v: Any) -> float:
        """T = ½ vᵀ M(q) v [J]."""
        return float(pin.computeKineticEnergy(self.model, self.data, self.check_q(q), self.check_v(v)))

    def potential_energy(self, q: Any) -> float:
        """Gravitational potential energy V(q) [J], zero at world z = 0 (bodies welded to the world excluded)."""
        return float(pin.computePotentialEnergy(self.model, self.data, self.check_q(q)))

    def total_energy(self, q: Any, v: Any) -> float:
        """Hamiltonian H = T + V [J]."""
        return self.kinetic_energy(q, v) + self.potential_energy(q)

    @property
    def damped(self) -> bool:
        """Whether the joint damping term -D v (and its ledger line, joint_damping) is in play."""
        return self._damped

    # Ledger: the power flowing in (work) or out (dissipated) through each element, integrated by the
    # integrator with its own quadrature so that the ledger is as accurate as the trajectory.
    @property
    def ledger_elements(self) -> list[tuple[str, str]]:
        """(name, kind) of every energy-ledger element, kind "work" (in) or "dissipated" (out)."""
        elements = [("joint_torques", "work")]
        if self._damped:
            elements.append(("joint_damping", "dissipated"))
        return elements

    def ledger_power(
        self, q: np.ndarray, v: np.ndarray, tau: np.ndarray, out: np.ndarray | None = None, t: float = 0.0
    ) -> np.ndarray:
        """Power of each ledger element [W] at (q, v, tau), in ledger_elements order (no checks).

        Writes into `out` (shape (n_elements,)) when given, so the stepping loop allocates nothing.
        """
        if out is None:
            out = np.empty(2 if self._damped else 1)
        out[0] = ordered_dot(tau, v)  # in index order, as the native kernel sums (ordered.py)
        if self._damped:
            out[1] = ordered_dot(v, self.damping * v)
        return out

    def unchecked_energies(self, q: np.ndarray, v: np.ndarray) -> tuple[float, float]:
        """(T, V) [J] without argument checks."""
        pin.forwardKinematics(self.model, self.data, q, v)  # once, for both energies
        return float(pin.computeKineticEnergy(self.model, self.data)), float(
            pin.computePotentialEnergy(self.model, self.data)
        )

    # What a system records at each sample besides the state and energies: (category, name, width) with category
    # "potential" (a spring's stored energy) or "constraint" (forces, then drift and velocity drift). A robot alone
    # records nothing; scenes do.
    record_fields: tuple[tuple[str, str, int], ...] = ()

    def unchecked_record(self, q: np.ndarray, v: np.ndarray, tau: np.ndarray, t: float, out: np.ndarray) -> None:
        """Write the record_fields' values at a sample into `out` (a robot has none)."""

    @property
    def energy_scale(self) -> float:
        """A natural energy unit [J]: lifting the whole robot by one metre (floor for blow-up detection)."""
        return max(self.total_mass * float(np.linalg.norm(self.model.gravity.linear)), 1e-6)

    # ---- limits --------------------------------------------------------------------------------------
    def limit_excess(self, Q: np.ndarray, *, columns: np.ndarray | None = None, t: Any = None) -> np.ndarray:
        """How far each configuration coordinate is outside its position limits, shape like Q (0 inside).

        Round-off is not a violation: an excess counts (and is returned as it is) only when it exceeds
        `limit_tolerance + limit_drift t`: LIMIT_TOLERANCE_ULPS (8) machine epsilons times max(|lower|, |upper|, 1)
        for that coordinate, a few units in the last place (1.8e-15 rad or m for limits within ±1), and on a
        coordinate a contact solve holds, what the solve's accuracy lets it drift by time t.

        Args:
            Q: one configuration (nq,) or a stack of them (n, nq); with `columns`, only those coordinates.
            columns: the coordinate each column of Q holds (indices), or None for all of them in order.
            t: the time since the run's start [s], broadcastable to Q's rows ((n,) or (n, 1), or like Q); None: 0.
        """
        single = np.ndim(Q) == 1
        Q = np.atleast_2d(np.asarray(Q, dtype=float))
        width = self.nq if columns is None else len(columns)
        if Q.ndim != 2 or Q.shape[1] != width:
            raise InvalidArgumentError(f"Q must have shape ({width},) or (n, {width}), got {np.shape(Q)}")
        excess = np.zeros_like(Q)
        lim = self._limited if columns is None else self._limited[columns]
        if lim.any():
            at = lim if columns is None else np.asarray(columns)[lim]  # the limited coordinates' indices
            outside = np.maximum(self.lower_limit[at] - Q[:, lim], 0.0) + np.maximum(
                Q[:, lim] - self.upper_limit[at], 0.0
            )
            tolerance = self.limit_tolerance[at]
            if t is not None and self.limit_drift[at].any():
                elapsed = np.asarray(t, dtype=float)
                elapsed = elapsed[:, None] if elapsed.ndim == 1 else elapsed[:, lim]
                tolerance = tolerance + self.limit_drift[at] * np.abs(elapsed)
            excess[:, lim] = np.where(outside > tolerance, outside, 0.0)
        return excess[0] if single else excess

    # ---- argument checks ----------------------------------------------------------------------------
    def check_q(self, q: Any, name: str = "q") -> np.ndarray:
        """q as a float array of shape (nq,), finite and normalized, or InvalidArgumentError."""
        q = _as_vector(q, self.nq, name)
        if not self.space.is_normalized(q):
            raise InvalidArgumentError(
                f"{name} is not a valid configuration: its quaternion / (cos, sin) entries must have unit norm"
            )
        return q

    def check_v(self, v: Any, name: str = "v") -> np.ndarray:
        """v as a float array of shape (nv,), finite, or InvalidArgumentError."""
        return _as_vector(v, self.nv, name)

    def check_tau(self, tau: Any, name: str = "tau") -> np.ndarray:
        """tau as a float array of shape (nv,), finite, zero on a floating base's 6 unactuated entries."""
        tau = _as_vector(tau, self.nv, name)
        if self._n_base and np.any(tau[:6]):
            raise InvalidArgumentError(
                f"{name}[0:6] acts on the unactuated floating base and must be zero, got {tau[:6].tolist()}"
            )
        end = self.actuated.stop
        if end < self.nv and np.any(tau[end:]):
            raise InvalidArgumentError(
                f"{name}[{end}:{self.nv}] acts on the scene's free objects, which are unactuated, and must be zero, "
                f"got {tau[end:].tolist()}"
            )
        return tau

    def unactuated_load(self, tau: np.ndarray, *, per_row: bool = False) -> Any:
        """Whether tau (nv,) or rows of it (n, nv) put anything on unactuated coordinates (cheap; no message): a bool,
        or with `per_row` one per row of tau (n, nv), shape (n,)."""
        start, stop = self.actuated.start, self.actuated.stop
        if start == 0 and stop == self.nv:  # every coordinate is actuated
            return np.zeros(tau.shape[:-1], dtype=bool) if per_row else False
        head, tail = tau[..., :start], tau[..., stop:]
        if per_row:
            return head.any(axis=-1) | tail.any(axis=-1)
        return bool(head.any() or tail.any())


def check_system(value: Any, name: str = "system") -> Robot:
    """value if it is a Robot (a Scene is one), else InvalidArgumentError (a robot's name is not the robot)."""
    if not isinstance(value, Robot):
        hint = f" (load it first: load_robot({value!r}) or load_scene({value!r}))" if isinstance(value, str) else ""
        raise InvalidArgumentError(f"{name} must be a Robot or a Scene, got {type(value).__name__}{hint}")
    return value


def real_array(value: Any, name: str, expected: str) -> np.ndarray:
    """value as a float array if it holds real numbers (strings, objects, complex and ragged nesting are refused
    rather than coerced), else InvalidArgumentError: "{name} must be {expected}, got ..."."""
    try:
        raw = np.asarray(value)
    except ValueError:  # ragged nesting
        raw = None
    if raw is None or raw.dtype.kind not in "biuf":
        got = f"dtype {value.dtype}" if isinstance(value, np.ndarray) else type(value).__name__
        raise InvalidArgumentError(f"{name} must be {expected}, got {got}")
    return np.array(raw, dtype=float)


def _as_vector(value: Any, size: int, name: str) -> np.ndarray:
    arr = real_array(value, name, f"an array of {size} real numbers")
    if arr.shape != (size,):
        raise InvalidArgumentError(f"{name} must have shape ({size},), got {arr.shape}")
    if not np.isfinite(arr).all():
        bad = np.flatnonzero(~np.isfinite(arr)).tolist()
        raise InvalidArgumentError(f"{name} must be finite, got non-finite entries at indices {bad}")
    return arr


def _random_unit_quaternion(rng: np.random.Generator) -> np.ndarray:
    x = rng.normal(size=4)  # an isotropic Gaussian, normalized, is uniform on S³
    return x / np.linalg.norm(x)


def _dof_names(model: pin.Model) -> list[str]:
    names = []
    for i in range(1, model.njoints):
        joint, name = model.joints[i], model.names[i]
        if joint.nv == 1:
            names.append(name)
        elif joint.nv == 6:
            names += [f"{name}.{c}" for c in ("vx", "vy", "vz", "wx", "wy", "wz")]
        elif joint.shortname() == "JointModelPlanar":
            names += [f"{name}.{c}" for c in ("vx", "vy", "wz")]
        elif joint.nv == 3 and joint.nq == 4:
            names += [f"{name}.{c}" for c in ("wx", "wy", "wz")]
        else:
            names += [f"{name}[{k}]" for k in range(joint.nv)]
    return names


def _effort_limits(model: pin.Model, floating_base: bool, limits: str = "effortLimit") -> np.ndarray:
    """The model's effort (or velocity: limits="velocityLimit") limits per dof, inf where there is none."""
    effort = np.array(getattr(model, limits), dtype=float)
    effort[(effort <= 0.0) | (effort >= _UNBOUNDED)] = np.inf  # 0 or absent means "no limit"
    if floating_base:
        effort[:6] = np.inf
    return effort


def _position_limits(model: pin.Model) -> tuple[np.ndarray, np.ndarray]:
    """Finite limits only on 1-coordinate joints whose URDF declares a real range (lower < upper)."""
    lower = np.full(model.nq, -np.inf)
    upper = np.full(model.nq, np.inf)
    for joint in model.joints[1:]:
        if joint.nq == 1 and joint.nv == 1:
            i = joint.idx_q
            lo, hi = model.lowerPositionLimit[i], model.upperPositionLimit[i]
            if -_UNBOUNDED < lo < hi < _UNBOUNDED:
                lower[i], upper[i] = lo, hi
    return lower, upper
