"""Outputs declared to be the largest (``error: max``) or smallest (``error: min``) of the coordinates they read.

Beyond the paper. Its Sec. 5.1 map ``w = max(x)`` has no informative affine approximation: any ``M̄`` leaves
``eps >= 16 (n - 1) / n`` on ``[0, 32]^n``, so from ``n ~ 32`` every state admits every cell of ``w``
(:func:`~pipelines.interconnection.nodes.covers_box`). A user who knows the map is such a reduction declares it,
as one declares a map linear; compabs checks the declaration on held-out samples (:func:`check_reduction`)
and abstracts the output exactly, whatever the number of coordinates (:func:`reduction_nodes`):

* Intermediate nodes form a tree of in-degree 2 over the support (coordinates in increasing order). An
  intermediate ``z`` is the largest (smallest) *cell index* of the coordinates under it: all of them share one
  grid, on which a clipped cell's lower and upper ends grow with its index, so for states in cells ``k_i`` the
  reduction lies in the clipped cell ``K = max_i k_i`` (``min``) - exactly that cell's interval, however many
  coordinates. ``z`` is a function of the cells, with no concrete counterpart, on the coordinates' own grid.
* The final node allows the internal cells meeting cell ``K``'s interval (widened by the floating-point margin
  of :mod:`~pipelines.interconnection.certification`). Its error bound is 0: nothing is approximated; the cells
  a state admits are those its reduction's cell meets (3 on the scalability example, for every ``N``).

In-degree 2 keeps each node's table at ``size^2`` entries (33^2 on the scalability example, against 33^4 at
``sigma = 4``; at ``N = 1024``: 1,023 nodes, 9 MB in all). The nodes come in post-order (each parent right after
its children), and the symbolic model puts each ``z`` right below the blocks of the coordinates under it
(:func:`~pipelines.symbolic.order.variable_order`), so conjoining them never holds more than a running maximum.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from pipelines.errors import CertificationError, SpecError
from pipelines.grid import UniformGrid
from pipelines.interconnection.certification import FP_ATOL, FP_RTOL
from pipelines.interconnection.grids import cell_bounds, clip_range
from pipelines.interconnection.node_relations import NodeRelation

__all__ = ["REDUCTIONS", "check_reduction", "reduction_nodes"]

#: The declarable reductions: ``interconnection.error`` value -> numpy reduction over the last axis.
REDUCTIONS = {"max": np.max, "min": np.min}


def check_reduction(op: str, j: int, support: Sequence[int], X: np.ndarray, Y: np.ndarray) -> None:
    """The declaration ``w_j = op(x[support])`` against samples ``X`` (states) and ``Y`` (map values).

    Raises
    ------
    CertificationError
        The output reads no coordinate, or differs from the declared reduction at a sample (beyond the
        floating-point margin): the state, both values and the support are named.
    """
    if not support:
        raise CertificationError(
            f"interconnection.error is '{op}' but output w{j} depends on no state coordinate: the {op} of nothing "
            "is undefined (use error: linear for a constant output)"
        )
    want = REDUCTIONS[op](X[:, list(support)], axis=1)
    got = Y[:, j]
    tol = FP_RTOL * np.maximum(np.abs(want), np.abs(got)) + FP_ATOL
    bad = np.abs(got - want) > tol
    if bad.any():
        r = int(np.argmax(bad))
        raise CertificationError(
            f"interconnection.error is '{op}' but output w{j} is not the {op} of the coordinates it reads "
            f"{list(support)[:8]}{' ...' if len(support) > 8 else ''}: at x = {X[r].tolist()[:8]}"
            f"{' ...' if X.shape[1] > 8 else ''} the map gives {got[r]:.17g}, the {op} is {want[r]:.17g}; "
            "declare error: certify or direct instead"
        )


def _common_grid(j: int, support: Sequence[int], x_grids: Sequence[UniformGrid]) -> UniformGrid:
    """The one grid all coordinates of the support share (the index trick needs it)."""
    first = x_grids[support[0]]
    for i in support[1:]:
        if x_grids[i].describe() != first.describe():
            raise SpecError(
                f"interconnection.error is a reduction but output w{j} reads x{support[0]} and x{i}, whose grids "
                f"differ ({first.describe()} vs {x_grids[i].describe()}); a reduction needs one grid for all the "
                "coordinates it reads: use error: certify or direct"
            )
    return first


def reduction_nodes(
    op: str, j: int, support: Sequence[int], x_grids: Sequence[UniformGrid], w_grid: UniformGrid, z_start: int,
) -> tuple[list[NodeRelation], dict[str, UniformGrid]]:
    """The exact node tree of ``w_j = op(x[support])`` (module docstring): nodes in post-order, the final
    node ``w{j}`` last, and the grid of every intermediate variable (``z{z_start}``, ... in creation order).

    Raises
    ------
    SpecError
        The coordinates of the support do not share one grid.
    """
    support = sorted(int(i) for i in support)
    grid = _common_grid(j, support, x_grids)
    reduce = REDUCTIONS[op]
    nodes: list[NodeRelation] = []
    z_grids: dict[str, UniformGrid] = {}
    counter = [z_start]

    def index_table(k: int) -> np.ndarray:
        """``op`` of the input cell indices over the product of ``k`` copies of the grid."""
        mesh = np.meshgrid(*([np.arange(grid.size, dtype=np.int32)] * k), indexing="ij")
        return reduce(np.stack(mesh, axis=-1), axis=-1).astype(np.int32)

    def build(items: list[int]) -> str:
        # Post-order: both halves (and their nodes) before the node that reads them.
        if len(items) == 1:
            return f"x{items[0]}"
        half = (len(items) + 1) // 2
        inputs = (build(items[:half]), build(items[half:]))
        name = f"z{counter[0]}"
        counter[0] += 1
        K = index_table(2)
        nodes.append(NodeRelation(name, grid, inputs, (grid, grid), None, K, K.copy(), 0.0))
        z_grids[name] = grid
        return name

    if len(support) > 2:
        half = (len(support) + 1) // 2
        inputs: tuple[str, ...] = (build(support[:half]), build(support[half:]))
    else:
        inputs = tuple(f"x{i}" for i in support)
    K = index_table(len(inputs))
    lo_v, hi_v = grid.clipped_cells(np.arange(grid.size)[:, None])
    c, r = cell_bounds(grid)
    margin = FP_RTOL * float((np.abs(c) + r).max()) + FP_ATOL
    lo, hi = clip_range(w_grid, lo_v[K, 0] - margin, hi_v[K, 0] + margin)
    nodes.append(NodeRelation(f"w{j}", w_grid, inputs, (grid,) * len(inputs), None, lo, hi, 0.0))
    return nodes, z_grids
