"""Named poses from SRDF files (`<group_state>`), read as untrusted input.

Pinocchio's own reader (`pin.loadReferenceConfigurations`) is not used: on bad input it prints to stdout and keeps
going with the joint at its neutral value (a value "abc", "nan" or "1 2 3" silently becomes 0), ignores a DOCTYPE's
entities the same way, has no size limit (200,000 states took 8.5 s), and fails on a missing attribute with
"No such node (<xmlattr>.name)". This reader takes the same rules as our URDF reader (no DTD, no entities, bounded
size and element count) and refuses a bad value in one line naming the file, the state and the joint.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pinocchio as pin

from ..exceptions import ModelError
from .reading import parse_xml, read_xml_file


def read_poses(path: Path, model: pin.Model) -> dict[str, np.ndarray]:
    """The SRDF's `<group_state>` poses as configurations of `model`, shape (nq,) each, in file order.

    A state sets the joints it names and leaves the others at their neutral value (as Pinocchio does). Joints the
    model does not have are skipped: one SRDF often serves several models (talos.srdf: the whole robot, one arm,
    the legs); a state that names none of the model's joints is dropped, and a file none of whose states fits the
    model is refused. Values: one number per coordinate (a revolute or prismatic joint: 1; a free-flyer:
    x y z qx qy qz qw; a spherical joint: qx qy qz qw; a continuous joint: its angle, or cos sin); quaternions are
    normalized and must not be zero.

    Raises:
        ModelError: the file is missing, too large, not safe XML, not an SRDF, or a state is malformed (duplicate
            name, a missing attribute, a value that is not a finite number or has the wrong count).
    """
    xml = read_xml_file(path, "SRDF")
    root = parse_xml(xml, path, "SRDF", "(the largest catalog SRDF has about 1300)")
    if root.tag != "robot":
        raise ModelError(f"{path}: not an SRDF: the root element is <{root.tag}>, expected <robot>")
    poses: dict[str, np.ndarray] = {}
    limits = (np.asarray(model.lowerPositionLimit, dtype=float), np.asarray(model.upperPositionLimit, dtype=float))
    states = root.findall("group_state")
    for state in states:
        name = state.get("name")
        if not name:
            raise ModelError(f"{path}: a <group_state> has no 'name' attribute")
        if name in poses:
            raise ModelError(f"{path}: group_state '{name}' is defined twice")
        q = pin.neutral(model)
        matched = False
        for element in state.findall("joint"):
            joint_name = element.get("name")
            text = element.get("value")
            if joint_name is None or text is None:
                raise ModelError(f"{path}: group_state '{name}': a <joint> needs both 'name' and 'value' attributes")
            if not model.existJointName(joint_name):
                continue
            joint = model.joints[model.getJointId(joint_name)]
            if joint.nq == 0:  # a mimic follower: its leader's value decides
                continue
            _set(q, joint, _numbers(text, path, name, joint_name), limits, path, name, joint_name)
            matched = True
        if matched:
            poses[name] = q
    if states and not poses:
        raise ModelError(
            f"{path}: none of its group_state joints is a joint of the model ({len(states)} state(s)): "
            "is it this robot's SRDF?"
        )
    return poses


def _numbers(text: str, path: Path, state: str, joint: str) -> list[float]:
    where = f"{path}: group_state '{state}', joint '{joint}'"
    try:
        values = [float(token) for token in text.split()]
    except ValueError:
        raise ModelError(f"{where}: value '{text}' is not a list of numbers") from None
    if not values or not all(math.isfinite(v) for v in values):
        raise ModelError(f"{where}: value '{text}' must be finite numbers")
    return values


def _set(
    q: np.ndarray,
    joint: pin.JointModel,
    values: list[float],
    model_limits: tuple[np.ndarray, np.ndarray],
    path: Path,
    state: str,
    name: str,
) -> None:
    """Write a joint's values into q, in Pinocchio's layout for its type."""
    i, nq, nv = joint.idx_q, joint.nq, joint.nv
    where = f"{path}: group_state '{state}', joint '{name}'"
    if (nq, nv) == (2, 1) and len(values) == 1:  # a continuous joint given by its angle
        q[i], q[i + 1] = math.cos(values[0]), math.sin(values[0])
        return
    if (nq, nv) == (1, 1) and len(values) == 1 and joint.shortname().startswith("JointModelR"):
        values = [_wrapped(values[0], model_limits[0][i], model_limits[1][i])]
    if len(values) != nq:
        raise ModelError(f"{where}: has {len(values)} value(s), the joint has {nq} coordinate(s)")
    block = np.array(values)
    unit = {(7, 6): slice(3, 7), (4, 3): slice(0, 4), (2, 1): slice(0, 2)}.get((nq, nv))
    if unit is not None and joint.shortname() != "JointModelPlanar":
        norm = float(np.linalg.norm(block[unit]))
        if norm < 1e-9:
            raise ModelError(f"{where}: its quaternion (or cos, sin) pair is zero")
        block[unit] /= norm
    elif joint.shortname() == "JointModelPlanar":  # x, y, cos, sin
        norm = float(np.linalg.norm(block[2:4]))
        if norm < 1e-9:
            raise ModelError(f"{where}: its (cos, sin) pair is zero")
        block[2:4] /= norm
    q[i : i + nq] = block


def _wrapped(angle: float, lower: float, upper: float) -> float:
    """A revolute joint's angle moved by whole turns into [lower, upper] when that is possible (the same physical
    pose: kinova's SRDF gives joint 3 as -1.5707 rad, its URDF's range is [0.33, 5.95] rad), else unchanged."""
    if not (-1e300 < lower <= upper < 1e300) or lower <= angle <= upper:
        return angle
    turns = math.ceil((lower - angle) / (2 * math.pi))
    moved = angle + turns * 2 * math.pi
    return moved if lower <= moved <= upper else angle
