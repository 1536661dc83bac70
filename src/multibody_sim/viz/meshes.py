"""Visual geometry as plain triangle meshes: mesh files and primitives converted once, with trimesh.

Every visual becomes indexed triangles with their own normals and one colour per part, sent to meshcat as a
three.js BufferGeometry. Converting ourselves (rather than handing meshcat the COLLADA file) renders meshes that
meshcat's own loader shows with missing parts (ur5's nested materials), keeps the files' colours, and shares
vertices, which keeps the HTML export small.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from ..exceptions import ModelError
from ._deps import require

# Vertices closer than this are merged when they also share a normal [m]: far below what a screen shows.
_MERGE_RESOLUTION = 1e-6
_CYLINDER_SECTIONS = 32
_PRIMITIVES = ("Box", "Sphere", "Cylinder", "Capsule", "Cone", "Ellipsoid", "Plane", "Halfspace")


@dataclass(frozen=True)
class MeshPart:
    """Triangles of one colour, in the frame of their geometry object (URDF scale applied).

    Attributes:
        vertices: positions [m], shape (n, 3), float32.
        normals: unit normals, shape (n, 3), float32.
        faces: vertex indices, shape (m, 3), counter-clockwise seen from outside.
        color: RGBA in [0, 1].
    """

    vertices: np.ndarray
    normals: np.ndarray
    faces: np.ndarray
    color: tuple[float, float, float, float]

    def bounds(self) -> np.ndarray:
        """Axis-aligned bounding box, shape (2, 3): [min, max]."""
        return np.array([self.vertices.min(axis=0), self.vertices.max(axis=0)], dtype=float)


def geometry_parts(geometry_object: Any, allowed_roots: list[Path]) -> list[MeshPart]:
    """The triangle meshes of one Pinocchio GeometryObject (mesh file or primitive shape).

    Args:
        geometry_object: a pinocchio.GeometryObject of the visual model.
        allowed_roots: folders a mesh file must lie in (the URDF's folder and the package directories).

    Raises:
        ModelError: a mesh file lies outside the allowed folders or cannot be read.
    """
    trimesh = require("trimesh", "visual meshes")
    color = tuple(float(c) for c in geometry_object.meshColor)
    shape = geometry_object.geometry
    kind = type(shape).__name__
    path = geometry_object.meshPath
    if kind not in _PRIMITIVES:  # a mesh (its coal type depends on the loader Pinocchio was given)
        if not path or path.upper() == path and "/" not in path:  # "BOX", "SPHERE", ... name primitives
            return []
        mesh_file = _checked_mesh_path(Path(path), allowed_roots)
        scale = np.asarray(geometry_object.meshScale, dtype=float)
        use_file_colors = not geometry_object.overrideMaterial
        return _file_parts(trimesh, mesh_file, scale, color, use_file_colors)
    if kind == "Box":
        mesh = trimesh.creation.box(extents=2.0 * np.asarray(shape.halfSide, dtype=float))
    elif kind == "Sphere":
        mesh = trimesh.creation.icosphere(subdivisions=3, radius=float(shape.radius))
    elif kind == "Cylinder":
        mesh = trimesh.creation.cylinder(
            radius=float(shape.radius), height=2.0 * float(shape.halfLength), sections=_CYLINDER_SECTIONS
        )
    elif kind == "Capsule":
        mesh = trimesh.creation.capsule(
            height=2.0 * float(shape.halfLength), radius=float(shape.radius), count=[24, 24]
        )
    elif kind == "Cone":
        mesh = trimesh.creation.cone(radius=float(shape.radius), height=2.0 * float(shape.halfLength))
        mesh.apply_translation([0.0, 0.0, -float(shape.halfLength)])  # trimesh's cone starts at z = 0
    elif kind == "Ellipsoid":
        mesh = trimesh.creation.icosphere(subdivisions=3, radius=1.0)
        mesh.apply_scale(np.asarray(shape.radii, dtype=float))
    else:
        return []  # planes and half-spaces have no finite surface to draw
    # Primitives: hard edges (box, cylinder rims) get their own vertices so that shading stays flat there.
    mesh = mesh.smooth_shaded
    return [_part(mesh.vertices, mesh.vertex_normals, mesh.faces, color)]


def skeleton_parts(
    child_offsets: list[np.ndarray], center_of_mass: np.ndarray | None, radius: float, color: tuple[float, ...]
) -> list[MeshPart]:
    """Stand-in geometry for a body without visuals: a ball at its joint, rods to its children and its centre of mass.

    Args:
        child_offsets: positions of the child joints in the body frame [m], each shape (3,).
        center_of_mass: the body's centre of mass in its frame [m], or None.
        radius: ball radius [m]; rods are a third of it.
        color: RGBA in [0, 1].
    """
    trimesh = require("trimesh", "visual meshes")
    meshes = [trimesh.creation.icosphere(subdivisions=2, radius=radius)]
    ends = [np.asarray(p, dtype=float) for p in child_offsets]
    if center_of_mass is not None and np.linalg.norm(center_of_mass) > 1e-9:
        ends.append(np.asarray(center_of_mass, dtype=float))
        ball = trimesh.creation.icosphere(subdivisions=2, radius=0.8 * radius)
        ball.apply_translation(center_of_mass)
        meshes.append(ball)
    for end in ends:
        if np.linalg.norm(end) > 1e-9:
            meshes.append(trimesh.creation.cylinder(radius=radius / 3, segment=[np.zeros(3), end], sections=16))
    merged = trimesh.util.concatenate(meshes).smooth_shaded
    return [_part(merged.vertices, merged.vertex_normals, merged.faces, tuple(color))]  # type: ignore[arg-type]


def _checked_mesh_path(path: Path, allowed_roots: list[Path]) -> Path:
    resolved = path.resolve()
    roots = [root.resolve() for root in allowed_roots]
    if not any(resolved.is_relative_to(root) for root in roots):
        raise ModelError(
            f"mesh '{path}' lies outside the allowed folders ({', '.join(str(r) for r in roots)}); "
            "add its folder to package_dirs"
        )
    if not resolved.is_file():
        raise ModelError(f"mesh '{path}' does not exist")
    return resolved


def _file_parts(
    trimesh: Any, path: Path, scale: np.ndarray, urdf_color: tuple[float, ...], use_file_colors: bool
) -> list[MeshPart]:
    try:
        scene = trimesh.load(str(path), force="scene", process=False)
    except Exception as exc:  # trimesh and its format readers raise anything from ValueError to KeyError
        raise ModelError(f"cannot read mesh '{path}' ({type(exc).__name__}: {exc})") from None
    scaling = np.diag([*scale, 1.0])
    by_color: dict[tuple[float, ...], list[MeshPart]] = {}
    for node in scene.graph.nodes_geometry:
        transform, name = scene.graph[node]
        mesh = scene.geometry.get(name)
        if mesh is None or not hasattr(mesh, "faces") or len(mesh.faces) == 0:
            continue  # points, paths and empty meshes draw nothing
        own = _file_color(mesh) if use_file_colors else None
        color = own if own is not None else urdf_color
        part = _transformed_part(mesh, scaling @ transform, color)
        by_color.setdefault(_color_key(color), []).append(part)
    return [_concatenate(parts) for parts in by_color.values()]


def _file_color(mesh: Any) -> tuple[float, float, float, float] | None:
    """The mesh file's own colour (COLLADA/OBJ material), or None when it has none (STL)."""
    visual = mesh.visual
    material = getattr(visual, "material", None)
    if material is not None:
        main = np.asarray(material.main_color, dtype=float)
        return tuple(main / 255.0)  # type: ignore[return-value]
    if getattr(visual, "kind", None) in ("face", "vertex"):
        colors = np.asarray(visual.face_colors if visual.kind == "face" else visual.vertex_colors, dtype=float)
        return tuple(colors.mean(axis=0) / 255.0)  # type: ignore[return-value]
    return None


def _transformed_part(mesh: Any, matrix: np.ndarray, color: tuple[float, ...]) -> MeshPart:
    linear = matrix[:3, :3]
    vertices = np.asarray(mesh.vertices, dtype=float) @ linear.T + matrix[:3, 3]
    # Normals transform with the inverse transpose (non-uniform URDF scales); faces flip under a mirror.
    normals = np.asarray(mesh.vertex_normals, dtype=float) @ np.linalg.inv(linear)
    faces = np.asarray(mesh.faces, dtype=np.int64)
    if np.linalg.det(linear) < 0:
        faces = faces[:, ::-1]
    return _part(vertices, normals, faces, color)


def _part(vertices: np.ndarray, normals: np.ndarray, faces: np.ndarray, color: tuple[float, ...]) -> MeshPart:
    """Normalize normals and share vertices that have the same position and normal."""
    vertices = np.asarray(vertices, dtype=float)
    normals = np.asarray(normals, dtype=float)
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = np.divide(normals, length, out=np.zeros_like(normals), where=length > 0)
    key = np.hstack([np.round(vertices / _MERGE_RESOLUTION), np.round(normals * 127.0)]).astype(np.int64)
    first, inverse = _unique_rows(key)
    faces = inverse[np.asarray(faces, dtype=np.int64)]
    return MeshPart(
        vertices=vertices[first].astype(np.float32),
        normals=normals[first].astype(np.float32),
        faces=faces,
        color=tuple(float(c) for c in color),  # type: ignore[arg-type]
    )


def _unique_rows(key: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(index of each distinct row's first occurrence, distinct-row number of every row); np.unique(axis=0)
    does the same several times slower."""
    if len(key) == 0:
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
    order = np.lexsort(key.T[::-1])
    ordered = key[order]
    starts = np.ones(len(key), dtype=bool)
    starts[1:] = np.any(ordered[1:] != ordered[:-1], axis=1)
    inverse = np.empty(len(key), dtype=np.int64)
    inverse[order] = np.cumsum(starts) - 1
    return order[starts], inverse


def _concatenate(parts: list[MeshPart]) -> MeshPart:
    if len(parts) == 1:
        return parts[0]
    offsets = np.cumsum([0] + [len(p.vertices) for p in parts[:-1]])
    return MeshPart(
        vertices=np.vstack([p.vertices for p in parts]),
        normals=np.vstack([p.normals for p in parts]),
        faces=np.vstack([p.faces + offset for p, offset in zip(parts, offsets, strict=True)]),
        color=parts[0].color,
    )


def _color_key(color: tuple[float, ...]) -> tuple[float, ...]:
    return tuple(round(c * 255) for c in color)
