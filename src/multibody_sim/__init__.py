"""multibody-sim: simulate URDF robots on Pinocchio with swappable integrators and an energy ledger.

The public names load on first use (PEP 562): `import multibody_sim` and the command line's `--help` import only
what they touch, and `from multibody_sim import X` imports X's submodule then.
"""

from __future__ import annotations

import importlib
import sys
import types
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # the same names, eagerly, for type checkers and IDEs
    from . import analysis
    from .bench import (
        BenchInterrupted,
        Choice,
        Measurement,
        WorkPrecision,
        choose_integrator,
        plot_work_precision,
        recommend,
        trajectory_error,
        work_precision,
    )
    from .catalog import CATALOG, catalog_table, load_robot
    from .controllers import (
        CONTROLLERS,
        PD,
        ComputedTorque,
        GravityCompensation,
        LocalMinimum,
        PDGravity,
        PotentialField,
        TrackingLog,
        make_controller,
    )
    from .derivatives import StepJacobians, linearize
    from .exceptions import (
        ControllerOutputError,
        InvalidArgumentError,
        MissingDependencyError,
        ModelError,
        MultibodySimError,
        RobotNotFoundError,
        SceneError,
        SimulationError,
        SimulationInterrupted,
        TrajectoryFileError,
        UnknownIntegratorError,
        UnknownNameError,
    )
    from .integrators import INTEGRATORS, ButcherTableau, ExplicitRungeKutta, Integrator, get_integrator
    from .robot import Robot
    from .rollout import BatchTrajectory, rollout
    from .scenes import Scene, load_scene, make_scene
    from .simulation import simulate
    from .stability import LadderRung, StabilityLimit, Stiffness, largest_stable_dt, linearization, stiffness_ratio
    from .stepper import BatchStep, BatchStepper, Stepper, StepperState
    from .trajectory import ConstraintRecord, LedgerEntry, LimitViolations, Trajectory

__version__ = "0.1.0"

# Each public name -> the submodule that defines it (analysis is itself a submodule; rollout, both a
# submodule and a function, is the property below).
_SOURCE: dict[str, str] = {
    "ControllerOutputError": "exceptions",
    "CATALOG": "catalog",
    "CONTROLLERS": "controllers",
    "INTEGRATORS": "integrators",
    "PD": "controllers",
    "BatchStep": "stepper",
    "BatchStepper": "stepper",
    "BatchTrajectory": "rollout",
    "BenchInterrupted": "bench",
    "ButcherTableau": "integrators",
    "Choice": "bench",
    "ComputedTorque": "controllers",
    "ConstraintRecord": "trajectory",
    "ExplicitRungeKutta": "integrators",
    "GravityCompensation": "controllers",
    "Integrator": "integrators",
    "InvalidArgumentError": "exceptions",
    "MissingDependencyError": "exceptions",
    "LadderRung": "stability",
    "LedgerEntry": "trajectory",
    "LimitViolations": "trajectory",
    "LocalMinimum": "controllers",
    "Measurement": "bench",
    "ModelError": "exceptions",
    "MultibodySimError": "exceptions",
    "PDGravity": "controllers",
    "PotentialField": "controllers",
    "Robot": "robot",
    "Scene": "scenes",
    "SceneError": "exceptions",
    "RobotNotFoundError": "exceptions",
    "SimulationError": "exceptions",
    "SimulationInterrupted": "exceptions",
    "StabilityLimit": "stability",
    "StepJacobians": "derivatives",
    "Stepper": "stepper",
    "StepperState": "stepper",
    "Stiffness": "stability",
    "TrackingLog": "controllers",
    "Trajectory": "trajectory",
    "TrajectoryFileError": "exceptions",
    "UnknownIntegratorError": "exceptions",
    "UnknownNameError": "exceptions",
    "WorkPrecision": "bench",
    "analysis": "analysis",
    "catalog_table": "catalog",
    "choose_integrator": "bench",
    "get_integrator": "integrators",
    "largest_stable_dt": "stability",
    "linearization": "stability",
    "linearize": "derivatives",
    "load_robot": "catalog",
    "load_scene": "scenes",
    "make_scene": "scenes",
    "make_controller": "controllers",
    "plot_work_precision": "bench",
    "recommend": "bench",
    "simulate": "simulation",
    "stiffness_ratio": "stability",
    "trajectory_error": "bench",
    "work_precision": "bench",
}

__all__ = [
    "ControllerOutputError",
    "CATALOG",
    "CONTROLLERS",
    "INTEGRATORS",
    "PD",
    "BatchStep",
    "BatchStepper",
    "BatchTrajectory",
    "BenchInterrupted",
    "ButcherTableau",
    "Choice",
    "ComputedTorque",
    "ConstraintRecord",
    "ExplicitRungeKutta",
    "GravityCompensation",
    "Integrator",
    "InvalidArgumentError",
    "MissingDependencyError",
    "LadderRung",
    "LedgerEntry",
    "LimitViolations",
    "LocalMinimum",
    "Measurement",
    "ModelError",
    "MultibodySimError",
    "PDGravity",
    "PotentialField",
    "Robot",
    "Scene",
    "SceneError",
    "RobotNotFoundError",
    "SimulationError",
    "SimulationInterrupted",
    "StabilityLimit",
    "StepJacobians",
    "Stepper",
    "StepperState",
    "Stiffness",
    "TrackingLog",
    "Trajectory",
    "TrajectoryFileError",
    "UnknownIntegratorError",
    "UnknownNameError",
    "WorkPrecision",
    "analysis",
    "catalog_table",
    "choose_integrator",
    "get_integrator",
    "largest_stable_dt",
    "linearization",
    "linearize",
    "load_robot",
    "load_scene",
    "make_scene",
    "make_controller",
    "plot_work_precision",
    "recommend",
    "rollout",
    "simulate",
    "stiffness_ratio",
    "trajectory_error",
    "work_precision",
]


def __getattr__(name: str) -> Any:
    """Import a public name's submodule on first access (then cache the name here); also any submodule by name."""
    source = _SOURCE.get(name)
    if source is None:
        try:
            module = importlib.import_module(f"{__name__}.{name}")
        except ModuleNotFoundError as exc:
            if exc.name != f"{__name__}.{name}":
                raise
            raise AttributeError(f"module {__name__!r} has no attribute {name!r}") from None
        return module
    module = importlib.import_module(f"{__name__}.{source}")
    value = module if name == "analysis" else getattr(module, name)
    globals()[name] = value
    return value


class _Package(types.ModuleType):
    """This package's module type: `rollout` names both a submodule and its function, and the function wins
    (importing the submodule binds it on the package, which would otherwise hide the function)."""

    @property
    def rollout(self) -> Any:
        """multibody_sim.rollout.rollout, the function."""
        return importlib.import_module(f"{__name__}.rollout").rollout

    @rollout.setter
    def rollout(self, value: Any) -> None:
        """Ignore the import system's binding of the submodule."""


sys.modules[__name__].__class__ = _Package


def __dir__() -> list[str]:
    return sorted({*globals(), *__all__})
