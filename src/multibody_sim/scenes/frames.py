"""A scene's frames by name: the lookup every declaration that names a frame goes through, with a message that
names the valid ones."""

from __future__ import annotations

import pinocchio as pin

from ..exceptions import SceneError
from ..text import name_hint


def frame_id(model: pin.Model, name: str, key: str, *, moving: bool = False) -> int:
    """The id of a frame by name, or SceneError naming the valid ones (only those on moving bodies if `moving`)."""
    if name != "universe" and model.existFrame(name):
        fid = model.getFrameId(name)
        if not moving or model.frames[fid].parentJoint != 0:
            return fid
    names = [f.name for f in model.frames if f.name != "universe" and (f.parentJoint != 0 or not moving)]
    if name not in names:
        if moving and model.existFrame(name):
            raise SceneError(f"{key}: '{name}' is welded to the world: nothing there moves (valid: {', '.join(names)})")
        raise SceneError(f"{key}: unknown frame '{name}' ({name_hint(name, names)})")  # talos has 60 frames
    return model.getFrameId(name)
