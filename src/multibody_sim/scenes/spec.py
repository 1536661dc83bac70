"""What a scene file says: its vocabulary (keys, enumerations, defaults) and the frozen dataclasses a validated scene
is made of (parse.py reads and checks a scene's TOML, or the same dict built in Python, into them). Names that need
the model (joints, frames) are checked later, when the Scene is built.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..exceptions import InvalidArgumentError
from ..text import printable

TOP_LEVEL_KEYS = (
    "description",
    "gravity",
    "friction_velocity",
    "robot",
    "lock",
    "joints",
    "force",
    "payload",
    "constraint",
    "initial",
    "simulation",
    "controller",
    "ground",
    "contact",
    "object",
    "actuator",
    "actuators",
    "sensor",
    "randomize",
)
ROBOT_KEYS = ("source", "base", "position", "rpy", "damping", "mimic", "package_dirs")
JOINT_KEYS = ("damping", "friction", "stiffness", "rest", "armature")
FORCE_KEYS = ("name", "frame", "force", "torque", "reference", "shape", "start", "ramp_time", "frequency", "phase")
PAYLOAD_KEYS = ("frame", "mass", "com", "inertia")
CONSTRAINT_KEYS = ("name", "type", "frames", "position", "stabilization")
INITIAL_KEYS = ("q", "v")
SIMULATION_OPTIONS = ("output_dt", "control_dt", "rtol", "atol", "max_step")
SIMULATION_KEYS = ("duration", "dt", "integrator", *SIMULATION_OPTIONS)
BASES = ("fixed", "floating")
REFERENCES = ("world", "local")
SHAPES = ("constant", "step", "ramp", "sine")
# Which optional keys of a [[force]] each shape reads: any other is a mistake worth reporting.
SHAPE_KEYS = {
    "constant": (),
    "step": ("start",),
    "ramp": ("start", "ramp_time"),
    "sine": ("start", "frequency", "phase"),
    "callable": (),
}
CONSTRAINT_FRAMES = {"loop": 2, "point": 1, "weld": 2}
DEFAULT_FRICTION_VELOCITY = 1e-3
GROUND_KEYS = ("height", "friction", "restitution")
CONTACT_KEYS = (
    "pairs",
    "limits",
    "velocity_limits",
    "friction",
    "solver",
    "body_friction",
    "body_restitution",
    "robot_geometry",
    "geometry",
)
CONTACT_PAIRS = ("ground", "all")
CONTACT_LIMITS = ("enforce", "report")
SPEED_CAPS = ("enforce", "brake")  # [contact] velocity_limits: the brakes' limits as constraints too, or brakes alone
CONTACT_FRICTION = ("exact", "regularized")
CONTACT_SOLVERS = ("admm", "pgs")
ROBOT_GEOMETRY = ("urdf", "declared")
OBJECT_SHAPES = ("box", "sphere", "cylinder")
# The dimensions each shape takes (and requires).
SHAPE_DIMENSIONS = {"box": ("size",), "sphere": ("radius",), "cylinder": ("radius", "length")}
GEOMETRY_KEYS = ("frame", "shape", "size", "radius", "length", "position", "rpy")
OBJECT_KEYS = ("name", "shape", "size", "radius", "length", "mass", "position", "rpy", "velocity")
DEFAULT_GROUND_FRICTION = 0.5
ACTUATOR_KEYS = (  # the three that take names first, then those that take a number (ACTUATOR_NUMBERS)
    "joints",
    "kind",
    "overspeed",
    "kp",
    "kv",
    "gear",
    "rotor_inertia",
    "effort_limit",
    "velocity_limit",
    "stall_torque",
    "no_load_speed",
    "overspeed_band",
)
ACTUATOR_NUMBERS = ACTUATOR_KEYS[3:]  # the keys that take a number
ACTUATOR_KINDS = ("torque", "position", "velocity")
ACTUATOR_OVERSPEED = ("brake", "none")  # the overspeed protections (scenes/actuators.py)
# Which gains each kind takes (any other is a mistake worth reporting).
ACTUATOR_GAINS = {"torque": (), "position": ("kp", "kv"), "velocity": ("kv",)}
ACTUATOR_SOURCES = ("catalog",)  # the top-level `actuators` key: where default actuators come from
CONTACT_INTEGRATOR = "timestepping"  # the one integrator that steps contact scenes
SENSOR_KEYS = ("name", "kind", "frame", "joint", "body", "joints", "noise", "bias", "rate", "latency", "seed")
# Each kind of sensor and where it is: the keys that place it (one of them required when several are listed).
SENSOR_PLACES = {
    "imu": ("frame",),
    "force_torque": ("frame", "joint"),
    "contact_force": ("body",),
    "joint_position": ("joints",),
    "joint_velocity": ("joints",),
    "joint_torque": ("joints",),
    "frame_pose": ("frame",),
}
SENSOR_KINDS = tuple(SENSOR_PLACES)
RANDOMIZE_KEYS = ("seed", "parameter")
PARAMETER_KEYS = ("name", "bodies", "joints", "payloads", "distribution", "scale", "value", "shared")
DISTRIBUTIONS = ("uniform", "normal", "loguniform")  # uniform [low, high], normal [mean, std], loguniform [low, high]


@dataclass(frozen=True)
class Quantity:
    """A scene parameter [randomize] may draw: what it selects, the range of its values, its unit.

    Attributes:
        target: the key that selects what it applies to ("bodies", "joints", "payloads"), or None (one value for
            the scene).
        low, high: the range of its values (of a drawn `value`; of nominal x `scale` when the Scene is built).
        open_low: whether `low` itself is excluded (masses: > 0).
        unit: for messages and docs.
        scale_only: the value is itself a factor (inertia): `value` is refused.
        what: one line for describe() and the docs.
    """

    target: str | None
    low: float
    high: float
    open_low: bool
    unit: str
    what: str
    scale_only: bool = False


# The parameters [randomize] draws, by name (scenes/randomize.py applies them; docs/randomize.md describes them).
QUANTITIES = {
    "mass": Quantity("bodies", 0.0, math.inf, True, "kg", "a body's mass, its rotational inertia in proportion"),
    "inertia": Quantity("bodies", 0.0, math.inf, True, "", "a factor on a body's rotational inertia", True),
    "payload_mass": Quantity("payloads", 0.0, math.inf, True, "kg", "a payload's mass, its inertia in proportion"),
    "ground_friction": Quantity(None, 0.0, math.inf, False, "", "Coulomb μ of every contact with the ground"),
    "ground_restitution": Quantity(None, 0.0, 1.0, False, "", "Newton's e of every contact with the ground"),
    "body_friction": Quantity(None, 0.0, math.inf, False, "", "Coulomb μ of every contact between bodies"),
    "body_restitution": Quantity(None, 0.0, 1.0, False, "", "Newton's e of every contact between bodies"),
    "damping": Quantity("joints", 0.0, math.inf, False, "N·m·s/rad or N·s/m", "a joint's viscous damping"),
    "friction": Quantity("joints", 0.0, math.inf, False, "N·m or N", "a joint's Coulomb friction"),
    "armature": Quantity("joints", 0.0, math.inf, False, "kg·m² or kg", "a joint's armature (its rotor's aside)"),
    "kp": Quantity("joints", 0.0, math.inf, False, "N·m/rad or N/m", "a position servo's stiffness"),
    "kv": Quantity("joints", 0.0, math.inf, False, "N·m·s/rad or N·s/m", "a servo's damping"),
    "gear": Quantity("joints", 0.0, math.inf, True, "", "an actuator's gear ratio"),
    "rotor_inertia": Quantity("joints", 0.0, math.inf, False, "kg·m²", "an actuator's rotor inertia"),
    "effort_limit": Quantity("joints", 0.0, math.inf, True, "N·m or N", "an actuator's effort limit"),
    "velocity_limit": Quantity("joints", 0.0, math.inf, True, "rad/s or m/s", "an actuator's velocity limit"),
    "stall_torque": Quantity("joints", 0.0, math.inf, True, "N·m or N", "an actuator's stall torque"),
    "no_load_speed": Quantity("joints", 0.0, math.inf, True, "rad/s or m/s", "an actuator's no-load speed"),
}
# The actuator constants among them: an [[actuator]] table's numbers but the overspeed brake's band (scenes/
# actuators.py's Actuator fields of the same names).
ACTUATOR_QUANTITIES = tuple(key for key in ACTUATOR_NUMBERS if key != "overspeed_band")
TARGET_KEYS = ("bodies", "joints", "payloads")


# ---- the parsed scene ----------------------------------------------------------------------------------
@dataclass(frozen=True)
class RobotSpec:
    """The robot a scene simulates.

    Attributes:
        source: a catalog name, or a URDF path (a relative path in a scene file is made relative to the file's
            folder).
        base: "fixed", "floating", or None for the natural base (the catalog entry's; fixed for URDF paths).
        position: where a fixed base's root link is welded [m], shape (3,); None: the origin.
        rpy: roll, pitch, yaw of that weld [rad], shape (3,); None: identity.
        damping: apply the URDF's ``<dynamics damping>``.
        mimic: honour the URDF's ``<mimic>`` joints.
        package_dirs: extra ``package://`` roots (relative ones made relative to the scene file's folder).
    """

    source: str
    base: str | None = None
    position: tuple[float, float, float] | None = None
    rpy: tuple[float, float, float] | None = None
    damping: bool = True
    mimic: bool = False
    package_dirs: tuple[str, ...] = ()


@dataclass(frozen=True)
class JointSpec:
    """Per-joint overrides and additions on a 1-dof joint; None leaves a property as the URDF has it.

    Attributes:
        damping: viscous damping [N·m·s/rad or N·s/m], >= 0; replaces the URDF value.
        friction: Coulomb friction [N·m or N], >= 0; replaces the URDF value.
        stiffness: spring stiffness [N·m/rad or N/m], >= 0.
        rest: spring rest position [rad or m] (None: 0).
        armature: rotor inertia added to M's diagonal [kg·m² or kg], >= 0.
    """

    damping: float | None = None
    friction: float | None = None
    stiffness: float | None = None
    rest: float | None = None
    armature: float | None = None


@dataclass(frozen=True)
class ForceSpec:
    """An external wrench on a named frame, scaled over time by a shape.

    Attributes:
        name: ledger name (the element is ``force:<name>``).
        frame: a frame of the model (link, joint or fixed frame).
        force: force [N], shape (3,).
        torque: torque [N·m], shape (3,).
        reference: "world" (world-aligned axes at the frame's origin) or "local" (the frame's own axes).
        shape: "constant", "step", "ramp", "sine", or a Python callable ``t -> scale`` (from Python only).
        start: when step, ramp and sine switch on [s].
        ramp_time: time a ramp takes from 0 to full value [s], > 0.
        frequency: sine frequency [Hz], > 0.
        phase: sine phase [rad].
    """

    name: str
    frame: str
    force: tuple[float, float, float] = (0.0, 0.0, 0.0)
    torque: tuple[float, float, float] = (0.0, 0.0, 0.0)
    reference: str = "world"
    shape: str | Callable[[float], float] = "constant"
    start: float = 0.0
    ramp_time: float = 1.0
    frequency: float = 1.0
    phase: float = 0.0

    def scale(self, t: float) -> float:
        """The factor on (force, torque) at time t [s].

        constant: 1. step: 0 before start, 1 from start on. ramp: clip((t − start) / ramp_time, 0, 1).
        sine: sin(2π frequency (t − start) + phase) from start on, 0 before. A callable: its value at t.

        Raises:
            InvalidArgumentError: a callable shape returned something other than a finite real number.
        """
        shape = self.shape
        if callable(shape):
            value = shape(t)
            if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real) or not math.isfinite(value):
                raise InvalidArgumentError(
                    printable(f"force '{self.name}': shape({t!r}) returned {value!r}, not a finite real number")
                )
            return float(value)
        if shape == "constant":
            return 1.0
        if t < self.start:
            return 0.0
        if shape == "step":
            return 1.0
        if shape == "ramp":
            return min((t - self.start) / self.ramp_time, 1.0)
        return math.sin(2.0 * math.pi * self.frequency * (t - self.start) + self.phase)


@dataclass(frozen=True)
class PayloadSpec:
    """Extra mass rigidly attached to a frame.

    Attributes:
        frame: the frame it is attached to.
        mass: [kg], > 0.
        com: centre of mass in the frame [m], shape (3,).
        inertia: about the centre of mass, in the frame's axes: (ixx, iyy, izz, ixy, ixz, iyz) [kg·m²]; a
            physical inertia (positive semi-definite, principal moments obeying the triangle inequality).
    """

    frame: str
    mass: float
    com: tuple[float, float, float] = (0.0, 0.0, 0.0)
    inertia: tuple[float, float, float, float, float, float] = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@dataclass(frozen=True)
class ConstraintSpec:
    """A holonomic constraint, enforced with Lagrange multipliers.

    Attributes:
        name: ledger name (the element is ``constraint:<name>``).
        type: "loop" (two frames' origins coincide, 3 rows), "point" (a frame's origin fixed in the world, 3
            rows) or "weld" (two frames held at their initial relative pose, 6 rows).
        frames: two distinct frames for loop and weld, one for point.
        position: point only: the world anchor [m], shape (3,); None: where the frame is at the initial q.
        stabilization: Baumgarte gains (Kp [1/s²], Kd [1/s]) on the drift, both >= 0; None: the default.
    """

    name: str
    type: str
    frames: tuple[str, ...]
    position: tuple[float, float, float] | None = None
    stabilization: tuple[float, float] | None = None


@dataclass(frozen=True)
class GroundSpec:
    """The ground: the plane z = height, normal +z.

    Attributes:
        height: [m].
        friction: Coulomb coefficient μ >= 0 of every contact with the ground.
        restitution: Newton's coefficient e in [0, 1] of every contact with the ground.
    """

    height: float = 0.0
    friction: float = DEFAULT_GROUND_FRICTION
    restitution: float = 0.0


@dataclass(frozen=True)
class ShapeSpec:
    """A collision shape: "box" (size = full extents x, y, z [m]), "sphere" (radius [m]) or "cylinder" (radius,
    length along its z axis [m]).

    Attributes:
        shape: "box", "sphere" or "cylinder".
        size: box extents [m], shape (3,), else None.
        radius: sphere and cylinder radius [m], else None.
        length: cylinder length [m], else None.
    """

    shape: str
    size: tuple[float, float, float] | None = None
    radius: float | None = None
    length: float | None = None

    @property
    def dimensions(self) -> tuple[float, ...]:
        """The shape's numbers: box (x, y, z), sphere (radius,), cylinder (radius, length) [m]."""
        if self.shape == "box":
            return tuple(self.size or ())
        if self.shape == "sphere":
            return (self.radius,)  # type: ignore[return-value]
        return (self.radius, self.length)  # type: ignore[return-value]


@dataclass(frozen=True)
class GeometrySpec:
    """Collision geometry of a robot's body, in place of its URDF's collision geometry.

    Attributes:
        frame: a frame of the robot on a moving body.
        shape: the shape.
        position: its centre relative to the frame [m], shape (3,).
        rpy: its orientation relative to the frame [rad], shape (3,).
    """

    frame: str
    shape: ShapeSpec
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)


