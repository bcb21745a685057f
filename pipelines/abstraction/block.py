"""One block of the per-cell stage (Algorithm 1, Definition 4.2): the black box on the samples of a block of
triples ``(x̂, û, ŵ)``, the growth bounds' boxes, their successor cells and statistics, and the slopes that check
the Lipschitz constants (:mod:`pipelines.abstraction.cells` cuts chunks into blocks and joins them).

Three paths give the same bits: the compiled pass of a scalar subsystem (:func:`compiled.scalar_block`), the
compiled pass of the Lipschitz and hull bounds of any other (:func:`compiled.box_block`), and the growth bound
objects on numpy arrays, the reference both are tested against.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

import pipelines.abstraction.kernels as compiled
from pipelines.abstraction.cost import STATISTICS_SAMPLE, statistics_fraction
from pipelines.abstraction.growth_bound import (
    FP_RTOL,
    SCP_SKIP_RTOL,
    SCP_TIE_RTOL,
    GrowthBound,
    HullBound,
    LipschitzBound,
    SampleBlock,
    ScpBound,
    standard_bounds,
    subgrid_counts,
    widen,
)
from pipelines.abstraction.relation import SlopeRecord
from pipelines.grid import SNAP_RTOL, UniformGrid
from pipelines.network import Subsystem

__all__ = ["STATISTICS_SAMPLE", "abstract_block", "chunk_invariants", "statistics_rows", "statistics_sample",
           "triple_samples"]


def _unit_offsets(counts: tuple[int, ...]) -> np.ndarray:
    """Centres of a regular sub-grid of the unit cube, shape (prod(counts), len(counts)), row-major."""
    if not counts:
        return np.zeros((1, 0))
    axes = [(np.arange(m) + 0.5) / m for m in counts]
    mesh = np.meshgrid(*axes, indexing="ij")
    return np.stack([g.ravel() for g in mesh], axis=-1)


def _axis_slopes(Vg: np.ndarray, axes: range, counts: tuple[int, ...], h: np.ndarray) -> np.ndarray:
    """Largest slope ``|ΔV_i| / h_a`` of each component ``i`` between neighbouring samples along each of the given
    sub-grid axes ``a``: an entry of a matrix of Lipschitz constants.

    Along one axis only one coordinate changes, by ``h_a``, so this is an exact difference quotient of component
    ``i`` along coordinate ``a``; its largest over ``i`` is the one in the infinity norm. For a scalar argument the
    largest slope over all sample pairs is attained by neighbours.

    Parameters
    ----------
    Vg : ndarray, shape (*sub-grid shape, B, n)
        Samples, the sub-grid axes first and the batch next to last.
    axes : range
        Positions of these sub-grid axes in ``Vg``.
    counts : tuple of int
        Their lengths.
    h : ndarray, shape (B, len(counts))
        Sub-cell spacing along each of them.

    Returns
    -------
    slope : ndarray, shape (B, n, len(counts))
    """
    B, n = Vg.shape[-2], Vg.shape[-1]
    best = np.zeros((B, n, len(counts)))
    for a, ax, m in zip(range(len(counts)), axes, counts):
        if m < 2:
            continue
        lead = (slice(None),) * ax
        diff = np.subtract(Vg[lead + (slice(1, None),)], Vg[lead + (slice(None, -1),)])
        np.abs(diff, out=diff)
        d = diff.reshape(-1, B, n).max(axis=0)  # over every sub-grid axis; the batch and components stay
        best[:, :, a] = _slope(d, h[:, a, None])
    return best


def _diagonal_slopes(V: np.ndarray, counts: tuple[int, ...], axes: range, h: np.ndarray) -> np.ndarray:
    """Largest slope ``||ΔV||_∞ / max_a h_a`` between diagonal neighbours of the sub-grid axes ``axes`` (a step of
    one sample along every one of them with at least two points, in every sign pattern; the other axes fixed), per
    triple: what a single constant in the infinity norm must bound beyond the axis-aligned quotients of
    :func:`_axis_slopes` (a map whose norm is ``Σ_j |J_ij|`` shows only ``max_j |J_ij|`` along an axis). Zero with
    fewer than two such axes. One compiled pass over the samples (:func:`compiled.diagonal_pass`).

    Parameters
    ----------
    V : ndarray, shape (S, B, n)
        Samples, row-major over the sub-grid ``counts`` (state axes, then internal-input axes).
    h : ndarray, shape (B, len(axes))
        Sample spacing along ``axes``.

    Returns
    -------
    slope : ndarray, shape (B,)
    """
    moving = [a for a in axes if counts[a] >= 2]
    if len(moving) < 2:
        return np.zeros(V.shape[1])
    best = compiled.diagonal_pass(V, np.asarray(counts, dtype=np.int64), np.asarray(moving, dtype=np.int64))
    return _slope(best, h[:, [a - axes.start for a in moving]].max(axis=1))


#: Samples (``S_x * S_w * B``) up to which :func:`_scalar_sample_pass` works on whole arrays (fewer calls, 2 MB
#: temporaries at most) instead of row by row with small buffers (measured: faster up to about this size).
SMALL_PASS = 1 << 18


def _scalar_sample_pass(V1: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Everything the growth bounds and the slope check need from the samples of a scalar state with at most
    one internal-input sub-grid axis, in one pass over the state samples.

    Parameters
    ----------
    V1 : ndarray, shape (S_x, S_w, B)
        Successor samples (state sample, internal-input sample, triple).

    Returns
    -------
    vmax_w, vmin_w : ndarray, shape (S_x, B)
        Extremes over the internal-input samples at each state sample.
    dx, dw : ndarray, shape (B,)
        Largest ``|ΔV|`` between neighbouring samples along the state axis and along the internal-input axis.

    Notes
    -----
    The same values as :func:`_axis_slopes` and ``max``/``min`` over whole axes (maxima and differences are
    exact, so the order of evaluation does not change a bit), computed on ``(S_w, B)`` rows with small
    reusable buffers: no temporary of the size of the samples (whose first touch costs page faults), and
    reductions straight from each row (reads are cheaper than the writes of ``|.|`` and running maxima).
    """
    Sx, Sw, B = V1.shape

    def largest_abs(diff: np.ndarray) -> np.ndarray:
        # max |diff| over the leading axes as max(max, -min): two reads, no |.| pass (negation is exact)
        flat = diff.reshape(-1, B)
        return np.maximum(flat.max(axis=0), -flat.min(axis=0))

    if V1.size <= SMALL_PASS:  # a few whole-array calls (their temporaries are small)
        dx = largest_abs(V1[1:] - V1[:-1]) if Sx > 1 else np.zeros(B)
        dw = largest_abs(V1[:, 1:] - V1[:, :-1]) if Sw > 1 else np.zeros(B)
        return V1.max(axis=1), V1.min(axis=1), dx, dw
    vmax_w = np.empty((Sx, B))
    vmin_w = np.empty((Sx, B))
    dx = np.zeros(B)
    dw = np.zeros(B)
    buf_x = np.empty((Sw, B))
    buf_w = np.empty((max(Sw - 1, 0), B))
    for k in range(Sx):
        row = V1[k]
        np.max(row, axis=0, out=vmax_w[k])
        np.min(row, axis=0, out=vmin_w[k])
        if k:
            np.subtract(row, V1[k - 1], out=buf_x)
            np.maximum(dx, largest_abs(buf_x), out=dx)
        if Sw > 1:
            np.subtract(row[1:], row[:-1], out=buf_w)
            np.maximum(dw, largest_abs(buf_w), out=dw)
    return vmax_w, vmin_w, dx, dw


