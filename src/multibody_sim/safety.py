"""Limits on untrusted files: what a trajectory archive may make us allocate or decompress before we read it.

An .npz is a zip of .npy members. numpy allocates each array from the shape its header claims and zipfile
inflates whatever the archive holds, so a 10 MB file can ask for gigabytes: a member whose header claims a huge
shape, a highly compressed member (a zip bomb), a bzip2 or LZMA member (which inflate far more per byte read),
or millions of tiny members. `check_npz` refuses all of these from the archive's directory and the members'
headers alone, reading at most a few kilobytes of each member; `read_npz` is np.load behind that check, with
every failure turned into a TrajectoryFileError. It also says what this process may allocate (`memory_room`,
`check_allocation`) and write (`file_size_limit`, `check_file_size`).
"""

from __future__ import annotations

import math
import os
import re
import struct
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path
from typing import BinaryIO

import numpy as np

from .exceptions import TrajectoryFileError
from .text import printable

MAX_NPZ_MEMBERS = 4096  # a trajectory has ~11 arrays plus one per ledger element
# A file may expand to MAX_EXPANSION times its size, or MIN_BUDGET_BYTES whatever its size. Trajectory.save
# stores members uncompressed (expansion 1); deflate reaches ~1000x on constant arrays (the bombs). A deflated
# trajectory of a pendulum at rest expands ~33x; a many-joint robot at rest could pass 100x, and then loads
# only up to MIN_BUDGET_BYTES (save such files uncompressed).
MAX_EXPANSION = 100
MIN_BUDGET_BYTES = 256 * 1024 * 1024
MAX_HEADER_BYTES = 10_000  # np.load's own default limit on an .npy header
# A trajectory's JSON header nests 5 deep (header > metadata > robot > load_robot > package_dirs); json.loads
# recurses once per level and raises RecursionError near 1000, so deeper documents are refused before parsing.
MAX_JSON_DEPTH = 64
# Scene files nest arrays and inline tables 2 deep (waypoints); tomllib recurses ~3 frames per level and raises
# RecursionError near 500, so a scene (a file, or a trajectory's stored scene text) nesting deeper is refused unread.
MAX_TOML_DEPTH = 64
# Allocations up to this size are not checked against the memory room: reading it (/proc/meminfo, the cgroup's files)
# costs 0.2-0.7 ms, as much as a whole short native run or a short rollout's assembly, and no process that got as far
# as running lacks 16 MiB.
SMALL_ALLOCATION = 2**24  # [bytes]
_JSON_STRING = re.compile(r'"(?:[^"\\]|\\.)*"')
# TOML's strings and comments, in the order a parser meets them: multi-line basic and literal strings (which may end
# with one or two quotes of their own before the closing three), basic and literal strings, comments.
_TOML_SKIPPED = re.compile(
    r'"""(?:[^\\]|\\.)*?"""(?:"{1,2}(?!"))?|\'\'\'.*?\'\'\'(?:\'{1,2}(?!\'))?|"(?:[^"\\\n]|\\.)*"|\'[^\'\n]*\'|#[^\n]*',
    re.DOTALL,
)
_READABLE_COMPRESSION = {zipfile.ZIP_STORED: "stored", zipfile.ZIP_DEFLATED: "deflated"}
_END_OF_DIRECTORY = b"PK\x05\x06"
_END_RECORD_SIZE = 22  # the fixed part of zip's end-of-central-directory record; a comment (<= 64 KiB) may follow


# What reading a damaged or hostile archive raises besides our own errors: zlib.error for a corrupted deflate
# stream, struct.error for a damaged header, NotImplementedError / RuntimeError for a zip version, compression
# method or encryption zipfile cannot read (fuzzing found each of them).
ARCHIVE_ERRORS = (
    OSError,
    ValueError,
    EOFError,
    KeyError,
    zipfile.BadZipFile,
    zlib.error,
    struct.error,
    NotImplementedError,
    RuntimeError,
)


def json_depth(text: str) -> int:
    """How deep a JSON text nests its arrays and objects, counted without parsing it (no recursion: linear time,
    whatever the text; brackets inside strings do not count)."""
    return _bracket_depth(_JSON_STRING.sub('""', text))


def toml_depth(text: str) -> int:
    """How deep a TOML text nests its arrays and inline tables (what tomllib recurses on), counted without parsing
    it, as json_depth does: brackets inside strings and comments do not count; a table header ([a] or [[a]]) counts
    1 or 2 while it is open."""
    return _bracket_depth(_TOML_SKIPPED.sub("", text))


