"""Contact: collision geometry, the pairs that may touch, and the unilateral constraints of one time step.

A scene with contact keeps its collision shapes (coal shapes: the ground's half-space, the objects' shapes and the
robot's collision geometry) and, at each step of the `timestepping` integrator, turns the pairs within the
speculative margin into constraint rows (narrow_phase.py finds the points): a Coulomb cone per contact point (3
rows: two tangential, then the normal), a row per position limit near its bound (``limits = "enforce"``), a row
per joint with dry friction (``friction = "exact"``) and a row per actuator velocity limit near its bound
(``velocity_limits = "enforce"``, see below). The problem handed to the cone solver (integrators/
cone_solver.py) is Coulomb's law on

    u = G λ + g,    G = J M⁻¹ Jᵀ (the Delassus matrix),   g = J v_free + b,

with λ the constraint impulses [N·s, N·m·s] and b the velocity bias of each row (see :class:`ContactProblem`).

One CRBA and Pinocchio's tree-sparse Cholesky M = U D Uᵀ serve the step: contact rows are the frame Jacobians of
the contact points (from the CRBA's joint Jacobians), limit and friction rows select a coordinate, and
G = Zᵀ D⁻¹ Z with Z = U⁻¹ Jᵀ, each column of Z nonzero only on the coordinates that support its row (the chains
from the root to the bodies). Every sum is formed in index order from +0.0 (cone_solver.zsum), as the native
kernel (src/native/contact.cpp) forms it, which may skip the structural zeros.

Contact frames and signs. A contact point ties point 1 on the first shape of a pair (the ground for ground
pairs) to point 2 on the second; its frame's z axis is the patch normal, pointing from shape 1 to shape 2. J's
rows give point 2's velocity relative to point 1 in that frame, so a positive normal velocity separates, and λ is
the impulse on body 2 (body 1 feels the opposite).

Bias b (normal rows only; documented choices, each booked in the energy ledger):

- Speculative contact: a gap d > 0 within SPECULATIVE_MARGIN enters as d / dt, so the constraint
  ``u⁺ + d/dt ≥ 0`` lets the bodies close the gap within the step and no further.
- Penetration correction: a penetration (d < 0) enters as ``PENETRATION_CORRECTION · min(d + s, 0) / dt``: a
  fifth of the penetration beyond the slop s = PENETRATION_SLOP (1 nm, above coal's own round-off) is pushed out
  per step (Baumgarte's stabilization at the velocity level), at most MAX_CORRECTION_SPEED (1 m/s) so that a deep
  penetration comes out over several steps. The energy this puts in is the ledger's
  ``penetration_correction`` (kind "work"): ``-λᵀ b_corr ≥ 0``.
- Restitution (Newton's law), in two steps so that the bounce starts at the surface: a pair with coefficient
  e > 0 whose gap closes within the step (its speculative row is active) lands exactly on the surface at the
  step's end, and its approach speed u⁻ (the normal velocity at the step's start) is remembered in the solver
  state; on the next step, touching (gap below TOUCHING), it gets ``e u⁻`` as its bias: ``u⁺ ≥ -e u⁻``. A pair
  that starts a step touching and approaching (no landing remembered) bounces on its own u⁻. Approaches slower
  than the speed one step of free fall gives (|g| dt) never bounce, so resting contacts stay at rest. Bouncing
  one step after landing delays the bounce by at most a step but starts it from the surface, so apex heights
  are not biased by the gap at which the step found the pair. The energy a bounce gives back is the ledger's
  ``restitution`` (kind "work"): ``-λᵀ b_rest ≥ 0``; the landing took it out (in ``contact``) the step before.

Velocity limits (the actuators' velocity limits as constraints, as PhysX's maximum joint velocity): every joint
whose actuator has an overspeed brake (scenes/actuators.py) gets, in a step where its speed may reach its limit
v_max, a row ``v⁺_j ≤ v_max`` (upper: J = −e_j, b = v_max, so u = v_max − v⁺_j ≥ 0) or ``v⁺_j ≥ −v_max`` (lower: J =
+e_j), its impulse λ ≥ 0 complementary to u: the joint ends the step at most at its limit whatever the impulses of
the contacts do to it (an impact back-driving a leg). A selection row like a limit's: its Delassus entries are
entries of M⁻¹. A row joins the problem when the joint's free velocity is within SPEED_BAND of its limit; after
the solve, a joint that the other impulses carried past its limit gets its row and the problem is solved again
(warm-started), until no joint is past its limit (speeding()): a step far from the limits costs one comparison per
joint. Rows come last, after the friction rows, in the order they joined. The work of a row's impulse,
``½ λ J (v⁺ + v_free)`` (≤ 0 when it holds a joint at its limit), is booked as dissipated in its actuator's
``actuator_overspeed:<joint>`` line (the motor holding the speed), not in ``contact``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import coal
import numpy as np
import pinocchio as pin

from ..exceptions import SceneError
from ..integrators.cone_solver import CONE, HALFLINE, INTERVAL, NEWTON_ITERATIONS, Blocks, matvec, zsum
from ..ordered import ordered_matvec
from ..text import name_hint, safe_name
from . import narrow_phase as narrow
from .frames import frame_id
from .narrow_phase import MAX_PATCH_POINTS, MIN_PATCH_SPACING, PRIMITIVE_SPACING, SPECULATIVE_MARGIN

PENETRATION_CORRECTION = 0.2  # the fraction of a penetration pushed out per step
# Penetrations below this are left alone [m]: coal's box–plane distance is off by ~5e-12 m, and pushing that out
# would jitter resting stacks at 1e-9 m/s.
PENETRATION_SLOP = 1e-9
# The correction never pushes faster than this [m/s or rad/s]: a deep penetration (a body placed inside another)
# comes out over several steps instead of being shot out at depth/dt.
MAX_CORRECTION_SPEED = 1.0
# Position limits within this distance of q [rad or m] join the step's problem (speculatively): a joint faster than
# LIMIT_MARGIN / dt (50 rad/s at 1 ms) may end a step past its limit, which the correction then undoes.
LIMIT_MARGIN = 0.05
# A velocity-limit row joins a step's problem when the joint's free velocity is beyond (1 - SPEED_BAND) v_max.
SPEED_BAND = 0.02
TOUCHING = 1e-6  # [m]: a gap below this is a touching contact (restitution applies)
_WORLD = pin.Convention.WORLD
# The shape kinds the native kernel renders (src/native/contact.hpp's ShapeKind); others stay on the Python kernel.
NATIVE_SHAPES = ("halfspace", "box", "sphere", "cylinder", "capsule", "mesh")
_Z = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class Geometry:
    """One collision shape on one body.

    Attributes:
        body: the body's name ("ground", an object's name, or the frame a [[contact.geometry]] names).
        joint: the joint the body moves with (0: the world).
        placement: the shape's pose in that joint's frame.
        shape: the coal shape.
        kind: "halfspace", "box", "sphere", "cylinder" or "mesh" (a URDF mesh's convex hull, a coal.ConvexBase).
        dimensions: box: full extents (3,) [m]; sphere: (radius,); cylinder: (radius, length); halfspace: (height,);
            mesh: ().
        from_urdf: the shape is the URDF's collision geometry (robot_geometry = "urdf"), not declared by the scene.
    """

    body: str
    joint: int
    placement: pin.SE3
    shape: Any
    kind: str
    dimensions: tuple[float, ...]
    from_urdf: bool = False


@dataclass(frozen=True)
class ContactPoint:
    """One contact point at the start of a step.

    Attributes:
        key: (pair index, feature index): what the warm start is keyed on (narrow_phase.py's features).
        bodies: (body 1, body 2) names.
        joint1, joint2: the joints the bodies move with.
        point1, point2: the closest points on body 1 and body 2, world [m], shape (3,) each.
        rotation: the contact frame in world axes, its z the normal, shape (3, 3).
        position: the point midway between the shapes, world [m], shape (3,).
        normal: unit normal from shape 1 to shape 2, world, shape (3,).
        gap: signed distance along the normal [m] (negative: penetration).
        friction: Coulomb μ.
        restitution: Newton's e.
    """

    key: tuple[int, int]
    bodies: tuple[str, str]
    joint1: int
    joint2: int
    point1: np.ndarray
    point2: np.ndarray
    rotation: np.ndarray
    position: np.ndarray
    normal: np.ndarray
    gap: float
    friction: float
    restitution: float


@dataclass
class ContactProblem:
    """The constraint problem of one step (see the module docstring).

    Attributes:
        points: the contact points, in row order (3 rows each, the normal last).
        keys: one warm-start key per block: ("point", pair, feature), ("limit", joint, side), ("friction", joint),
            ("speed", joint, side) (side 0: the lower bound, 1: the upper).
        sizes: rows of each block.
        blocks: the blocks of the cone solver's set K.
        jacobian: J, shape (m, nv).
        delassus: G = J M⁻¹ Jᵀ, shape (m, m).
        g: J v_free + b, shape (m,).
        correction: b's penetration-correction part, ≤ 0, shape (m,).
        restitution: b's restitution part, ≤ 0, shape (m,).
        velocity_scale: the largest free constraint velocity |J v_free|, at least |g| h [m/s, rad/s].
        landings: pair index -> approach speed u⁻ (< 0) of the pairs that land this step (restitution).
        limit_rows, friction_rows: rows of the joint-limit and joint-friction blocks.
        speeds: the velocity-limit rows, last, in order: (sign, v index, joint, v_max, ledger line, side) each.
    """

    points: list[ContactPoint]
    keys: list[tuple[Any, ...]]
    sizes: list[int]
    blocks: Blocks
    jacobian: np.ndarray
    delassus: np.ndarray
    g: np.ndarray
    correction: np.ndarray
    restitution: np.ndarray
    velocity_scale: float
    landings: dict[int, float] = field(default_factory=dict)
    limit_rows: int = 0
    friction_rows: int = 0
    speeds: list[tuple[float, int, int, float, int, int]] = field(default_factory=list)


@dataclass(frozen=True)
class ShapeData:
    """What the narrow phase reads of a shape: its kind, dimensions, hull vertices (mesh: (n, 3) in the shape's
    frame) and bounding sphere (centre in the shape's frame, radius [m])."""

    kind: str
    dimensions: tuple[float, ...]
    vertices: np.ndarray | None
    centre: np.ndarray
    radius: float


def _penetration_correction(gap: float, dt: float) -> float:
    """The penetration-correction bias b_corr ≤ 0 [m/s or rad/s] of a gap [m or rad] over a step dt [s]: the
    fraction PENETRATION_CORRECTION of the penetration beyond PENETRATION_SLOP per step, at most
    MAX_CORRECTION_SPEED (0 for a gap ≥ -PENETRATION_SLOP)."""
    return max(PENETRATION_CORRECTION * min(gap + PENETRATION_SLOP, 0.0) / dt, -MAX_CORRECTION_SPEED)


def make_shape(kind: str, dimensions: Sequence[float]) -> Any:
    """The coal shape of a declared shape: box (full extents x, y, z), sphere (radius), cylinder (radius, length)."""
    if kind == "box":
        return coal.Box(*map(float, dimensions))
    if kind == "sphere":
        return coal.Sphere(float(dimensions[0]))
    if kind == "cylinder":
        return coal.Cylinder(float(dimensions[0]), float(dimensions[1]))
    raise ValueError(f"unknown shape {kind!r}")


def shape_inertia(kind: str, dimensions: Sequence[float], mass: float) -> pin.Inertia:
    """The inertia of a uniform solid about its centre: box, sphere, cylinder (axis z)."""
    if kind == "box":
        return pin.Inertia.FromBox(mass, *map(float, dimensions))
    if kind == "sphere":
        return pin.Inertia.FromSphere(mass, float(dimensions[0]))
    return pin.Inertia.FromCylinder(mass, float(dimensions[0]), float(dimensions[1]))


class ContactModel:
    """A scene's collision geometry and unilateral constraints, on the scene's Pinocchio model.

    Args:
        model: the scene's model (objects included); a private Data is kept.
        geometries: every collision shape (the ground first when there is one).
        pairs: index pairs into `geometries` that may touch (the ground, when in a pair, first).
        ground_friction, ground_restitution: μ and e of pairs with the ground.
        body_friction, body_restitution: μ and e of other pairs.
        solver: "admm" or "pgs".
        limits: "enforce" or "report".
        friction: "exact" or "regularized" (joint dry friction).
        limited_joints: joint ids whose position limits are enforced (limits = "enforce").
        friction_joints: (joint id, F [N·m or N]) of joints with exact dry friction.
        speed_limits: (joint id, v_max [rad/s or m/s], ledger line) of joints whose velocity limit is a constraint
            (the line: the index of its actuator_overspeed line in the scene's ledger).
        has_robot: the scene has a robot (describe() then says whether it has collision geometry).
        robot_geometry_note: why the robot has no collision geometry, if it has none (for describe()).
        robot_file: "URDF" or "MJCF": the file the robot's collision geometry comes from (for describe()).
    """

    def __init__(
        self,
        model: pin.Model,
        geometries: Sequence[Geometry],
        pairs: Sequence[tuple[int, int]],
        *,
        ground_friction: float,
        ground_restitution: float,
        body_friction: float,
        body_restitution: float,
        solver: str = "admm",
        limits: str = "report",
        friction: str = "regularized",
        limited_joints: Sequence[int] = (),
        friction_joints: Sequence[tuple[int, float]] = (),
        speed_limits: Sequence[tuple[int, float, int]] = (),
        has_robot: bool = False,
        robot_geometry_note: str = "",
        robot_file: str = "URDF",
    ):
        self.model = model
        self.data = model.createData()
        self.geometries = list(geometries)
        self.pairs = list(pairs)
        self.solver = solver
        self.limits = limits
        self.friction = friction
        self.gravity = float(np.linalg.norm(model.gravity.linear))
        gm = pin.GeometryModel()
        for k, geometry in enumerate(self.geometries):
            gm.addGeometryObject(
                pin.GeometryObject(
                    f"{geometry.body}:{k}", geometry.joint, geometry.joint, geometry.placement, geometry.shape
                )
            )
        for first, second in self.pairs:
            gm.addCollisionPair(pin.CollisionPair(first, second))
        self.geometry_model = gm
        self.geometry_data = pin.GeometryData(gm)
        for request in self.geometry_data.collisionRequests:
            request.enable_contact = True  # without it box–box normals are NaN
            request.security_margin = SPECULATIVE_MARGIN
        self._ground_coefficients = (ground_friction, ground_restitution)
        self.has_robot = has_robot
        self.robot_geometry_note = robot_geometry_note
        self.robot_file = robot_file
        self._body_index = {name: k for k, name in enumerate(self.body_names)}
        self._object_names = {g.body for g in self.geometries if g.joint and model.names[g.joint] == g.body}
        self._coefficients = [
            (ground_friction, ground_restitution)
            if "ground" in (self.geometries[a].body, self.geometries[b].body)
            else (body_friction, body_restitution)
            for a, b in self.pairs
        ]
        self.limited_joints = list(limited_joints)
        self.friction_joints = list(friction_joints)
        self.speed_limits = [(int(j), float(vmax), int(line)) for j, vmax, line in speed_limits]
        self._speeds = [(jid, model.joints[jid].idx_v, vmax, line) for jid, vmax, line in self.speed_limits]
        self.shapes = [_shape_data(g) for g in self.geometries]
        self.pair_kinds = [narrow.pair_kind(self.geometries[a].kind, self.geometries[b].kind) for a, b in self.pairs]
        # the dofs supporting each joint (its own and its ancestors'), ascending: where its Jacobian can be nonzero
        self.supports = [np.zeros(0, dtype=int)]
        for jid in range(1, model.njoints):
            dofs = [
                model.joints[j].idx_v + k for j in model.supports[jid] if j > 0 for k in range(model.joints[j].nv)
            ]
            self.supports.append(np.array(sorted(dofs), dtype=int))
        self._limits = [
            (jid, model.joints[jid].idx_q, model.joints[jid].idx_v) for jid in self.limited_joints
        ]  # (joint, q index, v index)

    # ---- what it models ----------------------------------------------------------------------------
    @property
    def empty(self) -> bool:
        """No pair, no enforced limit, no exact friction, no velocity limit: nothing to solve, ever."""
        return not self.pairs and not self.limited_joints and not self.friction_joints and not self.speed_limits

    @property
    def body_names(self) -> list[str]:
        """Every body with collision geometry, in the order Trajectory.contacts indexes them."""
        return list(dict.fromkeys(g.body for g in self.geometries))

    def native_data(self) -> dict[str, Any]:
        """The geometry, constraints and constants (this module's and narrow_phase.py's) as the native kernel takes
        them (_native.ContactScene's fields, shapes as _native.ContactShape's; the time-stepper adds its solver's
        settings: kernels/native.contact_data)."""
        model = self.model
        force = np.zeros(model.nv)
        for jid, f in self.friction_joints:
            force[model.joints[jid].idx_v] = f
        shapes = []
        for g, data in zip(self.geometries, self.shapes, strict=True):
            archive = b""
            if g.kind == "mesh":  # coal's own archive of the hull, for the pairs coal computes
                buffer = pin.serialization.StreamBuffer()
                g.shape.saveToBuffer(buffer)
                archive = bytes(buffer.tobytes())
            shapes.append(
                {
                    "kind": g.kind,
                    "joint": int(g.joint),
                    "body": self._body_index[g.body],
                    "rotation": np.array(g.placement.rotation, dtype=float),
                    "translation": np.array(g.placement.translation, dtype=float),
                    "dimensions": [float(x) for x in g.dimensions],
                    "vertices": data.vertices if data.vertices is not None else np.zeros((0, 3)),
                    "archive": np.frombuffer(archive, dtype=np.uint8).copy(),
                    "centre": np.array(data.centre, dtype=float),
                    "radius": float(data.radius),
                }
            )
        return {
            "shapes": shapes,
            "pairs": [(int(a), int(b)) for a, b in self.pairs],
            "friction": [float(mu) for mu, _ in self._coefficients],
            "restitution": [float(e) for _, e in self._coefficients],
            "limited_joints": [int(j) for j in self.limited_joints],
            "friction_joints": [int(j) for j, _ in self.friction_joints],
            "friction_force": force,
            "speed_joints": [j for j, _, _ in self.speed_limits],
            "speed_limits": [vmax for _, vmax, _ in self.speed_limits],
            "speed_lines": [line for _, _, line in self.speed_limits],
            "constants": {
                "speculative_margin": SPECULATIVE_MARGIN,
                "penetration_correction": PENETRATION_CORRECTION,
                "penetration_slop": PENETRATION_SLOP,
                "max_correction_speed": MAX_CORRECTION_SPEED,
                "touching": TOUCHING,
                "limit_margin": LIMIT_MARGIN,
                "speed_band": SPEED_BAND,
                "max_patch_points": MAX_PATCH_POINTS,
                "min_patch_spacing": MIN_PATCH_SPACING,
                "primitive_spacing": PRIMITIVE_SPACING,
                "patch_depth": narrow.PATCH_DEPTH,
                "flat_disk": narrow.FLAT_DISK,
                "axis_tolerance": narrow.AXIS_TOLERANCE,
                "parallel_edges": narrow.PARALLEL_EDGES,
                "pgs": self.solver == "pgs",
                "gravity": self.gravity,
            },
        }

    def records(self, problem: ContactProblem, impulses: np.ndarray) -> np.ndarray | None:
        """The contact points of a solved problem as (k, 11) rows: pair (2 indices into body_names), point (3),
        normal (3), impulse on body 2 in world axes (3) [N·s]; None without points."""
        points = problem.points
        if not points:
            return None
        index = self._body_index
        rows = np.empty((len(points), 11))
        for c, point in enumerate(points):
            rotation = point.rotation
            rows[c, 0], rows[c, 1] = index[point.bodies[0]], index[point.bodies[1]]
            rows[c, 2:5] = point.position
            rows[c, 5:8] = point.normal
            rows[c, 8:11] = ordered_matvec(rotation, impulses[3 * c : 3 * c + 3])
        return rows

    def pair_names(self) -> list[tuple[str, str]]:
        """The body pairs that may touch (one per pair of bodies, in order)."""
        seen: list[tuple[str, str]] = []
        for a, b in self.pairs:
            names = (self.geometries[a].body, self.geometries[b].body)
            if names not in seen:
                seen.append(names)
        return seen

    def describe(self) -> list[str]:
        """What the contact models, a few lines for describe() and the run header."""
        lines = []
        ground = [g for g in self.geometries if g.body == "ground"]
        if ground:
            mu, e = self._ground_coefficients
            lines.append(f"  ground: plane z = {ground[0].dimensions[0]:g} m, friction {mu:g}, restitution {e:g}")
        else:
            lines.append("  ground: none")
        robot = [g for g in self.geometries if g.joint and g.body not in self._object_names]
        declared = sorted({g.body for g in robot if not g.from_urdf})
        urdf = [g for g in robot if g.from_urdf]
        if declared:
            lines.append("  robot collision geometry (declared): " + ", ".join(map(safe_name, declared)))
        if urdf:
            meshes = sum(g.kind == "mesh" for g in urdf)
            links = len({g.body for g in urdf})
            lines.append(
                f"  robot collision geometry (the {self.robot_file}'s): {len(urdf)} shapes on {links} links, "
                f"{meshes} of them meshes as their convex hulls (at most {MAX_PATCH_POINTS} contact points per pair)"
                + (" where none is declared" if declared else "")
            )
        if not robot and self.has_robot:
            lines.append(
                f"  robot collision geometry: none ({self.robot_geometry_note}): the robot passes through "
                'everything; declare [[contact.geometry]] (spheres on feet, boxes on soles) or robot_geometry = "urdf"'
            )
        pairs = self.pair_names()
        shown = ", ".join(f"{safe_name(a)}-{safe_name(b)}" for a, b in pairs[:12]) + (
            f" (+{len(pairs) - 12} more)" if len(pairs) > 12 else ""
        )
        lines.append(f"  contact pairs: {shown if pairs else 'none'}")
        solver = (
            f"semismooth Newton, ADMM after {NEWTON_ITERATIONS} Newton iterations" if self.solver == "admm"
            else "Gauss-Seidel sweeps, semismooth Newton between them"
        )
        lines.append(
            f"  contact solver: {solver}, velocity-level time-stepping (exact Coulomb cones, speculative margin "
            f"{SPECULATIVE_MARGIN:g} m, penetration correction {PENETRATION_CORRECTION:g} per step)"
        )
        limits = (
            f"enforced as unilateral constraints ({len(self.limited_joints)} joints)"
            if self.limits == "enforce"
            else "reported, not enforced"
        )
        lines.append(f"  position limits: {limits}")
        if self.speed_limits:
            n = len(self.speed_limits)
            lines.append(
                f"  velocity limits: enforced as unilateral constraints on {n} joint{'s' if n != 1 else ''} (their "
                "actuators' overspeed brakes; velocity_limits = \"brake\" leaves the brakes alone)"
            )
        if self.friction == "exact":
            lines.append(f"  joint dry friction: exact (a constraint: stiction), on {len(self.friction_joints)} joints")
        else:
            lines.append("  joint dry friction: regularized (tanh), if any")
        return lines

    # ---- one step ----------------------------------------------------------------------------------
    def detect(self, q: np.ndarray) -> list[ContactPoint]:
        """The contact points at q: of every pair whose bounding spheres come within SPECULATIVE_MARGIN, the
        points narrow_phase.py keeps.

        Runs the kinematics of q in the contact's own Data (``updateGeometryPlacements``).
        """
        model, data, gm, gd = self.model, self.data, self.geometry_model, self.geometry_data
        if not self.pairs:
            return []
        pin.updateGeometryPlacements(model, data, gm, gd, q)
        poses = [(np.array(p.rotation), np.array(p.translation)) for p in gd.oMg]
        points: list[ContactPoint] = []
        for k, ((a, b), kind) in enumerate(zip(self.pairs, self.pair_kinds, strict=True)):
            found, normal = self._pair_candidates(k, a, b, kind, poses)
            if not found:
                continue
            g1, g2 = self.geometries[a], self.geometries[b]
            spacing = MIN_PATCH_SPACING if "mesh" in (g1.kind, g2.kind) else PRIMITIVE_SPACING
            rotation = pin.Quaternion.FromTwoVectors(_Z, normal).matrix()
            friction, restitution = self._coefficients[k]
            for c in narrow.select(found, normal, spacing):
                points.append(
                    ContactPoint(
                        key=(k, c.feature),
                        bodies=(g1.body, g2.body),
                        joint1=g1.joint,
                        joint2=g2.joint,
                        point1=c.point1,
                        point2=c.point2,
                        rotation=rotation,
                        position=0.5 * (c.point1 + c.point2),
                        normal=normal,
                        gap=c.gap,
                        friction=friction,
                        restitution=restitution,
                    )
                )
        return points

    def _pair_candidates(
        self, k: int, a: int, b: int, kind: int, poses: list[tuple[np.ndarray, np.ndarray]]
    ) -> tuple[list[narrow.Candidate], np.ndarray]:
        """Pair k's candidates and normal (narrow_phase.py), none when its bounding spheres are apart."""
        s1, s2 = self.shapes[a], self.shapes[b]
        (R1, t1), (R2, t2) = poses[a], poses[b]
        c2 = narrow.transform(R2, t2, s2.centre[None, :])[0]
        if s1.kind == "halfspace":
            if (c2[2] - s1.dimensions[0]) - s2.radius >= SPECULATIVE_MARGIN:
                return [], _Z
        else:
            c1 = narrow.transform(R1, t1, s1.centre[None, :])[0]
            d = c2 - c1
            if np.sqrt((d[0] * d[0] + d[1] * d[1]) + d[2] * d[2]) - (s1.radius + s2.radius) >= SPECULATIVE_MARGIN:
                return [], _Z
        if kind <= narrow.MESH_GROUND:
            return narrow.ground_candidates(kind, s1.dimensions[0], R2, t2, s2), _Z
        if kind == narrow.SPHERE_SPHERE:
            return narrow.sphere_sphere(t1, s1.dimensions[0], t2, s2.dimensions[0])
        if kind == narrow.SPHERE_BOX:
            found, normal = narrow.sphere_box(t1, s1.dimensions[0], R2, t2, 0.5 * np.asarray(s2.dimensions))
            return [narrow.Candidate(c.feature, c.point2, c.point1, c.gap) for c in found], -normal
        if kind == narrow.BOX_SPHERE:
            return narrow.sphere_box(t2, s2.dimensions[0], R1, t1, 0.5 * np.asarray(s1.dimensions))
        if kind == narrow.BOX_BOX:
            return narrow.box_box(R1, t1, 0.5 * np.asarray(s1.dimensions), R2, t2, 0.5 * np.asarray(s2.dimensions))
        return narrow.coal_candidates(self.geometry_model, self.geometry_data, k)

    def problem(
        self,
        q: np.ndarray,
        v: np.ndarray,
        v_free: np.ndarray,
        dt: float,
        landed: dict[int, float] | None = None,
        previous: ContactProblem | None = None,
        added: Sequence[tuple[float, int, int, float, int, int]] = (),
    ) -> ContactProblem | None:
        """The constraint problem of a step from (q, v) whose unconstrained end velocity is v_free, or None when
        nothing is in contact, near a limit (of position, or of velocity within SPEED_BAND) or under exact friction.

        Args:
            q: configuration at the step's start, shape (nq,).
            v: velocity at the step's start, shape (nv,) (restitution reads the approach speed from it).
            v_free: v + dt · a(q, v, tau): the end velocity without constraint impulses, shape (nv,).
            dt: the step [s].
            landed: pair index -> approach speed of the pairs that landed on the previous step (restitution).
            previous, added: the same step's problem solved already, and the velocity-limit rows to add to it
                (speeding()): its points, limits and speed rows are kept, these appended.
        """
        model, data = self.model, self.data
        points = self.detect(q) if previous is None else previous.points
        keys: list[tuple[Any, ...]] = [("point", *point.key) for point in points]
        sizes = [3] * len(points)
        # (sign, v index, joint, distance) of each limit within LIMIT_MARGIN of q: lower bounds push up, upper down
        limits = []
        lower, upper = model.lowerPositionLimit, model.upperPositionLimit
        for jid, iq, iv in self._limits:
            below, above = q[iq] - lower[iq], upper[iq] - q[iq]
            if below < LIMIT_MARGIN:
                limits.append((1.0, iv, jid, float(below)))
                keys.append(("limit", jid, 0))
            if above < LIMIT_MARGIN:
                limits.append((-1.0, iv, jid, float(above)))
                keys.append(("limit", jid, 1))
        keys += [("friction", jid) for jid, _ in self.friction_joints]
        if previous is None:  # the velocity limits the free velocity comes within SPEED_BAND of
            speeds = self.speeding(v_free, band=SPEED_BAND)
        else:
            speeds = [*previous.speeds, *added]
        keys += [("speed", jid, side) for _, _, jid, _, _, side in speeds]
        sizes += [1] * (len(limits) + len(self.friction_joints) + len(speeds))
        if not keys:
            return None
        n_points, nv = len(points), model.nv
        n_speeds = len(speeds)
        m = 3 * n_points + len(limits) + len(self.friction_joints) + n_speeds
        if previous is None:  # (a velocity-limit re-solve is at the same q: its factors and data.J stand)
            pin.crba(model, data, q, _WORLD)  # M (upper triangle) and the joint Jacobians data.J, world frame
            pin.cholesky.decompose(model, data)  # M = U D Uᵀ
        # ---- J, row by row on its support
        J = np.zeros((m, nv))
        joint_jacobians = np.asarray(data.J)
        for c, point in enumerate(points):
            J[3 * c : 3 * c + 3] = self._point_rows(point, joint_jacobians, nv)
        row = 3 * n_points
        for sign, iv, _, _ in limits:
            J[row, iv] = sign
            row += 1
        for jid, _ in self.friction_joints:
            J[row, model.joints[jid].idx_v] = 1.0
            row += 1
        for sign, iv, _, _, _, _ in speeds:
            J[row, iv] = sign
            row += 1
        # ---- G = Zᵀ D⁻¹ Z, Z = U⁻¹ Jᵀ (the tree-sparse back substitution of Pinocchio's cholesky::Uiv)
        U = np.asarray(data.U)
        subtree = data.nvSubtree_fromRow
        Z = J.T.copy()
        for k in range(nv - 2, -1, -1):
            n = subtree[k] - 1
            if n:
                Z[k] = Z[k] - zsum(U[k, k + 1 : k + 1 + n][:, None] * Z[k + 1 : k + 1 + n], axis=0)
        W = (1.0 / np.asarray(data.D))[:, None] * Z
        G = zsum(Z[:, :, None] * W[:, None, :], axis=0)
        lower = np.tril_indices(m, -1)
        G[lower] = G.T[lower]  # exactly symmetric: the upper triangle's sums
        # ---- g = J v_free + b
        free = matvec(J, v_free)
        g = free.copy()
        correction = np.zeros(m)
        restitution = np.zeros(m)
        landings: dict[int, float] = {}
        if points:
            approach = matvec(J[2 : 3 * n_points : 3], v)  # normal velocities at the step's start
            threshold = -self.gravity * dt
            landed = landed or {}
            for c, point in enumerate(points):
                row, pair = 3 * c + 2, point.key[0]
                if point.gap < 0.0:
                    correction[row] = bias = _penetration_correction(point.gap, dt)
                else:
                    bias = point.gap / dt
                if point.restitution > 0.0:
                    if point.gap < TOUCHING:
                        speed = landed.get(pair, approach[c])
                        if speed < threshold:
                            restitution[row] = point.restitution * speed
                            bias = min(bias, 0.0) + restitution[row]
                    elif g[row] + bias < 0.0 and approach[c] < threshold:  # lands within this step
                        landings[pair] = min(landings.get(pair, 0.0), float(approach[c]))
                g[row] += bias
        row = 3 * n_points
        for _, _, _, distance in limits:  # the distance to the limit as a contact's gap
            correction[row] = _penetration_correction(distance, dt)
            g[row] += distance / dt if distance >= 0.0 else correction[row]
            row += 1
        row += len(self.friction_joints)
        for _, _, _, vmax, _, _ in speeds:  # u = v_max ± v⁺ ≥ 0
            g[row] += vmax
            row += 1
        kinds = [CONE] * n_points + [HALFLINE] * len(limits) + [INTERVAL] * len(self.friction_joints)
        kinds += [HALFLINE] * n_speeds
        starts = [3 * c for c in range(n_points)] + list(range(3 * n_points, m))
        params = [p.friction for p in points] + [0.0] * len(limits) + [f * dt for _, f in self.friction_joints]
        params += [0.0] * n_speeds
        blocks = Blocks(np.array(kinds, dtype=int), np.array(starts, dtype=int), np.array(params, dtype=float))
        scale = max(float(np.max(np.abs(free))), self.gravity * dt)
        return ContactProblem(
            points=points,
            keys=keys,
            sizes=sizes,
            blocks=blocks,
            jacobian=J,
            delassus=G,
            g=g,
            correction=correction,
            restitution=restitution,
            velocity_scale=scale,
            landings=landings,
            limit_rows=len(limits),
            friction_rows=len(self.friction_joints),
            speeds=speeds,
        )

    def speeding(
        self, v: np.ndarray, problem: ContactProblem | None = None, band: float = 0.0
    ) -> list[tuple[float, int, int, float, int, int]]:
        """The velocity-limit rows a step needs: (sign, v index, joint, v_max, ledger line, side) of each joint whose
        velocity in v (nv,) is beyond (1 - band) v_max, in joint order, lower side first, but for the rows `problem`
        has already. A step's first selection is its free velocity's within SPEED_BAND; after a solve, the joints
        past their limit at its end velocity (band 0)."""
        present = {(jid, side) for _, _, jid, _, _, side in problem.speeds} if problem is not None else set()
        out = []
        for jid, iv, vmax, line in self._speeds:
            reach = (1.0 - band) * vmax
            if v[iv] < -reach and (jid, 0) not in present:
                out.append((1.0, iv, jid, vmax, line, 0))
            if v[iv] > reach and (jid, 1) not in present:
                out.append((-1.0, iv, jid, vmax, line, 1))
        return out

    def _point_rows(self, point: ContactPoint, jacobians: np.ndarray, nv: int) -> np.ndarray:
        """A contact point's 3 rows of J: the velocity of point 2 relative to point 1 in the contact frame, from the
        joint Jacobians (world frame: linear velocity at the origin, angular), on the bodies' supports."""
        out = np.zeros((3, nv))
        w = np.zeros((3, nv))
        union = np.union1d(self.supports[point.joint1], self.supports[point.joint2])
        for joint, p, sign in ((point.joint2, point.point2, 1.0), (point.joint1, point.point1, -1.0)):
            if not joint:
                continue
            cols = self.supports[joint]
            lin, ang = jacobians[:3, cols], jacobians[3:, cols]
            vel = np.array(
                [
                    lin[0] + (ang[1] * p[2] - ang[2] * p[1]),
                    lin[1] + (ang[2] * p[0] - ang[0] * p[2]),
                    lin[2] + (ang[0] * p[1] - ang[1] * p[0]),
                ]
            )
            if sign > 0.0:
                w[:, cols] = vel
            else:
                w[:, cols] = w[:, cols] - vel
        R, w = point.rotation, w[:, union]
        for r in range(3):
            out[r, union] = (R[0, r] * w[0] + R[1, r] * w[1]) + R[2, r] * w[2]
        return out

    def inverse_mass_times(self, x: np.ndarray) -> np.ndarray:
        """M⁻¹ x at the latest problem's q (its Cholesky factors, in the contact's Data)."""
        return np.array(pin.cholesky.solve(self.model, self.data, x), dtype=float)

    def kinetic_energy(self, v: np.ndarray, raised: np.ndarray | None = None) -> float:
        """T = ½ vᵀ M v [J] at the latest problem's q, from its M (CRBA's upper triangle, armature included): M v
        each row's products in column order from +0.0 (matvec), then vᵀ (M v) in index order (zsum), halved, as the
        native kernel (src/native/contact.cpp, ContactScene::kinetic_energy) forms it. `raised` (nv,): what a
        step's servos added to the armature M was built with (Actuators.raised_armature); each row of M v then has
        raised · v taken off before the sum: T under the model's own armature."""
        M = np.asarray(self.data.M)
        full = np.where(np.triu(np.ones(M.shape, dtype=bool)), M, M.T)
        mass_v = matvec(full, v)
        if raised is not None:
            mass_v = mass_v - raised * v
        return 0.5 * float(zsum(v * mass_v))


def build_contact(
    scene: Any,
    spec: Any,
    exact_friction: Sequence[tuple[int, float]],
    robot_lines: int = 0,
) -> ContactModel:
    """The ContactModel a scene declares: the ground, the objects' shapes, [[contact.geometry]] on the robot, the
    pairs, the limits to enforce, the joints with exact dry friction and the velocity limits to enforce: those of
    every actuator with an overspeed brake unless velocity_limits = "brake", each with its actuator_overspeed
    line's index in the scene's ledger (the actuators' lines follow the robot's `robot_lines`).

    Raises:
        SceneError: an unknown frame or body name (the message lists the valid ones).
    """
    model, where = scene.model, spec.source
    settings = spec.contact
    geometries: list[Geometry] = []
    if spec.ground is not None:
        height = spec.ground.height
        geometries.append(Geometry("ground", 0, pin.SE3.Identity(), coal.Halfspace(_Z, height), "halfspace", (height,)))
    for item in spec.objects:
        dims = item.shape.dimensions
        jid = model.getJointId(item.name)
        geometries.append(
            Geometry(item.name, jid, pin.SE3.Identity(), make_shape(item.shape.shape, dims), item.shape.shape, dims)
        )
    for i, declared in enumerate(settings.geometry if settings is not None else ()):
        fid = frame_id(model, declared.frame, f"{where}: contact.geometry[{i}].frame", moving=True)
        frame = model.frames[fid]
        offset = pin.SE3(pin.rpy.rpyToMatrix(*declared.rpy), np.array(declared.position, dtype=float))
        dims = declared.shape.dimensions
        geometries.append(
            Geometry(
                declared.frame,
                frame.parentJoint,
                frame.placement * offset,
                make_shape(declared.shape.shape, dims),
                declared.shape.shape,
                dims,
            )
        )
    pairs_setting = settings.pairs if settings is not None else "ground"
    choice = settings.effective_robot_geometry if settings is not None else "urdf"
    note = ""
    if spec.robot is not None and choice == "urdf":
        if spec.ground is None and pairs_setting == "ground":
            note = 'nothing to touch: no [ground], and contact.pairs is "ground"'
        else:
            declared_joints = {g.joint for g in geometries if g.joint and model.names[g.joint] != g.body}
            urdf = _urdf_geometries(scene, declared_joints, where)
            geometries += urdf
            note = "the URDF declares no collision geometry on a moving body" if not urdf else ""
    elif spec.robot is not None:
        note = 'robot_geometry = "declared" and no [[contact.geometry]]'
    pairs: list[tuple[int, int]] = []
    ground = [k for k, g in enumerate(geometries) if g.body == "ground"]
    bodies = [k for k, g in enumerate(geometries) if g.body != "ground"]
    if isinstance(pairs_setting, str):
        pairs += [(a, b) for a in ground for b in bodies]
        if pairs_setting == "all":
            for i, a in enumerate(bodies):
                for b in bodies[i + 1 :]:
                    if not _adjacent(model, geometries[a].joint, geometries[b].joint):
                        pairs.append((a, b))
    else:
        names = list(dict.fromkeys(g.body for g in geometries))
        for i, pair in enumerate(pairs_setting):
            for k, name in enumerate(pair):
                if name not in names:
                    none = "valid: none (declare [ground], [[object]] or [[contact.geometry]])"
                    hint = name_hint(name, names) if names else none
                    raise SceneError(f"{where}: contact.pairs[{i}][{k}]: unknown body {safe_name(name)!r} ({hint})")
            first, second = pair if pair[1] != "ground" else (pair[1], pair[0])
            for a in (k for k, g in enumerate(geometries) if g.body == first):
                for b in (k for k, g in enumerate(geometries) if g.body == second):
                    if (a, b) not in pairs and (b, a) not in pairs and geometries[a].joint != geometries[b].joint:
                        pairs.append((a, b))
    limited: list[int] = []
    if settings is not None and settings.limits == "enforce":
        for jid in range(1, model.njoints):
            joint = model.joints[jid]
            if joint.nq == 1 and joint.nv == 1 and np.isfinite(scene.lower_limit[joint.idx_q]):
                limited.append(jid)
    ground_spec = spec.ground
    return ContactModel(
        model,
        geometries,
        pairs,
        ground_friction=ground_spec.friction if ground_spec is not None else 0.0,
        ground_restitution=ground_spec.restitution if ground_spec is not None else 0.0,
        body_friction=settings.body_friction if settings is not None else 0.5,
        body_restitution=settings.body_restitution if settings is not None else 0.0,
        solver=settings.solver if settings is not None else "admm",
        limits=settings.limits if settings is not None else "report",
        friction=settings.friction if settings is not None else "regularized",
        limited_joints=limited,
        friction_joints=exact_friction,
        speed_limits=_speed_limits(scene.actuators, model, robot_lines, settings),
        has_robot=spec.robot is not None,
        robot_geometry_note=note,
        robot_file="MJCF" if scene.source.get("format") == "mjcf" else "URDF",
    )


def _speed_limits(actuators: Any, model: pin.Model, robot_lines: int, settings: Any) -> list[tuple[int, float, int]]:
    """(joint id, v_max, ledger line) of each velocity limit the contact step enforces (build_contact)."""
    if actuators is None or (settings is not None and settings.velocity_limits != "enforce"):
        return []
    names = [name for name, _ in actuators.ledger]
    return [
        (model.getJointId(a.joint), a.velocity_limit, robot_lines + names.index(f"actuator_overspeed:{a.joint}"))
        for a in actuators.items
        if a.overspeed == "brake"
    ]


def _urdf_geometries(scene: Any, skip_joints: set[int], where: str) -> list[Geometry]:
    """The robot's URDF collision geometry on the scene's model, on moving bodies other than `skip_joints`
    (those with declared geometry: it replaces the URDF's on every link that moves with that joint); meshes become
    their convex hulls (coal's ConvexBase: contact patches between hulls and planes; a mesh's own triangles would
    collide through its surface only)."""
    from ..catalog import build_geometry

    if not scene.source.get("urdf_path"):
        return []
    try:
        gm = build_geometry(scene.source, scene.model, "collision")
    except (RuntimeError, ValueError) as exc:  # e.g. a collision mesh that is not there
        first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
        raise SceneError(
            f"{where}: contact: Pinocchio cannot build the robot's collision geometry ({first}); declare "
            '[[contact.geometry]] instead, with robot_geometry = "declared"'
        ) from None
    geometries = []
    for obj in gm.geometryObjects:
        joint = int(obj.parentJoint)
        if joint == 0 or joint in skip_joints:  # welded to the world, or replaced by declared geometry
            continue
        shape, kind, dimensions = _urdf_shape(obj.geometry)
        body = scene.model.frames[obj.parentFrame].name
        geometries.append(Geometry(body, joint, obj.placement, shape, kind, dimensions, from_urdf=True))
    return geometries


def _urdf_shape(shape: Any) -> tuple[Any, str, tuple[float, ...]]:
    """(coal shape, kind, dimensions) of a URDF collision shape: a mesh as its convex hull, primitives as they are."""
    if isinstance(shape, coal.BVHModelBase):
        # The true hull (qhull): buildConvexRepresentation would take the mesh's own triangles as the hull, and an
        # STL's unshared vertices leave coal's support search stuck on a local vertex (a foot sank 28 µm).
        shape.buildConvexHull(True, "Qt")
        return shape.convex, "mesh", ()
    if isinstance(shape, coal.Box):
        return shape, "box", tuple(2.0 * float(h) for h in shape.halfSide)
    if isinstance(shape, coal.Sphere):
        return shape, "sphere", (float(shape.radius),)
    if isinstance(shape, coal.Cylinder):
        return shape, "cylinder", (float(shape.radius), 2.0 * float(shape.halfLength))
    if isinstance(shape, coal.Capsule):
        return shape, "capsule", (float(shape.radius), 2.0 * float(shape.halfLength))
    return shape, type(shape).__name__.lower(), ()


def _shape_data(geometry: Geometry) -> ShapeData:
    """The narrow phase's view of a shape (ShapeData)."""
    vertices = np.array(geometry.shape.points(), dtype=float) if geometry.kind == "mesh" else None
    centre, radius = narrow.bounding_radius(geometry.kind, geometry.dimensions, vertices)
    return ShapeData(geometry.kind, tuple(float(x) for x in geometry.dimensions), vertices, centre, radius)


def _adjacent(model: pin.Model, a: int, b: int) -> bool:
    """Whether two joints move one body, or one is the other's parent (adjacent links never collide)."""
    return a == b or model.parents[a] == b or model.parents[b] == a
