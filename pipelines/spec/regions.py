"""Regions of the specification, approximated from inside by whole cells (docs/method.md §1).

A region is a union of boxes over the composed state. Its abstraction keeps a cell only if the cell lies
wholly inside one of the boxes, so a concrete state in an abstract target cell satisfies the concrete
predicate. The abstraction is a union of *index boxes* (inclusive per-coordinate index ranges on the
composed state grid); its number of states is counted exactly, without enumerating them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property

import numpy as np

from pipelines.errors import SpecError
from pipelines.grid import UniformGrid
from pipelines.network import Network
from pipelines.spec.model import JobSpec, Region

IndexBox = tuple[np.ndarray, np.ndarray]  # (first, last), each shape (n,), inclusive


@dataclass(frozen=True)
class AbstractRegion:
    """A union of index boxes on the composed state grid."""

    boxes: tuple[IndexBox, ...]

    @cached_property
    def states(self) -> int:
        """Exact number of abstract states in the union (a sweep: counted once per region)."""
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
    return math.prod(int(high - low + 1) for low, high in zip(lo, hi)) if np.all(hi >= lo) else 0


def union_count(boxes: list[IndexBox]) -> int:
    """Exact number of integer points in a union of index boxes.

    A sweep over one coordinate at a time: the union's count is the sum, over the slabs between
    consecutive box boundaries of the first coordinate, of the slab width times the count of the union of
    the boxes covering that slab in the remaining coordinates. Sub-problems are memoised by the set of
    covering boxes, which repeats a lot for structured regions (the consensus windows: 32 boxes in 8-D in
    milliseconds, where a disjoint decomposition takes seconds).
    """
    boxes = [b for b in boxes if _volume(b) > 0]
    if not boxes:
        return 0
    los = np.array([b[0] for b in boxes], dtype=np.int64)
    his = np.array([b[1] for b in boxes], dtype=np.int64)
    n = los.shape[1]

    def slabs(d: int, active: frozenset[int]) -> list[tuple[int, frozenset[int]]]:
        """The slabs of coordinate ``d`` between consecutive box boundaries: (width, the boxes covering it)."""
        idx = np.fromiter(active, dtype=np.int64)
        cuts = np.unique(np.concatenate([los[idx, d], his[idx, d] + 1]))
        out = []
        for a, b in zip(cuts[:-1], cuts[1:]):
            cover = idx[(los[idx, d] <= a) & (his[idx, d] >= b - 1)]
            if cover.size:
                out.append((int(b - a), frozenset(cover.tolist())))
        return out

    # Depth-first over (coordinate, covering boxes) with an explicit stack: the depth is the dimension, which
    # reaches thousands for large networks (recursion would hit Python's limit).
    memo: dict[tuple[int, frozenset[int]], int] = {}
    stack = [(0, frozenset(range(len(boxes))))]
    while stack:
        key = stack[-1]
        d, active = key
        if key in memo:
            stack.pop()
        elif d == n:
            memo[key] = 1
            stack.pop()
        else:
            parts = slabs(d, active)
            missing = [(d + 1, cover) for _, cover in parts if (d + 1, cover) not in memo]
            if missing:
                stack.extend(missing)
            else:
                memo[key] = sum(width * memo[(d + 1, cover)] for width, cover in parts)
                stack.pop()
    return memo[(0, frozenset(range(len(boxes))))]


def _broadcast(v, n: int, name: str) -> np.ndarray:
    arr = np.atleast_1d(np.asarray(v, dtype=float))
    if arr.size == 1:
        arr = np.repeat(arr, n)
    if arr.shape != (n,):
        raise SpecError(f"{name}: {arr.size} components for a composed state of dimension {n}")
    return arr


def concrete_boxes(region: Region, n: int, name: str) -> list[tuple[np.ndarray, np.ndarray]]:
    """The region as closed boxes ``(lb, ub)`` of the composed state (dimension ``n``; scalars broadcast, the
    consensus region's windows listed).

    Raises
    ------
    SpecError
        A box with ``lb > ub`` or of the wrong dimension, a consensus region that is not finite or too large.
    """
    concrete: list[tuple[np.ndarray, np.ndarray]] = []
    for i, b in enumerate(region.boxes):
        lb, ub = _broadcast(b.lb, n, f"{name}.boxes[{i}].lb"), _broadcast(b.ub, n, f"{name}.boxes[{i}].ub")
        if np.any(lb > ub):
            raise SpecError(f"{name}.boxes[{i}]: lb exceeds ub")
        concrete.append((lb, ub))
    if region.consensus is not None:
        first, last, step = region.consensus.centers
        if not all(math.isfinite(v) for v in (first, last, step, region.consensus.radius)):
            raise SpecError(f"{name}.consensus: centers and radius must be finite numbers")
        if step <= 0 or last < first:
            raise SpecError(f"{name}.consensus.centers: need first <= last and step > 0")
        span = (last - first) / step * (1 + 1e-12)  # may overflow to inf for a tiny step
        if not math.isfinite(span) or span >= 100_000:
            raise SpecError(f"{name}.consensus.centers: more than 100000 centres ((last - first) / step = {span:.3g})")
        count = int(math.floor(span)) + 1
        for k in range(count):
            phi = first + k * step
            r = region.consensus.radius
            concrete.append((np.full(n, phi - r), np.full(n, phi + r)))
    return concrete


def abstract_region(region: Region, grid: UniformGrid, name: str, outer: bool = False) -> AbstractRegion:
    """Inner (default) or outer approximation of a region on the composed state grid.

    Targets and safe sets are approximated from inside, so an abstract cell in them is wholly in the concrete
    region; sets to avoid from outside (every cell that meets them), so avoiding the abstract set avoids the
    concrete one.

    Raises
    ------
    SpecError
        If the region contains no whole cell (an empty region cannot be a target or a safe set).
    """
    concrete = concrete_boxes(region, grid.dim, name)
    boxes = []
    for lb, ub in concrete:
        if outer:
            lo, hi = grid.cells_touching(lb[None, :], ub[None, :])
            lo = np.maximum(lo[0], 0)
            hi = np.minimum(hi[0], np.asarray(grid.shape) - 1)
        else:
            lo, hi = grid.inner_range(lb, ub)
        if np.all(hi >= lo):
            boxes.append((lo.astype(np.int64), hi.astype(np.int64)))
    if not boxes:
        if outer:
            raise SpecError(f"{name}: the region meets no grid cell")
        raise SpecError(f"{name}: the region contains no whole grid cell (it is empty after inner approximation)")
    return AbstractRegion(tuple(boxes))


def spec_regions(spec: JobSpec, network: Network) -> dict[str, AbstractRegion]:
    """The specification's regions on the composed grid: targets and safe sets from inside, avoid sets from
    outside (docs/method.md §1)."""
    grid = network.composed_state_grid()
    regions: dict[str, AbstractRegion] = {}
    for name in ("target", "safe", "avoid"):
        region = getattr(spec.specification, name)
        if region is not None:
            regions[name] = abstract_region(region, grid, f"specification.{name}", outer=(name == "avoid"))
    return regions


def closed_loop_regions(spec: JobSpec, network: Network,
                        regions: dict[str, AbstractRegion] | None = None) -> dict[str, AbstractRegion | None]:
    """The regions a closed-loop run is checked against, as keyword arguments of
    :func:`~pipelines.verification.closed_loop.simulate` (``target``, ``safe``, ``avoid``).

    For a ``safe`` specification the target is the safe set (a run's ``in_target`` flags say whether it is in
    ``S``); for the other kinds ``safe`` is the optional safe set, which no run may leave.

    Parameters
    ----------
    regions : dict, optional
        :func:`spec_regions` of the spec, if already computed.
    """
    regions = spec_regions(spec, network) if regions is None else regions
    kind = spec.specification.kind
    return {"target": regions.get("safe") if kind == "safe" else regions.get("target"),
            "safe": regions.get("safe"), "avoid": regions.get("avoid")}


def never_winning(spec: JobSpec, network: Network, regions: dict[str, AbstractRegion]) -> np.ndarray | None:
    """The cells of a single system that no fixed point of its specification can ever let in, as a boolean per
    flat cell (SCOTS does not abstract them either), or ``None`` for a network (whose composed cells are not one
    subsystem's) or where there are none.

    Every fixed point (docs/method.md §6) keeps to the safe set ``S`` (a ``safe`` specification's region, else the
    optional ``specification.safe``) and out of the avoid set ``A``: the cells outside ``S`` (inner approximation)
    or meeting ``A`` (outer approximation) are in no iterate, so no controller needs their successors.
    """
    if len(network.subsystems) != 1 or network.subsystems[0].reads:
        return None
    grid = network.composed_state_grid()
    dead = np.zeros(grid.shape, dtype=bool)
    safe = regions.get("safe")
    if safe is not None:
        dead[...] = True
        for lo, hi in safe.boxes:
            dead[tuple(slice(int(a), int(b) + 1) for a, b in zip(lo, hi))] = False
    avoid = regions.get("avoid") if spec.specification.kind == "reach_avoid" else None
    if avoid is not None:
        for lo, hi in avoid.boxes:
            dead[tuple(slice(int(a), int(b) + 1) for a, b in zip(lo, hi))] = True
    return dead.reshape(-1) if dead.any() else None


def dead_ranges(dead: np.ndarray | None, start: int, stop: int) -> tuple[tuple[int, int], ...]:
    """The runs ``[a, b)`` of ``True`` in ``dead[start:stop]``, as flat cell indices (empty for ``None``)."""
    if dead is None:
        return ()
    part = np.concatenate([[False], dead[start:stop], [False]]).astype(np.int8)
    edges = np.flatnonzero(np.diff(part))
    return tuple((start + int(a), start + int(b)) for a, b in zip(edges[::2], edges[1::2]))
