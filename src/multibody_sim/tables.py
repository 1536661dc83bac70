"""Trajectories as tables with named columns: pandas DataFrames, CSV and Parquet files (the `dataframe` extra).

Columns, in order: `t`; `q.<coordinate>` per configuration coordinate (a joint's name; a free-flyer's
`<joint>.x .y .z .qx .qy .qz .qw`, a continuous joint's `<joint>.cos .sin`, a spherical joint's `.qx .qy .qz .qw`,
a planar joint's `.x .y .cos .sin`); `v.<dof>` and `tau.<dof>` per velocity coordinate (Robot.dof_names);
`kinetic_energy`, `potential_energy`, `total_energy`, `work`, `dissipated`, `energy_error`; `ledger.<element>`
per ledger element; `constraint.<name>.force[k]`, `.drift` and `.velocity_drift` per scene constraint. A
trajectory without the robot's names in its metadata gets `q[k]`, `v[k]`, `tau[k]`.
"""

from __future__ import annotations

import importlib
import json
import os
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from .exceptions import InvalidArgumentError, MissingDependencyError
from .files import check_output, write_atomically
from .robot import Robot
from .trajectory import Trajectory

TABLE_FORMATS = (".csv", ".parquet")
ENERGY_COLUMNS = ("kinetic_energy", "potential_energy", "total_energy", "work", "dissipated", "energy_error")
INSTALL_HINT = "pip install 'multibody-sim[dataframe]'"
_BLOCK_ROWS = 50_000  # rows per block written: files of any length in bounded memory
_FREE_FLYER = ("x", "y", "z", "qx", "qy", "qz", "qw")


def configuration_names(robot: Robot) -> list[str]:
    """One name per configuration coordinate (length nq), in Pinocchio's order (see the module docstring)."""
    model = robot.model
    names: list[str] = []
    for jid in range(1, model.njoints):
        joint, name = model.joints[jid], model.names[jid]
        kind = joint.shortname()
        if joint.nq == 1:
            names.append(name)
        elif "FreeFlyer" in kind:
            names += [f"{name}.{c}" for c in _FREE_FLYER]
        elif "Planar" in kind:
            names += [f"{name}.{c}" for c in ("x", "y", "cos", "sin")]
        elif "Spherical" in kind and joint.nq == 4:
            names += [f"{name}.{c}" for c in ("qx", "qy", "qz", "qw")]
        elif joint.nq == 2 and joint.nv == 1:  # continuous (unbounded revolute): the angle as (cos, sin)
            names += [f"{name}.cos", f"{name}.sin"]
        else:
            names += [f"{name}[{k}]" for k in range(joint.nq)]
    return names


def column_names(trajectory: Trajectory, robot: Robot | None = None) -> list[str]:
    """The table's column names, in order (see the module docstring).

    Args:
        trajectory: the trajectory.
        robot: its robot, for the coordinate names; None reads them from the trajectory's metadata (and loads
            the robot from there only when the metadata cannot tell a continuous joint's two coordinates apart).
    """
    q_names, dof_names = _coordinate_names(trajectory, robot)
    columns = ["t", *(f"q{n}" for n in q_names), *(f"v{n}" for n in dof_names), *(f"tau{n}" for n in dof_names)]
    columns += ENERGY_COLUMNS
    columns += [f"ledger.{name}" for name in trajectory.ledger]
    for name, record in trajectory.constraints.items():
        rows = np.shape(record.force)[1] if np.ndim(record.force) == 2 else 0
        columns += [f"constraint.{name}.force[{k}]" for k in range(rows)]
        columns += [f"constraint.{name}.drift", f"constraint.{name}.velocity_drift"]
    return columns


def to_dataframe(trajectory: Trajectory, robot: Robot | None = None) -> Any:
    """The trajectory as a pandas DataFrame, one row per sample, columns as column_names() gives them.

    `DataFrame.attrs` holds the robot's name, the integrator, the status and each ledger element's kind.

    Raises:
        MissingDependencyError: pandas is not installed.
    """
    pandas = _require("pandas", "dataframes")
    columns = column_names(trajectory, robot)
    frame = pandas.DataFrame(_block(trajectory, slice(None)), columns=columns, copy=False)
    frame.attrs.update(_attributes(trajectory))
    return frame


