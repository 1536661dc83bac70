"""Nothing lost: runs write their samples to `out` however they end, and chunked runs stream to disk."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import textwrap
import tracemalloc
from pathlib import Path

import numpy as np
import pytest

import multibody_sim as ms

FIELDS = (
    "t",
    "q",
    "v",
    "tau",
    "kinetic_energy",
    "potential_energy",
    "total_energy",
    "work",
    "dissipated",
    "energy_error",
)


def same(a: ms.Trajectory, b: ms.Trajectory) -> None:
    for name in FIELDS:
        np.testing.assert_array_equal(np.asarray(getattr(a, name)), np.asarray(getattr(b, name)), err_msg=name)
    assert a.ledger.keys() == b.ledger.keys()
    for name in a.ledger:
        np.testing.assert_array_equal(a.ledger[name].energy, b.ledger[name].energy)
    assert a.status == b.status
    assert a.limit_violations == b.limit_violations


def push(t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
    return np.array([0.3 * np.sin(3.0 * t), -0.2])


@pytest.mark.parametrize("chunk", [1, 7, 100, 1000])
def test_a_chunked_run_equals_the_in_memory_run(robot, tmp_path: Path, chunk: int) -> None:
    pendulum = robot("double_pendulum")  # damped, so both ledger elements are exercised
    kwargs = dict(duration=0.5, dt=1e-3, output_dt=2e-3, controller=push)
    memory = ms.simulate(pendulum, [2.5, 0.3], [0.0, 1.0], **kwargs)
    out = tmp_path / "run.npz"
    streamed = ms.simulate(pendulum, [2.5, 0.3], [0.0, 1.0], out=out, chunk=chunk, **kwargs)
    same(memory, streamed)
    assert isinstance(streamed.q, np.memmap)  # bounded memory: the arrays stay on disk
    assert sorted(os.listdir(tmp_path)) == ["run.npz"]  # the parts were merged and removed
    same(memory, ms.Trajectory.load(out))


def test_limit_violations_are_combined_across_chunks(tmp_path: Path, write_urdf) -> None:
    from conftest import joint, link, urdf

    path = write_urdf(
        urdf(
            link("base", com="0 0 0"),
            link("bob"),
            joint("hinge", "base", "bob", limits='lower="-0.1" upper="0.1" effort="1" velocity="1"'),
        )
    )
    tight = ms.load_robot(path)
    memory = ms.simulate(tight, [0.5], [0.0], duration=2.0, dt=1e-3, output_dt=1e-2)
    streamed = ms.simulate(tight, [0.5], [0.0], duration=2.0, dt=1e-3, output_dt=1e-2, out=tmp_path / "r.npz", chunk=17)
    assert memory.limit_violations.count > 0
    assert streamed.limit_violations == memory.limit_violations


def test_out_without_chunks_is_written_however_the_run_ends(robot, tmp_path: Path) -> None:
    pendulum = robot("pendulum")
    done = ms.simulate(pendulum, [1.0], [0.0], duration=0.2, dt=1e-2, out=tmp_path / "done.npz")
    same(done, ms.Trajectory.load(tmp_path / "done.npz"))

    def stop(t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        if t > 0.095:
            raise KeyboardInterrupt
        return np.zeros(1)

    with pytest.raises(ms.SimulationInterrupted) as info:
        ms.simulate(pendulum, [1.0], [0.0], duration=0.2, dt=1e-2, controller=stop, out=tmp_path / "stop.npz")
    same(info.value.trajectory, ms.Trajectory.load(tmp_path / "stop.npz"))
    assert ms.Trajectory.load(tmp_path / "stop.npz").status == "interrupted"


@pytest.mark.parametrize("chunk", [3, 1000])
def test_an_interrupted_chunked_run_keeps_every_sample(robot, tmp_path: Path, chunk: int) -> None:
    pendulum = robot("pendulum")

    def stop(t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        if t > 0.2995:
            raise KeyboardInterrupt
        return np.zeros(1)

    with pytest.raises(ms.SimulationInterrupted) as memory:
        ms.simulate(pendulum, [1.0], [0.0], duration=1.0, dt=1e-3, output_dt=1e-2, controller=stop)
    with pytest.raises(ms.SimulationInterrupted) as streamed:
        ms.simulate(
            pendulum,
            [1.0],
            [0.0],
            duration=1.0,
            dt=1e-3,
            output_dt=1e-2,
            controller=stop,
            out=tmp_path / "r.npz",
            chunk=chunk,
        )
    same(memory.value.trajectory, streamed.value.trajectory)
    assert streamed.value.trajectory.t[-1] == pytest.approx(0.3)
    assert ms.Trajectory.load(tmp_path / "r.npz").status == "interrupted"


def test_a_diverged_chunked_run_keeps_its_finite_samples(robot, tmp_path: Path) -> None:
    dp = robot("double_pendulum", damping=False)
    args = ([3.0, 0.0], [40.0, -40.0])
    with pytest.raises(ms.SimulationError) as memory:
        ms.simulate(dp, *args, duration=20.0, dt=0.05, integrator="euler")
    with pytest.raises(ms.SimulationError) as streamed:
        ms.simulate(dp, *args, duration=20.0, dt=0.05, integrator="euler", out=tmp_path / "d.npz", chunk=2)
    assert str(streamed.value) == str(memory.value)
    same(memory.value.trajectory, streamed.value.trajectory)
    assert ms.Trajectory.load(tmp_path / "d.npz").status == "diverged"


def test_a_run_killed_before_merging_leaves_loadable_parts(tmp_path: Path) -> None:
    """A hard kill (no Python cleanup) between chunk writes: the parts folder loads as an incomplete run."""
    out = tmp_path / "killed.npz"
    script = textwrap.dedent(f"""
        import os
        import numpy as np
        import multibody_sim as ms
        robot = ms.load_robot("pendulum")
        def die(t, q, v):
            if t > 0.4995:
                os._exit(9)  # like SIGKILL: nothing is flushed or merged
            return np.zeros(1)
        ms.simulate(robot, [1.0], [0.0], duration=1.0, dt=1e-3, output_dt=1e-2, controller=die,
                    out={str(out)!r}, chunk=20)
    """)
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert result.returncode == 9, result.stderr
    assert not out.exists()
    parts = sorted(os.listdir(out.with_name("killed.npz.parts")))
    assert parts == ["chunk_000000.npz", "chunk_000001.npz"]  # 40 samples on disk, the 10 in memory lost
    for path in (out, out.with_name("killed.npz.parts")):  # the file's name or the folder itself
        survivor = ms.Trajectory.load(path)
        assert survivor.status == "incomplete"
        np.testing.assert_allclose(survivor.t, np.arange(40) * 1e-2, atol=1e-12)
        reference = ms.simulate(ms.load_robot("pendulum"), [1.0], [0.0], duration=0.39, dt=1e-3, output_dt=1e-2)
        np.testing.assert_array_equal(survivor.q, reference.q)
        np.testing.assert_array_equal(survivor.energy_error, reference.energy_error)


def test_chunked_runs_keep_memory_bounded(robot, tmp_path: Path) -> None:
    """Peak traced memory (numpy reports its buffers to tracemalloc) of a run sampled at every step: streamed in
    chunks it is bounded by a chunk; in memory it grows with the samples. (scripts/memory_study.py measures the
    process's peak RSS on a 1e7-step run.)"""
    pendulum = robot("pendulum")
    peaks = {}
    for name, sink in (("memory", {}), ("chunked", {"out": tmp_path / "long.npz", "chunk": 500})):
        tracemalloc.start()
        traj = ms.simulate(pendulum, [1.0], [0.0], duration=2.0, dt=2e-4, integrator="euler", **sink)
        peaks[name] = tracemalloc.get_traced_memory()[1]
        tracemalloc.stop()
        assert len(traj.t) == 10_001
    # In memory: 7 float64 per sample in the buffer alone: 10k × 7 × 8 B = 560 kB.
    assert peaks["memory"] > 10_001 * 7 * 8
    # Chunked: a 500-sample buffer (28 kB), a chunk's trajectory and file; never the whole run.
    assert peaks["chunked"] < 0.25 * peaks["memory"], peaks


def test_bad_chunk_arguments(robot, tmp_path: Path) -> None:
    pendulum = robot("pendulum")
    with pytest.raises(
        ms.InvalidArgumentError,
        match=re.escape("chunk needs out: the chunks are streamed to out.npz.parts/ and merged"),
    ):
        ms.simulate(pendulum, [0.1], [0.0], duration=0.1, dt=1e-2, chunk=10)
    for bad in (0, -3, 2.5, True, "10"):
        with pytest.raises(
            ms.InvalidArgumentError, match=re.escape(f"chunk must be a positive whole number of samples, got {bad!r}")
        ):
            ms.simulate(pendulum, [0.1], [0.0], duration=0.1, dt=1e-2, out=tmp_path / "x.npz", chunk=bad)
    (tmp_path / "y.npz.parts").mkdir()
    with pytest.raises(
        ms.InvalidArgumentError,
        match=re.escape(f"{tmp_path / 'y.npz.parts'} already exists (a previous chunked run's parts): move it first"),
    ):
        ms.simulate(pendulum, [0.1], [0.0], duration=0.1, dt=1e-2, out=tmp_path / "y.npz", chunk=10)
