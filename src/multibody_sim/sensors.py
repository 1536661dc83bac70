"""Sensors: what a scene's [[sensor]] tables measure at a tick, and the readings made of those measurements.

A tick is the end of a step (every so many steps: the sensor's rate). What it measures is the state at that instant
with the step that just ended: the acceleration a sensor feels is that step's velocity change over its length,
``(v⁺ − v) / h`` (the time-stepper's impulses included), and the contact forces are its impulses over h. So a
reading at a control instant depends on the torque held up to that instant, never on the torque a controller is
about to choose from it. The first tick, at the run's start, takes the acceleration and impulses of a first step
of dt under the command held at the start (zero), computed and discarded (no step has ended yet).

Kinds (components; axes):

- ``imu`` at a frame: specific force ``Rᵀ(a − g)`` [m/s²] (a: the frame origin's acceleration, g: gravity; at rest
  it reads g upward, in free fall zero) and angular velocity [rad/s], both in the frame's axes: ax ay az wx wy wz.
- ``force_torque`` at a joint or a frame: the wrench the proximal side exerts on everything distal to the cut,
  at the frame's origin in its axes [N, N·m]: fx fy fz tx ty tz. The cut at a joint (or at its frame) carries the
  joint's whole subtree; at a frame inside a body (a URDF fixed joint, a link's frame) it carries the links after
  that frame in the URDF, what hangs below them, and the payloads, wrenches and contacts on them; a body's own
  part before the frame is not measured (at rest: the distal weight, plus any external force on the distal side).
- ``contact_force`` on a body with collision geometry: the sum of the contact forces on it, world axes [N]:
  fx fy fz.
- ``joint_position``, ``joint_velocity``, ``joint_torque`` of 1-dof joints [rad or m, rad/s or m/s, N·m or N]: one
  component per joint (a continuous joint's angle is atan2(sin, cos)); the torque is the one delivered to the
  joint under the command held over the step that ended: that command (after saturation) for an ideal torque
  source, an actuator's output at the tick's state (scenes/actuators.py; for semi-implicit Euler and the
  time-stepper, exactly the servo torque their implicit step applied), not its command.
- ``frame_pose``: the frame's position and orientation in the world: x y z qx qy qz qw (Pinocchio's quaternion).

Readings (SensorStream): a sensor reads at its own rate (every `stride` ticks of the run's clock); reading m is
measurement m − latency (the first measurement before that) plus the bias plus Gaussian noise of the declared
std, drawn from the sensor's own stream (noise.NormalStream seeded with ``seed + row``), one draw per component
per reading, in order. Between its readings a sensor holds its latest one. The kernels measure (the Python kernel with
Sensors.measure, the native one with its rendering in src/native/measure.hpp, bit for bit); the readings are made
by SensorStream (multibody_sim/readings.py) for every kernel alike.
"""

from __future__ import annotations

import fnmatch
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
import pinocchio as pin

from .exceptions import InvalidArgumentError
from .ordered import ordered_matvec
from .readings import SensorStream
from .scenes.spec import SensorSpec

COMPONENTS = {
    "imu": ("ax", "ay", "az", "wx", "wy", "wz"),
    "force_torque": ("fx", "fy", "fz", "tx", "ty", "tz"),
    "contact_force": ("fx", "fy", "fz"),
    "frame_pose": ("x", "y", "z", "qx", "qy", "qz", "qw"),
}
_LOCAL = pin.ReferenceFrame.LOCAL


@dataclass(frozen=True)
class Cut:
    """Where a force–torque sensor cuts the tree, on the scene's model.

    Attributes:
        joint: the joint whose body is cut (its id).
        whole: the cut is at the joint: the sensor carries the joint's whole subtree.
        placement: the sensor frame in the joint's frame.
        inertia: whole=False: the distal part's inertia in the joint's frame (links after the frame, payloads).
        children: whole=False: the child joints hanging from the distal part.
        frames: whole=False: the frames on the distal part (external forces on them count).
    """

    joint: int
    whole: bool
    placement: pin.SE3
    inertia: pin.Inertia | None = None
    children: tuple[int, ...] = ()
    frames: frozenset[int] = frozenset()


