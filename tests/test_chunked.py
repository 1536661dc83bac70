"""Nothing lost: runs write their samples to `out` however they end, and chunked runs stream to disk."""

from __future__ import annotations

import errno
import os
import re
import signal
import subprocess
import sys
import textwrap
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from conftest import ctrl_c_at

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
    stop = ctrl_c_at(0.095, 1)
    with pytest.raises(ms.SimulationInterrupted) as info:
        ms.simulate(pendulum, [1.0], [0.0], duration=0.2, dt=1e-2, controller=stop, out=tmp_path / "stop.npz")
    same(info.value.trajectory, ms.Trajectory.load(tmp_path / "stop.npz"))
    assert ms.Trajectory.load(tmp_path / "stop.npz").status == "interrupted"


@pytest.mark.parametrize("chunk", [3, 1000])
def test_an_interrupted_chunked_run_keeps_every_sample(robot, tmp_path: Path, chunk: int) -> None:
    pendulum = robot("pendulum")
    stop = ctrl_c_at(0.2995, 1)
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


# ---- whatever ends a run: signals while writing, disk full, file-size limits, memory (issue 17) ------------------
def leftovers(folder: Path) -> list[str]:
    """Temporary and lock files left in a folder (and in a parts folder inside it)."""
    names = [p.relative_to(folder).as_posix() for p in folder.rglob("*")]
    return sorted(n for n in names if n.rsplit("/", 1)[-1].startswith(".") or n.endswith(".lock"))


def reference(duration: float = 1.0) -> ms.Trajectory:
    return ms.simulate(ms.load_robot("pendulum"), [1.0], [0.0], duration=duration, dt=1e-3, output_dt=1e-2)


def chunked(out: Path, **kwargs: object) -> ms.Trajectory:
    return ms.simulate(ms.load_robot("pendulum"), [1.0], [0.0], duration=1.0, dt=1e-3, output_dt=1e-2, out=out,
                       chunk=20, **kwargs)  # fmt: skip


def test_sigint_while_the_chunks_are_merged_keeps_the_parts(tmp_path: Path, monkeypatch) -> None:
    """A real SIGINT from inside the merge's writer: the merge stops, its temporary file is removed, the parts stay
    whole and load; the error says where the samples are."""
    out = tmp_path / "run.npz"
    real = np.lib.format.write_array_header_2_0  # the merge writes each member's header with it
    calls = []

    def signalled(*args: object, **kwargs: object) -> None:
        calls.append(1)
        if len(calls) == 3:  # a few members into the merge
            os.kill(os.getpid(), signal.SIGINT)
        real(*args, **kwargs)

    monkeypatch.setattr(np.lib.format, "write_array_header_2_0", signalled)
    with pytest.raises(ms.SimulationInterrupted) as info:
        chunked(out)
    parts = tmp_path / "run.npz.parts"
    assert str(info.value) == (
        f"interrupted while writing the samples, after the run completed at t = 1 s; 101 samples kept; merging the "
        f"chunks was interrupted: 101 samples stay in {parts} (Trajectory.load reads the folder)"
    )
    assert info.value.saved_to == parts and not out.exists()
    assert leftovers(tmp_path) == []
    kept = ms.Trajectory.load(out)  # the parts, found from the file's name
    np.testing.assert_array_equal(kept.q, reference().q)
    assert kept.status == "incomplete"


def test_sigint_while_a_chunk_is_written_completes_the_chunk(tmp_path: Path, monkeypatch) -> None:
    from multibody_sim import trajectory

    out = tmp_path / "run.npz"
    real = trajectory.write_chunk
    calls = []

    def signalled(*args: object, **kwargs: object) -> object:
        calls.append(1)
        if len(calls) == 3:
            os.kill(os.getpid(), signal.SIGINT)  # held off until chunk 2 and its bookkeeping are complete
        return real(*args, **kwargs)

    monkeypatch.setattr("multibody_sim.driver.write_chunk", signalled)
    with pytest.raises(ms.SimulationInterrupted) as info:
        chunked(out)
    assert str(info.value) == "interrupted at t = 0.59 s (step 590); 60 samples kept"  # the third chunk's end
    saved = ms.Trajectory.load(out)
    assert saved.status == "interrupted" and info.value.saved_to == out
    np.testing.assert_array_equal(saved.q, reference(0.59).q)  # every sample, none twice
    assert sorted(os.listdir(tmp_path)) == ["run.npz"]


