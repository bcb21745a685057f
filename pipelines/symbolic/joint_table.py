"""A controller ``C(x̂, û)`` as a node table over its state and input bits: inputs drawn at many cells at once.

Closed loops draw an admissible input at every run's cell in every step. Per cell, a ``let`` and exact model counts
of the cofactor (:class:`~.counting.Sampler`) cost milliseconds of Python each: on a ring of 100 rooms, ten
milliseconds a cell and two thirds of the job's time. Here one table of the controller's nodes (CUDD's, complement
edges included; node 0 the constant TRUE, an edge ``(node << 1) | complemented``, as in :mod:`.node_table`) serves
every cell. For a batch of cells, :func:`draw` computes bottom-up, with array operations over the cells, the
model count of every node over the input bits at and below its level, the state bits fixed by each cell; then it
walks down once per cell, taking each input bit's branch with its share of the models and a level the node does
not test with probability 1/2. That is :class:`~.counting.Sampler`'s uniform distribution over the cell's
admissible joint inputs; the counts are kept as base-2 logarithms (a network of a thousand subsystems has more
than 2**1024 joint inputs), so the shares are exact up to float rounding, and a branch without models (log count
``-inf``) is never taken.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

#: Node-by-cell entries of the count arrays :func:`draw` holds at once (two float64 arrays of this size).
COUNT_BLOCK = 1 << 22


@dataclass(frozen=True)
class JointTable:
    """A reduced BDD over current-state and input bits (module docstring).

    Attributes
    ----------
    is_input : ndarray of bool, shape (V,)
        Per level (top first): an input bit (else a current-state bit).
    digit, shift : ndarray of int64, shape (V,)
        Per level: the state coordinate or the input digit (subsystem) the bit belongs to, and its shift
        (``code >> shift & 1``).
    var, low, high : ndarray of int64, shape (K + 1,)
        Per node: its level (``V`` for the constant, node 0) and its children as edges.
    root : int
        The controller's edge.
    inputs : int
        Input digits (one per subsystem).
    """

    is_input: np.ndarray
    digit: np.ndarray
    shift: np.ndarray
    var: np.ndarray
    low: np.ndarray
    high: np.ndarray
    root: int
    inputs: int

    @property
    def levels(self) -> int:
        return int(self.is_input.size)

    def free_below(self) -> np.ndarray:
        """Input levels at or below each level, shape (V + 1,) (0 at the constant's level ``V``)."""
        return np.concatenate([np.cumsum(self.is_input[::-1])[::-1], [0]]).astype(np.int64)


def joint_table(model: Any, f: Any) -> JointTable:
    """The :class:`JointTable` of ``f``, a BDD over the current-state and input bits of ``model`` (a
    :class:`~.symbolic_model.SymbolicModel`); one walk of its nodes, Python work proportional to the BDD."""
    bdd = model.bdd
    bits = sorted([*model.x_bits, *model.u_bits], key=bdd.level_of_var)
    level_of = {bdd.level_of_var(b): k for k, b in enumerate(bits)}
    is_input, digit, shift = [], [], []
    for b in bits:
        name, pos = b.split("_")
        is_input.append(name[0] == "u")
        digit.append(int(name[1:]))
        shift.append(len(model.bits[name]) - 1 - int(pos))
    ids: dict[int, int] = {int(bdd.true): 0}
    order: list[Any] = []
    stack = [~f if f.negated else f]
    while stack:
        g = stack.pop()
        if int(g) in ids:
            continue
        ids[int(g)] = len(ids)
        order.append(g)
        for child in (g.high, g.low):
            reg = ~child if child.negated else child
            if int(reg) not in ids:
                stack.append(reg)

    def edge(g: Any) -> int:
        reg = ~g if g.negated else g
        return (ids[int(reg)] << 1) | int(g.negated)

    K = len(order) + 1
    var = np.full(K, len(bits), dtype=np.int64)
    low, high = np.zeros(K, dtype=np.int64), np.zeros(K, dtype=np.int64)
    for g in order:
        k = ids[int(g)]
        var[k], low[k], high[k] = level_of[g.level], edge(g.low), edge(g.high)
    return JointTable(np.asarray(is_input, dtype=bool), np.asarray(digit, dtype=np.int64),
                      np.asarray(shift, dtype=np.int64), var, low, high, edge(f), len(model.u_digits()))


def _densities(t: JointTable, idx: np.ndarray) -> np.ndarray:
    """Per edge and cell (shape (2 (K + 1), B), an edge ``e`` at row ``e``): the share of the assignments of the input
    bits at and below the edge's node's level that satisfy the edge's function, the state bits set by the cells
    ``idx``.

    A share does not depend on the levels an edge skips, so a node's is the mean of its children's at an input
    level and the child's the cell picks at a state level. Both polarities are computed, never ``1 - share``, so a
    share of ``2**-60`` is not lost to rounding; the smallest non-zero share is ``2**-(input bits)``, inside float64
    up to 1,000 input bits and inside ``longdouble`` (x86's 80 bits) past them."""
    dtype = np.float64 if int(t.is_input.sum()) <= 1000 else np.longdouble
    B, K = idx.shape[0], t.var.size
    D = np.zeros((2 * K, B), dtype=dtype)
    D[0] = 1.0  # TRUE; D[1], FALSE, stays 0
    by_level = np.argsort(-t.var[1:], kind="stable") + 1
    for nodes in np.split(by_level, np.flatnonzero(np.diff(t.var[by_level])) + 1):
        v = int(t.var[nodes[0]])
        lo, hi = t.low[nodes], t.high[nodes]
        if t.is_input[v]:
            D[2 * nodes] = (D[lo] + D[hi]) * 0.5
            D[2 * nodes + 1] = (D[lo ^ 1] + D[hi ^ 1]) * 0.5
        else:
            bit = ((idx[:, t.digit[v]] >> t.shift[v]) & 1).astype(bool)
            child = np.where(bit[None, :], hi[:, None], lo[:, None])
            cells = np.arange(B)[None, :]
            D[2 * nodes] = D[child, cells]
            D[2 * nodes + 1] = D[child ^ 1, cells]
    return D


def _block(t: JointTable, idx: np.ndarray, rng: np.random.Generator | None) -> tuple[np.ndarray, np.ndarray]:
    """:func:`draw` on one block of cells."""
    D = _densities(t, idx)
    B, V = idx.shape[0], t.levels
    ok = D[t.root] > 0
    inputs = np.flatnonzero(t.is_input)
    U = np.ones((B, inputs.size))
    if rng is not None:
        U[ok] = rng.random((int(ok.sum()), inputs.size))
    # every input bit drawn free (1/2, or 0 for the first); the walk overwrites the bits its nodes test
    bits = np.zeros((B, V), dtype=np.int64)
    if rng is not None:
        bits[:, inputs] = U < 0.5
    column = np.cumsum(t.is_input) - 1
    walking = np.flatnonzero(ok)
    e = np.full(walking.size, t.root, dtype=np.int64)
    level = np.full(walking.size, int(t.var[t.root >> 1]), dtype=np.int64)
    while walking.size:
        v = int(level.min())
        if v >= V:
            break
        at = np.flatnonzero(level == v)
        rows, node, neg = walking[at], e[at] >> 1, e[at] & 1
        lo, hi = t.low[node] ^ neg, t.high[node] ^ neg
        if t.is_input[v]:
            d_lo = D[lo, rows]
            if rng is None:
                take = d_lo == 0  # the first: low wherever it has a model
            else:
                d_hi = D[hi, rows]
                take = U[rows, column[v]] * (d_lo + d_hi) < d_hi
        else:
            take = ((idx[rows, t.digit[v]] >> t.shift[v]) & 1).astype(bool)
        bits[rows, v] = take
        e[at] = np.where(take, hi, lo)
        level[at] = t.var[e[at] >> 1]
    codes = np.zeros((B, t.inputs), dtype=np.int64)
    for v in inputs.tolist():
        codes[:, t.digit[v]] |= bits[:, v] << t.shift[v]
    return codes, ok


def draw(t: JointTable, idx: np.ndarray, rng: np.random.Generator | None) -> tuple[np.ndarray, np.ndarray]:
    """An admissible joint input at each cell: codes per subsystem, shape (B, inputs), and whether the cell has
    any (shape (B,); its codes are meaningless where not). Uniform over the cell's inputs with ``rng``, drawing
    ``rng.random(input bits)`` per cell that has inputs, in row order (so one call on many cells draws what calls on
    one cell each would); else the first in the variable order (low branches first, skipped bits 0)."""
    idx = np.asarray(idx, dtype=np.int64).reshape(-1, idx.shape[-1] if np.ndim(idx) else 1)
    per = max(1, COUNT_BLOCK // int(t.var.size))
    parts = [_block(t, idx[s:s + per], rng) for s in range(0, idx.shape[0], per)]
    if not parts:
        return np.zeros((0, t.inputs), dtype=np.int64), np.zeros(0, dtype=bool)
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def contains(t: JointTable, idx: np.ndarray, codes: np.ndarray) -> np.ndarray:
    """Whether the controller allows the joint input ``codes`` (shape (B, inputs)) at the cells ``idx`` (B, n)."""
    idx, codes = np.asarray(idx, dtype=np.int64), np.asarray(codes, dtype=np.int64)
    e = np.full(idx.shape[0], t.root, dtype=np.int64)
    level = np.full(idx.shape[0], int(t.var[t.root >> 1]), dtype=np.int64)
    for v in range(t.levels):
        here = np.flatnonzero(level == v)
        if here.size == 0:
            continue
        source = codes if t.is_input[v] else idx
        bit = (source[here, t.digit[v]] >> t.shift[v]) & 1
        node, neg = e[here] >> 1, e[here] & 1
        e[here] = np.where(bit == 1, t.high[node], t.low[node]) ^ neg
        level[here] = t.var[e[here] >> 1]
    return (e & 1) == 0
