"""Node relations (Algorithm 3, line 8): one relation per MDec node on a grid of dimension ``<= sigma``.

* :func:`linear_node`: a node of ``M̄`` (its weights, intercept and ``eps``) on the product of its input grids.
* :func:`intermediate_grid`: an intermediate ``z`` lives on a covering grid of the interval range of its partial
  sum (MDec uses partial sums, see :mod:`pipelines.interconnection.mdec`), spacing ``intermediate_eta``
  (default: the spacing of its output's grid).
* :func:`covers_box` and :func:`box_node`: an output whose certified range ``M̄_j x + b_j ± eps_j`` covers its
  whole internal box at every state of the state box allows every cell whatever the state, and so does every
  node tree MDec would build for it (below). It is then one node without inputs. This is what ``max(x)`` of
  many coordinates gets: any affine ``M̄_j`` leaves ``eps_j >= 16 (n - 1) / n`` on ``[0, 32]^n`` (the error at
  ``0``, at ``32 e_i`` and at ``32 · 1`` cannot all be smaller), and ``certify`` on one cell (``n >= 22``)
  adds ``L_M`` times the half-width, 16, on top; building the tree would cost 33^4 entries per leaf for no
  information.
* :func:`direct_node` (``direct`` mode, beyond the paper): an output whose support has at most ``sigma``
  coordinates gets one node built straight from the black box, like a static subsystem (docs/method.md §2 ``hull``):
  per support cell, ``M_j`` is sampled on a sub-grid of ``samples_per_cell`` points (sub-cell spacing ``h``)
  and the node allows the cells meeting ``[min - L_M ||h/2||_inf, max + L_M ||h/2||_inf]``. Its reported
  ``eps_j`` is that margin (the largest over cells), *not* a bound on ``|M_j - M̄_j x - b_j|``.

Relations are clipped to the output grid. For ``z`` this is exact (the grid covers the range); for ``w_j`` it
relies on the declared internal box holding every value of ``M_j`` (Definition intercon), which
:class:`~pipelines.interconnection.sampling.Sampler` checks on every sample taken.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np

from pipelines.errors import SpecError
from pipelines.grid import UniformGrid
from pipelines.interconnection.certification import FP_ATOL, FP_RTOL
from pipelines.interconnection.grids import axis_grid, cell_bounds, clip_range, subgrid_counts, unravel
from pipelines.interconnection.mdec import NodePlan
from pipelines.interconnection.node_relations import NodeRelation
from pipelines.interconnection.sampling import Sampler

__all__ = ["linear_node", "direct_node", "intermediate_grid", "covers_box", "box_node", "MAX_NODE_ENTRIES",
           "DIRECT_ROWS"]

#: Largest number of entries of one node relation (product of its input grid sizes).
MAX_NODE_ENTRIES = 50_000_000
#: Points per call of one output in ``direct`` mode: small enough that the expression's temporaries stay in
#: cache and are reused by the allocator (large fresh arrays cost page faults on every call).
DIRECT_ROWS = 131_072


def _check_entries(name: str, grids: Sequence[UniformGrid]) -> None:
    entries = math.prod(g.size for g in grids)
    if entries > MAX_NODE_ENTRIES:
        raise SpecError(
            f"interconnection node {name} reads grids of sizes {[g.size for g in grids]} ({entries} combinations, "
            f"more than {MAX_NODE_ENTRIES}); use a coarser intermediate_eta or a smaller sigma"
        )


def linear_node(
    plan: NodePlan,
    output_grid: UniformGrid,
    input_grids: Sequence[UniformGrid],
    intercept: float,
    eps: float,
) -> NodeRelation:
    """Relation of one linear node (Algorithm 3, line 8, on a grid of dimension ``<= sigma``).

    For every combination of input cells (clipped cells: centre ``c_k``, half-width ``r_k``) the value lies in
    ``b + sum_k a_k c_k ± (sum_k |a_k| r_k + eps)``, widened by a relative ``FP_RTOL`` margin; the node allows
    the output cells meeting that interval. Vectorised over the product of the input grids.
    """
    _check_entries(plan.output, input_grids)
    k = len(input_grids)
    centre = np.full((1,) * k, float(intercept))
    radius = np.full((1,) * k, float(eps))
    scale = abs(intercept) + eps
    for d, (g, a) in enumerate(zip(input_grids, plan.weights)):
        c, r = cell_bounds(g)
        shape = [1] * k
        shape[d] = g.size
        centre = centre + a * c.reshape(shape)
        radius = radius + abs(a) * r.reshape(shape)
        scale += abs(a) * float((np.abs(c) + r).max())
    margin = FP_RTOL * scale + FP_ATOL
    full = tuple(g.size for g in input_grids)
    lo, hi = clip_range(output_grid, np.broadcast_to(centre - radius - margin, full),
                         np.broadcast_to(centre + radius + margin, full))
    return NodeRelation(
        plan.output, output_grid, plan.inputs, tuple(input_grids), tuple(plan.weights), lo, hi,
        float(eps) if plan.is_final else 0.0,
    )


def covers_box(
    output_grid: UniformGrid, row: np.ndarray, intercept: float, eps: float, lb: np.ndarray, ub: np.ndarray
) -> bool:
    """Whether ``[M̄_j x + b_j - eps_j, M̄_j x + b_j + eps_j]`` holds the output's box for every ``x`` in ``[lb, ub]``.

    Then the MDec tree of the output allows every cell of its grid at every state: for any combination of
    intermediate cells, its final node's interval reaches below the smallest and above the largest value of
    ``M̄_j x + b_j`` over the box widened by ``eps_j`` (each ``z`` cell meets the range of its partial sum), so
    it meets every cell, and the grid's cells are those meeting the box. :func:`box_node` is then the same
    relation. (Where rounding decides the comparison, the box node allows at least what the tree allows:
    never less, so never unsound.)
    """
    row = np.asarray(row, dtype=float)
    low = float(intercept + np.minimum(row * lb, row * ub).sum())
    high = float(intercept + np.maximum(row * lb, row * ub).sum())
    return low + eps >= output_grid.ub[0] and high - eps <= output_grid.lb[0]


def box_node(output: str, output_grid: UniformGrid, eps: float) -> NodeRelation:
    """A final node without inputs that allows every cell of its grid (see :func:`covers_box`)."""
    return NodeRelation(
        output, output_grid, (), (), (), np.array(0, dtype=np.int32), np.array(output_grid.size - 1, dtype=np.int32),
        float(eps),
    )


def direct_node(
    sample: Sampler, j: int, support: Sequence[int], L: float, samples_per_cell: int, extra: float
) -> tuple[NodeRelation, float]:
    """Node ``w_j`` built straight from the black box on its support (beyond the paper; docs/method.md §2 ``hull``).

    Per support cell (clipped), ``M_j`` is sampled at the centres of a sub-grid of at most
    ``samples_per_cell`` sub-cells (spacing ``h``, non-support coordinates at the box centre); every point of
    the cell is within ``h/2`` of a sample, so ``M_j`` lies in ``[min - m, max + m]`` with
    ``m = L_M ||h/2||_inf + extra`` (``extra``: largest change seen when the non-support coordinates moved).

    The non-support coordinates are held at the centre on the strength of the support validation (all of them
    resampled at once on ``holdout`` states moved ``M_j`` by at most ``extra``, which is in the margin); how
    ``M_j`` is evaluated does not touch that argument. Where the map allows it only output ``j`` is evaluated
    (:meth:`Sampler.column`: entry ``j`` of a list map, compiled alone), on states laid out transposed,
    ``(n, points)``, in a buffer whose non-support rows are written once; the points are ordered sample-major
    (sub-grid point, then cell), so the extremes per cell are reductions over the leading axis. Sample values,
    map values and extremes are the same numbers as when the whole map was evaluated on ``(points, n)`` rows
    (the entry is the same compiled closure; IEEE arithmetic and ``sqrt`` do not depend on memory layout, and
    the tests find identical nodes on maps with ``exp`` and ``tanh`` too); any difference of a transcendental
    function in the last bit would be covered by the relative margin ``FP_RTOL`` below.

    Returns ``(node, largest margin m)``.
    """
    grid = sample.network.composed_state_grid()
    grids = [axis_grid(grid, i) for i in support]
    _check_entries(f"w{j}", grids)
    output_grid = sample.network.internal_grids[j]
    s = len(support)
    counts = subgrid_counts(samples_per_cell, s)
    unit = [(np.arange(q) + 0.5) / q for q in counts]
    offsets = np.stack([g.ravel() for g in np.meshgrid(*unit, indexing="ij")], -1) if s else np.zeros((1, 0))
    Q = offsets.shape[0]
    bounds = [g.clipped_cells(np.arange(g.size)[:, None]) for g in grids]
    shape = tuple(g.size for g in grids)
    total = math.prod(shape)
    lo = np.empty(total, dtype=np.int32)
    hi = np.empty(total, dtype=np.int32)
    worst_margin = 0.0
    evaluate, _ = sample.column(j)
    step = max(1, DIRECT_ROWS // Q)
    xt_buf = np.empty((sample.lb.size, Q * min(step, total)))
    xt_buf[...] = sample.centre[:, None]  # non-support coordinates: the box centre, for every block
    for start in range(0, total, step):
        flat = np.arange(start, min(total, start + step))
        F = flat.size
        idx = unravel(flat, shape)
        xt = xt_buf[:, : Q * F]
        h_max = np.zeros(F)
        for d, i in enumerate(support):
            c_lo = bounds[d][0][idx[d], 0]
            width = bounds[d][1][idx[d], 0] - c_lo
            h = width / counts[d]
            h_max = np.maximum(h_max, h)
            xt[i].reshape(Q, F)[...] = c_lo[None, :] + offsets[:, d, None] * width[None, :]
        y = evaluate(xt).reshape(Q, F)
        margin = L * h_max / 2 + extra
        worst_margin = max(worst_margin, float(margin.max(initial=0.0)))
        vmin, vmax = y.min(axis=0), y.max(axis=0)
        fp = FP_RTOL * np.maximum(np.abs(vmin), np.abs(vmax)) + FP_ATOL
        lo[flat], hi[flat] = clip_range(output_grid, vmin - margin - fp, vmax + margin + fp)
    node = NodeRelation(
        f"w{j}", output_grid, tuple(f"x{i}" for i in support), tuple(grids), None,
        lo.reshape(shape), hi.reshape(shape), worst_margin,
    )
    return node, worst_margin


def intermediate_grid(
    plan: NodePlan, input_ranges: Sequence[tuple[float, float]], eta: float
) -> UniformGrid:
    """Covering grid of the interval range of a partial sum ``sum_k a_k v_k`` with ``v_k ∈ [l_k, u_k]``."""
    lo = hi = 0.0
    scale = 0.0
    for a, (low, high) in zip(plan.weights, input_ranges):
        lo += min(a * low, a * high)
        hi += max(a * low, a * high)
        scale += abs(a) * max(abs(low), abs(high))
    margin = FP_RTOL * scale + FP_ATOL
    return UniformGrid.covering(lo - margin, hi + margin, eta, name=f"intermediate variable {plan.output}")