@dataclass(frozen=True)
class ObjectSpec:
    """A free rigid body of uniform density (its inertia from its shape), a free-flyer after the robot's joints.

    Attributes:
        name: its name (its dofs are "<name>.vx" ... "<name>.wz").
        shape: the shape.
        mass: [kg], > 0.
        position: its centre in the world [m], shape (3,).
        rpy: its orientation [rad], shape (3,).
        velocity: linear then angular velocity in world axes [m/s, rad/s], shape (6,).
    """

    name: str
    shape: ShapeSpec
    mass: float
    position: tuple[float, float, float] = (0.0, 0.0, 0.0)
    rpy: tuple[float, float, float] = (0.0, 0.0, 0.0)
    velocity: tuple[float, float, float, float, float, float] = (0.0,) * 6


@dataclass(frozen=True)
class ContactSpec:
    """What touches what, and how unilateral constraints are treated.

    Attributes:
        pairs: "ground" (every collision geometry against the ground), "all" (also between bodies, adjacent
            links excluded) or explicit pairs of body names (links, objects or "ground").
        limits: "enforce" (URDF position limits as unilateral constraints) or "report" (counted only).
        velocity_limits: "enforce" (the velocity limit of every actuator with an overspeed brake as unilateral
            constraints of the step: joint speeds within their limits through impacts) or "brake" (the brakes
            alone, which impacts can back-drive past the limit).
        friction: "exact" (joint dry friction as a constraint: exact stiction) or "regularized" (tanh).
        solver: "admm" (Pinocchio's ADMM) or "pgs" (projected Gauss–Seidel).
        body_friction: Coulomb μ of contacts between bodies (ground contacts take [ground] friction).
        body_restitution: Newton's e of contacts between bodies.
        robot_geometry: the robot's collision geometry: "urdf" (the URDF's collision shapes, meshes as their
            convex hulls, on every body without declared geometry) or "declared" ([[contact.geometry]] only); None
            (not given): "declared" when the scene declares geometry, else "urdf" (see effective_robot_geometry).
        geometry: collision geometry replacing the URDF's on the bodies it names.
    """

    pairs: str | tuple[tuple[str, str], ...] = "ground"
    limits: str = "report"
    velocity_limits: str = "enforce"
    friction: str = "regularized"
    solver: str = "admm"
    body_friction: float = DEFAULT_GROUND_FRICTION
    body_restitution: float = 0.0
    robot_geometry: str | None = None
    geometry: tuple[GeometrySpec, ...] = ()

    @property
    def effective_robot_geometry(self) -> str:
        """robot_geometry as declared, else its default: "declared" when [[contact.geometry]] is given, else "urdf"."""
        if self.robot_geometry is not None:
            return self.robot_geometry
        return "declared" if self.geometry else "urdf"


