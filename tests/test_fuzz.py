"""Fuzzing the loaders of untrusted files: whatever the bytes, only the project's own errors come out.

Slow (run by scripts/fuzz.py, which sets the case budget): hypothesis mutates valid URDFs (attribute values
including NaN, inf, huge, negative and path tricks; deleted, duplicated, moved and renamed elements; random
bytes; truncation) and valid trajectory files (byte flips and cuts in the zip structures, rewritten members,
random JSON headers), and feeds them to load_robot and Trajectory.load. A model that loads must be usable
(finite, positive-definite mass matrix); a refusal must be a MultibodySimError with a one-line message that
starts with the file's path, and must leave nothing on stderr (file descriptor 2: C++ logging included).

Environment: MBS_FUZZ_CASES (examples per fuzzer, default 200), MBS_FUZZ_REPORT (a file to which each fuzzer
appends one JSON line: its name, the cases it ran, and the failures it saw).
"""

from __future__ import annotations

import contextlib
import copy
import io
import json
import os
import re
import sys
import tempfile
import traceback
import warnings
import zipfile
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import joint, link, urdf

import multibody_sim as ms
from multibody_sim.catalog import CATALOG, catalog_urdf

hypothesis = pytest.importorskip("hypothesis")
from hypothesis import HealthCheck, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from lxml import etree  # noqa: E402

pytestmark = pytest.mark.slow

CASES = int(os.environ.get("MBS_FUZZ_CASES", "200"))
REPORT = os.environ.get("MBS_FUZZ_REPORT")
FUZZ_SETTINGS = settings(
    max_examples=CASES,
    deadline=None,
    derandomize=True,  # seeded: the same cases on every run
    database=None,  # nothing written into the repository
    suppress_health_check=list(HealthCheck),
    print_blob=True,
)


# ---- bookkeeping -----------------------------------------------------------------------------------------
class Tally:
    """Cases run and failures seen by one fuzzer; written to MBS_FUZZ_REPORT at the end."""

    def __init__(self, name: str):
        self.name = name
        self.cases = 0
        self.outcomes: dict[str, int] = {}
        self.failures: list[str] = []
        self.repeats: dict[str, int] = {}
        self.known = False  # every failure is of a known, reported bug

    def count(self, outcome: str) -> None:
        self.cases += 1
        self.outcomes[outcome] = self.outcomes.get(outcome, 0) + 1

    def fail(self, description: str) -> None:
        """Record a failure; repeats of a kind already seen (same first line and raising line) are only counted."""
        frames = re.findall(r'File "[^"]+", line \d+, in \w+', description)
        kind = description.splitlines()[0][:80] + (frames[-1] if frames else "")
        self.repeats[kind] = self.repeats.get(kind, 0) + 1
        if self.repeats[kind] == 1 and len(self.failures) < 50:
            self.failures.append(description)

    def write(self) -> None:
        if REPORT:
            record = {
                "fuzzer": self.name,
                "cases": self.cases,
                "outcomes": self.outcomes,
                "failures": self.failures,
                "failure_counts": self.repeats,
                "known": self.known,
            }
            with open(REPORT, "a") as f:
                f.write(json.dumps(record) + "\n")


@contextmanager
def fd2_log() -> Iterator[Callable[[], str]]:
    """Redirect file descriptor 2 to a file for the block; yields a function returning what arrived since its
    previous call (what C++ code or Python wrote to stderr)."""
    sys.stderr.flush()
    saved = os.dup(2)
    with tempfile.TemporaryFile() as sink:
        os.dup2(sink.fileno(), 2)
        position = 0

        def since_last() -> str:
            nonlocal position
            sys.stderr.flush()
            sink.seek(position)
            text = sink.read().decode("utf-8", "replace")
            position = sink.tell()
            return text

        try:
            yield since_last
        finally:
            os.dup2(saved, 2)
            os.close(saved)


