"""Work-precision studies: the error every integrator reaches at each cost on one system, and the cheapest choice.

A study runs each integrator over a ladder of steps (fixed-step methods) or tolerances (adaptive ones) from one
initial state, and measures

- the error: max over a common sample grid of ‖(q ⊖ q_ref, v − v_ref)‖∞ (Pinocchio's difference in the tangent
  space, CONTRACTS.md's `--tolerance`), against a reference computed by DOP853 at a tight tolerance; the reference
  is checked by refining it once more (a tolerance `refinement` times tighter), and the largest difference
  between the two is its estimated error;
- the energy error max |H − H(0) − work + dissipated| from the ledger, shown beside the error and never used as
  it (the ledger does not see phase error);
- the cost: the CPU time of the run (median over repeats), the stepping loop's wall time (median) and the dynamics
  evaluations. CPU time is what "cheapest" means by default: it is what the run costs on an idle machine, while
  wall time on a shared machine also counts the turns other processes take (the wall time is kept beside it).

From the measurements it fits each integrator's observed order and recommends, for a requested accuracy, the
cheapest measured configuration whose error, plus the reference's own estimated error, stays within it.

The package: results.py (the study's data, tables, files, diagram, order fits and recommendation), study.py
(work_precision, the measuring), pilot.py (choose_integrator, the pilot study of `run --tolerance`) and savings.py
(measure_savings: a scene's cost per step against its full robot's).
"""

from .pilot import (
    PILOT_HORIZON,
    PILOT_MAX_RUN_TIME,
    PILOT_MIN_ERROR,
    PILOT_SAFETY,
    Choice,
    choose_integrator,
    default_cache_dir,
)
from .results import (
    ADAPTIVE_FIT_POINTS,
    CSV_COLUMNS,
    FIT_POINTS,
    FORMAT,
    FORMAT_VERSION,
    METHOD_COLORS,
    ORDER_MISMATCH,
    REFERENCE_MARGIN,
    STATUS_COMPLETED,
    STATUS_REFUSED,
    UNCONVERGED_REFERENCE,
    Measurement,
    OrderFit,
    Reference,
    WorkPrecision,
    observed_orders,
    plot_work_precision,
    recommend,
)
from .savings import measure_savings
from .study import (
    ADAPTIVE_FIRST_STEP,
    CONTACT_REFERENCE_DT,
    CONTROL_DT,
    MIN_ERROR,
    OUTPUT_DT,
    REFERENCE_INTEGRATOR,
    REFERENCE_TOLERANCE,
    REFINEMENT,
    REPEAT_BELOW,
    STEP_LADDER,
    TOLERANCE_LADDER,
    BenchInterrupted,
    trajectory_error,
    work_precision,
)

__all__ = [
    "BenchInterrupted",
    "Choice",
    "Measurement",
    "OrderFit",
    "Reference",
    "WorkPrecision",
    "choose_integrator",
    "default_cache_dir",
    "measure_savings",
    "observed_orders",
    "plot_work_precision",
    "recommend",
    "trajectory_error",
    "work_precision",
    # the study's settings (command line, scripts and tests read them)
    "ADAPTIVE_FIRST_STEP",
    "ADAPTIVE_FIT_POINTS",
    "CONTACT_REFERENCE_DT",
    "CONTROL_DT",
    "CSV_COLUMNS",
    "FIT_POINTS",
    "FORMAT",
    "FORMAT_VERSION",
    "METHOD_COLORS",
    "MIN_ERROR",
    "ORDER_MISMATCH",
    "OUTPUT_DT",
    "PILOT_HORIZON",
    "PILOT_MAX_RUN_TIME",
    "PILOT_MIN_ERROR",
    "PILOT_SAFETY",
    "REFERENCE_INTEGRATOR",
    "REFERENCE_MARGIN",
    "REFERENCE_TOLERANCE",
    "REFINEMENT",
    "REPEAT_BELOW",
    "STATUS_COMPLETED",
    "STATUS_REFUSED",
    "STEP_LADDER",
    "TOLERANCE_LADDER",
    "UNCONVERGED_REFERENCE",
]
