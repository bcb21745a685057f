"""Subsystem abstraction from data (Algorithm 1, Definition 4.2, Theorem 4.4).

For every triple ``(x̂, û, ŵ)`` the black box is sampled on a sub-grid of the joint cell
``cell(x̂) × cell(ŵ)`` (clipped to the concrete boxes), a growth bound gives a box around the reachable set,
and the successors are the cells the box meets. A triple whose box leaves the state box ``X`` is
*blocking*: ``û`` is not admissible at ``x̂`` under ``ŵ`` (METHOD §2).

The relation is stored as per-dimension successor index ranges ``[lo, hi]`` and a blocking flag, arrays of
shape ``(n_x, n_u, n_w[, n])`` indexed by the flat cell indices of the three grids. Work is split in chunks
of state cells; :func:`abstract_cells` computes one chunk and is what a distributed runner maps.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import BlackBoxError
from .growth_bound import (
    lipschitz_radius,
    pair_maxima_scalar,
    scp_parameters_scalar,
    scp_reference,
    scp_rho,
    subgrid_counts,
    widen,
)
from .network import Subsystem

METHODS = ("lipschitz", "scp", "scp_radius", "hull")
#: Relative slack when comparing an observed slope with a given Lipschitz constant: slopes are differences
#: of float64 values, and an excess below this is rounding, not evidence.
SLOPE_RTOL = 1e-9
#: Black-box evaluations per chunk when neither the spec nor the caller says: a few tenths of a second.
DEFAULT_CHUNK_POINTS = 2_000_000


@dataclass(frozen=True)
class SlopeRecord:
    """The largest slope observed in the data, and where (for Lipschitz validation, METHOD §3)."""

    slope: float = 0.0
    x_cell: int = -1
    u_index: int = -1
    w_cell: int = -1

    def merge(self, other: "SlopeRecord") -> "SlopeRecord":
        return other if other.slope > self.slope else self


@dataclass(frozen=True)
class CellsResult:
    """One chunk of a subsystem relation: state cells ``[start, stop)`` × all inputs × all internal cells."""

    start: int
    stop: int
    lo: np.ndarray  # (c, n_u, n_w, n) int32; empty range (0, -1) where blocking
    hi: np.ndarray
    blocking: np.ndarray  # (c, n_u, n_w) bool
    successors: dict[str, tuple[int, int]]  # method -> (sum of successor counts, non-blocking triples)
    slope_x: SlopeRecord = field(default_factory=SlopeRecord)
    slope_w: SlopeRecord = field(default_factory=SlopeRecord)


def _unit_offsets(counts: tuple[int, ...]) -> np.ndarray:
    """Centres of a regular sub-grid of the unit cube, shape (prod(counts), len(counts)), row-major."""
    if not counts:
        return np.zeros((1, 0))
    axes = [(np.arange(m) + 0.5) / m for m in counts]
    mesh = np.meshgrid(*axes, indexing="ij")
    return np.stack([g.ravel() for g in mesh], axis=-1)


def _axis_slopes(V: np.ndarray, axis_offset: int, counts: tuple[int, ...], h: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Largest slope ``||ΔV||_inf / h_a`` between neighbouring samples along each sub-grid axis.

    Along one axis only one coordinate changes, by ``h_a``, so this is an exact difference quotient in the
    infinity norm. For a scalar argument the largest slope over all sample pairs is attained by neighbours.

    Parameters
    ----------
    V : ndarray, shape (B, *sub-grid shape, n)
    axis_offset : int
        Position of the first of these axes among the sub-grid axes.
    h : ndarray, shape (B, len(counts))

    Returns
    -------
    slope : ndarray, shape (B,)
    """
    best = np.zeros(V.shape[0])
    for a, m in enumerate(counts):
        if m < 2:
            continue
        d = np.abs(np.diff(V, axis=1 + axis_offset + a)).max(axis=-1)
        d = d.reshape(V.shape[0], -1).max(axis=1)
        # A degenerate cell (a one-point internal grid) has h = 0 and identical samples: no slope.
        slope = np.divide(d, h[:, a], out=np.zeros_like(d), where=h[:, a] > 0)
        best = np.maximum(best, slope)
    return best