def check_refusal(exc: BaseException, path: Path) -> str | None:
    """None if exc is a proper refusal of the file at path, else what is wrong with it."""
    if not isinstance(exc, ms.MultibodySimError):
        return f"raw {type(exc).__name__}: {exc!s:.300}"
    message = str(exc)
    if "\n" in message:
        return f"multi-line message: {message!r:.300}"
    if not message.startswith(f"{path}") and not message.startswith(f"{path.resolve()}"):
        return f"message does not name the file: {message!r:.300}"
    return None


# ---- URDF seeds and mutations ----------------------------------------------------------------------------
def seed_urdfs() -> list[tuple[bytes, list[str]]]:
    """(URDF bytes, package dirs) of valid robots: small ones written here (every element kind the loader
    reads) and catalog files."""
    mesh = (
        '<visual><origin xyz="0 0 0.1" rpy="0 0 0"/><geometry><mesh filename="meshes/bob.stl" scale="1 1 1"/>'
        '</geometry><material name="red"><color rgba="1 0 0 1"/></material></visual>'
        '<collision><geometry><box size="0.1 0.1 0.1"/></geometry></collision>'
    )
    small = urdf(
        '<link name="base"/>',
        link("upper").replace("</link>", mesh + "</link>"),
        joint("shoulder", "base", "upper", damping=0.1),
        link("lower", mass=0.5, com="0 0 -0.4"),
        joint("elbow", "upper", "lower", xyz="0 0 -1", kind="continuous"),
        link("tool", mass=0.0, inertia="0 0 0"),
        joint("mount", "lower", "tool", kind="fixed", xyz="0 0 -0.8"),
        link("slider", mass=0.2, inertia="0.001 0.001 0.001"),
        joint("slide", "lower", "slider", kind="prismatic", axis="1 0 0"),
    )
    free = urdf(link("box", com="0 0 0", inertia="0.02 0.03 0.04"))
    seeds = [(small.encode(), []), (free.encode(), [])]
    for name in ("pendulum", "double_pendulum", "ur5", "solo12"):
        path, dirs = catalog_urdf(CATALOG[name])
        seeds.append((path.read_bytes(), [str(d) for d in dirs]))
    return seeds


SEEDS = seed_urdfs()
ATTRIBUTES = [
    "name", "type", "xyz", "rpy", "value", "ixx", "ixy", "ixz", "iyy", "iyz", "izz", "lower", "upper", "effort",
    "velocity", "damping", "friction", "filename", "link", "scale", "size", "radius", "length", "rgba", "joint",
    "multiplier", "offset",
]  # fmt: skip
TAGS = [
    "link", "joint", "inertial", "origin", "mass", "inertia", "axis", "limit", "dynamics", "parent", "child",
    "visual", "collision", "geometry", "mesh", "material", "texture", "mimic",
]  # fmt: skip
SPECIAL_VALUES = [
    "nan", "inf", "-inf", "NaN", "1e309", "-1e309", "1e308", "-1e308", "1e-320", "-0", "0", "-1", "", " ", "0x10",
    "1,2,3", "1 2", "1 2 3 4", "nan nan nan", "1e300 1e300 1e300", "package://", "package://x/../../../etc/passwd",
    "/etc/passwd", "file:///etc/passwd", "../../../../etc/passwd", "http://127.0.0.1:9/x.stl", "é", "a" * 2000,
    "revolute", "fixed", "floating", "planar", "continuous", "prismatic", "base", "root_joint", "universe",
    "a\nb", "x\x9b2J", "\u202eevil", "tab\there", "A" * 100_000,
]  # fmt: skip
numbers = st.floats(allow_nan=True, allow_infinity=True).map(repr)
vectors = st.lists(st.floats(allow_nan=True, allow_infinity=True, width=32), min_size=1, max_size=4).map(
    lambda v: " ".join(repr(float(x)) for x in v)
)
# XML attribute values cannot hold control characters or NUL (lxml refuses to write them).
words = st.text(alphabet=st.characters(blacklist_categories=("Cc", "Cs")), max_size=12)
values = st.one_of(st.sampled_from(SPECIAL_VALUES), numbers, vectors, words)


