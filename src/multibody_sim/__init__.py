"""multibody-sim: simulate URDF robots on Pinocchio with swappable integrators and an energy ledger."""

from .catalog import CATALOG, catalog_table, load_robot
from .exceptions import (
    InvalidArgumentError,
    ModelError,
    MultibodySimError,
    RobotNotFoundError,
    SimulationError,
    SimulationInterrupted,
    TrajectoryFileError,
    UnknownIntegratorError,
    UnknownNameError,
)
from .integrators import INTEGRATORS, ButcherTableau, ExplicitRungeKutta, Integrator, get_integrator
from .robot import Robot
from .simulation import simulate
from .trajectory import LedgerEntry, LimitViolations, Trajectory

__version__ = "0.1.0"

__all__ = [
    "CATALOG",
    "INTEGRATORS",
    "ButcherTableau",
    "ExplicitRungeKutta",
    "Integrator",
    "InvalidArgumentError",
    "LedgerEntry",
    "LimitViolations",
    "ModelError",
    "MultibodySimError",
    "Robot",
    "RobotNotFoundError",
    "SimulationError",
    "SimulationInterrupted",
    "Trajectory",
    "TrajectoryFileError",
    "UnknownIntegratorError",
    "UnknownNameError",
    "catalog_table",
    "get_integrator",
    "load_robot",
    "simulate",
]
