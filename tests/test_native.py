"""The compiled extension: the model hand-over, the RK4 floor against Pinocchio's own Python calls, the kernel
choice (MULTIBODY_SIM_NATIVE, --version) and the version pin."""

from __future__ import annotations

import hashlib
import importlib
import importlib.metadata
import importlib.util
import os
import re
import subprocess
import sys
import types
from pathlib import Path

import numpy as np
import pinocchio as pin
import pytest
from conftest import needs_native

from multibody_sim import native

REPO = Path(__file__).resolve().parents[1]
ROBOTS = ["double_pendulum", "ur5", "panda", "solo12", "talos"]
BUILT = importlib.util.find_spec("multibody_sim._native") is not None


def state(robot, seed: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A seeded random (q, v, tau) near the robot's default pose (q moved on its configuration manifold)."""
    rng = np.random.default_rng(seed)
    q = pin.integrate(robot.model, robot.default_pose(), 0.3 * rng.normal(size=robot.nv))
    return q, 0.5 * rng.normal(size=robot.nv), rng.normal(size=robot.nv)


def python_rk4(model: pin.Model, q, v, tau, dt: float, n: int) -> tuple[np.ndarray, np.ndarray]:
    """The RK4 loop of _native.Model.rk4_floor written with Pinocchio's Python calls (the oracle)."""
    data = model.createData()
    h, w = 0.5 * dt, dt / 6.0

    def aba(qs, vs):
        return pin.aba(model, data, qs, vs, tau, pin.Convention.WORLD).copy()

    for _ in range(n):
        a1 = aba(q, v)
        v2 = v + h * a1
        a2 = aba(pin.integrate(model, q, h * v), v2)
        v3 = v + h * a2
        a3 = aba(pin.integrate(model, q, h * v2), v3)
        v4 = v + dt * a3
        a4 = aba(pin.integrate(model, q, dt * v3), v4)
        q = pin.integrate(model, q, w * (v + 2.0 * v2 + 2.0 * v3 + v4))
        v = v + w * (a1 + 2.0 * a2 + 2.0 * a3 + a4)
    return q, v


@needs_native
@pytest.mark.parametrize("name", ROBOTS)
def test_the_model_crosses_to_cpp_whole(robot, name):
    r = robot(name)
    cpp = native.load_model(r.model)
    assert (cpp.nq, cpp.nv, cpp.njoints, cpp.name) == (r.model.nq, r.model.nv, r.model.njoints, r.model.name)
    for seed in range(3):
        q, v, tau = state(r, seed)
        expected = pin.aba(r.model, r.model.createData(), q, v, tau, pin.Convention.WORLD)
        assert np.array_equal(cpp.aba(q, v, tau), expected), name


@needs_native
@pytest.mark.parametrize("name", ["ur5", "solo12"])
def test_the_cpp_rk4_loop_equals_pinocchios_python_calls_bit_for_bit(robot, name):
    r = robot(name)
    q, v, tau = state(r, 7)
    cpp_q, cpp_v = native.load_model(r.model).rk4_floor(q, v, tau, 1e-3, 200)
    py_q, py_v = python_rk4(r.model, q, v, tau, 1e-3, 200)
    assert np.abs(cpp_v - v).max() > 1e-3  # it moved
    assert np.array_equal(cpp_q, py_q) and np.array_equal(cpp_v, py_v), (
        np.abs(cpp_q - py_q).max(),
        np.abs(cpp_v - py_v).max(),
    )


@needs_native
def test_a_model_is_rebuilt_in_cpp_only_when_it_changed(monkeypatch):
    import multibody_sim as ms

    r = ms.load_robot("ur5", damping=False)  # its own model: this test edits it
    q, v, tau = state(r, 3)
    first = native.load_model(r.model)
    assert native.load_model(r.model) is first  # unchanged: the same hand-over serves again
    r.model.inertias[3].mass *= 2.0  # edited in Python, as a scene does when it builds its model
    r.model.gravity.linear = np.array([0.0, 0.0, -1.62])
    edited = native.load_model(r.model)
    assert edited is not first
    expected = pin.aba(r.model, r.model.createData(), q, v, tau, pin.Convention.WORLD)
    assert np.array_equal(edited.aba(q, v, tau), expected)
    assert not np.array_equal(first.aba(q, v, tau), expected)  # the edit matters
    copy = r.model.copy()  # another pin.Model of equal content: its own hand-over, equal dynamics
    assert np.array_equal(native.load_model(copy).aba(q, v, tau), expected)
    # A run on the edited model steps with it: its native trajectory is the Python kernel's to round-off.
    traj = ms.simulate(r, q, v, duration=0.05, dt=1e-3)
    monkeypatch.setenv(native.ENV, "0")
    reference = ms.simulate(r, q, v, duration=0.05, dt=1e-3)
    assert traj.metadata["kernel"] == "native" and reference.metadata["kernel"] != "native"
    np.testing.assert_allclose(traj.v, reference.v, rtol=1e-12, atol=1e-12)


@needs_native
def test_bad_bytes_and_bad_sizes_are_one_clear_error(robot):
    with pytest.raises(ValueError, match="not a Pinocchio binary archive of a Model"):
        native.module.Model(b"not an archive")
    cpp = native.load_model(robot("ur5").model)
    with pytest.raises(ValueError, match="q0 must have 6 entries, got 7"):
        cpp.rk4_floor(np.zeros(7), np.zeros(6), np.zeros(6), 1e-3, 1)


def version_lines(**env: str) -> list[str]:
    """`multibody-sim --version`'s lines, run in a fresh process with env added."""
    result = subprocess.run(
        [sys.executable, "-m", "multibody_sim", "--version"],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, **env},
    )
    assert result.returncode == 0, result.stderr
    return result.stdout.splitlines()


