"""The energy monitor: a run's samples checked for blow-up (non-finite energy, an energy error or dissipation far
beyond the run's energy scale), which stops it as diverged."""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from .recording import SampleStore, ledger_sums

# Energy blow-up: |energy_error| beyond this many times the run's energy scale is divergence, not error.
BLOWUP_FACTOR = 1e3


class Monitor:
    """Energy blow-up detection at the samples: a run whose energy becomes non-finite, or whose energy error or
    dissipated energy exceeds BLOWUP_FACTOR times its energy scale, has diverged.

    The scale of a row is T0 + |V0| + the system's natural energy unit (lifting it by one metre); dissipation is
    left out of the bound (a diverging damped mode inflates it without bound, while a real run can only dissipate
    what it had or was given: the scale and the work).
    """

    def __init__(self, system: Any, B: int, systems: list[Any] | None = None):
        self.system = system
        # each row's energy unit (a randomised row's own masses), or the system's for every row
        self.energy_scale: Any = system.energy_scale
        if systems is not None:
            self.energy_scale = np.array([row.energy_scale for row in systems])
        elements = system.ledger_elements
        self.is_work = np.array([kind == "work" for _, kind in elements], dtype=bool)
        self._work_only = bool(self.is_work.all()) and len(self.is_work) == 1
        self._work_index = np.flatnonzero(self.is_work).tolist()
        self._dissipated_index = np.flatnonzero(~self.is_work).tolist()
        self._sides = np.stack([self.is_work, ~self.is_work], axis=1).astype(float)  # (m, 2): Σ work, Σ dissipated
        self.initial = np.zeros(B)  # H at the start [J]
        self.scale = np.zeros(B)
        self.started = np.zeros(B, dtype=bool)
        self.all_started = False

    def start(self, rows: np.ndarray, energies: np.ndarray) -> None:
        """The rows' initial (T, V), shape (n, 2)."""
        self.initial[rows] = energies.sum(axis=1)
        unit = self.energy_scale if np.ndim(self.energy_scale) == 0 else self.energy_scale[rows]
        self.scale[rows] = energies[:, 0] + np.abs(energies[:, 1]) + unit
        self.started[rows] = True
        self.all_started = bool(self.started.all())

    def suspects(self, store: SampleStore, rows: np.ndarray, start: int, limits: np.ndarray) -> np.ndarray:
        """The rows among `rows` that may have a problem among their samples start..limits[j]-1: every row that
        first_problem() would flag, and maybe a few more (judged at half the bound, all rows at once)."""
        stop = int(limits.max(initial=start))
        if stop <= start:
            return rows[:0]
        whole = len(rows) == store.B and (store.B == 1 or bool((rows == np.arange(store.B)).all()))
        index: Any = slice(None) if whole else rows  # every row in order (simulate, a rollout): views, not copies
        E = store.ENERGY[start:stop, index]
        total = E[..., 0] + E[..., 1]
        if self._work_only:  # the ledger's one element: the joint torques' work
            work, dissipated = store.FLOWS[start:stop, index, 0], None
        else:
            # Both sums in one product, without copies of the columns (fresh memory: page faults), rounded otherwise
            # than first_problem's sums (far within the factor 2 kept); a non-finite flow makes both sums, and so the
            # error, non-finite (0 · inf is NaN): the row is then a suspect.
            sums = store.batch_major("FLOWS")[index, start:stop] @ self._sides  # (rows, samples, 2)
            work, dissipated = sums[..., 0].T, sums[..., 1].T
        with np.errstate(over="ignore", invalid="ignore"):
            error = total - self.initial[index] - work
            if dissipated is not None:
                error += dissipated
            bound = np.abs(work)
            bound += self.scale[index]
            bound *= 0.5 * BLOWUP_FACTOR
            bad = np.abs(error) > bound
            bad |= ~np.isfinite(error)  # (a non-finite total makes it so)
            if dissipated is not None:
                bad |= dissipated > bound
        if (limits != stop).any():  # some rows hold fewer samples
            bad &= np.arange(stop - start)[:, None] < limits[None, :] - start
        return rows[bad.any(axis=0)]

    def surely_fine(self, store: SampleStore, b: int, i: int) -> bool:
        """Whether row b's sample i surely has no problem: first_problem's test at half its bound, in Python
        floats (for one sample, NumPy's calls cost more than the arithmetic; the sums' rounding may differ from
        NumPy's, by far less than the factor 2 kept)."""
        kinetic, potential = store.ENERGY[i, b].tolist()
        flows = store.FLOWS[i, b].tolist()
        work = sum([flows[k] for k in self._work_index])
        dissipated = sum([flows[k] for k in self._dissipated_index])
        total = kinetic + potential
        error = total - float(self.initial[b]) - work + dissipated
        bound = 0.5 * BLOWUP_FACTOR * (float(self.scale[b]) + abs(work))
        return math.isfinite(total) and abs(error) <= bound and dissipated <= bound

    def first_problem(self, store: SampleStore, b: int, start: int, stop: int) -> tuple[int, str, bool] | None:
        """(sample index, what, whether the sample is kept) of row b's first problem among samples start..stop-1,
        or None."""
        if stop <= start or (stop == start + 1 and self.surely_fine(store, b, start)):
            return None
        E = store.ENERGY[start:stop, b]
        total = E[:, 0] + E[:, 1]
        work, dissipated = ledger_sums(store.FLOWS[start:stop, b], self.is_work)
        with np.errstate(over="ignore", invalid="ignore"):
            error = total - self.initial[b] - work + dissipated
            bound = BLOWUP_FACTOR * (self.scale[b] + np.abs(work))
        nonfinite = ~np.isfinite(total)
        blown = (np.abs(error) > bound) | (dissipated > bound)
        bad = nonfinite | blown
        if not bad.any():
            return None
        i = int(np.argmax(bad))
        V = store.V[start + i, b]
        fastest = int(np.argmax(np.abs(V)))
        where = f"fastest in '{self.system.dof_names[fastest]}' ({V[fastest]:.3g})"
        if nonfinite[i]:
            return start + i, f"the energy became non-finite, {where}", False
        what = (
            f"the energy error {error[i]:.3g} J"
            if abs(error[i]) > bound[i]
            else f"the dissipated energy {dissipated[i]:.3g} J"
        )
        scale = bound[i] / BLOWUP_FACTOR
        return (
            start + i,
            f"{what} exceeds {BLOWUP_FACTOR:g} times the run's energy scale ({scale:.3g} J), {where}",
            True,
        )
