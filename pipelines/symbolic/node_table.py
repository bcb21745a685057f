"""A BDD over the current-state bits as a node table, evaluated on cell indices for many cells at once.

:class:`BDDTable` is a reduced BDD (CUDD's, complement edges included) with one root for a set of cells and one
per further function of the cell (the exported controller's input bits); a node is ``(var, low, high)`` and an
edge is ``(node << 1) | complemented``, node 0 being the constant TRUE. :func:`node_table` builds it from BDDs of
a :class:`~.symbolic_model.SymbolicModel` in one walk of their nodes; :meth:`BDDTable.evaluate` then answers for
a batch of cells with array operations, where a ``let`` per cell would cost a BDD operation each
(docs/method.md §5: never one point at a time). A controller's domain test and the export's tables use it.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

#: Cells :meth:`BDDTable.evaluate` walks at once.
EVAL_BLOCK = 1 << 17


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


def _edge(ids: dict[int, int], g: Any) -> int:
    reg = ~g if g.negated else g
    return (ids[int(reg)] << 1) | int(g.negated)


def bit_positions(model: Any, bits: Sequence[str]) -> np.ndarray:
    """Per bit (``x3_1``, ``u0_2``, ...): its digit's number and its shift in the digit's code (``code >> shift
    & 1``, most significant bit first), shape (len(bits), 2)."""
    out = []
    for b in bits:
        digit, pos = b.split("_")
        out.append((int(digit[1:]), len(model.bits[digit]) - 1 - int(pos)))
    return np.asarray(out, dtype=np.int64).reshape(-1, 2)


def node_arrays(bdd: Any, roots: Sequence[Any], var_of: dict[int, int]) -> tuple[np.ndarray, ...]:
    """The nodes below ``roots`` as arrays ``(var, low, high, root edges)``: node 0 the constant TRUE (its entries
    0), every other node numbered in one walk (Python work proportional to the BDDs), ``var`` its CUDD level mapped
    through ``var_of``, its children and the roots as edges ``(node << 1) | complemented``."""
    ids: dict[int, int] = {int(bdd.true): 0}
    order: list[Any] = []
    stack = [~g if g.negated else g for g in roots]
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
    return var, low, high, np.asarray([_edge(ids, g) for g in roots], dtype=np.int64)


def node_table(model: Any, domain: Any, outputs: Sequence[Any] = ()) -> BDDTable:
    """The :class:`BDDTable` of ``domain`` and ``outputs``, BDDs over the current-state bits of ``model`` (a
    :class:`~pipelines.symbolic.symbolic_model.SymbolicModel`), sharing their nodes.

    The walk visits every node once (Python work proportional to the BDDs, never to the states); what the table
    gives per cell is then one vectorised walk (:meth:`BDDTable.evaluate`).
    """
    bdd = model.bdd
    x_bits = sorted(model.x_bits, key=bdd.level_of_var)
    var, low, high, roots = node_arrays(bdd, [domain, *outputs], {bdd.level_of_var(b): k for k, b in enumerate(x_bits)})
    return BDDTable(bit_positions(model, x_bits), var, low, high, int(roots[0]), roots[1:])