def write_table(
    trajectory: Trajectory, path: str | os.PathLike[str], *, robot: Robot | None = None, format: str | None = None
) -> Path:
    """Write the trajectory as a table: CSV (a header line of column names) or Parquet.

    Written atomically, block by block (a memory-mapped trajectory of any length stays in bounded memory). CSV
    numbers are the shortest text that reads back to the same float64 (Python's float(), pandas 3's read_csv;
    pandas 2 needs `float_precision="round_trip"`); Parquet keeps float64 as is, with the trajectory's
    metadata as JSON under the schema's metadata key "multibody_sim".

    Args:
        trajectory: the trajectory.
        path: the file to write.
        robot: its robot, for the coordinate names (see column_names).
        format: "csv" or "parquet"; None takes the file's extension.

    Raises:
        InvalidArgumentError: an unknown format (or extension, without `format`).
        MissingDependencyError: pandas (and for Parquet, pyarrow) is not installed.
    """
    target = Path(path)
    suffix = check_table_format(target, format)
    check_output(target, "out", f"table{suffix}")  # before the work: only a regular file is replaced
    pandas = _require("pandas", "CSV and Parquet files")
    columns = column_names(trajectory, robot)
    frames = (
        pandas.DataFrame(_block(trajectory, rows), columns=columns, copy=False) for rows in _blocks(len(trajectory))
    )
    if suffix == ".csv":

        def write(f: Any) -> None:
            for k, frame in enumerate(frames):
                frame.to_csv(f, header=k == 0, index=False, float_format=None, lineterminator="\n")

    else:
        pyarrow = _require("pyarrow", "Parquet files")
        parquet = _require("pyarrow.parquet", "Parquet files")
        schema = pyarrow.schema(
            [(name, pyarrow.float64()) for name in columns],
            metadata={"multibody_sim": json.dumps(_attributes(trajectory) | {"metadata": trajectory.metadata})},
        )

        def write(f: Any) -> None:
            with parquet.ParquetWriter(f, schema) as writer:
                for frame in frames:
                    writer.write_table(pyarrow.Table.from_pandas(frame, schema=schema, preserve_index=False))

    write_atomically(target, write)
    return target


def check_table_format(path: Path, format: str | None = None) -> str:
    """The table format (".csv" or ".parquet") of a file, with its packages checked before any work.

    Raises:
        InvalidArgumentError: an unknown format (or extension, without `format`).
        MissingDependencyError: pandas (and for Parquet, pyarrow) is not installed.
    """
    suffix = path.suffix.lower() if format is None else f".{format.lower().lstrip('.')}"
    if suffix not in TABLE_FORMATS:
        given = f"extension '{path.suffix}'" if format is None else f"format '{format}'"
        raise InvalidArgumentError(f"{path}: unknown table {given} (choose from: {', '.join(TABLE_FORMATS)})")
    _require("pandas", "CSV and Parquet files")
    if suffix == ".parquet":
        _require("pyarrow.parquet", "Parquet files")
    return suffix


# ---- rows and names ---------------------------------------------------------------------------------------
def _blocks(n: int) -> Iterator[slice]:
    if n == 0:
        yield slice(0, 0)
    for start in range(0, n, _BLOCK_ROWS):
        yield slice(start, min(start + _BLOCK_ROWS, n))


def _block(trajectory: Trajectory, rows: slice) -> np.ndarray:
    """The table's values for some rows, shape (rows, columns), float64."""
    parts: list[np.ndarray] = [np.asarray(trajectory.t[rows], dtype=float)[:, None]]
    for name in ("q", "v", "tau"):
        parts.append(np.asarray(getattr(trajectory, name)[rows], dtype=float).reshape(len(parts[0]), -1))
    parts += [np.asarray(getattr(trajectory, name)[rows], dtype=float)[:, None] for name in ENERGY_COLUMNS]
    parts += [np.asarray(entry.energy[rows], dtype=float)[:, None] for entry in trajectory.ledger.values()]
    for record in trajectory.constraints.values():
        parts.append(np.asarray(record.force[rows], dtype=float).reshape(len(parts[0]), -1))
        parts += [np.asarray(record.drift[rows], dtype=float)[:, None]]
        parts += [np.asarray(record.velocity_drift[rows], dtype=float)[:, None]]
    return np.hstack(parts)


