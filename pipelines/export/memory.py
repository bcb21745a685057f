"""The export of a controller with memory (an ``ltl`` job's :class:`~pipelines.product_controller.ProductController`):
the automaton, the atoms' regions and, per automaton state, the determinized controller ``C_q``, as JSON and CSV
(``compabs export``; docs/export.md). :mod:`.memory_c` writes it as C.

A run reads it as the job's closed loop does (:mod:`pipelines.verification.product_loop`): the letter of a
concrete state ``x`` has bit ``i`` set iff ``x`` lies in one of atom ``i``'s closed boxes; the automaton state
moves ``q ← delta[q][letter(x)]`` on every state of the run, the first from ``initial``; the input at ``x`` is
``C_q``'s at ``x``'s cell. Every input of ``C_q`` makes progress in the product game, so each state's controller
is determinized by the smallest admissible input index (:func:`~.determinize.lexmin`), exactly.

The per-state controllers are kept as one BDD node table over the state bits (their nodes side by side, node 0
the shared constant), with per automaton state a domain root and one root per input bit: the BDD form of
:mod:`.table`, any grid size. The exact tree form is not offered for controllers with memory.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from pipelines.array_controller import ArrayController
from pipelines.controller_integrity import seal_export
from pipelines.errors import CompabsError
from pipelines.export.determinize import bdd_table, determinize
from pipelines.export.emit import as_bdd, bdd_bytes, domain_cells, domain_count
from pipelines.export.table import (
    CSV_MAX_ROWS,
    PRODUCT_EXPORT_FORMAT,
    RULE_TEXT,
    ExportError,
    bdd_table_from_dict,
    check_format,
    codes_from_bits,
    export_meta,
    read_export,
)
from pipelines.grid_controller import GridController
from pipelines.product_controller import ProductController
from pipelines.symbolic.node_table import BDDTable
from pipelines.temporal.automaton import Automaton
from pipelines.temporal.labels import letters_at

#: The one determinization rule of a controller with memory (module docstring).
RULE = "smallest_index"

Boxes = list[tuple[np.ndarray, np.ndarray]]


def _shift(edges: np.ndarray, base: int) -> np.ndarray:
    """Edges of one table with its internal nodes moved to start at ``base`` (node 0, the constant, stays)."""
    node, neg = edges >> 1, edges & 1
    return (np.where(node == 0, 0, node - 1 + base) << 1) | neg


def merge_tables(tables: list[BDDTable]) -> tuple[BDDTable, np.ndarray, np.ndarray]:
    """One node table holding every table's nodes: the merged table (its own ``domain`` and ``outputs`` unused),
    and per table its domain edge (Q,) and output edges (Q, B). The tables must share their state bits."""
    bits = tables[0].bits
    if any(not np.array_equal(t.bits, bits) for t in tables):
        raise ExportError("the automaton states' controllers order their state bits differently (a bug)")
    var, low, high, domains, outputs = [np.zeros(1, np.int64)], [np.zeros(1, np.int64)], [np.zeros(1, np.int64)], [], []
    base = 1
    for t in tables:
        var.append(t.var[1:])
        low.append(_shift(t.low[1:], base))
        high.append(_shift(t.high[1:], base))
        domains.append(int(_shift(np.asarray([t.domain]), base)[0]))
        outputs.append(_shift(np.asarray(t.outputs, dtype=np.int64), base))
        base += t.var.size - 1
    merged = BDDTable(bits, np.concatenate(var), np.concatenate(low), np.concatenate(high), 0,
                      np.zeros(0, dtype=np.int64))
    return merged, np.asarray(domains, dtype=np.int64), np.asarray(outputs, dtype=np.int64).reshape(len(tables), -1)


@dataclass
class ProductExport:
    """A controller with memory, determinized (what ``compabs export`` writes of an ``ltl`` job)."""

    meta: dict[str, Any]
    state_grid: Any
    input_grids: list[Any]
    widths: list[int]
    automaton: Automaton
    regions: list[Boxes]
    table: BDDTable
    domains: np.ndarray
    outputs: np.ndarray
    sizes: dict[str, Any]

    rule = RULE
    form = "bdd"

    def state_table(self, q: int) -> BDDTable:
        """Automaton state ``q``'s controller as a table of its own roots (over the shared nodes)."""
        return BDDTable(self.table.bits, self.table.var, self.table.low, self.table.high, int(self.domains[q]),
                        self.outputs[q])

    def to_json(self) -> dict[str, Any]:
        t = self.table
        out: dict[str, Any] = {
            "format": PRODUCT_EXPORT_FORMAT, "kind": self.meta.get("kind"), "fixed_point": self.meta.get("fixed_point"),
            "rule": RULE, "rule_text": RULE_TEXT[RULE], "form": "bdd", "state_grid": self.state_grid.describe(),
            "input_grids": [g.describe() for g in self.input_grids], "input_bits": list(self.widths),
            "sizes": self.sizes, "automaton": self.automaton.to_json(),
            "regions": {atom: [[lb.tolist(), ub.tolist()] for lb, ub in boxes]
                        for atom, boxes in zip(self.automaton.atoms, self.regions)},
            "bdd": {"bits": t.bits.tolist(), "var": t.var.tolist(), "low": t.low.tolist(), "high": t.high.tolist()},
            "states": [{"domain": int(d), "outputs": o.tolist()} for d, o in zip(self.domains, self.outputs)],
        }
        if "spec" in self.meta:
            out["spec"] = self.meta["spec"]
        return out

    def controller(self) -> ExportedProductController:
        """The export as read back from its JSON."""
        return ExportedProductController(json.loads(json.dumps(self.to_json())))