@dataclass(frozen=True)
class ActuatorSpec:
    """One [[actuator]] table: the actuator of a group of joints; None leaves a property to earlier tables (or the
    default). Later tables override earlier ones joint by joint, key by key (scenes/actuators.py merges them).

    Attributes:
        joints: joint names or glob patterns (``"*"``: every actuated joint), as given.
        kind: "torque" (the command is the torque), "position" (a servo to a position target: kp, kv) or
            "velocity" (a servo to a velocity target: kv).
        kp: position servo stiffness [N·m/rad or N/m], >= 0.
        kv: servo damping [N·m·s/rad or N·s/m], >= 0.
        gear: gear ratio N > 0 (joint torque = N × motor torque); the rotor's inertia is reflected onto the joint
            as the armature N² × rotor_inertia.
        rotor_inertia: the rotor's inertia about its axis at the motor [kg·m²], >= 0.
        effort_limit: the largest |torque| at the joint [N·m or N], > 0 (default: the URDF's).
        velocity_limit: the largest |speed| the actuator drives the joint at [rad/s or m/s], > 0 (default: the
            URDF's).
        stall_torque: the torque–speed curve: available |torque| at rest [N·m or N], > 0, falling linearly to 0 at
            no_load_speed [rad/s or m/s], > 0, while the torque drives the motion (both or neither).
        no_load_speed: see stall_torque.
        overspeed: "brake" (the default where the actuator has an effort and a velocity limit) or "none": whether
            past its velocity limit the actuator brakes the joint whatever the command (scenes/actuators.py).
        overspeed_band: the brake's band, a fraction of the velocity limit in (0, 1] (default 0.1): the brake's
            torque rises from 0 at the limit to the effort limit that far past it.
    """

    joints: tuple[str, ...]
    kind: str | None = None
    overspeed: str | None = None
    kp: float | None = None
    kv: float | None = None
    gear: float | None = None
    rotor_inertia: float | None = None
    effort_limit: float | None = None
    velocity_limit: float | None = None
    stall_torque: float | None = None
    no_load_speed: float | None = None
    overspeed_band: float | None = None


