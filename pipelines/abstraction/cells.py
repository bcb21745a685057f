"""Subsystem abstraction from data (Algorithm 1, Definition 4.2, Theorem 4.4).

For every triple ``(x̂, û, ŵ)`` the black box is sampled on a sub-grid of the joint cell
``cell(x̂) × cell(ŵ)`` (clipped to the concrete boxes), the growth bound the stage is given
(:class:`~pipelines.abstraction.growth_bound.GrowthBound`) gives a box around the reachable set, and the
successors are the cells the box meets. A triple whose box leaves the state box ``X`` is *blocking*: ``û`` is not
admissible at ``x̂`` under ``ŵ`` (docs/method.md §2). The same samples give the slopes that check the bound's
Lipschitz constants, per entry (docs/method.md §3).

The relation is stored as per-dimension successor index ranges ``[lo, hi]`` and a blocking flag, arrays of
shape ``(n_x, n_u, n_w[, n])`` indexed by the flat cell indices of the three grids. Work is split in chunks
of state cells; :func:`abstract_chunk` computes one chunk and is what a distributed runner maps.

Successor statistics (the report's ``mean_successors``) are exact for the bound that builds the relation and for
``hull``, and for ``lipschitz`` unless the hull builds it. The others are counted on every triple of a scalar
subsystem (the closed-form SCP costs little there) and, for ``dim(x) > 1``, on a fixed sample of the triples
(:func:`statistics_sample`, at most one in eight and small enough that it never costs more than the chosen growth
bound: :func:`~pipelines.abstraction.cost.statistics_fraction`), so their means are estimates and their
``non_blocking`` counts the sample's: the SCP objectives that do not build the relation, and the Lipschitz bound
when the hull does (which reads no centre: the black box is evaluated at the centres of the sample only).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipelines.abstraction.block import abstract_block, chunk_invariants
from pipelines.abstraction.constants import LipschitzMatrix
from pipelines.abstraction.cost import triple_cost
from pipelines.abstraction.growth_bound import GrowthBound, growth_bound, standard_bounds
from pipelines.abstraction.relation import CellsResult, SlopeRecord
from pipelines.network import Subsystem

__all__ = ["BLOCK_POINTS", "CellTask", "abstract_cells", "abstract_chunk", "abstract_live", "bound_of"]

#: Black-box evaluations (samples x triples) per block of :func:`abstract_cells`: a chunk's triples are
#: processed in blocks of about this many evaluations, so the temporaries (a few float64 arrays of this length)
#: stay near the caches and a task's memory is bounded whatever its chunk. Larger blocks crowd the shared L3 when
#: two workers run side by side; smaller ones pay the per-block overhead (two black-box calls and the compiled
#: pass, ~0.05 ms) more often (``bench/run.py --cases workers,floor`` measures both).
BLOCK_POINTS = 1 << 19

def abstract_chunk(
    sub: Subsystem, start: int, stop: int, bound: GrowthBound, *, full_statistics: bool | None = None
) -> CellsResult:
    """Abstract the state cells ``start .. stop-1`` of a subsystem under every input and internal cell.

    Parameters
    ----------
    sub : Subsystem
    start, stop : int
        Flat state-cell range of this chunk.
    bound : GrowthBound
        The growth bound whose successors are returned, with its Lipschitz constants
        (:func:`~pipelines.abstraction.growth_bound.growth_bound` makes the one a spec names). The successors of
        every standard bound under the same constants are counted for the report
        (:func:`~pipelines.abstraction.growth_bound.standard_bounds`).
    full_statistics : bool or None
        The successor counts of ``CellsResult.successors`` are exact for ``bound``, ``lipschitz`` and ``hull``.
        An SCP objective that is not ``bound`` is counted on every triple if ``True``, or on a fixed sample of the
        triples if ``False`` (:func:`statistics_sample` with :func:`~pipelines.abstraction.cost.statistics_fraction`,
        which is :data:`STATISTICS_SAMPLE` for ``dim(x) = 1``): an estimate, with the sample's count of
        non-blocking triples. ``None`` (the default): every triple for ``dim(x) = 1`` (the closed-form SCP costs
        0-3 % of the stage there), the sample otherwise (an LP per triple and row would cost more than the bound).

    Returns
    -------
    CellsResult
        With the largest slopes per entry of the constants (component of the successor, coordinate of ``x`` or
        ``w``) in ``slope_x``, ``slope_w``.

    Notes
    -----
    The chunk's triples ``(x, u, w)``, flat in row-major order over ``(c, n_u, n_w)``, are processed in
    consecutive blocks of about :data:`BLOCK_POINTS` evaluations (:func:`~pipelines.abstraction.block.abstract_block`). Every quantity is
    computed per triple, so blocks give the same bits as one pass; the slope records keep the first largest
    slope, as ``argmax`` over the whole chunk would.
    """
    lo, hi, blocking, successors, slope_x, slope_w = _abstract_at(sub, np.arange(start, stop), bound, full_statistics)
    return CellsResult(start, stop, lo, hi, blocking, successors, slope_x, slope_w)


def _abstract_at(sub: Subsystem, cells: np.ndarray, bound: GrowthBound, full_statistics: bool | None
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict[str, tuple[int, int]], SlopeRecord, SlopeRecord]:
    """:func:`abstract_chunk` of the state cells ``cells`` (flat indices, increasing): ``lo``, ``hi`` of shape
    ``(len(cells), n_u, n_w, n)``, ``blocking``, the successor counts and the slope records."""
    if bound.L_x.shape != (sub.n, sub.n) or bound.L_w.shape != (sub.n, sub.p):
        raise ValueError(f"constants of shapes {bound.L_x.shape} and {bound.L_w.shape} for a subsystem with "
                         f"dim(x) = {sub.n}, dim(w) = {sub.p}")
    xg, ug, wg = sub.state_grid, sub.input_grid, sub.internal_grid
    u_pts, w_lo, w_hi, counts, off_x, ws = chunk_invariants(ug, wg, sub.spec.samples, sub.n)
    c, n_u, n_w = cells.size, u_pts.shape[0], w_lo.shape[0]
    x_lo, x_hi = xg.clipped_cells(xg.unravel(cells))  # (c, n)
    samples = off_x.shape[0] * ws.shape[0]
    B = c * n_u * n_w
    step = max(1, BLOCK_POINTS // samples)
    full = sub.n == 1 if full_statistics is None else full_statistics
    parts = [
        abstract_block(sub, cells, x_lo, x_hi, t0, min(t0 + step, B), bound, full)
        for t0 in range(0, B, step)
    ]
    successors = {
        name: (sum(p.successors[name][0] for p in parts), sum(p.successors[name][1] for p in parts))
        for name in parts[0].successors
    }
    slope_x, slope_w = parts[0].slope_x, parts[0].slope_w
    for p in parts[1:]:
        slope_x, slope_w = slope_x.merge(p.slope_x), slope_w.merge(p.slope_w)
    cshape = (c, n_u, n_w)
    lo = np.concatenate([p.lo for p in parts]).reshape(cshape + (sub.n,))
    hi = np.concatenate([p.hi for p in parts]).reshape(cshape + (sub.n,))
    blocking = np.concatenate([p.blocking for p in parts]).reshape(cshape)
    return lo, hi, blocking, successors, slope_x, slope_w


def bound_of(sub: Subsystem, L_x: float | LipschitzMatrix, L_w: float | LipschitzMatrix, method: str,
             objective: str) -> GrowthBound:
    """The growth bound ``method`` (``objective`` for the SCP) of a subsystem under these constants: a number
    means every entry and the infinity-norm constant."""
    return growth_bound(method, LipschitzMatrix.of(L_x, sub.n, sub.n), LipschitzMatrix.of(L_w, sub.n, sub.p),
                        objective)


def abstract_cells(
    sub: Subsystem,
    start: int,
    stop: int,
    L_x: float | LipschitzMatrix,
    L_w: float | LipschitzMatrix,
    method: str,
    objective: str,
    *,
    full_statistics: bool | None = None,
) -> CellsResult:
    """:func:`abstract_chunk` with the growth bound named as a spec names it (:func:`bound_of`)."""
    return abstract_chunk(sub, start, stop, bound_of(sub, L_x, L_w, method, objective),
                          full_statistics=full_statistics)


@dataclass(frozen=True)
class CellTask:
    """One chunk of Algorithm 1: state cells ``[start, stop)`` of a subsystem under every input and internal cell,
    with the constants and growth bound it is computed with. The unit of work an executor runs
    (:mod:`workers.executors`); :meth:`run` is pure, so a task gives the same bits wherever and however often it
    runs.

    ``L_x``, ``L_w`` are numbers (every entry and the infinity-norm constant) or
    :class:`~pipelines.abstraction.constants.LipschitzMatrix`; ``float()`` of either is the infinity-norm constant.
    :attr:`bound` is the growth bound object the task hands to :func:`abstract_chunk`.
    """

    subsystem: Subsystem
    start: int
    stop: int
    L_x: float | LipschitzMatrix
    L_w: float | LipschitzMatrix
    method: str
    objective: str
    #: Ranges ``[a, b)`` of cells no controller can use (:func:`~pipelines.spec.regions.never_winning`): not sampled.
    dead: tuple[tuple[int, int], ...] = ()

    @property
    def bound(self) -> GrowthBound:
        return bound_of(self.subsystem, self.L_x, self.L_w, self.method, self.objective)

    @property
    def cost(self) -> float:
        """Work of the task in black-box evaluations (:func:`~pipelines.abstraction.cost.triple_cost`)."""
        sub = self.subsystem
        cells = self.stop - self.start - sum(b - a for a, b in self.dead)
        return cells * sub.input_grid.size * sub.n_w_cells * triple_cost(sub, self.method, self.objective)

    @property
    def constants(self) -> tuple[float | LipschitzMatrix, float | LipschitzMatrix, str, str]:
        """What, besides the subsystem, decides the bits of every chunk: ``(L_x, L_w, method, objective)``."""
        return (self.L_x, self.L_w, self.method, self.objective)

    def run(self) -> CellsResult:
        if self.dead:
            return abstract_live(self.subsystem, self.start, self.stop, self.dead, self.bound)
        return abstract_chunk(self.subsystem, self.start, self.stop, self.bound)


def abstract_live(sub: Subsystem, start: int, stop: int, dead: tuple[tuple[int, int], ...],
                  bound: GrowthBound) -> CellsResult:
    """:func:`abstract_chunk` on the cells of ``[start, stop)`` outside the ``dead`` ranges, gathered into one pass
    (the same bits: every quantity is per triple). A dead cell is blocking under every input: that claims no
    transition, and the fixed points never let it in (outside the safe set, inside an avoid set)."""
    n_u, n_w, n = sub.input_grid.size, sub.n_w_cells, sub.n
    c = stop - start
    live = np.ones(c, dtype=bool)
    for a, b in dead:
        live[max(a, start) - start:max(min(b, stop), start) - start] = False
    if not live.any():  # nothing live: no slopes (zero per entry, as a live chunk's records have them), no successors
        zero = [SlopeRecord(0.0, start, 0, 0, ((0.0, start, 0, 0),) * (n * d), (n, d)) if d else
                SlopeRecord(0.0, start, 0, 0) for d in (n, sub.p)]
        return CellsResult(start, stop, np.zeros((c, n_u, n_w, n), dtype=np.int32),
                           np.full((c, n_u, n_w, n), -1, dtype=np.int32), np.ones((c, n_u, n_w), dtype=bool),
                           {b.name: (0, 0) for b in standard_bounds(bound)}, *zero)
    # The live cells in one pass (not one per run between dead cells: a grid's border splits every row)
    lo_, hi_, blocking_, successors, slope_x, slope_w = _abstract_at(sub, start + np.flatnonzero(live), bound, None)
    lo = np.zeros((c, n_u, n_w, n), dtype=np.int32)
    hi = np.full((c, n_u, n_w, n), -1, dtype=np.int32)
    blocking = np.ones((c, n_u, n_w), dtype=bool)
    lo[live], hi[live], blocking[live] = lo_, hi_, blocking_
    return CellsResult(start, stop, lo, hi, blocking, successors, slope_x, slope_w)
