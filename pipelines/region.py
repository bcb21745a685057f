"""Regions of the specification, approximated from inside by whole cells (METHOD §1).

A region is a union of boxes over the composed state. Its abstraction keeps a cell only if the cell lies
wholly inside one of the boxes, so a concrete state in an abstract target cell satisfies the concrete
predicate. The abstraction is a union of *index boxes* (inclusive per-coordinate index ranges on the
composed state grid); its number of states is counted exactly, without enumerating them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .errors import SpecError
from .grid import UniformGrid
from .spec import Region

IndexBox = tuple[np.ndarray, np.ndarray]  # (first, last), each shape (n,), inclusive


@dataclass(frozen=True)
class AbstractRegion:
    """A union of index boxes on the composed state grid."""

    boxes: tuple[IndexBox, ...]

    @property
    def states(self) -> int:
        """Exact number of abstract states in the union."""
        return union_count(list(self.boxes))

    def contains(self, idx: np.ndarray) -> np.ndarray:
        """Whether composed cell indices, shape (B, n), lie in the region; returns bool (B,)."""
        out = np.zeros(idx.shape[0], dtype=bool)
        for lo, hi in self.boxes:
            out |= np.all((idx >= lo) & (idx <= hi), axis=1)
        return out

    def describe(self) -> list[dict]:
        return [{"first": lo.tolist(), "last": hi.tolist()} for lo, hi in self.boxes]


def _volume(box: IndexBox) -> int:
    lo, hi = box
    return math.prod(int(h - l + 1) for l, h in zip(lo, hi)) if np.all(hi >= lo) else 0


def _subtract(p: IndexBox, d: IndexBox) -> list[IndexBox]:
    """``p \\ d`` as at most ``2n`` disjoint boxes."""
    plo, phi = p
    dlo, dhi = d
    if np.any(dhi < plo) or np.any(dlo > phi):
        return [p]
    pieces = []
    lo, hi = plo.copy(), phi.copy()
    for i in range(len(lo)):
        if lo[i] < dlo[i]:
            a, b = lo.copy(), hi.copy()
            b[i] = dlo[i] - 1
            pieces.append((a, b))
            lo[i] = dlo[i]
        if hi[i] > dhi[i]:
            a, b = lo.copy(), hi.copy()
            a[i] = dhi[i] + 1
            pieces.append((a, b))
            hi[i] = dhi[i]
    return pieces


def union_count(boxes: list[IndexBox]) -> int:
    """Exact number of integer points in a union of index boxes (incremental disjoint decomposition)."""
    disjoint: list[IndexBox] = []
    for b in boxes:
        if _volume(b) == 0:
            continue
        pieces = [b]
        for d in disjoint:
            pieces = [q for piece in pieces for q in _subtract(piece, d)]
            if not pieces:
                break
        disjoint.extend(pieces)
    return sum(_volume(b) for b in disjoint)


def _broadcast(v, n: int, name: str) -> np.ndarray:
    arr = np.atleast_1d(np.asarray(v, dtype=float))
    if arr.size == 1:
        arr = np.repeat(arr, n)
    if arr.shape != (n,):
        raise SpecError(f"{name}: {arr.size} components for a composed state of dimension {n}")
    return arr


def abstract_region(region: Region, grid: UniformGrid, name: str) -> AbstractRegion:
    """Inner approximation of a region on the composed state grid.

    Raises
    ------
    SpecError
        If the region contains no whole cell (an empty region cannot be a target or a safe set).
    """
    n = grid.dim
    concrete: list[tuple[np.ndarray, np.ndarray]] = []
    for i, b in enumerate(region.boxes):
        lb, ub = _broadcast(b.lb, n, f"{name}.boxes[{i}].lb"), _broadcast(b.ub, n, f"{name}.boxes[{i}].ub")
        if np.any(lb > ub):
            raise SpecError(f"{name}.boxes[{i}]: lb exceeds ub")
        concrete.append((lb, ub))
    if region.consensus is not None:
        first, last, step = region.consensus.centers
        if step <= 0 or last < first:
            raise SpecError(f"{name}.consensus.centers: need first <= last and step > 0")
        count = int(math.floor((last - first) / step * (1 + 1e-12))) + 1
        if count > 100_000:
            raise SpecError(f"{name}.consensus.centers: {count} centres, the limit is 100000")
        for k in range(count):
            phi = first + k * step
            r = region.consensus.radius
            concrete.append((np.full(n, phi - r), np.full(n, phi + r)))
    boxes = []
    for lb, ub in concrete:
        lo, hi = grid.inner_range(lb, ub)
        if np.all(hi >= lo):
            boxes.append((lo.astype(np.int64), hi.astype(np.int64)))
    if not boxes:
        raise SpecError(f"{name}: the region contains no whole grid cell (it is empty after inner approximation)")
    return AbstractRegion(tuple(boxes))
