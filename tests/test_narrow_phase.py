"""The closed-form box–box narrow phase (scenes/narrow_phase.box_box) against independent answers: a box resting on a
box and crossed edges against hand closed forms, random poses against coal's GJK/EPA, the box stack's statics, and
the native kernel's rendering bit for bit on boxes tumbling onto boxes (every path: box 1's face, box 2's face, two
edges)."""

from __future__ import annotations


import coal
import numpy as np
import pinocchio as pin
import pytest
from conftest import assert_same_run, both, contact_steps, needs_native

import multibody_sim as ms
from multibody_sim.integrators.cone_solver import TOLERANCE
from multibody_sim.scenes import make_scene
from multibody_sim.scenes import narrow_phase as narrow

I3 = np.eye(3)
G = 9.81


def corners(R: np.ndarray, t: np.ndarray, half: np.ndarray) -> np.ndarray:
    return np.array([t + R @ (s * half) for s in narrow.BOX_CORNERS])


def test_a_box_resting_on_a_box_touches_at_its_four_lower_corners_along_z():
    """A 0.2 m box centred on a 0.3 m one: the normal is exactly +z (box 1's top face), the points are the upper
    box's four lower corners with their projections on the lower box's top, the gaps zero to round-off."""
    half1, half2 = np.array([0.15, 0.15, 0.05]), np.array([0.1, 0.1, 0.05])
    t1, t2 = np.array([0.0, 0.0, 0.05]), np.array([0.0, 0.0, 0.15])
    found, normal = narrow.box_box(I3, t1, half1, I3, t2, half2)
    assert normal.tolist() == [0.0, 0.0, 1.0]
    lower = corners(I3, t2, half2)[:4]  # z = -1 corners
    assert len(found) == 4
    assert sorted(map(tuple, np.array([c.point2 for c in found]).round(15))) == sorted(map(tuple, lower.round(15)))
    for c in found:
        assert abs(c.gap) < 1e-15
        np.testing.assert_array_equal(c.point1[:2], c.point2[:2])
        assert c.point1[2] == 0.1
    assert len({c.feature for c in found}) == 4
    # Upside down (box 2 below box 1): the same contact seen from the other side, the normal exactly -z.
    found, normal = narrow.box_box(I3, t2, half2, I3, t1, half1)
    assert normal.tolist() == [0.0, 0.0, -1.0] and len(found) == 4
    # Lifted by 5 mm: the same points, speculative (gap 5 mm < the margin); by 1 cm: none.
    found, _ = narrow.box_box(I3, t1, half1, I3, t2 + [0.0, 0.0, 0.005], half2)
    assert len(found) == 4 and all(c.gap == pytest.approx(0.005, abs=1e-15) for c in found)
    assert narrow.box_box(I3, t1, half1, I3, t2 + [0.0, 0.0, 1.01 * narrow.SPECULATIVE_MARGIN], half2)[0] == []


def test_a_box_overhanging_another_is_clipped_to_its_top_face():
    """The upper box shifted and turned by 30° about z, half over the edge: the patch is the upper box's bottom face
    clipped to the lower box's top face: within both faces, of the area of the two squares' intersection, the lower
    box's corner under the upper box's centre among its corners."""
    half = np.array([0.1, 0.1, 0.05])
    R2 = pin.utils.rotate("z", np.pi / 6)
    t2 = np.array([0.1, 0.1, 0.1])
    found, normal = narrow.box_box(I3, np.zeros(3), half, R2, t2, half)
    assert normal.tolist() == [0.0, 0.0, 1.0]
    points = np.array([c.point1 for c in found])
    np.testing.assert_allclose(points[:, 2], 0.05, atol=1e-15)
    assert (np.abs(points[:, :2]) <= 0.1 + 1e-15).all()  # within the lower box's top face
    local = (points - t2) @ R2  # within the upper box's bottom face
    assert (np.abs(local[:, :2]) <= 0.1 + 1e-12).all()
    # The polygon's area: the intersection of the two squares, from an independent clip (shapely is not a
    # dependency: a fine grid count instead).
    area = _polygon_area(_convex_order(points[:, :2]))
    grid = np.linspace(-0.1, 0.1, 801)
    X, Y = np.meshgrid(grid, grid)
    inside = (np.abs((np.stack([X, Y], -1) - t2[:2]) @ R2[:2, :2]) <= 0.1).all(-1)
    assert area == pytest.approx(inside.mean() * 0.04, rel=5e-3)
    assert np.abs(points - [0.1, 0.1, 0.05]).max(axis=1).min() < 1e-15  # the lower box's corner