def test_version_names_the_kernel_and_the_environment_variable_turns_native_off():
    runtime = importlib.metadata.version("pin")
    default = version_lines(MULTIBODY_SIM_NATIVE="")[1]
    if BUILT:
        assert default == f"kernel: native (C++, Pinocchio {runtime})"
    else:
        assert default.startswith("kernel: python (the C++ extension is not built"), default
    assert version_lines(MULTIBODY_SIM_NATIVE="0")[1] == "kernel: python (MULTIBODY_SIM_NATIVE=0)"
    bad = version_lines(MULTIBODY_SIM_NATIVE="yes")[1]
    assert bad == "kernel: python (MULTIBODY_SIM_NATIVE='yes' is not 0 (Python kernel) or 1 (native kernel when built))"


@pytest.mark.skipif(not BUILT, reason="the C++ extension is not built here")
def test_an_extension_built_against_another_pinocchio_is_refused_with_one_line(monkeypatch):
    monkeypatch.setattr(pin, "__version__", "4.0.9")
    module, why = native._load()
    assert module is None
    built = re.findall(r'"libpinocchio\[build\]==([0-9.]+)"', (REPO / "pyproject.toml").read_text())[0]
    assert why == (
        f"the C++ extension was built against Pinocchio {built} but Pinocchio 4.0.9 is "
        "installed (no ABI promise across versions): reinstall multibody-sim"
    )


@pytest.mark.skipif(not BUILT, reason="the C++ extension is not built here")
def test_an_extension_built_without_the_kernel_is_refused_with_one_line(monkeypatch):
    """A stale build (an editable install whose sources gained the kernel since) runs the Python kernel and
    says why, instead of failing inside the first run."""
    real = importlib.import_module

    def without_kernel(name: str, *args: object) -> object:
        module = real(name, *args)
        if name.endswith("._native"):
            return types.SimpleNamespace(**{k: v for k, v in vars(module).items() if k != "Kernel"})
        return module

    monkeypatch.setattr(importlib, "import_module", without_kernel)
    assert native._load() == (
        None,
        "the C++ extension was built without the stepping kernel: reinstall multibody-sim",
    )