@dataclass(frozen=True)
class SensorSpec:
    """A sensor: what it measures, where, and how its readings are spoiled (see multibody_sim.sensors).

    Attributes:
        name: unique among the scene's sensors; the key of Trajectory.sensors and the dataframe's column prefix.
        kind: one of SENSOR_KINDS.
        frame: imu, frame_pose and force_torque: the frame it sits at.
        joint: force_torque: the joint it sits at (instead of a frame).
        body: contact_force: a body with collision geometry (a [[contact.geometry]] frame or an [[object]]).
        joints: joint_position, joint_velocity, joint_torque: 1-dof joints (None: every actuated one).
        noise: standard deviation of the additive Gaussian noise, one number or one per component (>= 0).
        bias: constant offset, one number or one per component.
        rate: readings per second [Hz] (None: one per control instant, every step without control_dt).
        latency: how many of its own readings late each reading comes (>= 0).
        seed: its random generator's seed (numpy PCG64; a rollout's row b draws from seed + b).
    """

    name: str
    kind: str
    frame: str | None = None
    joint: str | None = None
    body: str | None = None
    joints: tuple[str, ...] | None = None
    noise: float | tuple[float, ...] = 0.0
    bias: float | tuple[float, ...] = 0.0
    rate: float | None = None
    latency: int = 0
    seed: int = 0


