"""Trajectory files: lossless round trips, plain-array .npz without pickle, atomic writes, refusing bad files."""

from __future__ import annotations

import dataclasses
import io
import json
import os
import pickle
import re
import zipfile
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from conftest import ctrl_c_at, joint, link, urdf

import multibody_sim as ms

ARRAYS = (
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
SENTINEL_ENV = "MULTIBODY_SIM_TEST_PICKLE_SENTINEL"


def exact(message: str) -> str:
    """A regex matching exactly `message` (pytest.raises searches, so anchor both ends)."""
    return f"^{re.escape(message)}$"


@pytest.fixture(scope="module")
def trajectory(tmp_path_factory: pytest.TempPathFactory) -> ms.Trajectory:
    """A run that fills every field: damping (two ledger entries), a controller, limit violations."""
    path = tmp_path_factory.mktemp("robot") / "damped.urdf"
    path.write_text(
        urdf(
            '<link name="base"/>',
            link("upper", com="0 0 -0.5"),
            joint(
                "shoulder", "base", "upper", limits='lower="-0.2" upper="0.2" effort="10" velocity="10"', damping=0.1
            ),
            link("lower", mass=0.5, com="0 0 -0.4"),
            joint("elbow", "upper", "lower", xyz="0 0 -1", damping=0.05),
        )
    )
    robot = ms.load_robot(path)
    traj = ms.simulate(
        robot,
        [0.6, -0.3],
        [0.0, 1.0],
        duration=0.5,
        dt=0.01,
        output_dt=0.02,
        controller=lambda t, q, v: np.array([0.3 * np.sin(3 * t), -0.1]),
    )
    # Make sure the fixture exercises what the round trip must carry.
    assert set(traj.ledger) == {"joint_torques", "joint_damping"}
    assert traj.limit_violations.count > 0
    return traj


def assert_same(loaded: ms.Trajectory, original: ms.Trajectory) -> None:
    """Every field of `loaded` equals the original's, arrays bit for bit."""
    for name in ARRAYS:
        a, b = getattr(loaded, name), getattr(original, name)
        assert a.dtype == b.dtype and a.shape == b.shape, name
        np.testing.assert_array_equal(a, b, err_msg=name)
    assert loaded.ledger.keys() == original.ledger.keys()
    for name, entry in original.ledger.items():
        assert loaded.ledger[name].kind == entry.kind
        np.testing.assert_array_equal(loaded.ledger[name].energy, entry.energy)
    assert loaded.limit_violations == original.limit_violations
    assert loaded.stats == original.stats
    assert loaded.status == original.status
    assert loaded.metadata == original.metadata


def test_save_and_load_round_trip_every_field(trajectory, tmp_path):
    path = tmp_path / "run.npz"
    assert trajectory.save(path) == path
    assert_same(ms.Trajectory.load(path), trajectory)
    assert_same(ms.Trajectory.load(str(path)), trajectory)  # a str path works too


def test_the_file_is_an_npz_of_plain_arrays_with_a_json_header(trajectory, tmp_path):
    path = trajectory.save(tmp_path / "run.npz")
    assert zipfile.is_zipfile(path)
    with np.load(path, allow_pickle=False) as npz:  # raises if anything needs unpickling
        contents = {name: npz[name] for name in npz.files}
    assert all(array.dtype != object for array in contents.values())
    for name in ARRAYS:
        np.testing.assert_array_equal(contents[name], getattr(trajectory, name))
    headers = [array for array in contents.values() if array.dtype.kind == "U" and array.ndim == 0]
    assert len(headers) == 1
    header = json.loads(str(headers[0][()]))
    assert header["metadata"] == json.loads(json.dumps(trajectory.metadata))
    assert header["status"] == "completed"


def test_a_failed_write_leaves_the_previous_file_and_no_temporary_files(trajectory, tmp_path, monkeypatch):
    path = trajectory.save(tmp_path / "run.npz")
    before = path.read_bytes()

    def dies_midway(file: Any, *args: Any, **kwargs: Any) -> None:
        file.write(b"PK\x03\x04 half an archive")  # some bytes reach the disk, then the disk fills up
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(np, "savez", dies_midway)
    with pytest.raises(OSError, match="No space left on device"):
        trajectory.save(path)
    assert path.read_bytes() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["run.npz"]


def test_ctrl_c_during_a_write_leaves_no_temporary_file(trajectory, tmp_path, monkeypatch):
    def interrupted(file: Any, *args: Any, **kwargs: Any) -> None:
        file.write(b"PK\x03\x04")
        raise KeyboardInterrupt

    monkeypatch.setattr(np, "savez", interrupted)
    with pytest.raises(KeyboardInterrupt):
        trajectory.save(tmp_path / "run.npz")
    assert list(tmp_path.iterdir()) == []


def test_save_creates_missing_folders(trajectory, tmp_path):
    path = trajectory.save(tmp_path / "a" / "b" / "run.npz")
    assert_same(ms.Trajectory.load(path), trajectory)


# ---- refusing bad files --------------------------------------------------------------------------------
def test_a_missing_file(tmp_path):
    path = tmp_path / "nothing.npz"
    with pytest.raises(ms.TrajectoryFileError, match=exact(f"{path}: no such trajectory file")):
        ms.Trajectory.load(path)


def test_a_truncated_file(trajectory, tmp_path):
    path = trajectory.save(tmp_path / "run.npz")
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])  # an interrupted copy: the zip directory at the end is gone
    # zipfile's own words for an archive without its central directory.
    with pytest.raises(
        ms.TrajectoryFileError, match=exact(f"{path}: not a readable trajectory file (File is not a zip file)")
    ):
        ms.Trajectory.load(path)


