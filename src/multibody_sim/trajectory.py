"""The result of a simulation: sampled states, the energy ledger, limit violations, stats; save and load."""

from __future__ import annotations

import json
import math
import os
import re
import zipfile
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np

from .exceptions import InvalidArgumentError, TrajectoryFileError
from .files import write_atomically
from .safety import ARCHIVE_ERRORS, MAX_JSON_DEPTH, check_npz, json_depth, read_npz
from .text import printable, safe_name
from .validation import check_flag, check_path, sample_times

FORMAT = "multibody-sim trajectory"
FORMAT_VERSION = 1
# The per-sample arrays every Trajectory (and BatchTrajectory) holds, in the order of the contract.
ARRAYS = (
    "t",
    "q",
    "v",
    "tau",
    "kinetic_energy",
    "potential_energy",
    "total_energy",
    "work",
    "dissipated",
    "energy_error",
)
_LEDGER_PREFIX = "ledger/"
_CONSTRAINT_PREFIX = "constraint/"
_SENSOR_PREFIX = "sensors/"
LEDGER_KINDS = ("work", "dissipated", "potential")


@dataclass(frozen=True)
class LedgerEntry:
    """One element of the energy ledger.

    Attributes:
        kind: "work" (energy put in, e.g. by joint torques), "dissipated" (taken out, e.g. by damping) or
            "potential" (stored, e.g. by a spring: part of potential_energy).
        energy: cumulative energy [J] at each sample (for "potential": the energy stored), shape (n_samples,).
    """

    kind: str
    energy: np.ndarray


@dataclass(frozen=True)
class Contacts:
    """The active contacts of a contact scene's run, compactly: one row per contact point per sample.

    The contacts of sample i are those of the step that ended there (for sample 0: none); rows are sorted by
    sample. Impulses are what the time-stepper applied over that step, on the second body, in world axes.

    Attributes:
        bodies: body names the rows index ("ground", objects, declared collision frames).
        sample: the sample each row belongs to, shape (m,), int.
        pair: the two bodies of each row (indices into `bodies`; the impulse acts on the second), shape (m, 2), int.
        point: the contact point midway between the shapes, world [m], shape (m, 3).
        normal: the unit normal from body 1 to body 2, world, shape (m, 3).
        impulse: the impulse on body 2 over the step, world [N·s], shape (m, 3).
    """

    bodies: list[str]
    sample: np.ndarray
    pair: np.ndarray
    point: np.ndarray
    normal: np.ndarray
    impulse: np.ndarray

    def at(self, i: int) -> Contacts:
        """The contacts of sample i (a Contacts with only its rows)."""
        lo, hi = np.searchsorted(self.sample, [i, i + 1])
        return Contacts(
            self.bodies,
            self.sample[lo:hi],
            self.pair[lo:hi],
            self.point[lo:hi],
            self.normal[lo:hi],
            self.impulse[lo:hi],
        )

    @staticmethod
    def empty(bodies: list[str]) -> Contacts:
        return Contacts(
            list(bodies),
            np.zeros(0, dtype=np.int64),
            np.zeros((0, 2), dtype=np.int64),
            np.zeros((0, 3)),
            np.zeros((0, 3)),
            np.zeros((0, 3)),
        )


CONTACT_PARTS = ("sample", "pair", "point", "normal", "impulse")
_CONTACT_PREFIX = "contacts/"


@dataclass(frozen=True)
class LimitViolations:
    """Position-limit violations at the output samples (reported, not enforced).

    Attributes:
        count: number of (sample, joint) pairs outside the limits.
        samples: number of samples with at least one joint outside its limits.
        worst_joint: the joint with the largest excess, or None.
        worst_excess: largest distance outside a limit [rad or m] (0 when none).
        worst_time: time of the worst excess [s], or None.
    """

    count: int = 0
    samples: int = 0
    worst_joint: str | None = None
    worst_excess: float = 0.0
    worst_time: float | None = None

    def describe(self) -> str:
        if not self.count:
            return "no position-limit violations"
        return (
            f"{self.count} position-limit violations in {self.samples} samples; worst: '{safe_name(self.worst_joint)}' "
            f"{self.worst_excess:.3g} outside its limit at t = {self.worst_time:.6g} s"
        )


@dataclass(frozen=True)
class ConstraintRecord:
    """One holonomic constraint of a scene, sampled with the trajectory.

    Attributes:
        force: the constraint force (Lagrange multipliers) in force at each sample [N, N·m], shape (n, rows).
        drift: how far the constraint is violated [m; rad for a weld's rotation], shape (n,).
        velocity_drift: how fast it is violated [m/s; rad/s], shape (n,).
    """

    force: np.ndarray
    drift: np.ndarray
    velocity_drift: np.ndarray


