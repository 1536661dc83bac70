"""Determinism as a promise (README "Determinism", CONTRACTS.md): the same inputs give byte-identical samples across
processes, `num_threads`, the two kernels, chunked and unchunked runs, and the local and Ray backends.

Each check hashes every sample array as bytes (times, states, torques, energies, the ledger, constraint and contact
records, status, step and solver counts; not the wall time or the metadata): -0.0 against 0.0, or two NaN payloads,
differ here where assert_array_equal would let them pass. Cheap on purpose: go2_standing (contact on a floating
base, the native contact step) for 30 ms, and ur5 under a controller for 50 ms.

Run as a script, this file prints the digests of RUNS as JSON (the second process of the first test).
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import multibody_sim as ms

ENERGIES = ("kinetic_energy", "potential_energy", "total_energy", "work", "dissipated", "energy_error")


def digest(run: ms.Trajectory) -> str:
    """SHA-256 of a trajectory's samples as bytes, with its status and counts (not wall time, not metadata)."""
    h = hashlib.sha256()

    def add(label: str, value: Any) -> None:
        array = np.ascontiguousarray(value)
        h.update(f"{label}:{array.dtype.str}:{array.shape}:".encode())
        h.update(array.tobytes())

    for name in ("t", "q", "v", "tau", *ENERGIES):
        add(name, getattr(run, name))
    for name, entry in run.ledger.items():
        add(f"ledger.{name}.{entry.kind}", entry.energy)
    for name, record in run.constraints.items():
        for part in ("force", "drift", "velocity_drift"):
            add(f"constraint.{name}.{part}", getattr(record, part))
    if run.contacts is not None:
        h.update(json.dumps(run.contacts.bodies).encode())
        for part in ("sample", "pair", "point", "normal", "impulse"):
            add(f"contacts.{part}", getattr(run.contacts, part))
    counts = {key: value for key, value in run.stats.items() if isinstance(value, (int, dict))}  # not wall time
    h.update(json.dumps([run.status, counts, run.limit_violations.__dict__], sort_keys=True, default=str).encode())
    return h.hexdigest()


def batch_digests(batch: Any) -> list[str]:
    return [digest(batch.element(b)) for b in range(len(batch.status))]


def go2() -> ms.Scene:
    return ms.load_scene("go2_standing")


def go2_starts(scene: ms.Scene, B: int = 4) -> tuple[np.ndarray, np.ndarray]:
    """B starts of go2: its standing pose, dropped from heights 0..3 mm and pushed sideways."""
    Q0, V0 = np.tile(scene.q0, (B, 1)), np.zeros((B, scene.nv))
    Q0[:, 2] += np.linspace(0.0, 3e-3, B)
    V0[:, 1] = np.linspace(-0.2, 0.2, B)
    return Q0, V0


def ur5_run(**options: Any) -> ms.Trajectory:
    ur5 = ms.load_robot("ur5")
    hold = ms.PDGravity(ur5, ur5.default_pose(), kp=200.0)
    q0 = ur5.default_pose() + 0.1
    return ms.simulate(ur5, q0, np.zeros(ur5.nv), duration=0.05, dt=1e-3, controller=hold, **options)


# What the second process computes too.
RUNS: dict[str, Callable[[], list[str]]] = {
    "go2_standing": lambda: [digest(go2().run(duration=0.03))],
    "ur5 PD + gravity, rk4": lambda: [digest(ur5_run())],
    "go2 rollout, 2 threads": lambda: batch_digests(
        ms.rollout(go2(), *go2_starts(go2()), duration=0.03, dt=1e-3, integrator="timestepping", num_threads=2)
    ),
}


def test_two_processes_give_the_same_bytes():
    """A second Python process (its own hash seed, its own allocations) computes the same bytes."""
    here = {name: run() for name, run in RUNS.items()}
    child = subprocess.run(
        [sys.executable, str(Path(__file__).resolve())],
        capture_output=True,
        text=True,
        timeout=600,
        env={**os.environ, "PYTHONHASHSEED": "12345"},
    )
    assert child.returncode == 0, child.stderr[-3000:]
    assert json.loads(child.stdout) == here


def test_thread_counts_give_the_same_bytes():
    scene = go2()
    Q0, V0 = go2_starts(scene)
    runs = [ms.rollout(scene, Q0, V0, duration=0.03, dt=1e-3, integrator="timestepping", num_threads=n) for n in (1, 2)]
    assert batch_digests(runs[0]) == batch_digests(runs[1])
    assert len(set(batch_digests(runs[0]))) == len(Q0)  # the rows differ from one another: the hash sees them