def _slope(d: np.ndarray, h: np.ndarray) -> np.ndarray:
    """``d / h``, 0 where ``h = 0`` (a degenerate cell has identical samples: no slope); ``h`` broadcasts."""
    return np.divide(d, h, out=np.zeros_like(d), where=np.broadcast_to(h > 0, d.shape))




def statistics_sample(first_triple: int, count: int, fraction: float = STATISTICS_SAMPLE) -> np.ndarray:
    """Which of the triples ``first_triple .. first_triple + count - 1`` (global flat indices ``(x, u, w)``
    of a subsystem) the sampled statistics use: a fixed hash of the global index below ``fraction``
    (:data:`STATISTICS_SAMPLE` by default), so the sample does not depend on how the cells are chunked.

    Returns
    -------
    ndarray of int64, shape (k,)
        Positions within the range, increasing.
    """
    return statistics_rows(np.arange(first_triple, first_triple + count, dtype=np.uint64), fraction)


def statistics_rows(triples: np.ndarray, fraction: float = STATISTICS_SAMPLE) -> np.ndarray:
    """:func:`statistics_sample` of any global flat triple indices (positions in ``triples`` that the sample
    takes): the same fixed hash, so the sample of a triple never depends on which others are computed with it."""
    t = np.asarray(triples, dtype=np.uint64)
    with np.errstate(over="ignore"):
        hashed = (t * np.uint64(0x9E3779B97F4A7C15)) >> np.uint64(40)  # Fibonacci hashing, top 24 bits
    return np.flatnonzero(hashed < np.uint64(int(fraction * (1 << 24))))


