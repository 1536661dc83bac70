"""Fuzzing the loaders of untrusted files: whatever the bytes, only the project's own errors come out.

Each fuzzer runs twice: its first SMOKE_CASES cases in the default suite (a few seconds), and MBS_FUZZ_CASES in
the slow tier (scripts/fuzz.py sets that budget). Hypothesis mutates valid URDFs (attribute values
including NaN, inf, huge, negative and path tricks; deleted, duplicated, moved and renamed elements; random
bytes; truncation) and valid trajectory files (byte flips and cuts in the zip structures, rewritten members,
random JSON headers), and feeds them to load_robot and Trajectory.load. A model that loads must be usable
(finite, positive-definite mass matrix); a refusal must be a MultibodySimError with a one-line message that
starts with the file's path, and must leave nothing on stderr (file descriptor 2: C++ logging included).
Scene files (objects in contact among them) are mutated the same way (every key given hostile numbers, names,
paths and shapes, keys deleted and added, damaged bytes) and a scene that loads runs a few steps with its own
settings; the gym environments get hostile settings, actions, seeds and reset options, and answer with finite
observations or one of our errors in one line; the command line's numeric options get hostile numbers, and must
exit 0, 1 or 2 with a one-line refusal and never a traceback.

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
from hypothesis import HealthCheck, example, given, settings  # noqa: E402
from hypothesis import strategies as st  # noqa: E402
from lxml import etree  # noqa: E402

CASES = int(os.environ.get("MBS_FUZZ_CASES", "200"))
# The default suite runs every fuzzer on its first SMOKE_CASES cases (a few seconds each); the slow tier (and
# scripts/fuzz.py) on CASES. Seeded: the smoke's cases are the full run's first ones.
SMOKE_CASES = 25
BUDGETS = [pytest.param(SMOKE_CASES, id="smoke"), pytest.param(CASES, id="full", marks=pytest.mark.slow)]
REPORT = os.environ.get("MBS_FUZZ_REPORT")


def fuzz_settings(cases: int) -> Any:
    """hypothesis settings for a fuzzer run of `cases` examples."""
    return settings(
        max_examples=cases,
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
    name: str,
    body: Callable[[Tally, Callable[[], str]], None],
    known: Callable[[str], bool] | None = None,
    cases: int = CASES,
) -> None:
    """Run body with stderr watched; fail on any failure, unless every one is a known, reported bug."""
    tally = Tally(name)
    with fd2_log() as stderr:
        try:
            body(tally, stderr)
        finally:
            tally.known = bool(tally.failures) and known is not None and all(known(f) for f in tally.failures)
            tally.write()
    assert tally.cases >= min(cases // 2, 50), f"{name} ran only {tally.cases} cases"
    if tally.known:
        pytest.xfail(f"{len(tally.failures)} failures, all of a known bug: {tally.failures[0].splitlines()[0]}")
    assert not tally.failures, "\n\n".join(tally.failures)


@pytest.mark.parametrize("cases", BUDGETS)
def test_fuzz_urdf_mutations(tmp_path_factory: pytest.TempPathFactory, cases: int):
    folder = tmp_path_factory.mktemp("fuzz-urdf")
    (folder / "meshes").mkdir()
    (folder / "meshes" / "bob.stl").write_text("solid bob\nendsolid bob\n")
    path = folder / "robot.urdf"

    def body(tally: Tally, stderr: Callable[[], str]) -> None:
        @fuzz_settings(cases)
        @given(mutated_urdf())
        def case(example: tuple[bytes, list[str]]) -> None:
            load_case(tally, path, example[0], example[1], stderr)

        case()

    run_fuzzer("urdf-mutations", body, cases=cases)


@pytest.mark.parametrize("cases", BUDGETS)
def test_fuzz_urdf_random_bytes(tmp_path_factory: pytest.TempPathFactory, cases: int):
    """Bytes from nowhere, and valid URDFs with random bytes after a random-length prefix."""
    path = tmp_path_factory.mktemp("fuzz-bytes") / "robot.urdf"

    @st.composite
    def spliced(draw: st.DrawFn) -> bytes:
        text, _ = draw(st.sampled_from(SEEDS))
        cut = draw(st.integers(0, len(text)))
        return text[:cut] + draw(st.binary(max_size=256))

    def body(tally: Tally, stderr: Callable[[], str]) -> None:
        @fuzz_settings(cases)
        @given(st.one_of(st.binary(max_size=2048), spliced()))
        def case(data: bytes) -> None:
            load_case(tally, path, data, [], stderr)

        case()

    run_fuzzer("urdf-bytes", body, cases=cases)


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


@pytest.mark.parametrize("cases", BUDGETS)
def test_fuzz_trajectory_files(tmp_path_factory: pytest.TempPathFactory, cases: int):
    folder = tmp_path_factory.mktemp("fuzz-npz")
    seeds = seed_trajectories(folder)
    path = folder / "fuzzed.npz"

    def body(tally: Tally, stderr: Callable[[], str]) -> None:
        @fuzz_settings(cases)
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

    run_fuzzer("trajectory-files", body, cases=cases)


# ---- scene files ------------------------------------------------------------------------------------------
SCENE_SEEDS = [
    "spring_chain", "double_pendulum_spring_friction", "four_bar", "free_body_torqued", "panda_payload",
    "sliding_box", "box_stack", "bouncing_ball",  # scenes with objects: sizes, masses, placements, contact
]  # fmt: skip
SCENE_VALUES = [
    float("nan"), float("inf"), float("-inf"), 1e308, -1e308, 1e-320, -1.0, 0.0, 0, -1, 2**63 - 1, -(2**63), True,
    "", "x" * 5000, "a\nb", "\u202eevil", "/etc", "../../..", "/etc/passwd", "ur5", "nope", [], [1.0], [1.0] * 50,
    [[1.0, 2.0]], {}, {"x": 1.0}, ["a"],
]  # fmt: skip
TOML_BARE = re.compile(r"^[A-Za-z0-9_-]+$")


def toml_text(value: Any) -> str:
    """A value as TOML (inline tables and arrays; nan and inf are TOML words)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        return (
            "nan"
            if value != value
            else ("inf" if value == float("inf") else "-inf" if value == -float("inf") else repr(value))
        )
    if isinstance(value, str):
        return json.dumps(value)  # JSON's string escapes are TOML's basic-string escapes
    if isinstance(value, (list, tuple)):
        return "[" + ", ".join(toml_text(v) for v in value) + "]"
    items = ", ".join(f"{_toml_key(k)} = {toml_text(v)}" for k, v in value.items())
    return "{" + items + "}"


