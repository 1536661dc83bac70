"""The time-stepper's cone solver: the impulses of one contact step, exact Coulomb friction, in a fixed order.

The problem (scenes/contact.py builds it): find impulses λ with

    λ ∈ K,   ũ = u + Φ(u) ∈ K*,   λᵀũ = 0,        u = G λ + g   (the constraint velocities after the step)

where K is a product of blocks: a Coulomb cone per contact point (rows t1, t2, n; ‖λ_t‖ ≤ μ λ_n), a half-line per
enforced limit (λ ≥ 0) and an interval per joint with dry friction (|λ| ≤ F h); K* is its dual, and Φ is De Saxcé's
correction (0, 0, μ‖u_t‖) on each cone, which makes the conic problem Coulomb's law exactly: a sliding contact keeps
u_n = 0 and its impulse opposes the slip on the cone's edge.

The solution is the zero of the natural map F(λ) = λ − P_K(λ − ũ(λ) / s) (P_K the projection onto K, s per block
its mean diagonal of G), and the residual max_b s_b ‖F_b(λ)‖ is a velocity [m/s, rad/s].

How it is solved:

1. Newton's method on F (semismooth: the generalized Jacobian of the projection and of Φ, each block's own
   formula), warm-started from the previous step's impulses at the same contacts, with a backtracking (Armijo)
   line search on ‖F‖² and a tiny diagonal regularization (redundant contacts, such as the four corners of a box
   on the ground, make the Jacobian singular). It converges quadratically once the contacts' states (open,
   sticking, sliding) are right: at rest, one or two iterations end the step to round-off.
2. The fallback, when Newton has not met the tolerance after NEWTON_ITERATIONS: ADMM (operator splitting, the
   scheme of Pinocchio's ADMMConstraintSolver: a proximal x-update on G + (μ + τρ)I factored by Cholesky, the
   projection onto K, the dual variable carrying the De Saxcé-corrected velocities; ρ from G's spectral bounds,
   multiplied or divided as the primal and dual residuals fall out of balance), which needs no regular Jacobian and
   makes steady progress on degenerate problems (a robot collapsing onto tens of contact points: 60+ rows on 18
   coordinates), with Newton tried again from its iterate after FALLBACK_ROUNDS, 4 x FALLBACK_ROUNDS, ...
   iterations. The `pgs` option's fallback is nonsmooth Gauss–Seidel instead (each block's own problem solved
   exactly by the same Newton, the others held, block after block).

Tolerance: the residual must be at most TOLERANCE times the step's velocity scale (the largest free constraint
velocity |J v_free|, at least |g| h): a physical, problem-relative bound. A step that reaches its iteration budget
(max_iterations: Newton's and the fallback's iterations together) keeps its best iterate; it counts as a fallback when that
iterate's residual is within FALLBACK_TOLERANCE times the velocity scale, else as unconverged.

Every sum is formed in index order starting from +0.0 (numpy's ``add.accumulate`` is sequential; C++ adds the
same products in the same order and may skip structural zeros, which cannot change a sum started at +0.0), so the
native kernel (src/native/contact.cpp) computes the same impulses bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

CONE, HALFLINE, INTERVAL = 0, 1, 2  # block kinds
TOLERANCE = 1e-9  # the residual's bound, relative to the step's velocity scale
FALLBACK_TOLERANCE = 1e-4  # the same, for a step that ends its iteration budget in the fallback
NEWTON_ITERATIONS = 20  # before the fallback
FALLBACK_ROUNDS = 10  # ADMM iterations or Gauss–Seidel sweeps before Newton is tried again (then 4x as many, ...)
PROXIMAL = 1e-6  # ADMM's proximal weight μ, relative to G's largest eigenvalue (bounded by Gershgorin's)
RELAXATION = 0.5  # ADMM's τ
RHO_POWER = 0.2  # ρ = √(L μ) (L / μ)^RHO_POWER at first, then multiplied or divided by (L / μ)^RHO_STEP ...
RHO_STEP = 0.05
RHO_BALANCE = 10.0  # ... when the primal and dual residuals differ by more than this ratio
RHO_MIN, RHO_MAX = 1e-6, 1e6  # ρ's range [m/s per N·s]
LOCAL_ITERATIONS = 20  # Newton iterations of one block's problem in a sweep
REGULARIZATION = 1e-10  # added to the Newton matrix's diagonal (dimensionless: F is scaled by s) ...
DAMPING = 1e-4  # ... or this after a shortened step (newton())
ARMIJO = 1e-4  # sufficient decrease of ‖F‖² along a Newton step
SHORTEST_STEP = 1e-8  # the line search gives up below this fraction of a Newton step


def zsum(products: np.ndarray, axis: int = -1) -> np.ndarray:
    """The sum of `products` along `axis`, in index order, started from +0.0 (as contact.cpp's loops: see the
    module docstring)."""
    return np.add.accumulate(products, axis=axis).take(-1, axis=axis) + 0.0


def matvec(A: np.ndarray, x: np.ndarray) -> np.ndarray:
    """A @ x, each row's products summed in column order from +0.0."""
    if A.shape[1] == 0:
        return np.zeros(A.shape[0])
    return zsum(A * x, axis=1)