KILLED = """
import os, signal, sys
import numpy as np
import multibody_sim as ms
from multibody_sim import driver
real = driver.write_chunk
calls = []
def signalled(*args, **kwargs):
    calls.append(1)
    if len(calls) == {at}:
        os.kill(os.getpid(), signal.SIGTERM)  # nothing handles SIGTERM in this process: its default is to die
    return real(*args, **kwargs)
driver.write_chunk = signalled
ms.simulate(ms.load_robot("pendulum"), [1.0], [0.0], duration=1.0, dt=1e-3, output_dt=1e-2, out=sys.argv[1], {kwargs})
print("not reached")
"""


@pytest.mark.parametrize("chunk", [20, None])
def test_sigterm_in_a_process_that_does_not_handle_it_keeps_every_sample(tmp_path: Path, chunk: int | None) -> None:
    """SIGTERM's default action would kill the process mid-run: while a run with out= steps, it stops the run like
    Ctrl-C instead, the samples are written, the lock released, then the process terminates by SIGTERM."""
    out = tmp_path / "run.npz"
    if chunk is None:  # no chunk writes to hook: the signal comes from the controller, at t = 0.5 s
        script = KILLED.replace("{at}", "0").replace(
            "{kwargs}",
            "controller=lambda t, q, v: (os.kill(os.getpid(), signal.SIGTERM) if abs(t - 0.5) < 1e-9 else None) "
            "or np.zeros(1)",
        )
    else:
        script = KILLED.replace("{at}", "3").replace("{kwargs}", f"chunk={chunk}")
    result = subprocess.run([sys.executable, "-c", script, str(out)], capture_output=True, text=True, timeout=120)
    assert result.returncode == -signal.SIGTERM, result.stderr
    assert result.stdout == "" and "Traceback" not in result.stderr
    saved = ms.Trajectory.load(out)
    assert saved.status == "interrupted"
    t_stop = 0.59 if chunk else 0.5
    np.testing.assert_array_equal(saved.q, reference(t_stop).q)
    assert sorted(os.listdir(tmp_path)) == ["run.npz"]  # no temporary file, no parts, no lock


def test_a_full_disk_mid_run_stops_it_with_what_was_written(tmp_path: Path, monkeypatch) -> None:
    """ENOSPC on the fourth chunk: the run stops there (status write_failed), the three chunks written stay and
    load, the error's trajectory holds them and the samples in memory; no temporary file, no lock."""
    from multibody_sim import trajectory

    out = tmp_path / "run.npz"
    real_save = trajectory.Trajectory.save
    saves = []

    def disk_fills(self: ms.Trajectory, path: object) -> object:
        saves.append(path)
        if len(saves) >= 4:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real_save(self, path)

    monkeypatch.setattr(trajectory.Trajectory, "save", disk_fills)
    with pytest.raises(ms.SimulationError) as info:
        chunked(out)
    parts = tmp_path / "run.npz.parts"
    assert str(info.value) == (
        f"could not write {parts / 'chunk_000003.npz'} (No space left on device) at t = 0.79 s: the run stopped; "
        f"60 samples stay in {parts} (Trajectory.load reads the folder), the last 20 only in memory"
    )
    assert info.value.status == "write_failed" and info.value.saved_to == parts
    np.testing.assert_array_equal(info.value.trajectory.q, reference(0.79).q)
    monkeypatch.undo()
    np.testing.assert_array_equal(ms.Trajectory.load(parts).q, reference(0.59).q)
    assert leftovers(tmp_path) == []