def _bracket_depth(skeleton: str) -> int:
    """The deepest nesting of [ and { in a text whose strings are gone (linear time, no recursion)."""
    codes = np.frombuffer(skeleton.encode("utf-8", "replace"), dtype=np.uint8)
    steps = np.isin(codes, (ord("["), ord("{"))).astype(np.int64) - np.isin(codes, (ord("]"), ord("}")))
    return int(np.cumsum(steps).max(initial=0))


def npz_budget(file_size: int) -> int:
    """The most bytes the arrays of an .npz of file_size bytes may take once read."""
    return max(MIN_BUDGET_BYTES, MAX_EXPANSION * file_size)


def check_npz(path: str | os.PathLike[str], *, max_bytes: int | None = None) -> None:
    """Refuse an .npz archive that would make np.load allocate or inflate far more than its size.

    Checks, in order, without reading any member's data: the number of members (from the end-of-directory
    record, before zipfile parses the directory), each member's compression method and encryption, that each
    .npy member's declared size equals what its header describes (shape x itemsize), and that the sizes add up
    to at most max_bytes.

    Args:
        path: the .npz file.
        max_bytes: the largest total size of the arrays once read [bytes]; default npz_budget(file size).

    Raises:
        TrajectoryFileError: the archive breaks one of the limits, or is not a readable zip archive.
    """
    path = Path(path)
    try:
        size = path.stat().st_size
        budget = npz_budget(size) if max_bytes is None else max_bytes
        with path.open("rb") as f:
            members = _member_count(f, size)
            if members is not None and members > MAX_NPZ_MEMBERS:
                raise TrajectoryFileError(
                    f"{path}: not a trajectory file ({members} archive members, more than {MAX_NPZ_MEMBERS})"
                )
            with zipfile.ZipFile(f) as archive:
                _check_members(archive, path, budget, size)
    except TrajectoryFileError as exc:  # member names come from the file: print them safely
        shown = printable(str(exc))
        if shown == str(exc):
            raise
        raise TrajectoryFileError(shown) from None
    except FileNotFoundError:
        raise TrajectoryFileError(f"{path}: no such trajectory file") from None
    except ARCHIVE_ERRORS as exc:
        raise TrajectoryFileError(f"{path}: not a readable trajectory file ({_first_line(exc)})") from None


def read_npz(path: str | os.PathLike[str], *, max_bytes: int | None = None) -> dict[str, np.ndarray]:
    """Every array of an .npz, read without pickle after check_npz.

    Args:
        path: the .npz file.
        max_bytes: as for check_npz.

    Returns:
        {member name without .npy: array}.

    Raises:
        TrajectoryFileError: check_npz refused the file, or it is truncated or corrupted (a bad CRC, a broken
            deflate stream, an object array that would need pickle).
    """
    path = Path(path)
    check_npz(path, max_bytes=max_bytes)
    try:
        with np.load(path, allow_pickle=False) as npz:
            return {name: npz[name] for name in npz.files}
    except FileNotFoundError:
        raise TrajectoryFileError(f"{path}: no such trajectory file") from None
    except ARCHIVE_ERRORS as exc:
        raise TrajectoryFileError(f"{path}: not a readable trajectory file ({_first_line(exc)})") from None


def _member_count(f: BinaryIO, size: int) -> int | None:
    """The member count in zip's end-of-central-directory record, or None if there is no such record.

    Read from the last 64 KiB + 22 bytes, so that an archive claiming millions of members is refused before
    zipfile builds one object per member. A count of 0xFFFF means "65535 or more" (zip64).
    """
    tail = min(size, _END_RECORD_SIZE + 0xFFFF)
    f.seek(size - tail)
    data = f.read(tail)
    at = data.rfind(_END_OF_DIRECTORY)
    if at < 0 or len(data) - at < _END_RECORD_SIZE:
        return None  # zipfile will say the file is not a zip file
    return int(struct.unpack("<H", data[at + 10 : at + 12])[0])


