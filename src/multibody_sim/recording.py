"""Where a run's samples go: the sample store the stepping core writes, and the trajectory built from it.

Rows of a run share their sample times (they step together) and are indexed sample first: ``Q[i, b]`` is row b's
configuration at sample i. The memory behind is batch-major (row b's samples are one block, as a BatchTrajectory and
a Trajectory hold them), so results are views of it, not reordered copies. A row that stopped early simply has fewer
samples (``n_samples[b]``).
"""

from __future__ import annotations

import functools
import math
from typing import Any

import numpy as np

from .safety import check_allocation, memory_room
from .trajectory import ConstraintRecord, Contacts, LedgerEntry, LimitViolations, Trajectory

# Counters kept per sample and row, so that a run truncated at a sample reports the counts it had there.
COUNTERS = ("steps", "rejected_steps", "evaluations")
# The store's arrays (SampleStore's attributes of these names), in the order the native kernel takes them.
STORE_ARRAYS = ("T", "Q", "V", "TAU", "ENERGY", "FLOWS", "COUNTS", "EXTRA")

# A row's contacts as written at once (one sample by the Python kernel, an engine call's samples by the native one):
# the sample indices written (w,) [int64] (a written sample without contacts has none), each contact row's sample
# (k,) [int64] and the rows (k, 11) of pair (2), point (3), normal (3), impulse (3). A later chunk that writes a
# sample again replaces what earlier chunks held for it.
ContactChunk = tuple[np.ndarray, np.ndarray, np.ndarray]


def contacts_at(chunks: list[ContactChunk], i: int) -> np.ndarray | None:
    """Sample i's contact rows (k, 11) from a row's chunks (the last chunk that wrote i), None without contacts."""
    for written, sample, rows in reversed(chunks):
        if np.any(written == i):
            held = rows[sample == i]
            return held if len(held) else None
    return None


def kept_contacts(chunks: list[ContactChunk], n: int) -> tuple[np.ndarray, np.ndarray]:
    """The contact rows of samples 0..n-1 from a row's chunks, in sample order (each sample's rows as written by the
    last chunk that wrote it): (sample (k,) [int64], rows (k, 11))."""
    sample, blocks = _kept_blocks(chunks, n)
    return sample, np.concatenate(blocks).reshape(-1, 11)


def _kept_blocks(chunks: list[ContactChunk], n: int) -> tuple[np.ndarray, list[np.ndarray]]:
    """kept_contacts' rows as blocks (k_i, 11) to be concatenated, with their samples (k,) [int64]: the chunks' own
    rows where every row is kept in order (a native run's chunks: each writes samples after the last one's), so that
    a caller copies each row once."""
    if not chunks:
        return np.zeros(0, dtype=np.int64), [np.zeros((0, 11))]
    sample = np.concatenate([s for _, s, _ in chunks]).astype(np.int64, copy=False)
    if _in_order(chunks, n):
        return sample, [r.reshape(-1, 11) for _, _, r in chunks]
    last = np.full(n, -1, dtype=np.int64)  # per sample, the last chunk that wrote it
    for c, (written, _, _) in enumerate(chunks):
        last[written[written < n]] = c
    origin = np.repeat(np.arange(len(chunks)), [len(s) for _, s, _ in chunks])
    rows = np.concatenate([r for _, _, r in chunks]).reshape(-1, 11)
    keep = sample < n
    keep[keep] = last[sample[keep]] == origin[keep]
    if keep.all() and np.all(sample[1:] >= sample[:-1]):  # nothing written again, in order: the arrays as they are
        return sample, [rows]
    order = np.argsort(sample[keep], kind="stable")
    return sample[keep][order], [rows[keep][order]]


def _in_order(chunks: list[ContactChunk], n: int) -> bool:
    """Whether every row of the chunks is kept, in the order written: each chunk's written samples increase and
    follow the previous chunk's, and its rows' samples, in order, are among them and below n (checked chunk by chunk:
    no temporary the size of the whole record)."""
    previous = -1
    for written, sample, _ in chunks:
        if not len(written):
            if len(sample):
                return False
            continue
        if written[0] <= previous or (len(written) > 1 and not np.all(written[1:] > written[:-1])):
            return False
        previous = int(written[-1])
        if not len(sample):
            continue
        if sample[-1] >= n or (len(sample) > 1 and not np.all(sample[1:] >= sample[:-1])):
            return False
        at = np.searchsorted(written, sample)
        if at[-1] >= len(written) or not np.array_equal(written[at], sample):
            return False
    return True


