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
from typing import Literal

import numpy as np
import pinocchio as pin

from ..exceptions import InvalidArgumentError
from ..robot import rowdot

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
        self._rough = np.flatnonzero(friction > 0.0)
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
        # atan2(c_r s - s_r c, c_r c + s_r s), whose two arguments are again linear in q (matrix W).
        plain = self._sprung[nq_of[self._sprung] == 1]
        circular = self._sprung[nq_of[self._sprung] == 2]
        self._plain_q, self._plain_rest = idx_q[plain], rest[idx_q[plain]]
        self._circular_pos = np.flatnonzero(nq_of[self._sprung] == 2)  # their places among the springs
        self._plain_pos = np.flatnonzero(nq_of[self._sprung] == 1)
        n_circ = circular.size
        W = np.zeros((2 * n_circ, nq))
        for row, dof in enumerate(circular):
            i = idx_q[dof]
            c_r, s_r = rest[i], rest[i + 1]
            W[row, i], W[row, i + 1] = -s_r, c_r  # sin of the difference
            W[n_circ + row, i], W[n_circ + row, i + 1] = c_r, s_r  # cos of the difference
        self._W = W

        # The joint elements as one product f = zᵀ H over a feature vector z = [q | v | tanh(v / v_s) | wrapped
        # angles | 1], blocks present only when used (one BLAS call over a few dozen entries beats several scattered
        # numpy operations); each wrench adds scale(t) · Jᵀw. Rows of states go through the same operations (one
        # feature row per state), so a row's force is the same whether it is evaluated alone or in a batch.
        self._wrenches = list(wrenches)
        blocks: list[tuple[str, int]] = []
        if plain.size:
            blocks.append(("q", nq))
        if self._damped.size:
            blocks.append(("v", nv))
        if self._rough.size:
            blocks.append(("tanh", nv))
        if n_circ:
            blocks.append(("angle", n_circ))
        if plain.size:
            blocks.append(("one", 1))
        width = sum(size for _, size in blocks)
        H = np.zeros((width, nv))
        self._slices: dict[str, slice] = {}
        start = 0
        for name, size in blocks:
            self._slices[name] = slice(start, start + size)
            if name == "q":
                H[start + idx_q[plain], plain] = -stiffness[plain]
            elif name == "v":
                H[start + self._damped, self._damped] = -self._d
            elif name == "tanh":
                H[start + self._rough, self._rough] = -self._fc
            elif name == "angle":
                H[start + np.arange(n_circ), circular] = -stiffness[circular]
            else:  # "one"
                H[start, plain] = stiffness[plain] * rest[idx_q[plain]]
            start += size
        self._width = width
        self._H = H
        self._W_T = np.ascontiguousarray(W.T)
        self._n_circ = n_circ
        self._inv_vs = np.full(nv, 1.0 / self.friction_velocity)

        # Wrenches: 6-vectors (force, torque).
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
        nd, nf = self._damped.size, self._rough.size
        self._n_flow_joint = nd + nf
        self._y_width = (nv if nd else 0) + (nv if nf else 0)  # features of powers(): [v² | v tanh(v / v_s)]
        self._P = np.zeros((self._y_width, nd + nf))
        self._P[self._damped, np.arange(nd)] = self._d
        self._P[self._y_width - nv + self._rough, nd + np.arange(nf)] = self._fc
        self._buffers: dict[int, _RowBuffers] = {}  # per number of rows
        self._model_g0: pin.Model | None = None  # built on the first jacobians() call with wrenches

    def _rows(self, n: int) -> _RowBuffers:
        buffers = self._buffers.get(n)
        if buffers is None:
            if len(self._buffers) >= 8:  # batches shrink as elements stop: keep the latest sizes
                del self._buffers[next(iter(self._buffers))]
            buffers = self._buffers[n] = _RowBuffers(n, self)
        return buffers

    # ---- the hot path ---------------------------------------------------------------------------------
    def evaluate(self, q: np.ndarray, v: np.ndarray, t: float = 0.0, out: np.ndarray | None = None) -> np.ndarray:
        """Total generalized force of all elements at (q, v, t) [N·m, N], shape (nv,) (no argument checks).

        Written into `out` (shape (nv,), float) and returned when given, so that the stepping loop allocates
        nothing; otherwise a new array. The wrenches' parts are remembered for powers().
        """
        rows = self.evaluate_rows(q[None, :], v[None, :], t)
        if out is None:
            return rows[0].copy()
        out[...] = rows[0]
        return out

    def evaluate_rows(self, Q: np.ndarray, V: np.ndarray, t: float = 0.0) -> np.ndarray:
        """evaluate() of n states at once: Q (n, nq), V (n, nv) -> (n, nv), each row exactly as evaluate() gives it.

        The result is a buffer that the next call with as many rows overwrites; the wrenches' parts are remembered
        for powers_rows().
        """
        buf = self._rows(len(Q))
        Z, slices = buf.Z, self._slices
        if "q" in slices:
            Z[:, slices["q"]] = Q
        if "v" in slices:
            Z[:, slices["v"]] = V
        if "tanh" in slices:
            zt = Z[:, slices["tanh"]]
            np.multiply(V, self._inv_vs, out=zt)
            np.tanh(zt, out=zt)
        if "angle" in slices:
            n_circ = self._n_circ
            np.matmul(Q[:, None, :], self._W_T, out=buf.SC[:, None, :])  # the same gemv per row at any n
            np.arctan2(buf.SC[:, :n_circ], buf.SC[:, n_circ:], out=Z[:, slices["angle"]])
        out = buf.F
        if self._width:
            np.matmul(Z[:, None, :], self._H, out=out[:, None, :])
        else:
            out[...] = 0.0
        if self._wrenches:
            self._wrench_forces(Q, t, buf)
            for k in range(len(self._wrenches)):
                force = buf.JW[k]
                if self._scales[k] != 1.0:
                    force = force * self._scales[k]
                np.add(out, force, out=out)
        return out

    def _wrench_forces(self, Q: np.ndarray, t: float, buf: _RowBuffers) -> None:
        """Each wrench's unscaled Jᵀw for every row into buf.JW (n_wrenches, n, nv), and its scale at t."""
        model, data = self._model, self._data
        one = len(self._wrenches) == 1
        for b, q in enumerate(Q):
            if one:  # kinematics along the frame's support only: cheaper than all joints
                J = pin.computeFrameJacobian(model, data, q, self._wrenches[0].frame_id, self._refs[0])
                # (6, nv), but Pinocchio returns a flat (6,) when nv = 1
                np.dot(self._w6[0], J.reshape(6, -1), out=buf.JW[0, b])
                continue
            pin.computeJointJacobians(model, data, q)  # one kinematics pass for every wrench
            for k, (wrench, ref, w6) in enumerate(zip(self._wrenches, self._refs, self._w6, strict=True)):
                np.dot(w6, pin.getFrameJacobian(model, data, wrench.frame_id, ref).reshape(6, -1), out=buf.JW[k, b])
        for k, scale in self._scaled:
            self._scales[k] = scale(t)

    def powers(self, v: np.ndarray, out: np.ndarray) -> None:
        """Power of each ledger element [W], written into out (shape (len(ledger),)), in ledger order.

        Dissipated elements are positive when they take energy out (``d v²``, ``F_c v tanh(v / v_s)``), computed
        from this v; work elements are positive when they put energy in: ``(Jᵀ w) · v`` with ``Jᵀ w`` from the
        latest evaluate(), so call it at the state (q, t) of interest first.
        """
        self.powers_rows(v[None, :], out[None, :])

    def powers_rows(self, V: np.ndarray, out: np.ndarray) -> None:
        """powers() of n rows, V (n, nv), into out (n, len(ledger)), with the wrench parts of the latest
        evaluate_rows() call with as many rows."""
        buf = self._rows(len(V))
        nf = self._n_flow_joint
        if nf:
            # One product again: powers = [v² | v tanh(v / v_s)] · P, P holding d and F_c in the ledger's columns.
            Y, nv = buf.Y, self.nv
            if self._damped.size:
                np.multiply(V, V, out=Y[:, :nv])
            if self._rough.size:
                yt = Y[:, self._y_width - nv :]
                np.multiply(V, self._inv_vs, out=yt)
                np.tanh(yt, out=yt)
                np.multiply(yt, V, out=yt)
            np.matmul(Y[:, None, :], self._P, out=buf.flows[:, None, :])
            out[:, :nf] = buf.flows
        for k in range(len(self._wrenches)):
            work = out[:, nf + k]
            rowdot(buf.JW[k], V, out=work)
            if self._scales[k] != 1.0:
                np.multiply(work, self._scales[k], out=work)

    # ---- energies and derivatives -------------------------------------------------------------------
    def spring_displacements(self, q: np.ndarray) -> np.ndarray:
        """q ⊖ rest of each spring [rad or m], shape (len(potentials),): wrapped to (-π, π] on continuous joints."""
        x = np.empty(self._sprung.size)
        x[self._plain_pos] = q[self._plain_q] - self._plain_rest
        if self._circular_pos.size:
            sc = self._W @ q
            n = self._circular_pos.size
            x[self._circular_pos] = np.arctan2(sc[:n], sc[n:])
        return x

    def potential_energies(self, q: np.ndarray) -> np.ndarray:
        """Energy stored in each spring, ½ k (q ⊖ rest)² [J], shape (len(potentials),)."""
        x = self.spring_displacements(q)
        return 0.5 * self._k * x * x

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


class _RowBuffers:
    """Work arrays of ForceElements for n rows: features Z, forces F, wrench forces JW, powers' features Y."""

    def __init__(self, n: int, elements: ForceElements):
        nv = elements.nv
        self.Z = np.zeros((n, elements._width))
        if "one" in elements._slices:
            self.Z[:, elements._slices["one"]] = 1.0
        self.SC = np.zeros((n, 2 * elements._n_circ))  # (sin, cos) of the continuous springs' angle differences
        self.F = np.zeros((n, nv))
        self.JW = np.zeros((len(elements._wrenches), n, nv))
        self.Y = np.zeros((n, elements._y_width))
        self.flows = np.zeros((n, elements._n_flow_joint))


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
