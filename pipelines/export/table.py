"""The exported form of a determinized controller, and the controller read back from its JSON.

A determinized controller maps each domain cell to one joint input (per-subsystem flat input indices) and says
"no input" elsewhere. It is kept in one of two exact forms, both evaluated on cell indices:

* :class:`~pipelines.symbolic.node_table.BDDTable`: a reduced BDD over the current-state bits as a node table,
  with one root for the domain and one per input bit (:func:`bdd_table_from_dict` reads it back, checked). As
  small as the BDD, whatever the state count.
* :class:`TreeTable`: an axis-aligned decision tree over the cell indices (``idx[feature] < threshold`` goes
  left), leaves naming a row of ``choices`` or ``-1`` (no input).

States are quantized as every controller quantizes them (:func:`pipelines.grid.quantize`, which the C export
reproduces).
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, TypeVar

import numpy as np

from pipelines.errors import CompabsError
from pipelines.grid_controller import GridController
from pipelines.symbolic.node_table import BDDTable

T = TypeVar("T")

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
#: ``format`` of a controller with memory's JSON export (:mod:`pipelines.export.memory`).
PRODUCT_EXPORT_FORMAT = "compabs-product-export/1"


class ExportError(CompabsError):
    """A controller cannot be exported as asked, or an export file cannot be read."""


def _ints(values: Any, name: str) -> np.ndarray:
    try:
        out = np.asarray(values, dtype=np.int64)
    except (TypeError, ValueError):
        raise ExportError(f"export file: {name} is not a list of integers") from None
    if out.ndim != 1:
        raise ExportError(f"export file: {name} is not a flat list")
    return out


def bdd_table_from_dict(d: dict[str, Any], n_coords: int, n_outputs: int) -> BDDTable:
    """The :class:`~pipelines.symbolic.node_table.BDDTable` of an export file's ``bdd`` entry, every index checked."""
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
    return BDDTable(bits, var, low, high, int(d["domain"]), outputs)


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


class ExportedController(GridController):
    """A determinized controller read back from its JSON export (``compabs import``, :func:`load_export`).

    It answers like :class:`~pipelines.controller.Controller` at concrete states, with at most one input each:
    :meth:`input` (``None`` outside the domain), :meth:`inputs` (zero or one row), :meth:`input_many`.
    """

    def __init__(self, data: dict[str, Any]) -> None:
        check_format(data, EXPORT_FORMAT)
        try:
            super().__init__(data, export_meta(data))
            self.widths = [int(w) for w in data["input_bits"]]
            self.kind, self.rule, self.form = str(data["kind"]), str(data["rule"]), str(data["form"])
            self.sizes = dict(data.get("sizes", {}))
            n = self._state_grid.dim
            if len(self.widths) != len(self._input_grids):
                raise ExportError("export file: input_bits and input_grids differ in length")
            if self.form == "bdd":
                self.bdd: BDDTable | None = bdd_table_from_dict(data["bdd"], n, sum(self.widths))
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

    def codes(self, idx: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Chosen per-subsystem flat input codes at cells, shape (B, n) -> (B, N), and whether each is in the
        domain, shape (B,)."""
        idx = np.asarray(idx, dtype=np.int64).reshape(-1, self._state_grid.dim)
        if self.bdd is not None:
            values = self.bdd.evaluate(idx)
            return codes_from_bits(values[:, 1:], self.widths), values[:, 0]
        assert self.tree is not None
        label = self.tree.evaluate(idx)
        ok = label >= 0
        return np.where(ok[:, None], self.choices[np.maximum(label, 0)], 0), ok

    def points(self, codes: np.ndarray) -> np.ndarray:
        """Concrete joint inputs of per-subsystem flat codes, shape (B, N) -> (B, m)."""
        parts = [g.points(g.unravel(codes[:, s])) for s, g in enumerate(self._input_grids)]
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

    def choose_many(self, X: np.ndarray, rng: np.random.Generator, how: str = "random") -> list[np.ndarray | None]:
        """The chosen input at each row of ``X`` (``None`` outside the domain): the closed-loop policy interface
        of :class:`~pipelines.controller.Controller` (``rng`` and ``how`` are unused: there is one input)."""
        U, ok = self.input_many(X)
        return [U[r] if ok[r] else None for r in range(len(ok))]


def check_format(data: Any, expected: str) -> None:
    """Refuse an export of another format, naming it.

    Raises
    ------
    ExportError
    """
    if not isinstance(data, dict) or data.get("format") != expected:
        got = data.get("format") if isinstance(data, dict) else type(data).__name__
        raise ExportError(f"not a {expected} export (format {got!r})")


def export_meta(data: dict[str, Any]) -> dict[str, Any]:
    """What an export says of its controller (kind, fixed point, rule, form, sizes, spec): its ``meta``."""
    return {k: data[k] for k in ("kind", "fixed_point", "rule", "form", "sizes", "spec") if k in data}


def load_export(path: str | os.PathLike[str]) -> ExportedController:
    """Read a JSON export (``compabs export --format json``) back, its integrity record verified first
    (:func:`~pipelines.controller_integrity.verify_export`: its checksum and its spec's hash)."""
    return read_export(path, EXPORT_FORMAT, ExportedController)


def read_export(path: str | os.PathLike[str], expected_format: str, make: Callable[[Any], T]) -> T:
    """``make(data)`` of the JSON export at ``path``: its integrity record verified first where its format is
    ``expected_format``; another format goes to ``make`` as it is, which refuses it naming the format.

    Raises
    ------
    ExportError
        Not JSON, or what ``make`` refuses, prefixed with the file.
    """
    from pipelines.controller_integrity import verify_export

    try:
        data = json.loads(Path(path).read_bytes())
    except ValueError as exc:
        raise ExportError(f"{path} is not JSON ({exc})") from None
    if not isinstance(data, dict) or data.get("format") != expected_format:
        return make(data)  # refused there, naming the format
    verify_export(data, path)
    try:
        return make(data)
    except ExportError as exc:
        raise ExportError(f"{path}: {exc}") from None
