"""What every trajectory's metadata starts with: package versions and how its robot (or scene) was made."""

from __future__ import annotations

import functools
from typing import Any


def run_metadata(system: Any) -> dict[str, Any]:
    """Package versions and the robot's description (its load_robot arguments, URDF SHA-256, a scene's TOML), and
    a scene's parameter values where they are not the declared ones (Scene.with_parameters: a randomised row's)."""
    parameters = getattr(system, "parameters", None)
    return {
        **({"parameters": parameters} if parameters is not None else {}),
        "versions": dict(versions()),
        "robot": {
            "name": system.name,
            "nq": system.nq,
            "nv": system.nv,
            "floating_base": system.floating_base,
            "damping": bool(system.source.get("load_robot", {}).get("damping", True)),
            "joint_names": system.joint_names,
            "dof_names": system.dof_names,
            **system.source,  # load_robot (the full arguments), urdf_path, urdf_sha256; a scene's TOML
        },
        **sensor_metadata(system),
    }


def sensor_metadata(system: Any) -> dict[str, Any]:
    """{"sensors": [{name, kind, components}, ...]} for a system with sensors (Trajectory.sensors' columns), else
    {}."""
    sensors = getattr(system, "sensors", None)
    if sensors is None:
        return {}
    return {
        "sensors": [
            {"name": p.spec.name, "kind": p.spec.kind, "components": list(p.components)} for p in sensors.placed
        ]
    }


@functools.cache
def versions() -> dict[str, str]:
    """Versions of the packages a result depends on ("not installed" where missing)."""
    import importlib.metadata  # here: it costs a few percent of `import multibody_sim`

    found = {}
    for dist in ("multibody-sim", "pin", "example-robot-data", "numpy", "yourdfpy"):
        try:
            found[dist] = importlib.metadata.version(dist)
        except importlib.metadata.PackageNotFoundError:
            found[dist] = "not installed"
    return found