def test_a_full_disk_at_the_end_of_an_in_memory_run(tmp_path: Path, monkeypatch) -> None:
    out = tmp_path / "run.npz"
    out.write_bytes(b"the previous file")

    def full(*args: object, **kwargs: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(np, "savez", full)
    with pytest.raises(ms.SimulationError) as info:
        ms.simulate(ms.load_robot("pendulum"), [1.0], [0.0], duration=1.0, dt=1e-3, output_dt=1e-2, out=out)
    assert str(info.value) == f"the run completed, but {out} could not be written (No space left on device)"
    assert info.value.status == "write_failed" and info.value.saved_to is None
    assert info.value.trajectory.status == "completed" and len(info.value.trajectory) == 101
    assert out.read_bytes() == b"the previous file" and sorted(os.listdir(tmp_path)) == ["run.npz"]


FSIZE = """
import resource, sys
from multibody_sim.cli import main
limit = int(sys.argv[1])
resource.setrlimit(resource.RLIMIT_FSIZE, (limit, resource.getrlimit(resource.RLIMIT_FSIZE)[1]))
sys.exit(main(sys.argv[2:]))
"""


def test_a_file_size_limit_at_the_merge_ends_the_run_in_one_line(tmp_path: Path) -> None:
    """RLIMIT_FSIZE (ulimit -f) set in a child: an adaptive run (its sample count is not known in advance) whose
    chunks fit the limit but whose merged file does not: the write fails (EFBIG; Python ignores SIGXFSZ): exit 1,
    one line saying where the samples are; the parts stay and load."""
    out = tmp_path / "run.npz"
    argv = [
        "run",
        "pendulum",
        "--integrator",
        "dp54",
        "--duration",
        "200",
        "--q0",
        "1",
        "--out",
        str(out),
        "--chunk",
        "300",
    ]
    result = subprocess.run(
        [sys.executable, "-c", FSIZE, str(128 * 1024), *argv], capture_output=True, text=True, timeout=300
    )
    assert result.returncode == 1, result.stderr
    lines = result.stderr.splitlines()
    assert len(lines) == 1 and "Traceback" not in result.stderr
    parts = re.escape(str(tmp_path / "run.npz.parts"))
    assert re.fullmatch(
        rf"multibody-sim: error: the run completed, but {re.escape(str(out))} could not be written \(File too "
        rf"large\): (\d+) samples stay in {parts} \(Trajectory\.load reads the folder\); partial trajectory "
        rf"\((\d+) samples, t = 0\.\.200 s\) kept in {parts} \(`multibody-sim plot`, `export` and "
        rf"Trajectory\.load read the folder\)",
        lines[0],
    ), lines[0]
    kept = ms.Trajectory.load(out)
    assert kept.t[-1] == 200.0 and len(kept) > 3000
    assert leftovers(tmp_path) == []


def test_a_memory_error_mid_run_ends_it_with_its_samples(tmp_path: Path, monkeypatch) -> None:
    """The store cannot grow (MemoryError): the run stops (status out_of_memory), its samples written to out."""
    from multibody_sim import recording

    real = recording.SampleStore._allocate
    grown = []

    def no_memory_past(self: object, capacity: int) -> None:
        grown.append(capacity)
        if len(grown) > 2:
            raise MemoryError
        real(self, capacity)

    monkeypatch.setattr(recording.SampleStore, "_allocate", no_memory_past)
    out = tmp_path / "run.npz"
    with pytest.raises(ms.SimulationError) as info:
        # adaptive, no output_dt: the store starts small and grows as samples come
        ms.simulate(ms.load_robot("pendulum"), [1.0], [0.0], duration=50.0, dt=1e-3, integrator="dp54", rtol=1e-8,
                    atol=1e-10, out=out)  # fmt: skip
    message = str(info.value)
    assert re.fullmatch(r"ran out of memory at t = \S+ s \(MemoryError\): the run stopped", message), message
    assert info.value.status == "out_of_memory" and info.value.saved_to == out
    saved = ms.Trajectory.load(out)
    assert saved.status == "out_of_memory" and len(saved) == len(info.value.trajectory) > 1000
    assert sorted(os.listdir(tmp_path)) == ["run.npz"]


# ---- a parts folder is checked before it is merged or loaded -----------------------------------------------------
def left_parts(tmp_path: Path, name: str = "run.npz") -> Path:
    """A chunked run's parts, left unmerged (the merge fails: its disk is 'full'): 6 chunks of 20 samples."""
    from multibody_sim import driver

    out = tmp_path / name

    def no_merge(*args: object, **kwargs: object) -> None:
        raise OSError(errno.ENOSPC, "No space left on device")

    real = driver.merge_parts
    driver.merge_parts = no_merge  # type: ignore[assignment]
    try:
        with pytest.raises(ms.SimulationError):
            ms.simulate(ms.load_robot("pendulum"), [1.0], [0.0], duration=1.0, dt=1e-3, output_dt=1e-2, out=out,
                        chunk=20)  # fmt: skip
    finally:
        driver.merge_parts = real  # type: ignore[assignment]
    parts = out.with_name(name + ".parts")
    assert sorted(os.listdir(parts)) == [f"chunk_{k:06d}.npz" for k in range(6)]
    return parts


def test_complete_parts_load_as_the_run(tmp_path: Path) -> None:
    np.testing.assert_array_equal(ms.Trajectory.load(left_parts(tmp_path)).q, reference().q)


def test_a_missing_chunk_is_named_never_stitched(tmp_path: Path) -> None:
    parts = left_parts(tmp_path)
    (parts / "chunk_000002.npz").unlink()
    with pytest.raises(ms.TrajectoryFileError) as info:
        ms.Trajectory.load(parts)
    assert str(info.value) == (
        f"{parts}: chunk_000002.npz is missing: the samples from t = 0.39 s to t = 0.6 s are lost; load the chunk "
        "files one by one (Trajectory.load(chunk))"
    )


def test_a_chunk_of_another_run_is_refused(tmp_path: Path) -> None:
    parts = left_parts(tmp_path)
    other = left_parts(tmp_path, "other.npz")
    (other / "chunk_000003.npz").replace(parts / "chunk_000003.npz")  # same times, same shapes: another run
    with pytest.raises(ms.TrajectoryFileError, match=r"chunk_000003\.npz belongs to another run \(run [0-9a-f]{12}, "):
        ms.Trajectory.load(parts)


def test_a_foreign_chunk_dropped_in_during_the_run_stops_the_merge(tmp_path: Path, monkeypatch) -> None:
    """Someone copies a chunk of another run into the folder while this run writes: the merge refuses to stitch
    it; the run's own chunks stay, and the error names the stranger."""
    stranger = left_parts(tmp_path, "other.npz") / "chunk_000005.npz"
    out = tmp_path / "run.npz"

    def drop_in(t: float, q: np.ndarray, v: np.ndarray) -> None:
        if abs(t - 0.95) < 1e-9:
            stranger.replace(tmp_path / "run.npz.parts" / "chunk_000009.npz")

    with pytest.raises(ms.SimulationError) as info:
        chunked(out, on_sample=drop_in)
    assert info.value.status == "write_failed"
    assert f"{out} could not be written ({tmp_path / 'run.npz.parts'}: chunk_000006.npz, chunk_000007.npz, " in str(
        info.value
    )
    assert not out.exists()


@pytest.mark.parametrize("where", ["controller", "on_sample"])
def test_user_code_that_raises_in_a_chunked_run_keeps_every_sample(tmp_path: Path, where: str) -> None:
    """The user-exception guarantee holds for chunked runs too: status failed, the cause chained, the samples so
    far merged into out, equal to the in-memory run's."""

    class Boom(Exception):
        pass

    def controller(t: float, q: np.ndarray, v: np.ndarray) -> np.ndarray:
        if where == "controller" and t > 0.4995:
            raise Boom("controller gave up")
        return np.zeros(1)

    def on_sample(t: float, q: np.ndarray, v: np.ndarray) -> None:
        if where == "on_sample" and t > 0.4995:
            raise Boom("viewer gave up")

    kwargs = dict(duration=1.0, dt=1e-3, output_dt=1e-2, controller=controller, on_sample=on_sample)
    with pytest.raises(ms.SimulationError) as memory:
        ms.simulate(ms.load_robot("pendulum"), [1.0], [0.0], **kwargs)
    out = tmp_path / "run.npz"
    with pytest.raises(ms.SimulationError) as streamed:
        ms.simulate(ms.load_robot("pendulum"), [1.0], [0.0], out=out, chunk=7, **kwargs)
    assert str(streamed.value) == str(memory.value)
    assert streamed.value.status == "failed" and isinstance(streamed.value.__cause__, Boom)
    assert streamed.value.saved_to == out
    same(memory.value.trajectory, streamed.value.trajectory)
    saved = ms.Trajectory.load(out)
    same(memory.value.trajectory, saved)
    assert saved.status == "failed" and sorted(os.listdir(tmp_path)) == ["run.npz"]


ADDRESS_SPACE = """
import resource, sys
import multibody_sim as ms
robot = ms.load_robot("pendulum")
ms.simulate(robot, [1.0], [0.0], duration=0.01, dt=1e-3, integrator="dp54", rtol=1e-6, atol=1e-8)  # warm up
used = next(int(line.split()[1]) * 1024 for line in open("/proc/self/status") if line.startswith("VmSize:"))
resource.setrlimit(resource.RLIMIT_AS, (used + 25 * 2**20, resource.getrlimit(resource.RLIMIT_AS)[1]))
try:
    ms.simulate(robot, [1.0], [0.0], duration=1e6, dt=1e-3, integrator="dp54", rtol=1e-12, atol=1e-12,
                out=sys.argv[1])
except ms.SimulationError as exc:
    print(exc.status, len(exc.trajectory), exc.saved_to)
    print(exc, file=sys.stderr)
"""


def test_a_run_that_outgrows_its_address_space_keeps_its_samples(tmp_path: Path) -> None:
    """RLIMIT_AS (ulimit -v) 25 MiB above what the child has mapped, and an adaptive run without output_dt (its
    samples cannot be counted in advance, so the store grows): the store stops growing while there is still room
    to assemble and write what it holds: SimulationError (status out_of_memory) with every sample, in the file."""
    out = tmp_path / "run.npz"
    result = subprocess.run(
        [sys.executable, "-c", ADDRESS_SPACE, str(out)], capture_output=True, text=True, timeout=600
    )
    assert result.returncode == 0, result.stderr
    match = re.fullmatch(
        r"ran out of memory at t = (\S+) s: \d+ samples would need \S+ GiB, more than the \S+ GiB available \(this "
        r"process's address-space limit \(ulimit -v\)\); the run stopped\n",
        result.stderr,
    )
    assert match, result.stderr
    status, samples, saved_to = result.stdout.split()
    assert (status, saved_to) == ("out_of_memory", str(out))
    saved = ms.Trajectory.load(out)
    assert saved.status == "out_of_memory" and len(saved) == int(samples) > 10_000
    t_stop = float(match.group(1))  # the state the run reached; its last sample is the one before
    assert t_stop - 0.1 < saved.t[-1] <= t_stop
    assert np.all(np.diff(saved.t) > 0) and np.all(np.isfinite(saved.q))
    assert sorted(os.listdir(tmp_path)) == ["run.npz"]


def test_a_chunk_that_does_not_continue_the_previous_one_is_refused(tmp_path: Path) -> None:
    """A chunk of the same run copied over its successor (same run id, the wrong samples): the sample count and
    the times say it does not continue the previous one."""
    import shutil

    parts = left_parts(tmp_path)
    shutil.copyfile(parts / "chunk_000002.npz", parts / "chunk_000003.npz")
    with pytest.raises(ms.TrajectoryFileError) as info:
        ms.Trajectory.load(parts)
    assert str(info.value) == (
        f"{parts}: chunk_000003.npz does not continue the previous chunk (it starts at sample 40, t = 0.4 s; expected "
        "sample 60, after t = 0.59 s); move it out of the folder"
    )