@dataclass(frozen=True)
class Wrench:
    """A scene's external wrench as the sensors see it: frame, force and torque [N, N·m], reference, scale(t)."""

    frame: int
    force: np.ndarray
    torque: np.ndarray
    local: bool
    scale: Any


@dataclass(frozen=True)
class Placed:
    """One sensor on the model.

    Attributes:
        spec: as declared.
        components: its components' names, shape (width,).
        frame: imu, frame_pose: the frame id.
        cut: force_torque: where it cuts.
        body: contact_force: the body's index among the contact model's bodies.
        coordinates: joint_*: (idx_q, idx_v, nq) of each joint.
        noise, bias: per component, shape (width,).
        stride: readings every this many ticks of the run's clock (set per run by SensorStream).
    """

    spec: SensorSpec
    components: tuple[str, ...]
    frame: int = -1
    cut: Cut | None = None
    body: int = -1
    coordinates: tuple[tuple[int, int, int], ...] = ()
    noise: np.ndarray | None = None
    bias: np.ndarray | None = None

    @property
    def width(self) -> int:
        return len(self.components)


class Sensors:
    """A scene's sensors on its model: the noiseless measurement at a tick (measure), the layout of the readings.

    Attributes:
        placed: the sensors, in declaration order.
        names: their names.
        offsets: where each one's components start in a tick's row, shape (n + 1,).
        width: components in all.
    """

    def __init__(
        self,
        model: pin.Model,
        placed: list[Placed],
        *,
        wrenches: list[Wrench],
        contact_joints: list[int] | None = None,
        contact_frames: list[int] | None = None,
        actuators: Any = None,
    ):
        """Args:
        model: the scene's model.
        placed: the sensors, placed on it.
        wrenches: the scene's external wrenches (force–torque sensors see them).
        contact_joints, contact_frames: per contact body (Trajectory.contacts' body indices), the joint it moves
            with and its frame on that joint (-1: none), for contact scenes.
        actuators: the scene's actuators (scenes/actuators.py), which turn the held command into the torque
            delivered to the joints; None: the command is the torque.
        """
        self.model = model
        self.data = model.createData()
        self.placed = placed
        self.names = [p.spec.name for p in placed]
        self.offsets = np.cumsum([0] + [p.width for p in placed])
        self.width = int(self.offsets[-1])
        self.wrenches = wrenches
        self.contact_joints = contact_joints or []
        self.contact_frames = contact_frames or []
        self.actuators = actuators
        kinds = {p.spec.kind for p in placed}
        self._kinematics = bool(kinds & {"imu", "frame_pose", "force_torque"})
        self._dynamics = "force_torque" in kinds
        self._gravity = np.array(model.gravity.linear, dtype=float)

    def __len__(self) -> int:
        return len(self.placed)

    def columns(self, k: int) -> slice:
        """Sensor k's components in a row of readings."""
        return slice(int(self.offsets[k]), int(self.offsets[k + 1]))

    def describe(self) -> str:
        """One line per sensor, for Scene.describe()."""
        lines = []
        for p in self.placed:
            spec = p.spec
            where = next(
                (f" at {getattr(spec, key)}" for key in ("frame", "joint", "body") if getattr(spec, key) is not None),
                "",
            )
            if spec.kind.startswith("joint_"):
                where = f" of {len(p.coordinates)} joint{'s' if len(p.coordinates) != 1 else ''}"
            rate = f"{spec.rate:g} Hz" if spec.rate is not None else "every control instant"
            spoil = []
            if spec.noise != 0.0:
                spoil.append(f"noise {_numbers(spec.noise)}")
            if spec.bias != 0.0:
                spoil.append(f"bias {_numbers(spec.bias)}")
            if spec.latency:
                spoil.append(f"latency {spec.latency}")
            extra = f", {', '.join(spoil)}" if spoil else ""
            lines.append(f"    {spec.name}: {spec.kind}{where}, {rate}{extra} ({' '.join(p.components)})")
        return "\n".join(lines)

    # ---- the native kernel's data -------------------------------------------------------------------------------
    def native_reason(self) -> str | None:
        """Why the native kernel cannot measure these sensors, or None."""
        kinds = {p.spec.kind for p in self.placed}
        if self.wrenches and "force_torque" in kinds:
            return "its force-torque sensors see its [[force]] wrenches, which the native kernel does not measure"
        return None

    def native_data(self) -> dict[str, Any]:
        """The sensors as _native.Sensors takes them (src/native/sensors.hpp): each one's kind, place and cut."""
        items = []
        for k, p in enumerate(self.placed):
            cut = p.cut if p.cut is not None else Cut(0, True, pin.SE3.Identity())
            inertia = cut.inertia if cut.inertia is not None else pin.Inertia.Zero()
            items.append(
                {
                    "kind": p.spec.kind,
                    "offset": int(self.offsets[k]),
                    "frame": int(p.frame),
                    "body": int(p.body),
                    "q_index": [c[0] for c in p.coordinates],
                    "v_index": [c[1] for c in p.coordinates],
                    "q_count": [c[2] for c in p.coordinates],
                    "cut_joint": int(cut.joint),
                    "cut_whole": bool(cut.whole),
                    "cut_rotation": np.array(cut.placement.rotation),
                    "cut_translation": np.array(cut.placement.translation),
                    "cut_mass": float(inertia.mass),
                    "cut_lever": np.array(inertia.lever),
                    "cut_inertia": np.array(inertia.inertia),
                    "cut_children": [int(c) for c in cut.children],
                    "cut_frames": sorted(int(f) for f in cut.frames),
                }
            )
        return {
            "width": self.width,
            "gravity": self._gravity.copy(),
            "items": items,
            "contact_joints": list(self.contact_joints),
            "contact_frames": list(self.contact_frames),
        }

    # ---- the measurement ----------------------------------------------------------------------------------------
    def measure(
        self,
        q: np.ndarray,
        v: np.ndarray,
        a: np.ndarray,
        tau: np.ndarray,
        t: float,
        contacts: np.ndarray | None,
        h: float,
        out: np.ndarray,
    ) -> None:
        """Every sensor's noiseless measurement at one tick, into `out` (width,).

        Args:
            q, v: the state at the tick.
            a: the acceleration the sensors feel: the ended step's (v⁺ − v) / h, shape (nv,).
            tau: the command held over that step, shape (nv,): the joint torque, or with actuators their
                command, whose delivered torque at (q, v) the joint_torque sensors read.
            t: the tick's time [s].
            contacts: that step's contacts as Trajectory.contacts rows (k, 11): pair, point, normal, impulse on
                body 2 [N·s], or None.
            h: that step's length [s].
        """
        model, data = self.model, self.data
        if self._kinematics:
            pin.forwardKinematics(model, data, q, v, a)
        fext = None
        delivered = None
        for k, p in enumerate(self.placed):
            kind = p.spec.kind
            row = out[self.offsets[k] : self.offsets[k + 1]]
            if kind == "imu":
                placement = pin.updateFramePlacement(model, data, p.frame)
                acceleration = pin.getFrameClassicalAcceleration(model, data, p.frame, _LOCAL).linear
                row[:3] = acceleration - ordered_matvec(placement.rotation.T, self._gravity)
                row[3:] = pin.getFrameVelocity(model, data, p.frame, _LOCAL).angular
            elif kind == "frame_pose":
                placement = pin.updateFramePlacement(model, data, p.frame)
                row[:3] = placement.translation
                row[3:] = pin.Quaternion(placement.rotation).coeffs()
            elif kind == "contact_force":
                row[:] = self._contact_force(p.body, contacts, h)
            elif kind == "force_torque":
                if fext is None:
                    fext = self._external(contacts, h, t)
                    pin.rnea(model, data, q, v, a, [f for f, _ in fext])
                assert p.cut is not None
                wrench = self._cut_wrench(p.cut, fext)
                row[:3] = wrench.linear
                row[3:] = wrench.angular
            else:  # joint_*
                if kind == "joint_torque" and delivered is None:
                    delivered = tau if self.actuators is None else self.actuators.joint_torques(q, v, tau)
                for i, (iq, iv, nq) in enumerate(p.coordinates):
                    if kind == "joint_position":
                        row[i] = q[iq] if nq == 1 else math.atan2(q[iq + 1], q[iq])
                    elif kind == "joint_velocity":
                        row[i] = v[iv]
                    else:
                        assert delivered is not None
                        row[i] = delivered[iv]

    def _contact_force(self, body: int, contacts: np.ndarray | None, h: float) -> np.ndarray:
        """The sum of the contact impulses on `body` over h [N], world axes."""
        total = np.zeros(3)
        if contacts is not None:
            for row in contacts:
                if int(row[1]) == body:
                    total = total + row[8:11]
                if int(row[0]) == body:
                    total = total - row[8:11]
        return total / h

    def _external(self, contacts: np.ndarray | None, h: float, t: float) -> list[tuple[pin.Force, list]]:
        """Per joint: the external forces on its body in its frame (for RNEA), and each one by frame: (frame id or
        -1, force in the joint's frame), in a fixed order: contacts (row order), then the wrenches."""
        model, data = self.model, self.data
        forces: list[tuple[pin.Force, list]] = [(pin.Force.Zero(), []) for _ in range(model.njoints)]

        def add(joint: int, frame: int, force: pin.Force) -> None:
            total, parts = forces[joint]
            forces[joint] = (total + force, parts)
            parts.append((frame, force))

        if contacts is not None:
            joints, frames = self.contact_joints, self.contact_frames
            for row in contacts:
                force = row[8:11] / h
                at = pin.SE3(np.eye(3), np.array(row[2:5]))
                for side, sign in ((1, 1.0), (0, -1.0)):
                    body = int(row[side])
                    joint = joints[body]
                    if joint:
                        world = at.act(pin.Force(sign * force, np.zeros(3)))
                        add(joint, frames[body], data.oMi[joint].actInv(world))
        for w in self.wrenches:
            scale = w.scale(t)
            frame = model.frames[w.frame]
            if w.local:
                local = pin.Force(scale * w.force, scale * w.torque)
            else:  # world axes at the frame's origin
                rotation = pin.updateFramePlacement(model, data, w.frame).rotation.T
                local = pin.Force(ordered_matvec(rotation, scale * w.force), ordered_matvec(rotation, scale * w.torque))
            add(frame.parentJoint, w.frame, frame.placement.act(local))
        return forces

    def _cut_wrench(self, cut: Cut, fext: list[tuple[pin.Force, list]]) -> pin.Force:
        """The wrench across the cut, at the sensor frame in its axes."""
        data = self.data
        if cut.whole:
            return cut.placement.actInv(data.f[cut.joint])
        assert cut.inertia is not None
        j = cut.joint
        velocity = data.v[j]
        wrench = cut.inertia * data.a_gf[j] + velocity.cross(cut.inertia * velocity)
        for child in cut.children:
            wrench = wrench + data.liMi[child].act(data.f[child])
        for frame, force in fext[j][1]:
            if frame in cut.frames:
                wrench = wrench - force
        return cut.placement.actInv(wrench)


