"""SDFormat (1.4-1.7) models as URDF text: the tree of links and joints, for Pinocchio's URDF parser.

pip's Pinocchio is built without SDFormat, and example-robot-data ships Cassie only as SDF. This converter reads one
`<model>` and writes the URDF of its kinematic tree: links, revolute / prismatic / fixed joints with limits and
`<dynamics>`, inertials, visual and collision geometry. What URDF cannot say is left out and listed in the
result's `dropped` notes: loop-closing joints (a joint whose child is already in the tree, found breadth first
from the root link; Cassie's achilles and plantar rods), joint springs (`spring_stiffness`). The file is untrusted
input under the URDF rules (size, no DTD or entities); mesh URIs `model://NAME/...` become `package://NAME/...`.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin
from lxml import etree

from ..exceptions import ModelError

_JOINT_TYPES = {"revolute": "revolute", "prismatic": "prismatic", "fixed": "fixed", "continuous": "continuous"}


@dataclass(frozen=True)
class ConvertedSdf:
    """A converted model: the URDF bytes and what was left out (one line each)."""

    urdf: bytes
    dropped: tuple[str, ...]


def sdf_to_urdf(root: Any, path: Path) -> ConvertedSdf:
    """The URDF of the SDF document `root` (an lxml element already parsed by catalog.parse_xml).

    Raises:
        ModelError: not an SDF with one model, or a tree joint of a type URDF cannot express (ball, universal,
            gearbox, screw), a link or joint named twice, a joint naming a missing link, a non-finite number.
    """
    if root.tag != "sdf":
        raise ModelError(f"{path}: not an SDF: the root element is <{root.tag}>, expected <sdf>")
    models = root.findall("model")
    if len(models) != 1:
        raise ModelError(f"{path}: an SDF must hold exactly one <model>, found {len(models)}")
    model = models[0]
    links = {}
    for link in model.findall("link"):
        name = _name(link, "link", path)
        if name in links:
            raise ModelError(f"{path}: link '{name}' is defined twice")
        links[name] = link
    joints = []
    names = set()
    for joint in model.findall("joint"):
        name = _name(joint, "joint", path)
        if name in names:
            raise ModelError(f"{path}: joint '{name}' is defined twice")
        names.add(name)
        parent, child = joint.findtext("parent", "").strip(), joint.findtext("child", "").strip()
        for role, link_name in (("parent", parent), ("child", child)):
            if link_name not in links:
                raise ModelError(f"{path}: joint '{name}' names {role} link '{link_name}', which does not exist")
        joints.append((name, parent, child, joint))
    if not links:
        raise ModelError(f"{path}: the model has no <link>")
    children = {child for _, _, child, _ in joints}
    roots = [name for name in links if name not in children]
    if len(roots) != 1:
        raise ModelError(
            f"{path}: the links must have exactly one root (a link that is no joint's child), found {len(roots)}"
        )
    root_link = roots[0]
    # Breadth first from the root: a joint reaching a link already in the tree closes a loop.
    below: dict[str, list[tuple[str, str, str, Any]]] = {}
    for entry in joints:
        below.setdefault(entry[1], []).append(entry)
    tree, dropped, seen = [], [], {root_link}
    queue = deque([root_link])
    while queue:
        for entry in below.get(queue.popleft(), []):
            name, parent, child, element = entry
            if child in seen:
                dropped.append(f"joint '{name}' ({element.get('type')}, {parent} -> {child}) closes a loop")
                continue
            seen.add(child)
            tree.append(entry)
            queue.append(child)
    unreachable = sorted(set(links) - seen)
    if unreachable:
        raise ModelError(f"{path}: links {', '.join(unreachable)} are not connected to the root link '{root_link}'")

    link_pose = {name: _pose(link, path, f"link '{name}'") for name, link in links.items()}  # in the model frame
    # URDF puts each child link's frame on its joint; the root keeps its own frame.
    frame = {root_link: link_pose[root_link]}
    out = etree.Element("robot", name=model.get("name") or path.stem)
    joint_elements = []
    for name, parent, child, element in tree:
        kind = element.get("type", "")
        if kind not in _JOINT_TYPES:
            raise ModelError(
                f"{path}: joint '{name}' of type '{kind}' is in the tree and URDF cannot express it "
                f"(supported: {', '.join(_JOINT_TYPES)})"
            )
        joint_frame = link_pose[child] * _pose(element, path, f"joint '{name}'")  # SDF: relative to the child
        frame[child] = joint_frame
        joint_elements.append(_joint(element, name, kind, parent, child, frame[parent], joint_frame, path, dropped))
    for name, link in links.items():
        out.append(_link(link, name, frame[name].inverse() * link_pose[name], path))
    for joint_element in joint_elements:
        out.append(joint_element)
    return ConvertedSdf(etree.tostring(out, pretty_print=True, xml_declaration=True, encoding="utf-8"), tuple(dropped))


def _name(element: Any, kind: str, path: Path) -> str:
    name = element.get("name")
    if not name:
        raise ModelError(f"{path}: a <{kind}> has no 'name' attribute")
    return str(name)


def _numbers(text: str | None, count: int, path: Path, where: str) -> np.ndarray:
    try:
        values = np.array([float(t) for t in (text or "").split()], dtype=float)
    except ValueError:
        raise ModelError(f"{path}: {where}: '{text}' is not a list of numbers") from None
    if values.shape != (count,) or not np.all(np.isfinite(values)):
        raise ModelError(f"{path}: {where}: expected {count} finite numbers, got '{text}'")
    return values


def _pose(element: Any, path: Path, where: str) -> pin.SE3:
    """An element's <pose> (x y z roll pitch yaw; fixed axes, as URDF's rpy), identity when absent."""
    text = element.findtext("pose")
    pose_element = element.find("pose")
    if pose_element is not None and pose_element.get("relative_to"):
        raise ModelError(f"{path}: {where}: <pose relative_to=...> is not supported")
    if text is None or not text.strip():
        return pin.SE3.Identity()
    x, y, z, roll, pitch, yaw = _numbers(text, 6, path, f"{where} <pose>")
    return pin.SE3(pin.rpy.rpyToMatrix(roll, pitch, yaw), np.array([x, y, z]))


def _origin(parent: Any, placement: pin.SE3) -> None:
    rpy = pin.rpy.matrixToRpy(placement.rotation)
    etree.SubElement(
        parent,
        "origin",
        xyz=" ".join(f"{v:.17g}" for v in placement.translation),
        rpy=" ".join(f"{v:.17g}" for v in rpy),
    )


def _joint(
    element: Any,
    name: str,
    kind: str,
    parent: str,
    child: str,
    parent_frame: pin.SE3,
    joint_frame: pin.SE3,
    path: Path,
    dropped: list[str],
) -> Any:
    joint = etree.Element("joint", name=name, type=_JOINT_TYPES[kind])
    etree.SubElement(joint, "parent", link=parent)
    etree.SubElement(joint, "child", link=child)
    _origin(joint, parent_frame.inverse() * joint_frame)
    axis = element.find("axis")
    if kind == "fixed":
        return joint
    where = f"joint '{name}'"
    if axis is None:
        raise ModelError(f"{path}: {where} has no <axis>")
    xyz = _numbers(axis.findtext("xyz"), 3, path, f"{where} <axis><xyz>")
    xyz_element = axis.find("xyz")
    in_model_frame = axis.findtext("use_parent_model_frame", "").strip().lower() in ("1", "true") or (
        xyz_element is not None and xyz_element.get("expressed_in") == "__model__"
    )
    if in_model_frame:
        xyz = joint_frame.rotation.T @ xyz
    if np.linalg.norm(xyz) < 1e-9:
        raise ModelError(f"{path}: {where} has a zero axis")
    etree.SubElement(joint, "axis", xyz=" ".join(f"{v:.17g}" for v in xyz / np.linalg.norm(xyz)))
    limit = axis.find("limit")
    values = {"lower": 0.0, "upper": 0.0, "effort": 0.0, "velocity": 0.0}  # zeros: no limit (our convention)
    if limit is not None:
        for key in values:
            text = limit.findtext(key)
            if text is not None and text.strip():
                values[key] = float(_numbers(text, 1, path, f"{where} <limit><{key}>")[0])
        if values["effort"] < 0:  # SDF's -1: unlimited
            values["effort"] = 0.0
        if values["velocity"] < 0:
            values["velocity"] = 0.0
        if abs(values["lower"]) >= 1e15 or abs(values["upper"]) >= 1e15:  # SDF's defaults for "none"
            values["lower"] = values["upper"] = 0.0
    if kind != "continuous":
        etree.SubElement(joint, "limit", **{k: f"{v:.17g}" for k, v in values.items()})
    dynamics = axis.find("dynamics")
    if dynamics is not None:
        attributes = {}
        for key in ("damping", "friction"):
            text = dynamics.findtext(key)
            if text is not None and text.strip():
                attributes[key] = f"{_numbers(text, 1, path, f'{where} <dynamics><{key}>')[0]:.17g}"
        if attributes:
            etree.SubElement(joint, "dynamics", **attributes)
        stiffness = dynamics.findtext("spring_stiffness")
        if stiffness is not None and stiffness.strip() and float(_numbers(stiffness, 1, path, where)[0]) != 0.0:
            dropped.append(f"joint '{name}': its spring (stiffness {stiffness.strip()}) is not modelled")
    return joint


def _link(element: Any, name: str, in_frame: pin.SE3, path: Path) -> Any:
    """The URDF <link>; in_frame places the SDF link frame in the URDF link frame."""
    link = etree.Element("link", name=name)
    inertial = element.find("inertial")
    if inertial is not None:
        where = f"link '{name}' <inertial>"
        out = etree.SubElement(link, "inertial")
        _origin(out, in_frame * _pose(inertial, path, where))
        mass = inertial.findtext("mass")
        etree.SubElement(out, "mass", value=f"{_numbers(mass or '1', 1, path, where)[0]:.17g}")
        tensor = inertial.find("inertia")
        values = {key: "0" for key in ("ixx", "ixy", "ixz", "iyy", "iyz", "izz")}
        if tensor is not None:
            for key in values:
                text = tensor.findtext(key)
                if text is not None and text.strip():
                    values[key] = f"{_numbers(text, 1, path, f'{where} <{key}>')[0]:.17g}"
        etree.SubElement(out, "inertia", **values)
    for kind in ("visual", "collision"):
        for k, shape in enumerate(element.findall(kind)):
            geometry = _geometry(shape.find("geometry"), path, f"link '{name}' <{kind}>")
            if geometry is None:
                continue
            out = etree.SubElement(link, kind, name=shape.get("name") or f"{name}_{kind}_{k}")
            _origin(out, in_frame * _pose(shape, path, f"link '{name}' <{kind}>"))
            out.append(geometry)
            diffuse = shape.findtext("material/diffuse") if kind == "visual" else None
            if diffuse is not None and diffuse.strip():
                rgba = _numbers(diffuse, len(diffuse.split()), path, f"link '{name}' <material><diffuse>")
                if rgba.size in (3, 4):
                    color = np.append(rgba, 1.0) if rgba.size == 3 else rgba
                    material = etree.SubElement(out, "material", name=f"{name}_{k}")
                    etree.SubElement(material, "color", rgba=" ".join(f"{v:.6g}" for v in color))
    return link


def _geometry(element: Any, path: Path, where: str) -> Any:
    if element is None:
        return None
    geometry = etree.Element("geometry")
    if (mesh := element.find("mesh")) is not None:
        uri = (mesh.findtext("uri") or "").strip()
        if uri.startswith("model://"):
            uri = "package://" + uri.removeprefix("model://")
        attributes = {"filename": uri}
        scale = mesh.findtext("scale")
        if scale is not None and scale.strip():
            attributes["scale"] = " ".join(f"{v:.17g}" for v in _numbers(scale, 3, path, f"{where} <scale>"))
        etree.SubElement(geometry, "mesh", **attributes)
    elif (box := element.find("box")) is not None:
        size = _numbers(box.findtext("size"), 3, path, f"{where} <box><size>")
        etree.SubElement(geometry, "box", size=" ".join(f"{v:.17g}" for v in size))
    elif (cylinder := element.find("cylinder")) is not None:
        radius = _numbers(cylinder.findtext("radius"), 1, path, f"{where} <cylinder><radius>")[0]
        length = _numbers(cylinder.findtext("length"), 1, path, f"{where} <cylinder><length>")[0]
        etree.SubElement(geometry, "cylinder", radius=f"{radius:.17g}", length=f"{length:.17g}")
    elif (sphere := element.find("sphere")) is not None:
        radius = _numbers(sphere.findtext("radius"), 1, path, f"{where} <sphere><radius>")[0]
        etree.SubElement(geometry, "sphere", radius=f"{radius:.17g}")
    else:
        return None  # planes, heightmaps, ...: nothing URDF can draw
    return geometry