@dataclass(frozen=True)
class ParameterSpec:
    """One [[randomize.parameter]] table: a scene parameter drawn from a distribution.

    Attributes:
        name: a key of QUANTITIES ("mass", "ground_friction", "damping", "kp", ...).
        targets: what it applies to, as given (names or glob patterns of bodies or joints, payload indices as
            strings, "*" for all); () for a parameter of the whole scene (ground_friction).
        distribution: "uniform" (arguments: low, high), "normal" (mean, std; values outside the quantity's range
            are drawn again: a truncated normal) or "loguniform" (low, high, both > 0).
        arguments: the distribution's two numbers.
        scale: the draw multiplies the nominal value (True) or is the value itself (False).
        shared: one draw for all its targets (True) or one per target (False, the default).
    """

    name: str
    targets: tuple[Any, ...]
    distribution: str
    arguments: tuple[float, float]
    scale: bool
    shared: bool = False


@dataclass(frozen=True)
class RandomizeSpec:
    """The [randomize] table: scene parameters drawn per rollout row or per gym reset.

    Attributes:
        seed: the draws' seed, a whole number >= 0 (row b of a rollout draws from numpy's generator seeded with
            (seed, b)).
        parameters: the [[randomize.parameter]] tables, in order (a later one overrides an earlier one on the same
            target).
    """

    seed: int = 0
    parameters: tuple[ParameterSpec, ...] = ()


