"""Bulk construction of BDDs from arrays: Shannon trees built bottom-up (docs/method.md §5, "never one point at a time").

A relation given per cell of some digits (the subsystem relations' interval arrays, the interconnection's node
ranges) is built as a Shannon tree, bottom-up: every cell gets a leaf id (:func:`range_leaves`: ``np.unique``
over its ``(lo, hi)`` rows; a leaf is a memoised interval comparator on the output bits), then (:func:`tree`)
for each input bit from the bottom level up siblings are paired, the distinct ``(low, high)`` id pairs are found
with :func:`factorize`, and one ``ite`` is made per distinct pair. The Python work is proportional to the number
of distinct subtrees, not to the number of cells.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence

import numpy as np

from pipelines.symbolic.symbolic_model import Function, SymbolicModel

#: The Shannon-tree keys are int64: at most this many bits per key; :func:`tree` splits wider relations by digit.
MAX_TREE_BITS = 62
#: ``say(message)``: what a long construction reports as it goes (at most every :data:`SAY_EVERY` seconds).
Say = Callable[[str], None]
SAY_EVERY = 1.0


class _Every:
    """``say``, at most every :data:`SAY_EVERY` seconds: :meth:`due` says whether to make a message now."""

    def __init__(self, say: Say | None) -> None:
        self.enabled = say is not None
        self.say: Say = say or (lambda _: None)
        self.last = time.monotonic()

    def due(self) -> bool:
        if not self.enabled or time.monotonic() - self.last < SAY_EVERY:
            return False
        self.last = time.monotonic()
        return True


def factorize(keys: np.ndarray, bound: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(keys, return_inverse=True)`` for int64 keys in ``[0, bound)``.

    When ``bound`` is small against ``len(keys)`` the distinct keys are found by marking a dense table
    (``O(N + bound)``, no sort): sorting such keys was a third of the BDD build of the 10 tanks' largest
    interconnection node.
    """
    keys = np.asarray(keys, dtype=np.int64).reshape(-1)
    if keys.size and bound <= 4 * keys.size + (1 << 16):
        present = np.zeros(bound, dtype=bool)
        present[keys] = True
        uniq = np.flatnonzero(present)
        slot = np.cumsum(present, dtype=np.int64) - 1
        return uniq, slot[keys]
    uniq, inverse = np.unique(keys, return_inverse=True)
    return uniq, inverse.reshape(-1)


