"""The abstract interconnection ``M̂`` as data: node relations and their composition (Theorem thrm_inter).

``M̂(x̂) = {ŵ : ∃ẑ. ∧_node R_node}``. Soundness (Theorem thrm_inter): for every concrete ``x`` in ``cell(x̂)``,
every cell containing ``M(x)`` is in ``M̂(x̂)``.

Representation
--------------
Every node is a :class:`NodeRelation`: for each cell of the product of its input grids (row-major, one axis
per input), the inclusive range ``[lo, hi]`` of output cell indices; ``lo > hi`` is an empty range. A node
without inputs (a constant output) has ``lo``/``hi`` of shape ``()``. Inputs are named ``"x5"`` (coordinate 5
of the composed state, indexed on that coordinate's state grid) or ``"z0"``; outputs ``"w3"`` or ``"z0"``.
Every ``z`` is read by exactly one node (MDec builds a forest), so :class:`InterconnectionAbstraction` decides
``∃z`` exactly, bottom-up.
"""

from __future__ import annotations

import itertools
import math
from dataclasses import dataclass, field

import numpy as np

from pipelines.grid import UniformGrid

__all__ = ["NodeRelation", "InterconnectionAbstraction", "CONTAINS_ROWS", "MAX_COMBINATIONS"]

#: Rows per batch in :meth:`InterconnectionAbstraction.contains`.
CONTAINS_ROWS = 16_384
#: Largest number of combinations of intermediate cells enumerated for one node in ``contains``.
MAX_COMBINATIONS = 1_000_000


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
        ``'linear'``, ``'certify'`` or ``'direct'`` (the spec's ``error``); ``'none'`` for a network without an
        interconnection (``p = 0``, no nodes).
    M_bar : ndarray, shape (p, n_total)
        Learned linear map (lasso support, least-squares refit); a zero row for a constant output.
    supports : tuple of p tuples of int
        Per output, the state coordinates it depends on (increasing).
    offsets : ndarray, shape (p,)
        Intercepts ``b_j``.
    error_bounds : ndarray, shape (p,)
        ``eps_j``: a certified bound on ``|M_j(x) - M̄_j x - b_j|`` for ``linear``/``certify`` outputs; the
        sampling margin of the node for ``direct`` outputs (see :mod:`pipelines.interconnection.nodes`).
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
        if all(n.output.startswith("w") and all(i.startswith("x") for i in n.inputs) for n in self.nodes):
            # every node reads states only (no MDec tree): ŵ_j's cells are one range per row, compared directly
            # (the masks of _masks cost 24 of 105 s of auditing a ring of 100 rooms)
            for node in self.nodes:
                at = tuple(x_idx[:, int(name[1:])] for name in node.inputs)
                w = w_idx[:, int(node.output[1:])]
                lo, hi = np.broadcast_to(node.lo[at], (B,)), np.broadcast_to(node.hi[at], (B,))
                result &= (w >= 0) & (w < node.output_grid.size) & (lo <= w) & (w <= hi)
            return result
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
