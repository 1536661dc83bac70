"""load_robot(): a catalog name or a URDF, SDF or MJCF file, read, checked and built into a Robot; and the
geometry of a loaded robot, built again from the same file."""

from __future__ import annotations

import difflib
import hashlib
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from ..exceptions import InvalidArgumentError, ModelError, RobotNotFoundError
from ..robot import Robot
from ..text import printable
from .checks import check_mass_matrix, check_model, check_urdf
from .entries import CATALOG, ROBOT_PREFIX, CatalogEntry, catalog_srdf, catalog_urdf, default_pose_name
from .mjcf import MJCF_SUFFIXES, load_mjcf
from .reading import captured_stderr, folder_list, parse_urdf, parse_xml, read_xml_file
from .srdf import read_poses


def load_robot(
    source: str | os.PathLike[str],
    *,
    floating_base: bool | None = None,
    damping: bool = True,
    package_dirs: list[str | os.PathLike[str]] | None = None,
    allowed_roots: list[str | os.PathLike[str]] | None = None,
    srdf: str | os.PathLike[str] | None = None,
) -> Robot:
    """Load a robot by catalog name or file path (URDF, or SDF converted to URDF) into Pinocchio.

    Files are untrusted input: no DTD or entity is expanded, nothing is fetched, files over MAX_URDF_BYTES, with
    more than MAX_XML_ELEMENTS elements, MAX_LINKS links, MAX_JOINTS joints or MAX_DOFS degrees of freedom are
    refused before they cost time or memory, and mesh paths must resolve (symlinks followed) inside the allowed
    folders: the file's folder, package_dirs and allowed_roots. SRDF files follow the same rules.

    Args:
        source: a catalog name (`multibody-sim models` lists them) or a path to a URDF (or SDF) file; a leading
            "robot:" is allowed (the CLI needs it for names that are also scenes: robot:four_bar).
        floating_base: True adds a free-flyer root joint, False welds the root to the world; None takes the
            catalog entry's natural base (fixed for files).
        damping: apply the URDF's joint viscous damping (tau = -D v); False ignores it.
        package_dirs: folders that `package://NAME/...` URIs resolve against; mesh paths must stay inside them
            or the URDF's folder. Catalog robots add their own.
        allowed_roots: further folders mesh paths may resolve into (e.g. a `../meshes` folder beside the
            URDF's), without being package roots; the CLI's `--allow-root`.
        srdf: an SRDF file whose `<group_state>`s become the robot's named poses (robot.poses, robot.pose(name),
            robot.default_pose()); catalog robots come with example-robot-data's where it ships one.

    Raises:
        InvalidArgumentError: an argument has the wrong type, or a folder given does not exist.
        RobotNotFoundError: source is neither a catalog name nor an existing file.
        ModelError: the file (or the SRDF) is malformed, too large, reaches outside the allowed folders or
            describes something that cannot be simulated.
    """
    if not isinstance(source, (str, os.PathLike)):
        raise InvalidArgumentError(f"source must be a catalog name or a URDF path, got {type(source).__name__}")
    for flag, value, allowed in (("floating_base", floating_base, "True, False or None"), ("damping", damping, "")):
        if not (isinstance(value, (bool, np.bool_)) or (value is None and allowed)):
            raise InvalidArgumentError(f"{flag} must be {allowed or 'True or False'}, got {value!r}")
    if srdf is not None and not isinstance(srdf, (str, os.PathLike)):
        raise InvalidArgumentError(f"srdf must be a path to an SRDF file, got {type(srdf).__name__}")
    dirs = folder_list("package_dirs", package_dirs)
    extra_roots = folder_list("allowed_roots", allowed_roots)
    name = os.fspath(source).removeprefix(ROBOT_PREFIX)  # the prefix only says "the robot, not the scene"
    arguments: dict[str, Any] = {
        "source": name,
        "floating_base": None if floating_base is None else bool(floating_base),
        "damping": bool(damping),
        "package_dirs": [os.fspath(p) for p in package_dirs or []],
    }
    # Only when given: metadata written before these options existed stays comparable.
    if allowed_roots:
        arguments["allowed_roots"] = [os.fspath(p) for p in allowed_roots]
    if srdf is not None:
        arguments["srdf"] = os.fspath(srdf)
    entry = CATALOG.get(name)
    srdf_path = Path(srdf).expanduser().resolve() if srdf is not None else None
    if entry is not None:
        path, extra_dirs = catalog_urdf(entry)
        dirs += extra_dirs
        floating = entry.floating_base if floating_base is None else bool(floating_base)
        if srdf_path is None:
            srdf_path = catalog_srdf(entry)
    else:
        path = Path(name).expanduser()
        if not path.is_file():
            raise _not_found(name, path)
        floating = bool(floating_base)
        name = path.stem
    try:
        # The checks test finiteness themselves: numpy's overflow warnings on a hostile file's 1e308s would only
        # add lines to stderr.
        with np.errstate(all="ignore"):
            return _load(path.resolve(), name, floating, bool(damping), dirs, extra_roots, arguments, entry, srdf_path)
    except ModelError as exc:
        # Messages quote names and paths from the file: never let them carry line breaks, terminal escapes
        # or megabytes to the user's terminal.
        shown = printable(str(exc))
        if shown == str(exc):
            raise
        raise ModelError(shown) from None


