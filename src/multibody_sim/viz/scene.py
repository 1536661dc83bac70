"""A robot as a meshcat scene: visual meshes per body, poses, recorded animations and the camera, as commands.

Commands are the dictionaries meshcat's viewer decodes (set_object, set_transform, set_animation, ...), plus a few
of our own ("multibody_sim_*") that our page handles: the camera target, the plot beside the view, frame markers.
The simulation never builds geometry; this module builds Pinocchio's visual GeometryModel for viewing only.
"""

from __future__ import annotations

import uuid
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from ..catalog import build_geometry, mesh_roots
from ..exceptions import InvalidArgumentError, UnknownNameError
from ..robot import Robot, check_system
from ..text import printable, safe_name
from ..validation import check_text
from ._deps import ViewerWarning, require
from .meshes import MeshPart, geometry_parts, skeleton_parts

ROOT = "/meshcat/robot"
_SKELETON_COLOR = (0.85, 0.55, 0.2, 1.0)
# three.js typed-array extension codes of msgpack-lite, as meshcat's viewer registers them.
_EXT = {np.dtype(np.int8): (0x11, "Int8Array"), np.dtype(np.int16): (0x13, "Int16Array")}
_EXT[np.dtype(np.uint16)] = (0x14, "Uint16Array")
_EXT.update({np.dtype(np.uint32): (0x16, "Uint32Array"), np.dtype(np.float32): (0x17, "Float32Array")})
# Camera views: (azimuth, elevation) [deg] of the direction from the target to the camera, x forward and z up
# (REP 103). The default is a three-quarter view from the front left, slightly above; "top" stops short of the
# vertical, where the camera's up direction (z) would be undefined. meshcat's field of view is 75 deg.
CAMERA_VIEWS = {
    "default": (40.0, 22.0),
    "front": (0.0, 12.0),
    "back": (180.0, 12.0),
    "left": (90.0, 12.0),
    "right": (-90.0, 12.0),
    "top": (0.0, 89.0),
}
_CAMERA_DISTANCE = 1.7  # in bounding-sphere radii: the sphere overestimates the robot, which still fits
_CAMERA_SAMPLES = 60  # frames sampled to frame the whole motion
_REACH_FACTOR = 1.5
# The farthest from the world origin a body, a contact point or the camera may be in a view [m]: meshcat sends
# positions as 32-bit floats (6 cm apart here; beyond 3.4e38 they overflow) and three.js squares distances.
VIEW_REACH = 1e6


class MissingVisualsWarning(ViewerWarning):
    """The robot is drawn without (some of) its URDF's visual meshes."""


@dataclass(frozen=True)
class _Visual:
    path: str  # meshcat path of the geometry node
    joint: int  # Pinocchio joint whose frame carries it
    placement: np.ndarray  # 4x4, in the joint frame
    parts: list[MeshPart]


