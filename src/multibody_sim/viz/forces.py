"""Contact forces as arrows over a recording: one arrow per simultaneous contact, animated with the motion.

An arrow starts at a contact point and points along the force on the second body of the pair (the impulse of the
step that ended at the sample shown, over that step: the mean force [N], Trajectory.contact_forces); the largest
force of the run is ARROW_LENGTH long, the others in proportion. Arrows of contacts that are not active are shrunk
to nothing. The HTML export (and videos) animate them with the motion; the live viewer animates them too, or moves
them frame by frame when it streams a recording (Viewer.play).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
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
FORCE_LIMIT = 1e300  # [N]: arrows are scaled by the largest force, whose norm must not overflow
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


@dataclass(frozen=True)
class ArrowTracks:
    """Where each arrow slot is at each display time: slot k shows the k-th contact of the sample on display.

    Attributes:
        positions: arrow origins (contact points), world [m], shape (slots, n, 3).
        quaternions: rotations taking +z onto the force's direction, x y z w, shape (slots, n, 4).
        scales: (1, 1, length [m]) per slot and time (a hidden slot shrinks to nothing), shape (slots, n, 3).
    """

    positions: np.ndarray
    quaternions: np.ndarray
    scales: np.ndarray

    def __len__(self) -> int:
        return len(self.positions)

    def setup_commands(self) -> list[dict[str, Any]]:
        """Remove the previous arrows, then create one arrow mesh per slot under FORCES/k/arrow."""
        return [{"type": "delete", "path": FORCES}, *slot_commands(0, len(self))]

    def pose_commands(self, f: int) -> list[dict[str, Any]]:
        """One set_transform per slot placing the arrows at display time index f (the live viewer's frames)."""
        return [
            slot_pose_command(k, self.positions[k, f], self.quaternions[k, f], self.scales[k, f])
            for k in range(len(self))
        ]

    def animations(self, times: np.ndarray) -> list[dict[str, Any]]:
        """meshcat animation entries of the slots over the display times (joined to the motion's animation)."""
        from .scene import _keys

        keys = (np.asarray(times, dtype=float) - float(times[0])).tolist()
        animations = []
        for k in range(len(self)):
            tracks = [
                {"name": ".position", "type": "vector3", "keys": _keys(keys, self.positions[k])},
                {"name": ".quaternion", "type": "quaternion", "keys": _keys(keys, self.quaternions[k])},
                {"name": ".scale", "type": "vector3", "keys": _keys(keys, self.scales[k])},
            ]
            animations.append({"path": f"{FORCES}/{k}", "clip": {"fps": 1, "name": "default", "tracks": tracks}})
        return animations


def arrow_tracks(trajectory: Trajectory, times: np.ndarray) -> ArrowTracks:
    """The arrows of the trajectory's contact forces at the display times (as many slots as the most contacts
    any displayed sample has; none when no displayed sample has a contact).

    Raises:
        InvalidArgumentError: the trajectory records no contacts (it is not a contact scene's run).
    """
    contacts = trajectory.contacts
    if contacts is None:
        raise InvalidArgumentError(
            "the trajectory records no contacts (forces are drawn for runs of scenes with contact)"
        )
    t = np.asarray(trajectory.t, dtype=float)
    times = np.asarray(times, dtype=float)
    shown = np.clip(np.searchsorted(t, times, side="right") - 1, 0, len(t) - 1)  # the sample on display
    counts = np.bincount(contacts.sample, minlength=len(t)) if len(contacts.sample) else np.zeros(len(t), int)
    slots = int(counts[shown].max()) if len(shown) else 0
    positions = np.zeros((slots, len(times), 3))
    quaternions = np.tile([0.0, 0.0, 0.0, 1.0], (slots, len(times), 1))
    scales = np.full((slots, len(times), 3), _HIDDEN)
    if slots:
        forces = trajectory.contact_forces()  # the mean force over each step [N]
        with np.errstate(over="ignore", invalid="ignore"):  # an overflow is refused below, in one line
            sizes = np.linalg.norm(forces, axis=1)
        _check_contacts(contacts.point, sizes, contacts.sample, t)
        largest = float(sizes.max()) or 1.0
        starts = np.searchsorted(contacts.sample, np.arange(len(t)))
        for f, i in enumerate(shown):
            for k in range(int(counts[i])):
                row = starts[i] + k
                positions[k, f] = contacts.point[row]
                quaternions[k, f], scales[k, f] = arrow_pose(forces[row], largest)
    return ArrowTracks(positions, quaternions, scales)


def _check_contacts(points: np.ndarray, sizes: np.ndarray, sample: np.ndarray, t: np.ndarray) -> None:
    """Refuse contacts a view cannot draw: a point beyond VIEW_REACH or a force beyond FORCE_LIMIT (not finite)."""
    from .scene import VIEW_REACH

    far = np.abs(points).max(axis=1) if len(points) else np.zeros(0)
    for what, values, limit, unit in (
        ("point", far, VIEW_REACH, "m from the world origin"),
        ("force", sizes, FORCE_LIMIT, "N"),
    ):
        bad = ~(values <= limit)  # NaN is bad too
        if bad.any():
            k = int(np.flatnonzero(bad)[0])
            raise InvalidArgumentError(
                f"a contact {what} of the trajectory is {values[k]:.3g} {unit} at t = {t[sample[k]]:.6g} s, beyond "
                f"the {limit:g} an arrow can show (the run diverged, or the file was edited)"
            )


def arrow_pose(force: np.ndarray, reference: float) -> tuple[np.ndarray, np.ndarray]:
    """(quaternion x y z w taking +z onto the force, scale (1, 1, ARROW_LENGTH |force| / reference)) of one arrow;
    a zero force is hidden (scaled to nothing)."""
    size = float(np.linalg.norm(force))
    if size == 0.0:
        return np.array([0.0, 0.0, 0.0, 1.0]), np.full(3, _HIDDEN)
    quaternion = pin.Quaternion.FromTwoVectors(_Z, force / size).coeffs()  # x y z w
    return np.asarray(quaternion, dtype=float), np.array([1.0, 1.0, ARROW_LENGTH * size / reference])


def slot_commands(first: int, end: int) -> list[dict[str, Any]]:
    """The arrow meshes of slots first .. end - 1, under FORCES/k/arrow."""
    from .scene import _mesh_command

    umsgpack = require("umsgpack", "the meshcat viewer")
    part = arrow_part()
    return [_mesh_command(umsgpack, f"{FORCES}/{k}/arrow", part) for k in range(first, end)]


def slot_pose_command(k: int, position: np.ndarray, quaternion: np.ndarray, scale: np.ndarray) -> dict[str, Any]:
    """The set_transform placing arrow slot k: at position, rotated by quaternion (x y z w), scaled along its own
    axes."""
    from .scene import transform_command

    matrix = np.eye(4)
    x, y, z, w = quaternion
    matrix[:3, :3] = pin.Quaternion(w, x, y, z).matrix() * scale
    matrix[:3, 3] = position
    return transform_command(f"{FORCES}/{k}", matrix)


class LiveArrows:
    """Contact-force arrows drawn as a run computes (Viewer.live(forces=True)): each frame shows the contacts of
    the step that ended at its sample, an arrow ARROW_LENGTH long for a force equal to the system's weight (the run's
    largest force is not known yet, as a recording's is). Slots are created as more contacts appear; unused ones
    are hidden.

    Args:
        send: sends one meshcat command to the page.
        weight: the reference force [N]: total mass × |gravity| (1 N for a weightless system).
    """

    def __init__(self, send: Any, weight: float):
        self.send, self.weight = send, weight if weight > 0 else 1.0
        self.slots = 0  # arrow meshes in the page
        self.latest: tuple[np.ndarray | None, float] = (None, math.nan)

    def contacts(self, rows: np.ndarray | None, dt: float) -> None:
        """The contacts of the latest sample: (k, 11) rows as Trajectory.contacts holds them (point at 2:5, impulse
        at 8:11 [N·s]) over its step dt [s], or None."""
        self.latest = (rows, dt)

    def draw(self) -> None:
        """Place the arrows of the latest sample's contacts (before the frame that shows its configuration)."""
        rows, dt = self.latest
        count = 0 if rows is None else len(rows)
        if count > self.slots:
            if self.slots == 0:
                self.send({"type": "delete", "path": FORCES})
            for command in slot_commands(self.slots, count):
                self.send(command)
            self.slots = count
        for k in range(self.slots):
            if rows is not None and k < count:
                quaternion, scale = arrow_pose(rows[k, 8:11] / dt, self.weight)
                self.send(slot_pose_command(k, rows[k, 2:5], quaternion, scale))
            else:
                self.send(slot_pose_command(k, np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]), np.full(3, _HIDDEN)))


def force_arrows(trajectory: Trajectory, times: np.ndarray) -> tuple[list[dict[str, Any]], list[dict[str, Any]]]:
    """(setup commands, animation entries) of the trajectory's contact forces at the display times (the HTML
    export's; see arrow_tracks)."""
    tracks = arrow_tracks(trajectory, times)
    if not len(tracks):
        return [], []
    return tracks.setup_commands(), tracks.animations(times)
