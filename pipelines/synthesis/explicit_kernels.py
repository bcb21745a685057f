"""Compiled loops of the explicit games (:mod:`.explicit`): predecessor lists and the worklist fixed points.

A game is given by one box of successor cells per pair ``p = x̂ · n_u + û`` (``lo[p]``, ``hi[p]``, grid
indices per coordinate, ``blocking[p]``). Nothing here lists transitions as Python objects: the predecessor
lists are one CSR array (``indptr`` over cells, ``preds`` holding pair indices), made in two passes over the
boxes, and the fixed points are SCOTS's worklist algorithms on it, linear in the transitions. Each fixed point
processes its worklist generation by generation, so its generations are the iterations of the symbolic fixed
point on the same game (the explicit and the BDD solvers report the same iteration counts).
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: A counter no decrement can bring to 0 (blocking pairs, pairs of states that cannot enter).
NEVER = np.int32(2**30)


@njit(cache=True, nogil=True)
def _flat(idx: np.ndarray, strides: np.ndarray) -> np.int64:
    c = np.int64(0)
    for d in range(idx.size):
        c += np.int64(idx[d]) * strides[d]
    return c


@njit(cache=True, nogil=True)
def _next(idx: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> bool:
    """Advance ``idx`` through the box ``lo .. hi`` (row-major); False once past its last cell."""
    d = idx.size - 1
    while d >= 0:
        idx[d] += 1
        if idx[d] <= hi[d]:
            return True
        idx[d] = lo[d]
        d -= 1
    return False


@njit(cache=True, nogil=True)
def _boxes(lo: np.ndarray, hi: np.ndarray, blocking: np.ndarray, strides: np.ndarray, slots: np.ndarray,
           preds: np.ndarray, fill: bool) -> None:
    """Visit every cell of every non-blocking pair's box: count it (``slots[c + 1] += 1``) or, with ``fill``,
    write the pair into the next free slot of the cell (``preds[slots[c]] = p``)."""
    P, n = lo.shape
    idx = np.empty(n, dtype=np.int64)
    for p in range(P):
        if blocking[p]:
            continue
        for d in range(n):
            idx[d] = lo[p, d]
        while True:
            cell = _flat(idx, strides)
            if fill:
                preds[slots[cell]] = p
                slots[cell] += 1
            else:
                slots[cell + 1] += 1
            if not _next(idx, lo[p], hi[p]):
                break


@njit(cache=True, nogil=True)
def predecessor_lists(lo: np.ndarray, hi: np.ndarray, blocking: np.ndarray, strides: np.ndarray,
                      n_cells: int) -> tuple[np.ndarray, np.ndarray]:
    """The CSR predecessor lists: the pairs whose box holds cell ``c`` are ``preds[indptr[c]:indptr[c + 1]]``,
    in increasing pair order. ``lo``, ``hi``: (P, n) int; ``blocking``: (P,) bool; ``strides``: (n,) int64;
    ``P < 2**31`` (pair indices are int32: half the memory of the largest array). Two passes over the boxes:
    one counts, one fills."""
    indptr = np.zeros(n_cells + 1, dtype=np.int64)
    preds = np.empty(0, dtype=np.int32)
    _boxes(lo, hi, blocking, strides, indptr, preds, False)
    for c in range(n_cells):
        indptr[c + 1] += indptr[c]
    preds = np.empty(indptr[n_cells], dtype=np.int32)
    _boxes(lo, hi, blocking, strides, indptr[:-1].copy(), preds, True)
    return indptr, preds


@njit(cache=True, nogil=True)
def successor_counts(lo: np.ndarray, hi: np.ndarray, blocking: np.ndarray) -> np.ndarray:
    """Cells in each pair's box, shape (P,) int32; :data:`NEVER` for a blocking pair."""
    P, n = lo.shape
    out = np.empty(P, dtype=np.int32)
    for p in range(P):
        if blocking[p]:
            out[p] = NEVER
            continue
        k = 1
        for d in range(n):
            k *= hi[p, d] - lo[p, d] + 1
        out[p] = k
    return out


@njit(cache=True, nogil=True)
def _outside_counts(indptr: np.ndarray, preds: np.ndarray, inside: np.ndarray, P: int) -> np.ndarray:
    """Per pair, how many cells of its box lie outside ``inside`` (one pass over those cells' lists)."""
    out = np.zeros(P, dtype=np.int32)
    for c in range(inside.size):
        if not inside[c]:
            for k in range(indptr[c], indptr[c + 1]):
                out[preds[k]] += 1
    return out


