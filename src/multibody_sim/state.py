"""The configuration manifold: integrate, difference and the local-chart map, in one place.

Every integrator moves configurations through this module, so nobody writes ``q + dt * v`` on a quaternion.
"""

from __future__ import annotations

import functools
from collections.abc import Callable
from typing import Any

import numpy as np
import pinocchio as pin

from .ordered import ordered_matvec

_ARG_Q = pin.ArgumentPosition.ARG0
_ARG_V = pin.ArgumentPosition.ARG1

# Taylor coefficients b_n of x / (1 - e^-x) = Σ b_n xⁿ (b_n = |B_n| / n! but b_1 = +½): the chart map's series,
# J(ξ)⁻¹ = Σ b_n A(ξ)ⁿ with A linear in ξ (see ConfigurationSpace).
CHART_SERIES = (1.0, 1 / 2, 1 / 12, 0.0, -1 / 720, 0.0, 1 / 30240, 0.0, -1 / 1209600)
# The same series in H = A / 2 (an exact scaling): Σ b_n 2ⁿ Hⁿ, whose first two coefficients are 1, so Horner's
# rule on H needs no multiplication at its last two steps.
_HALF_SERIES = tuple(b * 2.0**n for n, b in enumerate(CHART_SERIES))


def chart_terms(order: int) -> int:
    """Highest power of A(ξ) an explicit Runge–Kutta method of this order needs in the chart map.

    A stage's ξ is O(h), so dropping the terms above A^K changes ξ' by O(h^(K+1)) and the step by O(h^(K+2)): a
    method of order p keeps its order with K = p - 1 (Munthe-Kaas's truncated dexpinv), lowered to the last non-zero
    coefficient (b_3 = b_5 = … = 0: RK4 needs A² only).
    """
    k = min(max(order - 1, 0), len(CHART_SERIES) - 1)
    while k > 1 and CHART_SERIES[k] == 0.0:
        k -= 1
    return k