def _check_members(archive: zipfile.ZipFile, path: Path, budget: int, size: int) -> None:
    members = archive.infolist()
    if len(members) > MAX_NPZ_MEMBERS:
        raise TrajectoryFileError(
            f"{path}: not a trajectory file ({len(members)} archive members, more than {MAX_NPZ_MEMBERS})"
        )
    total = 0
    for info in members:
        name = info.filename
        if info.flag_bits & 0x1:
            raise TrajectoryFileError(f"{path}: not a trajectory file (member '{name}' is encrypted)")
        if info.compress_type not in _READABLE_COMPRESSION:
            raise TrajectoryFileError(
                f"{path}: not a trajectory file (member '{name}' uses zip compression method {info.compress_type}; "
                "only stored and deflated members are read)"
            )
        total += info.file_size
        if total > budget:
            raise TrajectoryFileError(_too_big(path, total, budget, size))
        if name.endswith(".npy"):
            _check_npy_header(archive, info, path)


def _check_npy_header(archive: zipfile.ZipFile, info: zipfile.ZipInfo, path: Path) -> None:
    """The member's declared size must be exactly its header plus shape x itemsize bytes.

    np.load allocates the array from the header's shape before reading any data: a header that claims more
    than the member holds would make it allocate without bound.
    """
    with archive.open(info) as member:
        try:
            version = np.lib.format.read_magic(member)
            if version == (1, 0):
                shape, _, dtype = np.lib.format.read_array_header_1_0(member, max_header_size=MAX_HEADER_BYTES)
            elif version == (2, 0):
                shape, _, dtype = np.lib.format.read_array_header_2_0(member, max_header_size=MAX_HEADER_BYTES)
            else:
                raise TrajectoryFileError(
                    f"{path}: not a readable trajectory file (member '{info.filename}' is .npy format version "
                    f"{version[0]}.{version[1]}; trajectories use 1.0 or 2.0)"
                )
        except (TrajectoryFileError, OSError, EOFError, zlib.error, zipfile.BadZipFile):
            raise  # a damaged archive, not a damaged header: check_npz words it
        # numpy parses the header's Python literal with tokenize and ast: a damaged one raises ValueError,
        # SyntaxError or tokenize.TokenError (atheris found the last), none of them ours.
        except Exception as exc:
            raise TrajectoryFileError(
                f"{path}: not a readable trajectory file (member '{info.filename}' has a malformed .npy header: "
                f"{_first_line(exc)})"
            ) from None
        header_bytes = member.tell()  # ZipExtFile counts the uncompressed bytes read so far
    if dtype.hasobject:
        return  # a pickled object array: np.load(allow_pickle=False) refuses it with its own words
    data_bytes = dtype.itemsize * math.prod(shape)  # Python integers: a claimed shape cannot overflow
    if header_bytes + data_bytes != info.file_size:
        raise TrajectoryFileError(
            f"{path}: not a readable trajectory file (member '{info.filename}' holds {info.file_size} bytes but "
            f"its header describes {header_bytes + data_bytes}: shape {tuple(shape)}, dtype {dtype})"
        )


def _too_big(path: Path, total: int, budget: int, size: int) -> str:
    return (
        f"{path}: refused: its arrays would take more than {budget} bytes once read "
        f"(at least {total}, from a {size}-byte file; the limit is {MAX_EXPANSION} times the file's size or "
        f"{MIN_BUDGET_BYTES} bytes, whichever is larger)"
    )


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


# ---- resources: what this process may still allocate and write ----------------------------------------------
_GENEROUS = 1 << 40  # where a limit cannot be read (not Linux): assume a generous machine
_NO_CGROUP_LIMIT = 1 << 60  # cgroup v1 writes "no limit" as a huge number (9223372036854771712)


@dataclass(frozen=True)
class Room:
    """How many bytes this process may still allocate, and which limit binds.

    Attributes:
        bytes: the room [bytes].
        limit: the binding limit, in words ("the machine's available memory", "this process's address-space limit
            (ulimit -v)", "its cgroup's memory limit").
    """

    bytes: int
    limit: str


def usable_memory() -> int:
    """Memory this process may still allocate [bytes]: the least of the machine's available memory, the room left
    under its address-space limit (RLIMIT_AS) and the room left under its cgroup's memory limit (v2 or v1)."""
    return memory_room().bytes


def memory_room(*, cgroup_root: Path = Path("/sys/fs/cgroup"), proc_cgroup: Path = Path("/proc/self/cgroup")) -> Room:
    """usable_memory() with the limit that binds (the paths are parameters for tests)."""
    rooms = [Room(_available_memory(), "the machine's available memory")]
    address_space = _address_space_room()
    if address_space is not None:
        rooms.append(Room(address_space, "this process's address-space limit (ulimit -v)"))
    cgroup = cgroup_memory_room(cgroup_root, proc_cgroup)
    if cgroup is not None:
        rooms.append(Room(cgroup, "its cgroup's memory limit"))
    return min(rooms, key=lambda room: room.bytes)


