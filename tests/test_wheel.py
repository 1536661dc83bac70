"""The built wheel ships models/ as package data and the compiled extension: every catalog entry loads from an
installed wheel. Nothing here compiles C++: the wheel is built around the extension this suite runs on (see
`wheel`), and the no-compiler fallback fails at CMake's compiler check."""

from __future__ import annotations

import ast
import importlib
import importlib.metadata
import importlib.util
import json
import os
import re
import shutil
import subprocess
import sys
import textwrap
import zipfile
from pathlib import Path

import pytest

import multibody_sim as ms

REPO = Path(__file__).resolve().parents[1]
# What a wheel is built from: the project's metadata, its code and the models it ships (never build/ or caches).
SOURCES = ("pyproject.toml", "CMakeLists.txt", "README.md", "CHANGELOG.md", "LICENSE", "src", "models")
IGNORED = shutil.ignore_patterns("__pycache__", "*.egg-info", "*.pyc")


def shipped_model_files() -> list[str]:
    """Every file under the repository's models/ (the data package), relative to it."""
    return sorted(
        p.relative_to(REPO / "models").as_posix()
        for p in (REPO / "models").rglob("*")
        if p.is_file() and "__pycache__" not in p.parts
    )


def copy_sources(dest: Path) -> Path:
    """A copy of what a wheel is built from (building in place would race other test runs)."""
    dest.mkdir(parents=True, exist_ok=True)
    for name in SOURCES:
        if (REPO / name).is_dir():
            shutil.copytree(REPO / name, dest / name, ignore=IGNORED)
        elif (REPO / name).is_file():
            shutil.copy2(REPO / name, dest / name)
    return dest


def build_wheel(
    source: Path,
    out: Path,
    *,
    isolated: bool = True,
    env: dict[str, str] | None = None,
    settings: dict[str, str] | None = None,
) -> subprocess.CompletedProcess[str]:
    """Build a wheel of source into out, as pip would (isolated: build requirements fetched into a fresh
    environment) or with this environment's build requirements (scripts/test.sh installs them); settings are
    scikit-build-core's config settings (`-C key=value`)."""
    config = [f"--config-setting={key}={value}" for key, value in (settings or {}).items()]
    if importlib.util.find_spec("build") is not None:  # the [test] extra brings it
        command = [sys.executable, "-m", "build", "--wheel", *config, "--outdir", str(out), str(source)]
        if not isolated:
            command.insert(4, "--no-isolation")
    else:
        config = [c.replace("--config-setting=", "--config-settings=") for c in config]
        command = [sys.executable, "-m", "pip", "wheel", "--no-deps", *config, "--wheel-dir", str(out), str(source)]
        if not isolated:
            command.insert(4, "--no-build-isolation")
    return subprocess.run(command, capture_output=True, text=True, timeout=600, env=env)


def installed_extension() -> Path | None:
    """The compiled extension this suite runs on (the editable install's file), or None where none is built."""
    spec = importlib.util.find_spec("multibody_sim._native")
    return Path(spec.origin) if spec is not None and spec.origin is not None else None


def build_record(text: str) -> dict[str, object]:
    """The constants of a _native_build.py (the build record CMakeLists.txt writes), read without running it."""
    return {
        node.targets[0].id: ast.literal_eval(node.value)
        for node in ast.parse(text).body
        if isinstance(node, ast.Assign) and isinstance(node.targets[0], ast.Name)
    }