class ConfigurationSpace:
    """Pinocchio's configuration manifold of one model, with the chart map explicit RK stages need.

    Runge–Kutta stages are built in the local chart ``q = integrate(q_n, xi)`` around the step's start
    ``q_n``. There the state (xi, v) lives in a vector space and obeys ``xi' = J(xi)^-1 v`` with
    ``J = dIntegrate/dv``. ``J`` is the identity for joints whose Lie group is commutative (revolute,
    prismatic, continuous); on the blocks of non-commutative joints (free-flyer SE(3), spherical SO(3), planar
    SE(2)) ``J(xi)^-1 = Σ b_n A(xi)^n`` with ``A`` linear in xi (± the Lie algebra's ad). The integrators use
    this series truncated after the power their order needs (``chart_terms``): a few small products instead of
    a solve, and no loss of digits at small angles (Pinocchio 4.1's Jexp6 loses up to 8 just above 1e-4 rad).
    Summing stage velocities taken at different base points instead would drop RK4 to order 2 on a floating
    base.

    Attributes:
        nq: configuration size.
        nv: tangent (velocity) size.
        curved_blocks: (start, stop) velocity-index ranges whose chart Jacobian is not the identity.
        neutral: the neutral configuration, shape (nq,) (do not modify).
    """

    def __init__(self, model: pin.Model):
        self.model = model
        self.nq = model.nq
        self.nv = model.nv
        self.curved_blocks = _curved_blocks(model)
        # Per curved block, A's generators G (d, d·d): A(xi) = (xi_block @ G).reshape(d, d). Every entry of A is
        # one coordinate of xi times 0 or ±1, so H = A / 2 is built by indexing: H = xi_block[index] * sign / 2.
        self.chart_generators = [_chart_generators(model, start, stop) for start, stop in self.curved_blocks]
        self._chart_entries = [
            (np.argmax(G != 0.0, axis=0).reshape(stop - start, -1), 0.5 * G.sum(axis=0).reshape(stop - start, -1))
            for (start, stop), G in zip(self.curved_blocks, self.chart_generators, strict=True)
        ]
        # For a stack of rows, H y without per-row matrices: H's non-zero entries (i, j), each ±xi_k / 2, give
        # the products xi_k y_j (18 on se(3)), which one matrix S (terms, d) of ±1/2 sums into their outputs i.
        self._chart_products = [
            _chart_products(G, stop - start)
            for (start, stop), G in zip(self.curved_blocks, self.chart_generators, strict=True)
        ]
        self.neutral = pin.neutral(model)
        self._batch: BatchSpace | None = None

    @property
    def is_flat(self) -> bool:
        """True when the chart map is the identity (no free-flyer, spherical or planar joint)."""
        return not self.curved_blocks

    def integrate(self, q: np.ndarray, dv: np.ndarray) -> np.ndarray:
        """q ⊕ dv: move q (nq,) along the tangent vector dv (nv,) for unit time."""
        return pin.integrate(self.model, q, dv)

    def difference(self, q0: np.ndarray, q1: np.ndarray) -> np.ndarray:
        """q1 ⊖ q0: the tangent vector (nv,) that integrate() maps q0 to q1 with."""
        return pin.difference(self.model, q0, q1)

    def interpolate(self, q0: np.ndarray, q1: np.ndarray, u: float) -> np.ndarray:
        """Geodesic interpolation between q0 (u = 0) and q1 (u = 1)."""
        return pin.interpolate(self.model, q0, q1, u)

    def chart_velocity(self, xi: np.ndarray, v: np.ndarray, terms: int) -> np.ndarray:
        """Rate of the chart coordinate, xi' = J(xi)^-1 v with the series truncated after A^terms, shape (nv,)."""
        if not self.curved_blocks or terms == 0:
            return v
        out = v.copy()
        for (start, stop), (index, half_sign) in zip(self.curved_blocks, self._chart_entries, strict=True):
            H = xi[start:stop][index] * half_sign
            out[start:stop] = _chart_series(functools.partial(ordered_matvec, H), v[start:stop], terms)
        return out

    def chart_rates(self, XI: np.ndarray, V: np.ndarray, terms: int, out: np.ndarray) -> np.ndarray:
        """chart_velocity of n rows at once, shapes (n, nv) × 3; returns out. The same series as chart_velocity,
        but each H y is summed from its non-zero products by one matrix product over all rows (an order of
        additions that can differ from chart_velocity's by an ulp); no row's result depends on the batch."""
        np.copyto(out, V)
        if terms == 0:
            return out
        for (start, stop), (k, j, S) in zip(self.curved_blocks, self._chart_products, strict=True):
            xi = XI[:, start:stop][:, k]  # (n, terms): the coordinate of xi in each product

            def apply_h(y: np.ndarray, xi: np.ndarray = xi, j: np.ndarray = j, S: np.ndarray = S) -> np.ndarray:
                return np.multiply(xi, y[:, j]) @ S

            out[:, start:stop] = _chart_series(apply_h, np.ascontiguousarray(V[:, start:stop]), terms)
        return out

    def chart_matrix(self, xi: np.ndarray, terms: int) -> list[np.ndarray]:
        """The truncated J(xi)^-1 = Σ_{n≤terms} b_n A(xi)^n of each curved block, shapes (d, d)."""
        out = []
        for (start, stop), (index, half_sign) in zip(self.curved_blocks, self._chart_entries, strict=True):
            H = xi[start:stop][index] * half_sign
            out.append(_chart_series(H.dot, np.eye(stop - start), terms))
        return out

    def d_integrate(self, q: np.ndarray, xi: np.ndarray, d_q: np.ndarray, d_xi: np.ndarray) -> np.ndarray:
        """Derivative of (q ⊕ δq) ⊕ ξ in the tangent space at q ⊕ ξ: D_q d_q + D_ξ d_xi, where d_q and d_xi
        (each (nv, k)) are the derivatives of δq and ξ with respect to k variables (identities on flat models)."""
        if self.is_flat:
            return d_q + d_xi
        D_q = pin.dIntegrate(self.model, q, xi, _ARG_Q)
        D_xi = pin.dIntegrate(self.model, q, xi, _ARG_V)
        return D_q @ d_q + D_xi @ d_xi

    def add_chart_curvature(
        self, d_rate: np.ndarray, xi: np.ndarray, v: np.ndarray, d_xi: np.ndarray, terms: int
    ) -> None:
        """Add ∂(chart_velocity(ξ, v, terms))/∂ξ · d_xi to d_rate (nv, k) on each curved block (in place)."""
        for (start, stop), G in zip(self.curved_blocks, self.chart_generators, strict=True):
            N = _chart_velocity_derivative(G, xi[start:stop], v[start:stop], terms)
            d_rate[start:stop] += N @ d_xi[start:stop]

    @property
    def batch(self) -> BatchSpace:
        """The same manifold over many rows at once (made on first use, then kept with this space)."""
        if self._batch is None:
            self._batch = BatchSpace(self.model)
        return self._batch

    def is_normalized(self, q: np.ndarray, tolerance: float = 1e-6) -> bool:
        """Whether the unit-quaternion and unit-complex entries of q have unit norm."""
        return bool(pin.isNormalized(self.model, q, tolerance))


