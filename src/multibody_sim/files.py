"""Writing outputs safely: one check of an output's name, atomic replacement, signals held off, run locks.

Every writer (trajectories, chunk files and their merge, tables, plots, HTML pages, videos, bench results) goes
through `check_output` before its work and `write_atomically` (or `atomic_path`) for the write itself:

- Only regular files are replaced. A directory, FIFO, socket or device node given as an output is refused in one
  line (InvalidArgumentError). A symbolic link is written through: the link stays, its target is replaced
  atomically.
- A write goes to a temporary file in the target's folder, is flushed to disk, then renamed over the target: a
  reader never sees half a file, and a failure (disk full, a file-size limit, an exception) leaves the previous
  file and no temporary file behind.
- SIGINT and SIGTERM are held off while a write runs (`signals_held`): "finish" completes the write and then
  delivers the signal as it would have been (KeyboardInterrupt, the command line's handler, or the default
  action); "abort" stops the write, removes its temporary file, then delivers the signal. Either way nothing is
  left half-written, even when the signal's default action would have killed the process mid-write.
- `RunLock` keeps two runs from writing the same `out`: a lock file beside it names the owner's process; a lock
  whose process is gone is stale and taken over.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import stat
import threading
import uuid
from collections.abc import Callable, Iterator
from pathlib import Path
from types import FrameType
from typing import Any, BinaryIO, Literal

from .exceptions import InvalidArgumentError

HELD_SIGNALS = (signal.SIGINT, signal.SIGTERM)
LOCK_SUFFIX = ".lock"
_KINDS = (
    (stat.S_ISDIR, "a directory"),
    (stat.S_ISFIFO, "a FIFO (named pipe)"),
    (stat.S_ISSOCK, "a socket"),
    (stat.S_ISCHR, "a character device"),
    (stat.S_ISBLK, "a block device"),
)


# ---- the name of an output -------------------------------------------------------------------------------
def check_output(path: str | os.PathLike[str], what: str = "out", example: str = "run.npz") -> Path:
    """The file a writer will replace for the output `path`, checked before any work.

    A symbolic link is followed (the link stays; its target is replaced). Missing folders are allowed (writers
    create them) if the nearest existing one is a writable folder.

    Args:
        path: the output's name.
        what: how messages name it ("out", "--csv", ...).
        example: a file name to suggest.

    Returns:
        The path to replace: `path`, or the final target of a symbolic link.

    Raises:
        InvalidArgumentError: the output (or a link's target) exists and is not a regular file, or its folder is
            not writable.
    """
    given = Path(path).expanduser()
    target = Path(os.path.realpath(given)) if given.is_symlink() else given
    try:
        mode = target.stat().st_mode
    except FileNotFoundError:
        mode = None
    except OSError as exc:
        raise InvalidArgumentError(f"{what} {given}: cannot be checked ({exc.strerror or exc})") from None
    if mode is not None and not stat.S_ISREG(mode):
        kind = next((name for test, name in _KINDS if test(mode)), "not a regular file")
        through = f" (a symbolic link to {target})" if target != given else ""
        expected = (
            f"expected a file name such as {example}"
            if kind == "a directory"
            else f"only regular files are replaced; give a file name such as {example}"
        )
        raise InvalidArgumentError(f"{what} {given}{through}: is {kind}, {expected}")
    folder = target.absolute().parent
    while not folder.exists():
        folder = folder.parent
    if not folder.is_dir() or not os.access(folder, os.W_OK | os.X_OK):
        raise InvalidArgumentError(f"{what} {given}: cannot create a file in {folder} (not a writable folder)")
    return target


# ---- signals held off during a write --------------------------------------------------------------------
class _Abort(BaseException):
    """Raised inside an "abort" section by the first SIGINT/SIGTERM (not an Exception: user code won't catch it)."""


class Hold:
    """A section's signal mode, which it may switch from "abort" to "finish" once it reaches its commit."""

    def __init__(self, mode: Literal["finish", "abort"]):
        self.mode = mode


@contextlib.contextmanager
def signals_held(mode: Literal["finish", "abort"]) -> Iterator[Hold]:
    """Hold SIGINT and SIGTERM off a critical section, then deliver the first one received to the handler that was
    in place (KeyboardInterrupt for SIGINT, the command line's SIGTERM handler, or the default action).

    Args:
        mode: "finish": the section runs to its end before the signal is delivered; "abort": the first signal stops
            the section (as an exception that unwinds it, running its cleanup), then is delivered. The section
            may set the yielded Hold's mode to "finish" where it must not be stopped any more.

    Python lets only the main thread install handlers: elsewhere the section runs unprotected.
    """
    hold = Hold(mode)
    if threading.current_thread() is not threading.main_thread():
        yield hold
        return
    received: list[int] = []

    def handle(signum: int, frame: FrameType | None) -> None:
        received.append(signum)
        if hold.mode == "abort" and len(received) == 1:
            raise _Abort

    previous = {signum: signal.signal(signum, handle) for signum in HELD_SIGNALS}
    try:
        yield hold
    except _Abort:
        pass  # the section unwound (its cleanup ran); the signal is delivered below
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, signal.SIG_DFL if handler is None else handler)
        if received:
            signal.raise_signal(received[0])


class SigtermAsInterrupt:
    """While a run with an output steps, a SIGTERM that nothing handles (its default action would kill the process
    with the samples in memory and a half-written file) raises KeyboardInterrupt instead, so that the run stops as
    on Ctrl-C and keeps its samples; on exit, once they are written, SIGTERM is delivered again with its default
    action: the process still terminates, and loses nothing.

    With ``owner=True`` the caller owns the process (the command line): SIGTERM is taken over from whatever handles
    it, that handler is back on exit, and SIGTERM is not delivered again (the command line exits with 143 itself).

    Attributes:
        received: whether SIGTERM arrived.
    """

    def __init__(self, *, owner: bool = False) -> None:
        self.received = False
        self.owner = owner
        self._active = False
        self._previous: Any = None

    def _handle(self, signum: int, frame: FrameType | None) -> None:
        first = not self.received
        self.received = True
        if first:  # one interrupt; a second SIGTERM while the samples are written is the same request
            raise KeyboardInterrupt

    def __enter__(self) -> SigtermAsInterrupt:
        # Python lets only the main thread install handlers; elsewhere SIGTERM keeps its action.
        if threading.current_thread() is threading.main_thread() and (
            self.owner or signal.getsignal(signal.SIGTERM) in (signal.SIG_DFL, None)
        ):
            self._previous = signal.signal(signal.SIGTERM, self._handle)
            self._active = True
        return self

    def __exit__(self, *exc: object) -> None:
        if self._active:  # None: the previous handler was not installed from Python; the default then
            signal.signal(signal.SIGTERM, signal.SIG_DFL if self._previous is None else self._previous)
            if self.received and not self.owner:
                signal.raise_signal(signal.SIGTERM)


# ---- atomic writes ----------------------------------------------------------------------------------------
@contextlib.contextmanager
def atomic_path(
    path: str | os.PathLike[str], *, what: str = "out", mode: Literal["finish", "abort"] = "abort", suffix: str = ""
) -> Iterator[Path]:
    """A temporary file name beside the output, renamed over it when the block succeeds (for writers that need a
    name rather than a file object: video encoders). Signals are held off as `signals_held(mode)` says; on any
    failure the temporary file is removed and the previous output stays."""
    target = check_output(path, what)
    target.parent.mkdir(parents=True, exist_ok=True)
    with signals_held(mode) as hold:
        import tempfile  # here: it imports shutil, bz2 and lzma, which `import multibody_sim` need not pay

        fd, name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=f".tmp{suffix}", dir=target.parent)
        tmp = Path(name)
        try:
            os.close(fd)
            _usual_permissions(tmp)
            yield tmp
            with tmp.open("rb+") as f:
                os.fsync(f.fileno())
            hold.mode = "finish"
            os.replace(tmp, target)
        finally:
            tmp.unlink(missing_ok=True)