@st.composite
def mutated_urdf(draw: st.DrawFn) -> tuple[bytes, list[str]]:
    text, dirs = draw(st.sampled_from(SEEDS))
    root = etree.fromstring(text, etree.XMLParser(remove_comments=True))
    for _ in range(draw(st.integers(1, 4))):
        elements = list(root.iter())
        target = draw(st.sampled_from(elements))
        action = draw(st.sampled_from(["attribute", "attribute", "delete", "duplicate", "move", "retag"]))
        if action == "attribute":
            name = draw(st.sampled_from(sorted(target.attrib) or ATTRIBUTES) | st.sampled_from(ATTRIBUTES))
            target.set(name, draw(values))
        elif target is root:
            continue
        elif action == "delete":
            target.getparent().remove(target)
        elif action == "duplicate":
            target.addnext(copy.deepcopy(target))
        elif action == "move":
            destination = draw(st.sampled_from(elements))
            if target not in destination.iterancestors() and destination is not target:
                destination.append(target)
        else:
            target.tag = draw(st.sampled_from(TAGS))
    data = etree.tostring(root)
    tail = draw(st.sampled_from(["none", "none", "truncate", "insert", "overwrite"]))
    if tail != "none":
        at = draw(st.integers(0, len(data)))
        if tail == "truncate":
            data = data[:at]
        elif tail == "insert":
            data = data[:at] + draw(st.binary(min_size=1, max_size=16)) + data[at:]
        else:
            patch = draw(st.binary(min_size=1, max_size=16))
            data = data[:at] + patch + data[at + len(patch) :]
    return data, dirs


def load_case(tally: Tally, path: Path, data: bytes, dirs: list[str], stderr: Callable[[], str]) -> None:
    """Load one fuzzed URDF and record what happened; a raw exception or stray stderr is a failure."""
    path.write_bytes(data)
    stderr()
    python_stderr = io.StringIO()  # logging's last-resort handler and print(file=sys.stderr) land here
    try:
        with warnings.catch_warnings(record=True) as caught, contextlib.redirect_stderr(python_stderr):
            warnings.simplefilter("always")  # a warning is a line on the CLI's stderr
            robot = ms.load_robot(path, package_dirs=dirs or None)
    except Exception as exc:  # anything but our own errors is the finding
        problem = check_refusal(exc, path)
        tally.count(type(exc).__name__)
        if problem is None and (log := stderr() + python_stderr.getvalue()):
            problem = f"refusal with output on stderr: {log!r:.300}"
        if problem is None and caught:
            problem = f"refusal with a warning: {caught[0].message!s:.300}"
        if problem is not None:
            tally.fail(f"{problem}\n  input: {data[:400]!r}\n  {''.join(traceback.format_exception(exc))[-1500:]}")
        return
    tally.count("loaded")
    if caught:
        tally.fail(f"loaded with a warning: {caught[0].message!s:.300} ({caught[0].filename}:{caught[0].lineno})")
    stderr()  # what urdfdom says about a model that does build is passed on; not a failure
    M = robot.mass_matrix(robot.neutral())
    if not (np.all(np.isfinite(M)) and np.all(np.linalg.eigvalsh(M) > 0)):
        tally.fail(f"loaded with a singular or non-finite mass matrix\n  input: {data[:400]!r}")


def run_fuzzer(
    name: str, body: Callable[[Tally, Callable[[], str]], None], known: Callable[[str], bool] | None = None
) -> None:
    """Run body with stderr watched; fail on any failure, unless every one is a known, reported bug."""
    tally = Tally(name)
    with fd2_log() as stderr:
        try:
            body(tally, stderr)
        finally:
            tally.known = bool(tally.failures) and known is not None and all(known(f) for f in tally.failures)
            tally.write()
    assert tally.cases >= min(CASES, 50), f"{name} ran only {tally.cases} cases"
    if tally.known:
        pytest.xfail(f"{len(tally.failures)} failures, all of a known bug: {tally.failures[0].splitlines()[0]}")
    assert not tally.failures, "\n\n".join(tally.failures)


