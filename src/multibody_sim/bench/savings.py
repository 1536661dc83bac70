"""What a scene saves: its time per step against its full robot's (nothing locked, no elements, no constraints), a
short side benchmark that `run --report-savings`, `inspect` and scripts/scene_report.py run when asked."""

from __future__ import annotations

import math
import time
from typing import Any

import numpy as np

from ..exceptions import InvalidArgumentError
from ..robot import Robot
from ..scenes import Scene
from ..scenes.spec import CONTACT_INTEGRATOR
from ..simulation import simulate
from ..validation import positive_count


def measure_savings(scene: Scene, steps: int = 200, repeats: int = 5) -> dict[str, Any]:
    """Time per step of `scene` against its full robot. RK4 at 1 ms; a contact scene with its integrator,
    timestepping, against the bare robot with the same integrator.

    Args:
        scene: the scene.
        steps: steps per timing (of 1 ms each).
        repeats: timings per system; the median is kept.

    Returns:
        {"scene_us": median CPU µs per step, "full_us": median CPU µs per step of the full model (nan for a scene of
        objects only: there is no robot), "ratio": scene/full, "integrator": the integrator's name}.

    Raises:
        InvalidArgumentError: scene is not a Scene, or steps or repeats is not a positive whole number.
    """
    if not isinstance(scene, Scene):
        raise InvalidArgumentError(f"scene must be a Scene (load_scene's), got {type(scene).__name__}")
    steps = positive_count(steps, "steps")
    repeats = positive_count(repeats, "repeats")
    integrator = CONTACT_INTEGRATOR if scene.contact is not None else "rk4"

    def per_step(system: Robot, q0: np.ndarray) -> float:
        times = []
        for _ in range(repeats):
            start = time.process_time()
            simulate(
                system,
                q0,
                scene.v0 if system is scene else np.zeros(system.nv),
                duration=steps * 1e-3,
                dt=1e-3,
                integrator=integrator,
                progress=False,
                output_dt=0.01,
            )
            times.append((time.process_time() - start) / steps * 1e6)
        return float(np.median(times))

    full = scene.full_robot
    scene_us = per_step(scene, scene.q0)
    full_us = per_step(full, scene.full_configuration(scene.q0)) if full.nv else math.nan
    return {"scene_us": scene_us, "full_us": full_us, "ratio": scene_us / full_us, "integrator": integrator}