@pytest.fixture(scope="module")
def wheel(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The wheel pip builds from a copy of the checkout (isolated), around the extension this suite runs on.

    The extension is not compiled a second time: CMakeLists.txt installs the given file (MULTIBODY_SIM_REUSE) when
    its build record says it was built from these sources with these settings, and MULTIBODY_SIM_REUSE_ONLY makes
    anything else an error instead of a compile. What an isolated build proves besides compiling (its build
    requirements install, CMake finds Pinocchio and nanobind in them, the install layout) it still proves; the
    compile itself is scripts/test.sh's editable build, with the same requirements and CMakeLists.txt. Where no
    extension is built, the wheel is the pure-Python one (`wheel.cmake=false`).
    """
    source = copy_sources(tmp_path_factory.mktemp("source"))
    out = tmp_path_factory.mktemp("dist")
    extension = installed_extension()
    if extension is None:
        settings = {"wheel.cmake": "false"}
    else:
        settings = {
            "cmake.define.MULTIBODY_SIM_REUSE": str(extension),
            "cmake.define.MULTIBODY_SIM_REUSE_ONLY": "ON",
        }
    result = build_wheel(source, out, settings=settings)
    assert result.returncode == 0, f"building the wheel failed:\n{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    if extension is not None:
        assert f"multibody-sim: reusing {extension}" in result.stdout, result.stdout[-3000:]
    wheels = list(out.glob("multibody_sim-*.whl"))
    assert len(wheels) == 1, wheels
    return wheels[0]


def test_the_wheel_holds_every_model_file_as_package_data(wheel):
    names = set(zipfile.ZipFile(wheel).namelist())
    models = shipped_model_files()
    assert {"pendulum/pendulum.urdf", "free_body/free_body.urdf", "__init__.py"} <= set(models)
    missing = [f for f in models if f"multibody_sim/models/{f}" not in names]
    assert not missing, f"models/ files left out of the wheel (package-data patterns?): {missing}"
    with zipfile.ZipFile(wheel) as archive:
        for f in models:
            assert archive.read(f"multibody_sim/models/{f}") == (REPO / "models" / f).read_bytes(), f
    assert "multibody_sim/py.typed" in names
    # The data package lives inside multibody_sim: no top-level `models` package to collide with others.
    assert not any(name.startswith("models/") for name in names)


def extension_in(wheel: Path) -> list[str]:
    """The compiled extension's files in the wheel (empty for a pure-Python wheel)."""
    return [n for n in zipfile.ZipFile(wheel).namelist() if re.fullmatch(r"multibody_sim/_native\.[^/]*\.so", n)]


def test_the_wheel_holds_the_compiled_extension_and_its_build_record(wheel):
    """The wheel ships the very extension this suite ran on, byte for byte (nothing was compiled for it), with the
    build record native.py checks it by before loading it."""
    extension = installed_extension()
    if extension is None and os.environ.get("CI") != "true":  # CI builds the extension: its absence fails there
        pytest.skip("no C++ extension is built here: the wheel is pure Python (the fallback)")
    assert extension is not None
    (name,) = extension_in(wheel)
    archive = zipfile.ZipFile(wheel)
    assert name == f"multibody_sim/{extension.name}"
    assert archive.read(name) == extension.read_bytes()
    record = build_record(archive.read("multibody_sim/_native_build.py").decode())
    built = importlib.import_module("multibody_sim._native_build")
    assert record["BUILD_SHA256"] == built.BUILD_SHA256 and record["SOURCES_SHA256"] == built.SOURCES_SHA256
    assert record["EXTENSION_SIZE"] == extension.stat().st_size
    assert not wheel.name.endswith("-py3-none-any.whl"), wheel.name  # tagged for this interpreter and platform


def test_every_catalog_entry_loads_from_the_installed_wheel(wheel, tmp_path):
    site = tmp_path / "site"
    install = subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "--no-deps",
            "--no-index",
            "--no-compile",
            "--disable-pip-version-check",
            "--target",
            str(site),
            str(wheel),
        ],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert install.returncode == 0, install.stderr[-3000:]
    elsewhere = tmp_path / "elsewhere"  # neither the checkout nor its src/ on the path by accident
    elsewhere.mkdir()
    probe = textwrap.dedent("""
        import json
        import sys
        # An editable install of the checkout (scripts/test.sh's) hooks imports ahead of the path: drop its hook so
        # the wheel's copy, first on the path, is what loads.
        sys.meta_path[:] = [f for f in sys.meta_path if type(f).__name__ != "ScikitBuildRedirectingFinder"]
        import multibody_sim as ms
        from multibody_sim import native
        from multibody_sim.catalog import CATALOG, load_robot, shipped_models_dir
        sizes = {}
        for name in CATALOG:
            robot = load_robot(name)
            sizes[name] = [robot.nq, robot.nv, robot.floating_base, robot.source["urdf_path"]]
        extension = native.module.__file__ if native.module is not None else None
        report = {"file": ms.__file__, "models": str(shipped_models_dir()), "sizes": sizes}
        print(json.dumps({**report, "kernel": native.kernel(), "extension": extension}))
    """)
    # The installed copy comes first on the path; dependencies (pin, ...) come from this environment.
    result = subprocess.run(
        [sys.executable, "-c", probe],
        cwd=elsewhere,
        capture_output=True,
        text=True,
        timeout=120,
        env={**_clean_env(), "PYTHONPATH": str(site)},
    )
    assert result.returncode == 0, result.stderr[-3000:]
    report = json.loads(result.stdout.strip().splitlines()[-1])
    assert Path(report["file"]).resolve().is_relative_to(site.resolve()), report["file"]
    assert Path(report["models"]).resolve() == (site / "multibody_sim" / "models").resolve()
    assert set(report["sizes"]) == set(ms.CATALOG)
    if extension_in(wheel):  # the wheel's own extension runs, against this environment's Pinocchio
        assert report["kernel"] == f"native (C++, Pinocchio {importlib.metadata.version('pin')})", report["kernel"]
        assert Path(report["extension"]).resolve().is_relative_to(site.resolve()), report["extension"]
    for name, (nq, nv, floating, urdf_path) in report["sizes"].items():
        here = ms.load_robot(name)
        assert (nq, nv, floating) == (here.nq, here.nv, here.floating_base), name
        if ms.CATALOG[name].provider == "multibody-sim":  # shipped models come from the wheel, not the checkout
            assert Path(urdf_path).resolve().is_relative_to(site.resolve()), urdf_path


