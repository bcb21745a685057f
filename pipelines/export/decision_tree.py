"""An exact axis-aligned decision tree over the cell indices, from the determinized controller's table.

The table gives every cell of the state grid a label (the row of the chosen joint input, ``-1`` outside the
domain). The tree splits a box of cells at ``idx[axis] < threshold`` until every box holds one label, so it
reproduces the table on every cell, in and out of the domain (dtControl's exact trees, here with the CART
criterion). The split of a box is the one of largest Gini gain, ``Σ_sides Σ_labels c² / n``, computed for all
axes and thresholds of the box at once from per-slice label counts; Python work is one step per tree node.
"""

from __future__ import annotations

import numpy as np

from pipelines.export.table import TreeTable


def _best_split(block: np.ndarray) -> tuple[int, int]:
    """``(axis, offset)`` of the best split of a box's labels, shape (d1, ..., dn): cells with index ``< offset``
    along ``axis`` (relative to the box) go left."""
    _, inverse = np.unique(block, return_inverse=True)
    inverse = inverse.reshape(block.shape)
    L = int(inverse.max()) + 1
    total = np.bincount(inverse.ravel(), minlength=L).astype(float)
    best, where = -1.0, (0, 1)
    for axis, S in enumerate(block.shape):
        if S < 2:
            continue
        moved = np.moveaxis(inverse, axis, 0).reshape(S, -1)
        keys = (np.arange(S)[:, None] * L + moved).ravel()
        counts = np.bincount(keys, minlength=S * L).reshape(S, L).astype(float)
        left = np.cumsum(counts, axis=0)[:-1]
        right = total - left
        nl, nr = left.sum(axis=1), right.sum(axis=1)
        score = (left**2).sum(axis=1) / nl + (right**2).sum(axis=1) / nr
        k = int(np.argmax(score))
        if score[k] > best + 1e-12:
            best, where = float(score[k]), (axis, k + 1)
    return where


def decision_tree(labels: np.ndarray, max_nodes: int | None = None) -> TreeTable | None:
    """The exact tree of a label table over the whole grid, shape ``grid.shape`` (``-1``: no input), or ``None``
    if it would need more than ``max_nodes`` nodes (then a BDD is smaller anyway)."""
    labels = np.asarray(labels, dtype=np.int64)
    feature: list[int] = [-1]
    threshold: list[int] = [0]
    left: list[int] = [0]
    right: list[int] = [0]
    leaf: list[int] = [-1]
    depth_of = [0]
    stack = [(0, tuple(0 for _ in labels.shape), labels.shape)]
    while stack:
        node, lo, hi = stack.pop()
        block = labels[tuple(slice(a, b) for a, b in zip(lo, hi))]
        first = int(block.flat[0])
        if bool(np.all(block == first)):
            leaf[node] = first
            continue
        axis, offset = _best_split(block)
        cut = lo[axis] + offset
        feature[node], threshold[node] = axis, cut
        kids = []
        for a, b in ((lo[axis], cut), (cut, hi[axis])):
            k = len(feature)
            feature.append(-1)
            threshold.append(0)
            left.append(0)
            right.append(0)
            leaf.append(-1)
            depth_of.append(depth_of[node] + 1)
            kids.append(k)
            stack.append((k, lo[:axis] + (a,) + lo[axis + 1:], hi[:axis] + (b,) + hi[axis + 1:]))
        left[node], right[node] = kids
        if max_nodes is not None and len(feature) > max_nodes:
            return None
    def arr(v: list[int]) -> np.ndarray:
        return np.asarray(v, dtype=np.int64)

    return TreeTable(arr(feature), arr(threshold), arr(left), arr(right), arr(leaf), depth=max(depth_of))
