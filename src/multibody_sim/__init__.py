"""multibody-sim: simulate URDF robots on Pinocchio with swappable integrators and an energy ledger."""

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
