"""What a stepping core asks of a kernel: the rows' state (Kernel, every kernel) and, for the loop that runs in
Python, the arithmetic of one step (StepKernel, the row kernel).

The native kernel runs the whole loop in C++ (kernels/native.py's NativeCore.advance), so it is a Kernel and not a
StepKernel: no kernel implements a member it cannot honour.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Protocol

import numpy as np

from ..recording import SampleStore


@dataclass(slots=True)
class KernelAttempt:
    """A step attempted for every running row.

    Attributes:
        error: the scaled error norm (adaptive methods: one row), or None.
        evaluations: evaluations each row's attempt cost, shape (n,) (or an int for every row).
        failures: (j, status, message) of rows whose step failed.
    """

    error: float | None
    evaluations: Any
    failures: list[tuple[int, str, str]]


class Kernel(Protocol):
    """The running rows' states, what Core's own code (records, stops, torques) and the entry points need.

    Rows are named by their position j among the running rows (0 <= j < n); `keep` removes rows.
    """

    @property
    def n(self) -> int:
        """Running rows."""

    @property
    def t(self) -> float:
        """The time of the current state [s]."""

    def start_at(self, t: float) -> None:
        """Continue from time t [s] (set by hand: Stepper.t, a resumed run)."""

    def set_torques(self, TAU: np.ndarray, jump: bool) -> None:
        """Hold TAU (n, nv) from now on; with `jump`, every row restarts its solver state (a new torque)."""

    def keep(self, keep: np.ndarray) -> None:
        """Keep only the rows where `keep` (bool, shape (n,)) is true."""

    def states(self) -> tuple[list[np.ndarray], list[np.ndarray]]:
        """The running rows' current q and v, one array each, which a controller may see but not modify."""

    def flows_of(self, j: int) -> np.ndarray:
        """Row j's cumulative ledger flows [J], shape (n_elements,)."""

    def set_row(self, j: int, q: np.ndarray, v: np.ndarray) -> None:
        """Put row j at (q, v) by hand (a jump: its solver state restarts; its flows stay)."""

    def solver_stats(self, j: int) -> dict[str, int]:
        """Counts row j's solver state keeps (a contact solver's: steps, unconverged steps, iterations), or {}."""

    def write_sample(self, store: SampleStore, i: int, index: Any, js: np.ndarray | None = None) -> None:
        """Write the current state of the running rows (q, v, tau, energies, flows, records) as sample i of the
        store's rows `index` (an int, a slice or row indices), or of the rows at positions js only."""

    def snapshot(self) -> Any:
        """Every row's whole state and the time, for restore() (Stepper's undo point before each step)."""

    def restore(self, snapshot: Any) -> None:
        """Return to `snapshot` (the latest one taken)."""


class StepKernel(Kernel, Protocol):
    """A Kernel whose steps Core.advance takes one at a time: the arithmetic of one step for the running rows."""

    def attempt(self, h: float) -> KernelAttempt:
        """Attempt a step of h from the current state of every row (the result is kept as pending)."""

    def nonfinite(self) -> np.ndarray:
        """Rows (indices) whose pending state is not finite."""

    def nonfinite_dof(self, j: int) -> int:
        """The first velocity coordinate of row j's pending state that is not finite."""

    def accept(self, t_next: float) -> None:
        """The pending state becomes the current one, at time t_next (one assignment: never half done)."""

    def reject(self) -> None:
        """Drop the pending state; keep what the attempt learned of the step's start (its retry state)."""

    def write_dense(self, store: SampleStore, i: int, index: Any, theta: float, h: float, t_out: float) -> int:
        """Write the pending step's dense output at t + θh (= t_out) as sample i; returns the evaluations it cost."""
