"""The exported form of a determinized controller, and the controller read back from its JSON.

A determinized controller maps each domain cell to one joint input (per-subsystem flat input indices) and says
"no input" elsewhere. It is kept in one of two exact forms, both evaluated on cell indices:

* :class:`BDDTable`: a reduced BDD over the current-state bits (CUDD's, complement edges included) with one
  root for the domain and one per input bit; a node is ``(var, low, high)`` and an edge is
  ``(node << 1) | complemented``, node 0 being the constant TRUE. As small as the BDD, whatever the state count.
* :class:`TreeTable`: an axis-aligned decision tree over the cell indices (``idx[feature] < threshold`` goes
  left), leaves naming a row of ``choices`` or ``-1`` (no input).

:func:`quantize` is the quantizer of :meth:`~pipelines.controller.Controller.cells` and of the C export: a state
on a cell boundary goes to the upper cell, or, per coordinate, to the lower one where the upper is off the grid
(the upper edge of the box on a cell boundary).
"""

from __future__ import annotations

import json
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipelines.errors import CompabsError
from pipelines.grid import UniformGrid

#: The determinization rules (:mod:`pipelines.export.determinize`), ``auto`` first, and what each does.
RULES = ("auto", "earliest_layer", "smallest_index")
RULE_TEXT = {
    "earliest_layer": "a cell first in layer k > 0 gets an input into the earliest layer it can reach in one step "
                      "(most progress), ties by the smallest input index; cells of layer 0 the smallest input "
                      "keeping the invariant (reach-and-stay) or the smallest valid input (a reach target)",
    "smallest_index": "the smallest admissible input index (per-subsystem flat input indices, lexicographic in "
                      "subsystem order)",
}
#: The export forms (:mod:`pipelines.export.emit`); ``auto`` is the one with fewer bytes.
FORMS = ("auto", "bdd", "tree")
#: Default cap on the rows of a CSV export (one row per domain cell).
CSV_MAX_ROWS = 100_000

#: ``format`` of a JSON export.
EXPORT_FORMAT = "compabs-controller/1"
#: Cells :meth:`BDDTable.evaluate` walks at once.
EVAL_BLOCK = 1 << 17


class ExportError(CompabsError):
    """A controller cannot be exported as asked, or an export file cannot be read."""