@needs_native
def test_cmake_and_python_digest_the_sources_alike_and_an_edit_makes_the_build_stale(tmp_path):
    """The digest CMake wrote at the build (this checkout's editable install) equals the one Python computes
    from the same files; one byte changed in a copy of the sources makes that copy stale, and _load refuses an
    extension whose sources moved on (it would otherwise run against a Python side it does not match)."""
    build = importlib.import_module("multibody_sim._native_build")
    if native.SOURCES.is_dir():  # a checkout (the editable install the suite runs on): its sources were built
        assert native.sources_digest(native.SOURCES) == build.SOURCES_SHA256
    copy = tmp_path / "native"
    copy.mkdir()
    for path in sorted((REPO / "src" / "native").iterdir()):
        (copy / path.name).write_bytes(path.read_bytes())
    assert native._stale_sources(build.SOURCES_SHA256, copy) is None
    kernel = copy / "engine.cpp"
    kernel.write_bytes(kernel.read_bytes() + b"\n")
    assert native._stale_sources(build.SOURCES_SHA256, copy) == copy
    (copy / "new.hpp").write_text("")  # a new file counts too
    kernel.write_bytes((REPO / "src" / "native" / "engine.cpp").read_bytes())
    assert native._stale_sources(build.SOURCES_SHA256, copy) == copy
    assert native._stale_sources(build.SOURCES_SHA256, tmp_path) is None  # no sources there: nothing to check


@needs_native
def test_the_build_records_the_installed_extensions_size_and_digest_and_load_checks_them(tmp_path):
    """CMake's record of the extension as installed (after RPATH editing and stripping) is the file Python finds;
    a copy of it cut short or with one byte changed is refused before loading (tests/bad_inputs.py runs both in a
    fresh process), and so is a record that gives nothing to check by."""
    build = importlib.import_module("multibody_sim._native_build")
    path = Path(native.module.__file__)
    assert (path.name, path.stat().st_size) == (build.EXTENSION, build.EXTENSION_SIZE)
    assert hashlib.sha256(path.read_bytes()).hexdigest() == build.EXTENSION_SHA256
    assert native._damaged(build, path) is None
    copy = tmp_path / path.name
    copy.write_bytes(path.read_bytes()[:-1] + bytes([path.read_bytes()[-1] ^ 1]))
    assert native._damaged(build, copy) == (
        f"the C++ extension {copy} is damaged: its SHA-256 is not the one its build recorded: reinstall multibody-sim"
    )
    copy.write_bytes(path.read_bytes()[:4096])
    assert native._damaged(build, copy) == (
        f"the C++ extension {copy} is damaged: 4096 bytes where its build wrote {build.EXTENSION_SIZE} (an "
        "interrupted copy or install?): reinstall multibody-sim"
    )
    assert native._damaged(types.SimpleNamespace(PINOCCHIO_VERSION=build.PINOCCHIO_VERSION), path) == (
        "the C++ extension's build record gives no size and SHA-256 to check it by: reinstall multibody-sim"
    )


@pytest.mark.skipif(not BUILT, reason="the C++ extension is not built here")
def test_the_extension_itself_refuses_another_pinocchio_at_import():
    probe = (
        "import pinocchio; pinocchio.__version__ = '4.0.9'\n"
        "from multibody_sim import native; print(native.kernel())\n"
        "import multibody_sim._native\n"
    )
    result = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120)
    assert result.returncode != 0 and result.stdout.startswith("python (the C++ extension was built against")
    built = re.findall(r'"libpinocchio\[build\]==([0-9.]+)"', (REPO / "pyproject.toml").read_text())[0]
    assert result.stderr.strip().splitlines()[-1] == (
        f"ImportError: multibody_sim._native was built against Pinocchio {built} but Pinocchio 4.0.9 is installed "
        "(no ABI promise across versions): reinstall multibody-sim"
    )


def test_runtime_and_build_pinocchio_are_pinned_to_the_same_exact_version():
    text = (REPO / "pyproject.toml").read_text()
    runtime = re.findall(r'"pin==([0-9.]+)"', text)
    build = re.findall(r'"libpinocchio\[build\]==([0-9.]+)"', text)
    assert len(runtime) == 1 and runtime == build, (runtime, build)
    assert importlib.metadata.version("pin") == runtime[0]