def export_product(ctrl: ProductController, form: str = "auto", rule: str = "auto") -> ProductExport:
    """Determinize each automaton state's controller (module docstring) and keep them in one node table."""
    if form not in ("auto", "bdd"):
        raise ExportError(f"an 'ltl' controller (a controller with memory) is exported in the BDD form only; --form "
                          f"{form} is not for it (use auto or bdd)")
    if rule not in ("auto", RULE):
        raise ExportError(f"an 'ltl' controller is determinized by the smallest admissible input index (every input "
                          f"makes progress in the product); --rule {rule} is not for it (use auto or {RULE})")
    tables = []
    widths: list[int] = []
    for c in ctrl.per_state:
        bdd_ctrl = as_bdd(c) if isinstance(c, ArrayController) else c
        D, _ = determinize(bdd_ctrl, RULE)
        m = bdd_ctrl.model
        widths = [len(m.bits[d]) for d in m.u_digits()]
        tables.append(bdd_table(m, D))
    table, domains, outputs = merge_tables(tables)
    automaton = ctrl.automaton
    cells = ctrl.state_grid.unravel(np.arange(ctrl.state_grid.size)) if ctrl.state_grid.size <= 1 << 22 else None
    sizes: dict[str, Any] = {
        "automaton_states": automaton.n_states, "atoms": len(automaton.atoms),
        "accepting_states": int(automaton.accepting.sum()),
        "domain_states": int(ctrl.in_domain(cells).sum()) if cells is not None else None,
        "winning_cells_per_state": [domain_count(t) for t in tables],
        "grid_states": ctrl.state_grid.size, "bdd_nodes": table.nodes, "bdd_bytes": bdd_bytes(table), "form": "bdd"}
    regions = _regions(ctrl.meta, automaton)
    return ProductExport(ctrl.meta, ctrl.state_grid, ctrl.input_grids, widths, automaton, regions, table, domains,
                         outputs, sizes)


def _regions(data: dict[str, Any], automaton: Automaton) -> list[Boxes]:
    """The atoms' closed boxes a header or an export records (``regions``: per atom a list of ``[lb, ub]``)."""
    return [[(np.asarray(lb, dtype=float), np.asarray(ub, dtype=float)) for lb, ub in data["regions"][atom]]
            for atom in automaton.atoms]


