"""MuJoCo XML (MJCF) robots: checked like URDFs, built by Pinocchio's MJCF parser."""

from __future__ import annotations

import hashlib
import os
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pinocchio as pin

from ..exceptions import ModelError
from ..robot import Robot
from .checks import check_mass_matrix, check_model
from .entries import default_pose_name
from .reading import MAX_JOINTS, MAX_LINKS, captured_stderr, resolve_in_roots
from .srdf import read_poses

MJCF_SUFFIXES = (".xml", ".mjcf")  # files with these suffixes whose root element is <mujoco> are MJCF
# MJCF elements whose `file` attribute names a file MuJoCo (or a viewer) would read, and the <compiler> attribute
# holding the folder it is relative to.
_MJCF_FILES = {"mesh": "meshdir", "texture": "texturedir", "hfield": "assetdir", "skin": "assetdir"}


def load_mjcf(
    path: Path,
    xml: bytes,
    root: Any,
    name: str,
    damping: bool,
    dirs: list[Path],
    extra_roots: list[Path],
    arguments: dict[str, Any],
    srdf_path: Path | None,
) -> Robot:
    """A MuJoCo XML file through Pinocchio's MJCF parser, behind the URDF checks (see check_mjcf).

    The base is the file's: floating when its root body has a free joint; a floating_base argument that says
    otherwise is refused. Gravity comes from its <option gravity> (Pinocchio's parser ignores it); what ABA does not
    model (contacts, actuators, tendons, equality constraints, joint limits as constraints, springs, friction loss)
    is left out, as it is from URDFs.
    """
    free = check_mjcf(root, path, package_dirs=[path.parent, *dirs], allowed_roots=extra_roots)
    requested = arguments["floating_base"]
    if requested is not None and bool(requested) != free:
        # Pinocchio's MJCF parser neither adds a root joint to a model whose bodies hang from the world by their
        # own joints nor removes one: the file decides.
        said = "has a free joint" if free else "has no free joint"
        raise ModelError(
            f"{path}: an MJCF file declares its base (its root body {said}): floating_base={requested} cannot change "
            "it; leave floating_base=None or edit the file's <freejoint/>"
        )
    error: BaseException | None = None
    with captured_stderr() as logged:
        try:
            model = pin.buildModelFromMJCF(str(path))
        except (RuntimeError, ValueError, TypeError, OverflowError) as exc:
            error = exc
    if error is not None:
        # Pinocchio's exceptions name its source file and function, then "message:", then the reason.
        text = [line.strip() for line in str(error).strip().splitlines()]
        after = [text[i + 1] for i, line in enumerate(text[:-1]) if line == "message:"]
        reason = after[0] if after else (text[0] if text else type(error).__name__)
        raise ModelError(f"{path}: Pinocchio cannot build the model ({reason})") from None
    if "".join(logged):
        sys.stderr.write("".join(logged))
    gravity = root.find("option")
    if gravity is not None and gravity.get("gravity") is not None:  # Pinocchio's parser keeps -9.81 m/s² z
        model.gravity.linear = _mjcf_numbers(gravity.get("gravity"), 3, path, "<option gravity>")
    check_model(model, path)
    poses: dict[str, np.ndarray] = {}
    if srdf_path is not None:
        poses = read_poses(srdf_path, model)
    source: dict[str, Any] = {
        "load_robot": arguments,
        "urdf_path": str(path),
        "urdf_sha256": hashlib.sha256(xml).hexdigest(),
        "format": "mjcf",
    }
    if srdf_path is not None:
        source["srdf_path"] = str(srdf_path)
    floating = free
    robot = Robot(
        model,
        name=name,
        floating_base=floating,
        damping=damping,
        source=source,
        poses=poses,
        default_pose=default_pose_name(poses),
    )
    check_mass_matrix(robot, path)
    return robot


def check_mjcf(root: Any, path: Path, *, package_dirs: list[Path], allowed_roots: list[Path] | None = None) -> bool:
    """Refuse what Pinocchio's MJCF parser would mis-read or what reaches outside the allowed folders.

    No <include> (Pinocchio's parser does not follow them: inline the included file), at most MAX_LINKS bodies and
    MAX_JOINTS joints, and every file a <mesh>, <texture>, <hfield> or <skin> names (relative to the
    <compiler>'s meshdir, texturedir or assetdir, themselves relative to the file's folder) inside the allowed
    folders.

    Returns:
        Whether the root body has a free joint (a floating base).
    """
    if root.find(".//include") is not None:
        raise ModelError(
            f"{path}: <include> is not supported (Pinocchio's MJCF parser does not follow it): inline the included file"
        )
    for kind, xpath, limit in (
        ("bodie", "count(//body)", MAX_LINKS),
        ("joint", "count(//joint|//freejoint)", MAX_JOINTS),
    ):
        count = int(root.xpath(xpath))
        if count > limit:
            raise ModelError(f"{path}: the robot has {count} {kind}s, more than the {limit} this simulator accepts")
    compiler = root.find("compiler")
    folders = {key: compiler.get(key) if compiler is not None else None for key in set(_MJCF_FILES.values())}
    package_roots = [Path(os.path.realpath(p)) for p in package_dirs]
    roots = package_roots + [Path(os.path.realpath(p)) for p in allowed_roots or []]
    for tag, folder_key in _MJCF_FILES.items():
        for element in root.iter(tag):
            name = element.get("file")
            if not name:
                continue
            folder = folders[folder_key] or folders["assetdir"] or ""
            candidate = (path.parent / folder / name) if not os.path.isabs(name) else Path(name)
            resolve_in_roots(str(candidate.absolute()), path, package_roots, roots, tag)
    worldbody = root.find("worldbody")
    first = worldbody.find("body") if worldbody is not None else None
    return first is not None and (
        first.find("freejoint") is not None or any(j.get("type") == "free" for j in first.findall("joint"))
    )


def _mjcf_numbers(text: str, count: int, path: Path, where: str) -> np.ndarray:
    try:
        values = np.array([float(v) for v in text.split()], dtype=float)
    except ValueError:
        raise ModelError(f"{path}: {where}: '{text}' is not a list of numbers") from None
    if values.shape != (count,) or not np.all(np.isfinite(values)):
        raise ModelError(f"{path}: {where}: expected {count} finite numbers, got '{text}'")
    return values