def build_sensors(
    scene: Any,
    spec: Any,
    *,
    frame_id: Callable[..., int],
    joint_id: Callable[[pin.Model, str, str, bool], int],
    payloads: list[tuple[int, pin.Inertia]],
) -> Sensors:
    """A scene's sensors (spec.sensors, a SceneSpec's) on its model.

    Args:
        scene: the Scene being built (its model, floating base, actuated dofs, constraints, contact, actuators).
        frame_id: ``frame_id(model, name, key, moving=False)``: a frame's id, or SceneError naming the valid ones.
        joint_id: ``joint_id(model, name, key, floating)``: a 1-dof joint's id, or SceneError.
        payloads: the scene's payloads: (frame id, inertia in that frame).

    Raises:
        SceneError: a sensor that names what the scene lacks, or cannot measure there (one line each).
    """
    from .exceptions import SceneError
    from .text import name_hint

    model, where = scene.model, spec.source
    one_dof = [model.names[j] for j in range(1, model.njoints) if model.joints[j].nv == 1]
    actuated = [
        n for n in one_dof if scene.actuated.start <= model.joints[model.getJointId(n)].idx_v < scene.actuated.stop
    ]
    placed = []
    for i, sensor in enumerate(spec.sensors):
        key = f"{where}: sensor[{i}]"
        frame = joint = body = -1
        joints: list[int] = []
        if sensor.kind == "force_torque":
            if scene.constraints is not None or scene.mimic:
                what = "[[constraint]]" if scene.constraints is not None else "mimic joints"
                raise SceneError(
                    f"{key}.kind: force_torque sensors and {what} cannot be combined yet (the constraint forces are "
                    "not in the sensor's balance)"
                )
            if sensor.joint is not None:
                joint = joint_id(model, sensor.joint, f"{key}.joint", scene.floating_base)
            else:
                frame = frame_id(model, sensor.frame or "", f"{key}.frame", moving=True)
        elif sensor.frame is not None:
            frame = frame_id(model, sensor.frame, f"{key}.frame")
        elif sensor.kind == "contact_force":
            if scene.contact is None:
                raise SceneError(
                    f"{key}.body: a contact_force sensor needs contact ([ground], [contact] or [[object]])"
                )
            names = scene.contact.body_names
            if sensor.body not in names:
                raise SceneError(
                    f"{key}.body: '{sensor.body}' has no collision geometry ({name_hint(sensor.body, names)})"
                )
            body = names.index(sensor.body)
        else:  # joint_*: named (globs allowed), else every actuated 1-dof joint
            chosen: list[str] = []
            for pattern in sensor.joints if sensor.joints is not None else actuated:
                found = fnmatch.filter(actuated, pattern) if any(c in pattern for c in "*?[") else [pattern]
                if not found:
                    raise SceneError(
                        f"{key}.joints: '{pattern}' matches no actuated joint (valid: {', '.join(actuated)})"
                    )
                chosen += [name for name in found if name not in chosen]
            joints = [joint_id(model, name, f"{key}.joints", scene.floating_base) for name in chosen]
        placed.append(place(model, sensor, key, frame, joint, body, joints, payloads=payloads))
    wrenches = [
        Wrench(
            frame=frame_id(model, force.frame, f"{where}: force[{i}].frame", moving=True),
            force=np.array(force.force, dtype=float),
            torque=np.array(force.torque, dtype=float),
            local=force.reference == "local",
            scale=force.scale,
        )
        for i, force in enumerate(spec.forces)
    ]
    contact_joints: list[int] = []
    contact_frames: list[int] = []
    if scene.contact is not None:
        for name in scene.contact.body_names:
            jid = next(g.joint for g in scene.contact.geometries if g.body == name)
            fid = model.getFrameId(name) if model.existFrame(name) else -1
            contact_joints.append(int(jid))
            contact_frames.append(fid if fid >= 0 and model.frames[fid].parentJoint == jid else -1)
    return Sensors(
        model,
        placed,
        wrenches=wrenches,
        contact_joints=contact_joints,
        contact_frames=contact_frames,
        actuators=scene.actuators,
    )


