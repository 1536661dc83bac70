"""Contact forces as arrows over a recording: one arrow per simultaneous contact, animated with the motion.

An arrow starts at a contact point and points along the force on the second body of the pair (the impulse of the
step that ended at the sample shown, over that step: the mean force [N]); the largest force of the run is
ARROW_LENGTH long, the others in proportion. Arrows of contacts that are not active are shrunk to nothing.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pinocchio as pin

from ..exceptions import InvalidArgumentError
from ..trajectory import Trajectory
from ._deps import require
from .meshes import MeshPart

FORCES = "/meshcat/forces"
ARROW_LENGTH = 0.2  # [m]: the largest force of the run
_ARROW_COLOR = (0.85, 0.1, 0.1, 1.0)
_HIDDEN = 1e-6  # the scale of an arrow with no contact behind it
_Z = np.array([0.0, 0.0, 1.0])


def arrow_part() -> MeshPart:
    """A unit arrow along +z from the origin: a shaft of 0.8 and a head of 0.2 (its width does not scale)."""
    trimesh = require("trimesh", "contact force arrows")
    shaft = trimesh.creation.cylinder(radius=0.006, height=0.8, sections=16)
    shaft.apply_translation([0.0, 0.0, 0.4])
    head = trimesh.creation.cone(radius=0.016, height=0.2, sections=16)
    head.apply_translation([0.0, 0.0, 0.8])
    mesh = trimesh.util.concatenate([shaft, head])
    return MeshPart(
        np.asarray(mesh.vertices, dtype=np.float32),
        np.asarray(mesh.vertex_normals, dtype=np.float32),
        np.asarray(mesh.faces, dtype=np.int64),
        _ARROW_COLOR,
    )


def force_arrows(trajectory: Trajectory, times: np.ndarray) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """(setup commands, animation entries) of the trajectory's contact forces at the display times.

    Raises:
        InvalidArgumentError: the trajectory records no contacts (it is not a contact scene's run).
    """
    from .scene import _keys, _mesh_command

    contacts = trajectory.contacts
    if contacts is None:
        raise InvalidArgumentError(
            "the trajectory records no contacts (forces are drawn for runs of scenes with contact)"
        )
    dt = float(trajectory.metadata.get("options", {}).get("dt", math.nan))
    if not (math.isfinite(dt) and dt > 0):
        raise InvalidArgumentError("the trajectory's metadata has no step (options.dt): its forces are unknown")
    t = np.asarray(trajectory.t, dtype=float)
    shown = np.clip(np.searchsorted(t, times, side="right") - 1, 0, len(t) - 1)  # the sample on display
    counts = np.bincount(contacts.sample, minlength=len(t)) if len(contacts.sample) else np.zeros(len(t), int)
    slots = int(counts[shown].max()) if len(shown) else 0
    if slots == 0:
        return [], []
    forces = contacts.impulse / dt
    largest = float(np.linalg.norm(forces, axis=1).max()) or 1.0
    starts = np.searchsorted(contacts.sample, np.arange(len(t)))
    umsgpack = require("umsgpack", "the meshcat viewer")
    part = arrow_part()
    keys = (np.asarray(times, dtype=float) - float(times[0])).tolist()
    setup: list[dict[str, Any]] = [{"type": "delete", "path": FORCES}]
    animations = []
    for k in range(slots):
        positions = np.zeros((len(times), 3))
        quaternions = np.tile([0.0, 0.0, 0.0, 1.0], (len(times), 1))
        scales = np.full((len(times), 3), _HIDDEN)
        for f, i in enumerate(shown):
            if k >= counts[i]:
                continue
            row = starts[i] + k
            force = forces[row]
            size = float(np.linalg.norm(force))
            if size == 0.0:
                continue
            positions[f] = contacts.point[row]
            quaternions[f] = pin.Quaternion.FromTwoVectors(_Z, force / size).coeffs()  # x y z w
            scales[f] = (1.0, 1.0, ARROW_LENGTH * size / largest)
        path = f"{FORCES}/{k}"
        setup.append(_mesh_command(umsgpack, f"{path}/arrow", part))
        tracks = [
            {"name": ".position", "type": "vector3", "keys": _keys(keys, positions)},
            {"name": ".quaternion", "type": "quaternion", "keys": _keys(keys, quaternions)},
            {"name": ".scale", "type": "vector3", "keys": _keys(keys, scales)},
        ]
        animations.append({"path": path, "clip": {"fps": 1, "name": "default", "tracks": tracks}})
    return setup, animations