def npy_bytes() -> bytes:
    """A plain .npy file's bytes (what np.load returns an array for, not an archive)."""
    buffer = io.BytesIO()
    np.save(buffer, np.zeros(3))
    return buffer.getvalue()


@pytest.mark.parametrize(
    "content",
    [
        b"",
        np.random.default_rng(7).bytes(4096),
        npy_bytes(),
        b'{"t": [0, 1]}',
        pickle.dumps({"t": [0.0, 1.0]}),
    ],
    ids=["empty", "random-bytes", "plain-npy", "json-text", "pickle"],
)
def test_a_file_that_is_not_an_npz_archive(tmp_path, content):
    path = tmp_path / "impostor.npz"
    path.write_bytes(content)
    # Never numpy's advice to load it with allow_pickle: these files may come from strangers.
    with pytest.raises(ms.TrajectoryFileError, match=exact(f"{path}: not a trajectory file (not an .npz archive)")):
        ms.Trajectory.load(path)


def test_a_pickle_file_is_refused_without_running_it(tmp_path, monkeypatch):
    sentinel = tmp_path / "pickle-ran"
    monkeypatch.setenv(SENTINEL_ENV, str(sentinel))
    path = tmp_path / "booby.npz"
    path.write_bytes(pickle.dumps(_Booby()))
    with pytest.raises(ms.TrajectoryFileError, match=exact(f"{path}: not a trajectory file (not an .npz archive)")):
        ms.Trajectory.load(path)
    assert not sentinel.exists()
    pickle.loads(path.read_bytes())  # the trap is real: unpickling it does run code
    assert sentinel.exists()


def test_a_folder_is_not_a_trajectory_file(tmp_path):
    with pytest.raises(ms.TrajectoryFileError) as info:
        ms.Trajectory.load(tmp_path)
    assert str(info.value).startswith(f"{tmp_path}: ")


def test_an_npz_that_is_not_ours(tmp_path):
    path = tmp_path / "other.npz"
    np.savez(path, t=np.linspace(0, 1, 5), q=np.zeros((5, 2)))
    with pytest.raises(
        ms.TrajectoryFileError, match=exact(f"{path}: not a multibody-sim trajectory (no valid header)")
    ):
        ms.Trajectory.load(path)


def rewrite(source: Path, target: Path, **changes: Any) -> Path:
    """A copy of the trajectory file `source` with some arrays replaced (None removes one)."""
    with np.load(source, allow_pickle=False) as npz:
        contents = {name: npz[name] for name in npz.files}
    for name, value in changes.items():
        if value is None:
            del contents[name]
        else:
            contents[name] = value
    with target.open("wb") as f:
        np.savez(f, **contents)
    return target


def header_of(path: Path) -> dict[str, Any]:
    with np.load(path, allow_pickle=False) as npz:
        return json.loads(str(npz["header"][()]))