def place(
    model: pin.Model,
    spec: SensorSpec,
    key: str,
    frame: int,
    joint: int,
    body: int,
    joints: list[int],
    *,
    payloads: list[tuple[int, pin.Inertia]],
) -> Placed:
    """A sensor on the model, its names resolved to ids (frame, joint, body, joints; -1 or [] where none).

    Args:
        key: the sensor's place in the scene, for messages ("scene.toml: sensor[0]").
        payloads: the scene's payloads: (frame id, inertia in that frame).

    Raises:
        SceneError: noise or bias with a count of components other than one or the sensor's.
    """
    from .exceptions import SceneError

    coordinates: tuple[tuple[int, int, int], ...] = ()
    cut = None
    if spec.kind.startswith("joint_"):
        coordinates = tuple((model.joints[j].idx_q, model.joints[j].idx_v, model.joints[j].nq) for j in joints)
        components = tuple(model.names[j] for j in joints)
    else:
        components = COMPONENTS[spec.kind]
    if spec.kind == "force_torque":
        cut = _cut(model, frame, joint, payloads)
    width = len(components)
    spoilers = {}
    for name in ("noise", "bias"):
        value = getattr(spec, name)
        if isinstance(value, tuple) and len(value) != width:
            raise SceneError(
                f"{key}.{name}: must be one number or {width} (one per component: {' '.join(components)}), got "
                f"{len(value)}"
            )
        spoilers[name] = np.broadcast_to(np.array(value, dtype=float), (width,)).copy()
    return Placed(spec, components, frame=frame, cut=cut, body=body, coordinates=coordinates, **spoilers)


