"""The export of a controller: determinized, minimised (the smaller of the BDD table and the exact tree), as JSON
and CSV (``compabs export``; docs/export.md).

Sizes are those of the tables the C export writes (:func:`int_type` per array), so "smaller" means fewer bytes
of constant data in the controller a target runs.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipelines.array_controller import ArrayController
from pipelines.controller import Controller
from pipelines.controller_integrity import seal_export
from pipelines.export.decision_tree import decision_tree
from pipelines.export.determinize import bdd_table, determinize
from pipelines.export.table import (
    CSV_MAX_ROWS,
    EXPORT_FORMAT,
    FORMS,
    RULE_TEXT,
    ExportedController,
    ExportError,
    TreeTable,
    codes_from_bits,
)
from pipelines.grid import UniformGrid
from pipelines.symbolic.counting import count
from pipelines.symbolic.node_table import BDDTable
from pipelines.symbolic.order import SubsystemLayout
from pipelines.symbolic.relations import pair_set
from pipelines.symbolic.symbolic_model import SymbolicModel

#: Largest state grid for which the exact tree is built (it labels every cell of the grid).
TREE_MAX_CELLS = 1 << 21
#: Cells evaluated at once when labelling the grid.
BLOCK = 1 << 16


def int_type(lo: int, hi: int) -> tuple[str, int]:
    """The smallest C integer type holding ``lo .. hi`` and its size in bytes."""
    for bits in (8, 16, 32, 64):
        if lo >= 0 and hi < 1 << bits:
            return f"uint{bits}_t", bits // 8
        if lo >= -(1 << (bits - 1)) and hi < 1 << (bits - 1):
            return f"int{bits}_t", bits // 8
    raise ExportError(f"no C integer type holds {lo} .. {hi}")


def _nbytes(a: np.ndarray) -> int:
    return a.size * int_type(int(a.min()), int(a.max()))[1] if a.size else 0


def bdd_bytes(t: BDDTable) -> int:
    """Bytes of the BDD's node arrays in the C export."""
    return _nbytes(t.var) + _nbytes(t.low) + _nbytes(t.high)


def tree_bytes(t: TreeTable, choices: np.ndarray) -> int:
    """Bytes of the tree's arrays (and its table of chosen inputs) in the C export."""
    return sum(_nbytes(a) for a in (t.feature, t.threshold, t.left, t.right, t.leaf)) + _nbytes(choices.ravel())


@dataclass
class Export:
    """A determinized, minimised controller (what ``compabs export`` writes)."""

    meta: dict[str, Any]
    rule: str
    state_grid: UniformGrid
    input_grids: list[UniformGrid]
    widths: list[int]
    bdd: BDDTable
    tree: TreeTable | None
    choices: np.ndarray
    form: str
    sizes: dict[str, Any]

    def to_json(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "format": EXPORT_FORMAT,
            "kind": self.meta.get("kind"),
            "fixed_point": self.meta.get("fixed_point"),
            "rule": self.rule,
            "rule_text": RULE_TEXT[self.rule],
            "form": self.form,
            "state_grid": self.state_grid.describe(),
            "input_grids": [g.describe() for g in self.input_grids],
            "input_bits": list(self.widths),
            "sizes": self.sizes,
        }
        if self.form == "bdd":
            out["bdd"] = self.bdd.to_dict()
        else:
            assert self.tree is not None
            out["tree"] = self.tree.to_dict()
            out["choices"] = self.choices.tolist()
        if "spec" in self.meta:
            out["spec"] = self.meta["spec"]
        return out

    def controller(self) -> ExportedController:
        """The export as read back from its JSON."""
        return ExportedController(json.loads(json.dumps(self.to_json())))

    def codes(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Chosen per-subsystem codes at cells (B, n) -> (B, N) and whether each is in the domain, from the BDD."""
        values = self.bdd.evaluate(idx)
        return codes_from_bits(values[:, 1:], self.widths), values[:, 0]


def grid_labels(t: BDDTable, widths: list[int], grid: UniformGrid) -> tuple[np.ndarray, np.ndarray]:
    """Every cell's label (row of ``choices``, ``-1`` outside the domain), shape ``grid.shape``, and ``choices``,
    shape (L, N), from the BDD table (in blocks of cells)."""
    codes = np.zeros((grid.size, len(widths)), dtype=np.int64)
    ok = np.zeros(grid.size, dtype=bool)
    for start in range(0, grid.size, BLOCK):
        flat = np.arange(start, min(grid.size, start + BLOCK))
        values = t.evaluate(grid.unravel(flat))
        codes[flat], ok[flat] = codes_from_bits(values[:, 1:], widths), values[:, 0]
    choices, inverse = np.unique(codes[ok], axis=0, return_inverse=True)
    labels = np.full(grid.size, -1, dtype=np.int64)
    labels[ok] = inverse.reshape(-1)
    return labels.reshape(grid.shape), choices.reshape(-1, len(widths))


def domain_cells(t: BDDTable, grid: UniformGrid) -> np.ndarray:
    """Every cell of the BDD table's domain, shape (D, n), level by level over the state bits (one numpy step per
    bit; the frontier never exceeds the domain, whose BDD excludes invalid codes)."""
    n = grid.dim
    codes = np.zeros((1, n), dtype=np.int64)
    e = np.asarray([t.domain], dtype=np.int64)
    for v, (coord, shift) in enumerate(t.bits.tolist()):
        keep = e != 1  # the FALSE edge: no cell below
        codes, e = codes[keep], e[keep]
        node = e >> 1
        here = (node != 0) & (t.var[node] == v)
        c = e & 1
        lo = np.where(here, t.low[node] ^ c, e)
        hi = np.where(here, t.high[node] ^ c, e)
        one = codes.copy()
        one[:, coord] |= 1 << shift
        codes, e = np.concatenate([codes, one]), np.concatenate([lo, hi])
    cells = codes[e == 0]
    cells = cells[grid.on_grid(cells)]
    return cells[np.lexsort(cells.T[::-1])] if cells.size else cells


def _edge_models(t: BDDTable, models: list[int], e: int, level: int) -> int:
    """Assignments of the variables ``level .. V-1`` that satisfy the edge ``e`` (whose node tests no variable
    above ``level``), from the regular nodes' counts ``models``."""
    V = t.bits.shape[0]
    node = e >> 1
    top = V if node == 0 else int(t.var[node])
    n = models[node] << (top - level)
    return (1 << (V - level)) - n if e & 1 else n


