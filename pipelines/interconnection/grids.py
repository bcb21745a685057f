"""The low-dimensional grids a node reads: axis grids, clipped cells, cell ranges, flat indexing of products.

Every relation and every certification is computed on the product of at most a few one-dimensional grids
(one per support coordinate or node input), never on the full product grid (docs/method.md §4). These helpers give
the 1-D grid of one coordinate, the clipped cells of a 1-D grid (``cell ∩ [lb, ub]``, which hold every
concrete value a cell stands for), the cells an interval meets, and row-major flat indexing of a product with
any number of axes.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from pipelines.grid import UniformGrid

__all__ = ["axis_grid", "cell_bounds", "clip_range", "unravel", "subgrid_counts"]


def axis_grid(grid: UniformGrid, i: int) -> UniformGrid:
    """The 1-D grid of dimension ``i`` of a product grid."""
    return UniformGrid(
        origin=(grid.origin[i],), eta=(grid.eta[i],), k_lo=(grid.k_lo[i],), k_hi=(grid.k_hi[i],),
        lb=(grid.lb[i],), ub=(grid.ub[i],),
    )


def cell_bounds(grid: UniformGrid) -> tuple[np.ndarray, np.ndarray]:
    """Centres and half-widths of every clipped cell of a 1-D grid, shape (size,) each.

    The clipped cell ``cell ∩ [lb, ub]`` holds every concrete value the cell stands for (docs/method.md §1).
    """
    lo, hi = grid.clipped_cells(np.arange(grid.size)[:, None])
    return (lo[:, 0] + hi[:, 0]) / 2, (hi[:, 0] - lo[:, 0]) / 2


def clip_range(grid: UniformGrid, lo_v: np.ndarray, hi_v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cells of a 1-D grid meeting ``[lo_v, hi_v]`` (any shape), clipped to the grid; ``lo > hi`` if none."""
    shape = np.shape(lo_v)
    first, last = grid.cells_touching(np.reshape(lo_v, (-1, 1)), np.reshape(hi_v, (-1, 1)))
    first = np.maximum(first[:, 0], 0)
    last = np.minimum(last[:, 0], grid.size - 1)
    return first.astype(np.int32).reshape(shape), last.astype(np.int32).reshape(shape)


def unravel(flat: np.ndarray, shape: Sequence[int]) -> tuple[np.ndarray, ...]:
    """``np.unravel_index(flat, shape)`` for any number of axes (numpy allows at most 64).

    Row-major, by ``divmod`` from the last axis; an axis of one cell gets index 0 without arithmetic, so a
    support of 128 coordinates certified on one cell (the scalability example) costs nothing.
    """
    flat = np.asarray(flat, dtype=np.int64)
    out: list[np.ndarray] = []
    rest = flat
    for size in reversed(shape):
        if size == 1:
            out.append(np.zeros_like(flat))
        else:
            rest, q = np.divmod(rest, size)
            out.append(q)
    return tuple(reversed(out))


def subgrid_counts(samples: int, s: int) -> list[int]:
    """Points per axis of a sub-grid of at most ``samples`` points over ``s`` axes, as even as possible."""
    counts = [1] * s
    grown = True
    while grown:
        grown = False
        for d in range(s):
            trial = counts.copy()
            trial[d] += 1
            if math.prod(trial) <= samples:
                counts = trial
                grown = True
    return counts