def _available_memory() -> int:
    """MemAvailable (what can be allocated without swapping), else the free pages."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (ValueError, OSError, AttributeError):
        return _GENEROUS


def _address_space_room() -> int | None:
    """RLIMIT_AS less the address space already mapped (VmSize), or None without a limit."""
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_AS)[0]
    except (ImportError, OSError, ValueError):
        return None
    if soft == resource.RLIM_INFINITY:
        return None
    try:
        with open("/proc/self/status") as f:
            used = next(int(line.split()[1]) * 1024 for line in f if line.startswith("VmSize:"))
    except (OSError, ValueError, StopIteration):
        used = 0
    return max(0, soft - used)


def cgroup_memory_room(cgroup_root: Path, proc_cgroup: Path) -> int | None:
    """The room under the memory limits of this process's cgroup and its ancestors (the tightest), or None.

    cgroup v2 ("0::/path" in /proc/self/cgroup): memory.max less memory.current in cgroup_root/path and each
    parent. cgroup v1 ("N:...memory...:/path"): memory.limit_in_bytes less memory.usage_in_bytes under
    cgroup_root/memory/path and its parents.
    """
    try:
        lines = proc_cgroup.read_text().splitlines()
    except OSError:
        return None
    rooms = []
    for line in lines:
        fields = line.split(":", 2)
        if len(fields) != 3:
            continue
        hierarchy, controllers, path = fields
        if hierarchy == "0" and controllers == "":
            base, limit_file, usage_file = cgroup_root, "memory.max", "memory.current"
        elif "memory" in controllers.split(","):
            base, limit_file, usage_file = cgroup_root / "memory", "memory.limit_in_bytes", "memory.usage_in_bytes"
        else:
            continue
        folder = base / path.lstrip("/")
        while True:
            room = _cgroup_room(folder, limit_file, usage_file)
            if room is not None:
                rooms.append(room)
            if folder == base or base not in folder.parents:
                break
            folder = folder.parent
    return min(rooms) if rooms else None


def _cgroup_room(folder: Path, limit_file: str, usage_file: str) -> int | None:
    try:
        text = (folder / limit_file).read_text().strip()
    except OSError:
        return None
    if text == "max" or not text.isdigit() or int(text) >= _NO_CGROUP_LIMIT:
        return None
    try:
        used = int((folder / usage_file).read_text().strip())
    except (OSError, ValueError):
        used = 0
    return max(0, int(text) - used)


def check_allocation(nbytes: float, what: str, advice: str) -> None:
    """Refuse an allocation of nbytes that this process cannot make, before making it (a MemoryError, or the
    kernel's OOM killer, helps no one). Allocations up to SMALL_ALLOCATION are let through unread.

    Args:
        nbytes: the bytes needed.
        what: what needs them ("this run would keep 1e+09 samples"), the start of the message.
        advice: what to do instead.

    Raises:
        InvalidArgumentError: nbytes exceeds usable_memory(); the message names the binding limit.
    """
    if nbytes <= SMALL_ALLOCATION:
        return
    room = memory_room()
    if nbytes > room.bytes:
        from .exceptions import InvalidArgumentError

        raise InvalidArgumentError(
            f"{what} ({nbytes / 2**30:.3g} GiB) in memory, more than the {room.bytes / 2**30:.3g} GiB available "
            f"({room.limit}): {advice}"
        )


def file_size_limit() -> int | None:
    """This process's file-size limit (RLIMIT_FSIZE, ulimit -f) [bytes], or None without one."""
    try:
        import resource

        soft = resource.getrlimit(resource.RLIMIT_FSIZE)[0]
    except (ImportError, OSError, ValueError):
        return None
    return None if soft == resource.RLIM_INFINITY else int(soft)


def check_file_size(nbytes: float, what: str, advice: str) -> None:
    """Refuse to start writing a file of about nbytes that RLIMIT_FSIZE would cut short (EFBIG mid-write).

    Raises:
        InvalidArgumentError: nbytes exceeds file_size_limit().
    """
    limit = file_size_limit()
    if limit is not None and nbytes > limit:
        from .exceptions import InvalidArgumentError

        raise InvalidArgumentError(
            f"{what} would take about {nbytes / 1e6:.3g} MB, more than this process's file-size limit "
            f"({limit / 1e6:.3g} MB, ulimit -f): {advice}"
        )
