"""The compiled extension (multibody_sim._native): whether it runs here, why not, and the model hand-over.

`available` is True when the extension was built (`pip install .` with a C++ compiler) from the sources beside
it (in a checkout), against the Pinocchio installed now, is the file its build wrote (size and SHA-256, checked
before loading it), loads, and `MULTIBODY_SIM_NATIVE=0` is not set; otherwise `why_unavailable` says why in one
line and runs take the Python kernel. `kernel()` is the one phrase the CLI and run headers print.
"""

from __future__ import annotations

import hashlib
import importlib
import importlib.util
import os
from pathlib import Path
from types import ModuleType
from typing import Any

import pinocchio as pin

from .exceptions import MissingDependencyError

#: Set to 0 to run the Python kernel even where the extension is built (1 or unset: native when available).
ENV = "MULTIBODY_SIM_NATIVE"


def _load() -> tuple[ModuleType | None, str | None]:
    """The extension module, or None and why it cannot run here."""
    setting = os.environ.get(ENV, "").strip()
    if setting == "0":
        return None, f"{ENV}=0"
    if setting not in ("", "1"):
        return None, f"{ENV}={setting!r} is not 0 (Python kernel) or 1 (native kernel when built)"
    try:
        build = importlib.import_module(f"{__package__}._native_build")  # written by the C++ build
    except ImportError:
        return None, (
            "the C++ extension is not built (no C++ compiler at install time, or its build failed: "
            "`pip install -v .` shows why)"
        )
    stale = _stale_sources(getattr(build, "SOURCES_SHA256", None))
    if stale is not None:
        return None, (
            f"the C++ extension is older than its sources in {stale} (edited or pulled, not rebuilt): rebuild it "
            "(`bash scripts/test.sh --co -q` or `pip install -e .`)"
        )
    built, running = build.PINOCCHIO_VERSION, pin.__version__
    if built != running:
        return None, (
            f"the C++ extension was built against Pinocchio {built} but Pinocchio {running} is installed "
            "(no ABI promise across versions): reinstall multibody-sim"
        )
    spec = importlib.util.find_spec(f"{__package__}._native")  # where it is, without loading it
    damaged = _damaged(build, Path(spec.origin)) if spec is not None and spec.origin is not None else None
    if damaged is not None:
        return None, damaged
    try:
        extension = importlib.import_module(f"{__package__}._native")
    except ImportError as exc:
        return None, f"the C++ extension does not load: {exc}"
    if not hasattr(extension, "Kernel"):  # an older build of the sources (e.g. an editable install not rebuilt)
        return None, "the C++ extension was built without the stepping kernel: reinstall multibody-sim"
    if not hasattr(extension, "SceneForces"):  # ... built before the scenes' elements joined it (scene.cpp)
        return None, "the C++ extension was built without the scenes' elements: reinstall multibody-sim"
    return extension, None


def sources_digest(folder: Path) -> str:
    """CMakeLists.txt's digest of the C++ sources: SHA-256 of the lines "<file name> <its SHA-256>" of the
    folder's *.cpp and *.hpp files, sorted by name."""
    lines = "".join(
        f"{path.name} {hashlib.sha256(path.read_bytes()).hexdigest()}\n"
        for path in sorted(folder.iterdir(), key=lambda p: p.name)
        if path.suffix in (".cpp", ".hpp")
    )
    return hashlib.sha256(lines.encode()).hexdigest()


def file_digest(path: Path) -> str:
    """The file's SHA-256 in hex, as CMake's file(SHA256) writes it."""
    digest = hashlib.sha256()
    with open(path, "rb") as file:
        while chunk := file.read(1 << 20):
            digest.update(chunk)
    return digest.hexdigest()


def _damaged(build: Any, path: Path) -> str | None:
    """Why the extension file at path is not the one its build wrote (truncated by an interrupted copy or install,
    or altered since), or None. Checked before loading it: the dynamic loader dies of SIGBUS on a truncated file.

    Args:
        build: the build record (the module _native_build, or anything with its attributes).
        path: the extension file.
    """
    size, digest = getattr(build, "EXTENSION_SIZE", None), getattr(build, "EXTENSION_SHA256", None)
    if size is None or digest is None:
        return "the C++ extension's build record gives no size and SHA-256 to check it by: reinstall multibody-sim"
    try:
        actual = path.stat().st_size
        if actual != size:
            return (
                f"the C++ extension {path} is damaged: {actual} bytes where its build wrote {size} (an interrupted "
                "copy or install?): reinstall multibody-sim"
            )
        if file_digest(path) != digest:
            return (
                f"the C++ extension {path} is damaged: its SHA-256 is not the one its build recorded: reinstall "
                "multibody-sim"
            )
    except OSError as exc:
        return f"the C++ extension {path} cannot be read ({exc.strerror}): reinstall multibody-sim"
    return None


#: Where the C++ sources sit in a checkout (src/native beside src/multibody_sim); a wheel ships none.
SOURCES = Path(__file__).resolve().parent.parent / "native"


def _stale_sources(built: str | None, folder: Path = SOURCES) -> Path | None:
    """The source folder when the extension was built from other sources than those in it (an editable install
    whose C++ changed since its build), else None (a wheel ships no sources: nothing to check)."""
    if not (folder / "module.cpp").is_file():
        return None
    try:
        current = sources_digest(folder)
    except OSError:
        return None
    return None if current == built else folder


module, why_unavailable = _load()
#: Whether runs can use the compiled kernel here (see why_unavailable when not).
available: bool = module is not None
#: The Pinocchio version the extension was built against (None when it is not available).
pinocchio_version: str | None = module.PINOCCHIO_VERSION if module is not None else None


def kernel() -> str:
    """Which kernel runs, in one phrase: 'native (C++, Pinocchio 4.1.0)' or 'python (<why>)'."""
    return f"native (C++, Pinocchio {pinocchio_version})" if available else f"python ({why_unavailable})"


def function(name: str) -> Any:
    """The extension's function (or class) `name`, or None where the extension is not available (or was built
    without it)."""
    return getattr(module, name, None) if available else None


def model_bytes(model: pin.Model) -> bytes:
    """The model as Pinocchio's binary archive (what `_native.Model(bytes)` rebuilds in C++)."""
    buffer = pin.serialization.StreamBuffer()
    model.saveToBinary(buffer)
    return buffer.tobytes()


# The latest models handed over: id(pin.Model) -> (its archive, its _native.Model), oldest first.
_HANDED: dict[int, tuple[bytes, Any]] = {}
_HANDED_SIZE = 16


def load_model(model: pin.Model) -> Any:
    """The model handed over to C++: a `_native.Model` (pinocchio::Model + Data) built from model_bytes(model).

    The model is serialized at every call, but rebuilt in C++ only when its archive differs from the one this very
    pin.Model had at its latest hand-over (a model edited in Python since, e.g. by a Scene, is rebuilt): the same
    `_native.Model` then serves again (the kernel and the scene's forces copy what they use from it).

    Raises:
        MissingDependencyError: the extension is not available here (the message says why).
    """
    if module is None:
        raise MissingDependencyError(f"the native kernel is not available: {why_unavailable}")
    archive = model_bytes(model)
    held = _HANDED.pop(id(model), None)
    if held is None or held[0] != archive:  # a new model, or this one changed (equal archives: equal models)
        held = (archive, module.Model(archive))
    _HANDED[id(model)] = held  # the latest at the end
    if len(_HANDED) > _HANDED_SIZE:
        del _HANDED[next(iter(_HANDED))]
    return held[1]