@functools.lru_cache(maxsize=64)
def chunk_invariants(
    ug: UniformGrid, wg: UniformGrid | None, samples: int, n: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, ...], np.ndarray, np.ndarray]:
    """What every chunk of a subsystem samples alike (grids are immutable and hashable), computed once.

    Returns
    -------
    u_pts : (n_u, m) input points; w_lo, w_hi : (n_w, p) clipped internal cells (one empty cell without
    internal inputs); counts : sub-grid points per axis, x then w; off_x : (S_x, n) unit offsets of the state
    samples; ws : (S_w, n_w, p) internal-input samples of every internal cell, sample-major (a block gathers its
    triples' columns into the row-major ``(S_w, B, p)`` it passes to the black box). Read-only arrays.
    """
    p = 0 if wg is None else wg.dim
    u_pts = ug.all_points()
    if wg is None:
        w_lo = w_hi = np.zeros((1, 0))
    else:
        w_lo, w_hi = wg.clipped_cells(wg.unravel(np.arange(wg.size)))
    counts = subgrid_counts(samples, n + p)
    off_x, off_w = _unit_offsets(counts[:n]), _unit_offsets(counts[n:])
    ws = np.ascontiguousarray((w_lo[:, None, :] + off_w[None] * (w_hi - w_lo)[:, None, :]).transpose(1, 0, 2))
    for a in (u_pts, w_lo, w_hi, off_x, ws):
        a.setflags(write=False)
    return u_pts, w_lo, w_hi, counts, off_x, ws


def triple_samples(sub: Subsystem, x_cell: int, u_index: int, w_cell: int
                   ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[int, ...]]:
    """The samples of one triple as :func:`abstract_chunk` draws them, on their joint sub-grid.

    Returns
    -------
    X : ndarray, shape (*counts, n)
    W : ndarray, shape (*counts, p)
    u : ndarray, shape (m,)
    counts : tuple of int
        Sub-grid points per axis, ``x`` then ``w``.
    """
    xg = sub.state_grid
    u_pts, _, _, counts, off_x, ws = chunk_invariants(sub.input_grid, sub.internal_grid, sub.spec.samples, sub.n)
    x_lo, x_hi = xg.clipped_cells(xg.unravel(np.array([x_cell])))  # (1, n)
    xs = x_lo + off_x * (x_hi - x_lo)  # (S_x, n)
    w = ws[:, w_cell]  # (S_w, p)
    Sx, Sw = xs.shape[0], w.shape[0]
    X = np.broadcast_to(xs[:, None, :], (Sx, Sw, sub.n)).reshape(counts + (sub.n,))
    W = np.broadcast_to(w[None], (Sx, Sw, sub.p)).reshape(counts + (sub.p,))
    return X, W, u_pts[u_index], counts


@functools.lru_cache(maxsize=64)
def _grid_arrays(g: UniformGrid) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """``origin, eta, k_lo, shape, lb, ub`` of a grid as the arrays :func:`compiled.scalar_block` takes."""
    f, i = np.float64, np.int64
    return (np.asarray(g.origin, dtype=f), np.asarray(g.eta, dtype=f), np.asarray(g.k_lo, dtype=i),
            np.asarray(g.shape, dtype=i), np.asarray(g.lb, dtype=f), np.asarray(g.ub, dtype=f))