@pytest.mark.parametrize(
    ("edit", "reason"),
    [
        (lambda h: h.update(format="someone else's"), "not a multibody-sim trajectory (wrong format tag)"),
        (lambda h: h.update(format_version=99), "trajectory format version 99 is not supported (this version reads 1)"),
        (
            lambda h: h.update(limit_violations={"count": 1, "bogus": 2}),
            "malformed limit_violations in the header (expected only the fields count, samples, worst_joint, "
            "worst_excess, worst_time)",
        ),
        # Fields summary() formats as numbers or prints (a stranger's file must not raise inside it, or print an
        # escape sequence as a status).
        (
            lambda h: h["limit_violations"].update(worst_excess="big"),
            "malformed limit_violations.worst_excess in the header (expected a number)",
        ),
        (
            lambda h: h["limit_violations"].update(count=True),
            "malformed limit_violations.count in the header (expected a whole number)",
        ),
        (lambda h: h["stats"].update(wall_time="slow"), "malformed stats.wall_time in the header (expected a number)"),
        (lambda h: h["stats"].update(steps=1.5), "malformed stats.steps in the header (expected a whole number)"),
        (lambda h: h["stats"].update(wall_time=None), "malformed stats.wall_time in the header (expected a number)"),
        (
            lambda h: h["stats"].update(saturated_dofs={"elbow": "often"}),
            "malformed stats.saturated_dofs in the header (expected an object of whole numbers)",
        ),
        (
            lambda h: h.update(status="\x1b[2Jdone"),
            "malformed status in the header (expected one lowercase word such as completed or interrupted)",
        ),
        (
            lambda h: h.update(status=["completed"]),
            "malformed status in the header (expected one lowercase word such as completed or interrupted)",
        ),
        (lambda h: h.update(constraints="loop"), "malformed constraints in the header (expected a list of names)"),
        (
            lambda h: h["metadata"]["robot"].update(nq="2"),
            "malformed metadata.robot.nq in the header (expected a whole number)",
        ),
        # Array shapes must agree with the robot the metadata describes.
        (
            lambda h: h["metadata"]["robot"].update(nq=3),
            "array 'q' has shape (26, 2), but the metadata's robot has nq = 3",
        ),
        (
            lambda h: h["metadata"]["robot"].update(nv=7),
            "array 'v' has shape (26, 2), but the metadata's robot has nv = 7",
        ),
        # A name from the file is quoted on one line.
        (
            lambda h: h["ledger_kinds"].update({"fric\ntion": "dissipated"}),
            "ledger entry 'fric\\x0ation' is missing or has the wrong shape",
        ),
        (
            lambda h: h["ledger_kinds"].update(friction="dissipated"),
            "ledger entry 'friction' is missing or has the wrong shape",
        ),
    ],
)
def test_a_header_that_does_not_fit(trajectory, tmp_path, edit, reason):
    good = trajectory.save(tmp_path / "good.npz")
    header = header_of(good)
    edit(header)
    path = rewrite(good, tmp_path / "edited.npz", header=np.array(json.dumps(header)))
    with pytest.raises(ms.TrajectoryFileError, match=exact(f"{path}: {reason}")):
        ms.Trajectory.load(path)


def test_a_deeply_nested_header_is_refused_before_it_is_parsed(trajectory, tmp_path, monkeypatch):
    """json.loads recurses once per level (RecursionError near 1000): a nesting bomb is refused by counting."""
    good = trajectory.save(tmp_path / "good.npz")
    header = header_of(good)
    text = json.dumps(header)[:-1] + ', "deep": ' + "[" * 100_000 + "]" * 100_000 + "}"
    path = rewrite(good, tmp_path / "deep.npz", header=np.array(text))
    parsed = []
    monkeypatch.setattr(json, "loads", lambda *a, **k: parsed.append(1))
    message = f"{path}: refused: its header nests 100001 levels deep, more than the 64 a trajectory header may"
    for mmap in (False, True):
        with pytest.raises(ms.TrajectoryFileError, match=exact(message)):
            ms.Trajectory.load(path, mmap=mmap)
    assert not parsed
    monkeypatch.undo()
    # 64 levels is the documented limit (ours nest 5): a header that deep still loads.
    header["metadata"]["deep"] = json.loads("[" * 60 + "]" * 60)
    path = rewrite(good, tmp_path / "deep-enough.npz", header=np.array(json.dumps(header)))
    assert ms.Trajectory.load(path).metadata["deep"] == json.loads("[" * 60 + "]" * 60)


@pytest.mark.parametrize(
    "text",
    ['{"a": "[[[[{{{{", "b": [1, [2, [3]]]}', '["\\"]]]", [[{}]]]', "[]", '"[[["', "{}", '{"x": {"y": {"z": []}}}'],
)
def test_the_nesting_count_agrees_with_the_parsed_document(text):
    """safety.json_depth counts brackets outside strings; the oracle walks what json.loads built."""
    from multibody_sim.safety import json_depth

    def depth(value: Any) -> int:
        children = value.values() if isinstance(value, dict) else value if isinstance(value, list) else None
        return 0 if children is None else 1 + max((depth(c) for c in children), default=0)

    assert json_depth(text) == depth(json.loads(text))


