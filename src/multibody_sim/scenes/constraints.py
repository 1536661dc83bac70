"""Holonomic constraints (closed loops, world anchors, welds) by Lagrange multipliers with Baumgarte stabilization.

The constrained dynamics are Lagrange's equations of the first kind,

    M(q) a + h(q, v) = tau + Jᵀ λ,        J a + J̇ v = -Kd (J v) - Kp e(q),

with J the constraint Jacobian, λ the constraint forces and e the position residual; the right-hand side of
the second line is Baumgarte's stabilization (zero on the constraint manifold, where e = 0 and J v = 0). The
system is solved by Pinocchio's ``constraintDynamics`` (a sparse Cholesky factorisation of the KKT matrix,
refined by proximal iterations, which keeps redundant rows harmless: a planar loop closed by a 3D point
constraint has an identically zero out-of-plane row).

Constraint frames and signs. Constraint k ties a point (and for welds a frame) c1 on the body of its first
frame to c2 on the body of its second frame (the world for "point"). Its multipliers are the force [N] (and,
for welds, then the torque [N·m] about c1's origin) that the constraint exerts ON THE FIRST FRAME'S BODY at
c1's origin, in world-aligned axes; the second body feels the opposite. So ``Jᵀ λ`` is the generalised
constraint force that enters M a + h = tau + Jᵀ λ, with J (rows of constraint k) the world-aligned Jacobian of
c1 minus that of c2 (a weld's J maps v to the linear then angular velocity of body 1 relative to body 2 at c1).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, NamedTuple

import numpy as np
import pinocchio as pin

from ..exceptions import InvalidArgumentError
from ..text import name_hint

CONSTRAINT_TYPES = ("loop", "point", "weld")
ROWS = {"loop": 3, "point": 3, "weld": 6}
# Critically damped drift, e'' + Kd e' + Kp e = 0 with Kp = ω², Kd = 2ω and ω = 10 /s: drift decays with a
# 0.1 s time constant and no overshoot, fast next to the ~1 s motions of the shipped models, and slow next to any
# step an integrator takes (ω dt = 0.01 at 1 ms, against RK4's real-axis stability limit of 2.8): the correction
# never limits the step nor makes the system stiff. On the constraint manifold it does nothing at all.
DEFAULT_STABILIZATION = (100.0, 20.0)
# Proximal settings of constraintDynamics. Its defaults (mu = 0, one iteration) return NaN as soon as one row is
# redundant (a planar loop's out-of-plane row). mu regularises the Delassus matrix G = J M⁻¹ Jᵀ: each iteration
# shrinks the error by mu / (σ + mu) for the singular values σ of G (1e-7 … 1e2 in SI units on the catalog arms at
# random configurations), so a few iterations reach round-off. Along rows with σ = 0 (redundant rows) an exactly
# consistent right-hand side leaves the multipliers at zero (a planar loop's out-of-plane row); a residual r there
# (round-off, ~1e-15 … 1e-13 m/s², or constraints that disagree in a direction no motion can correct) makes them
# drift by r / mu per iteration along null(Jᵀ), where they change neither the accelerations nor the power. When
# that drift could exceed _MULTIPLIER_TOLERANCE of the multipliers, λ is recomputed by least squares instead.
# Pinocchio's "absolute residual" is not a residual of the KKT system: that criterion is disabled.
_MU = 1e-8
_STEP_TOLERANCE = 1e-10  # [N or N·m]: converged when no multiplier changes by more in one iteration
_MAX_ITER = 10
_MULTIPLIER_TOLERANCE = 1e-6  # relative to (1 + |λ|∞)
_LWA = pin.ReferenceFrame.LOCAL_WORLD_ALIGNED


class _Record(NamedTuple):
    """A validated declaration in plain values: what pickling keeps (Pinocchio's constraint objects do not pickle)."""

    name: str
    type: str
    frames: tuple[str, ...]
    position: tuple[float, float, float] | None
    stabilization: tuple[float, float]


class Constraints:
    """Holonomic constraints on one Pinocchio model, enforced with Lagrange multipliers.

    Args:
        model: the (scene's) Pinocchio model; the constraints keep their own Data workspaces.
        specs: constraint declarations, each with ``.name``, ``.type`` ("loop": two frames' origins coincide,
            3 rows; "point": a frame's origin held at a world point, 3 rows; "weld": two frames held at their
            relative pose at q_ref, 6 rows), ``.frames`` (frame names: two for loop and weld, one for point; the
            frame "universe" is the world), ``.position`` (point only: the anchor [m], shape (3,); None: where the
            frame's origin is at q_ref) and ``.stabilization`` ((Kp [1/s²], Kd [1/s]) Baumgarte gains, or None for
            DEFAULT_STABILIZATION).
        q_ref: the configuration that fixes point anchors (when not given) and weld poses, shape (nq,).

    Attributes:
        names: constraint names, in declaration order.
        types: their types.
        rows: number of multipliers (rows) of each constraint.
        n_rows: total number of rows.
        stabilization: (Kp, Kd) of each constraint.
        ledger: (name, kind) of each constraint's flow element: ("constraint:<name>", "work").
        fallbacks: number of forward_dynamics calls whose multipliers were recomputed by least squares (about
            25 µs more): redundant rows that disagree beyond round-off. Zero for independent constraints and for
            redundancy up to round-off.

    Raises:
        InvalidArgumentError: an unknown type or frame (the message lists the valid ones), a wrong number of
            frames, a bad anchor or gains, duplicate names, frames on one rigid body, q_ref of the wrong shape.
    """

    def __init__(self, model: pin.Model, specs: Sequence[Any], q_ref: np.ndarray):
        q_ref = np.asarray(q_ref, dtype=float)
        if q_ref.shape != (model.nq,) or not np.all(np.isfinite(q_ref)):
            raise InvalidArgumentError(f"q_ref must be a finite array of shape ({model.nq},), got {q_ref.shape}")
        if not specs:
            raise InvalidArgumentError("constraints: at least one constraint is needed")
        self.model = model
        self.data = model.createData()  # constraintDynamics' workspace: nothing else writes into it
        self._probe = model.createData()  # drift(): leaves the latest solve's quantities intact
        pin.framesForwardKinematics(model, self._probe, q_ref)
        self.names: list[str] = []
        self.types: list[str] = []
        self.rows: list[int] = []
        self.stabilization: list[tuple[float, float]] = []
        self._records: list[_Record] = []
        self._q_ref = q_ref.copy()
        self._models = pin.StdVec_RigidConstraintModel()
        for spec in specs:
            self._models.append(self._build(spec))
        self._datas = pin.StdVec_RigidConstraintData()
        for cm in self._models:
            self._datas.append(cm.createData())
        pin.initConstraintDynamics(model, self.data, self._models, self._datas)
        self._settings = pin.ProximalSettings(0.0, _STEP_TOLERANCE, _MU, _MAX_ITER)
        self.n_rows = int(sum(self.rows))
        self._starts = np.cumsum([0, *self.rows[:-1]])
        self.ledger = [(f"constraint:{name}", "work") for name in self.names]
        self._lambda = np.zeros(self.n_rows)
        self.fallbacks = 0

    def __getstate__(self) -> dict[str, Any]:
        # Pinocchio's constraint models, data and settings do not pickle: keep the declarations and rebuild.
        return {"model": self.model, "records": self._records, "q_ref": self._q_ref, "fallbacks": self.fallbacks}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__init__(state["model"], state["records"], state["q_ref"])  # type: ignore[misc]
        self.fallbacks = state["fallbacks"]

    def __repr__(self) -> str:
        parts = ", ".join(f"{n} ({t}, {r} rows)" for n, t, r in zip(self.names, self.types, self.rows, strict=True))
        return f"Constraints({parts})"

    # ---- construction --------------------------------------------------------------------------------
    def _build(self, spec: Any) -> pin.RigidConstraintModel:
        """Pinocchio's model of one constraint: (joint, placement) of c1 and of c2, rows, gains."""
        name = getattr(spec, "name", None)
        if not isinstance(name, str) or not name:
            raise InvalidArgumentError(f"constraint names must be non-empty strings, got {name!r}")
        if name in self.names:
            raise InvalidArgumentError(f"constraint '{name}' is declared twice")
        kind = getattr(spec, "type", None)
        if kind not in CONSTRAINT_TYPES:
            raise InvalidArgumentError(
                f"constraint '{name}': type must be one of {', '.join(CONSTRAINT_TYPES)}, got {kind!r}"
            )
        frames = tuple(getattr(spec, "frames", ()))
        wanted = 1 if kind == "point" else 2
        if len(frames) != wanted or len(set(frames)) != wanted:
            what = "one frame" if wanted == 1 else "two distinct frames"
            raise InvalidArgumentError(f"constraint '{name}': a {kind} constraint takes {what}, got {list(frames)}")
        ids = [self._frame_id(name, frame) for frame in frames]
        position = getattr(spec, "position", None)
        if position is not None and kind != "point":
            raise InvalidArgumentError(f"constraint '{name}': position applies to point constraints only")
        given = getattr(spec, "stabilization", None)
        try:
            gains = DEFAULT_STABILIZATION if given is None else tuple(float(g) for g in given)
        except (TypeError, ValueError):
            gains = ()
        if len(gains) != 2 or not all(np.isfinite(g) and g >= 0 for g in gains):
            shown = list(given) if isinstance(given, (list, tuple)) else given
            raise InvalidArgumentError(
                f"constraint '{name}': stabilization must be two finite gains (Kp, Kd) >= 0, got {shown!r}"
            )
        model, oMf = self.model, self._probe.oMf
        frame1 = model.frames[ids[0]]
        joint1, placement1 = frame1.parentJoint, frame1.placement
        if kind == "point":
            if position is None:
                anchor = oMf[ids[0]].translation.copy()
            else:
                try:
                    anchor = np.asarray(position, dtype=float)
                except (TypeError, ValueError):
                    anchor = np.full(1, np.nan)
                if anchor.shape != (3,) or not np.all(np.isfinite(anchor)):
                    raise InvalidArgumentError(
                        f"constraint '{name}': position must be 3 finite numbers [m], got {position!r}"
                    )
            joint2, placement2 = 0, pin.SE3(np.eye(3), anchor)
        else:
            frame2 = model.frames[ids[1]]
            joint2, placement2 = frame2.parentJoint, frame2.placement
            if kind == "weld":  # c2 rides on body 2 where c1 is at q_ref: the pose to keep
                placement2 = placement2 * (oMf[ids[1]].actInv(oMf[ids[0]]))
        if joint1 == joint2:  # nothing could move one end relative to the other
            body = "the world" if joint1 == 0 else f"one rigid body (joint '{model.names[joint1]}')"
            what = f"frame '{frames[0]}' is" if kind == "point" else f"frames '{frames[0]}' and '{frames[1]}' are"
            raise InvalidArgumentError(f"constraint '{name}': {what} fixed to {body}: the constraint could not act")
        contact = pin.ContactType.CONTACT_6D if kind == "weld" else pin.ContactType.CONTACT_3D
        cm = pin.RigidConstraintModel(contact, model, joint1, placement1, joint2, placement2, _LWA)
        cm.name = name
        corrector = cm.m_baumgarte_parameters
        corrector.Kp, corrector.Kd = gains
        cm.setBaumgarteCorrectorParameters(corrector)
        self.names.append(name)
        self.types.append(kind)
        self.rows.append(ROWS[kind])
        self.stabilization.append((gains[0], gains[1]))
        anchor_given = None if position is None else (float(anchor[0]), float(anchor[1]), float(anchor[2]))
        self._records.append(_Record(name, kind, frames, anchor_given, (gains[0], gains[1])))
        return cm

    def _frame_id(self, constraint: str, frame: Any) -> int:
        if isinstance(frame, str) and self.model.existFrame(frame):
            return int(self.model.getFrameId(frame))
        names = sorted({f.name for f in self.model.frames})
        raise InvalidArgumentError(f"constraint '{constraint}': unknown frame {frame!r} ({name_hint(frame, names)})")

    # ---- dynamics ------------------------------------------------------------------------------------
    def forward_dynamics(self, q: np.ndarray, v: np.ndarray, tau: np.ndarray) -> np.ndarray:
        """Constrained accelerations a, shape (nv,), and the multipliers (see multipliers()); no argument checks.

        Args:
            q: configuration, shape (nq,).
            v: velocity, shape (nv,).
            tau: every generalised force but the constraints' (torques, damping, force elements), shape (nv,).
        """
        settings = self._settings
        a = pin.constraintDynamics(self.model, self.data, q, v, tau, self._models, self._datas, settings)
        self._lambda = self.data.lambda_c.copy()  # lambda_c is a view into data, overwritten by the next call
        step = settings.relative_residual  # the last increment: it bounds each iteration's drift along null(Jᵀ)
        if step > _STEP_TOLERANCE and _MAX_ITER * step > _MULTIPLIER_TOLERANCE * (1.0 + np.abs(self._lambda).max()):
            self._lambda = self._least_squares_multipliers(q, v, tau, a)
        return a

    def _least_squares_multipliers(self, q: np.ndarray, v: np.ndarray, tau: np.ndarray, a: np.ndarray) -> np.ndarray:
        """Minimum-norm λ with Jᵀ λ = M a + h - tau: the proximal iterations drifted along redundant rows.

        The accelerations are right regardless (Jᵀ maps those rows' multipliers to zero); only λ is repaired.
        """
        self.fallbacks += 1
        J = self._jacobian()
        generalized = pin.rnea(self.model, self._probe, q, v, a) - tau  # M a + h - tau (armature included)
        return np.linalg.lstsq(J.T, generalized, rcond=1e-10)[0]

    def _jacobian(self) -> np.ndarray:
        """J of the latest solve, shape (n_rows, nv) (eigenpy returns a flat vector when nv = 1)."""
        J = pin.getConstraintsJacobian(self.model, self.data, self._models, self._datas)
        return J.reshape(self.n_rows, self.model.nv)

    def multipliers(self) -> np.ndarray:
        """The constraint forces of the latest forward_dynamics call, shape (n_rows,) (a copy).

        Per constraint, in declaration order: the force [N] (loop, point: 3 rows) or force then torque [N, N·m]
        (weld: 6 rows) exerted on the first frame's body at the constraint point, in world-aligned axes (see the
        module docstring). Zero before the first call.
        """
        return self._lambda.copy()

    def powers(self, v: np.ndarray, out: np.ndarray) -> np.ndarray:
        """Power of each constraint's forces [W] at the latest forward_dynamics call, into out (n_constraints,).

        λ_k · (J_k v): zero on the constraint manifold (J v = 0); off it the Baumgarte terms make it non-zero.
        `v` must be the velocity of that call.
        """
        rates = self._jacobian() @ v
        if len(out) == 1:  # the common case, without reduceat's overhead
            out[0] = self._lambda @ rates
        else:
            out[:] = np.add.reduceat(self._lambda * rates, self._starts)
        return out

    # ---- diagnostics ---------------------------------------------------------------------------------
    def drift(self, q: np.ndarray, v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """How far (q, v) is off each constraint, shape (n_constraints,) each.

        Returns:
            (position residuals, velocity residuals). Loop and point: ‖p(c1) − p(c2)‖ [m] and ‖ṗ(c1) − ṗ(c2)‖
            [m/s]. Weld: the larger of the translation error ‖p(c1) − p(c2)‖ [m] and the rotation angle
            between c1 and c2 [rad] (1 rad counts as 1 m, as --tolerance mixes them), and likewise the larger
            of the relative linear velocity [m/s] and angular velocity [rad/s].
        """
        model, data = self.model, self._probe
        pin.forwardKinematics(model, data, q, v)
        position = np.empty(len(self.names))
        velocity = np.empty(len(self.names))
        for k, cm in enumerate(self._models):
            oMc1 = data.oMi[cm.joint1_id] * cm.joint1_placement
            oMc2 = data.oMi[cm.joint2_id] * cm.joint2_placement
            v1 = oMc1.rotation @ cm.joint1_placement.actInv(data.v[cm.joint1_id]).linear
            v2 = oMc2.rotation @ cm.joint2_placement.actInv(data.v[cm.joint2_id]).linear
            position[k] = np.linalg.norm(oMc1.translation - oMc2.translation)
            velocity[k] = np.linalg.norm(v1 - v2)
            if self.types[k] == "weld":
                angle = np.linalg.norm(pin.log3(oMc1.rotation.T @ oMc2.rotation))
                w1 = data.oMi[cm.joint1_id].rotation @ data.v[cm.joint1_id].angular
                w2 = data.oMi[cm.joint2_id].rotation @ data.v[cm.joint2_id].angular
                position[k] = max(position[k], angle)
                velocity[k] = max(velocity[k], np.linalg.norm(w1 - w2))
        return position, velocity