class ExportedProductController(GridController):
    """A controller with memory read back from its JSON export (:func:`load_product_export`): the automaton, the
    atoms' boxes, and per automaton state one input per cell of its domain."""

    def __init__(self, data: dict[str, Any]) -> None:
        check_format(data, PRODUCT_EXPORT_FORMAT)
        try:
            super().__init__(data, export_meta(data))
            self.widths = [int(w) for w in data["input_bits"]]
            if len(self.widths) != len(self._input_grids):
                raise ExportError("export file: input_bits and input_grids differ in length")
            self.automaton = Automaton.from_json(data["automaton"])
            n = self._state_grid.dim
            self.regions = _regions(data, self.automaton)
            if any(lb.shape != (n,) or ub.shape != (n,) for boxes in self.regions for lb, ub in boxes):
                raise ExportError(f"export file: a region's box is not of the state's {n} coordinates")
            states = data["states"]
            if not isinstance(states, list) or len(states) != self.automaton.n_states:
                raise ExportError("export file: 'states' does not hold one controller per automaton state")
            self.tables = [bdd_table_from_dict({**data["bdd"], **s}, n, sum(self.widths)) for s in states]
        except (KeyError, TypeError, ValueError, IndexError, AttributeError) as exc:
            if isinstance(exc, CompabsError):
                raise
            raise ExportError(f"export file: missing or malformed field ({type(exc).__name__}: {exc})") from None

    def letters_at(self, X: np.ndarray) -> np.ndarray:
        """The letter of each concrete state of ``X`` (shape (B, n)); int64 (B,)."""
        return letters_at(self.regions, X)

    def next_states(self, q: np.ndarray | int, X: np.ndarray) -> np.ndarray:
        """``delta[q][letter(x)]`` per row of ``X``; int64 (B,)."""
        X = np.atleast_2d(np.asarray(X, dtype=float))
        q = np.broadcast_to(np.asarray(q, dtype=np.int64), (X.shape[0],))
        return self.automaton.delta[q, self.letters_at(X)].astype(np.int64)

    def input_many(self, X: np.ndarray, q: np.ndarray | int) -> tuple[np.ndarray, np.ndarray]:
        """The chosen inputs at states ``X`` (B, n) in automaton states ``q`` -> (B, m), and whether each has one."""
        X = np.atleast_2d(np.asarray(X, dtype=float))
        q = np.broadcast_to(np.asarray(q, dtype=np.int64), (X.shape[0],))
        idx, ok = self.cells(X)
        U = np.full((X.shape[0], self.input_dim), np.nan)
        for state in np.unique(q).tolist():  # automaton states: a handful; the states are bulk
            rows = np.flatnonzero(q == state)
            values = self.tables[state].evaluate(np.where(ok[rows, None], idx[rows], 0))
            codes = codes_from_bits(values[:, 1:], self.widths)
            ok[rows] &= values[:, 0]
            parts = [g.points(g.unravel(codes[:, s])) for s, g in enumerate(self._input_grids)]
            U[rows] = np.concatenate(parts, axis=1)
        U[~ok] = np.nan
        return U, ok

    def step(self, X: np.ndarray, q: np.ndarray | int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What the C export's ``compabs_step`` does per row: the next automaton state on ``x``'s letter, and the
        input of that state's controller at ``x``: ``(U, ok, q_next)``."""
        q_next = self.next_states(q, X)
        U, ok = self.input_many(X, q_next)
        return U, ok, q_next


def load_product_export(path: str | os.PathLike[str]) -> ExportedProductController:
    """Read a controller with memory's JSON export back, its integrity record verified first."""
    return read_export(path, PRODUCT_EXPORT_FORMAT, ExportedProductController)


def write_product_json(export: ProductExport, path: str | os.PathLike[str]) -> Path:
    """The export as JSON with its integrity record (:func:`~pipelines.controller_integrity.seal_export`)."""
    out = Path(path)
    out.write_text(json.dumps(seal_export(export.to_json()), separators=(",", ":")))
    return out


def write_product_csv(export: ProductExport, path: str | os.PathLike[str], max_rows: int = CSV_MAX_ROWS
                      ) -> list[Path]:
    """Three CSV files: ``PATH`` one row per automaton state and cell of its controller's domain (``q``, the
    cell centre ``x1..xn``, the chosen input ``u1..um``); ``PATH_automaton.csv`` one row per automaton state
    (``q``, ``initial``, ``accepting``, then the next state per letter, ``next_0 ..``); ``PATH_regions.csv`` one
    row per box (``atom`` the letter's bit, ``lb1..lbn``, ``ub1..ubn``; the atoms' names in the JSON export)."""
    counts = export.sizes["winning_cells_per_state"]
    if sum(counts) > max_rows:
        raise ExportError(f"the automaton states' domains have {sum(counts):,} cells, more than the CSV limit of "
                          f"{max_rows:,} rows; export --format c or --format json, or raise --max-rows")
    g = export.state_grid
    rows = []
    for q in range(export.automaton.n_states):
        t = export.state_table(q)
        cells = domain_cells(t, g)
        values = t.evaluate(cells)
        codes = codes_from_bits(values[:, 1:], export.widths)
        if cells.shape[0] != counts[q] or not values[:, 0].all():
            raise ExportError("the domain's cells do not match its count (a bug)")
        parts = [ig.points(ig.unravel(codes[:, s])) for s, ig in enumerate(export.input_grids)]
        U = np.concatenate(parts, axis=1) if parts else np.zeros((cells.shape[0], 0))
        rows.append(np.concatenate([np.full((cells.shape[0], 1), q), g.points(cells), U], axis=1))
    n, m = g.dim, sum(ig.dim for ig in export.input_grids)
    base = Path(path)
    stem = base.with_suffix("") if base.suffix == ".csv" else base
    names = ["q"] + [f"x{i + 1}" for i in range(n)] + [f"u{j + 1}" for j in range(m)]
    np.savetxt(base, np.concatenate(rows) if rows else np.zeros((0, 1 + n + m)), fmt="%.17g", delimiter=",",
               header=",".join(names), comments="")
    a = export.automaton
    table = np.concatenate([np.arange(a.n_states)[:, None], (np.arange(a.n_states) == a.initial)[:, None],
                            a.accepting[:, None], a.delta], axis=1).astype(np.int64)
    automaton = stem.with_name(stem.name + "_automaton.csv")
    np.savetxt(automaton, table, fmt="%d", delimiter=",", comments="",
               header=",".join(["q", "initial", "accepting"] + [f"next_{s}" for s in range(a.n_letters)]))
    boxes = [[i, *lb.tolist(), *ub.tolist()] for i, per_atom in enumerate(export.regions) for lb, ub in per_atom]
    regions = stem.with_name(stem.name + "_regions.csv")
    np.savetxt(regions, np.asarray(boxes, dtype=float).reshape(-1, 1 + 2 * n), fmt="%.17g", delimiter=",",
               comments="", header=",".join(["atom"] + [f"lb{i + 1}" for i in range(n)]
                                            + [f"ub{i + 1}" for i in range(n)]))
    return [base, automaton, regions]
