"""What a robot description and the model built from it must satisfy before anything is simulated: a URDF's tree,
joints, numbers and mesh paths; finite model values; body inertias; a regular mass matrix."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from ..exceptions import ModelError
from ..robot import Robot
from .reading import MAX_DOFS, resolve_in_roots

SUPPORTED_JOINT_TYPES = ("continuous", "fixed", "floating", "planar", "prismatic", "revolute")


def check_urdf(
    description: Any, path: Path, *, package_dirs: list[Path], allowed_roots: list[Path] | None = None
) -> None:
    """Refuse what Pinocchio would mis-read: unsupported joints, broken trees, bad numbers, escaping URIs.

    Args:
        description: yourdfpy's URDF, from parse_urdf.
        path: the URDF file (named in messages).
        package_dirs: the URDF's folder and the folders package:// URIs resolve against.
        allowed_roots: further folders mesh paths may resolve into.
    """
    robot = description.robot
    links = {link.name for link in robot.links}
    if not robot.links:
        raise ModelError(f"{path}: the robot has no <link>")
    if len(links) != len(robot.links):
        raise ModelError(f"{path}: duplicate link names")
    joint_names = [joint.name for joint in robot.joints]
    if len(set(joint_names)) != len(joint_names):
        repeated = sorted({str(n) for n in joint_names if joint_names.count(n) > 1})
        raise ModelError(f"{path}: duplicate joint names ({', '.join(repeated)})")
    children: dict[str, str] = {}
    for joint in robot.joints:
        if joint.type not in SUPPORTED_JOINT_TYPES:
            raise ModelError(
                f"{path}: joint '{joint.name}' has unsupported type '{joint.type}' "
                f"(supported: {', '.join(SUPPORTED_JOINT_TYPES)})"
            )
        for role, link in (("parent", joint.parent), ("child", joint.child)):
            if link not in links:
                raise ModelError(f"{path}: joint '{joint.name}' names {role} link '{link}', which does not exist")
        if joint.child in children:
            raise ModelError(
                f"{path}: link '{joint.child}' is the child of two joints "
                f"('{children[joint.child]}' and '{joint.name}')"
            )
        children[joint.child] = joint.name
        if (
            joint.type in ("revolute", "continuous", "prismatic")
            and joint.axis is not None
            and not (np.all(np.isfinite(joint.axis)) and np.linalg.norm(joint.axis) > 1e-9)
        ):
            raise ModelError(f"{path}: joint '{joint.name}' has a zero or non-finite axis")
        _check_joint_numbers(joint, path)
    roots = links - set(children)
    if not roots:
        raise ModelError(f"{path}: the joints form a cycle (every link has a parent joint)")
    if len(roots) != 1:
        raise ModelError(f"{path}: the links must form one tree, found {len(roots)} roots ({', '.join(sorted(roots))})")
    unreachable = links - _descendants(next(iter(roots)), robot.joints)
    if unreachable:  # one root, yet a loop elsewhere: those links each have a parent but never reach the root
        raise ModelError(
            f"{path}: the joints form a cycle (links {', '.join(sorted(unreachable))} are not connected to the root)"
        )
    welded = {joint.child for joint in robot.joints if joint.type == "fixed"}
    package_roots = [Path(os.path.realpath(p)) for p in package_dirs]
    mesh_roots = package_roots + [Path(os.path.realpath(p)) for p in allowed_roots or []]
    checked: set[tuple[str, str]] = set()  # visual and collision geometry often share files

    def check_uri(uri: str, kind: str) -> None:
        if (uri, kind) not in checked:
            resolve_in_roots(uri, path, package_roots, mesh_roots, kind)
            checked.add((uri, kind))

    for link in robot.links:
        _check_inertial(link, path, welded=link.name in welded)
        for kind, elements in (("visual", link.visuals), ("collision", link.collisions)):
            for element in elements:
                _check_geometry(element, kind, link.name, path)
                mesh = getattr(element.geometry, "mesh", None) if element.geometry is not None else None
                if mesh is not None and mesh.filename:
                    check_uri(mesh.filename, "mesh")
    # Textures are files a viewer would read, like meshes: the same folders bound them.
    materials = [*robot.materials, *(v.material for link in robot.links for v in link.visuals)]
    for material in materials:
        texture = getattr(material, "texture", None) if material is not None else None
        if texture is not None and texture.filename:
            check_uri(texture.filename, "texture")


def _descendants(root: str, joints: list[Any]) -> set[str]:
    """The links reachable from root through the joints (root included), without recursion."""
    below: dict[str, list[str]] = {}
    for joint in joints:
        below.setdefault(joint.parent, []).append(joint.child)
    seen, stack = {root}, [root]
    while stack:
        for child in below.get(stack.pop(), []):
            if child not in seen:
                seen.add(child)
                stack.append(child)
    return seen


def _check_joint_numbers(joint: Any, path: Path) -> None:
    """Origins, limits and dynamics that Pinocchio would take as they are (NaN, inverted, negative)."""
    where = f"{path}: joint '{joint.name}'"
    if joint.origin is not None and not np.all(np.isfinite(joint.origin)):
        raise ModelError(f"{where} has a non-finite origin")
    limit = joint.limit
    if limit is not None:
        for attribute in ("lower", "upper", "effort", "velocity"):
            value = getattr(limit, attribute)
            if value is not None and not np.isfinite(value):
                raise ModelError(f"{where} has {attribute} limit {value}; it must be finite")
        for attribute in ("effort", "velocity"):
            value = getattr(limit, attribute)
            if value is not None and value < 0:
                raise ModelError(f"{where} has {attribute} limit {value}; it must be >= 0 (0 means none)")
        if limit.lower is not None and limit.upper is not None and limit.lower > limit.upper:
            raise ModelError(f"{where} has lower limit {limit.lower} above its upper limit {limit.upper}")
    if joint.dynamics is not None:
        for attribute in ("damping", "friction"):
            text = getattr(joint.dynamics, attribute)  # yourdfpy keeps these as the file's strings
            if text is None:
                continue
            try:
                value = float(text)
            except (TypeError, ValueError):
                raise ModelError(f"{where} has {attribute} '{text}', which is not a number") from None
            if not np.isfinite(value) or value < 0:  # negative damping or friction would feed energy in
                raise ModelError(f"{where} has {attribute} {value}; it must be finite and >= 0")


def _check_geometry(element: Any, kind: str, link: str, path: Path) -> None:
    """Visual and collision shapes: finite origins, sizes and mesh scales (the viewer builds them)."""
    sizes: list[Any] = []
    scale = None
    geometry = element.geometry
    if geometry is not None:
        if geometry.box is not None:
            sizes.append(geometry.box.size)
        if geometry.cylinder is not None:
            sizes += [geometry.cylinder.radius, geometry.cylinder.length]
        if geometry.sphere is not None:
            sizes.append(geometry.sphere.radius)
        if geometry.mesh is not None:
            scale = geometry.mesh.scale  # may be negative: talos mirrors its right arm with scale="1 -1 1"
    if element.origin is not None and not np.all(np.isfinite(element.origin)):
        raise ModelError(f"{path}: link '{link}' has a {kind} with a non-finite origin")
    numbers = np.concatenate([np.ravel(np.asarray(size, dtype=float)) for size in sizes] + [np.zeros(0)])
    if not (np.all(np.isfinite(numbers)) and np.all(numbers >= 0)):
        raise ModelError(f"{path}: link '{link}' has a {kind} with a non-finite or negative size")
    if scale is not None and not np.all(np.isfinite(np.asarray(scale, dtype=float))):
        raise ModelError(f"{path}: link '{link}' has a {kind} mesh with a non-finite scale")


def _inertia_tolerance(inertia: np.ndarray, mass: float) -> float:
    """How negative an inertia's eigenvalue may be and still be round-off [kg·m²]: 1e-9 of its trace, or of what a
    1 mm body of its mass would have when the file gives a point mass (icub's links hold zeros plus 1e-20s)."""
    return 1e-9 * max(float(np.trace(inertia)), mass * 1e-6, 1e-300)


def _check_inertial(link: Any, path: Path, *, welded: bool = False) -> None:
    """A link's mass and inertia: finite, mass >= 0 and (unless `welded`) a positive semi-definite inertia.

    A link welded to its parent by a fixed joint is never a body of its own: Pinocchio merges it into the body it
    is welded to, and check_body_inertias judges that body. (tiago's 1 mg antennas carry inertias with a
    -3.5e-8 kg·m² eigenvalue, an error in the file that changes its base's merged inertia by less than 1e-7.)
    """
    inertial = link.inertial
    if inertial is None:
        return
    mass = inertial.mass if inertial.mass is not None else 0.0
    if not np.isfinite(mass) or mass < 0:
        raise ModelError(f"{path}: link '{link.name}' has mass {mass}; it must be finite and >= 0")
    if inertial.origin is not None and not np.all(np.isfinite(inertial.origin)):
        raise ModelError(f"{path}: link '{link.name}' has a non-finite inertial origin")
    if inertial.inertia is not None:
        inertia = np.asarray(inertial.inertia, dtype=float)
        if not np.all(np.isfinite(inertia)):
            raise ModelError(f"{path}: link '{link.name}' has a non-finite inertia")
        eig = np.linalg.eigvalsh(inertia)
        if not welded and eig[0] < -_inertia_tolerance(inertia, mass):
            raise ModelError(f"{path}: link '{link.name}' has an inertia with a negative eigenvalue ({eig[0]:.3g})")


def check_body_inertias(model: pin.Model, path: Path) -> None:
    """Each rigid body (links welded together merged, as Pinocchio does) must have a positive semi-definite
    inertia whose principal moments satisfy the triangle inequality: a single massless dummy link may be thin,
    the body it is welded to may not."""
    for i in range(1, model.njoints):
        inertia = model.inertias[i].inertia
        a, b, c = np.linalg.eigvalsh(inertia)
        if a < -_inertia_tolerance(inertia, model.inertias[i].mass):
            raise ModelError(
                f"{path}: the body moved by joint '{model.names[i]}' has an inertia with a negative eigenvalue "
                f"({a:.3g})"
            )
        if a + b < c - 1e3 * _inertia_tolerance(inertia, model.inertias[i].mass):  # 1e-6 of the trace
            raise ModelError(
                f"{path}: the body moved by joint '{model.names[i]}' has principal inertias "
                f"{a:.3g}, {b:.3g}, {c:.3g} that violate the triangle inequality"
            )


def check_model(model: pin.Model, path: Path) -> None:
    """What every model Pinocchio built (from a URDF, SDF or MJCF) must satisfy before Robot() creates its Data,
    whose size grows as nv^3: at most MAX_DOFS degrees of freedom, finite numbers, physical body inertias."""
    if model.nv > MAX_DOFS:
        raise ModelError(
            f"{path}: the robot has {model.nv} degrees of freedom, more than the {MAX_DOFS} this simulator accepts"
        )
    check_model_numbers(model, path)
    check_body_inertias(model, path)


def check_model_numbers(model: pin.Model, path: Path) -> None:
    """Whatever the URDF said, the model Pinocchio built must hold finite numbers (urdfdom reads some values
    yourdfpy does not, and vice versa)."""
    for i in range(model.njoints):
        inertia, placement = model.inertias[i], model.jointPlacements[i]
        numbers = [inertia.mass, *inertia.lever, *inertia.inertia.ravel(), *placement.homogeneous.ravel()]
        if not np.all(np.isfinite(numbers)):
            raise ModelError(f"{path}: the model Pinocchio built for joint '{model.names[i]}' has non-finite values")
    for name in ("damping", "friction"):
        if not np.all(np.isfinite(np.asarray(getattr(model, name), dtype=float))):
            raise ModelError(f"{path}: the model Pinocchio built has non-finite {name} values")
    for name in ("effortLimit", "velocityLimit", "lowerPositionLimit", "upperPositionLimit"):
        # ±inf means "no limit" (Pinocchio writes it for planar joints); NaN means nothing
        if np.any(np.isnan(np.asarray(getattr(model, name), dtype=float))):
            raise ModelError(f"{path}: the model Pinocchio built has NaN {name} values")


# A mass matrix whose smallest eigenvalue is below this fraction of its largest is singular for the purpose of
# simulating: its inverse amplifies round-off by as much (icub's point-mass head on the neck-yaw axis: -1.6e-17 of
# 29). The catalog's stiffest sound robots stay above 2e-7 (tiago_no_hand's wrist).
SINGULAR_MASS_RATIO = 1e-12


def check_mass_matrix(robot: Robot, path: Path) -> None:
    """A moving subtree with no mass (or no inertia about its axis) makes M(q) singular: refuse it at load, not
    mid-run. Checked at the neutral configuration, the default pose and a random configuration."""
    if robot.nv == 0:
        raise ModelError(f"{path}: the robot has no movable joint (a fixed base with only fixed joints)")
    for q in (robot.neutral(), robot.default_pose(), robot.random_configuration(np.random.default_rng(0))):
        with np.errstate(all="ignore"):
            M = robot.mass_matrix(q)
        if not np.all(np.isfinite(M)):  # finite inputs can still overflow (masses and lengths near 1e300)
            raise ModelError(f"{path}: the mass matrix is not finite (masses, inertias or distances are too large)")
        eigenvalues = np.linalg.eigvalsh(M)
        if eigenvalues[0] <= SINGULAR_MASS_RATIO * eigenvalues[-1]:
            weak = int(np.argmax(np.abs(np.linalg.eigh(M)[1][:, 0])))  # the main dof of the null direction
            raise ModelError(
                f"{path}: the mass matrix is singular: the subtree moved by '{robot.dof_names[weak]}' has no mass "
                "or inertia"
            )
