"""Interconnection abstraction (Section 4.2: lasso, Lemma lem1, Algorithm 2 MDec, Algorithm 3 IA).

Paper references name the labels of its source, because its printed numbering is ambiguous: Eq. (lasso) is
the lasso problem, Lemma lem1 the error bound with Eq. (eps_hat), Eq. (e_func) the DAG edges, Theorem
thrm_inter the soundness of IA ("Theorem 4.7" in METHOD), Definition intercon the interconnection map.

The map ``M`` (all states -> all internal variables) is a black box. We learn a sparse linear map ``M̄`` and
intercept ``b`` from samples, certify per output ``j`` an error bound ``eps_j`` with
``|M_j(x) - M̄_j x - b_j| <= eps_j`` on the whole state box, decompose ``M̄`` into nodes of in-degree
``<= sigma`` (MDec), and build one relation per node on its low-dimensional input grid. The abstraction is
``M̂(x̂) = {ŵ : ∃ẑ. ∧_node R_node}``. Soundness (Theorem thrm_inter): for every concrete ``x`` in
``cell(x̂)``, every cell containing ``M(x)`` is in ``M̂(x̂)``.

Departures from the paper (METHOD §4), and why
-----------------------------------------------
* Algorithm 3 as printed loops over every ``x̂`` of the full product grid, which is exponential in ``N``.
  Here ``eps_j`` is certified on the support of row ``j`` only, and every relation is enumerated on the
  product of at most ``sigma`` one-dimensional grids.
* ``eps_j`` is a single bound per output, computed soundly per mode (``error`` in the spec):

  - ``linear`` (the spec declares ``M`` affine): ``M̄`` is identified exactly; ``eps_j = 2 * max held-out
    residual + a floating-point margin``. A residual above ``1e-9`` relative to the output scale refutes the
    declaration (:class:`CertificationError`, "not linear").
  - ``certify`` (Lemma lem1 made sound, needs ``L_M``): on the grid of the support coordinates (or a coarser
    uniform partition with at most ``max_certify_cells`` cells, down to one cell),
    ``|M_j(x) - M̄_j x - b_j| <= |M_j(c) - M̄_j c - b_j| + L_M ||r||_inf + sum_i |M̄_ji| r_i`` on a cell with
    centre ``c`` and half-widths ``r`` (the paper's Eq. (eps_hat) with the neighbourhood a cell, and with the
    linear part bounded over the cell instead of at one point). ``eps_j`` is the maximum over cells.
  - ``direct`` (beyond the paper): an output whose support has at most ``sigma`` coordinates gets one node
    built straight from the black box, like a static subsystem (METHOD §2 ``hull``): per support cell, ``M_j``
    is sampled on a sub-grid of ``samples_per_cell`` points (sub-cell spacing ``h``) and the node allows the
    cells meeting ``[min - L_M ||h/2||_inf, max + L_M ||h/2||_inf]``. Its reported ``eps_j`` is that margin
    (the largest over cells), *not* a bound on ``|M_j - M̄_j x - b_j|``. An output whose support exceeds
    ``sigma`` falls back to ``certify`` + MDec (recorded per output in ``output_modes``).
* Lasso alone over-selects: with ``alpha = 'cv'`` on the tank map and ``N_I = 80`` it typically keeps several
  spurious coordinates (e.g. 7 for ``w6 = sqrt(x4)``), because cross-validation tunes prediction, not
  support recovery; it did not miss a true coordinate in the cases tried. Lasso's support is
  therefore only a candidate set: a candidate ``x_i`` is dropped when resampling ``x_i`` alone on ``holdout``
  random states never changes ``M_j`` (relative ``1e-9``). The surviving support is then validated jointly
  (all other coordinates resampled together); a dependence lasso missed is an error ("lower alpha").
  The largest change seen in that joint test (normally exactly 0) is added to ``eps_j`` in ``certify`` and
  ``direct`` modes, so a dependence below the tolerance is still covered.
* After lasso, ``M̄_j`` and ``b_j`` are refitted by ordinary least squares on the support, so that a linear map
  is identified exactly (lasso shrinks its coefficients). ``alpha`` is scikit-learn's (its objective divides
  the squared error by ``2 N``, unlike Eq. (lasso)).
* MDec uses partial sums (see :mod:`pipelines.interconnection.mdec`); an intermediate ``z`` lives on a covering grid of the
  interval range of its partial sum, spacing ``intermediate_eta`` (default: the spacing of its output's grid).
* Relations are clipped to the output grid. For ``z`` this is exact (the grid covers the range); for ``w_j`` it
  relies on the declared internal box holding every value of ``M_j`` (Definition intercon), which is checked on
  every sample taken; a map value outside the box is a :class:`SpecError`.
* A given ``L_M`` is checked against slopes observed on random nearby pairs (METHOD §3); a larger slope is a
  :class:`LipschitzError`. In ``certify`` mode a held-out residual above ``eps_j`` is one too.

Representation
--------------
Every node is a :class:`NodeRelation`: for each cell of the product of its input grids (row-major, one axis
per input), the inclusive range ``[lo, hi]`` of output cell indices; ``lo > hi`` is an empty range. A node
without inputs (a constant output) has ``lo``/``hi`` of shape ``()``. Inputs are named ``"x5"`` (coordinate 5
of the composed state, indexed on that coordinate's state grid) or ``"z0"``; outputs ``"w3"`` or ``"z0"``.
"""

from __future__ import annotations

import ast
import itertools
import math
import time
import warnings
from dataclasses import dataclass, field
from typing import Callable, Sequence

import numpy as np

from pipelines.blackbox import BlackBox
from pipelines.errors import CertificationError, LipschitzError, SpecError
from pipelines.grid import UniformGrid
from pipelines.interconnection.mdec import NodePlan, mdec
from pipelines.network import Network