@njit(cache=True, nogil=True)
def safety(indptr: np.ndarray, preds: np.ndarray, blocking: np.ndarray, n_u: int, S: np.ndarray,
           fixed: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """``νZ. fixed ∨ (S ∧ ∃u.CPre(Z))`` by removing states (SCOTS's invariance worklist).

    ``fixed`` states (a subset of ``S``) never leave: ``∅`` gives the safety game ``νZ. S ∧ ∃u.CPre(Z)``; the
    co-Büchi inner fixed point passes ``CPre(X)``. Returns ``Z`` (bool per cell), per pair the number of its
    successors outside ``Z`` (``0``: ``CPre(Z)`` holds for a non-blocking pair), and the generations of removals
    plus one (the symbolic iterations).
    """
    n_x = S.size
    P = blocking.size
    Z = S.copy()
    out = _outside_counts(indptr, preds, Z, P)
    good = np.zeros(n_x, dtype=np.int32)
    for p in range(P):
        if not blocking[p] and out[p] == 0:
            good[p // n_u] += 1
    frontier = np.empty(n_x, dtype=np.int64)
    size = 0
    for x in range(n_x):
        if Z[x] and not fixed[x] and good[x] == 0:
            Z[x] = False
            frontier[size] = x
            size += 1
    nxt = np.empty(n_x, dtype=np.int64)
    generations = 1
    while size > 0:
        generations += 1
        new = 0
        for i in range(size):
            y = frontier[i]
            for k in range(indptr[y], indptr[y + 1]):
                p = preds[k]
                out[p] += 1
                if out[p] == 1 and not blocking[p]:
                    x = p // n_u
                    if Z[x] and not fixed[x]:
                        good[x] -= 1
                        if good[x] == 0:
                            Z[x] = False
                            nxt[new] = x
                            new += 1
        frontier, nxt = nxt, frontier
        size = new
    return Z, out, generations


@njit(cache=True, nogil=True)
def reach(indptr: np.ndarray, preds: np.ndarray, counts: np.ndarray, n_u: int, T: np.ndarray,
          keep: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``μZ. (T ∨ ∃u.CPre(Z)) ∧ keep`` with its layers (SCOTS's reachability worklist, breadth first).

    ``counts``: :func:`successor_counts`. Returns per cell its layer (``0`` for ``T ∧ keep``, ``k`` for a cell
    that enters at iteration ``k``, ``-1`` outside the attractor) and per pair whether it is the progress
    controller's: a pair of a cell of layer ``k > 0`` all of whose successors lie in layers ``< k``.
    """
    n_x = keep.size
    P = counts.size
    layer = np.full(n_x, -1, dtype=np.int32)
    remaining = counts.copy()
    chosen = np.zeros(P, dtype=np.bool_)
    frontier = np.empty(n_x, dtype=np.int64)
    size = 0
    for x in range(n_x):
        if T[x] and keep[x]:
            layer[x] = 0
            frontier[size] = x
            size += 1
    nxt = np.empty(n_x, dtype=np.int64)
    k = 0
    while size > 0:
        new = 0
        for i in range(size):
            y = frontier[i]
            for j in range(indptr[y], indptr[y + 1]):
                p = preds[j]
                x = p // n_u
                if not keep[x] or (layer[x] != -1 and layer[x] <= k):
                    continue
                remaining[p] -= 1
                if remaining[p] == 0:
                    chosen[p] = True
                    if layer[x] == -1:
                        layer[x] = k + 1
                        nxt[new] = x
                        new += 1
        frontier, nxt = nxt, frontier
        size = new
        k += 1
    return layer, chosen


@njit(cache=True, nogil=True)
def cobuchi(indptr: np.ndarray, preds: np.ndarray, blocking: np.ndarray, counts: np.ndarray, n_u: int,
            phi: np.ndarray, top: np.ndarray) -> tuple[np.ndarray, np.ndarray, int, int]:
    """``μX. νY. (φ ∧ CPre(Y)) ∨ (top ∧ CPre(X))`` (``φ ⊆ top``) with the co-Büchi controller.

    A cell that enters at outer iteration ``k + 1`` gets the pairs ``(φ(x̂) ∧ CPre(X_{k+1})) ∨ CPre(X_k)``.
    Returns the domain, the controller's pairs, the outer iterations and the inner ones (all generations).
    """
    n_x = top.size
    P = blocking.size
    X = np.zeros(n_x, dtype=np.bool_)
    out_X = counts.copy()  # successors outside X (NEVER for blocking pairs)
    chosen = np.zeros(P, dtype=np.bool_)
    outer = 0
    inner = 0
    while True:
        outer += 1
        pre_X = np.zeros(n_x, dtype=np.bool_)
        for p in range(P):
            if out_X[p] == 0 and top[p // n_u]:
                pre_X[p // n_u] = True
        start = pre_X | phi
        Y, out_Y, generations = safety(indptr, preds, blocking, n_u, start, pre_X)
        inner += generations
        changed = False
        for x in range(n_x):
            if Y[x] != X[x]:
                changed = True
                break
        if not changed:
            break
        for p in range(P):
            x = p // n_u
            if Y[x] and not X[x] and not blocking[p]:
                chosen[p] = (phi[x] and out_Y[p] == 0) or (out_X[p] == 0 and top[x])
        for c in range(n_x):
            if Y[c] and not X[c]:
                for j in range(indptr[c], indptr[c + 1]):
                    out_X[preds[j]] -= 1
        X = Y
    return X, chosen, outer, inner