def abstract_cells(
    sub: Subsystem,
    start: int,
    stop: int,
    L_x: float,
    L_w: float,
    method: str,
    objective: str,
) -> CellsResult:
    """Abstract the state cells ``start .. stop-1`` of a subsystem under every input and internal cell.

    Parameters
    ----------
    sub : Subsystem
    start, stop : int
        Flat state-cell range of this chunk.
    L_x, L_w : float
        Lipschitz constants (infinity norm) used by every growth bound.
    method : {'lipschitz', 'scp', 'hull'}
        The growth bound whose successors are returned (all are counted for the report).
    objective : {'paper', 'radius'}
        SCP objective for ``method == 'scp'``.

    Returns
    -------
    CellsResult
    """
    xg, ug, wg = sub.state_grid, sub.input_grid, sub.internal_grid
    n, p = sub.n, sub.p
    x_idx = xg.unravel(np.arange(start, stop))
    x_lo, x_hi = xg.clipped_cells(x_idx)  # (c, n)
    u_pts = ug.all_points()  # (n_u, m)
    if wg is None:
        w_lo = w_hi = np.zeros((1, 0))
    else:
        w_lo, w_hi = wg.clipped_cells(wg.unravel(np.arange(wg.size)))  # (n_w, p)
    c, n_u, n_w = stop - start, u_pts.shape[0], w_lo.shape[0]
    counts = subgrid_counts(sub.spec.samples, n + p)
    cx, cw = counts[:n], counts[n:]
    off_x, off_w = _unit_offsets(cx), _unit_offsets(cw)
    Sx, Sw = off_x.shape[0], off_w.shape[0]

    xs = x_lo[:, None, :] + off_x[None] * (x_hi - x_lo)[:, None, :]  # (c, Sx, n)
    ws = w_lo[:, None, :] + off_w[None] * (w_hi - w_lo)[:, None, :]  # (n_w, Sw, p)
    shape = (c, n_u, n_w, Sx, Sw)
    total = int(np.prod(shape))
    X = np.broadcast_to(xs[:, None, None, :, None, :], shape + (n,)).reshape(total, n)
    U = np.broadcast_to(u_pts[None, :, None, None, None, :], shape + (u_pts.shape[1],)).reshape(total, u_pts.shape[1])
    W = np.broadcast_to(ws[None, None, :, None, :, :], shape + (p,)).reshape(total, p)

    def where_sample(row: int) -> str:
        ci, ui, wi, _, _ = np.unravel_index(row, shape)
        return f"state cell {start + ci}, input {ui}, internal cell {wi}"

    V = sub.dynamics(X, U, W, describe=where_sample).reshape(shape + (n,))

    # Centre of the clipped joint cell: Lemma 4.3 and the SCP bound distances from it.
    xc, wc = (x_lo + x_hi) / 2, (w_lo + w_hi) / 2
    rx, rw = (x_hi - x_lo) / 2, (w_hi - w_lo) / 2
    cshape = (c, n_u, n_w)
    B = c * n_u * n_w
    XC = np.broadcast_to(xc[:, None, None, :], cshape + (n,)).reshape(B, n)
    UC = np.broadcast_to(u_pts[None, :, None, :], cshape + (u_pts.shape[1],)).reshape(B, u_pts.shape[1])
    WC = np.broadcast_to(wc[None, None, :, :], cshape + (p,)).reshape(B, p)

    def where_centre(row: int) -> str:
        ci, ui, wi = np.unravel_index(row, cshape)
        return f"centre of state cell {start + ci}, input {ui}, internal cell {wi}"

    C = sub.dynamics(XC, UC, WC, describe=where_centre)  # (B, n)

    RX = np.broadcast_to(rx[:, None, None, :], cshape + (n,)).reshape(B, n)
    RW = np.broadcast_to(rw[None, None, :, :], cshape + (p,)).reshape(B, p)
    HX = 2 * RX / np.asarray(cx, dtype=float) if n else RX
    HW = 2 * RW / np.asarray(cw, dtype=float) if p else RW
    Vf = V.reshape(B, Sx, Sw, n)

    boxes: dict[str, tuple[np.ndarray, np.ndarray]] = {}
    lip = lipschitz_radius(RX, RW, L_x, L_w)[:, None]
    boxes["lipschitz"] = (C - lip, C + lip)

    rho_h = L_x * np.max(HX, axis=1) / 2 + (L_w * np.max(HW, axis=1) / 2 if p else 0.0)
    vmin = Vf.min(axis=(1, 2))
    vmax = Vf.max(axis=(1, 2))
    boxes["hull"] = (vmin - rho_h[:, None], vmax + rho_h[:, None])

    rho = scp_rho(HX, HW, L_x, L_w)
    for name, weight in (("scp", None), ("scp_radius", RX)):
        if n == 1:
            E = pair_maxima_scalar(Vf[..., 0])  # (B, m_x)
            w1 = np.ones(B) if weight is None else weight[:, 0]
            t1, t2 = scp_parameters_scalar(E, HX[:, 0], rho, L_x, w1)
            rad = (t1 * RX[:, 0] + t2)[:, None]
        else:
            # No batched solver for dim(x) > 1 yet: the reference LP per triple (correct, slow).
            xs_b = np.broadcast_to(xs[:, None, None, :, None, :], shape + (n,)).reshape(B, Sx * Sw, n)
            rad = np.empty((B, n))
            for b in range(B):
                wt = np.ones(n) if weight is None else RX[b]
                th1, th2 = scp_reference(xs_b[b], Vf[b].reshape(-1, n), float(rho[b]), L_x, wt)
                rad[b] = th1 @ RX[b] + th2
        rad = np.minimum(rad, lip)  # both bounds are sound, so is their minimum
        boxes[name] = (C - rad, C + rad)

    X_lb, X_ub = np.asarray(xg.lb), np.asarray(xg.ub)
    successors: dict[str, tuple[int, int]] = {}
    chosen = "scp_radius" if (method == "scp" and objective == "radius") else method
    lo = hi = blocking = None
    for name, (a, b) in boxes.items():
        a, b = widen(a, b)
        block = np.any((a < X_lb) | (b > X_ub), axis=1)
        first, last = xg.cells_touching(a, b)
        first = np.clip(first, 0, np.asarray(xg.shape) - 1)
        last = np.clip(last, 0, np.asarray(xg.shape) - 1)
        count = np.prod(last - first + 1, axis=1)
        successors[name] = (int(count[~block].sum()), int((~block).sum()))
        if name == chosen:
            first = np.where(block[:, None], 0, first)
            last = np.where(block[:, None], -1, last)
            lo = first.astype(np.int32).reshape(cshape + (n,))
            hi = last.astype(np.int32).reshape(cshape + (n,))
            blocking = block.reshape(cshape)

    # Slopes for Lipschitz validation (METHOD §3): neighbours along x axes (w fixed) and w axes (x fixed).
    Vg = V.reshape((B,) + tuple(cx) + tuple(cw) + (n,))
    sx = _axis_slopes(Vg, 0, tuple(cx), HX)
    sw = _axis_slopes(Vg, len(cx), tuple(cw), HW) if p else np.zeros(B)

    def record(s: np.ndarray) -> SlopeRecord:
        k = int(np.argmax(s))
        ci, ui, wi = np.unravel_index(k, cshape)
        return SlopeRecord(float(s[k]), start + int(ci), int(ui), int(wi))

    return CellsResult(start, stop, lo, hi, blocking, successors, record(sx), record(sw))


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
    L_x: float
    L_w: float

    def successor_ranges(self, x: np.ndarray, u: np.ndarray, w: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Ranges and blocking flags of triples given by flat indices, each shape (B,)."""
        return self.lo[x, u, w], self.hi[x, u, w], self.blocking[x, u, w]


def assemble(results: list[CellsResult], n_x: int, method: str, L_x: float, L_w: float) -> SubsystemRelation:
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


def chunk_ranges(sub: Subsystem, chunk_cells: int | None, target_points: int | None = None) -> list[tuple[int, int]]:
    """Split the state cells of a subsystem into chunks.

    By default a chunk holds as many state cells as keep its black-box evaluations near ``target_points``
    (a few tenths of a second of numpy work: large enough that per-task overhead is small, small enough to
    bound memory).
    """
    n_x = sub.state_grid.size
    if target_points is None:
        target_points = DEFAULT_CHUNK_POINTS
    if chunk_cells is None:
        per_cell = sub.input_grid.size * sub.n_w_cells * max(1, sub.spec.samples)
        chunk_cells = max(1, target_points // per_cell)
    return [(s, min(n_x, s + chunk_cells)) for s in range(0, n_x, chunk_cells)]


__all__ = [
    "BlackBoxError",
    "CellsResult",
    "METHODS",
    "SlopeRecord",
    "SubsystemRelation",
    "abstract_cells",
    "assemble",
    "chunk_ranges",
]
