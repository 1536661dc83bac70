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
- sphere–sphere, sphere–box: the closest points, along the line between them.

Every other pair (box–box, hulls between themselves, cylinders against boxes, ...) goes to coal (Pinocchio's
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
SPHERE_SPHERE, SPHERE_BOX, BOX_SPHERE, COAL = 5, 6, 7, 8


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