def _cut(model: pin.Model, frame: int, joint: int, payloads: list[tuple[int, pin.Inertia]]) -> Cut:
    """Where a force–torque sensor at a joint (id, frame -1) or a frame (id) cuts the tree (see Cut)."""
    if frame < 0:
        return Cut(joint, True, pin.SE3.Identity())
    sensor = model.frames[frame]
    j = sensor.parentJoint
    at = frame
    if sensor.type == pin.FrameType.BODY:  # a link's frame: the cut is where the link starts
        at = sensor.parentFrame
    if model.frames[at].type == pin.FrameType.JOINT and model.frames[at].parentJoint == j:
        return Cut(j, True, sensor.placement)

    def distal(f: int) -> bool:
        """Whether frame f (on joint j) lies beyond the cut in the frame tree."""
        while f != at:
            parent = model.frames[f].parentFrame
            if model.frames[f].parentJoint != j or parent == f or f == 0:
                return False
            f = parent
        return True

    frames = frozenset(f for f in range(model.nframes) if model.frames[f].parentJoint == j and distal(f))
    inertia = pin.Inertia.Zero()
    for f in sorted(frames):
        inertia = inertia + model.frames[f].placement.act(model.frames[f].inertia)
    for f, payload in payloads:
        if f in frames:
            inertia = inertia + model.frames[f].placement.act(payload)
    children = tuple(
        k
        for k in range(1, model.njoints)
        if model.parents[k] == j
        and model.frames[model.getFrameId(model.names[k], pin.FrameType.JOINT)].parentFrame in frames
    )
    return Cut(j, False, sensor.placement, inertia, children, frames)