def _toml_key(key: str) -> str:
    return key if TOML_BARE.match(key) else json.dumps(key)


def toml_document(data: dict[str, Any]) -> str:
    return "".join(f"{_toml_key(k)} = {toml_text(v)}\n" for k, v in data.items())


def seed_scenes() -> list[dict[str, Any]]:
    from multibody_sim.scenes import shipped_scenes

    try:
        import tomllib
    except ModuleNotFoundError:  # Python < 3.11
        import tomli as tomllib  # type: ignore[no-redef]

    shipped = shipped_scenes()
    return [tomllib.loads(shipped[name].read_text()) for name in SCENE_SEEDS]


def _paths(value: Any, prefix: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    """Every key path into nested tables and arrays."""
    found = [prefix] if prefix else []
    if isinstance(value, dict):
        for key, item in value.items():
            found += _paths(item, (*prefix, key))
    elif isinstance(value, list):
        for i, item in enumerate(value):
            found += _paths(item, (*prefix, i))
    return found


@st.composite
def mutated_scene(draw: st.DrawFn, seeds: list[dict[str, Any]]) -> bytes:
    data = copy.deepcopy(draw(st.sampled_from(seeds)))
    for _ in range(draw(st.integers(1, 3))):
        paths = _paths(data)
        path = draw(st.sampled_from(paths))
        parent: Any = data
        for key in path[:-1]:
            parent = parent[key]
        action = draw(st.sampled_from(["value", "value", "value", "delete", "add"]))
        # Copies: a later mutation must not change SCENE_VALUES' lists and tables (nor make them hold themselves).
        if action == "value":
            value = draw(st.sampled_from(SCENE_VALUES) | st.floats() | st.integers() | st.text(max_size=8))
            parent[path[-1]] = copy.deepcopy(value)
        elif action == "delete":
            del parent[path[-1]]
        elif isinstance(parent, dict):
            parent[draw(st.text(min_size=1, max_size=8))] = copy.deepcopy(draw(st.sampled_from(SCENE_VALUES)))
    text = toml_document(data).encode()
    if draw(st.integers(0, 9)) == 0:  # and now and then damaged bytes, for the TOML parser and the size checks
        at = draw(st.integers(0, len(text)))
        text = text[:at] + draw(st.binary(min_size=1, max_size=16)) + text[at:]
    return text


def scene_regressions(seeds: list[dict[str, Any]]) -> Callable[[Callable[..., None]], Callable[..., None]]:
    """Scenes that once printed a traceback (issue 17), tried first by every run: the first seed (spring_chain)
    with a subnormal step, a step count beyond 2**53, an output period that overflows its count (scene.run
    keeps the scene's step and periods and shortens the duration)."""

    def variant(**simulation: Any) -> bytes:
        data = copy.deepcopy(seeds[0])
        settings = {k: v for k, v in data.get("simulation", {}).items() if k != "output_dt"}
        data["simulation"] = {**settings, "integrator": "rk4", **simulation}
        return toml_document(data).encode()

    cases = [variant(dt=1e-320), variant(duration=1e300, dt=1e-300), variant(dt=1e-10, output_dt=1e300)]

    def decorate(test: Callable[..., None]) -> Callable[..., None]:
        for data in reversed(cases):
            test = example(data)(test)
        return test

    return decorate


@pytest.mark.parametrize("cases", BUDGETS)
def test_fuzz_scene_files(tmp_path_factory: pytest.TempPathFactory, cases: int):
    """Mutated shipped scenes (hostile numbers, names, paths and shapes in every key; deleted and unknown keys;
    damaged bytes): load_scene raises only our errors, in one line, with nothing on stderr; a scene that loads
    runs three steps or stops with our error."""
    folder = tmp_path_factory.mktemp("fuzz-scenes")
    path = folder / "scene.toml"
    seeds = seed_scenes()

    def body(tally: Tally, stderr: Callable[[], str]) -> None:
        @fuzz_settings(cases)
        @given(mutated_scene(seeds))
        @scene_regressions(seeds)
        def case(data: bytes) -> None:
            path.write_bytes(data)
            stderr()
            try:
                with warnings.catch_warnings(record=True) as caught, time_limit(2.0):
                    warnings.simplefilter("always")
                    scene = ms.load_scene(path)
                    tally.count("loaded")
                    scene.describe()
                    scene.run(duration=3e-3)  # its own [simulation] settings: dt, integrator, periods
            except KeyboardInterrupt:  # the case's time ran out (a tiny dt, a slow model): not a finding
                tally.count("interrupted")
                return
            except Exception as exc:
                tally.count(type(exc).__name__)
                problem = None
                if not isinstance(exc, ms.MultibodySimError):
                    problem = f"raw {type(exc).__name__}: {exc!s:.300}"
                elif "\n" in str(exc):
                    problem = f"multi-line message: {str(exc)!r:.300}"
                if problem is not None:
                    trace = "".join(traceback.format_exception(exc))[-1500:]
                    tally.fail(f"{problem}\n  input: {data[:600]!r}\n  {trace}")
                return
            if log := stderr():
                tally.fail(f"output on stderr: {log!r:.300}\n  input: {data[:600]!r}")
            if [w for w in caught if not issubclass(w.category, RuntimeWarning)]:
                tally.fail(f"a warning: {caught[0].message!s:.300}\n  input: {data[:600]!r}")

        case()

    run_fuzzer("scene-files", body, cases=cases)


# ---- gym environments ------------------------------------------------------------------------------------
# Hostile entries of actions, states and seeds: non-finite, huge, subnormal, huge integers, booleans, complex numbers,
# strings, None and objects.
GYM_ENTRIES = [
    float("nan"), float("inf"), -float("inf"), 1e308, -1e308, 1e-320, 0.0, 1.0, -1.0, 2**64, -(2**70), True,
    1 + 1j, "1.0", "x", None, b"\x00",
]  # fmt: skip
GYM_SETTINGS = {
    "control_dt": [0.01, 0.0, -1.0, float("nan"), float("inf"), 1e308, 1e-320, 0.003, "0.01", None, True],
    "dt": [None, 0.002, 0.0, float("nan"), 1e-320, 1e308, 0.007, "x"],
    "method": [None, "rk4", "dp54", "implicit_euler", "timestepping", "nope", "", 3],
    "max_episode_steps": [None, 5, 0, -1, 1.5, 2**70, True, "5"],
    "reset_noise_q": [0.01, 0.0, -1.0, float("nan"), float("inf"), 1e308, "a"],
    "reset_noise_v": [0.01, 1e308, float("-inf"), None],
    "failure_reward": [0.0, float("nan"), float("inf"), -1e308, "0", None],
    "initial_q": [None, [0.0], [float("nan")] * 6, ["a"] * 6, 1e308],
    "num_envs": [2, 1, 0, -1, 2.0, True, "2", 2**62, 10**7],
    "autoreset_mode": ["NextStep", "SameStep", "Disabled", "never", None, 0],
    "num_threads": [1, 2, 0, -1, 1.5, 2**62],
}


@st.composite
def gym_array(draw: st.DrawFn, shape: tuple[int, ...]) -> Any:
    """An array-like of roughly `shape`: numbers, hostile entries, wrong shapes, ragged nesting, scalars, objects."""
    kind = draw(st.sampled_from(["numbers", "numbers", "hostile", "shape", "ragged", "scalar", "object", "dtype"]))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    if kind == "numbers":
        return rng.normal(scale=draw(st.sampled_from([1.0, 100.0, 1e6])), size=shape)
    if kind == "hostile":
        values = rng.normal(size=shape).astype(object)
        flat = values.reshape(-1)
        for _ in range(draw(st.integers(1, 3))):
            flat[draw(st.integers(0, len(flat) - 1))] = draw(st.sampled_from(GYM_ENTRIES))
        return values.tolist() if draw(st.booleans()) else values
    if kind == "shape":
        other = draw(st.lists(st.integers(0, 8), max_size=3).map(tuple))
        return np.zeros(other)
    if kind == "ragged":
        return [[0.0] * n for n in draw(st.lists(st.integers(0, 7), min_size=1, max_size=3))]
    if kind == "scalar":
        return draw(st.sampled_from(GYM_ENTRIES))
    if kind == "object":
        return draw(st.sampled_from([{"q": 1}, object(), "abc", [None], ()]))
    return np.zeros(shape, dtype=draw(st.sampled_from([np.float32, np.int8, np.uint64, np.complex64, np.bool_, "U3"])))


@st.composite
def gym_calls(draw: st.DrawFn, nq: int, nv: int, n: int) -> list[tuple[str, Any]]:
    """A few calls of an environment of n rows (n = 0: the single environment): steps and resets with seeds and
    options."""
    rows = () if n == 0 else (n,)
    calls: list[tuple[str, Any]] = [("reset", {"seed": draw(st.integers(0, 10))})]
    for _ in range(draw(st.integers(1, 4))):
        if draw(st.integers(0, 2)):
            calls.append(("step", draw(gym_array((*rows, nv)))))
            continue
        seed = draw(
            st.sampled_from([None, 0, 7, -1, 2**70, 1.5, "1", True, [0, 1], [0], [None, None], [-5, 2]])
            | st.integers(-(2**65), 2**65)
        )
        options: Any = draw(st.sampled_from([None, {}, "q", 3]))
        if isinstance(options, dict) and draw(st.booleans()):
            options = {"q": draw(gym_array((*rows, nq)))}
            if draw(st.booleans()):
                options["v"] = draw(gym_array((*rows, nv)))
        if n and draw(st.integers(0, 2)) == 0:
            mask = draw(st.sampled_from([np.array([True, False]), np.array([False, False]), [1, 0], np.ones(3, bool)]))
            options = {**(options if isinstance(options, dict) else {}), "reset_mask": mask}
        calls.append(("reset", {"seed": seed, "options": options}))
    return calls


def gym_refusal(exc: BaseException) -> str | None:
    """None if exc is a proper refusal (one of our errors, one line), else what is wrong with it."""
    if not isinstance(exc, ms.MultibodySimError):
        return f"raw {type(exc).__name__}: {exc!s:.300}"
    if "\n" in str(exc):
        return f"multi-line message: {str(exc)!r:.300}"
    return None


@pytest.mark.parametrize("cases", BUDGETS)
def test_fuzz_gym_environments(cases: int):
    """MultibodyEnv and MultibodyVectorEnv (ur5, solo12's floating base, a scene with a free object in contact) given
    hostile settings, actions, seeds and reset options: each call returns finite observations of the right shape or
    raises one of our errors in one line, with no warning and nothing on stderr."""
    gym = pytest.importorskip("multibody_sim.gym")
    systems = {
        "ur5": ms.load_robot("ur5"),
        "solo12": ms.load_robot("solo12"),
        "sliding_box": ms.load_scene("sliding_box"),
    }

    def reward(q: np.ndarray, v: np.ndarray, tau: np.ndarray) -> float:
        return float(-(v @ v))

    def body(tally: Tally, stderr: Callable[[], str]) -> None:
        @fuzz_settings(cases)
        @given(
            st.sampled_from(sorted(systems)),
            st.booleans(),
            st.dictionaries(st.sampled_from(sorted(GYM_SETTINGS)), st.integers(0, 10), max_size=3),
            st.data(),
        )
        def case(name: str, vector: bool, picks: dict[str, int], data: Any) -> None:
            system = systems[name]
            chosen = {key: GYM_SETTINGS[key][i % len(GYM_SETTINGS[key])] for key, i in picks.items()}
            settings = {"reward": reward, "control_dt": 0.01, "dt": 0.002 if name != "sliding_box" else None}
            settings.update({k: v for k, v in chosen.items() if k not in ("num_envs", "autoreset_mode", "num_threads")})
            n = 0
            if vector:
                n = chosen.get("num_envs", 2)
                extra = {k: chosen[k] for k in ("autoreset_mode", "num_threads") if k in chosen}
            stderr()
            described = f"{name} {'vector' if vector else 'single'} {chosen!r:.300}"
            try:
                with warnings.catch_warnings(record=True) as caught, time_limit(5.0):
                    warnings.simplefilter("always")
                    if vector:
                        env = gym.MultibodyVectorEnv(system, n, **settings, **extra)
                    else:
                        env = gym.MultibodyEnv(system, **settings)
                    tally.count("built")
                    calls = data.draw(gym_calls(system.nq, system.nv, env.num_envs if vector else 0))
                    described += f" calls {calls!r:.600}"
                    for call, argument in calls:
                        try:
                            result = env.step(argument) if call == "step" else env.reset(**argument)
                        except ms.MultibodySimError as exc:
                            if (problem := gym_refusal(exc)) is not None:
                                tally.fail(f"{problem}\n  case: {described}")
                            tally.count(f"{call} refused")
                            continue
                        observation = result[0]
                        shape = (env.num_envs, system.nq + system.nv) if vector else (system.nq + system.nv,)
                        if np.shape(observation) != shape or not np.all(np.isfinite(observation)):
                            tally.fail(f"{call} gave a bad observation {observation!r:.200}\n  case: {described}")
                        tally.count(call)
            except KeyboardInterrupt:  # the case's time ran out: not a finding
                tally.count("interrupted")
                return
            except Exception as exc:
                tally.count(type(exc).__name__)
                if (problem := gym_refusal(exc)) is not None:
                    trace = "".join(traceback.format_exception(exc))[-1500:]
                    tally.fail(f"{problem}\n  case: {described}\n  {trace}")
                return
            if log := stderr():
                tally.fail(f"output on stderr: {log!r:.300}\n  case: {described}")
            if caught:
                tally.fail(f"a warning: {caught[0].message!s:.300}\n  case: {described}")

        case()

    run_fuzzer("gym-environments", body, cases=cases)


# ---- command-line numbers ----------------------------------------------------------------------------------
NUMBER_WORDS = [
    "nan", "NaN", "inf", "-inf", "1e309", "-1e309", "1e308", "1e-320", "1e-400", "-0", "0", "-1", "1", "0.5",
    "1e300", "1e-300", "2e-16", "99999999999999999999999", "65535", "65536", "70000", "-65536", "0x10", "1_000",
    "", " ", "1e", "abc", "\u202e1",
]  # fmt: skip
# (command, option, the rest of a command line that runs quickly when the option's value is accepted)
NUMERIC_OPTIONS = [
    ("run", "--dt", ["--duration", "0.01"]),
    ("run", "--duration", ["--dt", "0.005"]),
    ("run", "--output-dt", ["--duration", "0.01"]),
    ("run", "--control-dt", ["--duration", "0.01"]),
    ("run", "--rtol", ["--integrator", "dp54", "--duration", "0.01"]),
    ("run", "--atol", ["--integrator", "dp54", "--duration", "0.01"]),
    ("run", "--max-step", ["--integrator", "dp54", "--duration", "0.01"]),
    ("run", "--view-speed", ["--duration", "0.01"]),
    ("run", "--view-port", ["--duration", "0.01"]),
    ("run", "--chunk", ["--duration", "0.01", "--out", "{tmp}/run.npz"]),
    ("run", "--q0", ["--duration", "0.01"]),
    ("run", "--tolerance", ["--duration", "0.02"]),
    ("play", "--fps", ["--html", "{tmp}/view.html"]),
    ("play", "--speed", ["--html", "{tmp}/view.html"]),
    ("play", "--port", []),
    ("play", "--width", ["--video", "{tmp}/v.mp4"]),
    ("bench", "--duration", ["--integrators", "euler", "--out", "{tmp}"]),
]


def _option(command: str, flag: str) -> tuple[str, str, list[str]]:
    return next(o for o in NUMERIC_OPTIONS if o[:2] == (command, flag))


# Inputs that once printed a traceback or were silently changed (issue 17): every run tries them first.
CLI_REGRESSIONS = [
    (("run", "--dt"), "1e-320"),  # OverflowError: duration / dt
    (("run", "--control-dt"), "1e308"),  # OverflowError: control_dt / dt
    (("run", "--output-dt"), "1e300"),
    (("run", "--view-port"), "70000"),  # wrapped to port 4464
    (("run", "--chunk"), "99999999999999999999999"),  # numpy: maximum allowed dimension exceeded
    (("run", "--rtol"), "1e-320"),  # silently accepted
    (("play", "--fps"), "1e9"),
    (("bench", "--duration"), "1e-320"),
]


def cli_regressions(test: Callable[..., None]) -> Callable[..., None]:
    for (command, flag), word in reversed(CLI_REGRESSIONS):
        test = example(_option(command, flag), word)(test)
    return test


@contextmanager
def time_limit(seconds: float) -> Iterator[None]:
    """Raise KeyboardInterrupt in the block after `seconds` (a run's own Ctrl-C path: an accepted input that runs
    long ends a case; it does not fail it)."""
    import signal

    def expire(signum: int, frame: Any) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGALRM, expire)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, previous)