def _load(
    path: Path,
    name: str,
    floating: bool,
    damping: bool,
    dirs: list[Path],
    extra_roots: list[Path],
    arguments: dict[str, Any],
    entry: CatalogEntry | None,
    srdf_path: Path | None,
) -> Robot:
    if path.suffix.lower() in MJCF_SUFFIXES:
        xml = read_xml_file(path, "MJCF")
        root = parse_xml(xml, path, "MJCF", "(the largest catalog robot has about 2000)")
        if root.tag == "mujoco":
            return load_mjcf(path, xml, root, name, damping, dirs, extra_roots, arguments, srdf_path)
    xml = read_xml_file(path, "SDF" if path.suffix.lower() == ".sdf" else "URDF")
    derivation = _derivation(xml, path, entry)
    urdf = derived_urdf(xml, path, derivation)
    description = parse_urdf(urdf, path)
    check_urdf(description, path, package_dirs=[path.parent, *dirs], allowed_roots=extra_roots)
    model = _build_model(urdf, path, floating)
    if entry is not None and entry.base_rpy is not None:
        _rotate_base(model, entry.base_rpy)
    check_model(model, path)
    poses: dict[str, np.ndarray] = {}
    if srdf_path is not None:
        poses = read_poses(srdf_path, model)
    default = default_pose_name(poses, entry.reference_pose if entry is not None else None)
    if entry is not None and entry.locked:
        model, poses = _lock(model, entry.locked, poses[default] if default else pin.neutral(model), poses)
    source: dict[str, Any] = {
        "load_robot": arguments,
        "urdf_path": str(path),
        "urdf_sha256": hashlib.sha256(xml).hexdigest(),
    }
    if derivation is not None:
        source["derivation"] = derivation
    if srdf_path is not None:
        source["srdf_path"] = str(srdf_path)
    robot = Robot(
        model,
        name=name,
        floating_base=floating,
        damping=damping,
        source=source,
        poses=poses,
        default_pose=default,
    )
    check_mass_matrix(robot, path)
    return robot


def _derivation(xml: bytes, path: Path, entry: CatalogEntry | None) -> str | None:
    """How the URDF the model is built from derives from the file read: None (it is the file), "sdf" (converted
    from SDFormat) or "prune:JOINT" (a catalog entry's subtree removed)."""
    if entry is not None and entry.prune is not None:
        return f"prune:{entry.prune}"
    if path.suffix.lower() == ".sdf":
        return "sdf"
    return None


def derived_urdf(xml: bytes, path: Path, derivation: str | None) -> bytes:
    """The URDF a robot's model is built from, given the bytes of its file and its source's "derivation".

    The viewer builds its meshes from the same text (`robot.source["derivation"]`).
    """
    if derivation is None:
        return xml
    if derivation == "sdf":
        from .sdformat import sdf_to_urdf

        return sdf_to_urdf(parse_xml(xml, path, "SDF", "(the largest catalog robot has about 2000)"), path).urdf
    if derivation.startswith("prune:"):
        return _prune(xml, path, derivation.removeprefix("prune:"))
    raise ModelError(f"{path}: unknown derivation '{derivation}' (expected sdf or prune:JOINT)")


