"""Uniform grids of cells (docs/method.md §1), the quantizer ``[X]_eta`` of the paper.

Grid points are ``origin + k * eta`` for integer ``k``; the cell of a point is the closed box
``point ± eta / 2``. A grid keeps the concrete box it was made for, because cells are only ever sampled
where they meet that box (a black box may be undefined outside it, and the concrete system never leaves it).

Indices are zero-based per dimension (``i = k - k_lo``) and flat indices are row-major, like SCOTS's
``UniformGrid``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numba import njit

from pipelines.errors import CompabsError, SpecError

#: A bound, spacing or origin: one number for every dimension, or one per dimension.
Values = float | Sequence[float]

#: Relative tolerance used to snap ratios such as ``(lb - origin) / eta`` to an integer or half-integer.
#: It is relative to the ratio's magnitude, never an absolute ``1e-10``: SCOTS's absolute ``eta/1e10``
#: mis-sizes grids whose bounds are not multiples of ``eta``.
SNAP_RTOL = 1e-9


def _snap(r: np.ndarray) -> np.ndarray:
    """Round ``r`` to the nearest integer where it is within a relative ``SNAP_RTOL`` of it."""
    r = np.asarray(r, dtype=float)
    nearest = np.round(r)
    close = np.abs(r - nearest) <= SNAP_RTOL * np.maximum(1.0, np.abs(r))
    return np.where(close, nearest, r)


#: Indices beyond this are clamped before the cast to int64: a box bound of 1e308 over a spacing of 0.25 is an
#: infinite index, and numpy's cast of ±inf gives -2^63 (an upper end of -2^63 made such a box an empty region).
_INDEX_LIMIT = float(2**62)


def _index(r: np.ndarray) -> np.ndarray:
    """``r`` (whole numbers, possibly ±inf) as int64 indices, clamped to ``±2^62``."""
    return np.clip(r, -_INDEX_LIMIT, _INDEX_LIMIT).astype(np.int64)


@njit(cache=True, nogil=True)
def cell_index(x: float, origin: float, eta: float, k_lo: int, upper: bool) -> np.int64:
    """:meth:`UniformGrid.cell_of`'s index of one coordinate: ``(x - origin) / eta + 0.5`` snapped as :func:`_snap`,
    floored (the upper cell at a tie) or ceiled less one (the lower), clamped as :func:`_index` (NaN to the lower
    clamp: off every grid)."""
    r = (x - origin) / eta + 0.5
    nearest = np.rint(r)
    if abs(r - nearest) <= SNAP_RTOL * max(1.0, abs(r)):
        r = nearest
    k = np.floor(r) if upper else np.ceil(r) - 1.0
    if not k >= -_INDEX_LIMIT:  # NaN too
        k = -_INDEX_LIMIT
    elif k > _INDEX_LIMIT:
        k = _INDEX_LIMIT
    return np.int64(k) - k_lo


@njit(cache=True, nogil=True)
def _cell_of(x: np.ndarray, origin: np.ndarray, eta: np.ndarray, k_lo: np.ndarray, upper: bool,
             idx: np.ndarray) -> None:
    """:func:`cell_index` of every coordinate of the rows ``x`` into ``idx``: one fused loop, where numpy
    expressions' temporaries over 2·10^6 rows of 100 coordinates were most of an audit."""
    B, d = x.shape
    for b in range(B):
        for j in range(d):
            idx[b, j] = cell_index(x[b, j], origin[j], eta[j], k_lo[j], upper)


def _as_vector(value: Values, dim: int, name: str) -> np.ndarray:
    arr = np.atleast_1d(np.asarray(value, dtype=float))
    if arr.shape == (1,) and dim > 1:
        arr = np.repeat(arr, dim)
    if arr.shape != (dim,):
        raise SpecError(f"{name} has {arr.size} components, expected {dim}")
    if not np.all(np.isfinite(arr)):
        raise SpecError(f"{name} must be finite, got {arr.tolist()}")
    return arr