#: Largest number of cells of the support grid on which ``certify`` evaluates ``M`` (METHOD §4).
MAX_CERTIFY_CELLS = 4_000_000
#: Largest number of entries of one node relation (product of its input grid sizes).
MAX_NODE_ENTRIES = 50_000_000
#: Points per call of the black box (bounds memory: a call holds ``(rows, n)`` and ``(rows, p)`` floats).
EVAL_ROWS = 400_000
#: Points per call of one output in ``direct`` mode: small enough that the expression's temporaries stay in
#: cache and are reused by the allocator (large fresh arrays cost page faults on every call).
DIRECT_ROWS = 131_072
#: Relative change of ``M_j`` that counts as "depends on this coordinate".
DEPENDENCE_RTOL = 1e-9
#: Relative held-out residual above which a map declared linear is refuted.
LINEAR_RTOL = 1e-9
#: Relative floating-point margin added to every bound (values are sums of a few float64 products).
FP_RTOL = 1e-12
#: Absolute floor of the floating-point margin.
FP_ATOL = 1e-300
#: Rows per batch in :meth:`InterconnectionAbstraction.contains`.
CONTAINS_ROWS = 16_384
#: Largest number of combinations of intermediate cells enumerated for one node in ``contains``.
MAX_COMBINATIONS = 1_000_000

Progress = Callable[[str, int, int, str], None]


# ====================================================================================== data model
@dataclass(frozen=True, eq=False)
class NodeRelation:
    """Relation between at most ``sigma`` input variables and one output variable (a node of MDec's DAG).

    Attributes
    ----------
    output : str
        ``"w3"`` (internal variable 3) or ``"z0"`` (intermediate variable 0).
    output_grid : UniformGrid
        1-D grid of the output.
    inputs : tuple of str, length k <= sigma
        ``"x5"`` (composed-state coordinate 5) or ``"z0"``.
    input_grids : tuple of UniformGrid, length k
        1-D each.
    weights : tuple of float or None
        Linear weights of the inputs (``None`` for a ``direct`` node built from the black box).
    lo, hi : ndarray of int32, shape ``tuple(g.size for g in input_grids)`` (``()`` when k = 0)
        First and last allowed output cell index per input cell combination; ``lo > hi`` means none.
    error_bound : float
        ``eps`` added at this node (0 for ``z`` nodes; for ``direct`` nodes the sampling margin).
    """

    output: str
    output_grid: UniformGrid
    inputs: tuple[str, ...]
    input_grids: tuple[UniformGrid, ...]
    weights: tuple[float, ...] | None
    lo: np.ndarray
    hi: np.ndarray
    error_bound: float

    def __post_init__(self) -> None:
        shape = tuple(g.size for g in self.input_grids)
        if len(self.inputs) != len(self.input_grids):
            raise ValueError(f"node {self.output}: {len(self.inputs)} inputs but {len(self.input_grids)} grids")
        if self.lo.shape != shape or self.hi.shape != shape:
            raise ValueError(f"node {self.output}: lo/hi have shape {self.lo.shape}, expected {shape}")

    @property
    def entries(self) -> int:
        """Number of input cell combinations (the size of the relation's domain)."""
        return int(self.lo.size)

    def mean_cells(self) -> float:
        """Average number of output cells allowed per input combination."""
        return float(np.maximum(self.hi.astype(np.int64) - self.lo + 1, 0).mean())

    def describe(self) -> dict:
        return {
            "output": self.output,
            "inputs": list(self.inputs),
            "weights": None if self.weights is None else [float(a) for a in self.weights],
            "input_sizes": [g.size for g in self.input_grids],
            "output_size": self.output_grid.size,
            "entries": self.entries,
            "mean_cells": self.mean_cells(),
            "error_bound": float(self.error_bound),
        }