def _node_models(t: BDDTable) -> list[int]:
    """Per node of the table (regular, not complemented), its exact model count over the variables from its own
    down (Python integers: 10 tanks have 60 state bits). Children sit below their parent, so the nodes are
    counted bottom level first (Python work per node, never per cell)."""
    models = [1] * t.var.size  # node 0, the constant TRUE
    for k in sorted(range(1, t.var.size), key=lambda k: -int(t.var[k])):
        below = int(t.var[k]) + 1
        models[k] = _edge_models(t, models, int(t.low[k]), below) + _edge_models(t, models, int(t.high[k]), below)
    return models


def domain_count(t: BDDTable) -> int:
    """The number of cells of the BDD table's domain (exact; codes beyond the grid are outside the domain BDD),
    counted on the table itself, independently of the symbolic model that made it."""
    return _edge_models(t, _node_models(t), int(t.domain), 0)


def sample_domain_cells(t: BDDTable, grid: UniformGrid, size: int, rng: np.random.Generator) -> np.ndarray:
    """``size`` cells drawn uniformly (with replacement) from the BDD table's domain, shape (size, n); shape
    (0, n) if the domain is empty.

    A walk from the domain's root takes, at each state bit, the high branch with probability (models of the
    high child) / (models of the node), from exact counts (:func:`domain_count`), and a bit the node skips with
    probability 1/2; a child without models has probability exactly 0, so every walk ends at TRUE. All walks
    advance together, one numpy step per state bit (60 for 10 tanks), so a million cells of a domain that
    fills 1.6e-5 of the grid (the tanks, where rejection sampling would need 6e10 draws) take about a second.
    """
    n = grid.dim
    models = _node_models(t)
    if _edge_models(t, models, int(t.domain), 0) == 0:
        return np.zeros((0, n), dtype=np.int64)
    # P(high) of each node reached plainly (column 0) or through a complemented edge (column 1)
    p_high = np.full((t.var.size, 2), 0.5)
    for k in range(1, t.var.size):
        v = int(t.var[k])
        for neg in (0, 1):
            total = _edge_models(t, models, (k << 1) | neg, v)
            if total:
                p_high[k, neg] = _edge_models(t, models, int(t.high[k]) ^ neg, v + 1) / total
    codes = np.zeros((size, n), dtype=np.int64)
    e = np.full(size, int(t.domain), dtype=np.int64)
    for level, (coord, shift) in enumerate(t.bits.tolist()):
        node, flip = e >> 1, e & 1
        here = (node != 0) & (t.var[node] == level)
        bit = rng.random(size) < np.where(here, p_high[node, flip], 0.5)
        e = np.where(here, np.where(bit, t.high[node], t.low[node]) ^ flip, e)
        codes[:, coord] |= bit.astype(np.int64) << shift
    if np.any(e != 0) or np.any(codes >= np.asarray(grid.shape)):
        raise ExportError("sampling the domain: a walk left the domain (a bug)")
    return codes