def quantize(grid: UniformGrid, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cell indices of concrete states, shape (B, n) -> (B, n), and whether each is in the box, shape (B,).

    Cells are closed, so a state on a cell boundary lies in two cells; the feedback refinement relation relates
    it to both and either cell's inputs are admissible there. The upper cell is taken (``UniformGrid.cell_of``
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


def _ints(values: Any, name: str) -> np.ndarray:
    try:
        out = np.asarray(values, dtype=np.int64)
    except (TypeError, ValueError):
        raise ExportError(f"export file: {name} is not a list of integers") from None
    if out.ndim != 1:
        raise ExportError(f"export file: {name} is not a flat list")
    return out


@dataclass(frozen=True)
class BDDTable:
    """A multi-rooted reduced BDD over the current-state bits (module docstring).

    Attributes
    ----------
    bits : ndarray of int64, shape (V, 2)
        Per variable (top level first): the state coordinate and the bit's shift (``idx >> shift & 1``).
    var, low, high : ndarray of int64, shape (K + 1,)
        Per node (node 0 is the constant TRUE and its entries are unused); ``low``/``high`` are edges.
    domain : int
        Edge of the domain.
    outputs : ndarray of int64, shape (B,)
        Edges of the chosen input's bits, digit by digit (subsystem order), most significant bit first.
    """

    bits: np.ndarray
    var: np.ndarray
    low: np.ndarray
    high: np.ndarray
    domain: int
    outputs: np.ndarray

    @property
    def nodes(self) -> int:
        """Internal nodes (the constant not counted)."""
        return int(self.var.size) - 1

    def evaluate(self, idx: np.ndarray) -> np.ndarray:
        """Every root at cells ``idx``, shape (B, n) -> bool (B, 1 + outputs): domain, then the input bits.

        All walks (one per cell and root) go down together, level by level: at level ``v`` only the walks whose
        node tests ``v`` move (children sit below their parent), so the work is the walks' lengths, not
        ``V`` steps for every walk (10 tanks: 60 levels, a million cells and 11 roots in about 2 s instead of
        38). Rows are taken in blocks of :data:`EVAL_BLOCK` cells to bound the memory.
        """
        idx = np.asarray(idx, dtype=np.int64)
        roots = np.concatenate([[self.domain], self.outputs]).astype(np.int64)
        V, R = self.bits.shape[0], roots.size
        level_of = self.var.astype(np.int32)
        level_of[0] = V  # the constant: below every level
        out = np.empty((idx.shape[0], R), dtype=bool)
        for start in range(0, idx.shape[0], EVAL_BLOCK):
            block = idx[start:start + EVAL_BLOCK]
            e = np.tile(roots, block.shape[0])  # walk r of row b at b * R + r
            level = level_of[e >> 1]
            for v, (coord, shift) in enumerate(self.bits.tolist()):
                at = np.flatnonzero(level == v)
                if at.size == 0:
                    continue
                here = e[at]
                node = here >> 1
                bit = (block[at // R, coord] >> shift) & 1
                nxt = np.where(bit == 1, self.high[node], self.low[node]) ^ (here & 1)
                e[at] = nxt
                level[at] = level_of[nxt >> 1]
            out[start:start + block.shape[0]] = ((e & 1) == 0).reshape(-1, R)
        return out

    def to_dict(self) -> dict[str, Any]:
        return {"bits": self.bits.tolist(), "var": self.var.tolist(), "low": self.low.tolist(),
                "high": self.high.tolist(), "domain": int(self.domain), "outputs": self.outputs.tolist()}

    @classmethod
    def from_dict(cls, d: dict[str, Any], n_coords: int, n_outputs: int) -> BDDTable:
        bits = np.asarray(d["bits"], dtype=np.int64).reshape(-1, 2)
        var, low, high = (_ints(d[k], f"bdd.{k}") for k in ("var", "low", "high"))
        outputs = _ints(d["outputs"], "bdd.outputs")
        K = var.size
        edges = np.concatenate([low[1:], high[1:], outputs, [int(d["domain"])]])
        if not (low.size == high.size == K >= 1 and outputs.size == n_outputs):
            raise ExportError("export file: the BDD's node arrays or outputs have inconsistent lengths")
        if np.any(edges < 0) or np.any(edges >> 1 >= K) or np.any(var[1:] < 0) or np.any(var[1:] >= len(bits)):
            raise ExportError("export file: a BDD edge or variable is out of range")
        if bits.size and (np.any(bits[:, 0] < 0) or np.any(bits[:, 0] >= n_coords) or np.any(bits[:, 1] < 0)):
            raise ExportError("export file: a BDD variable names no state bit")
        # Children sit below their parent (a reduced, ordered BDD): evaluation ends within V steps.
        for child in (low[1:] >> 1, high[1:] >> 1):
            inner = child != 0
            if np.any(var[child[inner]] <= var[1:][inner]):
                raise ExportError("export file: the BDD is not ordered")
        return cls(bits, var, low, high, int(d["domain"]), outputs)


def _edge(ids: dict[int, int], g: Any) -> int:
    reg = ~g if g.negated else g
    return (ids[int(reg)] << 1) | int(g.negated)


def node_table(model: Any, domain: Any, outputs: Sequence[Any] = ()) -> BDDTable:
    """The :class:`BDDTable` of ``domain`` and ``outputs``, BDDs over the current-state bits of ``model`` (a
    :class:`~pipelines.symbolic.symbolic_model.SymbolicModel`), sharing their nodes.

    The walk visits every node once (Python work proportional to the BDDs, never to the states); what the table
    gives per cell is then one vectorised walk (:meth:`BDDTable.evaluate`).
    """
    bdd = model.bdd
    x_bits = sorted(model.x_bits, key=bdd.level_of_var)
    var_of = {bdd.level_of_var(b): k for k, b in enumerate(x_bits)}
    bits = []
    for b in x_bits:
        digit, pos = b.split("_")
        width = len(model.bits[digit])
        bits.append((int(digit[1:]), width - 1 - int(pos)))
    ids: dict[int, int] = {int(bdd.true): 0}
    order: list[Any] = []
    stack = [~g if g.negated else g for g in (domain, *outputs)]
    while stack:  # preorder: a node gets its id before its children
        g = stack.pop()
        if int(g) in ids:
            continue
        ids[int(g)] = len(ids)
        order.append(g)
        for child in (g.high, g.low):
            reg = ~child if child.negated else child
            if int(reg) not in ids:
                stack.append(reg)
    K = len(order) + 1
    var = np.zeros(K, dtype=np.int64)
    low = np.zeros(K, dtype=np.int64)
    high = np.zeros(K, dtype=np.int64)
    for g in order:
        k = ids[int(g)]
        var[k] = var_of[g.level]
        low[k], high[k] = _edge(ids, g.low), _edge(ids, g.high)
    bits_arr = np.asarray(bits, dtype=np.int64).reshape(-1, 2)
    return BDDTable(bits_arr, var, low, high, _edge(ids, domain),
                    np.asarray([_edge(ids, f) for f in outputs], dtype=np.int64))


@dataclass(frozen=True)
class TreeTable:
    """An exact decision tree over cell indices (module docstring); node 0 is the root.

    Attributes
    ----------
    feature, threshold, left, right, leaf : ndarray of int64, shape (K,)
        ``feature`` is ``-1`` at a leaf; at an inner node ``idx[feature] < threshold`` goes to ``left``, else to
        ``right``. ``leaf`` is the row of ``choices`` at a leaf, ``-1`` for no input.
    depth : int
        Longest root-to-leaf path (edges).
    """

    feature: np.ndarray
    threshold: np.ndarray
    left: np.ndarray
    right: np.ndarray
    leaf: np.ndarray
    depth: int

    @property
    def nodes(self) -> int:
        return int(self.feature.size)

    def evaluate(self, idx: np.ndarray) -> np.ndarray:
        """Leaf labels at cells ``idx``, shape (B, n) -> (B,) (``-1``: no input)."""
        idx = np.asarray(idx, dtype=np.int64)
        n = np.zeros(idx.shape[0], dtype=np.int64)
        rows = np.arange(idx.shape[0])
        for _ in range(self.depth):
            f = self.feature[n]
            inner = f >= 0
            if not inner.any():
                break
            go_left = idx[rows, np.maximum(f, 0)] < self.threshold[n]
            n = np.where(inner, np.where(go_left, self.left[n], self.right[n]), n)
        return self.leaf[n]

    def to_dict(self) -> dict[str, Any]:
        return {"feature": self.feature.tolist(), "threshold": self.threshold.tolist(), "left": self.left.tolist(),
                "right": self.right.tolist(), "leaf": self.leaf.tolist(), "depth": int(self.depth)}

    @classmethod
    def from_dict(cls, d: dict[str, Any], n_coords: int, n_choices: int) -> TreeTable:
        arrays = [_ints(d[k], f"tree.{k}") for k in ("feature", "threshold", "left", "right", "leaf")]
        feature, threshold, left, right, leaf = arrays
        K = feature.size
        if K == 0 or any(a.size != K for a in arrays):
            raise ExportError("export file: the tree's arrays are empty or of different lengths")
        inner = feature >= 0
        ids = np.arange(K)
        if np.any(feature >= n_coords) or np.any(inner & ((left <= ids) | (right <= ids) | (left >= K) | (right >= K))):
            raise ExportError("export file: a tree node's feature or child is out of range")
        if np.any(~inner & ((leaf < -1) | (leaf >= n_choices))):
            raise ExportError("export file: a tree leaf names no choice")
        return cls(feature, threshold, left, right, leaf, int(d["depth"]))


def codes_from_bits(values: np.ndarray, widths: list[int]) -> np.ndarray:
    """Per-subsystem flat input codes from the input bits, shape (B, sum(widths)) -> (B, len(widths))."""
    out = np.zeros((values.shape[0], len(widths)), dtype=np.int64)
    c = 0
    for s, w in enumerate(widths):
        for k in range(w):
            out[:, s] = (out[:, s] << 1) | values[:, c + k].astype(np.int64)
        c += w
    return out


class ExportedController:
    """A determinized controller read back from its JSON export (``compabs import``, :func:`load_export`).

    It answers like :class:`~pipelines.controller.Controller` at concrete states, with at most one input each:
    :meth:`input` (``None`` outside the domain), :meth:`inputs` (zero or one row), :meth:`input_many`.
    """

    def __init__(self, data: dict[str, Any]) -> None:
        if not isinstance(data, dict) or data.get("format") != EXPORT_FORMAT:
            got = data.get("format") if isinstance(data, dict) else type(data).__name__
            raise ExportError(f"not a {EXPORT_FORMAT} export (format {got!r})")
        try:
            self.state_grid = UniformGrid.from_description(data["state_grid"])
            self.input_grids = [UniformGrid.from_description(g) for g in data["input_grids"]]
            self.widths = [int(w) for w in data["input_bits"]]
            self.kind, self.rule, self.form = str(data["kind"]), str(data["rule"]), str(data["form"])
            self.sizes = dict(data.get("sizes", {}))
            n = self.state_grid.dim
            if len(self.widths) != len(self.input_grids):
                raise ExportError("export file: input_bits and input_grids differ in length")
            if self.form == "bdd":
                self.bdd: BDDTable | None = BDDTable.from_dict(data["bdd"], n, sum(self.widths))
                self.tree: TreeTable | None = None
                self.choices = np.zeros((0, len(self.widths)), dtype=np.int64)
            elif self.form == "tree":
                self.choices = np.asarray(data["choices"], dtype=np.int64).reshape(-1, len(self.widths))
                self.tree, self.bdd = TreeTable.from_dict(data["tree"], n, self.choices.shape[0]), None
            else:
                raise ExportError(f"export file: unknown form {self.form!r} (expected 'bdd' or 'tree')")
        except (KeyError, TypeError, ValueError) as exc:
            if isinstance(exc, CompabsError):
                raise
            raise ExportError(f"export file: missing or malformed field ({type(exc).__name__}: {exc})") from None
        self.meta: dict[str, Any] = {k: data[k] for k in ("kind", "fixed_point", "rule", "form", "sizes", "spec")
                                     if k in data}

    @property
    def input_dim(self) -> int:
        return sum(g.dim for g in self.input_grids)

    def cells(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """As :meth:`~pipelines.controller.Controller.cells` (:func:`quantize`)."""
        return quantize(self.state_grid, X)

    def codes(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Chosen per-subsystem flat input codes at cells, shape (B, n) -> (B, N), and whether each is in the
        domain, shape (B,)."""
        idx = np.asarray(idx, dtype=np.int64).reshape(-1, self.state_grid.dim)
        if self.bdd is not None:
            values = self.bdd.evaluate(idx)
            return codes_from_bits(values[:, 1:], self.widths), values[:, 0]
        assert self.tree is not None
        label = self.tree.evaluate(idx)
        ok = label >= 0
        return np.where(ok[:, None], self.choices[np.maximum(label, 0)], 0), ok

    def points(self, codes: np.ndarray) -> np.ndarray:
        """Concrete joint inputs of per-subsystem flat codes, shape (B, N) -> (B, m)."""
        parts = [g.points(g.unravel(codes[:, s])) for s, g in enumerate(self.input_grids)]
        return np.concatenate(parts, axis=1)

    def input_many(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The chosen inputs at states ``X``, shape (B, n) -> (B, m), and whether each has one, shape (B,)."""
        idx, ok = self.cells(X)
        codes, dom = self.codes(idx)
        ok = ok & dom
        return np.where(ok[:, None], self.points(np.where(ok[:, None], codes, 0)), np.nan), ok

    def input(self, x: np.ndarray) -> np.ndarray | None:
        """The chosen input at ``x``, shape (m,), or ``None`` outside the domain."""
        U, ok = self.input_many(np.asarray(x, dtype=float).reshape(1, -1))
        return U[0] if ok[0] else None

    def inputs(self, x: np.ndarray) -> np.ndarray:
        """The determinized controller's inputs at ``x``: shape (1, m), or (0, m) outside the domain."""
        u = self.input(x)
        return np.zeros((0, self.input_dim)) if u is None else u.reshape(1, -1)

    def cell(self, x: np.ndarray) -> np.ndarray | None:
        """The cell indices of a concrete state, shape (n,), or ``None`` outside the box."""
        idx, ok = self.cells(np.asarray(x, dtype=float).reshape(1, -1))
        return idx[0] if ok[0] else None

    def choose_many(self, X: np.ndarray, rng: np.random.Generator, how: str = "random") -> list[np.ndarray | None]:
        """The chosen input at each row of ``X`` (``None`` outside the domain): the closed-loop policy interface
        of :class:`~pipelines.controller.Controller` (``rng`` and ``how`` are unused: there is one input)."""
        U, ok = self.input_many(X)
        return [U[r] if ok[r] else None for r in range(len(ok))]


def load_export(path: str | os.PathLike[str]) -> ExportedController:
    """Read a JSON export (``compabs export --format json``) back, its integrity record verified first
    (:func:`~pipelines.controller_integrity.verify_export`: its checksum and its spec's hash)."""
    from pipelines.controller_integrity import verify_export

    try:
        data = json.loads(Path(path).read_bytes())
    except ValueError as exc:
        raise ExportError(f"{path} is not JSON ({exc})") from None
    if not isinstance(data, dict) or data.get("format") != EXPORT_FORMAT:
        return ExportedController(data)  # refused there, naming the format
    verify_export(data, path)
    try:
        return ExportedController(data)
    except ExportError as exc:
        raise ExportError(f"{path}: {exc}") from None