#: Whether :func:`abstract_block` hands the triples of a scalar subsystem (one state dimension, at most one
#: internal-input sample axis) to :func:`compiled.scalar_block` (one compiled pass, 1.5-2.5x faster on the
#: examples) instead of its generic numpy path. The same bits (the tests switch it off to compare); the sampled
#: statistics (``full_statistics=False``) take the generic path.
_USE_SCALAR_KERNEL = True
_NO_W = np.zeros(0)  # the internal-input cells of a subsystem without internal inputs
#: Whether :func:`abstract_block` computes the Lipschitz and hull bounds (and the slopes) of a subsystem that is
#: not scalar in :func:`compiled.box_block` when one of them is the bound; the same bits as the generic numpy path
#: (the tests switch it off to compare).
_USE_BOX_KERNEL = True
_BOX_KERNEL_BOUNDS = (LipschitzBound, HullBound)
_BOX_KERNEL_NAMES = ("lipschitz", "hull")  # compiled.box_block's order

class _Block(NamedTuple):
    """What :func:`abstract_block` gives for its triples (flat, in order); :func:`abstract_chunk` joins them."""

    lo: np.ndarray  # (triples, n) int32; empty range (0, -1) where blocking
    hi: np.ndarray
    blocking: np.ndarray  # (triples,) bool
    successors: dict[str, tuple[int, int]]  # bound name -> (sum of successor counts, non-blocking triples)
    slope_x: SlopeRecord
    slope_w: SlopeRecord


#: The bounds :func:`compiled.scalar_block` computes (by their names in ``compiled.SCALAR_METHODS``).
_KERNEL_BOUNDS = (LipschitzBound, HullBound, ScpBound)


def _cost_names(bound: GrowthBound) -> tuple[str, str]:
    """``(method, objective)`` of a bound as the cost model names them."""
    if isinstance(bound, ScpBound):
        return "scp", bound.objective
    return bound.name, "paper"


def abstract_block(
    sub: Subsystem,
    cells: np.ndarray,
    x_lo: np.ndarray,
    x_hi: np.ndarray,
    t0: int,
    t1: int,
    bound: GrowthBound,
    full_statistics: bool,
) -> _Block:
    """The triples ``t0 .. t1-1`` of the state cells ``cells`` under every input and internal cell (see
    :func:`abstract_chunk`).

    Parameters
    ----------
    cells : ndarray of int, shape (c,)
        Flat state-cell indices, increasing.
    x_lo, x_hi : ndarray, shape (c, n)
        Their clipped cells.
    t0, t1 : int
        Flat triple range within them, row-major over ``(c, n_u, n_w)``.

    Returns
    -------
    _Block
        ``lo``, ``hi`` of shape ``(t1 - t0, n)``, ``blocking`` of shape ``(t1 - t0,)``, the successor counts and
        the slope records of these triples.

    Notes
    -----
    Layout: the samples of the block's triples are evaluated in one call of the black box, ordered with the
    sub-grid axes first and the triples last, ``(S_x, S_w, B)`` row-major, so every reduction over samples
    (extremes, neighbour differences, the SCP's pair maxima) runs over leading axes with the triples on the
    contiguous axis. The arguments are ``(S_x, 1, B, n)``, ``(B, m)`` and ``(S_w, B, p)`` arrays that the black
    box broadcasts (:class:`~pipelines.blackbox.BlackBox`: an expression reads them as views, a
    ``module:function`` gets them copied out to ``(S_x S_w B, d)``).
    """
    n_u, n_w = sub.input_grid.size, sub.n_w_cells
    t = np.arange(t0, t1)
    ci, ui, wi = t // (n_u * n_w), (t // n_w) % n_u, t % n_w  # each triple's state cell, input, internal cell
    xi = cells[ci]  # the state cells' flat indices
    scalar = sub.n == 1 and sub.p <= 1
    # The statistics of the bounds that do not build the relation, on a fixed sample of the triples; the hull
    # reads no centre, so centres are evaluated only where the statistics need them.
    sample = None if full_statistics else statistics_rows((xi * n_u + ui) * n_w + wi,
                                                          statistics_fraction(sub, *_cost_names(bound)))
    centres = sample if sample is not None and type(bound) is HullBound else None
    tr = _sample(sub, ci, xi, ui, wi, x_lo, x_hi, centres)
    if scalar and full_statistics and _USE_SCALAR_KERNEL and type(bound) in _KERNEL_BOUNDS:
        return _scalar_kernel_block(sub, tr, bound)
    return _generic_block(sub, tr, bound, sample, centres is None, scalar)