@dataclass(frozen=True, eq=False)
class InterconnectionAbstraction:
    """The abstract interconnection ``M̂`` (Algorithm 3, Theorem thrm_inter) as a forest of node relations.

    Attributes
    ----------
    mode : str
        ``'linear'``, ``'certify'`` or ``'direct'`` (the spec's ``error``).
    M_bar : ndarray, shape (p, n_total)
        Learned linear map (lasso support, least-squares refit); a zero row for a constant output.
    supports : tuple of p tuples of int
        Per output, the state coordinates it depends on (increasing).
    offsets : ndarray, shape (p,)
        Intercepts ``b_j``.
    error_bounds : ndarray, shape (p,)
        ``eps_j``: a certified bound on ``|M_j(x) - M̄_j x - b_j|`` for ``linear``/``certify`` outputs; the
        sampling margin of the node for ``direct`` outputs (see the module docstring).
    nodes : tuple of NodeRelation
        Topological order (a ``z`` node before the node that reads it); exactly one ``w{j}`` node per output.
    intermediate_grids : dict of str to UniformGrid
        Grid of each ``z``.
    output_modes : tuple of str
        Per output, how it was abstracted (``direct`` mode falls back to ``certify`` above ``sigma``).
    details : dict
        JSON-ready diagnostics: lasso alphas and candidate supports, residuals, certify resolutions, timings.
    """

    mode: str
    M_bar: np.ndarray
    supports: tuple[tuple[int, ...], ...]
    offsets: np.ndarray
    error_bounds: np.ndarray
    nodes: tuple[NodeRelation, ...]
    intermediate_grids: dict[str, UniformGrid]
    output_modes: tuple[str, ...] = ()
    details: dict = field(default_factory=dict)

    def __post_init__(self) -> None:
        # contains() computes ∃z exactly bottom-up, which requires every z to be read by exactly one node
        # (a forest); check it here rather than trust the builder.
        produced: set[str] = set()
        readers: dict[str, int] = {}
        for node in self.nodes:
            for name in node.inputs:
                if name.startswith("z"):
                    if name not in produced:
                        raise ValueError(f"node {node.output} reads {name} before it is produced")
                    readers[name] = readers.get(name, 0) + 1
            if node.output in produced:
                raise ValueError(f"{node.output} is produced twice")
            produced.add(node.output)
        for name in produced:
            if name.startswith("z") and readers.get(name, 0) != 1:
                raise ValueError(f"{name} is read by {readers.get(name, 0)} nodes; exactly one is required")
        finals = [n.output for n in self.nodes if n.output.startswith("w")]
        if sorted(finals) != sorted(f"w{j}" for j in range(self.p)):
            raise ValueError(f"final nodes {finals} do not match the {self.p} outputs")

    # ------------------------------------------------------------------ sizes
    @property
    def p(self) -> int:
        return int(self.M_bar.shape[0])

    @property
    def n(self) -> int:
        return int(self.M_bar.shape[1])

    def final_node(self, j: int) -> NodeRelation:
        return next(node for node in self.nodes if node.output == f"w{j}")

    # ------------------------------------------------------------------ queries
    def allowed_cells(self, x_idx: np.ndarray) -> list[np.ndarray]:
        """The sets ``M̂_j(x̂)``: per output, which cells of internal grid ``j`` are allowed.

        ``∃z`` is decided exactly: bottom-up, each ``z`` node's set of allowed cells is the union of its
        relation's ranges over the allowed cells of the ``z`` it reads (every ``z`` has one reader, so the
        choices are independent). No interval hull is taken.

        Parameters
        ----------
        x_idx : ndarray of int, shape (B, n_total)
            Per-coordinate cell indices on the state grids.

        Returns
        -------
        list of p ndarrays of bool, shape (B, size_j)
        """
        x_idx = self._check_x(x_idx)
        B = x_idx.shape[0]
        out = [np.zeros((B, self.final_node(j).output_grid.size), dtype=bool) for j in range(self.p)]
        for start in range(0, B, CONTAINS_ROWS):
            stop = min(B, start + CONTAINS_ROWS)
            masks = self._masks(x_idx[start:stop])
            for j in range(self.p):
                out[j][start:stop] = masks[f"w{j}"]
        return out

    def contains(self, x_idx: np.ndarray, w_idx: np.ndarray) -> np.ndarray:
        """Whether ``ŵ ∈ M̂(x̂)`` (exact ``∃z. ∧ R_node``).

        Parameters
        ----------
        x_idx : ndarray of int, shape (B, n_total)
            Per-coordinate cell indices on the state grids.
        w_idx : ndarray of int, shape (B, p)
            Cell indices on the internal grids; an index off the grid is not contained.

        Returns
        -------
        ndarray of bool, shape (B,)
        """
        x_idx = self._check_x(x_idx)
        w_idx = np.asarray(w_idx, dtype=np.int64)
        if w_idx.ndim != 2 or w_idx.shape != (x_idx.shape[0], self.p):
            raise ValueError(f"w_idx has shape {w_idx.shape}, expected ({x_idx.shape[0]}, {self.p})")
        B = x_idx.shape[0]
        result = np.ones(B, dtype=bool)
        for start in range(0, B, CONTAINS_ROWS):
            stop = min(B, start + CONTAINS_ROWS)
            masks = self._masks(x_idx[start:stop])
            rows = np.arange(stop - start)
            for j in range(self.p):
                m = masks[f"w{j}"]
                w = w_idx[start:stop, j]
                on_grid = (w >= 0) & (w < m.shape[1])
                result[start:stop] &= on_grid & m[rows, np.clip(w, 0, m.shape[1] - 1)]
        return result

    def _check_x(self, x_idx: np.ndarray) -> np.ndarray:
        x_idx = np.asarray(x_idx, dtype=np.int64)
        if x_idx.ndim != 2 or x_idx.shape[1] != self.n:
            raise ValueError(f"x_idx has shape {x_idx.shape}, expected (B, {self.n})")
        sizes = self.details.get("state_sizes")
        if sizes is not None and x_idx.size and (np.any(x_idx < 0) or np.any(x_idx >= np.asarray(sizes))):
            raise ValueError("x_idx holds a cell index off the state grid")
        return x_idx

    def _masks(self, x_idx: np.ndarray) -> dict[str, np.ndarray]:
        """Allowed output cells of every node for a batch, shape (B, output size) each (see allowed_cells)."""
        B = x_idx.shape[0]
        masks: dict[str, np.ndarray] = {}
        rows = np.arange(B)
        for node in self.nodes:
            size = node.output_grid.size
            fixed: list[np.ndarray | None] = []
            z_parts: list[tuple[int, np.ndarray, np.ndarray, np.ndarray]] = []
            for k, name in enumerate(node.inputs):
                if name.startswith("x"):
                    fixed.append(x_idx[:, int(name[1:])])
                else:
                    m = masks.pop(name)  # read by this node only
                    any_ = m.any(axis=1)
                    first = np.argmax(m, axis=1)
                    last = m.shape[1] - 1 - np.argmax(m[:, ::-1], axis=1)
                    width = np.where(any_, last - first + 1, 0)
                    fixed.append(None)
                    z_parts.append((k, m, first, width))
            if not z_parts:  # one range per row: compare, no difference array (np.add.at was most of the audit)
                lo = np.broadcast_to(node.lo[tuple(fixed)], (B,))
                hi = np.broadcast_to(node.hi[tuple(fixed)], (B,))
                cells = np.arange(size)
                masks[node.output] = (cells >= lo[:, None]) & (cells <= hi[:, None])
                continue
            widths = [int(w.max(initial=0)) for _, _, _, w in z_parts]
            if math.prod(widths) > MAX_COMBINATIONS:
                raise ValueError(
                    f"node {node.output}: {math.prod(widths)} combinations of intermediate cells to enumerate; "
                    "use a coarser intermediate_eta"
                )
            diff = np.zeros((B, size + 1), dtype=np.int32)
            for offsets in itertools.product(*(range(w) for w in widths)):
                idx = list(fixed)
                valid = np.ones(B, dtype=bool)
                for (k, m, first, width), o in zip(z_parts, offsets):
                    cell = np.minimum(first + o, m.shape[1] - 1)
                    valid &= (o < width) & m[rows, cell]
                    idx[k] = cell
                lo = np.broadcast_to(node.lo[tuple(idx)], (B,))
                hi = np.broadcast_to(node.hi[tuple(idx)], (B,))
                valid &= lo <= hi
                r = rows[valid]
                # Difference array: +1 at lo, -1 after hi; a positive prefix sum marks the union of ranges. Each row
                # appears once per offset, so plain fancy-index updates are exact (no np.add.at needed).
                diff[r, lo[valid]] += 1
                diff[r, hi[valid] + 1] -= 1
            masks[node.output] = np.cumsum(diff, axis=1)[:, :size] > 0
        return masks

    # ------------------------------------------------------------------ reporting
    def describe(self) -> dict:
        """A JSON-ready description: mode, ``M̄``, supports, error bounds, nodes, intermediate grids."""
        return {
            "mode": self.mode,
            "output_modes": list(self.output_modes),
            "M_bar": self.M_bar.tolist(),
            "offsets": self.offsets.tolist(),
            "supports": [list(s) for s in self.supports],
            "error_bounds": self.error_bounds.tolist(),
            "nodes": [node.describe() for node in self.nodes],
            "intermediate_grids": {k: g.describe() for k, g in self.intermediate_grids.items()},
            "details": self.details,
        }