def _block(shapes: dict[str, tuple[int, ...]], dtypes: dict[str, Any]) -> dict[str, np.ndarray]:
    """Zero arrays of these shapes (float64 unless `dtypes` names another 8-byte type), C-ordered, each a view of
    one block of memory at a 64-byte boundary.

    One block rather than an array each: a run's store is then one allocation, which the C library keeps and hands
    out again from one run to the next, where arrays of a few hundred KiB to a few MiB each are returned to the
    system and their pages faulted in afresh by every run (go2_standing with actuators and sensors: ~1000 page
    faults, ~0.3 µs a step, measured with getrusage in scripts/bench_sensors.py's pattern of runs)."""
    sizes = {name: 8 * math.prod(shape) for name, shape in shapes.items()}
    starts, total = {}, 0
    for name, size in sizes.items():
        starts[name] = total
        total += -(-size // 64) * 64
    memory = np.zeros(total + 64, dtype=np.uint8)
    skip = -memory.ctypes.data % 64
    return {
        name: memory[skip + starts[name] : skip + starts[name] + sizes[name]]
        .view(dtypes.get(name, np.float64))
        .reshape(shape)
        for name, shape in shapes.items()
    }


class SampleStore:
    """Growable per-sample arrays for B rows.

    Running rows record together, so they hold the same number of samples, `count`; a row that stops keeps what
    it has (and may take one last sample of its own at index `count`: its state before a failed step).

    Attributes:
        count: samples held by each running row (the next sample goes to index count).
        soft_capacity: when count reaches it the stepping core returns (`full`), so that the driver can check, flush
            or grow the store (the store itself grows past it if a step needs room for more samples).
        T: sample times [s], shape (capacity, B); Q, V, TAU: (capacity, B, nq / nv / nv); ENERGY: (capacity, B, 2)
            kinetic and potential energy [J]; FLOWS: (capacity, B, n_elements) cumulative ledger flows [J]; EXTRA:
            (capacity, B, extra_width) what the system records per sample; COUNTS: (capacity, B, 3) steps, rejected
            steps and evaluations when the sample was taken. Each is a view (axes 0 and 1 swapped) of a C-ordered
            batch-major array of shape (B, capacity, ...), which batch_major() gives (the native kernel writes those).
        batch_arrays: those batch-major arrays, in STORE_ARRAYS' order.
    """

    def __init__(
        self, B: int, nq: int, nv: int, n_elements: int, extra_width: int, capacity: int, sensor_width: int = 0
    ):
        self.B, self._shapes = B, (nq, nv, n_elements, extra_width)
        self.sensor_width = sensor_width
        self.sensed = np.zeros(B, dtype=np.int64)  # per row, samples whose SENSORS are written (sensors.Sensing)
        self.count = 0
        self._stopped_samples = np.zeros(B, dtype=int)  # samples of the rows that stopped
        self.running = np.ones(B, dtype=bool)
        self.soft_capacity: float = capacity
        self.full = False
        # A contact run's active contacts: row b -> its ContactChunks in the order written (contacts_at, kept_contacts).
        self.contacts: dict[int, list[ContactChunk]] = {}
        self._allocate(capacity)

    def _allocate(self, capacity: int) -> None:
        """The arrays for `capacity` samples, zeros, as views of one block of memory (see _block)."""
        nq, nv, m, e = self._shapes
        B = self.B
        shapes = {
            "T": (B, capacity),
            "Q": (B, capacity, nq),
            "V": (B, capacity, nv),
            "TAU": (B, capacity, nv),
            "ENERGY": (B, capacity, 2),
            "FLOWS": (B, capacity, m),
            "EXTRA": (B, capacity, e),
            "COUNTS": (B, capacity, len(COUNTERS)),
            "SENSORS": (B, capacity, self.sensor_width),
        }
        self._batch = _block(shapes, {"COUNTS": np.int64})
        self.T, self.Q, self.V, self.TAU, self.ENERGY, self.FLOWS, self.COUNTS, self.EXTRA = (
            np.swapaxes(self._batch[name], 0, 1) for name in STORE_ARRAYS
        )
        self.batch_arrays = tuple(self._batch[name] for name in STORE_ARRAYS)  # (B, capacity, ...) each
        self.SENSORS = np.swapaxes(self._batch["SENSORS"], 0, 1)  # (capacity, B, sensor_width): sensor readings

    def batch_major(self, name: str) -> np.ndarray:
        """The memory behind array `name` (one of STORE_ARRAYS, or SENSORS): shape (B, capacity, ...), C-ordered."""
        return self._batch[name]

    @property
    def capacity(self) -> int:
        return len(self.T)

    @property
    def sample_bytes(self) -> int:
        """Bytes a sample of every row takes in the store."""
        nq, nv, m, e = self._shapes
        return 8 * self.B * (1 + nq + 2 * nv + 2 + m + e + len(COUNTERS) + self.sensor_width)

    @property
    def n_samples(self) -> np.ndarray:
        """Samples held per row, shape (B,); row b's are the first n_samples[b]."""
        return np.where(self.running, self.count, self._stopped_samples)

    def samples_of(self, b: int) -> int:
        return self.count if self.running[b] else int(self._stopped_samples[b])

    def room(self, extra: int = 1) -> int:
        """The index of the next sample of the running rows, growing the arrays if `extra` samples do not fit."""
        i = self.count
        if i + extra > self.capacity:
            capacity = 2 * i + 16 + extra
            # The new arrays, and room left to assemble the samples into a trajectory at the end: a run that stops
            # here for want of memory can still keep every sample it has.
            needed = 2 * capacity * self.sample_bytes
            room = memory_room()
            if needed > room.bytes:
                raise MemoryError(
                    f"{capacity} samples would need {needed / 2**30:.3g} GiB, more than the {room.bytes / 2**30:.3g} "
                    f"GiB available ({room.limit})"
                )
            old = {name: getattr(self, name) for name in (*STORE_ARRAYS, "SENSORS")}
            self._allocate(capacity)
            n = min(i + 1, len(old["T"]))  # stopped rows may hold a last sample at index i
            for name, array in old.items():
                getattr(self, name)[:n] = array[:n]
        return i

    def advance(self) -> None:
        """The running rows' sample at index count is written: count it."""
        self.count += 1
        if self.count >= self.soft_capacity:
            self.full = True

    def stop(self, rows: np.ndarray, with_last: bool, *, count: int | None = None) -> None:
        """Rows stop with the samples the running rows hold (and the one at index count too, `with_last`); `count`:
        the running rows' count when they stopped, if not now (the native kernel reports its stops afterwards)."""
        self._stopped_samples[rows] = (self.count if count is None else count) + with_last
        self.running[rows] = False

    def clear(self) -> None:
        """Forget every sample (after they were written to a chunk file)."""
        self.count = 0
        self._stopped_samples[:] = 0
        self.sensed[:] = 0
        self.full = False
        self.contacts = {}

    def make_room(self, capacity: float) -> None:
        """Let the running rows take samples up to `capacity` before the core returns FULL again."""
        self.soft_capacity = capacity
        self.full = self.count >= capacity

    def truncate(self, b: int, n: int) -> None:
        """Row b (stopped) keeps its first n samples."""
        self._stopped_samples[b] = min(int(self._stopped_samples[b]), n)
        self.sensed[b] = min(int(self.sensed[b]), n)
        held = self.contacts.get(b)
        if held:
            self.contacts[b] = [(w[w < n], s[s < n], r[s < n]) for w, s, r in held]

    def write_contacts(self, i: int, b: int, rows: np.ndarray | None) -> None:
        """Row b's active contacts at sample i: (k, 11) rows of pair (2), point (3), normal (3), impulse (3)."""
        rows = np.empty((0, 11)) if rows is None else rows
        self.contacts.setdefault(b, []).append((np.array([i]), np.full(len(rows), i), rows))

    def trajectory(
        self,
        b: int,
        *,
        system: Any,
        initial_energy: float,
        status: str,
        stats: dict[str, Any],
        metadata: dict[str, Any],
        copy: bool = True,
    ) -> Trajectory:
        """Row b's samples as a Trajectory (copies), with the ledger, records and limit violations.

        Args:
            initial_energy: H at the run's start [J] (the reference of energy_error; chunks after the first lack it).
            copy: False: views of the store where possible (a run that ran out of memory keeps its samples without
                a second copy of them; the store must not be written to afterwards).
        """
        n = self.samples_of(b)
        elements = system.ledger_elements
        is_work = np.array([kind == "work" for _, kind in elements], dtype=bool)

        def take(array: np.ndarray) -> np.ndarray:
            return array.copy() if copy else array

        t = take(self.T[:n, b])
        Q = take(self.Q[:n, b])
        kinetic, potential = take(self.ENERGY[:n, b, 0]), take(self.ENERGY[:n, b, 1])
        flows = self.FLOWS[:n, b]
        ledger = {name: LedgerEntry(kind, take(flows[:, j])) for j, (name, kind) in enumerate(elements)}
        potentials, constraints = split_records(system.record_fields, self.EXTRA[:n, b], copy=copy)
        ledger.update(potentials)
        delivered = delivered_torques(system.record_fields, self.EXTRA[:n, b], copy=copy)
        work, dissipated = ledger_sums(flows, is_work)
        total = kinetic + potential
        return Trajectory(
            t=t,
            q=Q,
            v=take(self.V[:n, b]),
            tau=take(self.TAU[:n, b]) if delivered is None else delivered,
            ctrl=None if delivered is None else take(self.TAU[:n, b]),
            kinetic_energy=kinetic,
            potential_energy=potential,
            total_energy=total,
            work=work,
            dissipated=dissipated,
            energy_error=total - initial_energy - work + dissipated,
            ledger=ledger,
            constraints=constraints,
            limit_violations=find_limit_violations(system, t, Q),
            stats=stats,
            status=status,
            metadata=metadata,
            contacts=self.contacts_record(b, n, system),
            sensors=sensor_arrays(system, self.SENSORS[:n, b], copy=copy),
        )

    def contacts_record(self, b: int, n: int, system: Any) -> Contacts | None:
        """Row b's contacts over its first n samples as a Contacts record (None without contact)."""
        contact = getattr(system, "contact", None)
        if contact is None:
            return None
        sample, blocks = _kept_blocks(self.contacts.get(b, []), n)
        if not len(sample):
            return Contacts.empty(contact.body_names)

        def part(start: int, stop: int, dtype: Any = float) -> np.ndarray:  # columns start..stop-1, copied once
            return np.concatenate([block[:, start:stop] for block in blocks], dtype=dtype, casting="unsafe")

        return Contacts(list(contact.body_names), sample, part(0, 2, np.int64), part(2, 5), part(5, 8), part(8, 11))


def ledger_sums(flows: np.ndarray, is_work: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(work, dissipated): the sums of the ledger's "work" columns of flows (..., m) [J] and of its other columns,
    shape (...) each, bit for bit as ``flows[..., is_work].sum(-1)`` and ``flows[..., ~is_work].sum(-1)`` give them
    (a NaN where theirs is NaN, its sign and payload aside), without their copies of the columns (fresh memory, paid
    for in page faults)."""
    sums = _summer()
    sides = min(int(is_work.sum()), int((~is_work).sum()))
    if sums is not None and flows.flags.c_contiguous and flows[..., 0].size > 1 and sides > 1:
        work, dissipated = np.empty(flows.shape[:-1]), np.empty(flows.shape[:-1])
        sums(flows, np.ascontiguousarray(is_work, dtype=bool), work, dissipated)  # (the same sums in one pass)
        return work, dissipated
    return _columns_sum(flows, is_work), _columns_sum(flows, ~is_work)


@functools.cache
def _summer() -> Any:
    """The extension's ledger_sums (row by row, each side's columns in order from +0.0: _columns_sum's numbers in one
    pass over the flows' memory instead of one per column), or None without it."""
    from . import native  # (the extension loads on first use)

    return native.function("ledger_sums")


def _columns_sum(flows: np.ndarray, mask: np.ndarray) -> np.ndarray:
    # NumPy lays the columns that a boolean mask takes out of the last axis first in memory, and reduces them column
    # by column from its identity +0.0: here, in place. (A single sum, or one column, is reduced as NumPy reduces it.)
    columns = np.flatnonzero(mask).tolist()
    if len(columns) < 2 or flows[..., 0].size <= 1:
        return flows[..., mask].sum(axis=-1)
    total = np.add(flows[..., columns[0]], 0.0)
    for j in columns[1:]:
        total += flows[..., j]
    return total


def split_records(
    record_fields: tuple[tuple[str, str, int], ...], extra: np.ndarray, *, copy: bool = True
) -> tuple[dict[str, LedgerEntry], dict[str, ConstraintRecord]]:
    """A system's per-sample records (the last axis of `extra`, shape (..., Σ widths), as Robot.unchecked_record
    writes them) as the Trajectory's ledger potentials and constraint records, with extra's leading axes: copies, or
    (copy=False) views of extra."""

    def take(block: np.ndarray) -> np.ndarray:
        return block.copy() if copy else block

    potentials, constraints = {}, {}
    column = 0
    for category, name, width in record_fields:
        block = extra[..., column : column + width]
        column += width
        if category == "potential":
            potentials[name] = LedgerEntry("potential", take(block[..., 0]))
        elif category == "constraint":  # the forces, then the drift and the velocity drift
            constraints[name] = ConstraintRecord(take(block[..., :-2]), take(block[..., -2]), take(block[..., -1]))
    return potentials, constraints


def delivered_torques(
    record_fields: tuple[tuple[str, str, int], ...], extra: np.ndarray, *, copy: bool = True
) -> np.ndarray | None:
    """The joint torques a scene's actuators delivered at each sample (its "torque" record: the trajectory's tau, the
    commands being its ctrl), shape (..., nv): a copy, or (copy=False) a view of extra; None for a system without
    actuators."""
    column = 0
    for category, _, width in record_fields:
        if category == "torque":
            block = extra[..., column : column + width]
            return block.copy() if copy else block
        column += width
    return None


def sensor_width(system: Any) -> int:
    """Components of a system's sensors in all (0 without sensors)."""
    sensors = getattr(system, "sensors", None)
    return 0 if sensors is None else sensors.width


def sensor_arrays(system: Any, readings: np.ndarray, *, copy: bool = True) -> dict[str, np.ndarray]:
    """A system's sensor readings (the last axis of `readings`, shape (..., width)) by sensor name (copies; copy=False:
    views of `readings`), or {} for a system without sensors."""
    sensors = getattr(system, "sensors", None)
    if sensors is None:
        return {}
    views = {name: readings[..., sensors.columns(k)] for k, name in enumerate(sensors.names)}
    return {name: view.copy() for name, view in views.items()} if copy else views


def find_limit_violations(system: Any, t: np.ndarray, Q: np.ndarray) -> LimitViolations:
    """The position-limit report of samples (t, Q): count, worst joint, worst excess and its time."""
    return limit_reports(system, t[None], Q[None], np.array([len(t)]))[0]


def limit_reports(system: Any, T: np.ndarray, Q: np.ndarray, n: np.ndarray) -> list[LimitViolations]:
    """The position-limit report of each row of samples, T (B, N) [s] and Q (B, N, nq), over its first n[b] samples
    (the rows past them must be finite): count, worst joint, worst excess and its time.

    Each row's extreme coordinates pick the (row, coordinate) pairs to look at: Robot.limit_excess at (the lowest,
    the highest) value of a coordinate bounds its excess at every sample (a rounded difference is monotone in each
    operand; the tolerance is least at the start), so no violation is missed, and the other pairs cost two
    reductions. Times count from 0, where every run starts.
    """
    none = LimitViolations()  # frozen: one instance serves every row without violations
    B, N, _ = Q.shape
    if not N or not np.isfinite(system.limit_tolerance).any():  # no sample, or no position limit at all
        return [none] * B
    low, high = _extremes(Q)
    bound = np.maximum(system.lower_limit - low, 0.0) + np.maximum(high - system.upper_limit, 0.0)
    suspect = (bound > system.limit_tolerance) & (n > 0)[:, None]  # (B, nq): may leave its limits in this row
    reports = [none] * B
    # The (row, coordinate) pairs that may leave their limits, row by row (the others' excess is zero throughout):
    # each pair's excess at every sample, then each row's report from its pairs.
    pair_rows, pair_cols = np.nonzero(suspect)
    if not len(pair_rows):
        return reports
    excess = system.limit_excess(Q[pair_rows, :, pair_cols].T, columns=pair_cols, t=T[pair_rows].T).T  # (pairs, N)
    excess[np.arange(N)[None, :] >= n[pair_rows][:, None]] = 0.0  # past a row's samples
    outside = excess > 0
    rows, starts = np.unique(pair_rows, return_index=True)
    counts = np.add.reduceat(outside.sum(axis=1), starts)
    samples = np.logical_or.reduceat(outside, starts, axis=0).sum(axis=1)
    stops = [*starts[1:].tolist(), len(pair_rows)]
    joints = _coordinate_joints(system)
    for b, first, last, count, sampled in zip(
        rows.tolist(), starts.tolist(), stops, counts.tolist(), samples.tolist(), strict=True
    ):
        if not count:
            continue
        block = excess[first:last].T  # (N, its pairs): the first of the largest in sample, then coordinate, order
        i, j = divmod(int(block.argmax()), last - first)
        reports[b] = LimitViolations(
            count=int(count),
            samples=int(sampled),
            worst_joint=joints[int(pair_cols[first + j])],
            worst_excess=float(block[i, j]),
            worst_time=float(T[b, i]),
        )
    return reports


def _extremes(Q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Each row's lowest and highest value of each coordinate over its (finite) samples, Q (B, N, nq) -> (B, nq)
    each: Q.min(axis=1) and Q.max(axis=1) (the same numbers; a zero's sign may differ, which no excess sees), with k
    samples folded into one row of at least 64 numbers first (NumPy's reductions over many short rows cost per row)."""
    B, N, nq = Q.shape
    k = max(1, 64 // max(nq, 1))
    head = N - N % k
    if k == 1 or head == 0:
        return Q.min(axis=1), Q.max(axis=1)
    folded = Q[:, :head].reshape(B, head // k, k * nq)
    low = folded.min(axis=1).reshape(B, k, nq).min(axis=1)
    high = folded.max(axis=1).reshape(B, k, nq).max(axis=1)
    if head < N:
        np.minimum(low, Q[:, head:].min(axis=1), out=low)
        np.maximum(high, Q[:, head:].max(axis=1), out=high)
    return low, high


def _coordinate_joints(system: Any) -> list[str]:
    """The name of the joint of each configuration coordinate, shape (nq,)."""
    model = system.model
    names = [""] * model.nq
    for jid in range(model.njoints - 1, 0, -1):  # the first joint that holds a coordinate names it
        joint = model.joints[jid]
        for j in range(joint.idx_q, joint.idx_q + joint.nq):
            names[j] = model.names[jid]
    return names


def sample_bytes(system: Any, rows: int = 1) -> int:
    """Memory a sample of `rows` rows takes in the store and in the result [bytes]."""
    widths = 12 + system.nq + 3 * system.nv + 2 * len(system.ledger_elements) + 2 * sensor_width(system)
    widths += sum(width for _, _, width in system.record_fields)
    return 8 * widths * rows


def check_memory(n_samples: int, system: Any, rows: int = 1, advice: str | None = None) -> None:
    """Refuse a run whose samples cannot fit in memory, before allocating them (a MemoryError helps no one).

    The room is safety.usable_memory(): the machine's available memory, the address-space limit (RLIMIT_AS) and
    the cgroup's memory limit, whichever is least.
    """
    if rows > 1:  # a rollout: no chunks to stream to
        what = f"this rollout would keep {n_samples:.3g} samples of each of its {rows} elements"
        default = "sample less often (output_dt) or run the batch in smaller parts"
    else:
        what = f"this run would keep {n_samples:.3g} samples"
        default = "sample less often (output_dt) or stream to disk (out= and chunk=; --chunk in the CLI)"
    check_allocation(n_samples * sample_bytes(system, rows), what, advice or default)


def file_bytes(system: Any) -> int:
    """Bytes a sample takes in a trajectory file (t, q, v, tau, five energies, the ledger and the records)."""
    widths = 6 + system.nq + 2 * system.nv + len(system.ledger_elements) + sensor_width(system)
    return 8 * (widths + sum(width for _, _, width in system.record_fields))


def samples_needed(duration: float, period: float) -> int:
    """Samples of a run sampled every `period` over `duration`, plus the first and the last."""
    return math.ceil(duration / period) + 2
