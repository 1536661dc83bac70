"""Errors raised by multibody_sim: one base class, leaves that also subclass the builtin meaning."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from .text import printable

if TYPE_CHECKING:
    from pathlib import Path


class MultibodySimError(Exception):
    """Base class of every error this package raises on purpose."""


class InvalidArgumentError(MultibodySimError, ValueError):
    """An argument has the wrong shape, type or value (the message names it and what was expected)."""


class SceneError(InvalidArgumentError):
    """A scene (TOML file or dict) is malformed: the one-line message names the file, the key and the valid options."""


class UnknownNameError(MultibodySimError, LookupError):
    """A name (robot, integrator, ...) is not in its registry; the message lists close matches."""

    def __str__(self) -> str:  # LookupError would quote the message like a dict key
        # The names it lists may come from a file (joints, frames, poses): escaped, one line.
        return printable(str(self.args[0])) if self.args else ""


class RobotNotFoundError(UnknownNameError):
    """The robot source is neither a catalog name nor an existing URDF file."""


class UnknownIntegratorError(UnknownNameError):
    """The integrator name is not in the registry."""


class ModelError(MultibodySimError, ValueError):
    """A URDF (or model) file is missing, malformed or describes something we cannot simulate."""


class MissingDependencyError(MultibodySimError, ImportError):
    """An optional package (viewing, plotting) is not installed; the message says how to get it."""


class TrajectoryFileError(MultibodySimError, ValueError):
    """A trajectory file is missing, truncated, corrupted or not one of ours."""


class SimulationError(MultibodySimError, RuntimeError):
    """A simulation stopped before reaching its duration.

    Attributes:
        status: why it stopped ("diverged", "failed", "write_failed", "out_of_memory", ...).
        trajectory: every finite sample computed before the stop (a Trajectory; typed Any: errors sit below the
            modules that build trajectories and import none of them).
        saved_to: the file (or a chunked run's parts folder) holding them, or None when they are in memory only.
    """

    def __init__(
        self,
        message: str,
        *,
        status: str,
        trajectory: Any = None,
        saved_to: Path | None = None,
        **details: Any,
    ):
        super().__init__(message)
        self.status = status
        self.trajectory = trajectory
        self.saved_to = saved_to
        self.details = details


class SimulationInterrupted(KeyboardInterrupt):
    """Ctrl-C (or SIGTERM in the CLI) stopped a simulation; `.trajectory` holds the samples so far and `.saved_to`
    the file (or parts folder) holding them, or None."""

    def __init__(
        self,
        message: str,
        *,
        trajectory: Any = None,
        signal_name: str = "SIGINT",
        saved_to: Path | None = None,
    ):
        super().__init__(message)
        self.status = "interrupted"
        self.trajectory = trajectory
        self.signal_name = signal_name
        self.saved_to = saved_to


class ControllerOutputError(SimulationError, InvalidArgumentError):
    """A controller returned something that is not a torque (wrong shape, not finite, a push on an unactuated
    floating base): the run stopped with status "failed" and `.trajectory` holds the samples so far. It is also an
    InvalidArgumentError, as this mistake was before runs kept their samples."""