def write_atomically(
    path: str | os.PathLike[str],
    write: Callable[[BinaryIO], Any],
    *,
    what: str = "out",
    mode: Literal["finish", "abort"] = "abort",
    then: Callable[[], Any] | None = None,
) -> Path:
    """Call write(file) on a temporary file beside the output, flush it to disk, then rename it over the output.

    Args:
        path: the output (a symbolic link is written through).
        write: writes the contents to the binary file it is given.
        what: how messages name the output.
        mode: "finish" (a signal waits for the write: for samples that exist only in memory) or "abort" (a signal
            stops the write: for outputs that can be made again).
        then: called right after the rename, with signals held off until it returns (a merge removes its parts).

    Returns:
        The file replaced (a link's target).

    Raises:
        InvalidArgumentError: the output is not a regular file (check_output).
        OSError: the write failed (disk full, file-size limit): the previous file stays, no temporary file.
    """
    target = check_output(path, what)
    target.parent.mkdir(parents=True, exist_ok=True)
    with signals_held(mode) as hold:
        import tempfile

        fd, name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=target.parent)
        try:
            with os.fdopen(fd, "wb") as f:
                _usual_permissions(Path(name), f.fileno())
                write(f)
                f.flush()
                os.fsync(f.fileno())
            hold.mode = "finish"  # written: the rename and what follows it are not stopped half-way
            os.replace(name, target)
        except BaseException:
            Path(name).unlink(missing_ok=True)
            raise
        if then is not None:
            then()
    return target