def _convex_order(p: np.ndarray) -> np.ndarray:
    c = p.mean(0)
    return p[np.argsort(np.arctan2(p[:, 1] - c[1], p[:, 0] - c[0]))]


def _polygon_area(p: np.ndarray) -> float:
    x, y = p[:, 0], p[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1))))


@pytest.mark.parametrize("gap", [-2e-3, 0.0, 4e-3])
def test_crossed_edges_touch_at_one_point_where_they_cross(gap):
    """A ridge (a box turned 45° about y: its top is an edge along y) under a valley (turned 45° about x: its bottom
    is an edge along x), offset in x and y: one point at the crossing (x of the ridge, y of the valley), normal +z,
    its gap the heights' difference (hand closed form)."""
    h1, h2 = np.array([0.05, 0.15, 0.05]), np.array([0.15, 0.04, 0.04])
    R1, R2 = pin.utils.rotate("y", np.pi / 4), pin.utils.rotate("x", np.pi / 4)
    top = 0.05 * np.sqrt(2.0)  # the ridge's edge above its centre
    bottom = 0.04 * np.sqrt(2.0)  # the valley's edge below its centre
    t1, t2 = np.array([0.01, -0.02, 0.1]), np.array([-0.03, 0.02, 0.1 + top + bottom + gap])
    found, normal = narrow.box_box(R1, t1, h1, R2, t2, h2)
    assert len(found) == 1 and found[0].feature >= narrow.EDGE_FEATURES
    np.testing.assert_allclose(normal, [0.0, 0.0, 1.0], atol=1e-15)
    c = found[0]
    assert c.gap == pytest.approx(gap, abs=1e-15)
    np.testing.assert_allclose(c.point1, [0.01, 0.02, 0.1 + top], atol=1e-14)
    np.testing.assert_allclose(c.point2, [0.01, 0.02, 0.1 + top + gap], atol=1e-14)


def test_a_tilted_box_on_its_corner_meets_box_two_face():
    """A cube balanced on a corner above a slab listed after it: the slab's top face is the reference (box 2's),
    the normal from the cube to the slab exactly -z, one point at the cube's lowest corner."""
    half1, half2 = np.full(3, 0.05), np.array([0.3, 0.3, 0.05])
    R1 = pin.utils.rotate("x", np.pi / 4) @ pin.utils.rotate("y", np.arctan(1 / np.sqrt(2.0)))
    low = corners(R1, np.zeros(3), half1)[:, 2].min()
    t1 = np.array([0.02, 0.03, 0.1 - low - 1e-3])  # the lowest corner 1 mm into the slab's top at z = 0.1
    found, normal = narrow.box_box(R1, t1, half1, I3, np.array([0.0, 0.0, 0.05]), half2)
    assert normal.tolist() == [0.0, 0.0, -1.0]
    lowest = corners(R1, t1, half1)[np.argmin(corners(R1, t1, half1)[:, 2])]
    assert len(found) == 1
    np.testing.assert_allclose(found[0].point1, lowest, atol=1e-15)
    np.testing.assert_allclose(found[0].point2, [lowest[0], lowest[1], 0.1], atol=1e-15)
    assert found[0].gap == pytest.approx(-1e-3, abs=1e-15)


