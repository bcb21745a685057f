"""The relation of one subsystem (Definition 4.2) and the unit of work that computes a part of it.

A subsystem relation is stored as per-dimension successor index ranges ``[lo, hi]`` and a blocking flag, arrays
of shape ``(n_x, n_u, n_w[, n])`` indexed by the flat cell indices of the state, input and internal-input grids
(docs/method.md §2). It is computed in chunks of state cells: a :class:`CellTask` names one chunk and the constants it is
computed with, :func:`pipelines.abstraction.cells.abstract_cells` turns it into a :class:`CellsResult`, and
:func:`assemble` puts the chunks together.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from pipelines.abstraction.constants import LipschitzMatrix
from pipelines.network import Subsystem

METHODS = ("lipschitz", "scp", "scp_radius", "hull")
#: Relative slack when comparing an observed slope with a given Lipschitz constant: slopes are differences
#: of float64 values, and an excess below this is rounding, not evidence.
SLOPE_RTOL = 1e-9
#: Black-box evaluations per chunk when neither the spec nor the caller says (the tasks of a job in one process):
#: a few tenths of a second, so a chunk's store write (a few ms) stays small and threads share the chunks evenly.
DEFAULT_CHUNK_POINTS = 25_000_000


@dataclass(frozen=True)
class SlopeRecord:
    """The largest slopes observed in the data, and where (for Lipschitz validation, docs/method.md §3).

    ``slope`` is the largest over every entry, at the first triple (in the chunk's order) that shows it: the slope
    in the infinity norm that a constant for all components is checked against. ``entries`` holds, per entry
    ``(i, j)`` of a matrix of constants (component ``i`` of the successor, coordinate ``j`` of the argument),
    row-major over ``shape``, its largest slope and the first triple that shows it: ``(slope, x_cell, u_index,
    w_cell)``. An empty ``entries`` records no entries (a marker written before they were recorded).
    """

    slope: float = 0.0
    x_cell: int = -1
    u_index: int = -1
    w_cell: int = -1
    entries: tuple[tuple[float, int, int, int], ...] = ()
    shape: tuple[int, int] = (0, 0)

    def merge(self, other: SlopeRecord) -> SlopeRecord:
        """The records of two parts, ``self`` first: each largest slope kept where it is first seen. Entries are
        kept only if both parts recorded them (otherwise some part's entries are unknown)."""
        best = other if other.slope > self.slope else self
        entries: tuple[tuple[float, int, int, int], ...] = ()
        shape = (0, 0)
        if self.entries and other.entries and self.shape == other.shape:
            entries = tuple(b if b[0] > a[0] else a for a, b in zip(self.entries, other.entries))
            shape = self.shape
        return SlopeRecord(best.slope, best.x_cell, best.u_index, best.w_cell, entries, shape)

    def entry_slopes(self) -> np.ndarray:
        """The largest slope of each entry, shape ``self.shape`` (zeros where none was recorded)."""
        if not self.entries:
            return np.zeros(self.shape)
        return np.array([e[0] for e in self.entries], dtype=float).reshape(self.shape)

    def entry(self, i: int, j: int) -> SlopeRecord:
        """Entry ``(i, j)`` as a record of its own."""
        slope, x, u, w = self.entries[i * self.shape[1] + j]
        return SlopeRecord(slope, x, u, w)

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready: floats survive exactly (``repr`` round-trips float64)."""
        d: dict[str, Any] = {"slope": float(self.slope), "x_cell": int(self.x_cell), "u_index": int(self.u_index),
                             "w_cell": int(self.w_cell)}
        if self.entries:
            d["entries"] = [[float(s), int(x), int(u), int(w)] for s, x, u, w in self.entries]
            d["shape"] = [int(v) for v in self.shape]
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> SlopeRecord:
        entries = tuple((float(s), int(x), int(u), int(w)) for s, x, u, w in d.get("entries", ()))
        shape = tuple(int(v) for v in d.get("shape", (0, 0)))
        return cls(float(d["slope"]), int(d["x_cell"]), int(d["u_index"]), int(d["w_cell"]), entries,
                   (shape[0], shape[1]))


@dataclass(frozen=True)
class CellsResult:
    """One chunk of a subsystem relation: state cells ``[start, stop)`` × all inputs × all internal cells."""

    start: int
    stop: int
    lo: np.ndarray  # (c, n_u, n_w, n) int32; empty range (0, -1) where blocking
    hi: np.ndarray
    blocking: np.ndarray  # (c, n_u, n_w) bool
    # method -> (sum of successor counts, non-blocking triples); for an SCP objective that does not build the
    # relation, over a fixed sample of the triples unless asked for all (see abstract_cells)
    successors: dict[str, tuple[int, int]]
    slope_x: SlopeRecord = field(default_factory=SlopeRecord)
    slope_w: SlopeRecord = field(default_factory=SlopeRecord)


@dataclass(frozen=True)
class SubsystemRelation:
    """The finite abstraction ``f̂`` of one subsystem (Definition 4.2), as interval arrays.

    ``lo[x, u, w, :]`` .. ``hi[x, u, w, :]`` is the per-dimension range of successor cell indices of the
    triple with flat state cell ``x``, input ``u`` and flat internal cell ``w``; ``blocking[x, u, w]`` says the
    input is not admissible there (its range is then empty, ``lo = 0``, ``hi = -1``).
    """

    method: str
    lo: np.ndarray
    hi: np.ndarray
    blocking: np.ndarray
    L_x: float | LipschitzMatrix  # a relation read back from a store has the floats of its report
    L_w: float | LipschitzMatrix

    def successor_ranges(self, x: np.ndarray, u: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Ranges and blocking flags of triples given by flat indices, each shape (B,)."""
        return self.lo[x, u, w], self.hi[x, u, w], self.blocking[x, u, w]


def assemble(results: list[CellsResult], n_x: int, method: str, L_x: float | LipschitzMatrix,
             L_w: float | LipschitzMatrix) -> SubsystemRelation:
    """Put chunk results together in state-cell order."""
    results = sorted(results, key=lambda r: r.start)
    covered = sum(r.stop - r.start for r in results)
    if covered != n_x or any(a.stop != b.start for a, b in zip(results, results[1:])):
        raise RuntimeError(f"chunks cover {covered} of {n_x} state cells")  # a runner bug, not user input
    return SubsystemRelation(
        method,
        np.concatenate([r.lo for r in results]),
        np.concatenate([r.hi for r in results]),
        np.concatenate([r.blocking for r in results]),
        L_x,
        L_w,
    )


#: A subsystem whose per-cell stage costs at least half a task is split into at least this many tasks, so that
#: the two workers of the embedded cluster (and twice as many on a cluster) all get work: an 81 x 81 grid of a
#: 2-D system once became one task while a worker idled.
MIN_TASKS = 4


def default_chunk_cells(sub: Subsystem, target_points: int | None = None) -> int:
    """State cells per chunk when the spec does not say (``options.chunk_cells``).

    A chunk costs about ``target_points`` in units of one black-box evaluation: its triples times
    :func:`~pipelines.abstraction.cost.triple_cost`, which counts the samples, the growth bounds, the SCP's pair
    maxima and LPs and an ODE's integration steps (tasks sized by their real cost, not their evaluations), and a
    subsystem of at least half a task is split into at least :data:`MIN_TASKS`.
    """
    from pipelines.abstraction.cost import triple_cost

    if target_points is None:
        target_points = DEFAULT_CHUNK_POINTS
    n_x = sub.state_grid.size
    # Python integers do not overflow but floats do: a grid of 10^306 cells is a cost refusal, not an OverflowError
    # (the floats may still become inf, which gives one cell per chunk)
    triples = min(sub.input_grid.size * sub.n_w_cells, 10**300)
    per_cell = float(triples) * triple_cost(sub, sub.spec.growth_bound, sub.spec.scp_objective)
    by_cost = max(1, int(target_points // per_cell))
    spread = -(-n_x // MIN_TASKS) if per_cell * min(n_x, 10**300) >= target_points / 2 else n_x
    return max(1, min(by_cost, spread))


def chunk_ranges(sub: Subsystem, chunk_cells: int | None, target_points: int | None = None) -> list[tuple[int, int]]:
    """Split the state cells of a subsystem into chunks of ``chunk_cells`` (by default
    :func:`default_chunk_cells`: a few tenths of a second of work, large enough that per-task overhead is small,
    small enough to bound memory)."""
    n_x = sub.state_grid.size
    if chunk_cells is None:
        chunk_cells = default_chunk_cells(sub, target_points)
    return [(s, min(n_x, s + chunk_cells)) for s in range(0, n_x, chunk_cells)]