def _usual_permissions(path: Path, fd: int | None = None) -> None:
    """mkstemp makes 0600 files; an output gets the usual permissions (0666 less the umask)."""
    umask = os.umask(0)
    os.umask(umask)
    if fd is not None:
        os.fchmod(fd, 0o666 & ~umask)
    else:
        path.chmod(0o666 & ~umask)


# ---- one run per output -----------------------------------------------------------------------------------
def lock_path(out: Path) -> Path:
    """The lock file of a run writing `out`: out.lock beside it."""
    return out.with_name(out.name + LOCK_SUFFIX)


def lock_owner(out: Path) -> str | None:
    """Who holds `out`'s lock, in words ("process 1234 on host h"), or None when it is free or stale."""
    lock = lock_path(out)
    try:
        fields = lock.read_text(encoding="utf-8", errors="replace").split()
    except FileNotFoundError:
        return None
    except OSError as exc:
        return f"an unreadable lock ({exc.strerror or exc})"
    if len(fields) < 2 or not fields[0].isdigit():
        return None  # not ours, or damaged: no live run can be named in it
    pid, host = int(fields[0]), fields[1]
    if host != socket.gethostname():
        return f"process {pid} on host {host}"  # cannot be checked from here: assume it runs
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return None  # the run is gone: a stale lock
    except PermissionError:
        pass  # alive, someone else's
    return f"process {pid}"


def check_unlocked(out: Path, what: str = "out") -> None:
    """Refuse an output that another live run is writing (before any work; RunLock takes the lock)."""
    owner = lock_owner(out)
    if owner is not None:
        raise InvalidArgumentError(
            f"{what} {out}: another run is writing it ({owner}, lock file {lock_path(out)}); choose another file, or "
            "wait for that run to end"
        )


def remove_stale_temporaries(out: Path) -> list[Path]:
    """Remove the temporary files a run on `out` left when it was killed outright (SIGKILL, a power cut: no
    cleanup ran): .out.XXXX.tmp beside it and .chunk_NNNNNN.npz.XXXX.tmp in its parts folder. Called when its stale
    lock is taken over, so their writer is known to be gone.

    Returns:
        The files removed.
    """
    patterns = [(out.parent, f".{out.name}.*.tmp"), (out.with_name(out.name + ".parts"), ".chunk_*.npz.*.tmp")]
    removed = []
    for folder, pattern in patterns:
        for path in folder.glob(pattern):
            if path.name.startswith(f".{out.name}{LOCK_SUFFIX}."):
                continue  # the lock's own temporary file (the new owner's, being linked into place)
            with contextlib.suppress(OSError):
                path.unlink()
                removed.append(path)
    return removed


class RunLock:
    """out.lock, held while a run writes `out` (its chunks and their merge included).

    The lock file holds "pid host run_id" and is created whole (a complete temporary file hard-linked into
    place), so a reader never sees a half-written lock. A lock whose process is gone is stale and taken over, and
    the temporary files that process left are removed.

    Attributes:
        run_id: a fresh identifier of the run (also written into its chunk files).
    """

    def __init__(self, out: Path, what: str = "out"):
        self.out, self.what = out, what
        self.path = lock_path(out)
        self.run_id = uuid.uuid4().hex
        self.held = False

    def acquire(self) -> None:
        self.path.parent.mkdir(parents=True, exist_ok=True)
        import tempfile

        fd, name = tempfile.mkstemp(prefix=f".{self.path.name}.", suffix=".tmp", dir=self.path.parent)
        try:
            with os.fdopen(fd, "w") as f:
                f.write(f"{os.getpid()} {socket.gethostname()} {self.run_id}\n")
            for _ in range(3):
                try:
                    os.link(name, self.path)
                    self.held = True
                    return
                except FileExistsError:
                    check_unlocked(self.out, self.what)  # a live owner: refused
                    self.path.unlink(missing_ok=True)  # a stale lock: taken over
                    remove_stale_temporaries(self.out)
            check_unlocked(self.out, self.what)
            raise InvalidArgumentError(f"{self.what} {self.out}: could not take the lock file {self.path}")
        finally:
            Path(name).unlink(missing_ok=True)

    def release(self) -> None:
        if self.held:
            with contextlib.suppress(OSError):
                if self.path.read_text().split()[2:3] == [self.run_id]:  # still ours
                    self.path.unlink()
            self.held = False

    def __enter__(self) -> RunLock:
        self.acquire()
        return self

    def __exit__(self, *exc: object) -> None:
        self.release()