def _random_pose_pair(rng: np.random.Generator, separation: float):
    """Two random boxes, box 2 moved from box 1 along a random direction until their separation along the best
    of the 15 axes (computed here by bisection with numpy's cross products) is `separation`."""
    h1, h2 = rng.uniform(0.02, 0.2, 3), rng.uniform(0.02, 0.2, 3)
    R1, R2 = pin.exp3(rng.normal(size=3)), pin.exp3(rng.normal(size=3))
    t1 = 0.1 * rng.normal(size=3)
    u = rng.normal(size=3)
    u /= np.linalg.norm(u)
    axes = [*R1.T, *R2.T, *(np.cross(a, b) for a in R1.T for b in R2.T)]
    axes = [L / np.linalg.norm(L) for L in axes if np.linalg.norm(L) > 1e-6]

    def sat(s: float) -> float:
        d = s * u
        return max(abs(d @ L) - (h1 @ np.abs(R1.T @ L) + h2 @ np.abs(R2.T @ L)) for L in axes)

    lo, hi = 0.0, 2.0
    for _ in range(60):
        lo, hi = ((lo + hi) / 2, hi) if sat((lo + hi) / 2) < separation else (lo, (lo + hi) / 2)
    return R1, t1, h1, R2, t1 + lo * u, h2


def test_penetrating_random_poses_agree_with_coal():
    """300 random oriented boxes overlapping by up to 2 cm: the deepest point's gap is coal's (EPA) signed distance
    and the normal coal's, to coal's tolerance; the points lie on the boxes' surfaces."""
    rng = np.random.default_rng(7)
    kinds = set()
    for _ in range(300):
        R1, t1, h1, R2, t2, h2 = _random_pose_pair(rng, rng.uniform(-0.02, -1e-4))
        found, normal = narrow.box_box(R1, t1, h1, R2, t2, h2)
        kinds.add(found[0].feature >= narrow.EDGE_FEATURES)
        request, result = coal.CollisionRequest(), coal.CollisionResult()
        request.enable_contact = True
        box1, box2 = coal.Box(*(2 * h1)), coal.Box(*(2 * h2))
        assert coal.collide(box1, coal.Transform3s(R1, t1), box2, coal.Transform3s(R2, t2), request, result)
        contact = result.getContact(0)
        assert min(c.gap for c in found) == pytest.approx(contact.penetration_depth, abs=1e-9)
        np.testing.assert_allclose(normal, np.array(contact.normal), atol=1e-9)
        for c in found:
            for R, t, h, p in ((R1, t1, h1, c.point1), (R2, t2, h2, c.point2)):
                local = R.T @ (p - t)
                assert (np.abs(local) <= h + 1e-12).all() and (np.abs(np.abs(local) - h) < 1e-12).any()
    assert kinds == {False, True}  # both face and edge contacts were drawn


def test_separated_random_poses_are_never_reported_farther_than_coal_says_unless_true():
    """Separated by up to the margin: a face contact's points are real point pairs (gap = |p2 - p1| along the
    normal, hence >= coal's distance); an edge contact's gap is the separation along its axis, a lower bound of
    the distance (<= coal's); the smallest of them is coal's distance when coal's normal is the same axis."""
    rng = np.random.default_rng(11)
    same = 0
    for _ in range(300):
        R1, t1, h1, R2, t2, h2 = _random_pose_pair(rng, rng.uniform(1e-4, 0.9 * narrow.SPECULATIVE_MARGIN))
        found, normal = narrow.box_box(R1, t1, h1, R2, t2, h2)
        request, result = coal.DistanceRequest(), coal.DistanceResult()
        box1, box2 = coal.Box(*(2 * h1)), coal.Box(*(2 * h2))
        distance = coal.distance(box1, coal.Transform3s(R1, t1), box2, coal.Transform3s(R2, t2), request, result)
        for c in found:
            if c.feature >= narrow.EDGE_FEATURES:
                assert c.gap <= distance + 1e-9
            else:
                np.testing.assert_allclose(c.point2 - c.point1, c.gap * normal, atol=1e-12)
                assert c.gap >= distance - 1e-9
        if found and np.abs(np.array(result.normal) - normal).max() < 1e-6:
            same += 1
            assert min(c.gap for c in found) == pytest.approx(distance, abs=1e-9)
    assert same > 200


