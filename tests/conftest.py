"""Shared fixtures: cached catalog robots and small URDFs written in code."""

from __future__ import annotations

import functools
import os
import signal
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import pytest

import multibody_sim as ms
from multibody_sim import native
from multibody_sim.scenes import shipped_scenes
from multibody_sim.scenes.parse import parse_toml

# The tests stand for a user at a terminal, where Ctrl-C interrupts. A suite started in the background by a
# non-interactive shell (`cmd &`) inherits SIGINT ignored, which Python then keeps (no KeyboardInterrupt, and the
# children it starts ignore SIGINT too): give it back its default handler, which children reset to SIG_DFL.
if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
    signal.signal(signal.SIGINT, signal.default_int_handler)


# A test of the native kernel: skipped where the extension is not built, but not in CI, which builds it (its absence
# fails there).
needs_native = pytest.mark.skipif(
    not native.available and os.environ.get("CI") != "true",
    reason=f"the native kernel is not available here: {native.why_unavailable}",
)


def shipped(name: str, *, drop: tuple[str, ...] = ()) -> dict[str, Any]:
    """A shipped scene's tables (to add or change some), without the tables `drop` names (e.g. its "controller" and
    its "simulation" settings)."""
    path = shipped_scenes()[name]
    tables = parse_toml(path.read_text(encoding="utf-8"), str(path))
    for table in drop:
        tables.pop(table, None)
    return tables


def ctrl_c_at(t_stop: float, nv: int) -> Callable[..., Any]:
    """A controller of zero torques, shape (nv,), that raises KeyboardInterrupt (a user's Ctrl-C) from time t_stop [s]
    on (put t_stop between two control instants: round-off cannot move the stop then)."""
    import numpy as np

    def controller(t: float, q: Any, v: Any) -> Any:
        if t >= t_stop:
            raise KeyboardInterrupt
        return np.zeros(nv)

    return controller


def contact_steps(scene: ms.Scene, steps: int, dt: float) -> Iterator[tuple[Any, Any, Any]]:
    """The Python time-stepper's first `steps` steps of `dt` [s] from the scene's initial state under zero torques:
    after each, its active contact problem, the problem's impulses and the velocity v [nv]."""
    import numpy as np

    from multibody_sim.integrators.timestepping import TimeStepping

    method = TimeStepping()
    q, v, state = scene.q0, scene.v0, method.init(scene, scene.q0, scene.v0)
    for _ in range(steps):
        attempt = method.attempt(scene, q, v, np.zeros(scene.nv), dt, 0.0, state)
        q, v, state = attempt.q, attempt.v, attempt.state
        problem, impulses = state.active
        yield problem, impulses, v


@functools.cache
def _cached_robot(name: str, floating_base: bool | None, damping: bool) -> ms.Robot:
    return ms.load_robot(name, floating_base=floating_base, damping=damping)


@pytest.fixture(scope="session")
def robot() -> Callable[..., ms.Robot]:
    """robot(name, floating_base=None, damping=True): a catalog robot, loaded once per session.

    Robots hold a Pinocchio Data workspace: tests must not rely on its contents between calls.
    """

    def get(name: str, floating_base: bool | None = None, damping: bool = True) -> ms.Robot:
        return _cached_robot(name, floating_base, damping)

    return get


@pytest.fixture
def write_urdf(tmp_path: Path) -> Callable[[str, str], Path]:
    """write_urdf(text, name="robot.urdf") -> path: a URDF file in a fresh temporary folder."""

    def write(text: str, name: str = "robot.urdf") -> Path:
        path = tmp_path / name
        path.write_text(text)
        return path

    return write


def link(name: str, mass: float = 1.0, com: str = "0 0 -0.5", inertia: str = "0.01 0.01 0.01") -> str:
    """URDF text of a link with a diagonal inertia (ixx iyy izz)."""
    ixx, iyy, izz = inertia.split()
    return (
        f'<link name="{name}"><inertial><origin xyz="{com}"/><mass value="{mass}"/>'
        f'<inertia ixx="{ixx}" ixy="0" ixz="0" iyy="{iyy}" iyz="0" izz="{izz}"/></inertial></link>'
    )


def joint(
    name: str,
    parent: str,
    child: str,
    kind: str = "revolute",
    xyz: str = "0 0 0",
    axis: str = "0 1 0",
    limits: str = 'lower="-3" upper="3" effort="10" velocity="10"',
    damping: float | None = None,
) -> str:
    """URDF text of a joint."""
    dyn = f'<dynamics damping="{damping}"/>' if damping is not None else ""
    lim = f"<limit {limits}/>" if kind in ("revolute", "prismatic") else ""
    return (
        f'<joint name="{name}" type="{kind}"><parent link="{parent}"/><child link="{child}"/>'
        f'<origin xyz="{xyz}"/><axis xyz="{axis}"/>{lim}{dyn}</joint>'
    )


def urdf(*parts: str, name: str = "test_robot") -> str:
    """A whole URDF document from link() and joint() parts."""
    return f'<?xml version="1.0"?><robot name="{name}">{"".join(parts)}</robot>'


def on_kernel(native_on: bool, run: Callable[[], Any], monkeypatch: pytest.MonkeyPatch) -> Any:
    """run() on the native kernel (native_on) or the Python one (MULTIBODY_SIM_NATIVE=1 or 0 while it runs)."""
    monkeypatch.setenv("MULTIBODY_SIM_NATIVE", "1" if native_on else "0")
    try:
        return run()
    finally:
        monkeypatch.delenv("MULTIBODY_SIM_NATIVE")


def both(run: Callable[[], Any], monkeypatch: pytest.MonkeyPatch) -> tuple[Any, Any]:
    """(native, python) results of the same run."""
    return on_kernel(True, run, monkeypatch), on_kernel(False, run, monkeypatch)


# What a run's native and Python renderings must share bit for bit (tests/test_native_*.py).
FIELDS = ("t", "q", "v", "tau", "kinetic_energy", "potential_energy", "work", "dissipated", "energy_error")
COUNTS = ("steps", "rejected_steps", "evaluations", "controller_calls", "saturated_controls", "saturated_dofs")


def assert_same_stepper(a: Any, b: Any, *, energy_error: bool = True) -> None:
    """Two Steppers' state, ledger, stats and (unless told not to) energy error equal bit for bit."""
    import numpy as np

    np.testing.assert_array_equal(a.q, b.q)
    np.testing.assert_array_equal(a.v, b.v)
    assert a.ledger == b.ledger and a.stats == b.stats
    if energy_error:
        assert a.energy_error == b.energy_error


def assert_same_run(a: Any, b: Any, stats: tuple[str, ...] = COUNTS) -> None:
    """Every sample field, every ledger entry, the status and the named stats of two trajectories equal bit for
    bit."""
    import numpy as np

    for name in FIELDS:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert a.ledger.keys() == b.ledger.keys()
    for name in a.ledger:
        np.testing.assert_array_equal(a.ledger[name].energy, b.ledger[name].energy, err_msg=name)
    assert a.status == b.status
    for key in stats:
        assert a.stats[key] == b.stats[key], key