@dataclass(frozen=True)
class SimulationSpec:
    """How to run the scene; None leaves a setting to the caller (the command line or simulate's defaults).

    Attributes:
        duration: simulated time [s], > 0.
        dt: step (first trial step for adaptive methods) [s], > 0.
        integrator: an integrator name (multibody_sim.INTEGRATORS).
        options: the simulate() options given: output_dt, control_dt, max_step [s] and rtol, atol, all > 0.
    """

    duration: float | None = None
    dt: float | None = None
    integrator: str | None = None
    options: dict[str, float] = field(default_factory=dict)


@dataclass(frozen=True)
class ControllerSpec:
    """A built-in controller and its parameters.

    Attributes:
        name: a key of multibody_sim.CONTROLLERS.
        params: parameter values in the order given: numbers (int or float), booleans, strings, tuples of
            numbers (vectors), tuples of such tuples ("rows" parameters such as waypoints).
    """

    name: str
    params: dict[str, Any] = field(default_factory=dict)

    def as_param_strings(self) -> list[str]:
        """The parameters as make_controller's ``KEY=VALUE`` strings: ``["kp=100.0", "q_ref=0,-1,1"]``.

        Vectors are comma-joined; a "rows" parameter gives one string per row; floats are written with repr,
        which reads back to the same float.
        """
        strings = []
        for key, value in self.params.items():
            rows = value if isinstance(value, tuple) and value and isinstance(value[0], tuple) else (value,)
            strings += [f"{key}={_param_text(row)}" for row in rows]
        return strings


