"""Optional dependencies of the viewer: found lazily, with one actionable error when missing."""

from __future__ import annotations

import importlib
import importlib.util
from pathlib import Path
from types import ModuleType

from ..exceptions import MissingDependencyError

INSTALL_HINT = "pip install 'multibody-sim[viz]'"


class ViewerWarning(UserWarning):
    """Something the viewer could do only in part (base class of the viewer's warnings)."""


def require(module: str, purpose: str) -> ModuleType:
    """Import an optional module, or raise MissingDependencyError naming what needs it.

    Args:
        module: the module to import ("matplotlib.figure", "trimesh", ...).
        purpose: what it is needed for, for the message ("plots", "the meshcat viewer").
    """
    try:
        return importlib.import_module(module)
    except ImportError:
        top = module.split(".")[0]
        raise MissingDependencyError(
            f"{purpose} need the '{top}' package, which is not installed ({INSTALL_HINT})"
        ) from None


def meshcat_viewer_js() -> Path:
    """The meshcat viewer's bundled JavaScript (main.min.js), shipped inside the meshcat wheel.

    Located without importing meshcat: its package __init__ imports IPython, a second of start-up for nothing.
    """
    try:
        spec = importlib.util.find_spec("meshcat")
    except (ImportError, ValueError):  # ValueError: sys.modules holds None for it (treated as not installed)
        spec = None
    if spec is None or not spec.submodule_search_locations:
        raise MissingDependencyError(
            f"the meshcat viewer needs the 'meshcat' package, which is not installed ({INSTALL_HINT})"
        )
    path = Path(next(iter(spec.submodule_search_locations))) / "viewer" / "dist" / "main.min.js"
    if not path.is_file():
        raise MissingDependencyError(
            f"the meshcat package lacks its viewer JavaScript ({path}); reinstall it ({INSTALL_HINT})"
        )
    return path


def check_viewer_dependencies() -> None:
    """Raise MissingDependencyError now, before any work, if the viewer cannot run."""
    meshcat_viewer_js()
    for module in ("umsgpack", "tornado.web", "trimesh"):
        require(module, "the meshcat viewer")
