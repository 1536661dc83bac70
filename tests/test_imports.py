"""`import multibody_sim` and `multibody-sim --help` stay light: heavy optional or rarely needed packages are
imported where they are used, not at import (scripts/bench_import.py measures the times; this checks, without
timing anything, which modules a fresh interpreter holds)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

# Imported only by the code that needs them: the implicit and variational integrators and computed torque (SciPy),
# plots (matplotlib), progress bars (tqdm), URDF/SRDF parsing (lxml), mesh loading (yourdfpy, trimesh), the
# viewer (meshcat), tables (pandas), scene files (tomllib), package versions (importlib.metadata).
LAZY = (
    "scipy",
    "matplotlib",
    "tqdm",
    "lxml",
    "yourdfpy",
    "trimesh",
    "meshcat",
    "pandas",
    "tomllib",
    "importlib.metadata",
    "gymnasium",
)


def _loaded_after(code: str) -> list[str]:
    """The LAZY modules a fresh interpreter holds after running `code`."""
    probe = f"{code}\nimport json, sys\nprint(json.dumps([m for m in {LAZY!r} if m in sys.modules]))"
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_import_loads_none_of_the_heavy_modules() -> None:
    assert _loaded_after("import multibody_sim") == []


def test_help_loads_none_of_the_heavy_modules() -> None:
    code = (
        "import contextlib, io\nfrom multibody_sim.cli import main\n"
        "with contextlib.redirect_stdout(io.StringIO()) as out:\n    code = main(['--help'])\n"
        "assert code == 0 and 'usage: multibody-sim' in out.getvalue(), out.getvalue()"
    )
    assert _loaded_after(code) == []


@pytest.mark.parametrize(
    ("code", "module"),
    [
        ("import multibody_sim as ms; ms.get_integrator('implicit_euler')", None),
        ("import multibody_sim as ms; ms.load_robot('double_pendulum')", "lxml"),
        (
            "import multibody_sim as ms; r = ms.load_robot('double_pendulum'); "
            "ms.simulate(r, [0.1, 0.0], [0.0, 0.0], duration=0.01, dt=1e-3, integrator='implicit_euler')",
            "scipy",
        ),
    ],
)
def test_heavy_modules_come_with_their_first_use(code: str, module: str | None) -> None:
    """The probe itself can see a lazy import happen (so the tests above could fail): naming an integrator
    imports nothing, loading a URDF imports lxml, an implicit step SciPy."""
    loaded = _loaded_after(code)
    if module is None:
        assert loaded == []
    else:
        assert module in loaded


def _held_after(code: str, names: tuple[str, ...]) -> list[str]:
    """Which of `names` a fresh interpreter holds in sys.modules after running `code`."""
    probe = f"{code}\nimport json, sys\nprint(json.dumps([m for m in {names!r} if m in sys.modules]))"
    done = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, timeout=120, check=True)
    return json.loads(done.stdout.strip().splitlines()[-1])


# Pinocchio and the modules that step, load or check robots: `--help` needs none of them.
HEAVY_FOR_HELP = (
    "pinocchio",
    "numpy",
    "multibody_sim.controllers",
    "multibody_sim.driver",
    "multibody_sim.native",
    "multibody_sim.robot",
    "multibody_sim.simulation",
)


@pytest.mark.parametrize(
    ("argv", "loads_pinocchio"),
    [
        (["--help"], False),
        (["run", "--help"], True),  # its text lists the controllers: the probe sees Pinocchio come in
    ],
)
def test_help_imports_no_pinocchio(argv: list[str], loads_pinocchio: bool) -> None:
    code = (
        "import contextlib, io\nfrom multibody_sim.cli import main\n"
        f"with contextlib.redirect_stdout(io.StringIO()) as out:\n    code = main({argv!r})\n"
        "assert code == 0 and 'usage: multibody-sim' in out.getvalue(), out.getvalue()"
    )
    held = _held_after(code, HEAVY_FOR_HELP)
    if loads_pinocchio:
        assert "pinocchio" in held and "multibody_sim.controllers" in held
    else:
        assert held == []


def test_lazy_package_names() -> None:
    """`import multibody_sim` loads none of its submodules; every public name then resolves, `dir()` lists them,
    and `rollout` stays the function even after its submodule is imported."""
    code = (
        "import sys, types\nimport multibody_sim as ms\n"
        "assert 'multibody_sim.simulation' not in sys.modules and 'pinocchio' not in sys.modules\n"
        "assert set(ms.__all__) <= set(dir(ms))\n"
        "import multibody_sim.rollout\n"
        "assert callable(ms.rollout) and not isinstance(ms.rollout, types.ModuleType)\n"
        "ns = {}\nexec('from multibody_sim import ' + ', '.join(ms.__all__), ns)\n"
        "assert all(ns[name] is getattr(ms, name) for name in ms.__all__)\n"
        "assert isinstance(ms.analysis, types.ModuleType) and ms.simulate.__module__ == 'multibody_sim.simulation'\n"
        "try:\n    ms.no_such_name\nexcept AttributeError:\n    pass\nelse:\n    raise AssertionError('no error')\n"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