@dataclass
class Blocks:
    """The blocks of K, in row order.

    Attributes:
        kind: CONE, HALFLINE or INTERVAL per block.
        start: its first row.
        param: μ for a cone, the bound F h [N·m·s or N·s] for an interval, 0 for a half-line.
    """

    kind: np.ndarray
    start: np.ndarray
    param: np.ndarray

    def __post_init__(self) -> None:
        kind, start, param = self.kind, self.start, self.param
        cone = kind == CONE
        self.cone_rows = (start[cone][:, None] + np.arange(3)).astype(int)  # (c, 3): t1, t2, n
        self.mu = param[cone]
        self.half_rows = start[kind == HALFLINE].astype(int)
        self.box_rows = start[kind == INTERVAL].astype(int)
        self.bound = param[kind == INTERVAL]
        self.rows = int(3 * cone.sum() + (~cone).sum())

    @property
    def size(self) -> int:
        return self.rows


# ---- projections, the De Saxcé correction and the residual ----------------------------------------------------------
def project_cones(t1: np.ndarray, t2: np.ndarray, n: np.ndarray, mu: np.ndarray) -> tuple[np.ndarray, ...]:
    """The Euclidean projection of (t1, t2, n) onto the cones ‖t‖ ≤ μ n, elementwise."""
    tn = np.sqrt(t1 * t1 + t2 * t2)
    inside = tn <= mu * n
    polar = mu * tn <= -n
    with np.errstate(divide="ignore", invalid="ignore"):
        a = (mu * tn + n) / (mu * mu + 1.0)
        scale = mu * a / tn
        p1, p2 = scale * t1, scale * t2
    p1 = np.where(inside, t1, np.where(polar, 0.0, p1))
    p2 = np.where(inside, t2, np.where(polar, 0.0, p2))
    pn = np.where(inside, n, np.where(polar, 0.0, a))
    return p1, p2, pn


def project(x: np.ndarray, blocks: Blocks) -> np.ndarray:
    """The projection of x onto K."""
    out = x.copy()
    c = blocks.cone_rows
    if len(c):
        out[c[:, 0]], out[c[:, 1]], out[c[:, 2]] = project_cones(x[c[:, 0]], x[c[:, 1]], x[c[:, 2]], blocks.mu)
    h = blocks.half_rows
    out[h] = np.where(x[h] > 0.0, x[h], 0.0)
    b, bound = blocks.box_rows, blocks.bound
    out[b] = np.where(x[b] > bound, bound, np.where(x[b] < -bound, -bound, x[b]))
    return out