@pytest.mark.parametrize("cases", BUDGETS)
def test_fuzz_command_line_numbers(tmp_path_factory: pytest.TempPathFactory, cases: int):
    """Every numeric option of run, play and bench given hostile numbers (NaN, infinities, subnormals, overflows,
    ports beyond 65535, hex, words): the command exits 0, 1 or 2 (130 if the case's 2-second budget ran out), a
    refusal is exactly one line on stderr, and no traceback is ever printed."""
    from multibody_sim.cli import main

    folder = tmp_path_factory.mktemp("fuzz-cli")
    missing = folder / "none.npz"

    def body(tally: Tally, stderr: Callable[[], str]) -> None:
        @fuzz_settings(cases)
        @given(st.sampled_from(NUMERIC_OPTIONS), st.sampled_from(NUMBER_WORDS) | st.floats().map(repr))
        @cli_regressions
        def case(option: tuple[str, str, list[str]], word: str) -> None:
            command, flag, rest = option
            target = [str(missing)] if command == "play" else ["pendulum"]
            argv = [command, *target, flag, word, *(r.replace("{tmp}", str(folder)) for r in rest)]
            out, err = io.StringIO(), io.StringIO()
            stderr()
            try:
                with time_limit(2.0), contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
                    code = main(argv)
            except BaseException as exc:  # main() returns its exit code; anything raised is the finding
                tally.count(type(exc).__name__)
                tally.fail(f"raised {type(exc).__name__}: {exc!s:.300}\n  argv: {argv!r}")
                return
            text = err.getvalue() + stderr()
            tally.count(f"exit {code}")
            if code not in (0, 1, 2, 130):
                tally.fail(f"exit code {code}\n  argv: {argv!r}\n  stderr: {text[-500:]!r}")
            elif "Traceback" in text or "Traceback" in out.getvalue():
                tally.fail(f"a traceback\n  argv: {argv!r}\n  stderr: {text[-1500:]}")
            elif code == 2 and (text.count("\n") != 1 or not text.startswith("multibody-sim: error: ")):
                tally.fail(f"a refusal that is not one line\n  argv: {argv!r}\n  stderr: {text[-800:]!r}")

        case()

    run_fuzzer("command-line-numbers", body, cases=cases)


# ---- atheris (coverage-guided), when it installs -----------------------------------------------------------
@pytest.mark.slow
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