def _chart_series(apply_h: Callable[[np.ndarray], np.ndarray], v: np.ndarray, terms: int) -> np.ndarray:
    """Σ_{n≤terms} c_n Hⁿ v by Horner's rule, with H = A / 2 applied by `apply_h` (c_n: _HALF_SERIES). v is a
    vector, rows of vectors (chart_rates) or a matrix (then the result is the truncated J⁻¹ itself when v = I)."""
    y = v * _HALF_SERIES[terms]
    for k in range(terms - 1, -1, -1):  # y = H y + c_k v
        y = apply_h(y)
        if k < 2:  # c_0 = c_1 = 1
            y += v
        elif _HALF_SERIES[k]:
            y += v * _HALF_SERIES[k]
    return y


def _chart_velocity_derivative(G: np.ndarray, xi: np.ndarray, V: np.ndarray, terms: int) -> np.ndarray:
    """∂/∂ξ of Σ_{n≤terms} b_n A(ξ)ⁿ V (ConfigurationSpace.chart_velocity) on one block, A(x) = (x @ G).reshape(d, d).

    The derivative of Aⁿ V along η is Σ_k A^k A(η) A^(n-1-k) V, and A(η) w = -A(w) η (A is ± the Lie algebra's ad,
    antisymmetric in its two arguments). With w_m = Aᵐ V and T_n = Σ_{k<n} A^k A(w_{n-1-k}) = A(w_{n-1}) + A T_{n-1}
    the derivative is -Σ b_n T_n.
    """
    d = len(V)
    A = (xi @ G).reshape(d, d)
    w = V.copy()
    T = np.zeros((d, d))
    N = np.zeros((d, d))
    for n in range(1, terms + 1):
        T = (w @ G).reshape(d, d) + A @ T
        if CHART_SERIES[n]:
            N -= CHART_SERIES[n] * T
        w = A @ w
    return N


