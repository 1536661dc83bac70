"""Force elements of a scene: joint springs, viscous damping, regularized Coulomb friction and external wrenches.

All elements of a scene live in one :class:`ForceElements` object whose :meth:`ForceElements.evaluate` returns
their total generalized force f(q, v, t) [N·m, N], shape (nv,), which the scene adds to the joint torques before
forward dynamics. It runs at every Runge–Kutta stage, so it is vectorised: all elements are one vector-matrix
product ``zᵀ H`` over a feature vector ``z = [q, v, tanh(v / v_s), wrapped angles, 1, wrench scales]`` filled in
place (no Python loop over joints); the wrenches' rows of H (their ``Jᵀ w``) cost one kinematics pass plus one
small product per wrench.

Elements and their generalized forces:

- Spring (stiffness k, rest configuration r): ``f = -k (q ⊖ r)`` with ``q ⊖ r`` Pinocchio's difference on the
  joint: ``q - r`` on revolute and prismatic joints, the angle wrapped to (-π, π] on continuous joints. Stored
  energy ``½ k (q ⊖ r)²`` (a potential element of the ledger).
- Viscous damping d: ``f = -d v``; dissipated power ``d v²``.
- Coulomb friction F_c, regularized: ``f = -F_c tanh(v / v_s)``; dissipated power ``F_c v tanh(v / v_s) ≥ 0``.
- Wrench w = (force, torque) on a frame, scaled by ``scale(t)``: ``f = Jᵀ w`` with J the frame Jacobian in
  Pinocchio's LOCAL_WORLD_ALIGNED convention (reference "world": w in world axes, applied at the frame's origin;
  a force fixed in the world) or LOCAL (reference "local": w in the frame's own axes; a follower force that turns
  with the body). Power ``(Jᵀ w) · v``.

Springs, damping and friction act on 1-dof joints only (revolute, prismatic, continuous).

Error of the regularized friction
---------------------------------
The set-valued Coulomb law (``|f| ≤ F_c`` at rest, ``f = -F_c sign(v)`` when sliding) is replaced by the smooth
``-F_c tanh(v / v_s)``, which never sticks. Away from rest the two agree to ``F_c (1 - tanh(|v| / v_s)) ≈
2 F_c exp(-2 |v| / v_s)`` (below 1e-4 F_c once ``|v| > 5 v_s``). At rest they differ: under a constant net load
``|τ| < F_c`` that true friction would hold, the joint instead creeps at the steady velocity where
``τ = F_c tanh(v / v_s)``::

    v_creep = v_s · atanh(τ / F_c)        (≈ v_s τ / F_c for |τ| ≪ F_c; 0.55 v_s at τ = F_c / 2, 1.47 v_s at 0.9 F_c)

and so drifts by ``v_creep · T`` over a hold of duration T (v_s = 1e-3 rad/s and τ = F_c / 2: 0.55 mrad/s,
33 mrad per minute). The creep is proportional to v_s and unbounded as |τ| → F_c.

Stiffness it imposes
--------------------
Near rest the friction is a viscous damper of coefficient ``F_c / v_s`` (its slope at v = 0). On a joint of
effective inertia ``m = 1 / (M⁻¹)_ii`` it pulls the velocity to the creep value with time constant
``T_f = m v_s / F_c`` (eigenvalue ``λ = -F_c (M⁻¹)_ii / v_s`` of the linearised dynamics; with several
frictional joints the fastest eigenvalue of ``-M⁻¹ diag(F_c / v_s)`` is at least the largest of these). Explicit
methods are stable only while ``h |λ|`` stays inside their real stability interval: ``h < 2 T_f`` for explicit
and semi-implicit Euler, ``h < 2.79 T_f`` for RK4. Example: m = 0.01 kg·m², F_c = 0.3 N·m, v_s = 1e-3 rad/s give
T_f = 33 µs, so RK4 needs h below about 90 µs whenever that joint is near rest; adaptive explicit methods shrink
their steps to that scale by themselves. Implicit methods (Newton with :meth:`ForceElements.jacobians`) are not
limited by it. Raising v_s relaxes the limit in proportion and increases the creep in the same proportion.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
import pinocchio as pin

from ..exceptions import InvalidArgumentError
from ..ordered import ordered_dot, ordered_sum

_REFERENCES = {"world": pin.LOCAL_WORLD_ALIGNED, "local": pin.LOCAL}


def _unit_scale(t: float) -> float:
    return 1.0


@dataclass(frozen=True, eq=False)
class Wrench:
    """An external wrench on a frame of the model.

    Attributes:
        name: ledger name (the element is reported as ``force:<name>``).
        frame_id: index of the frame in ``model.frames``.
        force: force [N], shape (3,).
        torque: torque [N·m], shape (3,).
        reference: "world": force and torque in world-aligned axes, the force applied at the frame's origin (fixed
            in the world); "local": in the frame's own axes (turning with the body).
        scale: multiplier of the wrench as a function of time t [s] (constant: always 1).
    """

    name: str
    frame_id: int
    force: np.ndarray
    torque: np.ndarray = field(default_factory=lambda: np.zeros(3))
    reference: Literal["world", "local"] = "world"
    scale: Callable[[float], float] = _unit_scale

    def __post_init__(self) -> None:
        for name in ("force", "torque"):
            value = np.array(getattr(self, name), dtype=float)
            if value.shape != (3,) or not np.all(np.isfinite(value)):
                raise InvalidArgumentError(f"wrench {self.name!r}: {name} must be 3 finite numbers, got {value}")
            object.__setattr__(self, name, value)
        if self.reference not in _REFERENCES:
            raise InvalidArgumentError(
                f"wrench {self.name!r}: reference must be one of local, world, got {self.reference!r}"
            )
        if not callable(self.scale):
            raise InvalidArgumentError(f"wrench {self.name!r}: scale must be a callable t -> float")


class ForceElements:
    """All force elements of one scene: their generalized force, ledger powers, stored energies and Jacobians.

    Attributes:
        ledger: flow elements in order, (name, kind): ``("damping:<dof>", "dissipated")`` per damped dof,
            ``("friction:<dof>", "dissipated")`` per frictional dof, ``("force:<name>", "work")`` per wrench.
        potentials: ``"spring:<dof>"`` per dof with a spring.
        time_dependent: whether evaluate() depends on t (there is a wrench).
        empty: no element at all (evaluate() would always return zeros: callers may skip it).
    """

    def __init__(
        self,
        model: pin.Model,
        *,
        dof_names: Sequence[str],
        damping: np.ndarray,
        friction: np.ndarray,
        friction_velocity: float,
        stiffness: np.ndarray,
        rest: np.ndarray,
        wrenches: Sequence[Wrench] = (),
        keep: np.ndarray | None = None,
    ):
        """Build the elements.

        Args:
            model: the scene's Pinocchio model (not modified; a private Data is kept).
            dof_names: one name per velocity coordinate, length nv (used in ledger names).
            damping: viscous damping d ≥ 0 [N·m·s/rad or N·s/m], shape (nv,); 0 means none.
            friction: Coulomb friction F_c ≥ 0 [N·m or N], shape (nv,); 0 means none.
            friction_velocity: regularization velocity v_s > 0 [rad/s or m/s].
            stiffness: spring stiffness k ≥ 0 [N·m/rad or N/m], shape (nv,); 0 means none.
            rest: a full configuration, shape (nq,), whose spring joints sit at their rest positions.
            wrenches: external wrenches.
            keep: dofs (bool, shape (nv,)) whose friction element stays at a zero coefficient: a scene whose
                [randomize] draws their friction keeps one ledger for every row.

        Raises:
            InvalidArgumentError: wrong shapes, negative or non-finite coefficients, a joint element on a
                joint that is not a 1-dof joint, or a frame index out of range.
        """
        self._model = model
        self._data = model.createData()
        nq, nv = model.nq, model.nv
        self.nv = nv
        if len(dof_names) != nv:
            raise InvalidArgumentError(f"dof_names must have {nv} names, got {len(dof_names)}")
        damping = _coefficients(damping, nv, "damping")
        friction = _coefficients(friction, nv, "friction")
        stiffness = _coefficients(stiffness, nv, "stiffness")
        rest = np.array(rest, dtype=float)
        if rest.shape != (nq,) or not np.all(np.isfinite(rest)):
            raise InvalidArgumentError(f"rest must be {nq} finite numbers, got shape {rest.shape}")
        if not (np.isfinite(friction_velocity) and friction_velocity > 0.0):
            raise InvalidArgumentError(f"friction_velocity must be > 0, got {friction_velocity}")
        self.friction_velocity = float(friction_velocity)

        # The joint owning each velocity coordinate, to check elements sit on 1-dof joints and find their q.
        idx_q = np.full(nv, -1)
        nq_of = np.zeros(nv, dtype=int)
        for joint in model.joints[1:]:
            if joint.nv == 1 and joint.nq in (1, 2):  # revolute/prismatic/helical (nq 1), continuous (nq 2)
                idx_q[joint.idx_v] = joint.idx_q
                nq_of[joint.idx_v] = joint.nq
        for kind, values in (("damping", damping), ("friction", friction), ("stiffness", stiffness)):
            bad = np.flatnonzero((values > 0.0) & (idx_q < 0))
            if bad.size:
                raise InvalidArgumentError(
                    f"{kind} on {dof_names[int(bad[0])]!r}: joint elements apply to 1-dof joints "
                    "(revolute, prismatic, continuous) only"
                )

        self._damped = np.flatnonzero(damping > 0.0)
        self._rough = np.flatnonzero((friction > 0.0) | (keep if keep is not None else False))
        self._sprung = np.flatnonzero(stiffness > 0.0)
        self._d = damping[self._damped]
        self._fc = friction[self._rough]
        self._k = stiffness[self._sprung]
        names = list(dof_names)
        self.ledger: list[tuple[str, str]] = (
            [(f"damping:{names[i]}", "dissipated") for i in self._damped.tolist()]
            + [(f"friction:{names[i]}", "dissipated") for i in self._rough.tolist()]
            + [(f"force:{w.name}", "work") for w in wrenches]
        )
        self.potentials = [f"spring:{names[i]}" for i in self._sprung.tolist()]
        self.time_dependent = bool(wrenches)
        self.empty = not (self._damped.size or self._rough.size or self._sprung.size or wrenches)

        # Springs: plain joints (nq 1) are linear in q; continuous ones need the wrapped angle
        # atan2(c_r s - s_r c, c_r c + s_r s) of the difference with the rest angle (c_r, s_r).
        plain = self._sprung[nq_of[self._sprung] == 1]
        circular = self._sprung[nq_of[self._sprung] == 2]
        self._plain, self._plain_q, self._plain_rest = plain, idx_q[plain], rest[idx_q[plain]]
        # Column selections as slices where they are consecutive (a view, no gather): the hot path's indices.
        self._plain_at, self._plain_q_at = indexer(plain.tolist()), indexer(idx_q[plain].tolist())
        self._damped_at, self._rough_at = indexer(self._damped.tolist()), indexer(self._rough.tolist())
        self._plain_k = stiffness[plain]
        self._circular, self._circular_k = circular, stiffness[circular]
        self._cos_q, self._sin_q = idx_q[circular], idx_q[circular] + 1
        self._cos_rest, self._sin_rest = rest[self._cos_q], rest[self._sin_q]
        self._circular_pos = np.flatnonzero(nq_of[self._sprung] == 2)  # their places among the springs
        self._plain_pos = np.flatnonzero(nq_of[self._sprung] == 1)

        # The common case in a few whole-span operations: every element on a span of consecutive 1-dof joints
        # with consecutive q (no continuous spring). Dofs of the span without an element get zero coefficients
        # (adding exact zeros), so each force is the same arithmetic as the separate selections would give.
        self._span = None
        used = sorted(set(self._sprung.tolist()) | set(self._damped.tolist()) | set(self._rough.tolist()))
        if used and not circular.size:
            lo, hi = used[0], used[-1] + 1
            q_at = idx_q[lo:hi]
            if np.all(nq_of[lo:hi] == 1) and np.array_equal(q_at, q_at[0] + np.arange(hi - lo)):
                span_rest = np.zeros(hi - lo)
                span_rest[plain - lo] = rest[idx_q[plain]]
                self._span = (
                    slice(lo, hi),
                    slice(int(q_at[0]), int(q_at[0]) + hi - lo),
                    span_rest,
                    -np.where(stiffness[lo:hi] > 0.0, stiffness[lo:hi], 0.0),
                    damping[lo:hi] if self._damped.size else None,
                    friction[lo:hi] if self._rough.size else None,
                    hi - lo == nv,
                )

        # Every element acts with elementwise operations only (no per-row product) on a state or a stack of them.
        self._wrenches = list(wrenches)
        self._inv_vs = 1.0 / self.friction_velocity
        for w in self._wrenches:
            if not 0 <= w.frame_id < model.nframes:
                raise InvalidArgumentError(
                    f"wrench {w.name!r}: frame_id {w.frame_id} out of range [0, {model.nframes})"
                )
        self._w6 = [np.concatenate([w.force, w.torque]) for w in self._wrenches]
        self._refs = [_REFERENCES[w.reference] for w in self._wrenches]
        # Constant wrenches keep scale 1: no call per evaluation.
        self._scaled = [(k, w.scale) for k, w in enumerate(self._wrenches) if w.scale is not _unit_scale]
        self._scales = np.ones(len(self._wrenches))  # scale(t) of each wrench at the latest evaluation
        self._n_flow_joint = self._damped.size + self._rough.size
        # A world-fixed force at a frame's origin (no torque) is the gravity of a point mass (_Push); the other
        # wrenches take a frame Jacobian.
        self._pushes = {
            k: _Push(model, w.frame_id, w.force)
            for k, w in enumerate(self._wrenches)
            if w.reference == "world" and not w.torque.any()
        }
        self._other_wrenches = [k for k in range(len(self._wrenches)) if k not in self._pushes]
        self._unscaled = np.zeros((len(self._wrenches), 1, self.nv))  # each wrench's unscaled Jᵀw, one row
        self._jacobians = np.zeros((len(self._other_wrenches), 1, 6, self.nv))  # the frame Jacobians behind them
        self._model_g0: pin.Model | None = None  # built on the first jacobians() call with wrenches

    # ---- the hot path ---------------------------------------------------------------------------------
    def evaluate(self, q: np.ndarray, v: np.ndarray, t: float = 0.0, out: np.ndarray | None = None) -> np.ndarray:
        """Total generalized force of all elements at (q, v, t) [N·m, N], shape (nv,) (no argument checks).

        Written into `out` (shape (nv,), float) and returned when given, so that the stepping loop allocates
        nothing; otherwise a new array. The wrenches' parts are remembered for powers().
        """
        if out is None:
            out = np.empty(self.nv)
        self._joint_forces(q, v, out)
        if self._wrenches:
            forces = self._wrench_forces(q, t)
            for k in range(len(self._wrenches)):
                force = forces[k, 0] if self._scales[k] == 1.0 else forces[k, 0] * self._scales[k]
                np.add(out, force, out=out)
        return out

    def _joint_forces(self, Q: np.ndarray, V: np.ndarray, out: np.ndarray) -> None:
        """The joints' elements (springs, damping, friction) at Q (..., nq), V (..., nv), into out (..., nv):
        elementwise, so one row costs no more than its own arithmetic."""
        if self._span is not None:
            at, q_at, rest, minus_k, d, fc, whole = self._span
            if not whole:
                out[...] = 0.0
            force = out[..., at]
            np.multiply(Q[..., q_at] - rest, minus_k, out=force)
            if d is not None:
                force -= V[..., at] * d
            if fc is not None:
                force -= np.tanh(V[..., at] * self._inv_vs) * fc
            return
        out[...] = 0.0
        if self._plain.size:  # -k (q - rest)
            out[..., self._plain_at] = (Q[..., self._plain_q_at] - self._plain_rest) * -self._plain_k
        if self._circular.size:  # -k · wrapped angle from the rest angle
            c, s = Q[..., self._cos_q], Q[..., self._sin_q]
            angle = np.arctan2(self._cos_rest * s - self._sin_rest * c, self._cos_rest * c + self._sin_rest * s)
            out[..., self._circular] = angle * -self._circular_k
        if self._damped.size:  # -d v
            out[..., self._damped_at] -= V[..., self._damped_at] * self._d
        if self._rough.size:  # -F_c tanh(v / v_s)
            out[..., self._rough_at] -= np.tanh(V[..., self._rough_at] * self._inv_vs) * self._fc

    def _wrench_forces(self, q: np.ndarray, t: float) -> np.ndarray:
        """Each wrench's unscaled Jᵀw at q, shape (n_wrenches, 1, nv) (kept for powers()), and each wrench's scale
        at t."""
        forces = self._unscaled
        for k, push in self._pushes.items():
            push.forces(q, forces[k, 0])
        others = self._other_wrenches
        if others:
            model, data, jacobians = self._model, self._data, self._jacobians
            if len(others) == 1:  # kinematics along the frame's support only: cheaper than all joints
                k = others[0]
                J = pin.computeFrameJacobian(model, data, q, self._wrenches[k].frame_id, self._refs[k])
                jacobians[0, 0] = J.reshape(6, -1)  # J is (6, nv), but flat (6,) when nv = 1
            else:
                pin.computeJointJacobians(model, data, q)  # one kinematics pass for every wrench
                for m, k in enumerate(others):
                    J = pin.getFrameJacobian(model, data, self._wrenches[k].frame_id, self._refs[k])
                    jacobians[m, 0] = J.reshape(6, -1)
            for m, k in enumerate(others):  # wᵀJ in a fixed order (the native kernel's)
                ordered_sum(self._w6[k], jacobians[m], axis=1, out=forces[k])
        for k, scale in self._scaled:
            self._scales[k] = scale(t)
        return forces

    def powers(self, v: np.ndarray, out: np.ndarray) -> None:
        """Power of each ledger element [W], written into out (shape (len(ledger),)), in ledger order.

        Dissipated elements are positive when they take energy out (``d v²``, ``F_c v tanh(v / v_s)``), computed
        from this v; work elements are positive when they put energy in: ``(Jᵀ w) · v`` with ``Jᵀ w`` from the
        latest evaluate(), so call it at the state (q, t) of interest first.
        """
        self._joint_powers(v, out)
        if self._wrenches:
            forces, nf = self._unscaled, self._n_flow_joint
            for k in range(len(self._wrenches)):
                work = ordered_dot(forces[k, 0], v)
                out[nf + k] = work if self._scales[k] == 1.0 else work * self._scales[k]

    def _joint_powers(self, V: np.ndarray, out: np.ndarray) -> None:
        """The joints' dissipated powers at V (..., nv), into the first columns of out (..., len(ledger))."""
        nd, nf = self._damped.size, self._n_flow_joint
        if nd:
            v = V[..., self._damped_at]
            out[..., :nd] = v * v * self._d
        if nf > nd:
            v = V[..., self._rough_at]
            out[..., nd:nf] = v * np.tanh(v * self._inv_vs) * self._fc

    # ---- energies and derivatives -------------------------------------------------------------------
    def spring_displacements(self, q: np.ndarray) -> np.ndarray:
        """q ⊖ rest of each spring [rad or m], shape (..., len(potentials)) for q (..., nq): wrapped to (-π, π] on
        continuous joints."""
        if not self._circular_pos.size:
            return q[..., self._plain_q_at] - self._plain_rest
        x = np.empty((*q.shape[:-1], self._sprung.size))
        x[..., self._plain_pos] = q[..., self._plain_q] - self._plain_rest
        if self._circular_pos.size:
            c, s = q[..., self._cos_q], q[..., self._sin_q]
            sine = self._cos_rest * s - self._sin_rest * c
            x[..., self._circular_pos] = np.arctan2(sine, self._cos_rest * c + self._sin_rest * s)
        return x

    def potential_energies(self, q: np.ndarray) -> np.ndarray:
        """Energy stored in each spring, ½ k (q ⊖ rest)² [J], shape (..., len(potentials)) for q (..., nq)."""
        x = self.spring_displacements(q)
        return 0.5 * self._k * x * x

    def potential_energy(self, q: np.ndarray) -> np.ndarray:
        """The springs' total stored energy [J], shape (...) for q (..., nq): potential_energies summed in order
        (the native kernel's order), 0 without springs."""
        energies = self.potential_energies(q)
        if not energies.shape[-1]:
            return np.zeros(energies.shape[:-1])
        return np.add.accumulate(energies, axis=-1)[..., -1]

    # ---- the native kernel's data (src/native/scene.cpp) ------------------------------------------------
    def native_reason(self) -> str | None:
        """Why the native kernel cannot render these elements (a wrench whose scale is Python code), or None."""
        for w in self._wrenches:
            if _shape_data(w) is None:
                return f"force '{w.name}' has a Python callable shape"
        return None

    def native_data(self, load_model: Callable[[pin.Model], object]) -> dict[str, object]:
        """The elements as _native.SceneForces takes them: each term of evaluate(), powers() and
        potential_energies() with its coefficients, in their arithmetic order, as dicts of the native terms' field
        names (SpringTerm, CircularTerm, CoefficientTerm, WrenchTerm, SpringEnergy); `load_model` hands a Pinocchio
        model to C++ (the point-mass models of world forces)."""

        def spring(dof: Any, iq: Any, rest: Any, minus_k: Any) -> dict[str, object]:
            return {"dof": int(dof), "iq": int(iq), "rest": float(rest), "minus_k": float(minus_k)}

        def coefficient(dof: Any, c: Any) -> dict[str, object]:
            return {"dof": int(dof), "c": float(c)}

        springs, circular, damped, rough = [], [], [], []
        zero_all = True
        if self._span is not None:
            at, q_at, rest, minus_k, d, fc, whole = self._span
            zero_all = not whole
            dofs = range(at.start, at.stop)
            springs = [spring(i, q_at.start + n, rest[n], minus_k[n]) for n, i in enumerate(dofs)]
            if d is not None:
                damped = [coefficient(i, d[n]) for n, i in enumerate(dofs)]
            if fc is not None:
                rough = [coefficient(i, fc[n]) for n, i in enumerate(dofs)]
        else:
            springs = [
                spring(i, j, r, -k)
                for i, j, r, k in zip(self._plain, self._plain_q, self._plain_rest, self._plain_k, strict=True)
            ]
            circular = [
                {"dof": int(i), "ic": int(c), "cos_rest": float(cr), "sin_rest": float(sr), "minus_k": float(-k)}
                for i, c, cr, sr, k in zip(
                    self._circular, self._cos_q, self._cos_rest, self._sin_rest, self._circular_k, strict=True
                )
            ]
            damped = [coefficient(i, d) for i, d in zip(self._damped, self._d, strict=True)]
            rough = [coefficient(i, f) for i, f in zip(self._rough, self._fc, strict=True)]
        pushes: list[object] = []
        wrenches = []
        for k, w in enumerate(self._wrenches):
            push = -1
            if k in self._pushes:
                push = len(pushes)
                pushes.append(load_model(self._pushes[k].model))
            shape = _shape_data(w)
            assert shape is not None, "native_reason() says why"
            kind, (start, ramp_time, frequency, phase) = shape
            wrenches.append(
                {
                    "push": push,
                    "frame": w.frame_id,
                    "local": w.reference == "local",
                    "w6": self._w6[k].tolist(),
                    "shape": kind,
                    "start": start,
                    "ramp_time": ramp_time,
                    "frequency": frequency,
                    "phase": phase,
                }
            )
        energies = []
        plain_rest = dict(zip(self._plain.tolist(), self._plain_rest.tolist(), strict=True))
        circular_at = {int(i): n for n, i in enumerate(self._circular)}
        for i, k in zip(self._sprung.tolist(), self._k.tolist(), strict=True):
            energy: dict[str, object] = {"circular": False, "rest": 0.0, "cos_rest": 1.0, "sin_rest": 0.0, "k": k}
            if i in circular_at:
                n = circular_at[i]
                energy.update(circular=True, iq=int(self._cos_q[n]))
                energy.update(cos_rest=float(self._cos_rest[n]), sin_rest=float(self._sin_rest[n]))
            else:
                energy.update(iq=int(self._plain_q[list(self._plain).index(i)]), rest=plain_rest[i])
            energies.append(energy)
        return {
            "zero_all": zero_all,
            "inv_vs": self._inv_vs,
            "springs": springs,
            "circular": circular,
            "damped": damped,
            "rough": rough,
            "ledger_damped": [coefficient(i, d) for i, d in zip(self._damped, self._d, strict=True)],
            "ledger_rough": [coefficient(i, f) for i, f in zip(self._rough, self._fc, strict=True)],
            "wrenches": wrenches,
            "push_models": pushes,
            "energies": energies,
        }

    def jacobians(self, q: np.ndarray, v: np.ndarray, t: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
        """Partial derivatives of evaluate(q, v, t), exact, for implicit integrators' Newton iterations.

        Returns:
            (df_dq, df_dv), each shape (nv, nv); df_dq is taken in the tangent space at q (a variation dq moves
            q to q ⊕ dq). Springs give ``-k`` (also on continuous joints, away from the wrap at ±π), damping
            ``-d``, friction ``-F_c sech²(v / v_s) / v_s`` on the diagonal. A wrench's ``∂(Jᵀ w)/∂q`` comes from
            Pinocchio's RNEA derivatives with external forces (on a zero-gravity copy of the model, at zero
            velocity and acceleration), which hold each force fixed in its joint's frame: exact for "local"
            wrenches; for "world" wrenches, the turning of the joint frame under the fixed world wrench is added
            as ``J_iᵀ ∂f_i/∂q`` with J_i the joint's LOCAL Jacobian.
        """
        nv = self.nv
        df_dq = np.zeros((nv, nv))
        df_dv = np.zeros((nv, nv))
        df_dq[self._sprung, self._sprung] = -self._k
        df_dv[self._damped, self._damped] -= self._d
        if self._rough.size:
            # sech²(u) = 4 e / (1 + e)² with e = exp(-2|u|): cosh(u)² would overflow once |v| > 355 v_s.
            e = np.exp(-2.0 * np.abs(v[self._rough]) / self.friction_velocity)
            df_dv[self._rough, self._rough] -= self._fc * 4.0 * e / ((1.0 + e) ** 2 * self.friction_velocity)
        if self._wrenches:
            df_dq += self._wrench_jacobian(q, t)
        return df_dq, df_dv

    def _wrench_jacobian(self, q: np.ndarray, t: float) -> np.ndarray:
        model, data = self._model, self._data
        if self._model_g0 is None:
            self._model_g0 = pin.Model(model)
            self._model_g0.gravity = pin.Motion.Zero()  # so that RNEA at v = a = 0 is the external forces' part only
            self._data_g0 = self._model_g0.createData()
            self._fext = pin.StdVec_Force()
            for _ in range(model.njoints):
                self._fext.append(pin.Force.Zero())
            frames = [model.frames[w.frame_id] for w in self._wrenches]
            self._frame_joints = [f.parentJoint for f in frames]
            self._frame_placements = [f.placement.copy() for f in frames]
        fext = self._fext
        for i in self._frame_joints:
            fext[i] = pin.Force.Zero()
        pin.computeJointJacobians(model, data, q)  # oMi and the joint Jacobians for the "world" wrenches
        turning = np.zeros((self.nv, self.nv))
        for wrench, w6, i, placement in zip(
            self._wrenches, self._w6, self._frame_joints, self._frame_placements, strict=True
        ):
            if i == 0:  # a frame welded to the world: the wrench does no work and has no generalized force
                continue
            s = float(wrench.scale(t))
            if wrench.reference == "local":
                f_i = placement.act(pin.Force(s * w6))  # constant in the joint frame
            else:
                R = data.oMi[i].rotation
                f_l, n_l = R.T @ (s * w6[:3]), R.T @ (s * w6[3:])  # the world wrench in joint axes
                p = placement.translation  # the frame's origin in the joint frame (the point of application)
                f_i = pin.Force(f_l, n_l + _skew(p) @ f_l)
                # Joint axes turn by ω_k dq_k (the LOCAL Jacobian's angular rows), so a world-fixed vector a seen in
                # them changes by -ω_k × a = a × ω_k = [a]× ω_k.
                J_i = pin.getJointJacobian(model, data, i, pin.LOCAL)
                omega = J_i[3:]  # (3, nv)
                df = _skew(f_l) @ omega
                dn = _skew(n_l) @ omega + _skew(p) @ df
                turning += J_i[:3].T @ df + J_i[3:].T @ dn
            fext[i] = fext[i] + f_i
        zeros = np.zeros(self.nv)
        dtau_dq, _, _ = pin.computeRNEADerivatives(self._model_g0, self._data_g0, q, zeros, zeros, fext)
        # RNEA returns tau = ... - Σ J_iᵀ f_i: the generalized force of the wrenches is its negative.
        return turning - dtau_dq


class _Push:
    """A force f fixed in the world, applied at a frame's origin p, as a generalized force.

    Its generalized force J_p(q)ᵀ f is minus the generalized gravity of a unit point mass at p under the gravity f
    (the potential -fᵀ p(q)): one ``rnea(q, 0, 0)`` of a copy of the model whose only inertia is that point mass.
    """

    def __init__(self, model: pin.Model, frame_id: int, force: np.ndarray):
        frame = model.frames[frame_id]
        self.model = pin.Model(model)
        for i in range(self.model.njoints):
            self.model.inertias[i] = pin.Inertia.Zero()
        self.model.inertias[frame.parentJoint] = pin.Inertia(1.0, frame.placement.translation, np.zeros((3, 3)))
        self.model.gravity = pin.Motion(np.asarray(force, dtype=float), np.zeros(3))
        self.data = self.model.createData()
        self._zeros = np.zeros(self.model.nv)

    def forces(self, q: np.ndarray, out: np.ndarray) -> None:
        """J_p(q)ᵀ f at q (nq,), into out (nv,)."""
        zeros = self._zeros
        np.negative(pin.rnea(self.model, self.data, q, zeros, zeros), out=out)


# spec.ForceSpec.scale's shapes the native kernel renders (src/native/scene.hpp's Shape; "constant": no scale)
_SHAPES = ("constant", "step", "ramp", "sine")


def _shape_data(wrench: Wrench) -> tuple[str, list[float]] | None:
    """(shape, [start, ramp_time, frequency, phase]) of a wrench whose scale is a ForceSpec's declared shape (or the
    unit scale: "constant"), else None (a Python callable)."""
    from .spec import ForceSpec

    scale = wrench.scale
    if scale is _unit_scale:
        return "constant", [0.0, 1.0, 1.0, 0.0]
    spec = getattr(scale, "__self__", None)
    if type(spec) is not ForceSpec or getattr(scale, "__func__", None) is not ForceSpec.scale:
        return None
    if not isinstance(spec.shape, str) or spec.shape not in _SHAPES:
        return None
    return spec.shape, [float(spec.start), float(spec.ramp_time), float(spec.frequency), float(spec.phase)]


def _skew(a: np.ndarray) -> np.ndarray:
    """[a]×, the matrix of a × (·) (np.cross costs ~10 µs per call on small arrays)."""
    return np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])


def _coefficients(values: np.ndarray, nv: int, name: str) -> np.ndarray:
    arr = np.array(values, dtype=float)
    if arr.shape != (nv,):
        raise InvalidArgumentError(f"{name} must have shape ({nv},), got {arr.shape}")
    if not np.all(np.isfinite(arr)) or np.any(arr < 0.0):
        raise InvalidArgumentError(f"{name} must be finite and >= 0, got {arr.tolist()}")
    return arr


def indexer(indices: list[int]) -> slice | np.ndarray:
    """Column indices as a slice when they are consecutive (a view and a fast copy), else as an index array."""
    if indices and indices == list(range(indices[0], indices[-1] + 1)):
        return slice(indices[0], indices[-1] + 1)
    return np.array(indices, dtype=int)
