"""The robot catalog and load_robot(): locating URDFs, resolving package:// URIs, checking files."""

from __future__ import annotations

import difflib
import hashlib
import importlib.metadata
import importlib.resources
import os
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
from lxml import etree

from .exceptions import ModelError, RobotNotFoundError
from .robot import Robot

SUPPORTED_JOINT_TYPES = ("continuous", "fixed", "floating", "planar", "prismatic", "revolute")
MAX_URDF_BYTES = 32 * 1024 * 1024  # the largest catalog URDF is ~200 kB; anything this big is not a robot
_ERD = "example-robot-data"


@dataclass(frozen=True)
class CatalogEntry:
    """A named robot: where its URDF lives and which base it naturally has.

    Attributes:
        name: catalog name (what load_robot and the CLI accept).
        path: URDF path relative to its provider's robots folder.
        floating_base: the robot's natural base (arms fixed, legged robots and humanoids floating).
        provider: "example-robot-data" or "multibody-sim" (the repository's models/ folder).
        description: one line for `multibody-sim models`.
    """

    name: str
    path: str
    floating_base: bool
    provider: str
    description: str


def _erd(name: str, path: str, floating: bool, description: str) -> CatalogEntry:
    return CatalogEntry(name, path, floating, _ERD, description)


def _shipped(name: str, path: str, floating: bool, description: str) -> CatalogEntry:
    return CatalogEntry(name, path, floating, "multibody-sim", description)


CATALOG: dict[str, CatalogEntry] = {
    e.name: e
    for e in [
        _shipped("pendulum", "pendulum/pendulum.urdf", False, "simple pendulum: 1 kg bob on a light 1 m rod"),
        _shipped("free_body", "free_body/free_body.urdf", True, "free rigid box with distinct principal inertias"),
        _erd(
            "double_pendulum",
            "double_pendulum_description/urdf/double_pendulum.urdf",
            False,
            "planar double pendulum (q = 0 is upright; hanging is [pi, 0])",
        ),
        _erd(
            "double_pendulum_continuous",
            "double_pendulum_description/urdf/double_pendulum_continuous.urdf",
            False,
            "double pendulum with continuous joints (nq = 4, nv = 2)",
        ),
        _erd("ur3", "ur_description/urdf/ur3_robot.urdf", False, "Universal Robots UR3 arm"),
        _erd("ur5", "ur_description/urdf/ur5_robot.urdf", False, "Universal Robots UR5 arm"),
        _erd("ur10", "ur_description/urdf/ur10_robot.urdf", False, "Universal Robots UR10 arm"),
        _erd("panda", "panda_description/urdf/panda.urdf", False, "Franka Emika Panda arm with two fingers"),
        _erd("z1", "z1_description/urdf/z1.urdf", False, "Unitree Z1 arm"),
        _erd("solo12", "solo_description/robots/solo12.urdf", True, "ODRI Solo-12 quadruped"),
        _erd("go2", "go2_description/urdf/go2.urdf", True, "Unitree Go2 quadruped"),
        _erd("anymal", "anymal_b_simple_description/robots/anymal.urdf", True, "ANYbotics ANYmal B quadruped"),
        _erd("anymal_c", "anymal_c_simple_description/urdf/anymal.urdf", True, "ANYbotics ANYmal C quadruped"),
        _erd("talos", "talos_data/robots/talos_reduced.urdf", True, "PAL Talos humanoid (reduced)"),
        _erd("g1", "g1_description/urdf/g1_29dof_rev_1_0.urdf", True, "Unitree G1 humanoid, 29 DoF"),
    ]
}


def example_robot_data_share() -> Path:
    """The folder that holds `example-robot-data/robots` (its package:// root).

    Raises:
        ModelError: example-robot-data is not installed.
    """
    candidates = []
    try:
        dist = importlib.metadata.distribution(_ERD)
        candidates.append(Path(str(dist.locate_file("cmeel.prefix/share"))))
    except importlib.metadata.PackageNotFoundError:
        pass
    candidates += [Path(p) / "cmeel.prefix" / "share" for p in sys.path if p]
    for share in candidates:
        if (share / _ERD / "robots").is_dir():
            return share.resolve()
    raise ModelError("example-robot-data is not installed (pip install example-robot-data)")


def shipped_models_dir() -> Path:
    """The repository's models/ folder, as installed in the package (multibody_sim.models)."""
    return Path(str(importlib.resources.files("multibody_sim.models")))


def catalog_urdf(entry: CatalogEntry) -> tuple[Path, list[Path]]:
    """(URDF path, package directories) of a catalog entry."""
    if entry.provider == _ERD:
        share = example_robot_data_share()
        return share / _ERD / "robots" / entry.path, [share]
    models = shipped_models_dir()
    return models / entry.path, [models]