@dataclass(frozen=True)
class SceneSpec:
    """A validated scene, before any model is built.

    Attributes:
        robot: the robot and its base; None for a scene of objects only.
        description: free text.
        gravity: [m/s²], shape (3,); None: Pinocchio's (0, 0, −9.81).
        friction_velocity: regularization velocity of Coulomb friction [rad/s or m/s], > 0.
        lock: joints removed from the model and the positions they are held at [rad or m].
        joints: per-joint overrides, by joint name.
        forces: external wrenches.
        payloads: extra masses.
        constraints: holonomic constraints.
        initial_q: the scene model's q (after locking), or {joint: value} over 1-dof joints; None: the default.
        initial_v: the same for v.
        simulation: run settings, or None when the scene has no [simulation] table.
        controller: a built-in controller, or None.
        ground: the ground plane, or None.
        contact: the [contact] table (None without one: no limits enforced, regularized friction).
        objects: free rigid bodies.
        actuators: the [[actuator]] tables, in order (later ones override earlier ones joint by joint).
        actuator_defaults: where default actuators come from before those tables: "catalog" (the robot's published
            motor data, models/actuators/<robot>.toml) or None (none: the commands of joints without an actuator
            are ideal torques).
        sensors: the sensors, in the order declared.
        randomize: the [randomize] table (parameters drawn per rollout row or gym reset), or None.
        parameters: drawn parameter values this scene is built with (scenes/randomize.py's form: {name: value} or
            {name: {target: value}}), or None: the declared (nominal) values. Set by Scene.with_parameters.
        source: the name used in messages (the file path as given, or "<scene>").
        text: the scene file's text (for trajectory metadata); None for a dict.
        base_dir: the folder relative paths were resolved against (the scene file's); None for a dict.
        allowed_roots: further folders the robot's files and meshes may come from (load_scene's allowed_roots,
            the command line's --allow-root), besides the scene's folder and the catalog.
    """

    robot: RobotSpec | None
    description: str = ""
    gravity: tuple[float, float, float] | None = None
    friction_velocity: float = DEFAULT_FRICTION_VELOCITY
    lock: dict[str, float] = field(default_factory=dict)
    joints: dict[str, JointSpec] = field(default_factory=dict)
    forces: tuple[ForceSpec, ...] = ()
    payloads: tuple[PayloadSpec, ...] = ()
    constraints: tuple[ConstraintSpec, ...] = ()
    initial_q: tuple[float, ...] | dict[str, float] | None = None
    initial_v: tuple[float, ...] | dict[str, float] | None = None
    simulation: SimulationSpec | None = None
    controller: ControllerSpec | None = None
    ground: GroundSpec | None = None
    contact: ContactSpec | None = None
    objects: tuple[ObjectSpec, ...] = ()
    actuators: tuple[ActuatorSpec, ...] = ()
    actuator_defaults: str | None = None
    sensors: tuple[SensorSpec, ...] = ()
    randomize: RandomizeSpec | None = None
    parameters: dict[str, Any] | None = None
    source: str = "<scene>"
    text: str | None = None
    base_dir: Path | None = None
    allowed_roots: tuple[str, ...] = ()

    @property
    def has_contact(self) -> bool:
        """Whether the scene declares contact ([ground], [contact] or [[object]]): the timestepping integrator's."""
        return self.ground is not None or self.contact is not None or bool(self.objects)


def _param_text(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, tuple):
        return ",".join(_param_text(v) for v in value)
    if isinstance(value, float):
        return repr(value)
    return str(value)
