"""Weighted sums in one fixed order, so that a step's arithmetic does not depend on the machine's BLAS.

``a @ K`` goes through BLAS, whose kernels sum in an order (blocks, fused multiply-adds) that depends on the CPU
and the library. Adaptive steps amplify any difference: an error estimate is a small difference of large stage
derivatives, so one unit in the last place of a stage moves the next step size by ~1e-6 relative. The steps'
sums are formed here instead: each product rounded, then added one after the other in index order (numpy's
``add.accumulate`` is sequential by definition); the native kernel (src/native/methods.hpp) sums the same way, so
both agree bit for bit.
"""

from __future__ import annotations

import numpy as np


def ordered_sum(weights: np.ndarray, terms: np.ndarray, axis: int = 0, out: np.ndarray | None = None) -> np.ndarray:
    """Σ_j weights[j] · terms[j] along `axis` (terms has len(weights) entries there), j ascending, each product
    rounded and then added to the running sum; written into `out` when given."""
    if axis == 0 and terms.ndim == 2:  # the row kernel's stages, (s, n): the same operations, fewer calls
        products = weights[:, None] * terms
        np.add.accumulate(products, axis=0, out=products)
        total = products[-1]
    else:
        shape = [1] * terms.ndim
        shape[axis] = len(weights)
        products = np.multiply(np.reshape(weights, shape), terms)
        total = np.add.accumulate(products, axis=axis).take(-1, axis=axis)
    if out is None:
        return total
    out[...] = total
    return out


def ordered_matvec(H: np.ndarray, y: np.ndarray) -> np.ndarray:
    """H @ y for a small matrix H (d, d), each row's products added in column order."""
    return np.add.accumulate(H * y, axis=1)[:, -1]


def ordered_dot(x: np.ndarray, y: np.ndarray) -> float:
    """x · y for vectors, the products added in index order."""
    return float(np.add.accumulate(x * y)[-1])