@dataclass
class Trajectory:
    """Samples of a simulation, one row per sample time.

    Attributes:
        t: sample times [s], shape (n,).
        q: configurations, shape (n, nq).
        v: velocities, shape (n, nv).
        tau: torque applied from each sample to the next [N·m, N], shape (n, nv); the last row repeats.
        kinetic_energy, potential_energy, total_energy: T, V, H = T + V [J], shape (n,).
        work: cumulative work done by the torques (and other ledger "work" elements) [J], shape (n,).
        dissipated: cumulative energy removed by damping (and other "dissipated" elements) [J], shape (n,).
        energy_error: H - H(0) - work + dissipated [J], shape (n,): zero for the exact solution; a consistency
            check that does not see phase error.
        ledger: per-element breakdown of work, dissipated and (springs') potential energy.
        constraints: a scene's holonomic constraints: their forces and drift at each sample (empty otherwise).
        limit_violations: position-limit violations at the samples.
        stats: steps, rejected_steps, evaluations (forward dynamics), controller_calls, wall_time [s].
        status: "completed", or why the run stopped early ("diverged", "interrupted", ...).
        metadata: package versions, how the robot was loaded, integrator and options (JSON-serializable).
        contacts: a contact scene's active contacts per sample (points, normals, impulses), else None.
        ctrl: a scene with actuators: the command held from each sample to the next (torques, position or
            velocity targets, per actuator kind), shape (n, nv), tau being the joint torques the actuators delivered
            at each sample; None otherwise (tau is then the command).
        sensors: a scene's sensor readings at each sample, by sensor name, shape (n, components) each (the reading
            each sensor holds at the sample; components named in metadata["sensors"]); empty without sensors.
    """

    t: np.ndarray
    q: np.ndarray
    v: np.ndarray
    tau: np.ndarray
    kinetic_energy: np.ndarray
    potential_energy: np.ndarray
    total_energy: np.ndarray
    work: np.ndarray
    dissipated: np.ndarray
    energy_error: np.ndarray
    ledger: dict[str, LedgerEntry] = field(default_factory=dict)
    constraints: dict[str, ConstraintRecord] = field(default_factory=dict)
    limit_violations: LimitViolations = field(default_factory=LimitViolations)
    stats: dict[str, Any] = field(default_factory=dict)
    status: str = "completed"
    metadata: dict[str, Any] = field(default_factory=dict)
    contacts: Contacts | None = None
    ctrl: np.ndarray | None = None
    sensors: dict[str, np.ndarray] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.t)

    def __repr__(self) -> str:
        span = f"t = {self.t[0]:g}..{self.t[-1]:g} s" if len(self.t) else "empty"
        return f"<Trajectory {len(self)} samples, {span}, status {self.status!r}>"

    def contact_forces(self) -> np.ndarray:
        """Each contact row's mean force over the step that ended at its sample [N], world axes, on the second
        body of its pair, shape (m, 3) (Contacts.impulse over that step: dt, or the last step's shortened length).

        Raises:
            InvalidArgumentError: the trajectory records no contacts, or its metadata no step (options.dt).
        """
        contacts = self.contacts
        if contacts is None:
            raise InvalidArgumentError("the trajectory records no contacts (it is not a run of a scene with contact)")
        options = self.metadata.get("options")
        dt = options.get("dt") if isinstance(options, dict) else None
        if not (isinstance(dt, (int, float)) and not isinstance(dt, bool) and math.isfinite(dt) and dt > 0):
            raise InvalidArgumentError("the trajectory's metadata has no step (options.dt): its forces are unknown")
        t = np.asarray(self.t, dtype=float)[contacts.sample]
        # Steps end on the grid k dt (counted, so t == k * dt exactly) but for the last one, shortened to land on
        # the duration: its length is what lies past the grid point below it.
        k = np.floor(t / dt)
        step = np.where(t == np.round(t / dt) * dt, dt, t - k * dt)
        with np.errstate(over="ignore"):  # an impulse near 1e308 (a forged file) is an infinite force: left to callers
            return np.asarray(contacts.impulse, dtype=float) / step[:, None]

    @property
    def max_abs_energy_error(self) -> float:
        """max |energy_error| over the samples [J] (a chunked run's merge records it, so its mapped arrays are
        not read back)."""
        recorded = self.stats.get("max_abs_energy_error")
        if recorded is not None:
            return float(recorded)
        return _max_abs(self.energy_error)

    def summary(self) -> str:
        """A few lines for people: steps, cost, energies, ledger and limit violations."""
        s = self.stats
        wall = s.get("wall_time", float("nan"))
        sim_time = float(self.t[-1] - self.t[0]) if len(self.t) else 0.0
        rtf = sim_time / wall if wall and wall > 0 else float("inf")
        lines = [
            f"status: {self.status}",
            f"steps: {s.get('steps', 0)}  dynamics evaluations: {s.get('evaluations', 0)}  "
            f"wall time: {wall:.3f} s  real-time factor: {rtf:.1f}x",
        ]
        kernel = self.metadata.get("kernel")
        if isinstance(kernel, str):  # which stepping kernel ran (driver.kernel_name), and why not the native one
            why = self.metadata.get("why_not_native")
            lines.append(f"kernel: {safe_name(kernel)}" + (f" (not native: {safe_name(str(why))})" if why else ""))
        if len(self.t):
            lines += [
                f"energy [J]: T {self.kinetic_energy[0]:.6g} -> {self.kinetic_energy[-1]:.6g}, "
                f"V {self.potential_energy[0]:.6g} -> {self.potential_energy[-1]:.6g}, "
                f"H {self.total_energy[0]:.6g} -> {self.total_energy[-1]:.6g}",
                f"ledger [J]: work {self.work[-1]:.6g}, dissipated {self.dissipated[-1]:.6g}; "
                f"max |energy_error| {self.max_abs_energy_error:.3e}",
            ]
        if s.get("saturated_controls"):
            dofs = s.get("saturated_dofs", {})
            worst = max(dofs, key=dofs.get) if dofs else "?"
            lines.append(
                f"torque saturated at the effort limits in {s['saturated_controls']} of {s.get('controller_calls', 0)} "
                f"controller calls (most often '{safe_name(worst)}')"
            )
        for name, record in self.constraints.items():
            if len(record.drift):
                lines.append(
                    f"constraint '{safe_name(name)}': max drift {_max_abs(record.drift):.3g}, max velocity drift "
                    f"{_max_abs(record.velocity_drift):.3g}, max |force| {_max_abs(record.force):.3g}"
                )
        if "solver_steps" in s:  # the contact time-stepper's cone solver
            unconverged = s.get("solver_unconverged", 0)
            lines.append(
                f"contact solver: {s['solver_steps']} steps with constraints, {s.get('solver_iterations', 0)} "
                f"iterations; {unconverged} unconverged"
                + (" (each continued with the best impulses found)" if unconverged else "")
            )
        lines.append(self.limit_violations.describe())
        return "\n".join(lines)

    def summary_data(self) -> dict[str, Any]:
        """summary() as data, for programs (`run --json` prints it): plain numbers, strings, lists and dicts.

        Keys: status, samples, t_end [s], stats (steps, evaluations, wall_time [s], ...), real_time_factor,
        energy ({kinetic, potential, total}: [first, last] [J]), work, dissipated, max_abs_energy_error [J],
        ledger ({name: {kind, final [J]}}), constraints ({name: {max_drift, max_velocity_drift, max_force}}),
        limit_violations (count, samples, worst_joint, worst_excess, worst_time). Numbers that are not finite
        (an infinite real-time factor) are None, since JSON has no infinity.
        """
        n = len(self.t)
        wall = self.stats.get("wall_time")
        sim_time = float(self.t[-1] - self.t[0]) if n else 0.0
        data: dict[str, Any] = {
            "status": self.status,
            "samples": n,
            "t_end": float(self.t[-1]) if n else None,
            "stats": self.stats,
            "real_time_factor": sim_time / wall if wall else None,
            "energy": None,
            "work": None,
            "dissipated": None,
            "max_abs_energy_error": None,
            "ledger": {},
            "constraints": {},
            "limit_violations": asdict(self.limit_violations),
        }
        if n:
            data["energy"] = {
                name: [float(values[0]), float(values[-1])]
                for name, values in (
                    ("kinetic", self.kinetic_energy),
                    ("potential", self.potential_energy),
                    ("total", self.total_energy),
                )
            }
            data["work"], data["dissipated"] = float(self.work[-1]), float(self.dissipated[-1])
            data["max_abs_energy_error"] = self.max_abs_energy_error
            data["ledger"] = {name: {"kind": e.kind, "final": float(e.energy[-1])} for name, e in self.ledger.items()}
            data["constraints"] = {
                name: {
                    "max_drift": _max_abs(record.drift),
                    "max_velocity_drift": _max_abs(record.velocity_drift),
                    "max_force": _max_abs(record.force),
                }
                for name, record in self.constraints.items()
                if len(record.drift)
            }
        return plain_data(data)

    # ---- tables and notebooks (their code lives in tables.py and viz/notebook.py) -----------------------
    def to_dataframe(self, *, robot: Any = None) -> Any:
        """The samples as a pandas DataFrame, one row per sample, with named columns (pandas: the dataframe extra).

        Columns: t; q.<coordinate> (a free-flyer's <joint>.x .y .z .qx .qy .qz .qw); v.<dof> and tau.<dof> per
        dof name; kinetic_energy, potential_energy, total_energy, work, dissipated, energy_error;
        ledger.<element>; constraint.<name>.force[k], .drift, .velocity_drift; for a contact scene's run
        contact.<body>.normal, .tangential [N] and .count per contact body, and contact.count. See
        multibody_sim.tables.

        Args:
            robot: its Robot, for the coordinate names; None reads them from the metadata.
        """
        from .tables import to_dataframe

        return to_dataframe(self, robot)

    def contacts_dataframe(self) -> Any:
        """The contacts in long form, a pandas DataFrame of one row per contact point per sample: t, sample, body1,
        body2 (the impulse acts on body2), point.x .y .z [m], normal.x .y .z (from body1 to body2), impulse.x .y .z
        [N·s], force.x .y .z [N] (the mean force over the step), normal_force and tangential_force [N]. See
        multibody_sim.tables.

        Raises:
            InvalidArgumentError: the trajectory records no contacts.
        """
        from .tables import contacts_dataframe

        return contacts_dataframe(self)

    def show(
        self, *, robot: Any = None, fps: float = 30.0, speed: float = 1.0, height: int = 480, plot: bool = False
    ) -> None:
        """Display the motion inline in a Jupyter notebook, offline: the HTML export's page in the cell's output.

        Needs the viz extra; see multibody_sim.viz.inline_view for the arguments (robot: its Robot, None loads
        it from the metadata; fps: keyframes per second; speed: initial playback speed; height [px]; plot: the
        energy plot beside the view).
        """
        from .viz.notebook import display, inline_view

        display(inline_view(self, robot=robot, fps=fps, speed=speed, height=height, plot=plot))

    # ---- files ---------------------------------------------------------------------------------------
    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write an .npz of plain arrays plus JSON metadata, atomically (temporary file, then rename).

        Only a regular file is replaced (a symbolic link is written through: the link stays, its target is
        replaced). SIGINT and SIGTERM wait until the file is complete (these samples may exist nowhere else).

        Returns:
            The path given.

        Raises:
            InvalidArgumentError: path is a directory, FIFO, socket or device, or its folder is not writable.
            OSError: the write failed (disk full, a file-size limit): any previous file stays, and no temporary file.
        """
        path = Path(check_path(path, "path", "a trajectory file (.npz)"))
        arrays = {name: np.asarray(getattr(self, name)) for name in ARRAYS}
        if self.ctrl is not None:
            arrays["ctrl"] = np.asarray(self.ctrl)
        for name, entry in self.ledger.items():
            arrays[_LEDGER_PREFIX + name] = np.asarray(entry.energy)
        for name, record in self.constraints.items():
            for part in ("force", "drift", "velocity_drift"):
                arrays[f"{_CONSTRAINT_PREFIX}{name}/{part}"] = np.asarray(getattr(record, part))
        if self.contacts is not None:
            for part in CONTACT_PARTS:
                arrays[_CONTACT_PREFIX + part] = np.asarray(getattr(self.contacts, part))
        for name, readings in self.sensors.items():
            arrays[_SENSOR_PREFIX + name] = np.asarray(readings)
        header = {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "status": self.status,
            "stats": self.stats,
            "ledger_kinds": {name: entry.kind for name, entry in self.ledger.items()},
            "constraints": list(self.constraints),
            "limit_violations": self.limit_violations.__dict__,
            "metadata": self.metadata,
        }
        if self.contacts is not None:
            header["contact_bodies"] = list(self.contacts.bodies)
        if self.sensors:
            header["sensors"] = list(self.sensors)
        arrays["header"] = np.array(json.dumps(header, default=_json_default))
        write_atomically(path, lambda f: np.savez(f, **arrays), mode="finish")  # type: ignore[arg-type]
        return path

    @classmethod
    def load(cls, path: str | os.PathLike[str], *, mmap: bool = False) -> Trajectory:
        """Read a file written by save() (or a chunked run's FILE.npz.parts/ folder); never unpickles anything.

        Args:
            path: FILE.npz, or the FILE.npz.parts/ folder a chunked run left (loaded when FILE.npz is missing).
            mmap: map the arrays from the file instead of reading them (bounded memory for huge runs).

        Raises:
            TrajectoryFileError: the file is missing, truncated, corrupted or not a trajectory.
            InvalidArgumentError: path is not a path, or mmap not True or False.
        """
        path = Path(check_path(path, "path", "a trajectory file (.npz) or a parts folder"))
        check_flag(mmap, "mmap")
        parts = path if path.is_dir() else path.with_name(path.name + PARTS_SUFFIX)
        if path.is_dir() or (not path.exists() and parts.is_dir()):
            return cls._from_parts(parts)
        try:
            with path.open("rb") as f:
                if f.read(4) != b"PK\x03\x04":  # zip's signature: anything else is not an .npz at all
                    raise TrajectoryFileError(f"{path}: not a trajectory file (not an .npz archive)")
            if mmap:
                check_npz(path)  # before mapping what a hostile header claims: safety.py
                contents = _map_npz(path)
            if not mmap or contents is None:  # read_npz checks the archive the same way first
                contents = read_npz(path)
        except TrajectoryFileError:
            raise
        except FileNotFoundError:
            raise TrajectoryFileError(f"{path}: no such trajectory file") from None
        except ARCHIVE_ERRORS as exc:
            raise TrajectoryFileError(f"{path}: not a readable trajectory file ({_first_line(exc)})") from None
        return cls._from_arrays(contents, path)

    @classmethod
    def _from_arrays(cls, contents: dict[str, np.ndarray], path: Path) -> Trajectory:
        header = _read_header(contents, path)
        missing = [name for name in ARRAYS if name not in contents]
        if missing:
            raise TrajectoryFileError(f"{path}: trajectory file lacks arrays: {', '.join(missing)}")
        n = contents["t"].shape[0] if contents["t"].ndim == 1 else -1
        for name in ARRAYS:
            arr = contents[name]
            ndim = 2 if name in _PER_DOF else 1
            if arr.dtype.kind != "f" or arr.ndim != ndim or arr.shape[0] != n:
                raise TrajectoryFileError(
                    f"{path}: array '{name}' has shape {arr.shape} and dtype {arr.dtype}, inconsistent with {n} samples"
                )
        try:  # sample times from a file: finite and increasing (validation.py), or the file is refused
            sample_times(contents["t"], "t")
        except InvalidArgumentError as exc:
            raise TrajectoryFileError(f"{path}: sample times: {exc}") from None
        robot = header["metadata"].get("robot", {})
        for name, size in (("q", "nq"), ("v", "nv"), ("tau", "nv")):
            width = robot.get(size) if isinstance(robot, dict) else None
            if width is not None and contents[name].shape[1:] != (width,):
                raise TrajectoryFileError(
                    f"{path}: array '{name}' has shape {contents[name].shape}, but the metadata's robot has "
                    f"{size} = {printable(repr(width))}"
                )
        ctrl = contents.get("ctrl")
        if ctrl is not None and (ctrl.dtype.kind != "f" or ctrl.shape != contents["tau"].shape):
            raise TrajectoryFileError(
                f"{path}: array 'ctrl' has shape {ctrl.shape} and dtype {ctrl.dtype}, unlike tau's "
                f"{contents['tau'].shape}"
            )
        kinds = header["ledger_kinds"]
        ledger = {}
        for name, kind in kinds.items():
            key = _LEDGER_PREFIX + name
            if key not in contents or contents[key].shape != (n,):
                raise TrajectoryFileError(f"{path}: ledger entry '{printable(name)}' is missing or has the wrong shape")
            ledger[name] = LedgerEntry(kind=kind, energy=contents[key])
        names = header["constraints"]
        constraints = {}
        for name in names:
            parts = [
                contents.get(f"{_CONSTRAINT_PREFIX}{name}/{part}") for part in ("force", "drift", "velocity_drift")
            ]
            force, drift, velocity_drift = parts
            if (
                force is None
                or drift is None
                or velocity_drift is None
                or force.ndim != 2
                or force.shape[0] != n
                or drift.shape != (n,)
                or velocity_drift.shape != (n,)
            ):
                raise TrajectoryFileError(
                    f"{path}: constraint record '{printable(name)}' is missing or has the wrong shape"
                )
            constraints[name] = ConstraintRecord(force, drift, velocity_drift)
        return cls(
            **{name: contents[name] for name in ARRAYS},
            ledger=ledger,
            constraints=constraints,
            limit_violations=LimitViolations(**header["limit_violations"]),
            stats=dict(header["stats"]),
            status=header["status"],
            metadata=dict(header["metadata"]),
            contacts=_read_contacts(contents, header, n, path),
            ctrl=ctrl,
            sensors=_read_sensors(contents, header, n, path),
        )

    @classmethod
    def _from_parts(cls, parts: Path) -> Trajectory:
        """Concatenate a chunked run's parts in memory (a run stopped before merging them), checked first
        (check_parts): a hole, a chunk of another run or a jump back in time is refused, never stitched."""
        pieces = [cls.load(chunk) for chunk in check_parts(parts)]
        joined = cls.concatenate(pieces)
        joined.status = joined.status if joined.status != "running" else "incomplete"
        return joined

    @classmethod
    def concatenate(cls, pieces: list[Trajectory]) -> Trajectory:
        """Consecutive pieces of one run as one trajectory (the last piece's status, stats and metadata)."""
        if not isinstance(pieces, (list, tuple)) or not pieces or not all(isinstance(p, Trajectory) for p in pieces):
            raise InvalidArgumentError(f"pieces must be a non-empty list of Trajectory, got {pieces!r:.80}")
        last = pieces[-1]
        return cls(
            **{name: np.concatenate([getattr(p, name) for p in pieces]) for name in ARRAYS},
            ledger={
                name: LedgerEntry(entry.kind, np.concatenate([p.ledger[name].energy for p in pieces]))
                for name, entry in last.ledger.items()
            },
            constraints={
                name: ConstraintRecord(
                    *(
                        np.concatenate([getattr(p.constraints[name], part) for p in pieces])
                        for part in ("force", "drift", "velocity_drift")
                    )
                )
                for name in last.constraints
            },
            limit_violations=combine_limit_violations([p.limit_violations for p in pieces]),
            stats=last.stats,
            status=last.status,
            metadata={k: v for k, v in last.metadata.items() if k != "chunk"},
            contacts=_joined_contacts(pieces),
            ctrl=np.concatenate([p.ctrl for p in pieces]) if all(p.ctrl is not None for p in pieces) else None,
            sensors={name: np.concatenate([p.sensors[name] for p in pieces]) for name in last.sensors},
        )


def check_trajectory(value: Any, name: str = "trajectory") -> Trajectory:
    """value if it is a Trajectory, else InvalidArgumentError (a file name is not one, nor is a BatchTrajectory:
    batch.element(b) is)."""
    if not isinstance(value, Trajectory):
        hint = f" (load it first: Trajectory.load({value!r}))" if isinstance(value, str) else ""
        raise InvalidArgumentError(f"{name} must be a Trajectory, got {type(value).__name__}{hint}")
    return value


def _read_contacts(contents: dict[str, np.ndarray], header: dict[str, Any], n: int, path: Path) -> Contacts | None:
    """The contacts record of a file (checked: shapes, dtypes, sample indices within the n samples), or None."""
    bodies = header.get("contact_bodies")
    if bodies is None:
        return None
    parts = {part: contents.get(_CONTACT_PREFIX + part) for part in CONTACT_PARTS}
    sample, pair = parts["sample"], parts["pair"]
    if sample is None or pair is None or sample.ndim != 1 or sample.dtype.kind not in "iu":
        raise TrajectoryFileError(f"{path}: the contacts record is missing or malformed")
    m = len(sample)
    shapes_ok = pair.shape == (m, 2) and pair.dtype.kind in "iu"
    for part in ("point", "normal", "impulse"):
        array = parts[part]
        shapes_ok = shapes_ok and array is not None and array.shape == (m, 3) and array.dtype.kind == "f"
    if not shapes_ok:
        raise TrajectoryFileError(f"{path}: the contacts record is missing or malformed")
    if m and (sample.min() < 0 or sample.max() >= n or np.any(np.diff(sample) < 0)):
        raise TrajectoryFileError(f"{path}: the contacts record names samples outside the trajectory's {n}")
    if m and (pair.min() < 0 or pair.max() >= len(bodies)):
        raise TrajectoryFileError(f"{path}: the contacts record names bodies outside its {len(bodies)}")
    return Contacts(list(bodies), *(parts[part] for part in CONTACT_PARTS))  # type: ignore[arg-type]


def _read_sensors(contents: dict[str, np.ndarray], header: dict[str, Any], n: int, path: Path) -> dict[str, np.ndarray]:
    """The sensor readings of a file (checked: one float row per sample each), by name."""
    names = header.get("sensors", [])
    if not isinstance(names, list) or not all(isinstance(name, str) for name in names):
        raise TrajectoryFileError(f"{path}: the sensors record is malformed")
    sensors = {}
    for name in names:
        readings = contents.get(_SENSOR_PREFIX + name)
        if readings is None or readings.dtype.kind != "f" or readings.ndim != 2 or readings.shape[0] != n:
            raise TrajectoryFileError(f"{path}: sensor '{printable(name)}' is missing or has the wrong shape")
        sensors[name] = readings
    return sensors


def _joined_contacts(pieces: list[Trajectory]) -> Contacts | None:
    """The pieces' contacts as one record, sample indices shifted by the samples before each piece."""
    records = [p.contacts for p in pieces]
    if all(r is None for r in records):
        return None
    last = next(r for r in reversed(records) if r is not None)
    offsets = np.cumsum([0] + [len(p.t) for p in pieces[:-1]])
    held = [(r, o) for r, o in zip(records, offsets, strict=True) if r is not None]
    return Contacts(
        list(last.bodies),
        np.concatenate([r.sample + o for r, o in held]),
        *(np.concatenate([getattr(r, part) for r, _ in held]) for part in CONTACT_PARTS[1:]),
    )


_PER_DOF = ("q", "v", "tau")
# What the header's fields must hold (a file from a stranger is read, not trusted): the stats' counters are whole
# numbers, its times and errors numbers; a status is one lowercase word.
_STATS_COUNTS = ("steps", "rejected_steps", "evaluations", "controller_calls", "saturated_controls")
_STATS_NUMBERS = ("wall_time", "max_abs_energy_error")
_STATUS = re.compile(r"[a-z_]{1,40}")
_VIOLATION_FIELDS: dict[str, tuple[tuple[type, ...], str]] = {
    "count": ((int,), "a whole number"),
    "samples": ((int,), "a whole number"),
    "worst_joint": ((str, type(None)), "a joint name or null"),
    "worst_excess": ((int, float), "a number"),
    "worst_time": ((int, float, type(None)), "a number or null"),
}


def _read_header(contents: dict[str, np.ndarray], path: Path) -> dict[str, Any]:
    """The file's JSON header, every field the loader and summary() use checked for its type.

    Raises:
        TrajectoryFileError: no header, a header nested deeper than MAX_JSON_DEPTH (refused before parsing: json
            recurses per level), or a field of the wrong type (one line naming the field).
    """
    try:
        text = str(contents["header"][()])
    except (KeyError, ValueError, TypeError, IndexError):
        raise TrajectoryFileError(f"{path}: not a multibody-sim trajectory (no valid header)") from None
    depth = json_depth(text)
    if depth > MAX_JSON_DEPTH:
        raise TrajectoryFileError(
            f"{path}: refused: its header nests {depth} levels deep, more than the {MAX_JSON_DEPTH} a trajectory "
            "header may"
        )
    try:
        header = json.loads(text)
    except (ValueError, RecursionError):
        raise TrajectoryFileError(f"{path}: not a multibody-sim trajectory (no valid header)") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise TrajectoryFileError(f"{path}: not a multibody-sim trajectory (wrong format tag)")
    if header.get("format_version") != FORMAT_VERSION:
        raise TrajectoryFileError(
            f"{path}: trajectory format version {printable(repr(header.get('format_version')))[:40]} is not "
            f"supported (this version reads {FORMAT_VERSION})"
        )

    def malformed(key: str, expected: str) -> TrajectoryFileError:
        return TrajectoryFileError(f"{path}: malformed {key} in the header (expected {expected})")

    for key in ("stats", "ledger_kinds", "limit_violations", "metadata"):
        header.setdefault(key, {})
        if not isinstance(header[key], dict):
            raise malformed(key, "a JSON object")
    status = header.setdefault("status", "unknown")
    if not isinstance(status, str) or not _STATUS.fullmatch(status):
        raise malformed("status", "one lowercase word such as completed or interrupted")
    stats = header["stats"]
    for key in _STATS_COUNTS:
        if key in stats and not _is_int(stats[key]):
            raise malformed(f"stats.{key}", "a whole number")
    for key in _STATS_NUMBERS:
        if key in stats and not _is_number(stats[key]):
            raise malformed(f"stats.{key}", "a number")
    dofs = stats.get("saturated_dofs", {})
    if not isinstance(dofs, dict) or not all(_is_int(count) for count in dofs.values()):
        raise malformed("stats.saturated_dofs", "an object of whole numbers")
    kinds = header["ledger_kinds"]
    if not all(kind in LEDGER_KINDS for kind in kinds.values()):
        raise malformed("ledger_kinds", ", ".join(LEDGER_KINDS))
    names = header.setdefault("constraints", [])
    if not isinstance(names, list) or not all(isinstance(name, str) for name in names):
        raise malformed("constraints", "a list of names")
    bodies = header.get("contact_bodies")
    if bodies is not None and (not isinstance(bodies, list) or not all(isinstance(name, str) for name in bodies)):
        raise malformed("contact_bodies", "a list of names")
    violations = header["limit_violations"]
    for key, value in violations.items():
        if key not in _VIOLATION_FIELDS:
            raise malformed("limit_violations", f"only the fields {', '.join(_VIOLATION_FIELDS)}")
        types, expected = _VIOLATION_FIELDS[key]
        if isinstance(value, bool) or not isinstance(value, types):
            raise malformed(f"limit_violations.{key}", expected)
    robot = header["metadata"].get("robot", {})
    if isinstance(robot, dict):
        for key in ("nq", "nv"):
            if key in robot and not _is_int(robot[key]):
                raise malformed(f"metadata.robot.{key}", "a whole number")
    return header


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _is_number(value: Any) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


PARTS_SUFFIX = ".parts"
CHUNK_GLOB = "chunk_*.npz"


def chunk_path(out: Path, index: int) -> Path:
    """The file of chunk `index` of a chunked run writing `out`: out.parts/chunk_000000.npz, ..."""
    return out.with_name(out.name + PARTS_SUFFIX) / f"chunk_{index:06d}.npz"


def merge_parts(out: Path, *, status: str, stats: dict[str, Any], limit_violations: LimitViolations) -> Path:
    """Stream a chunked run's parts into one .npz at `out` (atomically), then remove the parts folder.

    The parts are checked first (check_parts). Each array is written chunk after chunk straight into the archive,
    so memory stays bounded by one chunk. SIGINT or SIGTERM during the streaming stops it (the temporary file is
    removed, the parts stay and load); once the file is complete, the rename and the removal of the parts finish
    before the signal is delivered.
    """
    parts = out.with_name(out.name + PARTS_SUFFIX)
    chunks = check_parts(parts)
    with np.load(chunks[-1], allow_pickle=False) as last:
        names = [name for name in last.files if name != "header"]
        header = json.loads(str(last["header"][()]))
    header.update(status=status, stats=stats, limit_violations=limit_violations.__dict__)
    header["metadata"].pop("chunk", None)
    shapes: dict[str, list[tuple[int, ...]]] = {name: [] for name in names}
    for chunk in chunks:
        with np.load(chunk, allow_pickle=False) as npz:
            for name in names:
                shapes[name].append(npz[name].shape)

    largest = [0.0]  # max |energy_error|, found while streaming, recorded in the stats

    def write(f: Any) -> None:
        with zipfile.ZipFile(f, "w", compression=zipfile.ZIP_STORED, allowZip64=True) as archive:
            for name in names:
                shape = (sum(s[0] for s in shapes[name]), *shapes[name][0][1:])
                # The contacts' sample and pair indices stay integers; sample indices count from the run's start.
                integer = name in (_CONTACT_PREFIX + "sample", _CONTACT_PREFIX + "pair")
                dtype = np.dtype(np.int64 if integer else float)
                with archive.open(name + ".npy", "w", force_zip64=True) as member:
                    np.lib.format.write_array_header_2_0(
                        member, {"descr": dtype.str, "fortran_order": False, "shape": shape}
                    )
                    offset = 0
                    for k, chunk in enumerate(chunks):
                        with np.load(chunk, allow_pickle=False) as npz:
                            array = np.ascontiguousarray(npz[name], dtype=dtype)
                            if name == _CONTACT_PREFIX + "sample":
                                array = array + offset
                            member.write(array.tobytes())
                            if name == "energy_error":
                                largest[0] = max(largest[0], _max_abs(npz[name]))
                        offset += shapes["t"][k][0]
            header["stats"] = {**header["stats"], "max_abs_energy_error": largest[0]}
            with archive.open("header.npy", "w") as member:
                np.lib.format.write_array(member, np.array(json.dumps(header, default=_json_default)))

    def remove_parts() -> None:
        for chunk in chunks:
            chunk.unlink()
        parts.rmdir()

    write_atomically(out, write, then=remove_parts)
    return out


def write_chunk(trajectory: Trajectory, out: Path, index: int, *, run_id: str, first_sample: int) -> Path:
    """Write chunk `index` of a chunked run writing `out` (its samples from number `first_sample` on), recording
    the run it belongs to so that check_parts can tell its chunks from a stranger's."""
    trajectory.metadata = {
        **trajectory.metadata,
        "chunk": {"run_id": run_id, "index": index, "first_sample": first_sample},
    }
    return trajectory.save(chunk_path(out, index))


def check_parts(parts: Path) -> list[Path]:
    """A chunked run's chunk files, in order, after checking that they are all there and all of one run.

    Checks the numbering (no hole), the run each chunk records (chunk files of another run are not mixed in), the
    sample counts and that time goes forward from one chunk to the next, from the chunks' headers and times alone.

    Raises:
        TrajectoryFileError: no chunks, a missing chunk (named, with the times it would have covered), a chunk of
            another run, or a chunk that does not continue the previous one.
    """
    files = sorted(parts.glob(CHUNK_GLOB))
    if not files:
        raise TrajectoryFileError(f"{parts}: no trajectory chunks in this folder")
    numbered = {}
    for path in files:
        match = _CHUNK_NAME.fullmatch(path.name)
        if match is None:
            raise TrajectoryFileError(
                f"{parts}: {printable(path.name)} is not a chunk file name (chunk_NNNNNN.npz); move it out of the "
                "folder"
            )
        numbered[int(match.group(1))] = path
    chunks = [numbered[k] for k in sorted(numbered)]
    records = [_chunk_record(path) for path in chunks]
    missing = sorted(set(range(max(numbered) + 1)) - set(numbered))
    if missing:
        after = max((k for k in numbered if k < missing[0]), default=None)
        before = min(k for k in numbered if k > missing[0])
        since = f"t = {records[sorted(numbered).index(after)][3]:.6g} s" if after is not None else "the start"
        until = records[sorted(numbered).index(before)][2]
        names = ", ".join(f"chunk_{k:06d}.npz" for k in missing[:5]) + (", ..." if len(missing) > 5 else "")
        raise TrajectoryFileError(
            f"{parts}: {names} {'is' if len(missing) == 1 else 'are'} missing: the samples from {since} to "
            f"t = {until:.6g} s are lost; load the chunk files one by one (Trajectory.load(chunk))"
        )
    run_id = records[0][0]
    expected_sample, previous_end = 0, -math.inf
    for path, (chunk_run, first_sample, t_first, t_last, n) in zip(chunks, records, strict=True):
        if chunk_run != run_id:
            raise TrajectoryFileError(
                f"{parts}: {path.name} belongs to another run (run {printable(str(chunk_run))[:12]}, not "
                f"{printable(str(run_id))[:12]} of {chunks[0].name}); move it out of the folder"
            )
        if first_sample != expected_sample or not t_first > previous_end:
            raise TrajectoryFileError(
                f"{parts}: {path.name} does not continue the previous chunk (it starts at sample "
                f"{printable(repr(first_sample))[:20]}, t = {t_first:.6g} s; expected sample {expected_sample}, "
                f"after t = {previous_end:.6g} s); move it out of the folder"
            )
        expected_sample, previous_end = expected_sample + n, t_last
    return chunks


_CHUNK_NAME = re.compile(r"chunk_(\d{6})\.npz")


def _chunk_record(path: Path) -> tuple[Any, Any, float, float, int]:
    """(run id, first sample, first time, last time, samples) of a chunk file, from its header and times."""
    check_npz(path)
    try:
        with np.load(path, allow_pickle=False) as npz:
            header = _read_header({"header": npz["header"]}, path)
            t = npz["t"]
    except TrajectoryFileError:
        raise
    except (*ARCHIVE_ERRORS, KeyError) as exc:
        raise TrajectoryFileError(f"{path}: not a readable trajectory file ({_first_line(exc)})") from None
    record = header["metadata"].get("chunk")
    if not isinstance(record, dict) or t.ndim != 1 or not len(t) or t.dtype.kind != "f":
        raise TrajectoryFileError(
            f"{path}: not a chunk of a run (no chunk record in its metadata, or no samples); move it out of the folder"
        )
    return record.get("run_id"), record.get("first_sample"), float(t[0]), float(t[-1]), len(t)


def combine_limit_violations(parts: list[LimitViolations]) -> LimitViolations:
    """The limit violations of consecutive pieces of one run, as one report."""
    worst = max(parts, key=lambda p: p.worst_excess, default=LimitViolations())
    return LimitViolations(
        count=sum(p.count for p in parts),
        samples=sum(p.samples for p in parts),
        worst_joint=worst.worst_joint,
        worst_excess=worst.worst_excess,
        worst_time=worst.worst_time,
    )


def _max_abs(values: np.ndarray, block: int = 1 << 20) -> float:
    """max |values| in blocks, so a memory-mapped array never needs a whole temporary copy."""
    return max((float(np.max(np.abs(values[i : i + block]))) for i in range(0, len(values), block)), default=0.0)


def _map_npz(path: Path) -> dict[str, np.ndarray] | None:
    """Memory-map every member of an uncompressed .npz (None when a member is compressed or not plain data)."""
    contents: dict[str, np.ndarray] = {}
    with zipfile.ZipFile(path) as archive, path.open("rb") as f:
        for info in archive.infolist():
            if info.compress_type != zipfile.ZIP_STORED or not info.filename.endswith(".npy"):
                return None
            f.seek(info.header_offset)
            local = f.read(30)  # the local file header: its name and extra-field lengths locate the data
            name_length = int.from_bytes(local[26:28], "little")
            extra_length = int.from_bytes(local[28:30], "little")
            f.seek(info.header_offset + 30 + name_length + extra_length)
            version = np.lib.format.read_magic(f)
            if version == (1, 0):
                shape, fortran, dtype = np.lib.format.read_array_header_1_0(f)
            else:
                shape, fortran, dtype = np.lib.format.read_array_header_2_0(f)
            name = info.filename[: -len(".npy")]
            if dtype.hasobject:
                return None
            if dtype.kind == "U":  # the JSON header: small, read it whole
                contents[name] = np.frombuffer(f.read(dtype.itemsize * int(np.prod(shape))), dtype=dtype).reshape(shape)
            else:
                order: Literal["F", "C"] = "F" if fortran else "C"
                contents[name] = np.memmap(path, dtype=dtype, mode="r", offset=f.tell(), shape=shape, order=order)
    return contents


def _json_default(value: Any) -> Any:
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    if isinstance(value, Path):
        return str(value)
    raise TypeError(f"cannot store {type(value).__name__} in trajectory metadata")


def _first_line(exc: BaseException) -> str:
    text = str(exc).strip()
    return text.splitlines()[0] if text else type(exc).__name__


def plain_data(value: Any) -> Any:
    """value with numpy scalars and arrays as Python numbers and lists, tuples as lists, and non-finite floats as
    None: what json.dumps(..., allow_nan=False) accepts."""
    if isinstance(value, dict):
        return {str(k): plain_data(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [plain_data(v) for v in value]
    if isinstance(value, np.ndarray):
        return plain_data(value.tolist())
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, (int, np.integer)):
        return int(value)
    if isinstance(value, (float, np.floating)):
        return float(value) if math.isfinite(value) else None
    return value
