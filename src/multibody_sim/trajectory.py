"""The result of a simulation: sampled states, the energy ledger, limit violations, stats; save and load."""

from __future__ import annotations

import json
import os
import tempfile
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from .exceptions import TrajectoryFileError

FORMAT = "multibody-sim trajectory"
FORMAT_VERSION = 1
_ARRAYS = (
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


@dataclass(frozen=True)
class LedgerEntry:
    """One element of the energy ledger.

    Attributes:
        kind: "work" (energy put in, e.g. by joint torques) or "dissipated" (taken out, e.g. by damping).
        energy: cumulative energy [J] at each sample, shape (n_samples,).
    """

    kind: str
    energy: np.ndarray


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
            f"{self.count} position-limit violations in {self.samples} samples; worst: '{self.worst_joint}' "
            f"{self.worst_excess:.3g} outside its limit at t = {self.worst_time:.6g} s"
        )


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
        ledger: per-element breakdown of work and dissipated.
        limit_violations: position-limit violations at the samples.
        stats: steps, rejected_steps, evaluations (forward dynamics), controller_calls, wall_time [s].
        status: "completed", or why the run stopped early ("diverged", "interrupted", ...).
        metadata: package versions, how the robot was loaded, integrator and options (JSON-serializable).
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
    limit_violations: LimitViolations = field(default_factory=LimitViolations)
    stats: dict[str, Any] = field(default_factory=dict)
    status: str = "completed"
    metadata: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.t)

    def __repr__(self) -> str:
        span = f"t = {self.t[0]:g}..{self.t[-1]:g} s" if len(self.t) else "empty"
        return f"<Trajectory {len(self)} samples, {span}, status {self.status!r}>"

    @property
    def max_abs_energy_error(self) -> float:
        """max |energy_error| over the samples [J]."""
        return float(np.max(np.abs(self.energy_error))) if len(self.t) else 0.0

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
        if len(self.t):
            lines += [
                f"energy [J]: T {self.kinetic_energy[0]:.6g} -> {self.kinetic_energy[-1]:.6g}, "
                f"V {self.potential_energy[0]:.6g} -> {self.potential_energy[-1]:.6g}, "
                f"H {self.total_energy[0]:.6g} -> {self.total_energy[-1]:.6g}",
                f"ledger [J]: work {self.work[-1]:.6g}, dissipated {self.dissipated[-1]:.6g}; "
                f"max |energy_error| {self.max_abs_energy_error:.3e}",
            ]
        lines.append(self.limit_violations.describe())
        return "\n".join(lines)

    # ---- files ---------------------------------------------------------------------------------------
    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write an .npz of plain arrays plus JSON metadata, atomically (temporary file, then rename)."""
        path = Path(path)
        arrays = {name: np.asarray(getattr(self, name)) for name in _ARRAYS}
        for name, entry in self.ledger.items():
            arrays[_LEDGER_PREFIX + name] = np.asarray(entry.energy)
        header = {
            "format": FORMAT,
            "format_version": FORMAT_VERSION,
            "status": self.status,
            "stats": self.stats,
            "ledger_kinds": {name: entry.kind for name, entry in self.ledger.items()},
            "limit_violations": self.limit_violations.__dict__,
            "metadata": self.metadata,
        }
        arrays["header"] = np.array(json.dumps(header, default=_json_default))
        write_atomically(path, lambda f: np.savez(f, **arrays))  # type: ignore[arg-type]
        return path

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> Trajectory:
        """Read a file written by save(); never unpickles anything.

        Raises:
            TrajectoryFileError: the file is missing, truncated, corrupted or not a trajectory.
        """
        path = Path(path)
        try:
            with path.open("rb") as f:
                if f.read(4) != b"PK\x03\x04":  # zip's signature: anything else is not an .npz at all
                    raise TrajectoryFileError(f"{path}: not a trajectory file (not an .npz archive)")
            with np.load(path, allow_pickle=False) as npz:
                contents = {name: npz[name] for name in npz.files}
        except TrajectoryFileError:
            raise
        except FileNotFoundError:
            raise TrajectoryFileError(f"{path}: no such trajectory file") from None
        except (OSError, ValueError, zipfile.BadZipFile, EOFError, KeyError) as exc:
            raise TrajectoryFileError(f"{path}: not a readable trajectory file ({_first_line(exc)})") from None
        return cls._from_arrays(contents, path)

    @classmethod
    def _from_arrays(cls, contents: dict[str, np.ndarray], path: Path) -> Trajectory:
        try:
            header = json.loads(str(contents["header"][()]))
        except (KeyError, ValueError, TypeError):
            raise TrajectoryFileError(f"{path}: not a multibody-sim trajectory (no valid header)") from None
        if not isinstance(header, dict) or header.get("format") != FORMAT:
            raise TrajectoryFileError(f"{path}: not a multibody-sim trajectory (wrong format tag)")
        if header.get("format_version") != FORMAT_VERSION:
            raise TrajectoryFileError(
                f"{path}: trajectory format version {header.get('format_version')!r} is not supported "
                f"(this version reads {FORMAT_VERSION})"
            )
        missing = [name for name in _ARRAYS if name not in contents]
        if missing:
            raise TrajectoryFileError(f"{path}: trajectory file lacks arrays: {', '.join(missing)}")
        n = contents["t"].shape[0] if contents["t"].ndim == 1 else -1
        for name in _ARRAYS:
            arr = contents[name]
            if arr.dtype.kind != "f" or arr.ndim not in (1, 2) or arr.shape[0] != n:
                raise TrajectoryFileError(
                    f"{path}: array '{name}' has shape {arr.shape} and dtype {arr.dtype}, inconsistent with {n} samples"
                )
        kinds = header.get("ledger_kinds", {})
        ledger = {}
        for name, kind in kinds.items():
            key = _LEDGER_PREFIX + name
            if key not in contents or contents[key].shape != (n,):
                raise TrajectoryFileError(f"{path}: ledger entry '{name}' is missing or has the wrong shape")
            ledger[name] = LedgerEntry(kind=kind, energy=contents[key])
        try:
            violations = LimitViolations(**header.get("limit_violations", {}))
        except TypeError:
            raise TrajectoryFileError(f"{path}: malformed limit_violations in the header") from None
        return cls(
            **{name: contents[name] for name in _ARRAYS},
            ledger=ledger,
            limit_violations=violations,
            stats=dict(header.get("stats", {})),
            status=str(header.get("status", "unknown")),
            metadata=dict(header.get("metadata", {})),
        )


def write_atomically(path: Path, write: Any) -> None:
    """Call write(file) on a temporary file beside path, then rename it over path.

    A crash mid-write leaves any previous file at path intact.
    """
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    umask = os.umask(0)  # mkstemp makes 0600 files; a saved trajectory gets the usual permissions
    os.umask(umask)
    os.fchmod(fd, 0o666 & ~umask)
    try:
        with os.fdopen(fd, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


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