def load_robot(
    source: str | os.PathLike[str],
    *,
    floating_base: bool | None = None,
    damping: bool = True,
    package_dirs: list[str | os.PathLike[str]] | None = None,
) -> Robot:
    """Load a robot by catalog name or URDF path into Pinocchio.

    Args:
        source: a catalog name (`multibody-sim models` lists them) or a path to a URDF file.
        floating_base: True adds a free-flyer root joint, False welds the root to the world; None takes the
            catalog entry's natural base (fixed for URDF paths).
        damping: apply the URDF's joint viscous damping (tau = -D v); False ignores it.
        package_dirs: folders that `package://NAME/...` URIs resolve against; mesh paths must stay inside them
            or the URDF's folder. Catalog robots add their own.

    Raises:
        RobotNotFoundError: source is neither a catalog name nor an existing file.
        ModelError: the URDF is malformed or describes something that cannot be simulated.
    """
    arguments = {
        "source": os.fspath(source),
        "floating_base": floating_base,
        "damping": damping,
        "package_dirs": [os.fspath(p) for p in package_dirs or []],
    }
    name = os.fspath(source)
    dirs = [Path(p).resolve() for p in package_dirs or []]
    if name in CATALOG:
        entry = CATALOG[name]
        path, extra_dirs = catalog_urdf(entry)
        dirs += extra_dirs
        floating = entry.floating_base if floating_base is None else floating_base
    else:
        path = Path(name).expanduser()
        if not path.is_file():
            raise _not_found(name, path)
        floating = bool(floating_base)
        name = path.stem
    path = path.resolve()
    xml = read_urdf(path)
    description = parse_urdf(xml, path)
    check_urdf(description, path, package_dirs=[path.parent, *dirs])
    model = _build_model(xml, path, floating)
    _check_body_inertias(model, path)
    robot = Robot(
        model,
        name=name,
        floating_base=floating,
        damping=damping,
        source={"load_robot": arguments, "urdf_path": str(path), "urdf_sha256": hashlib.sha256(xml).hexdigest()},
    )
    _check_mass_matrix(robot, path)
    return robot


def _not_found(name: str, path: Path) -> Exception:
    looks_like_path = os.sep in name or name.lower().endswith((".urdf", ".xml"))
    if looks_like_path:
        return ModelError(f"{name}: URDF file not found")
    close = difflib.get_close_matches(name, CATALOG, n=3, cutoff=0.5)
    hint = f"did you mean {', '.join(close)}? " if close else ""
    return RobotNotFoundError(
        f"unknown robot '{name}': not a catalog name nor an existing URDF file ({hint}"
        "`multibody-sim models` lists the catalog)"
    )


def read_urdf(path: Path) -> bytes:
    """The URDF's bytes, refusing directories and absurdly large files."""
    try:
        size = path.stat().st_size
        if size > MAX_URDF_BYTES:
            raise ModelError(f"{path}: file is {size} bytes, larger than the {MAX_URDF_BYTES}-byte limit for a URDF")
        return path.read_bytes()
    except OSError as exc:
        raise ModelError(f"{path}: cannot read URDF ({exc.strerror})") from None


def parse_urdf(xml: bytes, path: Path) -> Any:
    """Parse URDF bytes safely (no DTD, no entities, no network) into yourdfpy's description."""
    if b"<!DOCTYPE" in xml[:65536].upper():  # before any parsing: entities never get a chance to expand
        raise ModelError(f"{path}: DOCTYPE declarations are not allowed in a URDF (entities could expand)")
    parser = etree.XMLParser(
        resolve_entities=False, no_network=True, load_dtd=False, huge_tree=False, remove_comments=True, remove_pis=True
    )
    try:
        root = etree.fromstring(xml, parser=parser)
    except etree.XMLSyntaxError as exc:
        raise ModelError(f"{path}: malformed XML ({exc.msg})") from None
    if root.getroottree().docinfo.doctype:
        raise ModelError(f"{path}: DOCTYPE declarations are not allowed in a URDF (entities could expand)")
    if root.tag != "robot":
        raise ModelError(f"{path}: not a URDF: the root element is <{root.tag}>, expected <robot>")
    if "name" not in root.attrib:
        raise ModelError(f"{path}: the <robot> element has no 'name' attribute")
    import yourdfpy  # lazily: it imports trimesh, a second of start-up that `--help` should not pay

    try:
        return yourdfpy.URDF(
            robot=yourdfpy.URDF._parse_robot(xml_element=root),
            build_scene_graph=False,
            load_meshes=False,
            load_collision_meshes=False,
        )
    except (ValueError, TypeError, KeyError, AttributeError) as exc:
        raise ModelError(f"{path}: invalid URDF ({exc})") from None


def check_urdf(description: Any, path: Path, *, package_dirs: list[Path]) -> None:
    """Refuse what Pinocchio would mis-read: unsupported joints, broken trees, bad inertias, escaping URIs."""
    robot = description.robot
    links = {link.name for link in robot.links}
    if not robot.links:
        raise ModelError(f"{path}: the robot has no <link>")
    if len(links) != len(robot.links):
        raise ModelError(f"{path}: duplicate link names")
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
    roots = links - set(children)
    if not roots:
        raise ModelError(f"{path}: the joints form a cycle (every link has a parent joint)")
    if len(roots) != 1:
        raise ModelError(f"{path}: the links must form one tree, found {len(roots)} roots ({', '.join(sorted(roots))})")
    for link in robot.links:
        _check_inertial(link, path)
        for element in [*link.visuals, *link.collisions]:
            mesh = getattr(element.geometry, "mesh", None) if element.geometry is not None else None
            if mesh is not None and mesh.filename:
                resolve_mesh_uri(mesh.filename, path, package_dirs)


