"""The narrow phase of contact: the points where two shapes touch or nearly do (within the speculative margin).

Primitives against the ground (a half-space z ≥ h, normal +z) and a few pairs of primitives are computed here in
closed form, each point a material feature of its shape (a box's corner, a hull's vertex, a point of a cylinder's
rim), which is the warm start's identity across steps:

- sphere (radius r): its lowest point;
- box: its 8 corners;
- cylinder: 4 points of each end disk's rim, a quarter turn apart, starting at the lowest (on a disk lying flat:
  along its own x and y axes);
- capsule: the lowest points of its two end spheres;
- mesh (a convex hull): its vertices;
- sphere–sphere, sphere–box: the closest points, along the line between them;
- box–box: the separating-axis test over the 15 axes (3 face normals of each box, 9 edge cross products) gives
  the normal and the deepest separation; on a face axis, the other box's face most opposed to it (the incident
  face) clipped to the reference face (Sutherland–Hodgman against its 4 sides), each point of the clipped polygon
  named by the two polygon edges it joins (incident edges or reference sides); on an edge axis, the closest points
  of the two edges, one point (box_box). Apart (within the margin), a face contact's points are real point pairs and
  an edge contact's gap is the separation along its axis, a lower bound of the distance; a nearest pair that no axis
  names (vertex–vertex, vertex–edge) is seen through the best axis' points.

Every other pair (hulls between themselves, cylinders against boxes, ...) goes to coal (Pinocchio's
computeCollision and computeContactPatch on the pair alone), whose patch points are the features.

A pair's candidates are its features whose gap is below SPECULATIVE_MARGIN. Its patch is the candidates within
PATCH_DEPTH of the deepest (coal's patch tolerance: a box's top corners, a rounded foot's far vertices are not
part of what touches), and of the patch at most MAX_PATCH_POINTS points are kept: the deepest, then one after the
other the point farthest (along the contact plane) from those kept, none closer than MIN_PATCH_SPACING to another
when a mesh hull is in the pair (PRIMITIVE_SPACING otherwise): near-duplicate rows add no wrench the solver can use
and make its problem degenerate. Pairs whose bounding spheres are farther apart than the margin are skipped before any of this.

The arithmetic is written out in a fixed order (products then sums left to right), which the native kernel
(src/native/contact.cpp) repeats, so both find the same points bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
import pinocchio as pin

SPECULATIVE_MARGIN = 0.01  # [m] (see scenes/contact.py)
MAX_PATCH_POINTS = 4
# Kept points of a pair with a mesh hull are at least this far apart along the contact plane [m]: a hull's facet or
# rounded end within the margin gives dozens of vertices millimetres apart, nearly equal rows.
MIN_PATCH_SPACING = 0.01
PRIMITIVE_SPACING = 1e-4  # [m] the same for other pairs, whose features are distinct by construction
PATCH_DEPTH = 1e-3  # [m] a patch's points are within this of its deepest one
FLAT_DISK = 1e-9  # a cylinder's axis within this (squared sine) of vertical: its disks lie flat
# The pair kinds computed here (others: coal)
SPHERE_GROUND, BOX_GROUND, CYLINDER_GROUND, CAPSULE_GROUND, MESH_GROUND = 0, 1, 2, 3, 4
SPHERE_SPHERE, SPHERE_BOX, BOX_SPHERE, BOX_BOX, COAL = 5, 6, 7, 8, 9
# Box–box: an edge axis, or box 2's face, is the contact's axis only when its separation exceeds box 1's best face's
# by this [m] (exact ties, as a box resting flat on another, keep box 1's face; near-ties do not flip each step)
AXIS_TOLERANCE = 1e-6
PARALLEL_EDGES = 1e-12  # box–box: edges whose cross product's squared length is below this make no axis


@dataclass(frozen=True)
class Candidate:
    """One point of a pair within the margin.

    Attributes:
        feature: the shape feature's index (corner, vertex, rim point; a coal patch's point index).
        point1, point2: the closest points on shape 1 and shape 2, world [m], shape (3,) each.
        gap: signed distance along the normal [m] (negative: penetration).
    """

    feature: int
    point1: np.ndarray
    point2: np.ndarray
    gap: float


def pair_kind(kind1: str, kind2: str) -> int:
    """How a pair of shape kinds is computed: one of the closed forms above, or COAL."""
    if kind1 == "halfspace":
        return {
            "sphere": SPHERE_GROUND,
            "box": BOX_GROUND,
            "cylinder": CYLINDER_GROUND,
            "capsule": CAPSULE_GROUND,
            "mesh": MESH_GROUND,
        }.get(kind2, COAL)
    if kind1 == "sphere" and kind2 == "sphere":
        return SPHERE_SPHERE
    if kind1 == "sphere" and kind2 == "box":
        return SPHERE_BOX
    if kind1 == "box" and kind2 == "sphere":
        return BOX_SPHERE
    if kind1 == "box" and kind2 == "box":
        return BOX_BOX
    return COAL


def bounding_radius(kind: str, dimensions: tuple[float, ...], vertices: np.ndarray | None) -> tuple[np.ndarray, float]:
    """(centre in the shape's frame, radius) of a sphere holding the shape [m]; the half-space: radius inf."""
    if kind == "sphere":
        return np.zeros(3), float(dimensions[0])
    if kind == "box":
        a, b, c = (0.5 * float(x) for x in dimensions)
        return np.zeros(3), float(np.sqrt((a * a + b * b) + c * c))
    if kind == "cylinder":
        r, half = float(dimensions[0]), 0.5 * float(dimensions[1])
        return np.zeros(3), float(np.sqrt(r * r + half * half))
    if kind == "capsule":
        return np.zeros(3), float(dimensions[0]) + 0.5 * float(dimensions[1])
    if kind == "mesh" and vertices is not None and len(vertices):
        centre = 0.5 * (vertices.min(axis=0) + vertices.max(axis=0))
        d = vertices - centre
        return centre, float(np.sqrt(((d[:, 0] * d[:, 0] + d[:, 1] * d[:, 1]) + d[:, 2] * d[:, 2]).max()))
    return np.zeros(3), float("inf")


def transform(R: np.ndarray, t: np.ndarray, local: np.ndarray) -> np.ndarray:
    """R local + t for points local (n, 3) -> (n, 3), each coordinate's products summed left to right."""
    x, y, z = local[:, 0], local[:, 1], local[:, 2]
    out = np.empty_like(local)
    for r in range(3):
        out[:, r] = ((R[r, 0] * x + R[r, 1] * y) + R[r, 2] * z) + t[r]
    return out


def _ground(points2: np.ndarray, height: float, features: np.ndarray, drop: float = 0.0) -> list[Candidate]:
    """Candidates of lowest points (n, 3) (already lowered by their radius `drop`, if any) against z ≥ height."""
    gaps = points2[:, 2] - height
    out = []
    for k in np.flatnonzero(gaps < SPECULATIVE_MARGIN).tolist():
        p2 = points2[k]
        out.append(Candidate(int(features[k]), np.array([p2[0], p2[1], height]), p2.copy(), float(gaps[k])))
    return out


BOX_CORNERS = np.array([[sx, sy, sz] for sz in (-1.0, 1.0) for sy in (-1.0, 1.0) for sx in (-1.0, 1.0)])


def ground_candidates(kind: int, height: float, R: np.ndarray, t: np.ndarray, shape: Any) -> list[Candidate]:
    """The candidates of a shape (world pose R, t; `shape` its ShapeData) against the ground z ≥ height."""
    dims = shape.dimensions
    if kind == SPHERE_GROUND:
        low = np.array([[t[0], t[1], t[2] - dims[0]]])
        return _ground(low, height, np.zeros(1, dtype=int))
    if kind == BOX_GROUND:
        half = 0.5 * np.asarray(dims, dtype=float)
        return _ground(transform(R, t, BOX_CORNERS * half), height, np.arange(8))
    if kind == CAPSULE_GROUND:
        r, half = dims[0], 0.5 * dims[1]
        ends = transform(R, t, np.array([[0.0, 0.0, half], [0.0, 0.0, -half]]))
        ends[:, 2] = ends[:, 2] - r
        return _ground(ends, height, np.arange(2))
    if kind == CYLINDER_GROUND:
        return _ground(cylinder_rims(R, t, dims[0], 0.5 * dims[1]), height, np.arange(8))
    # MESH_GROUND: only the z of every vertex first, then the candidates' points in full
    V = shape.vertices
    z = ((R[2, 0] * V[:, 0] + R[2, 1] * V[:, 1]) + R[2, 2] * V[:, 2]) + t[2]
    near = np.flatnonzero(z - height < SPECULATIVE_MARGIN)
    return _ground(transform(R, t, V[near]), height, near)


def cylinder_rims(R: np.ndarray, t: np.ndarray, radius: float, half: float) -> np.ndarray:
    """The 8 rim points (4 per end disk, +z end first) of a cylinder at (R, t): +u, -u, +w, -w from each disk's
    centre, u the disk's steepest way down (its own x axis when the disk lies flat) and w = axis × u."""
    a = R[:, 2]
    px, py, pz = a[2] * a[0], a[2] * a[1], a[2] * a[2] - 1.0  # -e_z minus its part along the axis
    norm2 = (px * px + py * py) + pz * pz
    if norm2 <= FLAT_DISK:
        u = R[:, 0].copy()
        w = R[:, 1].copy()
    else:
        norm = np.sqrt(norm2)
        u = np.array([px / norm, py / norm, pz / norm])
        w = np.array([a[1] * u[2] - a[2] * u[1], a[2] * u[0] - a[0] * u[2], a[0] * u[1] - a[1] * u[0]])
    out = np.empty((8, 3))
    for end, sign in enumerate((1.0, -1.0)):
        centre = t + (sign * half) * a
        for k, (d, s) in enumerate(((u, 1.0), (u, -1.0), (w, 1.0), (w, -1.0))):
            out[4 * end + k] = centre + (s * radius) * d
    return out


def sphere_sphere(c1: np.ndarray, r1: float, c2: np.ndarray, r2: float) -> tuple[list[Candidate], np.ndarray]:
    """The closest points of two spheres along the line of centres, and the normal from 1 to 2."""
    d = c2 - c1
    dist = float(np.sqrt((d[0] * d[0] + d[1] * d[1]) + d[2] * d[2]))
    normal = d / dist if dist > 0.0 else np.array([0.0, 0.0, 1.0])
    gap = (dist - r1) - r2
    if gap >= SPECULATIVE_MARGIN:
        return [], normal
    return [Candidate(0, c1 + r1 * normal, c2 - r2 * normal, gap)], normal


def sphere_box(c: np.ndarray, r: float, R: np.ndarray, t: np.ndarray, half: np.ndarray) -> tuple[list[Candidate], np.ndarray]:
    """The closest points of a sphere (centre c, radius r) and a box (pose R, t; half extents): (candidates with
    point1 on the box, point2 on the sphere, normal from the box to the sphere)."""
    d = c - t
    local = np.array([(R[0, i] * d[0] + R[1, i] * d[1]) + R[2, i] * d[2] for i in range(3)])  # Rᵀ (c - t)
    clamped = local.copy()
    for i in range(3):
        x = -half[i] if local[i] < -half[i] else local[i]
        clamped[i] = half[i] if x > half[i] else x
    if (clamped == local).all():  # the centre inside the box: out through the nearest face
        depths = [half[i] - abs(local[i]) for i in range(3)]
        axis = int(np.argmin(depths))
        sign = 1.0 if local[axis] >= 0.0 else -1.0
        n_local = np.zeros(3)
        n_local[axis] = sign
        surface = local.copy()
        surface[axis] = sign * half[axis]
        gap = -depths[axis] - r
    else:
        diff = local - clamped
        dist = float(np.sqrt((diff[0] * diff[0] + diff[1] * diff[1]) + diff[2] * diff[2]))
        n_local = diff / dist
        surface = clamped
        gap = dist - r
    normal = np.array([(R[i, 0] * n_local[0] + R[i, 1] * n_local[1]) + R[i, 2] * n_local[2] for i in range(3)])
    if gap >= SPECULATIVE_MARGIN:
        return [], normal
    on_box = transform(R, t, surface[None, :])[0]
    return [Candidate(0, on_box, c - r * normal, float(gap))], normal


def _dot(u: Any, v: Any) -> float:
    return (u[0] * v[0] + u[1] * v[1]) + u[2] * v[2]


def _separation(d: list[float], a: list[np.ndarray], half1: Any, b: list[np.ndarray], half2: Any, n: Any) -> float:
    """The boxes' separation along the unit axis n [m]: |n·d| minus both boxes' half widths along n."""
    r1 = (half1[0] * abs(_dot(a[0], n)) + half1[1] * abs(_dot(a[1], n))) + half1[2] * abs(_dot(a[2], n))
    r2 = (half2[0] * abs(_dot(b[0], n)) + half2[1] * abs(_dot(b[1], n))) + half2[2] * abs(_dot(b[2], n))
    return abs(_dot(d, n)) - (r1 + r2)


def _face_axis(
    d: list[float], a: list[np.ndarray], half1: Any, b: list[np.ndarray], half2: Any, faces: list[np.ndarray]
) -> tuple[float, int]:
    """Of one box's face normals `faces` (a or b), the largest separation [m] and its axis (the first on a tie)."""
    best, axis = -np.inf, 0
    for i in range(3):
        sep = _separation(d, a, half1, b, half2, faces[i])
        if sep > best:
            best, axis = sep, i
    return best, axis


# Box–box features: a face contact's point is ((reference face, incident face) code) * FACE_POINTS + 8 * (label of
# the polygon edge into it) + (label of the edge out of it), labels 0..3 the incident face's edges, 4..7 the
# reference face's sides; an edge contact's is EDGE_FEATURES + 12 * (edge of box 1) + (edge of box 2), an edge
# 4 * axis + 2 * (sign of the next axis > 0) + (sign of the last axis > 0).
FACE_POINTS = 64
EDGE_FEATURES = 72 * FACE_POINTS


def box_box(
    R1: np.ndarray, t1: np.ndarray, half1: Any, R2: np.ndarray, t2: np.ndarray, half2: Any
) -> tuple[list[Candidate], np.ndarray]:
    """The candidates of two boxes (poses R, t; half extents [m]) and the normal from box 1 to box 2 (module
    docstring): the separating axis of largest separation (box 1's faces first, then box 2's, then the edge pairs,
    each replacing the best so far only by more than AXIS_TOLERANCE), then its contact points."""
    d = [t2[0] - t1[0], t2[1] - t1[1], t2[2] - t1[2]]
    a = [R1[:, i] for i in range(3)]
    b = [R2[:, j] for j in range(3)]
    best, axis = _face_axis(d, a, half1, b, half2, a)
    best2, axis2 = _face_axis(d, a, half1, b, half2, b)
    on2 = best2 > best + AXIS_TOLERANCE
    if on2:
        best, axis = best2, axis2
    edge, edge_best, edge_n = None, -np.inf, None
    for i in range(3):
        for j in range(3):
            u, w = a[i], b[j]
            L = [u[1] * w[2] - u[2] * w[1], u[2] * w[0] - u[0] * w[2], u[0] * w[1] - u[1] * w[0]]
            norm2 = (L[0] * L[0] + L[1] * L[1]) + L[2] * L[2]
            if norm2 < PARALLEL_EDGES:
                continue
            norm = np.sqrt(norm2)
            n = [L[0] / norm, L[1] / norm, L[2] / norm]
            sep = _separation(d, a, half1, b, half2, n)
            if sep > edge_best:
                edge, edge_best, edge_n = (i, j), sep, n
    if edge is not None and edge_best > best + AXIS_TOLERANCE:
        if edge_best >= SPECULATIVE_MARGIN:
            return [], np.array([0.0, 0.0, 1.0])
        return _edge_contact(R1, t1, half1, R2, t2, half2, edge, edge_n, d, edge_best)
    if best >= SPECULATIVE_MARGIN:
        return [], np.array([0.0, 0.0, 1.0])
    if on2:  # box 2's face is the reference, its outward normal towards box 1
        sign = -1.0 if _dot(d, b[axis]) >= 0.0 else 1.0
        found, outward = _face_contact(R2, t2, half2, axis, sign, R1, t1, half1, 1)
        found = [Candidate(c.feature, c.point2, c.point1, c.gap) for c in found]
        return found, np.array([-outward[0], -outward[1], -outward[2]])
    sign = 1.0 if _dot(d, a[axis]) >= 0.0 else -1.0
    return _face_contact(R1, t1, half1, axis, sign, R2, t2, half2, 0)


def _face_contact(
    Rr: np.ndarray, tr: np.ndarray, hr: Any, axis: int, sign: float, Ri: np.ndarray, ti: np.ndarray, hi: Any, ref: int
) -> tuple[list[Candidate], np.ndarray]:
    """The reference box's (Rr, tr, half extents hr) face at local coordinate axis = sign * hr[axis] against the
    incident box's face most opposed to it, clipped to it: (candidates with point1 on the reference box, point2 on
    the incident one, the reference face's outward normal); `ref` (0 or 1: box 1 or 2 is the reference) enters the
    features only."""
    outward = np.array([sign * Rr[0, axis], sign * Rr[1, axis], sign * Rr[2, axis]])
    dots = [_dot(Ri[:, j], outward) for j in range(3)]
    j = 0
    for k in (1, 2):  # the first of the largest |dot|
        if abs(dots[k]) > abs(dots[j]):
            j = k
    s = -1.0 if dots[j] >= 0.0 else 1.0
    ju, jv = (j + 1) % 3, (j + 2) % 3
    polygon = []  # (point in the reference box's frame, label of the polygon edge from it to the next)
    for label, (cu, cv) in enumerate(((1.0, 1.0), (-1.0, 1.0), (-1.0, -1.0), (1.0, -1.0))):
        corner = np.empty(3)
        corner[j], corner[ju], corner[jv] = s * hi[j], cu * hi[ju], cv * hi[jv]
        world = transform(Ri, ti, corner[None, :])[0]
        w = [world[0] - tr[0], world[1] - tr[1], world[2] - tr[2]]
        polygon.append(([(Rr[0, r] * w[0] + Rr[1, r] * w[1]) + Rr[2, r] * w[2] for r in range(3)], label))
    for side, (p, sigma) in enumerate((((axis + 1) % 3, 1.0), ((axis + 1) % 3, -1.0), ((axis + 2) % 3, 1.0),
                                       ((axis + 2) % 3, -1.0))):  # fmt: skip
        polygon = _clip(polygon, p, sigma, hr[p], 4 + side)
    code = ((6 * ref + 2 * axis + (sign < 0.0)) * 6 + 2 * j + (s < 0.0)) * FACE_POINTS
    out = []
    for k, (X, label) in enumerate(polygon):
        gap = sign * X[axis] - hr[axis]
        if gap >= SPECULATIVE_MARGIN:
            continue
        on_face = list(X)
        on_face[axis] = sign * hr[axis]
        points = transform(Rr, tr, np.array([on_face, X]))
        out.append(Candidate(int(code + 8 * polygon[k - 1][1] + label), points[0], points[1], float(gap)))
    return out, outward


def _clip(polygon: list, p: int, sigma: float, h: float, label: int) -> list:
    """Sutherland–Hodgman: the part of a convex polygon [(point, label of its edge to the next)] where
    sigma * x[p] <= h; the new edge along that side labelled `label`."""
    out = []
    n = len(polygon)
    for k in range(n):
        P, edge = polygon[k]
        Q = polygon[(k + 1) % n][0]
        fP, fQ = sigma * P[p] - h, sigma * Q[p] - h
        if fP <= 0.0:
            out.append((P, edge))
        if (fP <= 0.0) != (fQ <= 0.0):
            t = fP / (fP - fQ)
            X = [P[r] + t * (Q[r] - P[r]) for r in range(3)]
            X[p] = sigma * h
            out.append((X, label if fP <= 0.0 else edge))
    return out


def _edge_contact(
    R1: np.ndarray, t1: np.ndarray, half1: Any, R2: np.ndarray, t2: np.ndarray, half2: Any,
    edge: tuple[int, int], n: list[float], d: list[float], gap: float,
) -> tuple[list[Candidate], np.ndarray]:  # fmt: skip
    """The closest points of box 1's edge along its axis i farthest along n and box 2's along its axis j farthest
    against n (n oriented from box 1 to box 2), each clamped to its edge: one candidate, its gap the separation."""
    i, j = edge
    if _dot(d, n) < 0.0:
        n = [-n[0], -n[1], -n[2]]
    local1, local2 = np.zeros(3), np.zeros(3)
    id1, id2 = 4 * i, 4 * j
    for k, bit in (((i + 1) % 3, 2), ((i + 2) % 3, 1)):
        up = _dot(R1[:, k], n) > 0.0
        local1[k] = half1[k] if up else -half1[k]
        id1 += bit if up else 0
    for k, bit in (((j + 1) % 3, 2), ((j + 2) % 3, 1)):
        up = _dot(R2[:, k], n) <= 0.0
        local2[k] = half2[k] if up else -half2[k]
        id2 += bit if up else 0
    pA = transform(R1, t1, local1[None, :])[0]
    pB = transform(R2, t2, local2[None, :])[0]
    u, w = R1[:, i], R2[:, j]
    r = [pB[0] - pA[0], pB[1] - pA[1], pB[2] - pA[2]]
    c = _dot(u, w)
    ur, wr = _dot(u, r), _dot(w, r)
    denom = 1.0 - c * c
    s1 = (ur - c * wr) / denom
    s2 = (c * ur - wr) / denom
    local1[i] = min(max(s1, -half1[i]), half1[i])
    local2[j] = min(max(s2, -half2[j]), half2[j])
    p1 = transform(R1, t1, local1[None, :])[0]
    p2 = transform(R2, t2, local2[None, :])[0]
    return [Candidate(EDGE_FEATURES + 12 * id1 + id2, p1, p2, float(gap))], np.array(n)


def coal_candidates(gm: Any, gd: Any, k: int) -> tuple[list[Candidate], np.ndarray]:
    """Pair k's points from coal's contact patch (its normal from shape 1 to shape 2), or none."""
    if not pin.computeCollision(gm, gd, k):
        return [], np.zeros(3)
    pin.computeContactPatch(gm, gd, k)
    patches = gd.contactPatchResults[k]
    if patches.numContactPatches() == 0:
        return [], np.zeros(3)
    patch = patches.getContactPatch(0)
    normal = np.array(patch.getNormal(), dtype=float)
    out = []
    for i in range(patch.size()):
        p1 = np.array(patch.getPointShape1(i), dtype=float)
        p2 = np.array(patch.getPointShape2(i), dtype=float)
        d = p2 - p1
        gap = (normal[0] * d[0] + normal[1] * d[1]) + normal[2] * d[2]
        out.append(Candidate(i, p1, p2, float(gap)))
    return out, normal


def select(candidates: list[Candidate], normal: np.ndarray, spacing: float) -> list[Candidate]:
    """At most MAX_PATCH_POINTS well-spread candidates (module docstring), none closer than `spacing` [m] along the
    plane normal to `normal`, in the candidates' order."""
    if len(candidates) <= 1:
        return candidates
    deepest = min(c.gap for c in candidates)
    candidates = [c for c in candidates if c.gap <= deepest + PATCH_DEPTH]
    gaps = [c.gap for c in candidates]
    first = int(np.argmin(gaps))
    points = np.array([0.5 * (c.point1 + c.point2) for c in candidates])
    chosen = [first]
    nearest = _plane_distance2(points, points[first], normal)
    nearest[first] = -1.0  # (never again)
    spacing2 = spacing * spacing
    while len(chosen) < MAX_PATCH_POINTS:
        best = int(np.argmax(nearest))
        if not nearest[best] >= spacing2:
            break
        chosen.append(best)
        nearest = np.minimum(nearest, _plane_distance2(points, points[best], normal))
        nearest[best] = -1.0
    return [candidates[k] for k in sorted(chosen)]


def _plane_distance2(points: np.ndarray, p: np.ndarray, n: np.ndarray) -> np.ndarray:
    """Squared distances from p to each point (n, 3) along the plane normal to n."""
    d0, d1, d2 = points[:, 0] - p[0], points[:, 1] - p[1], points[:, 2] - p[2]
    along = (n[0] * d0 + n[1] * d1) + n[2] * d2
    return ((d0 * d0 + d1 * d1) + d2 * d2) - along * along
