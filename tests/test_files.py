"""Outputs are written safely (files.py): only regular files are replaced, symbolic links are written through,
signals never leave half a file or a temporary file, and two runs never write the same `out`.

Signals are real: delivered with os.kill, from inside the writer (so that the moment is the one chosen), to this
process (SIGINT: a KeyboardInterrupt) or to a child process (SIGTERM with its default action, which would kill the
process mid-write if nothing held it off).
"""

from __future__ import annotations

import os
import re
import signal
import socket
import stat
import subprocess
import sys
import textwrap
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

import multibody_sim as ms
from multibody_sim import files
from multibody_sim.cli import main

PREFIX = "multibody-sim: error: "


def exact(message: str) -> str:
    return f"^{re.escape(message)}$"


@pytest.fixture(scope="module")
def short_run() -> ms.Trajectory:
    return ms.simulate(ms.load_robot("pendulum"), [1.0], [0.0], duration=0.2, dt=0.01)


@pytest.fixture
def specials(tmp_path: Path) -> Iterator[dict[str, tuple[Path | None, str]]]:
    """Outputs that are not regular files: {name: (path, how check_output words its kind)} (the device is None
    where this process may not make device nodes: not root)."""
    folder = tmp_path / "folder.npz"
    folder.mkdir()
    fifo = tmp_path / "fifo.npz"
    os.mkfifo(fifo)
    sock_path = tmp_path / "sock.npz"
    server = socket.socket(socket.AF_UNIX)
    server.bind(str(sock_path))
    link = tmp_path / "link.npz"
    link.symlink_to(fifo)
    # A device node of our own (never the system's /dev/null: code that replaced it would break the machine).
    device = tmp_path / "null.npz"
    try:
        os.mknod(device, 0o666 | stat.S_IFCHR, os.makedev(1, 3))
    except PermissionError:
        device = None
    try:
        yield {
            "directory": (folder, "a directory"),
            "fifo": (fifo, "a FIFO (named pipe)"),
            "socket": (sock_path, "a socket"),
            "device": (device, "a character device"),
            "link-to-fifo": (link, "a FIFO (named pipe)"),
        }
    finally:
        server.close()


def refusal(path: Path, kind: str, what: str = "out", example: str = "run.npz") -> str:
    through = f" (a symbolic link to {os.path.realpath(path)})" if path.is_symlink() else ""
    expected = (
        f"expected a file name such as {example}"
        if kind == "a directory"
        else f"only regular files are replaced; give a file name such as {example}"
    )
    return f"{what} {path}{through}: is {kind}, {expected}"


def untouched(path: Path) -> tuple[Any, ...]:
    st = path.lstat()
    return (st.st_mode, st.st_ino, st.st_size, st.st_mtime_ns)


# ---- only regular files are replaced -------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["directory", "fifo", "socket", "device", "link-to-fifo"])
def test_an_output_that_is_not_a_regular_file_is_refused_before_any_work(
    name: str, specials: dict[str, tuple[Path, str]], short_run: ms.Trajectory, monkeypatch: pytest.MonkeyPatch
) -> None:
    path, kind = specials[name]
    if path is None:
        pytest.skip("making a device node needs root")
    before = untouched(path)
    stepped = []
    monkeypatch.setattr(ms.Robot, "unchecked_forward_dynamics", lambda *a, **k: stepped.append(1), raising=False)
    with pytest.raises(ms.InvalidArgumentError, match=exact(refusal(path, kind))):
        ms.simulate(ms.load_robot("pendulum"), [1.0], [0.0], duration=0.1, dt=0.01, out=path)
    assert not stepped  # refused before the run
    with pytest.raises(ms.InvalidArgumentError, match=exact(refusal(path, kind))):
        short_run.save(path)
    assert untouched(path) == before
    assert sorted(p.name for p in path.parent.iterdir() if p.name.startswith(".")) == []  # no temporary file


