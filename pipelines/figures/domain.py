"""The winning domain on a plane of two state coordinates, read off the domain BDD in one pass, and its reduction
to blocks of cells for drawing.

:meth:`Controller.in_domain` answers one cell at a time (one BDD evaluation each: about 10 µs, so 8 s for the
641,601 cells of the DC-DC converter). :func:`plane_mask` restricts the domain to the plane once (the other
coordinates fixed to one cell) and expands the restricted BDD over the bits of the two coordinates, sharing the
array of every node it meets: the same mask, cell for cell, in a fraction of the time.

:func:`block_levels` reduces a mask too large to be drawn one pixel per cell: a block of cells is drawn as
domain only if *every* cell of it is in the domain, and as partly in it otherwise, so no cell that is not in the
domain is ever drawn as domain.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

#: Most cells of a plane :func:`plane_mask` expands (its array has up to 4 times as many, padded to powers of two).
MAX_PLANE_CELLS = 4_000_000


def plane_mask(controller: Any, base: np.ndarray, i: int, j: int) -> np.ndarray:
    """Whether each cell of the plane of coordinates ``(i, j)`` through cell ``base`` is in the controller's
    domain, shape (shape[i], shape[j]); equal to :meth:`Controller.in_domain` of each cell.

    Parameters
    ----------
    controller : Controller or ArrayController
        Its ``model`` (the symbolic model: bits, manager) and ``domain`` (a BDD over current-state bits), or its own
        ``plane_mask`` (:meth:`~pipelines.array_controller.ArrayController.plane_mask`).
    base : ndarray of int, shape (n,)
        Cell indices; those of coordinates other than ``i`` and ``j`` fix the plane.
    i, j : int
        The plane's coordinates, 0-based, distinct.

    Raises
    ------
    ValueError
        The plane has more than :data:`MAX_PLANE_CELLS` cells, or the domain depends on bits other than the
        current state's.
    """
    own = getattr(controller, "plane_mask", None)
    if own is not None:  # an array controller slices its own domain
        return own(base, i, j)
    model = controller.model
    bdd = model.bdd
    ki, kj = model.state_sizes[i], model.state_sizes[j]
    if ki * kj > MAX_PLANE_CELLS:
        raise ValueError(f"a plane of {ki * kj:,} cells: at most {MAX_PLANE_CELLS:,}")
    bits_i, bits_j = list(model.bits[f"x{i}"]), list(model.bits[f"x{j}"])
    free = set(bits_i) | set(bits_j)
    fixed = {b: v for b, v in model.state_assignment([int(v) for v in base]).items() if b not in free}
    g = (bdd.let(fixed, controller.domain) if fixed else controller.domain) & model.domain([f"x{i}", f"x{j}"])
    extra = bdd.support(g) - free
    if extra:
        raise ValueError(f"the domain depends on bits other than the state's: {sorted(extra)[:6]}")
    order = sorted(free, key=bdd.level_of_var)  # the BDD's own order: one cofactor per level
    memo: dict[tuple[int, int], tuple[Any, np.ndarray]] = {}

    def expand(f: Any, t: int) -> np.ndarray:
        """``f`` over ``order[t:]``, as an array with one axis of length 2 per bit, in that order."""
        shape = (2,) * (len(order) - t)
        if f == bdd.false:
            return np.zeros(shape, dtype=bool)
        if f == bdd.true:
            return np.ones(shape, dtype=bool)
        key = (int(f), t)
        hit = memo.get(key)
        if hit is not None:
            return hit[1]
        b = order[t]
        out = np.stack([expand(bdd.let({b: False}, f), t + 1), expand(bdd.let({b: True}, f), t + 1)])
        memo[key] = (f, out)  # f is kept alive with its array: a node id is not reused while it is referenced
        return out

    full = expand(g, 0)
    # Axes in the digits' own bit order (most significant first), then one axis per coordinate.
    axes = [order.index(b) for b in bits_i + bits_j]
    full = np.transpose(full, axes).reshape(2 ** len(bits_i), 2 ** len(bits_j))
    return np.ascontiguousarray(full[:ki, :kj])


def block_factors(shape: tuple[int, int], most: int) -> tuple[int, int]:
    """Cells per block along each axis so that neither side has more than ``most`` blocks."""
    return max(1, math.ceil(shape[0] / most)), max(1, math.ceil(shape[1] / most))


def block_levels(mask: np.ndarray, factors: tuple[int, int]) -> np.ndarray:
    """Blocks of ``factors`` cells: 2 where every cell of the block is in the domain, 1 where some but not all
    are, 0 where none is; shape (ceil(ki / fi), ceil(kj / fj)), int8.

    The last block of an axis may hold fewer cells (those of the grid): it is judged on them.
    """
    fi, fj = factors
    ki, kj = mask.shape
    bi, bj = math.ceil(ki / fi), math.ceil(kj / fj)
    # Pad with cells that do not exist: neutral for "every cell" (True) and for "some cell" (False).
    every = np.ones((bi * fi, bj * fj), dtype=bool)
    some = np.zeros((bi * fi, bj * fj), dtype=bool)
    every[:ki, :kj] = mask
    some[:ki, :kj] = mask
    every_b = every.reshape(bi, fi, bj, fj).all(axis=(1, 3))
    some_b = some.reshape(bi, fi, bj, fj).any(axis=(1, 3))
    return np.where(every_b, 2, np.where(some_b, 1, 0)).astype(np.int8)