def _attributes(trajectory: Trajectory) -> dict[str, Any]:
    info = trajectory.metadata.get("robot")
    return {
        "robot": info.get("name") if isinstance(info, dict) else None,
        "integrator": trajectory.metadata.get("integrator"),
        "status": trajectory.status,
        "ledger_kinds": {name: entry.kind for name, entry in trajectory.ledger.items()},
    }


def _coordinate_names(trajectory: Trajectory, robot: Robot | None) -> tuple[list[str], list[str]]:
    """Column-name endings, one per q coordinate and one per v coordinate: ".<name>", or "[k]" without names."""
    nq = np.shape(trajectory.q)[1] if np.ndim(trajectory.q) == 2 else 0
    nv = np.shape(trajectory.v)[1] if np.ndim(trajectory.v) == 2 else 0
    if robot is not None:
        if (robot.nq, robot.nv) != (nq, nv):
            raise InvalidArgumentError(
                f"robot {robot.name} has nq = {robot.nq} and nv = {robot.nv}, the trajectory {nq} and {nv}"
            )
        return _dotted(configuration_names(robot)), _dotted(robot.dof_names)
    info = trajectory.metadata.get("robot")
    info = info if isinstance(info, dict) else {}
    joints, dofs = info.get("joint_names"), info.get("dof_names")
    if not (isinstance(joints, list) and isinstance(dofs, list) and len(dofs) == nv and info.get("nq") == nq):
        return [f"[{k}]" for k in range(nq)], [f"[{k}]" for k in range(nv)]
    dof_names = [str(d) for d in dofs]
    names = _names_from_dofs([str(j) for j in joints], dof_names, nq)
    if names is None:  # continuous joints among other one-dof joints: only the model can say which
        from .viz.frames import robot_from_trajectory

        names = configuration_names(robot_from_trajectory(trajectory))
    return _dotted(names), _dotted(dof_names)


def _dotted(names: list[str]) -> list[str]:
    return [f".{name}" for name in names]


def _names_from_dofs(joints: list[str], dofs: list[str], nq: int) -> list[str] | None:
    """Configuration names from joint and dof names (Robot.dof_names's pattern), or None if ambiguous."""
    per_joint: list[list[str] | None] = []  # None: a one-dof joint, one or two coordinates
    k = 0
    for joint in joints:
        own = []
        while k < len(dofs) and (dofs[k] == joint or dofs[k].startswith((f"{joint}.", f"{joint}["))):
            own.append(dofs[k][len(joint) :])
            k += 1
        if own == [""]:
            per_joint.append(None)
        elif own == [".vx", ".vy", ".vz", ".wx", ".wy", ".wz"]:
            per_joint.append([f"{joint}.{c}" for c in _FREE_FLYER])
        elif own == [".vx", ".vy", ".wz"]:
            per_joint.append([f"{joint}.{c}" for c in ("x", "y", "cos", "sin")])
        elif own == [".wx", ".wy", ".wz"]:
            per_joint.append([f"{joint}.{c}" for c in ("qx", "qy", "qz", "qw")])
        else:
            return None  # a joint kind whose coordinates the names do not tell
    if k != len(dofs):
        return None
    known = sum(len(names) for names in per_joint if names is not None)
    single = sum(names is None for names in per_joint)
    if nq - known == single:
        continuous = False
    elif nq - known == 2 * single:
        continuous = True
    else:
        return None
    result: list[str] = []
    for joint, names in zip(joints, per_joint, strict=True):
        if names is None:
            result += [f"{joint}.cos", f"{joint}.sin"] if continuous else [joint]
        else:
            result += names
    return result


def _require(module: str, purpose: str) -> Any:
    try:
        return importlib.import_module(module)
    except ImportError:
        top = module.split(".")[0]
        raise MissingDependencyError(
            f"{purpose} need the '{top}' package, which is not installed ({INSTALL_HINT})"
        ) from None