class RobotScene:
    """The meshcat scene of one robot: meshes grouped under one node per moving body.

    Only body nodes move (one set_transform per body per frame); geometry nodes keep their fixed placement.

    Attributes:
        robot: the robot shown.
        joints: Pinocchio joint ids that carry geometry (0, the world, for geometry welded to it).
        body_paths: meshcat path of each entry of `joints`.
        notes: what could not be drawn as the URDF says (also issued as MissingVisualsWarning).
    """

    def __init__(self, robot: Robot):
        self.robot = check_system(robot, "robot")
        self.model = robot.model
        self._data = self.model.createData()
        self.notes: list[str] = []
        contact = getattr(robot, "contact", None)
        objects_only = getattr(getattr(robot, "spec", None), "robot", False) is None  # a scene of objects only
        visuals = [] if objects_only else self._visuals()
        if not objects_only and not any(v.parts for v in visuals):
            if not self.notes:
                self.notes.append(f"{robot.name}: the URDF has no visual geometry; drawing a skeleton of its joints")
            visuals = self._skeleton()
        for note in self.notes:  # they quote names and mesh paths from the URDF: escaped for any terminal
            warnings.warn(printable(note), MissingVisualsWarning, stacklevel=2)
        # A contact scene's objects and declared collision geometry move with their bodies; the ground is a fixture
        # (drawn, never framed by the camera: it would shrink the robot to a dot).
        self.fixtures: list[_Visual] = []
        if contact is not None:
            moving, self.fixtures = _contact_visuals(self.model, contact)
            visuals = list(visuals) + moving
        self.visuals = [v for v in visuals if v.parts]
        self.joints = sorted({v.joint for v in self.visuals})
        self.body_paths = [f"{ROOT}/{_node_name(self.model.names[j])}" for j in self.joints]
        self._path_of = dict(zip(self.joints, self.body_paths, strict=True))

    # ---- geometry -------------------------------------------------------------------------------------
    def _visuals(self) -> list[_Visual]:
        source = self.robot.source
        urdf_path = source.get("urdf_path")
        if not urdf_path:
            self.notes.append(f"{self.robot.name}: no URDF recorded for this robot; drawing a skeleton of its joints")
            return []
        path = Path(urdf_path)
        roots = allowed_roots(self.robot)
        try:
            geometry_model = build_geometry(source, self.model, "visual", **_cheap_mesh_loader())
        except (RuntimeError, ValueError) as exc:  # e.g. a mesh file that is not there
            first = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            self.notes.append(f"{path}: Pinocchio cannot build the visual model ({first}); drawing a skeleton")
            return []
        visuals = []
        for index, obj in enumerate(geometry_model.geometryObjects):
            joint = int(obj.parentJoint)
            name = f"{_node_name(self.model.names[joint])}/{index:03d}_{_node_name(obj.name)}"
            parts = geometry_parts(obj, roots)
            visuals.append(_Visual(f"{ROOT}/{name}", joint, np.asarray(obj.placement.homogeneous), parts))
        return visuals

    def _skeleton(self) -> list[_Visual]:
        model = self.model
        pin.forwardKinematics(model, self._data, pin.neutral(model))
        reach = [np.linalg.norm(self._data.oMi[j].translation) for j in range(model.njoints)]
        size = max(0.02, 0.04 * max(reach + [0.1]))
        visuals = []
        for joint in range(1, model.njoints):
            children = [
                model.jointPlacements[c].translation for c in range(1, model.njoints) if model.parents[c] == joint
            ]
            inertia = model.inertias[joint]
            com = np.asarray(inertia.lever) if inertia.mass > 0 else None
            parts = skeleton_parts(children, com, size, _SKELETON_COLOR)
            name = f"{_node_name(model.names[joint])}/skeleton"
            visuals.append(_Visual(f"{ROOT}/{name}", joint, np.eye(4), parts))
        return visuals

    # ---- kinematics -----------------------------------------------------------------------------------
    def placements(self, q: np.ndarray, t: float | None = None) -> list[np.ndarray]:
        """World placement (4x4) of each body in `joints` at configuration q (at time t [s], for messages).

        Raises:
            InvalidArgumentError: a body is farther than VIEW_REACH from the world origin (or not finite).
        """
        pin.forwardKinematics(self.model, self._data, np.asarray(q, dtype=float))
        poses = [np.asarray(self._data.oMi[j].homogeneous) for j in self.joints]
        far = np.abs([pose[:3, 3] for pose in poses]).max(axis=1)
        if not np.all(far <= VIEW_REACH):  # NaN fails too
            b = int(np.argmax(np.where(far <= VIEW_REACH, -1.0, np.nan_to_num(far, nan=np.inf))))
            when = "" if t is None else f" at t = {t:.6g} s"
            raise InvalidArgumentError(
                f"the body of joint '{safe_name(self.model.names[self.joints[b]])}' is {far[b]:.3g} m from the world "
                f"origin{when}, beyond the {VIEW_REACH:g} m a view can show (positions reach the page as 32-bit "
                "floats): the motion left the scene (it diverged, or the file was edited)"
            )
        return poses

    # ---- commands -------------------------------------------------------------------------------------
    def setup_commands(self) -> list[dict[str, Any]]:
        """Clear the robot's node, then create every mesh under its body node, in a fixed order."""
        umsgpack = require("umsgpack", "the meshcat viewer")
        commands: list[dict[str, Any]] = [{"type": "delete", "path": ROOT}]
        for visual in [*self.visuals, *self.fixtures]:
            commands.append(transform_command(visual.path, visual.placement))
            for k, part in enumerate(visual.parts):
                commands.append(_mesh_command(umsgpack, f"{visual.path}/{k}", part))
        return commands

    def pose_commands(self, q: np.ndarray) -> list[dict[str, Any]]:
        """One set_transform per body, placing the robot at configuration q."""
        return [transform_command(p, m) for p, m in zip(self.body_paths, self.placements(q), strict=True)]

    def animation_command(
        self,
        times: np.ndarray,
        Q: np.ndarray,
        *,
        play: bool = True,
        loop: bool = True,
        speed: float = 1.0,
        seek: float | None = None,
    ) -> dict[str, Any]:
        """A meshcat animation (time slider, play/pause) of the bodies through the frames (times, Q).

        Args:
            times: frame times [s], shape (n,), increasing; the animation starts at times[0].
            Q: configurations at those times, shape (n, nq).
            play: start playing when loaded.
            loop: repeat (else stop at the end).
            speed: playback speed (1 = real time).
            seek: show this animation time [s] when loaded (with play=False).
        """
        rotation = require("scipy.spatial.transform", "the meshcat viewer").Rotation
        poses = np.array([self.placements(q, t) for t, q in zip(np.asarray(times, dtype=float), Q, strict=True)])
        keys = (np.asarray(times, dtype=float) - float(times[0])).tolist()  # clip fps is 1: keys in seconds
        animations = []
        for b, path in enumerate(self.body_paths):
            if self.joints[b] == 0:
                continue  # the world does not move
            positions = poses[:, b, :3, 3]
            quaternions = rotation.from_matrix(poses[:, b, :3, :3]).as_quat()  # x y z w, three.js's order
            # Consecutive keys on the same hemisphere: the interpolation then takes the short way round.
            signs = np.sign(np.einsum("ij,ij->i", quaternions[1:], quaternions[:-1]))
            signs[signs == 0] = 1.0
            quaternions[1:] *= np.cumprod(signs)[:, None]
            tracks = [
                {"name": ".position", "type": "vector3", "keys": _keys(keys, positions)},
                {"name": ".quaternion", "type": "quaternion", "keys": _keys(keys, quaternions)},
            ]
            animations.append({"path": path, "clip": {"fps": 1, "name": "default", "tracks": tracks}})
        options: dict[str, Any] = {"play": bool(play), "repetitions": 1_000_000_000 if loop else 1}
        options["multibody_sim_speed"] = float(speed)
        options["multibody_sim_start"] = float(times[0])  # animation time 0 is this trajectory time [s]
        if seek is not None:
            options["multibody_sim_seek"] = float(seek)
        return {"type": "set_animation", "path": "", "animations": animations, "options": options}

    def camera_command(
        self,
        Q: np.ndarray,
        *,
        view: str = "default",
        position: Any = None,
        target: Any = None,
        times: np.ndarray | None = None,
    ) -> dict[str, Any]:
        """Aim the camera at the box swept by the robot over the configurations Q (shape (n, nq)).

        Args:
            Q: configurations to frame, shape (n, nq).
            times: their times [s], shape (n,), for messages; None names no time.
            view: a name of CAMERA_VIEWS: the direction the camera looks from, at a distance that fits the box.
            position: the camera's position [m], world frame (3,); None places it by `view`.
            target: the point it looks at [m], world frame (3,); None takes the box's centre.

        Raises:
            UnknownNameError: `view` is not a camera view.
            InvalidArgumentError: position or target is not 3 numbers within VIEW_REACH, or they coincide; a body
                is beyond VIEW_REACH.
        """
        fixed_position, fixed_target = check_camera(view, position, target)
        Q = np.atleast_2d(np.asarray(Q, dtype=float))
        picks = np.unique(np.linspace(0, len(Q) - 1, min(len(Q), _CAMERA_SAMPLES)).round().astype(int))
        corners_by_joint: dict[int, list[np.ndarray]] = {j: [] for j in self.joints}
        for visual in self.visuals:
            for part in visual.parts:
                lo, hi = part.bounds()
                box = np.array([[x, y, z, 1.0] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
                corners_by_joint[visual.joint].append(box @ visual.placement.T)
        local = [np.vstack(corners_by_joint[j]) for j in self.joints]
        moving = [b for b, j in enumerate(self.joints) if j > 0]
        root = moving[0] if moving else 0
        # A body that drifts far from the rest (a finger sliding off along an unlimited prismatic joint) would
        # shrink the robot to a dot: keep bodies within REACH_FACTOR times the first frame's reach of the root.
        reach: float | None = None
        points = []
        for i in picks:
            poses = self.placements(Q[i], None if times is None else float(times[i]))
            world = [(corners @ pose.T)[:, :3] for corners, pose in zip(local, poses, strict=True)]
            spread = [float(np.linalg.norm(w - poses[root][:3, 3], axis=1).max()) for w in world]
            if reach is None:
                reach = max(max(spread), 0.05)
            points += [w for b, w in enumerate(world) if self.joints[b] == 0 or spread[b] <= _REACH_FACTOR * reach]
        cloud = np.vstack(points)
        lo, hi = cloud.min(axis=0), cloud.max(axis=0)
        centre = (lo + hi) / 2 if fixed_target is None else fixed_target
        radius = max(float(np.linalg.norm(hi - lo)) / 2, 0.05)
        if fixed_position is None:
            azimuth, elevation = np.radians(CAMERA_VIEWS[view])
            direction = np.array(
                [np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation)]
            )
            fixed_position = centre + _CAMERA_DISTANCE * radius * direction
        distance = float(np.linalg.norm(fixed_position - centre))
        if distance < 1e-6:
            raise InvalidArgumentError("the camera position and target coincide: the camera would look nowhere")
        return {
            "type": "multibody_sim_camera",
            "target": centre.tolist(),
            "position": fixed_position.tolist(),
            "near": distance / 100,
            "far": 20 * distance + radius,
        }


# Colours of contact geometry: objects (a warm grey-blue), declared robot collision shapes (translucent orange), the
# ground (a light grey slab GROUND_SIZE wide, GROUND_THICKNESS thick, its top face on the plane).
_OBJECT_COLOR = (0.35, 0.45, 0.6, 1.0)
_COLLISION_COLOR = (0.95, 0.55, 0.1, 0.6)
_GROUND_COLOR = (0.82, 0.82, 0.8, 1.0)
GROUND_SIZE = 6.0
GROUND_THICKNESS = 0.01


def _contact_visuals(model: pin.Model, contact: Any) -> tuple[list[_Visual], list[_Visual]]:
    """(moving, fixtures): a contact scene's objects and declared collision shapes on their bodies, and the ground
    (not the URDF's collision shapes: the robot's visual meshes stand for them)."""
    import coal

    moving, fixtures = [], []
    for index, geometry in enumerate(contact.geometries):
        if geometry.from_urdf:  # the URDF's collision shapes: the robot's visual meshes show them
            continue
        if geometry.kind == "halfspace":
            height = geometry.dimensions[0]
            shape = coal.Box(GROUND_SIZE, GROUND_SIZE, GROUND_THICKNESS)
            placement = pin.SE3(np.eye(3), np.array([0.0, 0.0, height - GROUND_THICKNESS / 2]))
            obj = pin.GeometryObject("ground", 0, 0, placement, shape)
            obj.meshColor = np.array(_GROUND_COLOR)
            fixtures.append(
                _Visual(f"{ROOT}/ground/{index:03d}", 0, np.asarray(placement.homogeneous), geometry_parts(obj, []))
            )
            continue
        obj = pin.GeometryObject(geometry.body, geometry.joint, geometry.joint, geometry.placement, geometry.shape)
        is_object = model.names[geometry.joint] == geometry.body
        obj.meshColor = np.array(_OBJECT_COLOR if is_object else _COLLISION_COLOR)
        name = f"{_node_name(model.names[geometry.joint])}/contact_{index:03d}_{_node_name(geometry.body)}"
        moving.append(
            _Visual(
                f"{ROOT}/{name}", geometry.joint, np.asarray(geometry.placement.homogeneous), geometry_parts(obj, [])
            )
        )
    return moving, fixtures


def _cheap_mesh_loader() -> dict[str, Any]:
    """Pinocchio loads every mesh into a collision structure we never use: the cheapest one (AABB) halves the
    time it takes."""
    try:
        import coal

        return {"mesh_loader": coal.MeshLoader(coal.NODE_TYPE.BV_AABB)}
    except (ImportError, AttributeError):
        return {}


def allowed_roots(robot: Robot) -> list[Path]:
    """Folders the robot's meshes may come from: the URDF's folder, its package directories and allowed roots,
    the catalog's package directory."""
    return mesh_roots(robot.source)


def pack(command: dict[str, Any]) -> bytes:
    """A command as the msgpack bytes meshcat's viewer decodes. Numbers go as 32-bit floats: what three.js
    keeps of them anyway (animation tracks are Float32Arrays), at half the size."""
    umsgpack = require("umsgpack", "the meshcat viewer")
    return bytes(umsgpack.packb(command, force_float_precision="single"))


def transform_command(path: str, matrix: np.ndarray) -> dict[str, Any]:
    """meshcat's set_transform: a 4x4 homogeneous matrix, column-major."""
    return {"type": "set_transform", "path": path, "matrix": np.asarray(matrix, dtype=float).T.reshape(-1).tolist()}


def frame_marker(index: int, time: float | None) -> dict[str, Any]:
    """Our marker sent after each displayed frame: the page records it (tests wait for it)."""
    return {"type": "multibody_sim_frame", "path": "", "index": int(index), "time": time}


def check_camera(
    view: Any, position: Any = None, target: Any = None, *, prefix: str = ""
) -> tuple[np.ndarray | None, np.ndarray | None]:
    """A camera's view, position and target checked before any work (camera_command's, export_video's and
    `play --video`'s arguments): the position and target as points [m], None where not given.

    Args:
        view: a name of CAMERA_VIEWS.
        position, target: 3 numbers x y z [m] within ±VIEW_REACH, or None.
        prefix: "--" names them as the command line's options (--camera, --camera-position, --camera-target).

    Raises:
        UnknownNameError: `view` is not a camera view.
        InvalidArgumentError: position or target is not 3 numbers within ±VIEW_REACH, or they coincide.
    """
    check_text(view, f"{prefix}camera", optional=False)
    if view not in CAMERA_VIEWS:
        what = f"{prefix}camera: unknown view" if prefix else "unknown camera view"
        raise UnknownNameError(f"{what} '{view}' (choose from: {', '.join(CAMERA_VIEWS)})")
    position_name, target_name, both = "the camera position", "the camera target", "the camera position and target"
    if prefix:
        position_name, target_name = f"{prefix}camera-position", f"{prefix}camera-target"
        both = f"{position_name} and {target_name}"
    fixed_position = None if position is None else _point(position, position_name)
    fixed_target = None if target is None else _point(target, target_name)
    if fixed_position is not None and fixed_target is not None and np.linalg.norm(fixed_position - fixed_target) < 1e-6:
        raise InvalidArgumentError(f"{both} coincide: the camera would look nowhere")
    return fixed_position, fixed_target


def _point(value: Any, subject: str) -> np.ndarray:
    """A point in space: 3 numbers [m] within ±VIEW_REACH."""
    try:
        point = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        point = np.array([np.nan])
    if point.shape != (3,) or not np.all(np.isfinite(point)):
        raise InvalidArgumentError(f"{subject} must be 3 finite numbers (x y z in metres), got {value!r}")
    if np.abs(point).max() > VIEW_REACH:
        raise InvalidArgumentError(
            f"{subject} must lie within {VIEW_REACH:g} m of the world origin (positions reach the page as 32-bit "
            f"floats), got {' '.join(f'{x:g}' for x in point)}"
        )
    return point


def _keys(times: list[float], values: np.ndarray) -> list[dict[str, Any]]:
    return [{"time": t, "value": v} for t, v in zip(times, values.tolist(), strict=True)]


def _mesh_command(umsgpack: Any, path: str, part: MeshPart) -> dict[str, Any]:
    ids = [str(uuid.uuid5(uuid.NAMESPACE_URL, f"multibody-sim:{path}:{kind}")) for kind in ("g", "m", "o")]
    index_type = np.uint16 if len(part.vertices) < 2**16 else np.uint32
    normals = np.clip(np.round(part.normals * 127.0), -127, 127).astype(np.int8)
    # Positions as 16-bit integers over the part's box, scaled back by the object's matrix: half the bytes of
    # float32, at a resolution of 1/65535 of the part's size (5 um on a 30 cm link). The scale is uniform, so
    # normals need no correction.
    vertices = part.vertices.astype(float)
    center = (vertices.min(axis=0) + vertices.max(axis=0)) / 2 if len(vertices) else np.zeros(3)
    scale = max(float(np.abs(vertices - center).max()) if len(vertices) else 0.0, 1e-9) / 32767.0
    quantized = np.clip(np.round((vertices - center) / scale), -32767, 32767).astype(np.int16)
    matrix = [scale, 0.0, 0.0, 0.0, 0.0, scale, 0.0, 0.0, 0.0, 0.0, scale, 0.0, *center.tolist(), 1.0]
    geometry = {
        "uuid": ids[0],
        "type": "BufferGeometry",
        "data": {
            "attributes": {
                "position": _typed(umsgpack, quantized, 3),
                "normal": _typed(umsgpack, normals, 3, normalized=True),
            },
            "index": _typed(umsgpack, part.faces.astype(index_type), 1),
        },
    }
    r, g, b, a = part.color
    material = {
        "uuid": ids[1],
        "type": "MeshPhongMaterial",
        "color": (round(r * 255) << 16) | (round(g * 255) << 8) | round(b * 255),
        "side": 2,  # both faces: some meshes wind triangles inconsistently
        "transparent": a < 1.0,
        "opacity": a,
        "shininess": 30,
    }
    obj = {"uuid": ids[2], "type": "Mesh", "geometry": ids[0], "material": ids[1], "matrix": matrix}
    return {
        "type": "set_object",
        "path": path,
        "object": {
            "metadata": {"version": 4.5, "type": "Object"},
            "geometries": [geometry],
            "materials": [material],
            "object": obj,
        },
    }


def _typed(umsgpack: Any, array: np.ndarray, item_size: int, normalized: bool = False) -> dict[str, Any]:
    code, name = _EXT[array.dtype]
    data = umsgpack.Ext(code, np.ascontiguousarray(array).tobytes())
    return {"itemSize": item_size, "type": name, "array": data, "normalized": normalized}


def _node_name(name: str) -> str:
    """A meshcat path element: no slashes, never empty."""
    return name.replace("/", "_") or "_"