def de_saxce(u: np.ndarray, blocks: Blocks) -> np.ndarray:
    """Φ(u): μ‖u_t‖ on each cone's normal row, 0 elsewhere."""
    s = np.zeros(len(u))
    c = blocks.cone_rows
    if len(c):
        s[c[:, 2]] = blocks.mu * np.sqrt(u[c[:, 0]] * u[c[:, 0]] + u[c[:, 1]] * u[c[:, 1]])
    return s


def block_scales(G: np.ndarray, blocks: Blocks) -> np.ndarray:
    """s per row: its block's mean diagonal of G (a cone's three rows share theirs) [m/s per N·s]."""
    d = np.diagonal(G).copy()
    c = blocks.cone_rows
    if len(c):
        mean = ((d[c[:, 0]] + d[c[:, 1]]) + d[c[:, 2]]) / 3.0
        for k in range(3):
            d[c[:, k]] = mean
    return d


def residual(lam: np.ndarray, u: np.ndarray, blocks: Blocks, scales: np.ndarray) -> float:
    """The natural-map residual of λ (in K) with constraint velocities u [m/s, rad/s]: zero exactly at a solution."""
    if not len(lam):
        return 0.0
    t = u + de_saxce(u, blocks)
    diff = lam - project(lam - t / scales, blocks)
    worst = 0.0
    c = blocks.cone_rows
    if len(c):
        d0, d1, d2 = diff[c[:, 0]], diff[c[:, 1]], diff[c[:, 2]]
        worst = float(np.max(scales[c[:, 0]] * np.sqrt((d0 * d0 + d1 * d1) + d2 * d2)))
    single = np.concatenate([blocks.half_rows, blocks.box_rows])
    if len(single):
        worst = max(worst, float(np.max(scales[single] * np.abs(diff[single]))))
    return worst


# ---- dense linear algebra in a fixed order ---------------------------------------------------------------------------
def lu_solve(A: np.ndarray, b: np.ndarray) -> np.ndarray:
    """x with A x = b by Gaussian elimination with partial pivoting (the first largest pivot)."""
    A = A.copy()
    b = b.copy()
    p = len(b)
    for j in range(p):
        k = j + int(np.argmax(np.abs(A[j:, j])))
        if k != j:
            A[[j, k]] = A[[k, j]]
            b[j], b[k] = b[k], b[j]
        if j + 1 < p:
            factors = A[j + 1 :, j] / A[j, j]
            A[j + 1 :, j + 1 :] -= factors[:, None] * A[j, j + 1 :]
            b[j + 1 :] -= factors * b[j]
    x = np.empty(p)
    for i in range(p - 1, -1, -1):
        x[i] = (b[i] - (zsum(A[i, i + 1 :] * x[i + 1 :]) if i + 1 < p else 0.0)) / A[i, i]
    return x


def cholesky(A: np.ndarray) -> np.ndarray:
    """L with L Lᵀ = A (A symmetric positive definite), column by column."""
    m = len(A)
    L = np.zeros((m, m))
    for j in range(m):
        row = L[j, :j]
        L[j, j] = np.sqrt(A[j, j] - zsum(row * row)) if j else np.sqrt(A[j, j] - 0.0)
        if j + 1 < m:
            s = zsum(L[j + 1 :, :j] * row, axis=1) if j else np.zeros(m - j - 1)
            L[j + 1 :, j] = (A[j + 1 :, j] - s) / L[j, j]
    return L


def cholesky_solve(L: np.ndarray, b: np.ndarray) -> np.ndarray:
    """x with L Lᵀ x = b: forward, then backward substitution."""
    m = len(b)
    y = np.empty(m)
    for i in range(m):
        y[i] = (b[i] - (zsum(L[i, :i] * y[:i]) if i else 0.0)) / L[i, i]
    x = np.empty(m)
    for i in range(m - 1, -1, -1):
        x[i] = (y[i] - (zsum(L[i + 1 :, i] * x[i + 1 :]) if i + 1 < m else 0.0)) / L[i, i]
    return x


