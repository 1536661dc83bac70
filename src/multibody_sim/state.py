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
        self.neutral = pin.neutral(model)

    def native_data(self) -> dict[str, Any]:
        """The chart map as the native kernel takes it (_native.Chart's fields): each curved block's start and size
        with H = A / 2 as indices into the block's xi and signs (H[r, c] = xi[start + index[r d + c]] ·
        half_sign[r d + c]), and the series' coefficients in H."""
        return {
            "blocks": [
                {
                    "start": start,
                    "size": stop - start,
                    "index": index.ravel().astype(int).tolist(),
                    "half_sign": half_sign.ravel().tolist(),
                }
                for (start, stop), (index, half_sign) in zip(self.curved_blocks, self._chart_entries, strict=True)
            ],
            "half_series": list(_HALF_SERIES),
        }

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

    def is_normalized(self, q: np.ndarray, tolerance: float = 1e-6) -> bool:
        """Whether the unit-quaternion and unit-complex entries of q have unit norm."""
        return bool(pin.isNormalized(self.model, q, tolerance))


def _chart_series(apply_h: Callable[[np.ndarray], np.ndarray], v: np.ndarray, terms: int) -> np.ndarray:
    """Σ_{n≤terms} c_n Hⁿ v by Horner's rule, with H = A / 2 applied by `apply_h` (c_n: _HALF_SERIES). v is a
    vector or a matrix (then the result is the truncated J⁻¹ itself when v = I)."""
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