def mesh_roots(source: dict[str, Any]) -> list[Path]:
    """Folders a robot's meshes may come from (its `source`: Robot.source): the URDF's folder, its package
    directories and allowed roots, the catalog's package directory."""
    arguments = source.get("load_robot", {})
    roots = [Path(source["urdf_path"]).parent] if source.get("urdf_path") else []
    roots += [Path(p) for p in arguments.get("package_dirs", []) or []]
    roots += [Path(p) for p in arguments.get("allowed_roots", []) or []]
    name = arguments.get("source")
    if name in CATALOG:
        roots += catalog_urdf(CATALOG[name])[1]
    return [r.resolve() for r in roots]


def build_geometry(source: dict[str, Any], model: pin.Model, kind: str, **loader: Any) -> pin.GeometryModel:
    """The visual or collision geometry of a robot's URDF (or MJCF) on `model` (its own, or a scene's built from
    it: shapes attach to the links of the same names), from the file its `source` (Robot.source) records: checked
    unchanged (SHA-256), derived as the model was (catalog pruning, SDFormat), meshes resolved in mesh_roots().

    Args:
        kind: "visual" or "collision".
        **loader: Pinocchio's builder options (mesh_loader).

    Raises:
        ModelError: the file cannot be read, or changed since the robot was loaded.
        RuntimeError, ValueError: Pinocchio cannot build it (e.g. a mesh file that is not there).
    """
    path = Path(source["urdf_path"])
    try:
        xml = path.read_bytes()
    except OSError as exc:
        raise ModelError(f"{path}: cannot read the URDF for its {kind} meshes ({exc.strerror})") from None
    expected = source.get("urdf_sha256")
    if expected and hashlib.sha256(xml).hexdigest() != expected:
        raise ModelError(f"{path}: the URDF changed after the robot was loaded (SHA-256 differs); reload it")
    geometry_type = pin.GeometryType.VISUAL if kind == "visual" else pin.GeometryType.COLLISION
    if source.get("format") == "mjcf":  # checked at load like a URDF; Pinocchio reads it from its path
        return pin.buildGeomFromMJCF(model, str(path), geometry_type)
    return pin.buildGeomFromUrdfString(
        model,
        derived_urdf(xml, path, source.get("derivation")).decode("utf-8"),
        geometry_type,
        package_dirs=[str(r) for r in mesh_roots(source)],
        **loader,
    )


def _prune(xml: bytes, path: Path, joint: str) -> bytes:
    """The URDF without `joint`, its child link and everything below it (transmissions and gazebo blocks of the
    removed parts too)."""
    root = parse_xml(xml, path, "URDF", "(the largest catalog robot has about 2000)")
    joints = root.findall("joint")
    cut = next((j for j in joints if j.get("name") == joint), None)
    if cut is None or cut.find("child") is None:
        raise ModelError(f"{path}: no joint '{joint}' to cut the tree at")
    below: dict[str, list[Any]] = {}
    for element in joints:
        parent = element.find("parent")
        if parent is not None:
            below.setdefault(str(parent.get("link")), []).append(element)
    removed_links, removed_joints = set(), {joint}
    stack = [str(cut.find("child").get("link"))]
    while stack:
        link = stack.pop()
        if link in removed_links:
            continue
        removed_links.add(link)
        for element in below.get(link, []):
            removed_joints.add(str(element.get("name")))
            child = element.find("child")
            if child is not None:
                stack.append(str(child.get("link")))
    for element in list(root):
        tag, name = element.tag, element.get("name")
        gone = (tag == "link" and name in removed_links) or (tag == "joint" and name in removed_joints)
        gone |= tag == "gazebo" and element.get("reference") in removed_links | removed_joints
        gone |= tag == "transmission" and any(j.get("name") in removed_joints for j in element.findall("joint"))
        if gone:
            root.remove(element)
    from lxml import etree

    return etree.tostring(root, xml_declaration=True, encoding="utf-8")