@pytest.mark.parametrize(
    "text",
    [
        'a = "[[[[{{{{"\nb = [1, [2, [3]]]',
        "a = '[[[' # [[[[[\nb = [[{}]]",
        'a = """\n[[[\n""" # ]\nb = [{c = [1]}]',
        "a = '''[[\n[{'''\nb = 1",
        'a = ["""x"""", [[1]]]',  # a multi-line string ending in a quote of its own, then nesting
        "a = ['''y''''', [[[2]]], \"z]\"]",
        'a = "\\\\" # [[\nb = [[], [[]]]',
        "a = [\n  [1, 2], # ]]]\n  [3],\n]",
    ],
)
def test_the_toml_nesting_count_agrees_with_the_parsed_document(text):
    """safety.toml_depth counts arrays and inline tables outside strings and comments; the oracle walks what tomllib
    built (documents of `key = value` lines: table headers would count while open)."""
    from multibody_sim.safety import toml_depth

    try:
        import tomllib
    except ModuleNotFoundError:  # Python < 3.11
        import tomli as tomllib  # type: ignore[no-redef]

    def depth(value: Any) -> int:
        children = value.values() if isinstance(value, dict) else value if isinstance(value, list) else None
        return 0 if children is None else 1 + max((depth(c) for c in children), default=0)

    assert toml_depth(text) == depth(tomllib.loads(text)) - 1  # the document's own table is no bracket


def test_a_header_that_is_not_json(trajectory, tmp_path):
    good = trajectory.save(tmp_path / "good.npz")
    path = rewrite(good, tmp_path / "edited.npz", header=np.array("{not json"))
    with pytest.raises(
        ms.TrajectoryFileError, match=exact(f"{path}: not a multibody-sim trajectory (no valid header)")
    ):
        ms.Trajectory.load(path)


def test_missing_and_inconsistent_arrays(trajectory, tmp_path):
    good = trajectory.save(tmp_path / "good.npz")
    path = rewrite(good, tmp_path / "missing.npz", v=None, work=None)
    with pytest.raises(ms.TrajectoryFileError, match=exact(f"{path}: trajectory file lacks arrays: v, work")):
        ms.Trajectory.load(path)
    n = len(trajectory)
    path = rewrite(good, tmp_path / "short.npz", q=trajectory.q[:-1])
    with pytest.raises(
        ms.TrajectoryFileError,
        match=exact(f"{path}: array 'q' has shape {(n - 1, 2)} and dtype float64, inconsistent with {n} samples"),
    ):
        ms.Trajectory.load(path)


class _Booby:
    """Unpickling this runs code (it creates the file named in the environment): loading must never do it."""

    def __reduce__(self) -> tuple[Any, ...]:
        return (Path.touch, (Path(os.environ[SENTINEL_ENV]),))


def test_an_npz_holding_a_pickled_object_array_is_refused_without_running_it(trajectory, tmp_path, monkeypatch):
    sentinel = tmp_path / "pickle-ran"
    monkeypatch.setenv(SENTINEL_ENV, str(sentinel))
    good = trajectory.save(tmp_path / "good.npz")
    booby = np.empty(1, dtype=object)
    booby[0] = _Booby()
    for name in ("header", "q"):
        path = rewrite(good, tmp_path / f"pickled-{name}.npz", **{name: booby})
        with pytest.raises(
            ms.TrajectoryFileError,
            match=exact(
                f"{path}: not a readable trajectory file (Object arrays cannot be loaded when allow_pickle=False)"
            ),
        ):
            ms.Trajectory.load(path)
    assert not sentinel.exists()
    # The booby trap is real: unpickling does run it.
    with np.load(path, allow_pickle=True) as npz:
        npz["q"]
    assert sentinel.exists()


# ---- early stops ---------------------------------------------------------------------------------------
@pytest.mark.filterwarnings("ignore:overflow encountered:RuntimeWarning")
def test_a_partial_trajectory_from_a_failed_run_saves_and_loads(robot, tmp_path):
    dp = robot("double_pendulum", damping=False)
    with pytest.raises(ms.SimulationError) as info:
        ms.simulate(dp, [1.0, 0.3], [10.0, -10.0], duration=50.0, dt=0.2, integrator="euler")
    partial = info.value.trajectory
    assert partial.status == "diverged" and partial.t[-1] < 50.0
    loaded = ms.Trajectory.load(partial.save(tmp_path / "partial.npz"))
    assert_same(loaded, partial)
    assert loaded.status == "diverged"


def test_an_interrupted_trajectory_saves_and_loads(robot, tmp_path):
    pendulum = robot("pendulum")
    with pytest.raises(ms.SimulationInterrupted) as info:
        ms.simulate(pendulum, [0.3], [0.0], duration=1.0, dt=0.01, controller=ctrl_c_at(0.095, 1))
    partial = info.value.trajectory
    loaded = ms.Trajectory.load(partial.save(tmp_path / "partial.npz"))
    assert_same(loaded, partial)
    assert loaded.status == "interrupted"


def test_limit_violations_survive_as_a_dataclass(trajectory, tmp_path):
    loaded = ms.Trajectory.load(trajectory.save(tmp_path / "run.npz"))
    assert isinstance(loaded.limit_violations, ms.LimitViolations)
    assert dataclasses.asdict(loaded.limit_violations) == dataclasses.asdict(trajectory.limit_violations)
    assert loaded.limit_violations.worst_joint == "shoulder"