def test_the_native_and_python_kernels_give_the_same_bytes(monkeypatch: pytest.MonkeyPatch):
    from conftest import both

    from multibody_sim import native

    if not native.available:
        if os.environ.get("CI") == "true":
            pytest.fail(f"the native kernel is not available in CI: {native.why_unavailable}")
        pytest.skip(f"the native kernel is not available here: {native.why_unavailable}")
    scene = go2()
    runs = {
        "go2_standing": lambda: scene.run(duration=0.03),
        "ur5": ur5_run,
        "go2 rollout": lambda: ms.rollout(scene, *go2_starts(scene), duration=0.03, dt=1e-3, integrator="timestepping"),
    }
    for name, run in runs.items():
        native_run, python_run = both(run, monkeypatch)
        kernels = [r.metadata.get("kernel") for r in (native_run, python_run)]
        assert kernels[0] == "native" and kernels[1].startswith("python"), (name, kernels)
        if isinstance(native_run, ms.Trajectory):
            assert digest(native_run) == digest(python_run), name
        else:
            assert batch_digests(native_run) == batch_digests(python_run), name


def test_a_chunked_run_gives_the_bytes_of_one_that_is_not(tmp_path: Path):
    """Streamed to disk in chunks of 7 samples, merged, loaded: the samples of the run kept in memory (contacts
    included: their sample indices count from the run's start across chunks)."""
    scene = go2()
    whole = scene.run(duration=0.03)
    scene.run(duration=0.03, out=tmp_path / "go2.npz", chunk=7)
    assert digest(ms.Trajectory.load(tmp_path / "go2.npz")) == digest(whole)
    ur5_run(out=tmp_path / "ur5.npz", chunk=7)
    assert digest(ms.Trajectory.load(tmp_path / "ur5.npz")) == digest(ur5_run())


def test_a_ray_run_gives_the_bytes_of_a_local_one(monkeypatch: pytest.MonkeyPatch):
    """rollout(backend="ray") on a local Ray instance: a contact scene (pickled as its declaration, built again on
    each worker) and ur5 under a closure (shipped by value) with one diverging element, each split into chunks."""
    # Ray replaces a node address of 127.0.0.1 by the machine's reachable one unless it runs without cluster
    # support: the test instance then binds every server to the loopback interface only.
    monkeypatch.setenv("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")
    try:
        import ray
        import ray._private.ray_constants
    except ImportError:
        if os.environ.get("CI") == "true":
            raise  # CI installs the test extra, which has Ray: its absence is a failure there
        pytest.skip("Ray is not installed (pip install 'multibody-sim[ray]'); CI runs this test")
    scene = go2()
    Q0, V0 = go2_starts(scene)
    contact = dict(duration=0.03, dt=1e-3, integrator="timestepping")
    ur5 = ms.load_robot("ur5")  # loaded here: what the tasks receive is this object, pickled
    rng = np.random.default_rng(11)
    U0 = np.array([ur5.random_configuration(rng) for _ in range(7)])
    W0 = rng.normal(scale=0.5, size=(7, ur5.nv))
    W0[4] = [0.0, 3e3, 0.0, -3e3, 0.0, 0.0]  # diverges: one chunk holds a failure, the others must not care
    gain = 50.0
    controller = lambda t, q, v: gain * (0.1 - q) - v  # noqa: E731  (a closure: shipped by value)
    arm = dict(duration=0.02, dt=2e-3, output_dt=4e-3, controller=controller)
    local = [ms.rollout(scene, Q0, V0, **contact), ms.rollout(ur5, U0, W0, **arm)]
    monkeypatch.setattr(ray._private.ray_constants, "ENABLE_RAY_CLUSTER", False)  # if Ray was imported before
    ray.init(num_cpus=2, include_dashboard=False, _node_ip_address="127.0.0.1", log_to_driver=False)
    try:
        assert ray.util.get_node_ip_address() == "127.0.0.1"
        distributed = [
            ms.rollout(scene, Q0, V0, backend="ray", chunk_size=2, **contact),
            ms.rollout(ur5, U0, W0, backend="ray", chunk_size=3, **arm),
        ]
    finally:
        ray.shutdown()
    assert [d.metadata["chunks"] for d in distributed] == [2, 3]
    assert all(d.metadata["backend"] == "ray" for d in distributed)
    assert "diverged" in local[1].status.tolist() and distributed[1].messages == local[1].messages
    for here, there in zip(local, distributed, strict=True):
        assert batch_digests(there) == batch_digests(here)


if __name__ == "__main__":  # the second process of test_two_processes_give_the_same_bytes
    print(json.dumps({name: run() for name, run in RUNS.items()}))