@dataclass(frozen=True)
class _Triples:
    """The triples of a block (flat, in order), their clipped cells and their successor samples: what every path
    of :func:`abstract_block` reads."""

    xi: np.ndarray  # (B,) flat state cell, input and internal cell of each triple
    ui: np.ndarray
    wi: np.ndarray
    xl: np.ndarray  # (B, n) clipped state cell
    xh: np.ndarray
    wl: np.ndarray  # (B, p) clipped internal-input cell
    wh: np.ndarray
    V: np.ndarray  # (S_x, S_w, B, n) successors of the samples
    C: np.ndarray  # (B, n) successor of each joint cell's centre
    counts_x: tuple[int, ...]  # sub-grid points per state axis, per internal-input axis
    counts_w: tuple[int, ...]

    @property
    def size(self) -> int:
        return int(self.xi.size)

    def record(self, s: np.ndarray, norm: np.ndarray | None = None) -> SlopeRecord:
        """The first largest slope of the block, overall and per entry; ``s`` of shape (B, n, d); ``norm``, shape
        (B,): slopes that count for the overall one only (:func:`_diagonal_slopes`)."""
        xi, ui, wi = self.xi, self.ui, self.wi
        if s.shape[2] == 0:  # no such argument: slope 0 at the first triple, no entries
            return SlopeRecord(0.0, int(xi[0]), int(ui[0]), int(wi[0]))
        overall = s.reshape(s.shape[0], -1).max(axis=1)
        if norm is not None:
            overall = np.maximum(overall, norm)
        k = int(np.argmax(overall))  # the first largest slope, as over the whole chunk
        first = np.argmax(s, axis=0)  # (n, d)
        entries = tuple(
            (float(s[b, i, j]), int(xi[b]), int(ui[b]), int(wi[b]))
            for (i, j), b in np.ndenumerate(first)
        )
        return SlopeRecord(float(overall[k]), int(xi[k]), int(ui[k]), int(wi[k]), entries,
                           (s.shape[1], s.shape[2]))


def _sample(sub: Subsystem, ci: np.ndarray, xi: np.ndarray, ui: np.ndarray, wi: np.ndarray, x_lo: np.ndarray,
            x_hi: np.ndarray, centres: np.ndarray | None) -> _Triples:
    """The black box on the samples of the triples (``ci``: their cells' positions in ``x_lo``, ``x_hi``; ``xi``,
    ``ui``, ``wi``: their flat state cell, input and internal cell; the layout is in :func:`abstract_block`'s
    notes) and on the centres of the triples ``centres`` (positions; ``None``: all; NaN elsewhere); a non-finite
    value names its sample and cell."""
    u_pts, w_lo, w_hi, counts, off_x, ws = chunk_invariants(sub.input_grid, sub.internal_grid, sub.spec.samples,
                                                             sub.n)
    Sx, Sw = off_x.shape[0], ws.shape[0]
    shape = (Sx, Sw, xi.size)

    xl, xh = x_lo[ci], x_hi[ci]  # (B, n)
    xs = xl[None] + off_x[:, None, :] * (xh - xl)[None]  # (Sx, B, n)
    # Each input once per triple and sample axis it varies along; the black box broadcasts them to (Sx, Sw, B).
    X = xs[:, None]  # (Sx, 1, B, n)
    U = u_pts[ui]  # (B, m)
    W = np.take(ws, wi, axis=1)  # (Sw, B, p), row-major (ws[:, wi] is not): so is V (ufuncs follow inputs)

    def where_triple(b: int) -> str:
        return f"state cell {int(xi[b])}, input {int(ui[b])}, internal cell {int(wi[b])}"

    def where_sample(row: int) -> str:
        return where_triple(int(np.unravel_index(row, shape)[2]))

    V = sub.dynamics(X, U, W, describe=where_sample)  # (Sx, Sw, B, n)
    # Centre of the clipped joint cell: Lemma 4.3 and the SCP bound distances from it.
    wl, wh = w_lo[wi], w_hi[wi]  # (B, p)
    at = slice(None) if centres is None else centres

    def where_centre(row: int) -> str:
        return "centre of " + where_triple(int(np.arange(xi.size)[at][row]))

    C = np.full(xl.shape, np.nan)
    C[at] = sub.dynamics((xl[at] + xh[at]) / 2, U[at], (wl[at] + wh[at]) / 2, describe=where_centre)  # (B, n)
    return _Triples(xi, ui, wi, xl, xh, wl, wh, V.reshape(shape + (sub.n,)), C, tuple(counts[:sub.n]),
                    tuple(counts[sub.n:]))