def test_the_stack_rests_on_exactly_vertical_normals_each_box_carrying_what_is_above():
    """box_stack at rest for 20 steps: every normal ±z to round-off (a box's face normal, its rotation off identity
    by ~1e-20 after a few steps of integration), and on each box the normal impulses from below
    minus those from above are its weight × dt to the solver's tolerance (statics: a box's momentum may change by
    TOLERANCE of g dt on either side of a step; the split among a patch's corners is free, the sums are fixed)."""
    scene = ms.load_scene("box_stack")
    dt = 1e-3
    mass = {o.name: o.mass for o in scene.spec.objects}
    for problem, impulses, v in contact_steps(scene, 20, dt):
        net = dict.fromkeys(mass, 0.0)
        for c, point in enumerate(problem.points):
            np.testing.assert_allclose(np.abs(point.normal), [0.0, 0.0, 1.0], rtol=0.0, atol=1e-15)  # the faces' own
            up = impulses[3 * c + 2] * point.normal[2]  # on body 2, upwards
            below, above = point.bodies
            if above in net:
                net[above] += up
            if below in net:
                net[below] -= up
        for name, m in mass.items():
            assert net[name] == pytest.approx(m * G * dt, rel=2 * TOLERANCE), name
    assert np.abs(v).max() < 1e-12


def tumbling_boxes() -> ms.Scene:
    """A cube falling corner first onto a slab listed after it (box 2's face), a ridge lying on an edge on the slab
    (box 1's face) and a valley crossing it above (two edges)."""
    cube = {"name": "cube", "shape": "box", "size": [0.08, 0.08, 0.08], "mass": 0.3, "position": [0.2, 0.15, 0.2],
            "rpy": [0.5, 0.4, 0.3]}  # fmt: skip
    slab = {"name": "slab", "shape": "box", "size": [0.6, 0.6, 0.1], "mass": 5.0, "position": [0.0, 0.0, 0.05]}
    ridge = {"name": "ridge", "shape": "box", "size": [0.1, 0.3, 0.1], "mass": 1.0, "position": [0.0, 0.0, 0.1707],
             "rpy": [0.0, np.pi / 4, 0.0]}  # fmt: skip
    valley = {"name": "valley", "shape": "box", "size": [0.3, 0.1, 0.1], "mass": 0.5, "position": [0.01, 0.02, 0.32],
              "rpy": [np.pi / 4, 0.0, 0.0]}  # fmt: skip
    contact = {"pairs": "all", "body_friction": 0.5}
    return make_scene(ground={"friction": 0.6}, contact=contact, object=[cube, slab, ridge, valley])


@needs_native
def test_boxes_tumbling_onto_boxes_run_natively_bit_for_bit(monkeypatch):
    scene = tumbling_boxes()
    run = lambda: ms.simulate(  # noqa: E731
        scene, scene.q0, scene.v0, duration=0.4, dt=1e-3, integrator="timestepping", progress=False
    )
    native_run, python_run = both(run, monkeypatch)
    assert native_run.metadata["kernel"] == "native" and python_run.metadata["kernel"] != "native"
    assert_same_run(native_run, python_run, ("steps", "solver_steps", "solver_unconverged", "solver_iterations"))
    for part in ("sample", "pair", "point", "normal", "impulse"):
        np.testing.assert_array_equal(getattr(native_run.contacts, part), getattr(python_run.contacts, part))
    seen = set()  # which of box_box's paths the run went through
    for q in python_run.q:
        for point in scene.contact.detect(q):
            pair, feature = point.key
            if scene.contact.pair_kinds[pair] == narrow.BOX_BOX:
                reference = 2 if feature // narrow.FACE_POINTS >= 36 else 1
                seen.add("edges" if feature >= narrow.EDGE_FEATURES else f"face of box {reference}")
    assert seen == {"edges", "face of box 1", "face of box 2"}
    ledger = python_run.ledger
    assert np.diff(ledger["contact"].energy).min() >= 0.0