def test_fuzz_urdf_mutations(tmp_path_factory: pytest.TempPathFactory):
    folder = tmp_path_factory.mktemp("fuzz-urdf")
    (folder / "meshes").mkdir()
    (folder / "meshes" / "bob.stl").write_text("solid bob\nendsolid bob\n")
    path = folder / "robot.urdf"

    def body(tally: Tally, stderr: Callable[[], str]) -> None:
        @FUZZ_SETTINGS
        @given(mutated_urdf())
        def case(example: tuple[bytes, list[str]]) -> None:
            load_case(tally, path, example[0], example[1], stderr)

        case()

    run_fuzzer("urdf-mutations", body)


def test_fuzz_urdf_random_bytes(tmp_path_factory: pytest.TempPathFactory):
    """Bytes from nowhere, and valid URDFs with random bytes after a random-length prefix."""
    path = tmp_path_factory.mktemp("fuzz-bytes") / "robot.urdf"

    @st.composite
    def spliced(draw: st.DrawFn) -> bytes:
        text, _ = draw(st.sampled_from(SEEDS))
        cut = draw(st.integers(0, len(text)))
        return text[:cut] + draw(st.binary(max_size=256))

    def body(tally: Tally, stderr: Callable[[], str]) -> None:
        @FUZZ_SETTINGS
        @given(st.one_of(st.binary(max_size=2048), spliced()))
        def case(data: bytes) -> None:
            load_case(tally, path, data, [], stderr)

        case()

    run_fuzzer("urdf-bytes", body)


# ---- trajectory files ------------------------------------------------------------------------------------
def seed_trajectories(folder: Path) -> list[bytes]:
    """A stored and a deflated trajectory file with every field filled (damping ledger, a controller)."""
    path = folder / "seed.urdf"
    path.write_text(
        urdf(
            '<link name="base"/>',
            link("upper"),
            joint("shoulder", "base", "upper", damping=0.1, limits='lower="-0.2" upper="0.2" effort="10" velocity="1"'),
            link("lower", mass=0.5),
            joint("elbow", "upper", "lower", xyz="0 0 -1"),
        )
    )
    run = ms.simulate(
        ms.load_robot(path), [0.5, -0.3], [0.0, 1.0], duration=0.05, dt=0.01, controller=lambda t, q, v: [0.1, -0.1]
    )
    stored = run.save(folder / "seed.npz")
    deflated = folder / "seed-deflated.npz"
    with zipfile.ZipFile(stored) as source, zipfile.ZipFile(deflated, "w", zipfile.ZIP_DEFLATED) as target:
        for info in source.infolist():
            target.writestr(info.filename, source.read(info))
    return [stored.read_bytes(), deflated.read_bytes()]


json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=8),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=8), children, max_size=4),
    max_leaves=12,
)