def _clean_env() -> dict[str, str]:
    """This process's environment without anything that would put the checkout on the path."""
    return {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP")}


def build_requirements_here() -> bool:
    """Whether this environment has pyproject's build requirements (scripts/test.sh installs them)."""
    try:
        return all(importlib.metadata.version(name) for name in ("scikit-build-core", "nanobind", "libpinocchio"))
    except importlib.metadata.PackageNotFoundError:
        return False


@pytest.mark.parametrize("ci", ["", "true"])
def test_without_a_compiler_the_install_falls_back_to_python_except_under_ci(ci, tmp_path):
    source = copy_sources(tmp_path / "source")
    out = tmp_path / "dist"
    env = {**_clean_env(), "CXX": "/bin/false", "CI": ci}  # a "compiler" that fails CMake's check
    result = build_wheel(source, out, isolated=not build_requirements_here(), env=env)
    if ci == "true":  # under CI a failed native build fails the install
        assert result.returncode != 0 and not list(out.glob("*.whl"))
        assert "/bin/false" in result.stdout + result.stderr  # CMake says which compiler failed
        return
    assert result.returncode == 0, f"{result.stdout[-3000:]}\n{result.stderr[-3000:]}"
    (wheel,) = out.glob("multibody_sim-*.whl")
    assert wheel.name.endswith("-py3-none-any.whl") and not extension_in(wheel), wheel.name
    assert "multibody_sim/_native_build.py" not in zipfile.ZipFile(wheel).namelist()
    site = tmp_path / "site"
    with zipfile.ZipFile(wheel) as archive:  # a pure-Python wheel installs by unpacking
        archive.extractall(site)
    probe = (
        "import sys\n"
        "sys.meta_path[:] = [f for f in sys.meta_path if type(f).__name__ != 'ScikitBuildRedirectingFinder']\n"
        "sys.argv = ['multibody-sim', '--version']\n"
        "from multibody_sim import cli, native\n"
        "assert native.__file__.startswith(r'SITE'), native.__file__\n"
        "sys.exit(cli.main())\n"
    ).replace("SITE", str(site))
    run = subprocess.run(
        [sys.executable, "-c", probe],
        capture_output=True,
        text=True,
        timeout=120,
        cwd=tmp_path,
        env={**_clean_env(), "PYTHONPATH": str(site)},
    )
    assert run.returncode == 0, run.stderr[-3000:]
    assert run.stdout.splitlines()[1] == (
        "kernel: python (the C++ extension is not built (no C++ compiler at install time, or its build failed: "
        "`pip install -v .` shows why))"
    )