def as_bdd(ctrl: ArrayController) -> Controller:
    """An explicit game's array controller as the same controller over state and input bits (built in bulk,
    :func:`~pipelines.symbolic.relations.pair_set`), which the export determinizes and minimises as any other."""
    g, (u,) = ctrl.state_grid, ctrl.input_grids
    layout = SubsystemLayout(0, tuple(g.shape), u.size, (), "0", 0, ctrl.meta.get("subsystem", ""))
    grids = {"state": [g.describe()], "input": [u.describe()], "internal": [], "intermediate": {}}
    model = SymbolicModel([layout], [], grids=grids)
    x, inputs = np.nonzero(ctrl.admissible)
    return Controller(model, pair_set(model, g.unravel(x), inputs.reshape(-1, 1)), {**ctrl.meta, "form": "explicit"})


def export_controller(ctrl: Controller | ArrayController, form: str = "auto", rule: str = "auto",
                      tree_max_cells: int = TREE_MAX_CELLS) -> Export:
    """Determinize ``ctrl`` (:func:`~.determinize.determinize`; an array controller through :func:`as_bdd`) and
    minimise it.

    ``form``: ``bdd`` (the node table, any size), ``tree`` (the exact decision tree; grids up to
    ``tree_max_cells``) or ``auto``: the one with fewer bytes (the tree is tried where the grid allows, and given
    up once it outgrows the BDD).
    """
    if form not in FORMS:
        raise ExportError(f"unknown form {form!r}; expected one of {', '.join(FORMS)}")
    if isinstance(ctrl, ArrayController):
        ctrl = as_bdd(ctrl)
    m = ctrl.model
    D, used = determinize(ctrl, rule)
    table = bdd_table(m, D)
    grid = ctrl.state_grid
    widths = [len(m.bits[d]) for d in m.u_digits()]
    sizes: dict[str, Any] = {"domain_states": count(m, m.bdd.exist(m.u_bits, D), m.x_digits()),
                             "grid_states": grid.size, "bdd_nodes": table.nodes, "bdd_bytes": bdd_bytes(table),
                             "tree_nodes": None, "tree_bytes": None}
    tree, choices = None, np.zeros((0, len(widths)), dtype=np.int64)
    if form == "tree" and grid.size > tree_max_cells:
        raise ExportError(f"the exact tree labels every cell of the grid: {grid.size:,} cells exceed the limit "
                          f"{tree_max_cells:,}; use --form bdd (exact, any size)")
    if form != "bdd" and grid.size <= tree_max_cells:
        labels, choices = grid_labels(table, widths, grid)
        # A tree node takes at least 5 bytes (one per array), so a tree past this many nodes cannot win.
        tree = decision_tree(labels, None if form == "tree" else max(3, sizes["bdd_bytes"] // 5 + 1))
        if tree is not None:
            sizes["tree_nodes"], sizes["tree_bytes"] = tree.nodes, tree_bytes(tree, choices)
    chosen = "bdd"
    if form == "tree" or (form == "auto" and tree is not None and sizes["tree_bytes"] < sizes["bdd_bytes"]):
        chosen = "tree"
    sizes["form"] = chosen
    return Export(ctrl.meta, used, grid, ctrl.input_grids, widths, table, tree, choices, chosen, sizes)


def write_json(export: Export, path: str | os.PathLike[str]) -> Path:
    """The export as JSON with its integrity record (:func:`~pipelines.controller_integrity.seal_export`), which
    :func:`~.table.load_export` verifies."""
    out = Path(path)
    out.write_text(json.dumps(seal_export(export.to_json()), separators=(",", ":")))
    return out


def write_csv(export: Export, path: str | os.PathLike[str], max_rows: int = CSV_MAX_ROWS) -> Path:
    """One row per domain cell: the cell centre ``x1..xn`` and the chosen input ``u1..um``."""
    n_dom = int(export.sizes["domain_states"])
    if n_dom > max_rows:
        raise ExportError(f"the domain has {n_dom:,} cells, more than the CSV limit of {max_rows:,} rows; export "
                          "--format c or --format json (an exact BDD or tree of any size), or raise --max-rows")
    cells = domain_cells(export.bdd, export.state_grid)
    codes, ok = export.codes(cells)
    if not ok.all() or cells.shape[0] != n_dom:
        raise ExportError("the domain's cells do not match its count (a bug)")
    parts = [g.points(g.unravel(codes[:, s])) for s, g in enumerate(export.input_grids)]
    X = export.state_grid.points(cells)
    U = np.concatenate(parts, axis=1) if parts else np.zeros((cells.shape[0], 0))
    names = [f"x{i + 1}" for i in range(X.shape[1])] + [f"u{j + 1}" for j in range(U.shape[1])]
    out = Path(path)
    np.savetxt(out, np.concatenate([X, U], axis=1), fmt="%.17g", delimiter=",", header=",".join(names), comments="")
    return out