def _scalar_kernel_block(sub: Subsystem, tr: _Triples, bound: GrowthBound) -> _Block:
    """The compiled pass of the standard bounds of a scalar subsystem (:func:`compiled.scalar_block`), under the
    constants of a scalar map: the smaller of entry and norm, which bound the same slope there."""
    p, B = sub.p, tr.size
    L_x = bound.L_x.effective()
    L_w = bound.L_w.effective() if p else 0.0
    Sx, Sw = tr.V.shape[:2]
    lo, hi, blocking, sums, live, sx, sw = compiled.scalar_block(
        tr.V.reshape(Sx, Sw, B), tr.C[:, 0], tr.xl[:, 0], tr.xh[:, 0], tr.wl[:, 0] if p else _NO_W,
        tr.wh[:, 0] if p else _NO_W, float(tr.counts_x[0]), float(tr.counts_w[0]) if p else 1.0, L_x, L_w,
        compiled.SCALAR_METHODS.index(bound.name), _grid_arrays(sub.state_grid), FP_RTOL, SNAP_RTOL, SCP_TIE_RTOL,
        SCP_SKIP_RTOL,
    )
    successors = {name: (int(sums[q]), int(live[q])) for q, name in enumerate(compiled.SCALAR_METHODS)}
    return _Block(lo, hi, blocking, successors, tr.record(sx[:, None, None]),
                  tr.record(sw[:, None, None] if p else np.zeros((B, 1, 0))))