def _check_inertial(link: Any, path: Path) -> None:
    inertial = link.inertial
    if inertial is None:
        return
    mass = inertial.mass if inertial.mass is not None else 0.0
    if not np.isfinite(mass) or mass < 0:
        raise ModelError(f"{path}: link '{link.name}' has mass {mass}; it must be finite and >= 0")
    if inertial.inertia is not None:
        inertia = np.asarray(inertial.inertia, dtype=float)
        if not np.all(np.isfinite(inertia)):
            raise ModelError(f"{path}: link '{link.name}' has a non-finite inertia")
        eig = np.linalg.eigvalsh(inertia)
        if eig[0] < -1e-9 * max(np.trace(inertia), 1e-300):
            raise ModelError(f"{path}: link '{link.name}' has an inertia with a negative eigenvalue ({eig[0]:.3g})")


def _check_body_inertias(model: pin.Model, path: Path) -> None:
    """Principal inertias of each rigid body (links welded together merged, as Pinocchio does) must satisfy
    the triangle inequality: a single massless dummy link may be thin, the body it is welded to may not."""
    for i in range(1, model.njoints):
        inertia = model.inertias[i].inertia
        a, b, c = np.linalg.eigvalsh(inertia)
        if a + b < c - 1e-6 * max(np.trace(inertia), 1e-300):
            raise ModelError(
                f"{path}: the body moved by joint '{model.names[i]}' has principal inertias "
                f"{a:.3g}, {b:.3g}, {c:.3g} that violate the triangle inequality"
            )


def resolve_mesh_uri(uri: str, urdf_path: Path, package_dirs: list[Path]) -> Path | None:
    """The file a mesh URI names, which must lie inside the URDF's folder or a package directory.

    Returns None when no candidate file exists (meshes only matter for viewing).

    Raises:
        ModelError: the URI resolves outside every allowed root.
    """
    roots = [p.resolve() for p in package_dirs]
    if uri.startswith("package://"):
        package, _, rest = uri[len("package://") :].partition("/")
        candidates = [root / package / rest for root in roots] + [root / rest for root in roots if root.name == package]
    elif uri.startswith("file://"):
        candidates = [Path(uri[len("file://") :])]
    elif "://" in uri:
        raise ModelError(f"{urdf_path}: mesh URI '{uri}' has an unsupported scheme (use package:// or a file path)")
    else:
        candidates = [urdf_path.parent / uri]
    found = None
    for candidate in candidates:
        resolved = candidate.resolve()
        if not any(resolved.is_relative_to(root) for root in roots):
            raise ModelError(
                f"{urdf_path}: mesh '{uri}' resolves outside the allowed folders "
                f"({', '.join(str(r) for r in roots)}); add its folder to package_dirs"
            )
        if found is None and resolved.is_file():
            found = resolved
    return found


def _build_model(xml: bytes, path: Path, floating: bool) -> pin.Model:
    try:
        if floating:
            return pin.buildModelFromXML(xml.decode("utf-8"), pin.JointModelFreeFlyer())
        return pin.buildModelFromXML(xml.decode("utf-8"))
    except (RuntimeError, ValueError, UnicodeDecodeError) as exc:
        raise ModelError(f"{path}: Pinocchio cannot build the model ({str(exc).strip().splitlines()[0]})") from None


def _check_mass_matrix(robot: Robot, path: Path) -> None:
    """A moving subtree with no mass makes M(q) singular: refuse it at load, not mid-run."""
    if robot.nv == 0:
        raise ModelError(f"{path}: the robot has no movable joint (a fixed base with only fixed joints)")
    for q in (robot.neutral(), robot.random_configuration(np.random.default_rng(0))):
        M = robot.mass_matrix(q)
        try:
            np.linalg.cholesky(M)
        except np.linalg.LinAlgError:
            eigenvalues, eigenvectors = np.linalg.eigh(M)
            weak = int(np.argmax(np.abs(eigenvectors[:, 0])))  # the main dof of the null direction
            raise ModelError(
                f"{path}: the mass matrix is singular: the subtree moved by '{robot.dof_names[weak]}' has no mass "
                "or inertia"
            ) from None


def catalog_table() -> list[dict[str, Any]]:
    """One row per catalog robot: name, nq, nv, base, description (loads every model)."""
    rows = []
    for entry in CATALOG.values():
        robot = load_robot(entry.name)
        rows.append(
            {
                "name": entry.name,
                "nq": robot.nq,
                "nv": robot.nv,
                "base": "floating" if robot.floating_base else "fixed",
                "description": entry.description,
            }
        )
    return rows