# ====================================================================================== sampling
def axis_grid(grid: UniformGrid, i: int) -> UniformGrid:
    """The 1-D grid of dimension ``i`` of a product grid."""
    return UniformGrid(
        origin=(grid.origin[i],), eta=(grid.eta[i],), k_lo=(grid.k_lo[i],), k_hi=(grid.k_hi[i],),
        lb=(grid.lb[i],), ub=(grid.ub[i],),
    )


def _cell_bounds(grid: UniformGrid) -> tuple[np.ndarray, np.ndarray]:
    """Centres and half-widths of every clipped cell of a 1-D grid, shape (size,) each.

    The clipped cell ``cell ∩ [lb, ub]`` holds every concrete value the cell stands for (METHOD §1).
    """
    lo, hi = grid.clipped_cells(np.arange(grid.size)[:, None])
    return (lo[:, 0] + hi[:, 0]) / 2, (hi[:, 0] - lo[:, 0]) / 2


class _Sampler:
    """Evaluates ``M`` in batches and checks every value against the internal boxes (Definition intercon)."""

    def __init__(self, network: Network) -> None:
        self.network = network
        self.map = network.interconnection_map
        grid = network.composed_state_grid()
        self.lb = np.asarray(grid.lb)
        self.ub = np.asarray(grid.ub)
        self.centre = (self.lb + self.ub) / 2
        self.w_lb = np.array([g.lb[0] for g in network.internal_grids])
        self.w_ub = np.array([g.ub[0] for g in network.internal_grids])
        self.evaluations = 0

    def uniform(self, count: int, rng: np.random.Generator) -> np.ndarray:
        """Uniform random states in the composed box, shape (count, n)."""
        return rng.uniform(self.lb, self.ub, (count, self.lb.size))

    def __call__(self, x: np.ndarray, columns: Sequence[int] | None = None) -> np.ndarray:
        """``M(x)``, shape (B, p), after checking ``columns`` (default all) lie in their internal boxes."""
        out = np.empty((x.shape[0], self.w_lb.size))
        for start in range(0, x.shape[0], EVAL_ROWS):
            xs = x[start : start + EVAL_ROWS]
            out[start : start + xs.shape[0]] = self.map(xs)
        self.evaluations += x.shape[0]
        cols = range(self.w_lb.size) if columns is None else columns
        for j in cols:
            self._check_box(j, out[:, j], lambda r: x[r])
        return out

    def _check_box(self, j: int, values: np.ndarray, point: Callable[[int], np.ndarray]) -> None:
        bad = (values < self.w_lb[j]) | (values > self.w_ub[j])
        if bad.any():
            r = int(np.argmax(bad))
            raise SpecError(
                f"interconnection map: internal variable w{j} = {float(values[r])!r} at x = {point(r).tolist()} lies "
                f"outside its box [{self.w_lb[j]}, {self.w_ub[j]}] (interconnection.internal[{j}]); the map "
                "must take its values in the internal boxes: widen that box"
            )

    def column(self, j: int) -> tuple[Callable[[np.ndarray], np.ndarray], bool]:
        """An evaluator of output ``j`` alone on states given transposed, ``xt`` of shape ``(n, B)`` -> ``(B,)``.

        The values are checked like :meth:`__call__` (finite, inside internal box ``j``). Where the map is a
        list literal ``[e_0, e_1, ...]`` of elementwise entries, row ``j`` of the map is entry ``j`` evaluated
        alone (``pipelines.expressions.compiler`` stacks the entries' values, one row each, each computed by its own compiled
        closure), so entry ``j`` is compiled on its own (through the same expression compiler, with the
        map's constants) and the other outputs are not computed. It is also checked to give the map's row
        ``j`` bit for bit on a few states. Otherwise (a vector expression, a module function, nested lists,
        any doubt) the whole map is evaluated and column ``j`` kept.

        Returns ``(evaluator, alone)``; ``alone`` says whether entry ``j`` is evaluated by itself.
        """
        entry = self._entry(j)

        def whole(xt: np.ndarray) -> np.ndarray:
            return self(xt.T, columns=[j])[:, j]

        if entry is None:
            return whole, False

        def alone(xt: np.ndarray) -> np.ndarray:
            y = entry(xt.T)[:, 0]
            self.evaluations += y.shape[0]
            self._check_box(j, y, lambda r: xt[:, r])
            return y

        return alone, True

    def _entry(self, j: int) -> BlackBox | None:
        """Entry ``j`` of a list-literal map as a black box of its own, or ``None`` (see :meth:`column`)."""
        from pipelines.spec.model import is_module_function

        source = self.map.source
        if is_module_function(source):
            return None
        try:
            text = source.lstrip()
            body = ast.parse(text, mode="eval").body
        except (SyntaxError, ValueError, RecursionError, MemoryError):  # pragma: no cover - the map compiled
            return None
        if not isinstance(body, (ast.List, ast.Tuple)) or len(body.elts) != self.w_lb.size:
            return None  # not one elementwise entry per output
        elt = body.elts[j]
        if isinstance(elt, (ast.List, ast.Tuple, ast.Starred)):
            return None
        segment = ast.get_source_segment(text, elt)
        if segment is None:  # pragma: no cover
            return None
        n = self.lb.size
        try:
            box = BlackBox(f"interconnection map (output w{j})", f"({segment})", {"x": n}, 1,
                           self.network.constants, ())
        except Exception:  # a vector entry (out_dim != 1), or anything unexpected: evaluate the whole map
            return None
        # Bit-for-bit agreement with the whole map on a few states (a local generator: the job's stream of
        # random numbers is not touched).
        probe = np.random.default_rng(j).uniform(self.lb, self.ub, (64, n))
        probe[0] = self.lb
        probe[1] = self.ub
        probe[2] = self.centre
        try:
            with np.errstate(all="ignore"):
                # the entry on states laid out as direct_node lays them out (transposed), the map as before
                same = np.array_equal(box(np.ascontiguousarray(probe.T).T)[:, 0], self.map(probe)[:, j])
        except Exception:  # e.g. a non-finite value at a probe: let the whole map report it
            return None
        return box if same else None