@dataclass(frozen=True)
class UniformGrid:
    """A product of uniform 1-D grids, restricted to the cells that matter for a concrete box.

    Parameters
    ----------
    origin, eta : tuple of float, shape (d,)
        Grid points are ``origin + k * eta``; ``eta > 0`` is the spacing (cell width).
    k_lo, k_hi : tuple of int, shape (d,)
        Inclusive range of the integer coordinates ``k`` per dimension.
    lb, ub : tuple of float, shape (d,)
        The concrete box this grid discretizes; cells are clipped to it for sampling.
    """

    origin: tuple[float, ...]
    eta: tuple[float, ...]
    k_lo: tuple[int, ...]
    k_hi: tuple[int, ...]
    lb: tuple[float, ...]
    ub: tuple[float, ...]

    # ------------------------------------------------------------------ construction
    @classmethod
    def covering(cls, lb: Values, ub: Values, eta: Values, origin: Values | None = None,
                 name: str = "grid") -> UniformGrid:
        """Grid of every point whose cell meets ``[lb, ub]`` in a set of positive measure (state grids).

        The cells then cover the box, so every concrete state lies in some cell (docs/method.md §1). A box that is a
        single point in some dimension gets the one cell containing it.
        """
        lb_, ub_, eta_, o_ = cls._check(lb, ub, eta, origin, name)
        # cell k = [o + (k - 1/2) eta, o + (k + 1/2) eta] meets (lb, ub) iff k > (lb-o)/eta - 1/2 and
        # k < (ub-o)/eta + 1/2; a bound exactly on a cell boundary belongs to the inner cell only.
        with np.errstate(over="ignore", invalid="ignore"):  # an overflow is _make's SpecError, not a warning
            lo_r = _snap((lb_ - o_) / eta_ + 0.5)
            hi_r = _snap((ub_ - o_) / eta_ - 0.5)
            k_lo = np.floor(lo_r)
            k_hi = np.ceil(hi_r)
            k_hi = np.where(lb_ == ub_, k_lo, k_hi)  # a point box: the one cell containing it
        return cls._make(o_, eta_, k_lo, k_hi, lb_, ub_, name)

    @classmethod
    def inside(cls, lb: Values, ub: Values, eta: Values, origin: Values | None = None,
               name: str = "grid") -> UniformGrid:
        """Grid of the points that lie in ``[lb, ub]`` (external-input grids: inputs are points, not cells)."""
        lb_, ub_, eta_, o_ = cls._check(lb, ub, eta, origin, name)
        with np.errstate(over="ignore", invalid="ignore"):  # an overflow is _make's SpecError, not a warning
            k_lo = np.ceil(_snap((lb_ - o_) / eta_))
            k_hi = np.floor(_snap((ub_ - o_) / eta_))
        return cls._make(o_, eta_, k_lo, k_hi, lb_, ub_, name)

    @staticmethod
    def _check(lb, ub, eta, origin, name):
        lb_arr = np.atleast_1d(np.asarray(lb, dtype=float))
        dim = lb_arr.size
        if dim == 0:
            raise SpecError(f"{name}: a grid needs at least one dimension")
        lb_ = _as_vector(lb, dim, f"{name}.lb")
        ub_ = _as_vector(ub, dim, f"{name}.ub")
        eta_ = _as_vector(eta, dim, f"{name}.eta")
        o_ = _as_vector(0.0 if origin is None else origin, dim, f"{name}.origin")
        if np.any(eta_ <= 0):
            raise SpecError(f"{name}.eta must be positive, got {eta_.tolist()}")
        if np.any(lb_ > ub_):
            raise SpecError(f"{name}: empty box, lb {lb_.tolist()} exceeds ub {ub_.tolist()}")
        return lb_, ub_, eta_, o_

    @classmethod
    def _make(cls, o_, eta_, k_lo, k_hi, lb_, ub_, name) -> UniformGrid:
        if not (np.all(np.isfinite(k_lo)) and np.all(np.isfinite(k_hi))):
            raise SpecError(
                f"{name}: spacing {eta_.tolist()} is too fine for the box [{lb_.tolist()}, {ub_.tolist()}] "
                "(the number of grid points overflows); use a larger eta"
            )
        if np.any(k_hi < k_lo):
            raise SpecError(
                f"{name}: empty grid, no point of spacing {eta_.tolist()} lies in [{lb_.tolist()}, {ub_.tolist()}]"
            )
        return cls(
            origin=tuple(float(v) for v in o_),
            eta=tuple(float(v) for v in eta_),
            k_lo=tuple(int(v) for v in k_lo),
            k_hi=tuple(int(v) for v in k_hi),
            lb=tuple(float(v) for v in lb_),
            ub=tuple(float(v) for v in ub_),
        )

    @classmethod
    def product(cls, grids: Sequence[UniformGrid]) -> UniformGrid:
        """The product of grids as one grid (dimensions concatenated in order)."""
        return cls(
            origin=sum((g.origin for g in grids), ()),
            eta=sum((g.eta for g in grids), ()),
            k_lo=sum((g.k_lo for g in grids), ()),
            k_hi=sum((g.k_hi for g in grids), ()),
            lb=sum((g.lb for g in grids), ()),
            ub=sum((g.ub for g in grids), ()),
        )

    # ------------------------------------------------------------------ sizes
    @property
    def dim(self) -> int:
        return len(self.eta)

    @property
    def shape(self) -> tuple[int, ...]:
        """Number of points per dimension."""
        return tuple(high - low + 1 for low, high in zip(self.k_lo, self.k_hi))

    @property
    def size(self) -> int:
        """Number of points (an exact Python integer; it can exceed 2**63 for product grids)."""
        return math.prod(self.shape)

    @property
    def eta_array(self) -> np.ndarray:
        return np.asarray(self.eta)

    # ------------------------------------------------------------------ indices and points
    def unravel(self, flat: np.ndarray) -> np.ndarray:
        """Flat (row-major) indices, shape (B,), to per-dimension indices, shape (B, d)."""
        return np.stack(np.unravel_index(np.asarray(flat, dtype=np.int64), self.shape), axis=-1)

    def on_grid(self, idx: np.ndarray) -> np.ndarray:
        """Whether each per-dimension index, shape (B, d), is a cell of this grid; bool (B,)."""
        idx = np.asarray(idx)
        return np.all((idx >= 0) & (idx < np.asarray(self.shape)), axis=-1)

    def ravel(self, idx: np.ndarray) -> np.ndarray:
        """Per-dimension indices, shape (B, d), to flat row-major indices, shape (B,)."""
        idx = np.asarray(idx, dtype=np.int64)
        return np.ravel_multi_index(tuple(idx.T), self.shape)

    def points(self, idx: np.ndarray) -> np.ndarray:
        """Grid points (cell centres) of per-dimension indices, shape (B, d) -> (B, d)."""
        k = np.asarray(idx, dtype=float) + np.asarray(self.k_lo, dtype=float)
        return np.asarray(self.origin) + k * self.eta_array

    def all_points(self) -> np.ndarray:
        """Every grid point, shape (size, d), row-major. Only for small grids."""
        return self.points(self.unravel(np.arange(self.size)))

    def axis_points(self, axis: int) -> np.ndarray:
        """Points of one dimension, shape (shape[axis],)."""
        k = np.arange(self.k_lo[axis], self.k_hi[axis] + 1, dtype=float)
        return self.origin[axis] + k * self.eta[axis]

    # ------------------------------------------------------------------ cells
    def clipped_cells(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The part of each cell inside the concrete box, ``cell(idx) ∩ [lb, ub]``.

        Returns
        -------
        lo, hi : ndarray, shape (B, d)
            Bounds of the clipped cells; ``lo <= hi`` for every cell of a ``covering`` grid.
        """
        c = self.points(idx)
        half = self.eta_array / 2
        lo = np.maximum(c - half, np.asarray(self.lb))
        hi = np.minimum(c + half, np.asarray(self.ub))
        return lo, hi

    def cell_of(self, x: np.ndarray, tie: str = "upper") -> tuple[np.ndarray, np.ndarray]:
        """Index of the cell containing each concrete point.

        A point on the boundary of two cells belongs to both (cells are closed); ``tie`` picks the upper or
        the lower one. The feedback refinement relation relates the point to both, so checks of soundness
        must look at both.

        Returns
        -------
        idx : ndarray of int64, shape (B, d)
        inside : ndarray of bool, shape (B,)
            Whether the cell is on this grid.
        """
        x = np.asarray(x, dtype=float)
        flat = np.ascontiguousarray(x.reshape(-1, self.dim))
        idx = np.empty(flat.shape, dtype=np.int64)
        _cell_of(flat, np.asarray(self.origin, dtype=float), self.eta_array.astype(float),
                 np.asarray(self.k_lo, dtype=np.int64), tie == "upper", idx)
        idx = idx.reshape(x.shape)
        return idx, self.on_grid(idx)

    def cells_touching(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Index range of the cells that meet the closed boxes ``[lo, hi]`` (successor sets, Def. 4.2).

        The range is rounded outwards: a box touching a cell boundary within floating-point error gets both
        neighbours, which can only add transitions. Indices are not clipped to the grid; a range reaching
        outside it means the box leaves the grid.

        Returns
        -------
        first, last : ndarray of int64, shape (B, d)
        """
        o = np.asarray(self.origin)
        eta = self.eta_array
        with np.errstate(over="ignore", invalid="ignore"):  # far bounds are infinite indices, clamped by _index
            a = (np.asarray(lo, dtype=float) - o) / eta - 0.5
            b = (np.asarray(hi, dtype=float) - o) / eta + 0.5
            # Outward rounding: a relative SNAP_RTOL widening cannot lose a cell that meets the box.
            a = a - SNAP_RTOL * np.maximum(1.0, np.abs(a))
            b = b + SNAP_RTOL * np.maximum(1.0, np.abs(b))
        first = _index(np.ceil(a)) - np.asarray(self.k_lo, dtype=np.int64)
        last = _index(np.floor(b)) - np.asarray(self.k_lo, dtype=np.int64)
        return first, last

    def inner_range(
        self, lb: np.ndarray | Sequence[float], ub: np.ndarray | Sequence[float]
    ) -> tuple[np.ndarray, np.ndarray]:
        """Index range of the grid cells lying wholly inside the box ``[lb, ub]`` (inner approximation).

        Returns ``(first, last)``, shape (d,), clipped to the grid; the range is empty where
        ``first > last``.
        """
        o = np.asarray(self.origin)
        eta = self.eta_array
        with np.errstate(over="ignore", invalid="ignore"):  # far bounds are infinite indices, clamped by _index
            first = _index(np.ceil(_snap((np.asarray(lb, dtype=float) - o) / eta + 0.5)))
            last = _index(np.floor(_snap((np.asarray(ub, dtype=float) - o) / eta - 0.5)))
        first = np.maximum(first - np.asarray(self.k_lo), 0)
        last = np.minimum(last - np.asarray(self.k_lo), np.asarray(self.shape) - 1)
        return first, last

    def describe(self) -> dict:
        """A JSON-ready description (for reports, Zarr attributes and controller headers)."""
        return {
            "origin": list(self.origin),
            "eta": list(self.eta),
            "k_lo": list(self.k_lo),
            "k_hi": list(self.k_hi),
            "lb": list(self.lb),
            "ub": list(self.ub),
            "shape": list(self.shape),
        }

    @classmethod
    def from_description(cls, d: dict) -> UniformGrid:
        return cls(
            origin=tuple(d["origin"]),
            eta=tuple(d["eta"]),
            k_lo=tuple(d["k_lo"]),
            k_hi=tuple(d["k_hi"]),
            lb=tuple(d["lb"]),
            ub=tuple(d["ub"]),
        )


def product_size(grids: Sequence[UniformGrid]) -> int:
    """Number of points of the product of grids (exact integer)."""
    return math.prod(g.size for g in grids)


def quantize(grid: UniformGrid, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cell indices of concrete states, shape (B, n) -> (B, n), and whether each is in the box, shape (B,): the
    quantizer of every controller's ``cells`` and of the C export.

    Cells are closed, so a state on a cell boundary lies in two cells; the feedback refinement relation relates
    it to both and either cell's inputs are admissible there. The upper cell is taken (:meth:`UniformGrid.cell_of`
    with its relative snapping), per coordinate the lower one where the upper is off the grid: a state on the
    upper edge of the box, when that edge is a cell boundary, still gets a cell. Indices of rows outside the
    box (or NaN) are meaningless.
    """
    X = np.asarray(X, dtype=float)
    if X.ndim != 2 or X.shape[1] != grid.dim:
        raise CompabsError(f"a state has {grid.dim} components, got shape {X.shape[1:]}")
    with np.errstate(invalid="ignore"):
        in_box = np.all((X >= np.asarray(grid.lb)) & (X <= np.asarray(grid.ub)), axis=1)
    shape = np.asarray(grid.shape, dtype=np.int64)
    upper, _ = grid.cell_of(np.where(np.isfinite(X), X, 0.0), "upper")
    lower, _ = grid.cell_of(np.where(np.isfinite(X), X, 0.0), "lower")
    idx = np.where((upper >= 0) & (upper < shape), upper, lower)
    ok = in_box & grid.on_grid(idx)
    return np.where(ok[:, None], idx, 0), ok