def _generic_block(sub: Subsystem, tr: _Triples, bound: GrowthBound, sample: np.ndarray | None, all_centres: bool,
                   scalar: bool) -> _Block:
    """The growth bound objects on the block (the reference of the compiled passes): the bound itself on every
    triple, then the report's other bounds: on the triples ``sample`` (``None``: all) the SCP objectives that are
    not the bound, and the Lipschitz bound where the centres are not ``all_centres``. Each box is computed per
    triple, so the same bits whichever triples are asked for. The Lipschitz and hull bounds of a subsystem that is
    not scalar, with the slopes, in one compiled pass (:func:`compiled.box_block`) where one of them is the
    bound."""
    xg, n, p, B = sub.state_grid, sub.n, sub.p, tr.size
    cx, cw = tr.counts_x, tr.counts_w
    RX, RW = (tr.xh - tr.xl) / 2, (tr.wh - tr.wl) / 2
    HX = 2 * RX / np.asarray(cx, dtype=float) if n else RX
    HW = 2 * RW / np.asarray(cw, dtype=float) if p else RW
    extremes = None
    if scalar:
        vmax_w, vmin_w, dx, dw = _scalar_sample_pass(tr.V[..., 0])
        extremes = (vmax_w, vmin_w)
    block = SampleBlock(tr.V, tr.C, RX, RW, HX, HW, cx, extremes)

    bounds = standard_bounds(bound)
    rows: dict[str, np.ndarray | None] = {b.name: None for b in bounds}
    for b in bounds[1:]:
        if isinstance(b, ScpBound) or (isinstance(b, LipschitzBound) and not all_centres):
            rows[b.name] = sample
    compiled_pass = not scalar and _USE_BOX_KERNEL and type(bound) in _BOX_KERNEL_BOUNDS
    in_kernel: tuple[str, ...] = ()
    if compiled_pass:  # the Lipschitz bound in the pass only where every centre is there
        in_kernel = _BOX_KERNEL_NAMES if all_centres else ("hull",)
    boxes = {b.name: b.boxes(block, rows[b.name]) for b in bounds if b.name not in in_kernel}
    counted, cells = _count_boxes(xg, boxes)
    if compiled_pass:
        lo, hi, blocking, sums, live, slopes = compiled.box_block(
            np.ascontiguousarray(tr.V.reshape(-1, B, n)), np.ascontiguousarray(tr.C),
            np.ascontiguousarray(bound.lipschitz_radius(block)), np.ascontiguousarray(bound.margin(block, 2)),
            np.asarray(cx + cw, dtype=np.int64), np.ascontiguousarray(np.concatenate([HX, HW], axis=1)),
            _BOX_KERNEL_NAMES.index(bound.name), _BOX_KERNEL_NAMES.index(in_kernel[0]), _grid_arrays(xg), FP_RTOL,
            SNAP_RTOL,
        )
        counted.update({name: (int(sums[q]), int(live[q])) for q, name in enumerate(_BOX_KERNEL_NAMES)
                        if name in in_kernel})
        sx, sw = slopes[:, :, :len(cx)], slopes[:, :, len(cx):]
    else:
        first, last, blocking = cells[bound.name]
        lo = np.where(blocking[:, None], 0, first).astype(np.int32)
        hi = np.where(blocking[:, None], -1, last).astype(np.int32)
        # Slopes for Lipschitz validation (docs/method.md §3), per entry: neighbours along x axes (w fixed) and w
        # axes (x fixed), each component on its own.
        if scalar:
            sx = _slope(dx, HX[:, 0])[:, None, None]
            sw = _slope(dw, HW[:, 0])[:, None, None] if p else np.zeros((B, 1, 0))
        else:
            Vg = tr.V.reshape(cx + cw + (B, n))
            sx = _axis_slopes(Vg, range(len(cx)), cx, HX)
            sw = _axis_slopes(Vg, range(len(cx), len(cx) + len(cw)), cw, HW) if p else np.zeros((B, n, 0))
    norm_x = norm_w = None
    if not scalar:  # a single constant is checked on diagonal neighbours too (one axis each: nothing to add)
        V = tr.V.reshape(-1, B, n)
        if bound.L_x.is_scalar:
            norm_x = _diagonal_slopes(V, cx + cw, range(len(cx)), HX)
        if p and bound.L_w.is_scalar:
            norm_w = _diagonal_slopes(V, cx + cw, range(len(cx), len(cx) + len(cw)), HW)
    order = [m for m in compiled.SCALAR_METHODS if m in counted] + [m for m in counted if m not in
                                                                   compiled.SCALAR_METHODS]
    return _Block(lo, hi, blocking, {name: counted[name] for name in order}, tr.record(sx, norm_x),
                  tr.record(sw, norm_w))


def _cells_of(xg: UniformGrid, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Successor cells of boxes (Definition 4.2): ``first``, ``last`` clipped to the grid, and whether the widened
    box leaves the state box (blocking)."""
    a, b = widen(lo, hi)
    leaves = np.any((a < np.asarray(xg.lb)) | (b > np.asarray(xg.ub)), axis=1)
    first, last = xg.cells_touching(a, b)
    top = np.asarray(xg.shape) - 1
    return np.clip(first, 0, top), np.clip(last, 0, top), leaves


def _count_boxes(xg: UniformGrid, boxes: dict[str, tuple[np.ndarray, np.ndarray]]
                 ) -> tuple[dict[str, tuple[int, int]], dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]]:
    """Per bound: successor cells summed over its non-blocking boxes and their number, and its boxes' cells
    (:func:`_cells_of`); all boxes at once: elementwise, so the same bits as one box at a time."""
    if not boxes:
        return {}, {}
    names = list(boxes)
    sizes = np.cumsum([0] + [boxes[k][0].shape[0] for k in names])
    first, last, leaves = _cells_of(xg, np.concatenate([boxes[k][0] for k in names]),
                                    np.concatenate([boxes[k][1] for k in names]))
    count = np.prod(last - first + 1, axis=1)
    counted, cells = {}, {}
    for name, a, b in zip(names, sizes[:-1], sizes[1:]):
        live = ~leaves[a:b]
        counted[name] = (int(count[a:b][live].sum()), int(live.sum()))
        cells[name] = (first[a:b], last[a:b], leaves[a:b])
    return counted, cells