def _numbers(value: float | tuple[float, ...]) -> str:
    return f"{value:g}" if isinstance(value, float) else "[" + ", ".join(f"{x:g}" for x in value) + "]"


# ---- the clock and the readings --------------------------------------------------------------------------------
class Ticks:
    """When the rows' sensors tick during a run (the end of every `every`-th step of a row, counted from the row's
    start), and the measurements the kernel took there, until the driver takes them (take()).

    The Python core calls after_step() after each accepted step; the native engine ticks inside its own loop and
    keeps its measurements until take() collects them (`source`).

    Attributes:
        every: steps between ticks.
        done: per row (its index in the run), steps it took before the core started, shape (B,).
        source: the native engine's take_ticks (its ticks since the last call: times (n,), rows (n,), values (n,
            width), the values where take()'s `into` puts them, else in a buffer its next call reuses), or None.
    """

    def __init__(self, every: int, B: int):
        self.every = every
        self.done = np.zeros(B, dtype=np.int64)
        self.source: Any = None
        self._taken: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
        self._borrowed = -1  # the entry of _taken whose values are the source's buffer (-1: none)

    def after_step(self, core: Any, h: float, t: float) -> None:
        """The core accepted a step of h landing at t: measure the running rows whose tick it is."""
        rows = core.rows
        if self.every == 1:
            js = np.arange(len(rows))
        else:
            due = (self.done[rows] + core.steps) % self.every == 0
            if not due.any():
                return
            js = np.flatnonzero(due)
        self._keep(t, rows[js], core.kernel.measure(js, h))

    def start(self, core: Any, js: np.ndarray, h: float) -> None:
        """The first tick of the running rows at positions js, at their current state (a trial step of h)."""
        if len(js):
            self._keep(core.t, core.rows[js], core.kernel.measure_start(js, h))

    def _keep(self, t: float, rows: np.ndarray, values: np.ndarray) -> None:
        self._collect()  # the engine's ticks (before this one)
        self._taken.append((np.full(len(rows), t), np.array(rows, dtype=np.int64), values))

    def _collect(self, into: Any = None) -> None:
        if self.source is not None:
            if self._borrowed >= 0:  # the source's next call reuses its buffer: keep a copy of what it holds
                times, rows, values = self._taken[self._borrowed]
                self._taken[self._borrowed] = (times, rows, values.copy())
                self._borrowed = -1
            times, rows, values = self.source(into)
            if len(times):
                self._taken.append((np.asarray(times), np.asarray(rows, dtype=np.int64), values))
                self._borrowed = len(self._taken) - 1

    def take(self, into: Any = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The ticks since the last call, in time order: times (n,), rows (n,), measurements (n, width) (valid until
        the core steps again: they may be the native engine's buffer). `into(n)`: where the native engine may write
        its n ticks' measurements (an (n, width) array), or None."""
        self._collect(into)
        taken, self._taken = self._taken, []
        self._borrowed = -1
        if len(taken) == 1:
            return taken[0]
        if not taken:
            return np.zeros(0), np.zeros(0, dtype=np.int64), np.zeros((0, 0))
        times, rows, values = zip(*taken, strict=True)
        return np.concatenate(times), np.concatenate(rows), np.concatenate(values)

    def clear(self) -> None:
        self.take()


def strides(sensors: Sensors, dt: float, control_every: int) -> tuple[int, list[int]]:
    """The run's tick period in steps (the greatest common divisor of the sensors') and each sensor's stride in
    those ticks, for steps of dt [s] and control every `control_every` steps (a sensor without a rate reads at
    every control instant).

    Raises:
        InvalidArgumentError: a sensor's period (1 / rate) is not a whole multiple of dt.
    """
    steps = []
    for p in sensors.placed:
        rate = p.spec.rate
        if rate is None:
            steps.append(control_every)
            continue
        k = round(1.0 / (rate * dt))
        if k < 1 or abs(k * dt * rate - 1.0) > 1e-9:
            slower = f"{1.0 / (max(k, 1) * dt):g}" if k >= 1 else f"{1.0 / dt:g}"
            raise InvalidArgumentError(
                f"sensor '{p.spec.name}': rate {rate:g} Hz must read every whole number of steps of dt = {dt:g} s "
                f"(its period 1 / rate = {1.0 / rate:g} s); e.g. rate = {slower} Hz"
            )
        steps.append(k)
    every = math.gcd(*steps)
    return every, [s // every for s in steps]


class Sensing:
    """A run's sensors: the clock its core ticks, the readings, and the readings written into its samples.

    Attributes:
        ticks: what the core measures when (Core.ticks).
        stream: the readings, row by row.
    """

    def __init__(self, sensors: Sensors, *, dt: float, control_every: int, rows: np.ndarray):
        """Args:
        sensors: the system's sensors.
        dt: the step [s]; control_every: steps per control instant (a sensor without a rate reads there).
        rows: each row's index for the seeds.
        """
        every, per = strides(sensors, dt, control_every)
        self.sensors = sensors
        self.ticks = Ticks(every, len(rows))
        self.stream = SensorStream(sensors, per, rows)

    def attach(self, core: Any, h: float, *, fresh: np.ndarray | None = None, done: np.ndarray | None = None) -> None:
        """Tick in this core (stepping.Core) from now on.

        Args:
            h: the step of the first ticks' trial steps [s].
            fresh: positions of the running rows that start now (default all): they read their state now.
            done: per row, the steps it took before this core started (default none).
        """
        self.ticks.clear()
        self.ticks.done = np.zeros(len(self.ticks.done), dtype=np.int64) if done is None else done.copy()
        core.ticks = self.ticks
        kernel = core.kernel
        self.ticks.source = None
        if hasattr(kernel, "set_sensors"):  # the native engine ticks in its own loop
            kernel.set_sensors(self.sensors, self.ticks.every, self.ticks.done)
            self.ticks.source = kernel.take_ticks
        self.ticks.start(core, np.arange(len(core.rows)) if fresh is None else fresh, h)
        self.update()

    def update(self, store: Any = None) -> None:
        """Turn the ticks the core took into readings; with a store (recording.SampleStore), also write each new
        sample's readings: those its sensors hold at its time."""
        if store is None:
            self.stream.push(*self.ticks.take())
            return
        stream, sensors = self.stream, self.sensors
        before = stream.latest.copy()
        readings = store.batch_major("SENSORS")
        direct: dict[int, int] = {}  # per row whose ticks are its latest samples: where they start
        wholes: dict[int, np.ndarray] = {}  # per other row, when every sensor reads at every tick: its readings
        capacity = store.capacity

        def into(b: int, times: np.ndarray) -> np.ndarray | None:
            """Row b's ticks at `times` up to its last new sample are its last new samples (sampling at every tick,
            the default): their readings go straight into the store, and those of its later ticks (a run's last
            tick, whose sample comes after) into the rows after them (taken later, or never). Else, when every
            sensor reads at every tick, into an array of their own, whose rows the samples then take."""
            lo, hi = int(store.sensed[b]), store.samples_of(b)
            if hi <= lo:
                return None
            T = store.T[:, b]
            k = int(np.searchsorted(times, T[hi - 1], side="right"))  # the ticks at or before the last new sample
            start = hi - k
            if (
                not k
                or start < lo
                or start + len(times) > capacity
                or not np.array_equal(T[start:hi], times[:k])
                or (start > lo and T[start - 1] >= times[0])
            ):
                if not stream.every_tick:
                    return None
                wholes[b] = np.empty((len(times), sensors.width))  # (the samples take rows of it below)
                return wholes[b]
            direct[b] = start
            return readings[b, start : start + len(times)]

        def spare(n: int) -> np.ndarray | None:
            """Where the native engine may write its n ticks' measurements: a lone row's rows where into() will most
            likely put its readings (its last new samples, and the rows after them); else they are written over."""
            lo, hi = int(store.sensed[0]), store.samples_of(0)
            start = max(lo, hi - n)
            return readings[0, start : start + n] if store.B == 1 and n and start + n <= capacity else None

        fresh = stream.push(*self.ticks.take(spare), into=into)
        for b in range(store.B):
            lo, hi = int(store.sensed[b]), store.samples_of(b)
            if hi <= lo:
                continue
            block = readings[b, lo:hi]  # (samples, width), contiguous
            new = fresh.get(b)
            if new is None:
                block[:] = before[b]
                store.sensed[b] = hi
                continue
            T = store.T[lo:hi, b]
            whole = wholes.get(b)
            if whole is not None:  # every sensor read at its ticks: each sample's latest readings, all columns at once
                _hold_latest(block, before[b], new[0][0], T, whole)
                store.sensed[b] = hi
                continue
            start = direct.get(b, hi) - lo  # the samples from here on hold the every-tick sensors' readings
            for k, (times, values) in enumerate(new):
                columns = sensors.columns(k)
                if start < len(T) and stream.strides[k] == 1:
                    block[:start, columns] = before[b, columns]  # the samples before this call's first reading
                    continue
                _hold_latest(block[:, columns], before[b, columns], times, T, values)
            store.sensed[b] = hi


def _hold_latest(block: np.ndarray, before: np.ndarray, times: np.ndarray, T: np.ndarray, values: np.ndarray) -> None:
    """Samples at times T (n,) into block (n, w): each one the latest of `values` (k, w), read at `times`
    (k,; ascending) at or before it; `before` (w,) where no reading of this call came yet."""
    index = np.searchsorted(times, T, side="right") - 1  # (times ascend, so index does too)
    held = int(np.searchsorted(index, 0))  # the samples before this call's first reading
    block[:held] = before
    block[held:] = values[index[held:]]


def run_sensing(system: Any, method: Any, dt: float, control_every: int, rows: np.ndarray) -> Sensing | None:
    """The sensors of a run of `method` with steps of dt [s] and control every `control_every` steps, for rows
    `rows` (their indices for the seeds); None for a system without sensors.

    Raises:
        InvalidArgumentError: the method is adaptive (sensors tick every so many fixed steps), or a sensor's rate
            does not divide into steps of dt.
    """
    sensors = getattr(system, "sensors", None)
    if sensors is None:
        return None
    if method.adaptive:
        raise InvalidArgumentError(
            f"sensors tick every so many fixed steps: integrator '{method.name}' is adaptive; choose a fixed-step "
            "integrator (rk4, semi_implicit_euler, ...)"
        )
    return Sensing(sensors, dt=dt, control_every=control_every, rows=rows)
