"""The contact step's parts against independent computations: the closed-form narrow phase against coal's distances,
the Jacobian and Delassus matrix against Pinocchio's constraint models and ConstraintCholeskyDecomposition, and the
cone solver's impulses against Coulomb's law checked condition by condition (and Pinocchio's ADMM)."""

from __future__ import annotations

import coal
import numpy as np
import pinocchio as pin
import pytest

import multibody_sim as ms
from multibody_sim.integrators import cone_solver as cs
from multibody_sim.scenes import make_scene
from multibody_sim.scenes import narrow_phase as narrow

RNG = np.random.default_rng(7)


def random_rotation() -> np.ndarray:
    q = RNG.normal(size=4)
    return pin.Quaternion(*(q / np.linalg.norm(q))).matrix()


def coal_distance(shape_a, pose_a: pin.SE3, shape_b, pose_b: pin.SE3) -> float:
    """coal's signed distance between two shapes (negative: penetration depth)."""
    request, result = coal.DistanceRequest(), coal.DistanceResult()
    request.enable_signed_distance = True
    coal.distance(shape_a, coal.Transform3s(pose_a.rotation, pose_a.translation), shape_b,
                  coal.Transform3s(pose_b.rotation, pose_b.translation), request, result)  # fmt: skip
    return float(result.min_distance)


class Shape:
    def __init__(self, kind: str, dims: tuple[float, ...], vertices: np.ndarray | None = None):
        self.dimensions, self.vertices, self.kind = dims, vertices, kind


@pytest.mark.parametrize(
    "kind, dims, shape",
    [
        ("sphere", (0.05,), coal.Sphere(0.05)),
        ("box", (0.2, 0.1, 0.06), coal.Box(0.2, 0.1, 0.06)),
        ("cylinder", (0.04, 0.3), coal.Cylinder(0.04, 0.3)),
        ("capsule", (0.03, 0.2), coal.Capsule(0.03, 0.2)),
    ],
)
def test_the_deepest_ground_point_of_a_primitive_is_coals_distance_to_the_plane(kind, dims, shape):
    """For random poses within the margin of the plane z = 0.01: the closed form's deepest candidate has coal's
    signed distance to the half-space, and lies on the shape's surface (its distance to the shape is 0). A
    cylinder's rim points are exact at the disk's lowest point only, which is the deepest of a tilted cylinder."""
    height = 0.01
    plane = coal.Halfspace(np.array([0.0, 0.0, 1.0]), height)
    pair = {"sphere": narrow.SPHERE_GROUND, "box": narrow.BOX_GROUND, "cylinder": narrow.CYLINDER_GROUND,
            "capsule": narrow.CAPSULE_GROUND}[kind]  # fmt: skip
    checked = 0
    for _ in range(200):
        R = random_rotation()
        lowest = narrow.ground_candidates(pair, 1e9, R, np.zeros(3), Shape(kind, dims))  # every feature: all below
        low = min(c.point2[2] for c in lowest)
        t = np.array([RNG.uniform(-1, 1), RNG.uniform(-1, 1), height - low + RNG.uniform(-0.004, 0.009)])
        found = narrow.ground_candidates(pair, height, R, t, Shape(kind, dims))
        expected = coal_distance(plane, pin.SE3.Identity(), shape, pin.SE3(R, t))
        if not found:
            assert expected >= narrow.SPECULATIVE_MARGIN - 1e-12
            continue
        deepest = min(found, key=lambda c: c.gap)
        assert deepest.gap == pytest.approx(expected, abs=1e-12)
        point_on = coal_distance(coal.Sphere(1e-9), pin.SE3(np.eye(3), deepest.point2), shape, pin.SE3(R, t))
        assert abs(point_on) < 1e-8  # on the surface (a tiny sphere there touches the shape)
        checked += 1
    assert checked > 100


def test_sphere_pairs_are_coals_distances():
    """sphere–sphere and sphere–box (the centre outside and inside the box): the gap is coal's signed distance and
    the normal points from shape 1 to shape 2."""
    for _ in range(200):
        c1, c2 = RNG.uniform(-0.1, 0.1, 3), RNG.uniform(-0.1, 0.1, 3)
        r1, r2 = RNG.uniform(0.01, 0.08, 2)
        found, normal = narrow.sphere_sphere(c1, r1, c2, r2)
        expected = coal_distance(coal.Sphere(r1), pin.SE3(np.eye(3), c1), coal.Sphere(r2), pin.SE3(np.eye(3), c2))
        if found:
            assert found[0].gap == pytest.approx(expected, abs=1e-12)
            np.testing.assert_allclose(normal, (c2 - c1) / np.linalg.norm(c2 - c1), atol=1e-14)
        half = RNG.uniform(0.02, 0.1, 3)
        R, t, r = random_rotation(), RNG.uniform(-0.05, 0.05, 3), RNG.uniform(0.005, 0.05)
        found, normal = narrow.sphere_box(c1, r, R, t, half)
        expected = coal_distance(coal.Box(*(2 * half)), pin.SE3(R, t), coal.Sphere(r), pin.SE3(np.eye(3), c1))
        if found:
            assert found[0].gap == pytest.approx(expected, abs=1e-9)
            np.testing.assert_allclose(found[0].point2, c1 - r * normal, atol=1e-14)


