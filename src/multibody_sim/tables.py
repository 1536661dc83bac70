"""Trajectories as tables with named columns: pandas DataFrames, CSV and Parquet files (the `dataframe` extra).

Columns, in order: `t`; `q.<coordinate>` per configuration coordinate (a joint's name; a free-flyer's
`<joint>.x .y .z .qx .qy .qz .qw`, a continuous joint's `<joint>.cos .sin`, a spherical joint's `.qx .qy .qz .qw`,
a planar joint's `.x .y .cos .sin`); `v.<dof>` and `tau.<dof>` per velocity coordinate (Robot.dof_names);
`kinetic_energy`, `potential_energy`, `total_energy`, `work`, `dissipated`, `energy_error`; `ledger.<element>`
per ledger element; `constraint.<name>.force[k]`, `.drift` and `.velocity_drift` per scene constraint; for a
contact scene's run, per contact body (Contacts.bodies: "ground", objects, declared collision frames)
`contact.<body>.normal`, the sum over its contact points of the normal forces (each along its contact's normal,
positive when it presses), `.tangential`, the size of the sum of the tangential forces on it (its net friction
force), both [N] and the mean forces over the step that ended at the sample, and `.count`, its contact points;
then `contact.count`, all the sample's contact points; `<sensor>.<component>` per sensor reading
(multibody_sim.sensors: `imu.ax`, `enc.<joint>`, ...). A trajectory without the robot's names in its metadata gets
`q[k]`, `v[k]`, `tau[k]` (and `<sensor>[k]`). `contacts_dataframe()` gives every contact point in long form.
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
CONTACT_PARTS = ("normal", "tangential", "count")  # a contact body's columns, in order
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
    if trajectory.contacts is not None:
        columns += [f"contact.{body}.{part}" for body in trajectory.contacts.bodies for part in CONTACT_PARTS]
        columns.append("contact.count")
    components = {
        entry.get("name"): entry.get("components")
        for entry in trajectory.metadata.get("sensors", [])
        if isinstance(entry, dict)
    }
    for name, readings in trajectory.sensors.items():
        width = np.shape(readings)[1]
        known = components.get(name)
        if isinstance(known, list) and len(known) == width:
            columns += [f"{name}.{component}" for component in known]
        else:
            columns += [f"{name}[{k}]" for k in range(width)]
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
    if trajectory.contacts is not None:
        parts.append(_contact_block(trajectory, rows, len(parts[0])))
    parts += [
        np.asarray(readings[rows], dtype=float).reshape(len(parts[0]), -1) for readings in trajectory.sensors.values()
    ]
    return np.hstack(parts)


def _contact_block(trajectory: Trajectory, rows: slice, n: int) -> np.ndarray:
    """The contact columns of some rows, shape (n, 3 x bodies + 1): per body its normal force, its tangential force
    and its contact count, then the sample's count."""
    contacts = trajectory.contacts
    assert contacts is not None
    start = rows.indices(len(trajectory.t))[0]
    bodies = len(contacts.bodies)
    block = np.zeros((n, len(CONTACT_PARTS) * bodies + 1))
    first, last = np.searchsorted(contacts.sample, [start, start + n])  # rows are sorted by sample
    if first == last:
        return block
    normal, tangent = _force_components(trajectory)
    normal, tangent = normal[first:last], tangent[first:last]
    sample = np.asarray(contacts.sample[first:last]) - start
    cells = n * bodies
    tangential = np.zeros((cells, 3))
    for side, sign in ((0, -1.0), (1, 1.0)):  # the force acts on the pair's second body, its opposite on the first
        index = sample * bodies + np.asarray(contacts.pair[first:last, side])
        block[:, 0 : 3 * bodies : 3] += np.bincount(index, normal, minlength=cells).reshape(n, bodies)
        block[:, 2 : 3 * bodies : 3] += np.bincount(index, minlength=cells).reshape(n, bodies)
        for axis in range(3):
            tangential[:, axis] += np.bincount(index, sign * tangent[:, axis], minlength=cells)
    block[:, 1 : 3 * bodies : 3] = np.linalg.norm(tangential, axis=1).reshape(n, bodies)
    block[:, -1] = np.bincount(sample, minlength=n)
    return block


def _force_components(trajectory: Trajectory) -> tuple[np.ndarray, np.ndarray]:
    """Each contact row's normal force, along its normal (positive pushes the bodies apart), shape (m,) [N], and
    its tangential force, the rest, on the pair's second body, world axes, shape (m, 3) [N]."""
    assert trajectory.contacts is not None
    force = trajectory.contact_forces()
    normals = np.asarray(trajectory.contacts.normal, dtype=float)
    normal = np.einsum("ij,ij->i", force, normals)
    return normal, force - normal[:, None] * normals


def contacts_dataframe(trajectory: Trajectory) -> Any:
    """A contact scene's contacts in long form: a pandas DataFrame of one row per contact point per sample.

    Columns: t [s], sample, body1, body2 (names; the force acts on body2, its opposite on body1), point.x .y .z
    [m], normal.x .y .z (unit, from body1 to body2), impulse.x .y .z [N·s] (over the step that ended at the
    sample), force.x .y .z [N] (the mean force over that step), normal_force and tangential_force [N] (the force's
    component along the normal and the size of the rest).

    Raises:
        InvalidArgumentError: the trajectory records no contacts (or no step in its metadata).
        MissingDependencyError: pandas is not installed.
    """
    pandas = _require("pandas", "dataframes")
    contacts = trajectory.contacts
    if contacts is None:
        raise InvalidArgumentError("the trajectory records no contacts (it is not a run of a scene with contact)")
    force = trajectory.contact_forces()
    normal, tangent = _force_components(trajectory)
    tangential = np.linalg.norm(tangent, axis=1)
    names = np.array(list(contacts.bodies) or [""], dtype=object)
    columns: dict[str, Any] = {
        "t": np.asarray(trajectory.t, dtype=float)[contacts.sample],
        "sample": np.asarray(contacts.sample, dtype=np.int64),
        "body1": names[contacts.pair[:, 0]] if len(contacts.sample) else np.zeros(0, dtype=object),
        "body2": names[contacts.pair[:, 1]] if len(contacts.sample) else np.zeros(0, dtype=object),
    }
    for name, values in (("point", contacts.point), ("normal", contacts.normal), ("impulse", contacts.impulse)):
        columns.update({f"{name}.{axis}": np.asarray(values, dtype=float)[:, k] for k, axis in enumerate("xyz")})
    columns.update({f"force.{axis}": force[:, k] for k, axis in enumerate("xyz")})
    columns.update(normal_force=normal, tangential_force=tangential)
    frame = pandas.DataFrame(columns)
    frame.attrs.update(_attributes(trajectory))
    return frame


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
        from .recorded import robot_from_trajectory

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
