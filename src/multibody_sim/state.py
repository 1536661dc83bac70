"""The configuration manifold: integrate, difference and the local-chart map, in one place.

Every integrator moves configurations through this module, so nobody writes ``q + dt * v`` on a quaternion.
"""

from __future__ import annotations

import numpy as np
import pinocchio as pin

_ARG_V = pin.ArgumentPosition.ARG1


class ConfigurationSpace:
    """Pinocchio's configuration manifold of one model, with the chart map explicit RK stages need.

    Runge–Kutta stages are built in the local chart ``q = integrate(q_n, xi)`` around the step's start
    ``q_n``. There the state (xi, v) lives in a vector space and obeys ``xi' = J(q_n, xi)^-1 v`` with
    ``J = dIntegrate/dv``. ``J`` is the identity for joints whose Lie group is commutative (revolute,
    prismatic, continuous); only the blocks of non-commutative joints (free-flyer SE(3), spherical SO(3),
    planar SE(2)) need the solve. Summing stage velocities taken at different base points instead would drop
    RK4 to order 2 on a floating base.

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
        if self.curved_blocks:  # imported here: scipy.linalg costs a fraction of a second to import
            from scipy.linalg.lapack import dgesv

            self._solve = dgesv
        self.neutral = pin.neutral(model)

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

    def chart_velocity(self, q_base: np.ndarray, xi: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Rate of the chart coordinate, xi' = J(q_base, xi)^-1 v, where q = integrate(q_base, xi)."""
        if not self.curved_blocks:
            return v
        J = pin.dIntegrate(self.model, q_base, xi, _ARG_V)
        xi_dot = v.copy()
        for start, stop in self.curved_blocks:
            # LAPACK directly: numpy's solve wrapper costs more than the 6x6 solve itself, on the hot path.
            _, _, solution, info = self._solve(J[start:stop, start:stop], v[start:stop])
            # The chart is singular only where a stage rotated by 2π within one step: the step is far too long or
            # the state has diverged. NaN lets the loop report it as divergence.
            xi_dot[start:stop] = solution if info == 0 else np.nan
        return xi_dot

    def is_normalized(self, q: np.ndarray, tolerance: float = 1e-6) -> bool:
        """Whether the unit-quaternion and unit-complex entries of q have unit norm."""
        return bool(pin.isNormalized(self.model, q, tolerance))


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