def unique_rows(rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``np.unique(rows, axis=0, return_inverse=True)``, through one int64 mixed-radix key when it fits.

    Parameters
    ----------
    rows : ndarray of int, shape (N, k)

    Returns
    -------
    uniq : ndarray, shape (U, k), in lexicographic order
    inverse : ndarray of int64, shape (N,)
    """
    rows = np.asarray(rows, dtype=np.int64)
    lo = rows.min(axis=0)
    span = rows.max(axis=0) - lo + 1
    if rows.shape[0] == 0 or math.prod(int(v) for v in span) >= 1 << 62:
        uniq, inverse = np.unique(rows, axis=0, return_inverse=True)
        return uniq, inverse.reshape(-1)
    key = np.zeros(rows.shape[0], dtype=np.int64)
    for c in range(rows.shape[1]):
        key = key * int(span[c]) + (rows[:, c] - lo[c])
    ukey, inverse = factorize(key, math.prod(int(v) for v in span))
    first = np.empty(ukey.size, dtype=np.int64)
    first[inverse] = np.arange(rows.shape[0])  # rows with equal keys are equal: any one will do
    return rows[first], inverse


class _Subtrees:
    """The subtrees built so far, by id: ``funcs[i]`` is subtree ``i``, ``False`` is 0. Equal functions get equal
    ids, so subtrees that CUDD finds equal pair up as equal (:func:`tree` makes one ``ite`` per distinct pair)."""

    def __init__(self, false: Function) -> None:
        self.funcs: list[Function] = [false]
        self.ident: dict[int, int] = {int(false): 0}

    def intern(self, f: Function) -> int:
        """The id of ``f``, a new one if no equal function has one."""
        k = int(f)
        i = self.ident.get(k)
        if i is None:
            i = self.ident[k] = len(self.funcs)
            self.funcs.append(f)
        return i


def tree(
    model: SymbolicModel,
    digits: Sequence[str],
    values: np.ndarray,
    leaf_ids: np.ndarray,
    leaves: Sequence[Function],
    say: Say | None = None,
) -> Function:
    """``∨_r (digits = values[r]) ∧ leaves[leaf_ids[r]]`` as a Shannon tree built bottom-up in bulk.

    Parameters
    ----------
    digits : sequence of str, length D
        The tree's branching digits (their bits may be interleaved with the leaves' variables; ``ite``
        handles any order).
    values : ndarray of int, shape (N, D)
        Distinct cells (codes per digit). Codes absent from ``values`` map to ``False``.
    leaf_ids : ndarray of int, shape (N,)
        Index into ``leaves`` per cell.
    leaves : sequence of Function
        Leaf functions (over variables other than the tree's bits).
    say : callable, optional
        Told the level being built, now and then (:data:`Say`).

    Notes
    -----
    Per bit, from the bottom level up, siblings are paired; one ``ite`` is made per distinct
    ``(low, high)`` pair of subtree ids, so Python work is proportional to the distinct subtrees
    (:func:`_build_levels`).

    Digits over more than :data:`MAX_TREE_BITS` bits in all (the ten tanks at spacing 1.25: 10 x 7 state bits)
    are split (:func:`_tree_by_first_digit`).
    """
    values = np.asarray(values, dtype=np.int64).reshape(len(leaf_ids), len(digits))
    leaf_ids = np.asarray(leaf_ids, dtype=np.int64)
    if len(digits) > 1 and sum(len(model.bits[d]) for d in digits) > MAX_TREE_BITS:
        return _tree_by_first_digit(model, digits, values, leaf_ids, leaves, say)
    subtrees = _Subtrees(model.bdd.false)
    leaf_map = np.array([subtrees.intern(f) for f in leaves], dtype=np.int64)
    ids = leaf_map[leaf_ids] if leaf_ids.size else leaf_ids
    keep = ids != 0  # absent codes are False already
    ids, values = ids[keep], values[keep]
    if ids.size == 0:
        return model.bdd.false
    names, keys = _tree_keys(model, digits, values)
    if not np.all(keys[1:] > keys[:-1]):  # often sorted already (row-major cells, digit-major order)
        srt = np.argsort(keys, kind="stable")
        keys, ids = keys[srt], ids[srt]
        if np.any(keys[1:] == keys[:-1]):
            raise ValueError("tree(): repeated cell in values")
    return _build_levels(model, names, keys, ids, subtrees, say)


def _tree_by_first_digit(model: SymbolicModel, digits: Sequence[str], values: np.ndarray, leaf_ids: np.ndarray,
                         leaves: Sequence[Function], say: Say | None) -> Function:
    """:func:`tree` of digits too wide for one int64 key: one tree over the other digits per code of the first
    digit, which become the leaves of a tree over the first digit (the same function, since the cells with one
    code of the first digit are that code's subtree)."""
    codes, which = np.unique(values[:, 0], return_inverse=True)
    which = which.reshape(-1)
    order = np.argsort(which, kind="stable")
    bounds = np.searchsorted(which[order], np.arange(codes.size + 1))
    subtrees = [tree(model, digits[1:], values[order[a:b], 1:], leaf_ids[order[a:b]], leaves, say)
                for a, b in zip(bounds[:-1], bounds[1:])]
    return tree(model, digits[:1], codes.reshape(-1, 1), np.arange(codes.size, dtype=np.int64), subtrees)


def _tree_keys(model: SymbolicModel, digits: Sequence[str], values: np.ndarray) -> tuple[list[str], np.ndarray]:
    """Each cell's path from the root of the tree as one int64 key: the bits of its codes, ordered as the BDD
    orders their variables (the top variable the most significant bit).

    Returns
    -------
    names : list of str
        The digits' bit variables in level order (``names[k]`` is key bit ``B - 1 - k``).
    keys : ndarray of int64, shape (N,)
    """
    names: list[str] = []
    for d, digit in enumerate(digits):
        m = len(model.bits[digit])
        if values[:, d].min() < 0 or values[:, d].max() >= 1 << m:
            raise ValueError(f"codes of digit {digit} outside 0 .. {(1 << m) - 1}")
        names.extend(model.bits[digit])
    B = len(names)
    if B > MAX_TREE_BITS:
        raise ValueError(f"a relation over {B} bits exceeds the {MAX_TREE_BITS}-bit tree keys")
    names.sort(key=model.bdd.level_of_var)
    shift = {name: B - 1 - k for k, name in enumerate(names)}  # key bit of each variable (top = MSB)
    keys = np.zeros(values.shape[0], dtype=np.int64)
    for d, digit in enumerate(digits):
        # One lookup table per digit scatters its code's bits to their key positions (bits of different
        # digits may interleave in level order).
        bits = model.bits[digit]
        m = len(bits)
        codes = np.arange(1 << m, dtype=np.int64)
        table = np.zeros(1 << m, dtype=np.int64)
        for b, name in enumerate(bits):
            table |= ((codes >> (m - 1 - b)) & 1) << shift[name]
        keys |= table[values[:, d]]
    return names, keys


def _build_levels(model: SymbolicModel, names: list[str], keys: np.ndarray, ids: np.ndarray, subtrees: _Subtrees,
                  say: Say | None) -> Function:
    """The Shannon tree from its cells' sorted keys (:func:`_tree_keys`) and leaf ids: for each bit from the
    bottom level up, siblings are paired and one ``ite`` is made per distinct ``(low, high)`` pair of ids."""
    ite = model.bdd.ite
    funcs = subtrees.funcs
    B = len(names)
    tell = _Every(say)
    for level in range(B - 1, -1, -1):
        if tell.due():
            tell.say(f"tree level {B - level} of {B}: {keys.size:,} subtrees")
        var = model.var(names[level])
        parent = keys >> 1
        first = np.ones(parent.size, dtype=bool)
        first[1:] = parent[1:] != parent[:-1]
        # Keys are sorted, so a parent's one or two rows are adjacent, the 0-child first.
        starts = np.flatnonzero(first)
        ends = np.empty_like(starts)
        ends[:-1] = starts[1:] - 1
        ends[-1] = keys.size - 1
        low = np.where((keys[starts] & 1) == 0, ids[starts], 0)
        high = np.where((keys[ends] & 1) == 1, ids[ends], 0)
        M = len(funcs)
        pairs, inverse = factorize(low * M + high, M * M)
        made = np.empty(pairs.size, dtype=np.int64)
        for q, pair in enumerate(pairs.tolist()):
            lo_id, hi_id = divmod(pair, M)
            made[q] = lo_id if lo_id == hi_id else subtrees.intern(ite(var, funcs[hi_id], funcs[lo_id]))
        ids = made[inverse.ravel()]
        keys = parent[starts]
    return funcs[int(ids[0])]


def range_leaves(
    model: SymbolicModel, out_digits: Sequence[str], lo: np.ndarray, hi: np.ndarray, empty: np.ndarray | None = None,
    say: Say | None = None,
) -> tuple[np.ndarray, list[Function]]:
    """Leaf ids and leaf functions for per-cell output ranges (grouping equal ranges).

    Parameters
    ----------
    out_digits : sequence of str, length k
    lo, hi : ndarray of int, shape (N, k)
        Inclusive range per output digit; a row with ``lo > hi`` in any digit is empty.
    empty : ndarray of bool, shape (N,), optional
        Rows forced empty (blocking triples).
    say : callable, optional
        Told how many leaves are built, now and then (:data:`Say`).

    Returns
    -------
    leaf_ids : ndarray of int64, shape (N,)
        0 for empty rows.
    leaves : list of Function
        ``leaves[0]`` is ``False``; the others are ``∧_d lo_d <= code(out_d) <= hi_d``.
    """
    lo = np.asarray(lo, dtype=np.int64).reshape(-1, len(out_digits))
    hi = np.asarray(hi, dtype=np.int64).reshape(-1, len(out_digits))
    dead = np.any(lo > hi, axis=1)
    if empty is not None:
        dead |= np.asarray(empty, dtype=bool).reshape(-1)
    leaf_ids = np.zeros(lo.shape[0], dtype=np.int64)
    leaves: list[Function] = [model.bdd.false]
    live = np.flatnonzero(~dead)
    if live.size == 0:
        return leaf_ids, leaves
    rows = np.concatenate([lo[live], hi[live]], axis=1)
    uniq, inverse = unique_rows(rows)
    k = len(out_digits)
    tell = _Every(say)
    for q, row in enumerate(uniq.tolist()):
        if tell.due():
            tell.say(f"leaves {q:,} of {len(uniq):,} distinct successor boxes")
        f = model.bdd.true
        for d, digit in enumerate(out_digits):
            f &= model.interval(digit, row[d], row[k + d])
        leaves.append(f)
    leaf_ids[live] = inverse + 1
    return leaf_ids, leaves