@st.composite
def mutated_npz(draw: st.DrawFn, seeds: list[bytes]) -> bytes:
    data = bytearray(draw(st.sampled_from(seeds)))
    kind = draw(st.sampled_from(["bytes", "bytes", "members", "header"]))
    if kind == "bytes":
        for _ in range(draw(st.integers(1, 4))):
            # Aim at the zip structures (local header at the start, directory at the end) as often as the data.
            region = draw(st.sampled_from(["start", "end", "anywhere"]))
            low, high = {"start": (0, 64), "end": (max(0, len(data) - 200), len(data)), "anywhere": (0, len(data))}[
                region
            ]
            at = draw(st.integers(low, max(low, high - 1)))
            action = draw(st.sampled_from(["flip", "cut", "insert"]))
            if action == "flip":
                patch = draw(st.binary(min_size=1, max_size=8))
                data[at : at + len(patch)] = patch
            elif action == "cut":
                del data[at : at + draw(st.integers(1, 64))]
            else:
                data[at:at] = draw(st.binary(min_size=1, max_size=8))
        return bytes(data)
    with zipfile.ZipFile(io.BytesIO(bytes(data))) as archive:
        members = {info.filename: archive.read(info) for info in archive.infolist()}
    if kind == "header":
        header = json.loads(str(np.load(io.BytesIO(members["header.npy"]), allow_pickle=False)[()]))
        key = draw(st.sampled_from(sorted(header) + ["stats", "ledger_kinds", "limit_violations", "metadata"]))
        inner = header.get(key)
        if isinstance(inner, dict) and inner and draw(st.booleans()):  # a field inside: stats.wall_time, ...
            inner[draw(st.sampled_from(sorted(inner)))] = draw(json_values)
        else:
            header[key] = draw(json_values)
        members["header.npy"] = _npy_bytes(np.array(json.dumps(header)))
    else:
        name = draw(st.sampled_from(sorted(members)))
        action = draw(st.sampled_from(["drop", "shape", "dtype", "garbage"]))
        if action == "drop":
            del members[name]
        elif action == "shape":
            shape = tuple(draw(st.lists(st.integers(-2, 10**13), max_size=3)))
            header = np.lib.format.header_data_from_array_1_0(np.zeros(1))
            header["shape"] = shape
            members[name] = _npy_header(header) + members[name][128:]
        elif action == "dtype":
            dtype = draw(st.sampled_from(["<i8", "<f4", "|b1", "<c16", "<U3", "|S5", "|V8", "<M8[s]"]))
            size = draw(st.integers(0, 6))
            members[name] = _npy_bytes(np.zeros(size, dtype=dtype))
        else:
            members[name] = draw(st.binary(max_size=64))
    compression = draw(st.sampled_from([zipfile.ZIP_STORED, zipfile.ZIP_DEFLATED]))
    out = io.BytesIO()
    with zipfile.ZipFile(out, "w", compression) as archive:
        for name, content in members.items():
            archive.writestr(name, content)
    return out.getvalue()


def _npy_bytes(array: np.ndarray) -> bytes:
    buffer = io.BytesIO()
    np.save(buffer, array)
    return buffer.getvalue()


def _npy_header(header: dict[str, Any]) -> bytes:
    buffer = io.BytesIO()
    np.lib.format.write_array_header_1_0(buffer, header)
    return buffer.getvalue()


def test_fuzz_trajectory_files(tmp_path_factory: pytest.TempPathFactory):
    folder = tmp_path_factory.mktemp("fuzz-npz")
    seeds = seed_trajectories(folder)
    path = folder / "fuzzed.npz"

    def body(tally: Tally, stderr: Callable[[], str]) -> None:
        @FUZZ_SETTINGS
        @given(mutated_npz(seeds), st.booleans())
        def case(data: bytes, mmap: bool) -> None:
            path.write_bytes(data)
            try:
                loaded = ms.Trajectory.load(path, mmap=mmap)
            except Exception as exc:  # anything but our own errors is the finding
                tally.count(type(exc).__name__)
                problem = check_refusal(exc, path)
                if problem is not None:
                    trace = "".join(traceback.format_exception(exc))[-1500:]
                    tally.fail(f"{problem}\n  input ({len(data)} bytes, mmap={mmap}): {data[:200]!r}\n  {trace}")
                return
            tally.count("loaded")
            len(loaded), loaded.summary()  # a loaded trajectory must be usable

        case()

    run_fuzzer("trajectory-files", body)


# ---- atheris (coverage-guided), when it installs -----------------------------------------------------------
def test_atheris_fuzzes_the_urdf_loader(tmp_path: Path):
    """A short coverage-guided run of scripts/fuzz.py's atheris harness (libFuzzer): no crash, no raw exception."""
    pytest.importorskip("atheris")
    import subprocess

    script = Path(__file__).resolve().parent.parent / "scripts" / "fuzz.py"
    runs = max(CASES, 200)
    result = subprocess.run(
        [sys.executable, str(script), "--atheris-worker", "urdf", "--runs", str(runs), "--work", str(tmp_path)],
        capture_output=True,
        text=True,
        timeout=3600,
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    assert f"Done {runs} runs" in result.stderr, result.stderr[-2000:]
