"""A controller ``C(x̂, û)`` as a node table over its state and input bits: inputs drawn at many cells at once.

Closed loops draw an admissible input at every run's cell in every step. Per cell, a ``let`` and exact model counts
of the cofactor (:class:`~.counting.Sampler`) cost milliseconds of Python each: on a ring of 100 rooms, ten
milliseconds a cell and two thirds of the job's time. Here one table of the controller's nodes (CUDD's, complement
edges included; node 0 the constant TRUE, an edge ``(node << 1) | complemented``, as in :mod:`.node_table`) serves
every cell, in compiled loops. Per cell, :func:`draw` computes, children first, the share of the assignments of
the input bits at and below each node's level that satisfy the node's function, for the nodes the cell reaches
(one child at a state level, the cell's bit; both at an input level: about the cell's cofactor). A share does not
depend on the levels an edge skips, so a node's is the mean of its children's at an input level and the picked
child's at a state level. Then one walk from the root takes each input bit's branch with its share, and a level
the node does not test with probability 1/2: :class:`~.counting.Sampler`'s uniform distribution over the cell's
admissible joint inputs. Shares are kept as base-2 logarithms, of the function and of its negation (never
``1 - share``, which rounds a share of ``2**-60`` away; a network of a thousand subsystems has shares below
float64's range), so the draw is uniform up to float rounding and a branch without models (log share ``-inf``)
is never taken.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np
from numba import njit

from pipelines.symbolic.node_table import bit_positions, node_arrays


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


def joint_table(model: Any, f: Any) -> JointTable:
    """The :class:`JointTable` of ``f``, a BDD over the current-state and input bits of ``model`` (a
    :class:`~.symbolic_model.SymbolicModel`); one walk of its nodes (:func:`~.node_table.node_arrays`)."""
    bdd = model.bdd
    bits = sorted([*model.x_bits, *model.u_bits], key=bdd.level_of_var)
    var, low, high, root = node_arrays(bdd, [f], {bdd.level_of_var(b): k for k, b in enumerate(bits)})
    var[0] = len(bits)  # the constant: below every level
    positions = bit_positions(model, bits)
    return JointTable(np.asarray([b[0] == "u" for b in bits], dtype=bool), positions[:, 0], positions[:, 1],
                      var, low, high, int(root[0]), len(model.u_digits()))


@njit(cache=True, nogil=True)
def _value(e: np.int64, L1: np.ndarray, L0: np.ndarray) -> tuple[float, float]:
    """log2 shares of the edge ``e`` and of its negation (the constant TRUE: 0 and -inf)."""
    node = e >> 1
    a, b = (0.0, -np.inf) if node == 0 else (L1[node], L0[node])
    return (b, a) if e & 1 else (a, b)


@njit(cache=True, nogil=True)
def _mean(a: float, b: float) -> float:
    """log2((2**a + 2**b) / 2), exact at -inf."""
    if a == -np.inf:
        return b - 1.0
    if b == -np.inf:
        return a - 1.0
    hi, lo = max(a, b), min(a, b)
    return hi + np.log2(1.0 + np.exp2(lo - hi)) - 1.0


@njit(cache=True, nogil=True)
def _shares(c: int, is_input: np.ndarray, digit: np.ndarray, shift: np.ndarray, var: np.ndarray, low: np.ndarray,
            high: np.ndarray, root: np.int64, idx: np.ndarray, stamp: np.ndarray, L1: np.ndarray, L0: np.ndarray,
            stack: np.ndarray) -> None:
    """The log2 shares (``L1``, ``L0``) of the nodes cell ``c`` reaches from the root (stamped ``c``), children
    first: one child at a state level (the cell's bit), both at an input level."""
    sp = 1
    stack[0] = root >> 1
    while sp > 0:
        n = stack[sp - 1]
        if n == 0 or stamp[n] == c:
            sp -= 1
            continue
        v = var[n]
        if is_input[v]:
            lo, hi = low[n] >> 1, high[n] >> 1
            pushed = False
            for child in (lo, hi):
                if child != 0 and stamp[child] != c:
                    stack[sp] = child
                    sp += 1
                    pushed = True
            if pushed:
                continue
            a1, a0 = _value(low[n], L1, L0)
            b1, b0 = _value(high[n], L1, L0)
            L1[n], L0[n] = _mean(a1, b1), _mean(a0, b0)
        else:
            e = high[n] if (idx[c, digit[v]] >> shift[v]) & 1 else low[n]
            child = e >> 1
            if child != 0 and stamp[child] != c:
                stack[sp] = child
                sp += 1
                continue
            L1[n], L0[n] = _value(e, L1, L0)
        stamp[n] = c
        sp -= 1


@njit(cache=True, nogil=True)
def _draw(is_input: np.ndarray, digit: np.ndarray, shift: np.ndarray, var: np.ndarray, low: np.ndarray,
          high: np.ndarray, root: np.int64, idx: np.ndarray, U: np.ndarray, first: bool, codes: np.ndarray,
          ok: np.ndarray) -> None:
    """:func:`draw`'s loop: per cell its shares, then one walk from the root (``U``: a uniform per input level)."""
    K, V = var.size, is_input.size
    stamp = np.full(K, -1, dtype=np.int64)
    L1, L0 = np.empty(K), np.empty(K)
    stack = np.empty(2 * V + 4, dtype=np.int64)
    for c in range(idx.shape[0]):
        _shares(c, is_input, digit, shift, var, low, high, root, idx, stamp, L1, L0, stack)
        ok[c] = _value(root, L1, L0)[0] > -np.inf
        if not ok[c]:
            continue
        e, col = root, 0
        for v in range(V):
            n = e >> 1
            if var[n] == v:
                if is_input[v]:
                    lo, hi = low[n] ^ (e & 1), high[n] ^ (e & 1)
                    l_lo, l_hi = _value(lo, L1, L0)[0], _value(hi, L1, L0)[0]
                    take = l_lo == -np.inf if first else U[c, col] * (1.0 + np.exp2(l_lo - l_hi)) < 1.0
                    e = hi if take else lo
                else:
                    take = (idx[c, digit[v]] >> shift[v]) & 1 == 1
                    e = high[n] ^ (e & 1) if take else low[n] ^ (e & 1)
            else:  # a level the node does not test: either value
                take = not first and U[c, col] < 0.5 if is_input[v] else False
            if is_input[v]:
                if take:
                    codes[c, digit[v]] |= np.int64(1) << shift[v]
                col += 1


def draw(t: JointTable, idx: np.ndarray, rng: np.random.Generator | None) -> tuple[np.ndarray, np.ndarray]:
    """An admissible joint input at each cell: codes per subsystem, shape (B, inputs), and whether the cell has
    any (shape (B,); its codes are meaningless where not). Uniform over the cell's inputs with ``rng``, drawing
    ``rng.random(input bits)`` per cell in row order (so one call on many cells draws what calls on one cell each
    would); else the first in the variable order (low branches first, skipped bits 0)."""
    idx = np.ascontiguousarray(idx, dtype=np.int64).reshape(-1, idx.shape[-1] if np.ndim(idx) else 1)
    n_in = int(t.is_input.sum())
    U = rng.random((idx.shape[0], n_in)) if rng is not None else np.zeros((idx.shape[0], n_in))
    codes = np.zeros((idx.shape[0], t.inputs), dtype=np.int64)
    ok = np.zeros(idx.shape[0], dtype=bool)
    _draw(t.is_input, t.digit, t.shift, t.var, t.low, t.high, np.int64(t.root), idx, U, rng is None, codes, ok)
    return codes, ok


@njit(cache=True, nogil=True)
def _contains(is_input: np.ndarray, digit: np.ndarray, shift: np.ndarray, var: np.ndarray, low: np.ndarray,
              high: np.ndarray, root: np.int64, idx: np.ndarray, codes: np.ndarray, out: np.ndarray) -> None:
    for c in range(idx.shape[0]):
        e = root
        while e >> 1 != 0:
            n = e >> 1
            v = var[n]
            code = codes[c, digit[v]] if is_input[v] else idx[c, digit[v]]
            e = (high[n] if (code >> shift[v]) & 1 else low[n]) ^ (e & 1)
        out[c] = e & 1 == 0


def contains(t: JointTable, idx: np.ndarray, codes: np.ndarray) -> np.ndarray:
    """Whether the controller allows the joint input ``codes`` (shape (B, inputs)) at the cells ``idx`` (B, n)."""
    idx, codes = np.ascontiguousarray(idx, dtype=np.int64), np.ascontiguousarray(codes, dtype=np.int64)
    out = np.zeros(idx.shape[0], dtype=bool)
    _contains(t.is_input, t.digit, t.shift, t.var, t.low, t.high, np.int64(t.root), idx, codes, out)
    return out