@pytest.mark.parametrize("name", ["directory", "fifo", "socket", "device", "link-to-fifo"])
def test_every_command_line_writer_refuses_them_in_one_line(
    name: str,
    specials: dict[str, tuple[Path, str]],
    short_run: ms.Trajectory,
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    path, kind = specials[name]
    if path is None:
        pytest.skip("making a device node needs root")
    saved = short_run.save(tmp_path / "saved.npz")
    commands = [
        (["run", "pendulum", "--duration", "0.05", "--out", str(path)], "--out", "run.npz"),
        (["plot", str(saved), "--out", str(path)], "--out", "plot.png"),
        (["export", str(saved), "--csv", str(path)], "--csv", "table.csv"),
        (["play", str(saved), "--html", str(path)], "--html", "view.html"),
    ]
    for argv, option, example in commands:
        capsys.readouterr()
        code = main(argv)
        out, err = capsys.readouterr()
        assert (code, err) == (2, PREFIX + refusal(path, kind, option, example) + "\n"), argv
        assert out == ""


def test_every_api_writer_refuses_a_fifo(specials: dict[str, tuple[Path, str]], short_run: ms.Trajectory) -> None:
    """plot_trajectory, export_html, write_table, WorkPrecision.write's files: the same check, the same line."""
    from multibody_sim import tables
    from multibody_sim.files import write_atomically

    fifo, kind = specials["fifo"]
    with pytest.raises(ms.InvalidArgumentError, match=exact(refusal(fifo, kind))):
        write_atomically(fifo, lambda f: f.write(b"x"))
    with pytest.raises(ms.InvalidArgumentError, match=exact(refusal(fifo, kind, example="table.csv"))):
        tables.write_table(short_run, fifo, format="csv")
    viz = pytest.importorskip("multibody_sim.viz")
    with pytest.raises(ms.InvalidArgumentError, match=exact(refusal(fifo, kind, example="plot.png"))):
        viz.plot_trajectory(short_run, fifo)
    with pytest.raises(ms.InvalidArgumentError, match=exact(refusal(fifo, kind, example="view.html"))):
        viz.export_html(short_run, fifo)
    video = fifo.with_name("video.mp4")
    os.mkfifo(video)
    with pytest.raises(ms.InvalidArgumentError, match=exact(refusal(video, kind, "video", "motion.mp4"))):
        viz.export_video(short_run, video)


def test_a_symlinked_output_is_written_through(short_run: ms.Trajectory, tmp_path: Path) -> None:
    """The link stays a link; its target is replaced (a new inode: atomically, by rename) with the new file."""
    target = tmp_path / "real" / "run.npz"
    target.parent.mkdir()
    target.write_bytes(b"old contents")
    old_inode = target.stat().st_ino
    link = tmp_path / "run.npz"
    link.symlink_to(target)
    assert short_run.save(link) == link
    assert link.is_symlink() and os.readlink(link) == str(target)
    assert target.stat().st_ino != old_inode
    np.testing.assert_array_equal(ms.Trajectory.load(target).q, short_run.q)
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["real", "run.npz", "run.npz"]
    # A run through the command line, and a dangling link (its target is created).
    dangling = tmp_path / "new.npz"
    dangling.symlink_to(tmp_path / "real" / "new-target.npz")
    assert main(["run", "pendulum", "--duration", "0.05", "--out", str(dangling)]) == 0
    assert dangling.is_symlink()
    assert len(ms.Trajectory.load(tmp_path / "real" / "new-target.npz")) == 51


# ---- signals during a write ----------------------------------------------------------------------------------
def test_sigint_inside_the_writer_waits_for_the_file(short_run: ms.Trajectory, tmp_path: Path, monkeypatch) -> None:
    """Trajectory.save holds SIGINT off (these samples may exist nowhere else): the file is complete, then the
    KeyboardInterrupt comes."""
    path = tmp_path / "run.npz"
    real_savez = np.savez

    def savez_signalled(f: Any, **arrays: Any) -> None:
        os.kill(os.getpid(), signal.SIGINT)  # a real signal, mid-write
        real_savez(f, **arrays)

    monkeypatch.setattr(np, "savez", savez_signalled)
    with pytest.raises(KeyboardInterrupt):
        short_run.save(path)
    monkeypatch.undo()
    np.testing.assert_array_equal(ms.Trajectory.load(path).q, short_run.q)
    assert sorted(os.listdir(tmp_path)) == ["run.npz"]
    assert signal.getsignal(signal.SIGINT) is signal.default_int_handler  # the handler is restored


def test_sigint_inside_an_abortable_writer_removes_its_temporary_file(tmp_path: Path) -> None:
    """Outputs that can be made again (plots, tables, pages) stop at once: the previous file stays."""
    path = tmp_path / "table.csv"
    path.write_text("previous\n")

    def write(f: Any) -> None:
        f.write(b"half a ")
        os.kill(os.getpid(), signal.SIGINT)
        f.write(b"table\n")  # not reached: the signal stops the write here
        raise AssertionError("the write went on after SIGINT")

    with pytest.raises(KeyboardInterrupt):
        files.write_atomically(path, write)
    assert path.read_text() == "previous\n"
    assert sorted(os.listdir(tmp_path)) == ["table.csv"]


CHILD = textwrap.dedent("""
    import os, signal, sys
    import numpy as np
    import multibody_sim as ms
    traj = ms.simulate(ms.load_robot("pendulum"), [1.0], [0.0], duration=0.2, dt=0.01)
    real_savez = np.savez
    def savez_signalled(f, **arrays):
        os.kill(os.getpid(), signal.SIGTERM)  # default action: terminate, unless held off
        real_savez(f, **arrays)
    np.savez = savez_signalled
    traj.save(sys.argv[1])
    print("not reached: SIGTERM is delivered once the file is complete")
""")


def test_sigterm_with_its_default_action_still_leaves_a_complete_file(tmp_path: Path) -> None:
    """In a process that never handles SIGTERM, the signal is held until the file is renamed into place, then
    delivered: the process dies of it (-SIGTERM), with a complete file and no temporary file."""
    path = tmp_path / "run.npz"
    result = subprocess.run([sys.executable, "-c", CHILD, str(path)], capture_output=True, text=True, timeout=120)
    assert result.returncode == -signal.SIGTERM, result.stderr
    assert result.stdout == ""
    assert len(ms.Trajectory.load(path)) == 21
    assert sorted(os.listdir(tmp_path)) == ["run.npz"]


# ---- one run per output --------------------------------------------------------------------------------------
def test_a_second_run_on_the_same_out_is_refused_while_the_first_runs(tmp_path: Path) -> None:
    """A real concurrent run: the child holds out.lock while it steps (its controller waits for a go file); this
    process's run on the same out is refused in one line, API and CLI; the child's file is then whole."""
    out = tmp_path / "shared.npz"
    go = tmp_path / "go"
    script = textwrap.dedent(f"""
        import os, time
        import numpy as np
        import multibody_sim as ms
        def wait(t, q, v):
            while t > 0.05 and not os.path.exists({str(go)!r}):
                time.sleep(0.01)
            return np.zeros(1)
        ms.simulate(ms.load_robot("pendulum"), [1.0], [0.0], duration=0.5, dt=1e-2, controller=wait,
                    out={str(out)!r}, chunk=3)
    """)
    child = subprocess.Popen([sys.executable, "-c", script], stderr=subprocess.PIPE, text=True)
    try:
        lock = out.with_name("shared.npz.lock")
        for _ in range(3000):
            if lock.exists() and out.with_name("shared.npz.parts").exists():
                break
            assert child.poll() is None, child.stderr.read() if child.stderr else ""
            subprocess.run(["sleep", "0.01"], check=True)
        message = (
            f"out {out}: another run is writing it (process {child.pid}, lock file {lock}); choose another file, "
            "or wait for that run to end"
        )
        for chunk in (None, 5):
            with pytest.raises(ms.InvalidArgumentError, match=exact(message)):
                ms.simulate(ms.load_robot("pendulum"), [0.5], [0.0], duration=0.1, dt=1e-2, out=out, chunk=chunk)
        result = subprocess.run(
            [sys.executable, "-m", "multibody_sim", "run", "pendulum", "--out", str(out)],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert (result.returncode, result.stderr) == (2, PREFIX + message.replace("out ", "--out ", 1) + "\n")
    finally:
        go.touch()
        assert child.wait(timeout=120) == 0, child.stderr.read() if child.stderr else ""
    whole = ms.Trajectory.load(out)
    assert whole.status == "completed" and len(whole) == 51 and whole.q[0, 0] == 1.0  # the child's run, whole
    assert sorted(os.listdir(tmp_path)) == ["go", "shared.npz"]  # lock and parts removed


def test_a_stale_lock_is_taken_over(tmp_path: Path) -> None:
    out = tmp_path / "run.npz"
    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    lock = out.with_name("run.npz.lock")
    lock.write_text(f"{int(dead.stdout)} {socket.gethostname()} 0123456789abcdef\n")  # its process has exited
    ms.simulate(ms.load_robot("pendulum"), [1.0], [0.0], duration=0.1, dt=1e-2, out=out)
    assert len(ms.Trajectory.load(out)) == 11
    assert not lock.exists()


def test_a_lock_of_another_host_is_respected(tmp_path: Path) -> None:
    """A pid on another machine (a shared folder) cannot be checked from here: the lock holds."""
    out = tmp_path / "run.npz"
    lock = out.with_name("run.npz.lock")
    lock.write_text("1 some-other-host abc\n")
    with pytest.raises(ms.InvalidArgumentError, match="another run is writing it \\(process 1 on host some-other-host"):
        ms.simulate(ms.load_robot("pendulum"), [1.0], [0.0], duration=0.1, dt=1e-2, out=out)
    assert not out.exists()


def test_a_killed_runs_lock_and_temporary_files_are_cleaned_by_the_next_run(tmp_path: Path) -> None:
    """SIGKILL mid-write (no cleanup can run): the lock and a temporary file stay behind; the next run on the same
    out finds the lock stale, takes it over, removes the dead run's temporary file and writes its file whole."""
    out = tmp_path / "run.npz"
    script = textwrap.dedent(f"""
        import os, signal
        import numpy as np
        import multibody_sim as ms
        real_savez = np.savez
        def savez_killed(f, **arrays):
            f.write(b"PK half a file")
            f.flush()
            os.kill(os.getpid(), signal.SIGKILL)
        np.savez = savez_killed
        ms.simulate(ms.load_robot("pendulum"), [1.0], [0.0], duration=0.1, dt=1e-2, out={str(out)!r})
    """)
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=120)
    assert result.returncode == -signal.SIGKILL, result.stderr
    left = sorted(os.listdir(tmp_path))
    assert left[-1] == "run.npz.lock" and len(left) == 2 and re.fullmatch(r"\.run\.npz\.\w+\.tmp", left[0]), left
    ms.simulate(ms.load_robot("pendulum"), [0.5], [0.0], duration=0.1, dt=1e-2, out=out)
    assert sorted(os.listdir(tmp_path)) == ["run.npz"]
    assert ms.Trajectory.load(out).q[0, 0] == 0.5


def test_bench_refuses_a_special_file_where_its_tables_go(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    os.mkfifo(tmp_path / "work_precision.csv")
    code = main(["bench", "pendulum", "--integrators", "rk4", "--duration", "0.1", "--out", str(tmp_path)])
    out, err = capsys.readouterr()
    assert (code, out) == (2, "")
    assert (
        err
        == PREFIX
        + refusal(tmp_path / "work_precision.csv", "a FIFO (named pipe)", "--out", "work_precision.csv")
        + "\n"
    )


BLOCKED_WRITER = """
import os, sys, time
import numpy as np
from multibody_sim.cli import main
ready, go = sys.argv[1], sys.argv[2]
real_savez = np.savez
def savez_blocked(f, **arrays):
    f.write(b"PK half")  # half a file on disk: the moment the parent signals
    open(ready, "w").close()
    while not os.path.exists(go):
        time.sleep(0.01)
    f.seek(0)
    f.truncate()
    real_savez(f, **arrays)
np.savez = savez_blocked
sys.exit(main(sys.argv[3:]))
"""


@pytest.mark.parametrize(("sig", "code"), [(signal.SIGINT, 130), (signal.SIGTERM, 143)])
def test_a_signal_from_outside_while_the_file_is_written(tmp_path: Path, sig: signal.Signals, code: int) -> None:
    """`multibody-sim run --out` in a child, stopped inside its final write (half the file on disk); the parent
    sends the signal then lets the write go on: the file is completed, the signal then takes effect (exit 130 /
    143), one line says what was kept, no temporary file."""
    out, ready, go = tmp_path / "run.npz", tmp_path / "ready", tmp_path / "go"
    argv = ["run", "pendulum", "--q0", "1", "--duration", "0.5", "--output-dt", "0.01", "--out", str(out)]
    child = subprocess.Popen(
        [sys.executable, "-c", BLOCKED_WRITER, str(ready), str(go), *argv],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        for _ in range(6000):
            if ready.exists() or child.poll() is not None:
                break
            subprocess.run(["sleep", "0.01"], check=True)
        assert ready.exists(), child.communicate()[1]
        os.kill(child.pid, sig)  # while the file is half written
        subprocess.run(["sleep", "0.2"], check=True)
        assert child.poll() is None  # held off: the process did not die mid-write
        go.touch()
        stdout, stderr = child.communicate(timeout=120)
    finally:
        if child.poll() is None:
            child.kill()
    assert child.returncode == code, stderr
    assert stderr == (
        f"multibody-sim: {sig.name}: interrupted while writing the samples, after the run completed at t = 0.5 s; 51 "
        f"samples kept; partial trajectory (51 samples, t = 0..0.5 s) written to {out}\n"
    )
    saved = ms.Trajectory.load(out)
    assert saved.status == "completed" and len(saved) == 51
    assert sorted(os.listdir(tmp_path)) == ["go", "ready", "run.npz"]


def _deliver_sigterm() -> None:
    """Send this process SIGTERM (its Python handler runs before the next bytecode of this thread)."""
    os.kill(os.getpid(), signal.SIGTERM)


def test_sigterm_as_interrupt_leaves_another_handler_to_the_library_and_takes_it_over_for_the_command_line() -> None:
    """Where something else handles SIGTERM (Ray installs sys.exit), a library run leaves it alone; the command
    line, which owns its process, takes SIGTERM over as Ctrl-C (exit 143, samples kept) and gives the handler back."""
    seen: list[int] = []
    previous = signal.signal(signal.SIGTERM, lambda signum, frame: seen.append(signum))
    try:
        handler = signal.getsignal(signal.SIGTERM)
        with files.SigtermAsInterrupt() as library:
            _deliver_sigterm()
        assert seen == [signal.SIGTERM] and not library.received
        with pytest.raises(KeyboardInterrupt), files.SigtermAsInterrupt(owner=True) as command_line:
            _deliver_sigterm()
        assert command_line.received and seen == [signal.SIGTERM]  # taken over, and not delivered again on exit
        assert signal.getsignal(signal.SIGTERM) is handler
    finally:
        signal.signal(signal.SIGTERM, previous)