def _rel_change(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Whether ``a`` and ``b`` differ by more than ``DEPENDENCE_RTOL`` relative to their magnitude."""
    return np.abs(a - b) > DEPENDENCE_RTOL * np.maximum(np.abs(a), np.abs(b))


# ====================================================================================== step 1: lasso
def _lasso_row(X: np.ndarray, y: np.ndarray, alpha: float | str) -> tuple[np.ndarray, float | None]:
    """Lasso (Eq. (lasso)) for one output row: coefficients (n,) and the alpha used (None for a constant row)."""
    from sklearn.exceptions import ConvergenceWarning
    from sklearn.linear_model import Lasso, LassoCV

    if np.ptp(y) <= 1e-12 * np.abs(y).max(initial=0.0):
        # A constant output (the tanks' w_1 = 0): no coordinate explains it, and LassoCV's alpha grid
        # degenerates to zero on it.
        return np.zeros(X.shape[1]), None
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", ConvergenceWarning)
        if alpha == "cv":
            model = LassoCV(cv=min(5, X.shape[0]), max_iter=100_000, n_jobs=1).fit(X, y)
            used = float(model.alpha_)
        else:
            model = Lasso(alpha=float(alpha), max_iter=100_000).fit(X, y)
            used = float(alpha)
    return np.asarray(model.coef_, dtype=float), used


def _support_of(coef: np.ndarray) -> tuple[int, ...]:
    """Indices of the nonzero coefficients (``|coef| > 1e-12 max|coef|``)."""
    big = np.abs(coef).max(initial=0.0)
    if big == 0:
        return ()
    return tuple(int(i) for i in np.flatnonzero(np.abs(coef) > 1e-12 * big))


def _refit(X: np.ndarray, y: np.ndarray, support: Sequence[int]) -> tuple[np.ndarray, float]:
    """Least squares with intercept on the support columns: row of ``M̄`` (n,) and ``b``."""
    row = np.zeros(X.shape[1])
    if not support:
        return row, float(np.mean(y))
    A = np.column_stack([X[:, list(support)], np.ones(X.shape[0])])
    sol, *_ = np.linalg.lstsq(A, y, rcond=None)
    row[list(support)] = sol[:-1]
    return row, float(sol[-1])


# ====================================================================================== step 2: supports
def _dependence(sample: _Sampler, count: int, rng: np.random.Generator) -> np.ndarray:
    """``D[i, j]``: whether ``M_j`` changed when coordinate ``i`` alone was resampled, shape (n, p).

    ``count`` random base states; for each coordinate a copy with that coordinate redrawn. Each evaluation
    serves every output; one coordinate at a time keeps memory at ``count * n`` floats.
    """
    n = sample.lb.size
    base = sample.uniform(count, rng)
    fresh = sample.uniform(count, rng)
    y0 = sample(base)
    dep = np.zeros((n, y0.shape[1]), dtype=bool)
    for i in range(n):
        moved = base.copy()
        moved[:, i] = fresh[:, i]
        dep[i] = _rel_change(y0, sample(moved)).any(axis=0)
    return dep


def _validate_support(
    sample: _Sampler, j: int, support: Sequence[int], dep: np.ndarray, count: int, rng: np.random.Generator
) -> float:
    """Check ``M_j`` does not depend on the coordinates outside its support; return the largest change.

    Every coordinate outside the support is redrawn at once on ``count`` random states.

    Raises
    ------
    CertificationError
        Naming the coordinate ``M_j`` depends on.
    """
    n = sample.lb.size
    outside = np.setdiff1d(np.arange(n), np.asarray(support, dtype=int))
    if outside.size == 0:
        return 0.0
    base = sample.uniform(count, rng)
    moved = base.copy()
    moved[:, outside] = sample.uniform(count, rng)[:, outside]
    y0 = sample(base)[:, j]
    y1 = sample(moved)[:, j]
    changed = _rel_change(y0, y1)
    if changed.any():
        culprits = [int(i) for i in outside if dep[i, j]]
        r = int(np.argmax(changed))
        which = f"coordinate x{culprits[0]}" if culprits else f"the coordinates {outside.tolist()} jointly"
        raise CertificationError(
            f"interconnection output w{j} depends on {which}, which lasso left out of its support "
            f"{list(support)}: M_{j} changed from {float(y0[r])!r} to {float(y1[r])!r} when it was resampled; "
            "lower alpha (or use 'cv') or give more samples"
        )
    return float(np.abs(y1 - y0).max(initial=0.0))


def _check_lipschitz(sample: _Sampler, L: float, count: int, rng: np.random.Generator) -> None:
    """Given ``L_M`` against slopes of random nearby pairs (METHOD §3): a larger slope is unsound.

    Pairs are ``x`` and ``x + d`` with ``d`` up to one cell width per coordinate (scaled down at random by up
    to 100), clipped to the box; the slope is ``|ΔM_j| / ||Δx||_inf``.
    """
    eta = np.asarray(sample.network.composed_state_grid().eta)
    x1 = sample.uniform(count, rng)
    scale = 10.0 ** rng.uniform(-2, 0, (count, 1))
    x2 = np.clip(x1 + rng.uniform(-1, 1, x1.shape) * eta * scale, sample.lb, sample.ub)
    dx = np.abs(x2 - x1).max(axis=1)
    keep = dx > 0
    x1, x2, dx = x1[keep], x2[keep], dx[keep]
    y1, y2 = sample(x1), sample(x2)
    dy = np.abs(y2 - y1)
    tol = FP_RTOL * np.maximum(np.abs(y1), np.abs(y2)) + FP_ATOL
    bad = dy > L * dx[:, None] * (1 + 1e-9) + tol
    if bad.any():
        r, j = np.unravel_index(int(np.argmax(bad)), bad.shape)
        slope = dy[r, j] / dx[r]
        raise LipschitzError(
            f"interconnection map output w{j}: slope {slope:.6g} between x = {x1[r].tolist()} and "
            f"x' = {x2[r].tolist()} exceeds the given Lipschitz constant L_M = {L} (infinity norm); the error "
            f"bound would be unsound: raise interconnection.lipschitz to at least {slope:.6g}"
        )


# ====================================================================================== step 3: eps
def _fp_margin(row: np.ndarray, b: float, xmax: float) -> float:
    """Floating-point margin for ``M̄_j x + b_j`` over the box (``xmax = max |x|``)."""
    return FP_RTOL * (np.abs(row).sum() * xmax + abs(b)) + FP_ATOL


def _eps_linear(
    j: int, row: np.ndarray, b: float, X: np.ndarray, Y: np.ndarray, xmax: float, n_support: int, n_train: int
) -> tuple[float, float]:
    """``eps_j`` of a map declared linear: ``2 * max held-out residual + fp margin``.

    ``X``, ``Y``: held-out states (H, n) and map values (H, p). Returns ``(eps_j, max residual)``.

    Raises
    ------
    CertificationError
        If the held-out residual exceeds ``LINEAR_RTOL`` of the output scale: the map is not linear.
    """
    res = np.abs(Y[:, j] - (X @ row + b))
    worst = float(res.max(initial=0.0))
    scale = max(float(np.abs(Y[:, j]).max(initial=0.0)), np.abs(row).sum() * xmax + abs(b))
    if worst > LINEAR_RTOL * scale:
        r = int(np.argmax(res))
        raise CertificationError(
            f"interconnection output w{j}: the map is declared linear (error: linear) but is not linear: "
            f"held-out residual {worst:.6g} (relative {worst / scale:.3g}) at x = {X[r].tolist()}; use "
            "error: certify with a Lipschitz constant"
            + (
                f" (or give more samples: {n_train} cannot identify {n_support} coefficients and an intercept)"
                if n_train <= n_support
                else ""
            )
        )
    return 2.0 * worst + _fp_margin(row, b, xmax), worst


def _certify_axes(
    grids: Sequence[UniformGrid], cap: int
) -> tuple[list[np.ndarray], list[np.ndarray], dict]:
    """Cells on which ``certify`` evaluates ``M``: per support axis, centres and half-widths.

    The state grids' clipped cells if their product has at most ``cap`` cells; otherwise a uniform partition
    of the support box into ``k`` parts per axis with ``k^s <= cap`` (down to ``k = 1``: one cell, the box).
    """
    sizes = [g.size for g in grids]
    if math.prod(sizes) <= cap:
        bounds = [_cell_bounds(g) for g in grids]
        info = {"source": "state grid", "cells_per_axis": sizes}
    else:
        s = len(grids)
        k = 1
        while (k + 1) ** s <= cap:
            k += 1
        bounds = []
        for g in grids:
            edges = np.linspace(g.lb[0], g.ub[0], k + 1)
            bounds.append(((edges[:-1] + edges[1:]) / 2, (edges[1:] - edges[:-1]) / 2))
        info = {"source": "uniform partition", "cells_per_axis": [k] * s}
    info["max_half_width"] = [float(r.max()) for _, r in bounds]
    return [c for c, _ in bounds], [r for _, r in bounds], info


def _eps_certify(
    sample: _Sampler,
    j: int,
    support: Sequence[int],
    row: np.ndarray,
    b: float,
    L: float,
    cap: int,
    xmax: float,
) -> tuple[float, dict]:
    """``eps_j`` from the Lipschitz bound on the support cells (Lemma lem1 made sound, METHOD §4).

    On a cell with centre ``c`` and half-widths ``r`` (support coordinates; the others are held at the box
    centre, which the support validation justifies):
    ``|M_j(x) - M̄_j x - b| <= |M_j(c) - M̄_j c - b| + L_M max_i r_i + sum_i |M̄_ji| r_i``.

    Returns ``(eps_j without the support-validation change, resolution info)``.
    """
    grid = sample.network.composed_state_grid()
    grids = [axis_grid(grid, i) for i in support]
    centres, radii, info = _certify_axes(grids, cap)
    a = row[list(support)]
    shape = tuple(c.size for c in centres)
    total = math.prod(shape)
    worst = 0.0
    for start in range(0, total, EVAL_ROWS):
        flat = np.arange(start, min(total, start + EVAL_ROWS))
        idx = _unravel(flat, shape)
        X = np.repeat(sample.centre[None], flat.size, axis=0)
        r_max = np.zeros(flat.size)
        lin_r = np.zeros(flat.size)
        for d, i in enumerate(support):
            X[:, i] = centres[d][idx[d]]
            r = radii[d][idx[d]]
            r_max = np.maximum(r_max, r)
            lin_r += abs(a[d]) * r
        y = sample(X, columns=[j])[:, j]
        bound = np.abs(y - (X @ row + b)) + L * r_max + lin_r
        worst = max(worst, float(bound.max(initial=0.0)))
    info["cells"] = total
    return worst + _fp_margin(row, b, xmax), info


def _unravel(flat: np.ndarray, shape: Sequence[int]) -> tuple[np.ndarray, ...]:
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


def _subgrid_counts(samples: int, s: int) -> list[int]:
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


# ====================================================================================== nodes
def _clip_range(grid: UniformGrid, lo_v: np.ndarray, hi_v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cells of a 1-D grid meeting ``[lo_v, hi_v]`` (any shape), clipped to the grid; ``lo > hi`` if none."""
    shape = np.shape(lo_v)
    first, last = grid.cells_touching(np.reshape(lo_v, (-1, 1)), np.reshape(hi_v, (-1, 1)))
    first = np.maximum(first[:, 0], 0)
    last = np.minimum(last[:, 0], grid.size - 1)
    return first.astype(np.int32).reshape(shape), last.astype(np.int32).reshape(shape)


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
        c, r = _cell_bounds(g)
        shape = [1] * k
        shape[d] = g.size
        centre = centre + a * c.reshape(shape)
        radius = radius + abs(a) * r.reshape(shape)
        scale += abs(a) * float((np.abs(c) + r).max())
    margin = FP_RTOL * scale + FP_ATOL
    full = tuple(g.size for g in input_grids)
    lo, hi = _clip_range(output_grid, np.broadcast_to(centre - radius - margin, full),
                         np.broadcast_to(centre + radius + margin, full))
    return NodeRelation(
        plan.output, output_grid, plan.inputs, tuple(input_grids), tuple(plan.weights), lo, hi,
        float(eps) if plan.is_final else 0.0,
    )


def direct_node(
    sample: _Sampler, j: int, support: Sequence[int], L: float, samples_per_cell: int, extra: float
) -> tuple[NodeRelation, float]:
    """Node ``w_j`` built straight from the black box on its support (beyond the paper; METHOD §2 ``hull``).

    Per support cell (clipped), ``M_j`` is sampled at the centres of a sub-grid of at most
    ``samples_per_cell`` sub-cells (spacing ``h``, non-support coordinates at the box centre); every point of
    the cell is within ``h/2`` of a sample, so ``M_j`` lies in ``[min - m, max + m]`` with
    ``m = L_M ||h/2||_inf + extra`` (``extra``: largest change seen when the non-support coordinates moved).

    The non-support coordinates are held at the centre on the strength of the support validation (all of them
    resampled at once on ``holdout`` states moved ``M_j`` by at most ``extra``, which is in the margin); how
    ``M_j`` is evaluated does not touch that argument. Where the map allows it only output ``j`` is evaluated
    (:meth:`_Sampler.column`: entry ``j`` of a list map, compiled alone), on states laid out transposed,
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
    counts = _subgrid_counts(samples_per_cell, s)
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
        idx = _unravel(flat, shape)
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
        lo[flat], hi[flat] = _clip_range(output_grid, vmin - margin - fp, vmax + margin + fp)
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
    for a, (l, u) in zip(plan.weights, input_ranges):
        lo += min(a * l, a * u)
        hi += max(a * l, a * u)
        scale += abs(a) * max(abs(l), abs(u))
    margin = FP_RTOL * scale + FP_ATOL
    return UniformGrid.covering(lo - margin, hi + margin, eta, name=f"intermediate variable {plan.output}")


# ====================================================================================== pipeline
def abstract_interconnection(
    network: Network,
    rng: np.random.Generator,
    progress: Progress | None = None,
    *,
    max_certify_cells: int = MAX_CERTIFY_CELLS,
) -> InterconnectionAbstraction:
    """Algorithm 3 (IA) without the exponential loop: lasso, support check, ``eps``, MDec, node relations.

    Parameters
    ----------
    network : Network
        Its ``interconnection_map`` maps states ``(B, n_total)`` to ``(B, p)``; its internal grids are 1-D.
    rng : numpy.random.Generator
        All sampling (training, hold-out, support checks) draws from it.
    progress : callable, optional
        ``progress(stage, done, total, message)`` with ``stage == "interconnection"``.
    max_certify_cells : int
        Cap on the cells ``certify`` evaluates per output (coarser uniform partition above it).

    Raises
    ------
    SpecError
        A map value outside its internal box; ``certify``/``direct`` without ``lipschitz``; ``sigma = 1`` with
        an output reading two variables; a node relation too large.
    CertificationError
        A dependence outside the learned support; a map declared linear that is not.
    LipschitzError
        ``L_M`` contradicted by the data.
    """
    ic = network.spec.interconnection
    report = progress or (lambda *_: None)
    t0 = time.perf_counter()
    mode = ic.error
    if mode in ("certify", "direct") and ic.lipschitz is None:
        raise SpecError(
            f"interconnection.error is '{mode}', which needs interconnection.lipschitz (L_M, infinity norm)"
        )
    if ic.alpha == "cv" and ic.samples < 4:
        raise SpecError(f"interconnection.samples is {ic.samples}; cross-validated lasso needs at least 4")
    L = float(ic.lipschitz) if ic.lipschitz is not None else None
    sample = _Sampler(network)
    n, p = sample.lb.size, sample.w_lb.size
    xmax = float(np.maximum(np.abs(sample.lb), np.abs(sample.ub)).max())
    steps = 4 + p
    report("interconnection", 0, steps, f"sampling the map ({ic.samples} states)")

    # 1. Samples and lasso (Eq. (lasso)), one row at a time.
    X = sample.uniform(ic.samples, rng)
    Y = sample(X)
    fits = [_lasso_row(X, Y[:, j], ic.alpha) for j in range(p)]
    lasso_supports = [_support_of(coef) for coef, _ in fits]
    report("interconnection", 1, steps, "lasso fitted")

    # 2. Supports: drop candidates M_j does not depend on, refit by least squares, validate the rest.
    # Lasso only sees linear correlation: an even function of a coordinate (0.3 x^2 on [-2, 2]) has none and
    # is left out. The one-coordinate-at-a-time dependence test sees any dependence, so it adds what lasso
    # missed (recorded in the report) instead of failing the job; the joint check below still certifies.
    dep = _dependence(sample, ic.holdout, rng)
    supports = [tuple(i for i in range(n) if dep[i, j]) for j in range(p)]
    added = [sorted(set(supports[j]) - set(lasso_supports[j])) for j in range(p)]
    M_bar = np.zeros((p, n))
    offsets = np.zeros(p)
    for j in range(p):
        M_bar[j], offsets[j] = _refit(X, Y[:, j], supports[j])
    moved = [_validate_support(sample, j, supports[j], dep, ic.holdout, rng) for j in range(p)]
    if mode in ("certify", "direct"):  # only where eps relies on L_M
        _check_lipschitz(sample, L, ic.holdout, rng)
    report("interconnection", 2, steps, f"supports {[list(s) for s in supports]}")

    # MDec (Algorithm 2) now, so that a sigma too small fails before the costly steps. A direct output gets
    # one node from the black box instead (an empty row here, replaced below).
    is_direct = [mode == "direct" and len(supports[j]) <= ic.sigma for j in range(p)]
    plans = mdec(M_bar, [() if is_direct[j] else supports[j] for j in range(p)], ic.sigma)

    # 3. Error bounds per output.
    X_hold = sample.uniform(ic.holdout, rng)
    Y_hold = sample(X_hold)
    eps = np.zeros(p)
    output_modes: list[str] = []
    residuals: list[float] = []
    resolution: dict[str, dict] = {}
    direct_nodes: dict[int, NodeRelation] = {}
    for j in range(p):
        res = np.abs(Y_hold[:, j] - (X_hold @ M_bar[j] + offsets[j]))
        residuals.append(float(res.max(initial=0.0)))
        if mode == "linear":
            eps[j], _ = _eps_linear(j, M_bar[j], offsets[j], X_hold, Y_hold, xmax, len(supports[j]), ic.samples)
            output_modes.append("linear")
        elif is_direct[j]:
            direct_nodes[j], eps[j] = direct_node(sample, j, supports[j], L, ic.samples_per_cell, moved[j])
            output_modes.append("direct")
        else:
            bound, resolution[f"w{j}"] = _eps_certify(
                sample, j, supports[j], M_bar[j], offsets[j], L, max_certify_cells, xmax
            )
            eps[j] = bound + moved[j]
            if residuals[-1] > eps[j]:
                raise LipschitzError(
                    f"interconnection output w{j}: held-out residual {residuals[-1]:.6g} exceeds the certified "
                    f"bound {eps[j]:.6g}; the Lipschitz constant L_M = {L} is too small"
                )
            output_modes.append("certify")
        report("interconnection", 3 + j, steps, f"w{j}: {output_modes[-1]}, eps = {eps[j]:.4g}")

    # 4-5. Grids of the intermediate variables and the node relations, in topological order.
    grid = network.composed_state_grid()
    x_grids = [axis_grid(grid, i) for i in range(n)]
    z_grids: dict[str, UniformGrid] = {}
    nodes: list[NodeRelation] = []
    for plan in plans:
        j = plan.target
        if j in direct_nodes:
            if plan.is_final:
                nodes.append(direct_nodes[j])
            continue
        in_grids = [x_grids[int(v[1:])] if v.startswith("x") else z_grids[v] for v in plan.inputs]
        if plan.is_final:
            nodes.append(linear_node(plan, network.internal_grids[j], in_grids, offsets[j], eps[j]))
        else:
            eta = ic.intermediate_eta or network.internal_grids[j].eta[0]
            z_grids[plan.output] = intermediate_grid(plan, [(g.lb[0], g.ub[0]) for g in in_grids], eta)
            nodes.append(linear_node(plan, z_grids[plan.output], in_grids, 0.0, 0.0))
    report("interconnection", steps, steps, f"{len(nodes)} nodes, {len(z_grids)} intermediate variables")

    details = {
        "alpha": [a for _, a in fits],
        "lasso_supports": [list(s) for s in lasso_supports],
        "support_added_by_dependence_test": added,
        "support_change": moved,
        "holdout_residual": residuals,
        "certify_resolution": resolution,
        "lipschitz": L,
        "sigma": ic.sigma,
        "evaluations": sample.evaluations,
        "seconds": time.perf_counter() - t0,
        "state_sizes": [g.size for g in x_grids],
    }
    return InterconnectionAbstraction(
        mode=mode,
        M_bar=M_bar,
        supports=tuple(tuple(s) for s in supports),
        offsets=offsets,
        error_bounds=eps,
        nodes=tuple(nodes),
        intermediate_grids=z_grids,
        output_modes=tuple(output_modes),
        details=details,
    )