def _chart_products(G: np.ndarray, d: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(k, j, S) with H(xi) y = (xi[k] * y[j]) @ S for H = A / 2 and A(xi) = (xi @ G).reshape(d, d): one term per
    non-zero entry G[k, i·d + j] of the generators, which S (terms, d) adds, times G's ±1 / 2, into output i."""
    k, column = np.nonzero(G)
    i, j = np.divmod(column, d)
    S = np.zeros((len(k), d))
    S[np.arange(len(k)), i] = 0.5 * G[k, column]
    return k, j, S


def _curved_blocks(model: pin.Model) -> list[tuple[int, int]]:
    """Velocity ranges of the joints whose chart Jacobian differs from the identity.

    Found numerically at a generic point, so no list of joint types has to be kept in step with Pinocchio.
    """
    rng = np.random.default_rng(0)
    q = pin.integrate(model, pin.neutral(model), rng.uniform(-1.0, 1.0, model.nv))
    xi = rng.uniform(-1.0, 1.0, model.nv)
    J = pin.dIntegrate(model, q, xi, _ARG_V)
    blocks = []
    for joint in model.joints[1:]:
        start, stop = joint.idx_v, joint.idx_v + joint.nv
        if stop > start and not np.allclose(J[start:stop, start:stop], np.eye(stop - start), atol=1e-12):
            blocks.append((start, stop))
    return blocks


def _chart_generators(model: pin.Model, start: int, stop: int) -> np.ndarray:
    """G (d, d·d) with J(xi)^-1 = I + ½ A(xi) + O(xi²), A(xi) = (xi @ G).reshape(d, d), on one curved block.

    Found from Pinocchio's own chart Jacobian, J(ε e_k) = I - ½ A(e_k) ε + O(ε²): central differences give A(e_k)
    to O(ε²), and its entries (the Lie algebra's structure constants: 0 or ±1 for SE(3), SO(3) and SE(2)) are
    rounded, so no table of joint types has to be kept in step with Pinocchio.
    """
    d, eps = stop - start, 1e-4
    q = pin.neutral(model)
    G = np.empty((d, d, d))
    for k in range(d):
        step = np.zeros(model.nv)
        step[start + k] = eps
        plus = pin.dIntegrate(model, q, step, _ARG_V)[start:stop, start:stop]
        minus = pin.dIntegrate(model, q, -step, _ARG_V)[start:stop, start:stop]
        G[k] = (minus - plus) / eps
    rounded = np.round(G).reshape(d, d * d)
    # se(3), so(3) and se(2): constants 0 or ±1, at most one coordinate per entry of A (which the indexing needs)
    if np.abs(G.reshape(d, d * d) - rounded).max() > 1e-6 or (np.count_nonzero(rounded, axis=0) > 1).any():
        raise ValueError("a joint's Lie algebra is not one this chart map supports")  # pragma: no cover
    return rounded


class BatchSpace:
    """The configuration manifold over a batch: q ⊕ dv for n rows at once.

    Coordinates of joints whose configuration is a vector (revolute, prismatic: Pinocchio's integrate is
    q + dv there, checked) are added in one numpy operation per run of them; the other joints (free-flyer,
    spherical, continuous, planar) go through one ``pin.integrate`` call on a model made of n copies of just
    those joints: Pinocchio's own per-joint code, so its results bit for bit, in one C++ loop. (The chart map needs no
    batch version: ConfigurationSpace.chart_rates takes many rows.)
    """

    def __init__(self, model: pin.Model):
        self.model = model
        self.nq, self.nv = model.nq, model.nv
        runs: list[list[int]] = []  # [q start, v start, length] of consecutive vector-coordinate joints
        lie: list[Any] = []
        lie_q: list[int] = []
        lie_v: list[int] = []
        for joint in model.joints[1:]:
            if joint.nq == joint.nv:
                if joint.nq == 0:
                    continue
                last = runs[-1] if runs else None
                if last is not None and last[0] + last[2] == joint.idx_q and last[1] + last[2] == joint.idx_v:
                    last[2] += joint.nq
                else:
                    runs.append([joint.idx_q, joint.idx_v, joint.nq])
            else:
                lie.append(joint)
                lie_q += range(joint.idx_q, joint.idx_q + joint.nq)
                lie_v += range(joint.idx_v, joint.idx_v + joint.nv)
        self.runs = [(q, v, n) for q, v, n in runs]
        self.lie_joints = lie
        self.lie_q, self.lie_v = indexer(lie_q), indexer(lie_v)
        self._lie_models: dict[int, pin.Model] = {}
        self.per_element = not self._check_integrate()
        self.vector_space = not lie and self.runs == [(0, 0, model.nq)] and not self.per_element
        # Whether every vector coordinate sits nq - nv columns after its velocity (the other joints come first,
        # as a floating base does): then q's vector coordinates and v line up with the stage rates' row under
        # one offset, as on a vector space (see _rk_step).
        extra = model.nq - model.nv
        self.aligned = not self.per_element and all(q - v == extra for q, v, _ in self.runs)

    def _check_integrate(self) -> bool:
        """Whether the vectorised integrate gives pin.integrate's results bit for bit on this model (a few random
        rows): vector coordinates must really be q + dv, and the copies-of-joints model must act as the original."""
        model = self.model
        rng = np.random.default_rng(0)
        rows = 3
        Q = np.array([pin.integrate(model, pin.neutral(model), rng.uniform(-3.0, 3.0, model.nv)) for _ in range(rows)])
        DV = rng.normal(size=(rows, model.nv)) * 10.0 ** rng.uniform(-8, 1, (rows, model.nv))
        out = np.empty_like(Q)
        self._vectorised_integrate(Q, DV, out)
        return all(np.array_equal(out[b], pin.integrate(model, Q[b], DV[b])) for b in range(rows))

    def _lie_model(self, n: int) -> pin.Model:
        model = self._lie_models.get(n)
        if model is None:
            if len(self._lie_models) >= _LIE_MODELS_KEPT:  # batches shrink as elements stop: keep the latest
                del self._lie_models[next(iter(self._lie_models))]
            model = pin.Model()
            for b in range(n):
                for j, joint in enumerate(self.lie_joints):
                    model.addJoint(0, joint, pin.SE3.Identity(), f"element{b}_joint{j}")
            self._lie_models[n] = model
        return model

    def integrate(self, Q: np.ndarray, DV: np.ndarray, out: np.ndarray) -> None:
        """out = Q ⊕ DV row by row, as pin.integrate; shapes (n, nq), (n, nv), (n, nq)."""
        if self.vector_space:
            np.add(Q, DV, out=out)
        elif self.per_element:
            model = self.model
            for j in range(len(Q)):
                out[j] = pin.integrate(model, Q[j], DV[j])
        else:
            self._vectorised_integrate(Q, DV, out)

    def _vectorised_integrate(self, Q: np.ndarray, DV: np.ndarray, out: np.ndarray) -> None:
        for q, v, n in self.runs:
            np.add(Q[:, q : q + n], DV[:, v : v + n], out=out[:, q : q + n])
        if self.lie_joints:
            self.integrate_lie(self.lie_coordinates(Q), DV, out)

    def lie_coordinates(self, Q: np.ndarray) -> np.ndarray:
        """The coordinates of Q's non-vector joints, flat and contiguous: integrate_lie's argument."""
        return np.ascontiguousarray(Q[:, self.lie_q]).reshape(-1)

    def integrate_lie(self, q_lie: np.ndarray, DV: np.ndarray, out: np.ndarray) -> None:
        """The non-vector joints' columns of out = Q ⊕ DV, from q_lie = lie_coordinates(Q); DV (n, nv)."""
        n = len(DV)
        dv = np.ascontiguousarray(DV[:, self.lie_v]).reshape(-1)
        out[:, self.lie_q] = pin.integrate(self._lie_model(n), q_lie, dv).reshape(n, -1)


_LIE_MODELS_KEPT = 8  # copies-of-joints models kept per space, one per batch size


def indexer(indices: list[int]) -> slice | np.ndarray:
    """Column indices as a slice when they are consecutive (a view and a fast copy), else as an index array."""
    if indices and indices == list(range(indices[0], indices[-1] + 1)):
        return slice(indices[0], indices[-1] + 1)
    return np.array(indices, dtype=int)