def pinocchio_problem(scene, q: np.ndarray):
    """J and G of the scene's contact points at q from Pinocchio's frame Jacobians (each body's velocity at its own
    contact point, world axes, turned into the contact frame) and a dense M⁻¹ (LAPACK)."""
    model, data = scene.model, scene.model.createData()
    pin.computeJointJacobians(model, data, q)
    rows = []
    for p in scene.contact.detect(q):
        relative = np.zeros((3, model.nv))
        for joint, point, sign in ((p.joint2, p.point2, 1.0), (p.joint1, p.point1, -1.0)):
            if joint:
                placement = data.oMi[joint].actInv(pin.SE3(np.eye(3), point))
                jac = pin.getFrameJacobian(model, data, joint, placement, pin.LOCAL_WORLD_ALIGNED)[:3]
                relative += sign * jac
        rows.append(p.rotation.T @ relative)
    J = np.vstack(rows)
    M = pin.crba(model, data, q)
    M = np.triu(M) + np.triu(M, 1).T
    return J, J @ np.linalg.solve(M, J.T)


@pytest.mark.parametrize("name", ["solo12_standing", "box_stack", "talos_standing"])
def test_the_jacobian_and_delassus_matrix_are_pinocchios(name):
    """The rows from the CRBA's joint Jacobians and G = Zᵀ D⁻¹ Z (Z = U⁻¹ Jᵀ on the supports) equal Pinocchio's
    frame Jacobians at the contact points and J M⁻¹ Jᵀ (dense, LAPACK) to round-off."""
    scene = ms.load_scene(name)
    q = scene.q0.copy()
    if scene.contact.robot_file and scene.nq > 7:
        q[2] -= 1e-4  # touching
    problem = scene.contact.problem(q, scene.v0, scene.v0, 1e-3)
    J, G = pinocchio_problem(scene, q)
    n = 3 * len(problem.points)
    assert n > 0
    np.testing.assert_allclose(problem.jacobian[:n], J, atol=1e-12)
    np.testing.assert_allclose(problem.delassus[:n, :n], G, rtol=1e-10, atol=1e-10 * np.abs(G).max())


def random_problem(rows_per_body: int, mu: float = 0.6):
    """A contact problem of a free box on points of its bottom face (redundant when more than 2 points), given an
    approach velocity: G, g and the blocks of K."""
    scene = make_scene(ground={"friction": mu}, object=[{"name": "b", "shape": "box", "size": [0.3, 0.2, 0.1],
                       "mass": 2.0, "position": [0.0, 0.0, 0.0499]}])  # fmt: skip
    q = scene.q0.copy()
    R = pin.rpy.rpyToMatrix(*RNG.uniform(-0.05, 0.05, 3))
    q[3:7] = pin.Quaternion(R).coeffs()
    v = np.concatenate([RNG.uniform(-1, 1, 3) * [1, 1, 0.5], RNG.uniform(-2, 2, 3)])
    return scene.contact.problem(q, v, v, 1e-3)


def test_the_solver_satisfies_coulombs_law_condition_by_condition():
    """Random landings of a box on its corners (redundant rows): each solution is in the cones, no contact
    approaches, open contacts carry nothing, sticking contacts do not slip, sliding ones push on the cone's edge
    against their slip; and the post-step velocities equal Pinocchio's ADMM's on the same G and g."""
    solved = 0
    for _ in range(40):
        p = random_problem(4)
        if p is None or not p.points:
            continue
        sol = cs.solve(p.delassus, p.g, p.blocks, np.zeros(len(p.g)), p.velocity_scale, 200)
        assert sol.converged and not sol.fallback
        lam, u = sol.impulses, p.delassus @ sol.impulses + p.g
        tol = 1e-8 * p.velocity_scale
        for c in range(len(p.points)):
            (t1, t2, n), (v1, v2, vn) = lam[3 * c : 3 * c + 3], u[3 * c : 3 * c + 3]
            mu = p.blocks.mu[c]
            assert n >= 0.0 and np.hypot(t1, t2) <= mu * n * (1 + 1e-12) + 1e-15
            assert vn >= -tol  # no approach
            assert abs(n * vn) <= tol * max(n, 1e-30)  # complementarity
            slip = np.hypot(v1, v2)
            if n > 1e-12 and slip > tol:  # sliding: on the edge, against the slip
                np.testing.assert_allclose([t1, t2], -mu * n * np.array([v1, v2]) / slip, rtol=1e-6, atol=1e-12)
        solved += 1
    assert solved > 20