def _rotate_base(model: pin.Model, rpy: tuple[float, float, float]) -> None:
    """Turn the robot by a constant rotation at its base: every joint and frame attached to the world."""
    turn = pin.SE3(pin.rpy.rpyToMatrix(*rpy), np.zeros(3))
    for jid in range(1, model.njoints):
        if model.parents[jid] == 0:
            model.jointPlacements[jid] = turn * model.jointPlacements[jid]
    for fid in range(1, len(model.frames)):
        frame = model.frames[fid]
        if frame.parentJoint == 0:
            frame.placement = turn * frame.placement
            model.frames[fid] = frame


def _lock(
    model: pin.Model, names: tuple[str, ...], reference: np.ndarray, poses: dict[str, np.ndarray]
) -> tuple[pin.Model, dict[str, np.ndarray]]:
    """The model without the named joints (locked where `reference` has them) and the poses on it."""
    ids = [model.getJointId(name) for name in names if model.existJointName(name)]
    if len(ids) != len(names):
        missing = [name for name in names if not model.existJointName(name)]
        raise ModelError(f"cannot lock joints the model does not have: {', '.join(missing)}")
    reduced = pin.buildReducedModel(model, ids, reference)
    return reduced, {name: reduce_configuration(model, reduced, q) for name, q in poses.items()}


def reduce_configuration(full: pin.Model, reduced: pin.Model, q: np.ndarray) -> np.ndarray:
    """A configuration of `full` on `reduced`, a model with some of its joints removed: each joint of `reduced`
    takes its coordinates from the joint of the same name in `full` (joints without coordinates are skipped)."""
    out = pin.neutral(reduced)
    for jid in range(1, reduced.njoints):
        joint = reduced.joints[jid]
        if joint.nq == 0 or not full.existJointName(reduced.names[jid]):
            continue
        source = full.joints[full.getJointId(reduced.names[jid])]
        if source.nq == joint.nq:
            out[joint.idx_q : joint.idx_q + joint.nq] = q[source.idx_q : source.idx_q + source.nq]
    return out


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


def _build_model(xml: bytes, path: Path, floating: bool) -> pin.Model:
    try:
        text = xml.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise ModelError(f"{path}: Pinocchio cannot build the model ({exc})") from None
    error: BaseException | None = None
    with captured_stderr() as logged:
        try:
            model = pin.buildModelFromXML(text, pin.JointModelFreeFlyer()) if floating else pin.buildModelFromXML(text)
        except (RuntimeError, ValueError, TypeError, OverflowError) as exc:
            error = exc
    log = "".join(logged)
    # urdfdom's first "Error:" line says what is wrong; Pinocchio's own message only that something is.
    reasons = [line.removeprefix("Error:").strip() for line in log.splitlines() if line.startswith("Error:")]
    if error is None and reasons:
        # urdfdom skips what it cannot read and carries on: an <inertial> without <inertia> leaves its link
        # massless, though the file says otherwise. No example-robot-data URDF that builds logs an error.
        raise ModelError(f"{path}: Pinocchio's URDF parser skipped part of the file ({reasons[0]})")
    if error is None:
        if log:  # warnings of a model that did build: pass them on unchanged
            sys.stderr.write(log)
        return model
    lines = str(error).strip().splitlines()
    reason = reasons[0] if reasons else (lines[0] if lines else type(error).__name__)
    raise ModelError(f"{path}: Pinocchio cannot build the model ({reason})") from None


def catalog_table() -> list[dict[str, Any]]:
    """One row per catalog robot: name, nq, nv, base, poses (names), default_pose (name or None), description.

    Loads every model (a few seconds for the whole catalog).
    """
    rows = []
    for entry in CATALOG.values():
        robot = load_robot(entry.name)
        rows.append(
            {
                "name": entry.name,
                "nq": robot.nq,
                "nv": robot.nv,
                "base": "floating" if robot.floating_base else "fixed",
                "poses": list(robot.poses),
                "default_pose": robot.default_pose_name,
                "description": entry.description,
            }
        )
    return rows