# ---- Newton on the natural map ----------------------------------------------------------------------------------------
def natural_map(
    G: np.ndarray, g: np.ndarray, blocks: Blocks, scales: np.ndarray, lam: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(F(λ), u, y): F = λ − P_K(y), y = λ − (u + Φ(u)) / s, u = G λ + g."""
    u = matvec(G, lam) + g
    y = lam - (u + de_saxce(u, blocks)) / scales
    return lam - project(y, blocks), u, y


def newton_matrix(
    G: np.ndarray, blocks: Blocks, scales: np.ndarray, u: np.ndarray, y: np.ndarray, damping: float
) -> np.ndarray:
    """The generalized Jacobian of F, I − P'(y) (I − (G + Φ'(u) G) / s), plus `damping` on the diagonal of the rows
    whose projection is not zero (an open block's rows are the identity: its impulse goes to exactly 0)."""
    m = len(u)
    A = G.copy()
    c = blocks.cone_rows
    for (t1, t2, n), mu in zip(c.tolist(), blocks.mu.tolist(), strict=True):
        s1, s2 = u[t1], u[t2]
        slip = np.sqrt(s1 * s1 + s2 * s2)
        if slip > 0.0:  # ∂(μ‖u_t‖)/∂u_t = μ u_t / ‖u_t‖
            A[n] = G[n] + ((mu * s1 / slip) * G[t1] + (mu * s2 / slip) * G[t2])
    B = np.eye(m) - A / scales[:, None]
    C = np.zeros((m, m))
    regularized = np.zeros(m, dtype=bool)
    for (t1, t2, n), mu in zip(c.tolist(), blocks.mu.tolist(), strict=True):
        P = cone_jacobian(y[t1], y[t2], y[n], mu)
        for i, r in enumerate((t1, t2, n)):
            C[r] = (P[i][0] * B[t1] + P[i][1] * B[t2]) + P[i][2] * B[n]
        regularized[[t1, t2, n]] = P[2][2] != 0.0
    for r in blocks.half_rows.tolist():
        regularized[r] = y[r] > 0.0
        C[r] = (1.0 if regularized[r] else 0.0) * B[r]
    for r, bound in zip(blocks.box_rows.tolist(), blocks.bound.tolist(), strict=True):
        regularized[r] = -bound < y[r] < bound
        C[r] = (1.0 if regularized[r] else 0.0) * B[r]
    H = np.eye(m) - C
    H[regularized, regularized] += damping
    return H


def cone_jacobian(t1: float, t2: float, n: float, mu: float) -> list[list[float]]:
    """The Jacobian of the projection onto ‖t‖ ≤ μ n at (t1, t2, n): I inside, 0 in the polar cone, else that of
    a (μ t/‖t‖, 1), a = (μ‖t‖ + n) / (μ² + 1)."""
    tn = np.sqrt(t1 * t1 + t2 * t2)
    if tn <= mu * n:
        return [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    if mu * tn <= -n:
        return [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]]
    c = mu * mu + 1.0
    a = (mu * tn + n) / c
    h = (t1 / tn, t2 / tn)
    k = mu * a / tn
    m2 = mu * mu
    out = [[0.0] * 3 for _ in range(3)]
    for i in range(2):
        for j in range(2):
            hh = h[i] * h[j]
            out[i][j] = (m2 * hh) / c + k * ((1.0 if i == j else 0.0) - hh)
        out[i][2] = mu * h[i] / c
        out[2][i] = mu * h[i] / c
    out[2][2] = 1.0 / c
    return out


def newton(
    G: np.ndarray,
    g: np.ndarray,
    blocks: Blocks,
    scales: np.ndarray,
    lam: np.ndarray,
    tolerance: float,
    iterations: int,
) -> tuple[np.ndarray, float, int]:
    """Newton's method on F from λ (module docstring): (λ projected onto K, its residual, iterations taken); it
    stops at the tolerance, after `iterations`, or when the line search finds no decrease. The matrix's diagonal
    damping is REGULARIZATION, or DAMPING (Levenberg–Marquardt's) after a step the line search had to shorten: far
    from the solution redundant contacts make the Jacobian nearly singular, and the undamped step is mostly a
    useless internal force between them; the step is then tried again, damped, from the same λ."""
    F, u, y = natural_map(G, g, blocks, scales, lam)
    best, best_r = _candidate(G, g, blocks, scales, lam)
    damping = REGULARIZATION
    taken = 0
    while best_r > tolerance and taken < iterations:
        d = lu_solve(newton_matrix(G, blocks, scales, u, y, damping), -F)
        taken += 1
        f0 = zsum(F * F)
        step = 1.0
        while True:
            trial = lam + step * d
            F_t, u_t, y_t = natural_map(G, g, blocks, scales, trial)
            if zsum(F_t * F_t) <= (1.0 - ARMIJO * step) * f0 or step < SHORTEST_STEP:
                break
            step = 0.5 * step
        if step < 1.0 and damping < DAMPING:  # shortened: damp, and try again from λ
            damping = DAMPING
            continue
        if step < SHORTEST_STEP:
            break
        if step == 1.0:
            damping = REGULARIZATION
        lam, F, u, y = trial, F_t, u_t, y_t
        candidate, r = _candidate(G, g, blocks, scales, lam)
        if r < best_r:
            best, best_r = candidate, r
    return best, best_r, taken


def _candidate(
    G: np.ndarray, g: np.ndarray, blocks: Blocks, scales: np.ndarray, lam: np.ndarray
) -> tuple[np.ndarray, float]:
    """λ projected onto K and its residual."""
    candidate = project(lam, blocks)
    return candidate, residual(candidate, matvec(G, candidate) + g, blocks, scales)


# ---- the fallbacks: ADMM, nonsmooth Gauss–Seidel ---------------------------------------------------------------------------
class Admm:
    """ADMM from λ (module docstring): step() advances one iteration and returns its projected iterate."""

    def __init__(self, G: np.ndarray, g: np.ndarray, blocks: Blocks, lam: np.ndarray):
        self.G, self.g, self.blocks = G, g, blocks
        m = len(g)
        largest = float(np.max(zsum(np.abs(G), axis=1)))  # Gershgorin's bound on G's largest eigenvalue
        self.mu = PROXIMAL * largest
        cond = largest / self.mu
        self.rho = min(max(float(np.sqrt(largest * self.mu)) * cond**RHO_POWER, RHO_MIN), RHO_MAX)
        self.factor = cond**RHO_STEP
        self.x = lam.copy()
        self.y = project(lam, blocks)
        u = matvec(G, self.y) + g
        self.z = u + de_saxce(u, blocks)
        self.eye = np.eye(m)
        self.L = cholesky(G + (self.mu + RELAXATION * self.rho) * self.eye)

    def step(self) -> np.ndarray:
        G, g, blocks, mu = self.G, self.g, self.blocks, self.mu
        x_prev, z_prev = self.x, self.z
        tr = RELAXATION * self.rho
        y = project(x_prev - z_prev / tr, blocks)
        rhs = -((((g + de_saxce(z_prev, blocks)) - tr * y) - mu * x_prev) - z_prev)
        x = cholesky_solve(self.L, rhs)
        self.z = z_prev - tr * (x - y)
        self.x, self.y = x, y
        primal = float(np.max(np.abs(x - y)))
        dual = max(mu, tr) * float(np.max(np.abs(x - x_prev)))
        rho = self.rho
        if primal > RHO_BALANCE * dual:
            rho = rho * self.factor
        elif dual > RHO_BALANCE * primal:
            rho = rho / self.factor
        rho = min(max(rho, RHO_MIN), RHO_MAX)
        if rho != self.rho:
            self.rho = rho
            self.L = cholesky(G + (mu + RELAXATION * rho) * self.eye)
        return y


class Sweeps:
    """Nonsmooth Gauss–Seidel from λ: step() sweeps once over the blocks, in row order, each block's problem (the
    others' impulses held) solved exactly (a cone by Newton, a half-line or an interval in closed form)."""

    def __init__(self, G: np.ndarray, g: np.ndarray, blocks: Blocks, scales: np.ndarray, lam: np.ndarray, tolerance: float):
        self.G, self.g, self.blocks, self.scales, self.tolerance = G, g, blocks, scales, tolerance
        self.lam = lam.copy()

    def step(self) -> np.ndarray:
        G, g, blocks, scales, lam = self.G, self.g, self.blocks, self.scales, self.lam
        for kind, start, param in zip(blocks.kind.tolist(), blocks.start.tolist(), blocks.param.tolist(), strict=True):
            size = 3 if kind == CONE else 1
            rows = slice(start, start + size)
            others = lam.copy()
            others[rows] = 0.0
            q = matvec(G[rows], others) + g[rows]  # the block's free velocity: the other blocks' impulses applied
            if kind == CONE:
                local = Blocks(np.array([CONE]), np.array([0]), np.array([param]))
                W = G[rows, rows]
                lam[rows] = newton(W, q, local, scales[rows], lam[rows], self.tolerance, LOCAL_ITERATIONS)[0]
            else:
                x = -q[0] / G[start, start]
                if kind == HALFLINE:
                    lam[start] = x if x > 0.0 else 0.0
                else:
                    lam[start] = param if x > param else (-param if x < -param else x)
        return lam.copy()


# ---- the driver -----------------------------------------------------------------------------------------------------------
@dataclass
class Solution:
    """What a solve returns.

    Attributes:
        impulses: λ, shape (m,).
        converged: the residual met the tolerance, or the fallback's.
        fallback: the step needed the fallback (ADMM, or Gauss–Seidel under `pgs`).
        iterations: Newton iterations, and the fallback's iterations or sweeps.
        residual: the natural-map residual of `impulses` [m/s, rad/s].
    """

    impulses: np.ndarray
    converged: bool
    fallback: bool
    iterations: int
    residual: float


def solve(
    G: np.ndarray,
    g: np.ndarray,
    blocks: Blocks,
    guess: np.ndarray,
    scale: float,
    max_iterations: int,
    *,
    pgs: bool = False,
) -> Solution:
    """The impulses of the problem (module docstring), warm-started from `guess`.

    Args:
        G: the Delassus matrix, symmetric, (m, m) [m/s per N·s].
        g: the free constraint velocities with their biases, (m,).
        blocks: the blocks of K.
        guess: warm-start impulses, (m,) (projected onto K first).
        scale: the step's velocity scale [m/s, rad/s] (the tolerances are relative to it).
        max_iterations: Newton iterations and the fallback's iterations at most.
        pgs: Gauss–Seidel sweeps first (no Newton before them) and as the fallback.
    """
    tolerance = TOLERANCE * scale
    scales = block_scales(G, blocks)
    lam, r = _candidate(G, g, blocks, scales, guess)
    taken = 0
    if r <= tolerance:
        return Solution(lam, True, False, 0, r)
    if not pgs:
        lam, r, taken = newton(G, g, blocks, scales, lam, tolerance, min(NEWTON_ITERATIONS, max_iterations))
        if r <= tolerance:
            return Solution(lam, True, False, taken, r)
    best, best_r = lam, r
    driver: Admm | Sweeps = Sweeps(G, g, blocks, scales, lam, tolerance) if pgs else Admm(G, g, blocks, lam)
    rounds, next_newton = 0, FALLBACK_ROUNDS
    while taken < max_iterations:
        iterate = driver.step()
        rounds += 1
        taken += 1
        candidate, r = _candidate(G, g, blocks, scales, iterate)
        if r < best_r:
            best, best_r = candidate, r
        if r <= tolerance:
            break
        if rounds == next_newton and taken < max_iterations:
            next_newton *= 4
            found, r, n = newton(G, g, blocks, scales, iterate, tolerance, min(NEWTON_ITERATIONS, max_iterations - taken))
            taken += n
            if r < best_r:
                best, best_r = found, r
            if r <= tolerance:
                break
    return Solution(best, best_r <= FALLBACK_TOLERANCE * scale, True, taken, best_r)
