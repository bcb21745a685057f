"""The abstraction as BDDs: subsystem relations, the interconnection relation, sets of states (Algorithm 5).

* :func:`subsystem_relations`: ``T_i(x_i, u_i, w_i, x'_i)`` over the non-blocking triples and the non-blocking
  set ``NB_i(x_i, u_i, w_i)`` of each subsystem (Definition 4.2), from the interval arrays of
  :class:`~pipelines.abstraction.relation.SubsystemRelation`; identical subsystems are built once and renamed.
* :func:`interconnection_parts`: ``M̂_j(x, w_j) = ∃z. ∧ R_node`` per internal variable (Section 4.2, Theorem
  4.7), with early quantification of the intermediate variables; :func:`interconnection` conjoins them.
* :func:`region`, :func:`state_set`, :func:`pair_set`: sets of states (and inputs) from boxes or cell lists.

All are built in bulk as Shannon trees (:mod:`.tree`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Mapping, Sequence
from typing import TYPE_CHECKING

import numpy as np

from pipelines.symbolic.order import SubsystemLayout, tree_owners
from pipelines.symbolic.symbolic_model import Function, SymbolicModel, and_exists
from pipelines.symbolic.tree import Say, range_leaves, tree

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from pipelines.abstraction.relation import SubsystemRelation
    from pipelines.interconnection import NodeRelation
    from pipelines.spec.regions import AbstractRegion


def subsystem_relation(model: SymbolicModel, s: SubsystemLayout, rel: SubsystemRelation, say: Say | None = None
                       ) -> tuple[Function, Function]:
    """``T_s(x_s, u_s, w_s, x'_s)`` over non-blocking triples and ``NB_s(x_s, u_s, w_s)`` (Def. 4.2).

    Parameters
    ----------
    s : SubsystemLayout
    rel : SubsystemRelation
        ``lo``, ``hi`` shape (n_x, n_u, n_w, n); ``blocking`` shape (n_x, n_u, n_w).
    say : callable, optional
        Told how the construction goes, now and then (:data:`~.tree.Say`).
    """
    n_x, n_u, n_w = rel.blocking.shape
    w_shape = tuple(model.w_sizes[j] for j in s.reads) or (1,)
    if n_x != math.prod(s.state_shape) or n_u != s.n_inputs or n_w != math.prod(w_shape):
        raise ValueError(
            f"relation of shape {rel.blocking.shape} does not fit subsystem {s.index} "
            f"(states {s.state_shape}, inputs {s.n_inputs}, internal {w_shape})"
        )
    t0 = time.perf_counter()
    dg = model.subsystem_digits(s)
    N = n_x * n_u * n_w
    xi, ui, wi = np.unravel_index(np.arange(N, dtype=np.int64), (n_x, n_u, n_w))
    cols = list(np.unravel_index(xi, s.state_shape)) + [ui]
    if s.reads:
        cols += list(np.unravel_index(wi, w_shape))
    values = np.stack(cols, axis=1)
    digits = dg["x"] + dg["u"] + dg["w"]
    blocking = rel.blocking.reshape(N)
    where = f"building the relation of subsystem {s.index} ({N:,} boxes)"
    tell = None if say is None else (lambda message: say(f"{where}: {message}"))
    if say is not None:
        say(where)
    with model.guard(where):
        ids, leaves = range_leaves(model, dg["xn"], rel.lo.reshape(N, -1), rel.hi.reshape(N, -1), blocking, tell)
        T = tree(model, digits, values, ids, leaves, tell)
        NB = tree(model, digits, values, (~blocking).astype(np.int64), [model.bdd.false, model.bdd.true])
    model.build_seconds[f"T{s.index}"] = time.perf_counter() - t0
    return T, NB


def renaming(model: SymbolicModel, src: SubsystemLayout, dst: SubsystemLayout) -> dict[str, str]:
    """Bit renaming that maps the variables of ``src`` to those of ``dst`` (identical subsystems)."""
    a, b = model.subsystem_digits(src), model.subsystem_digits(dst)
    out: dict[str, str] = {}
    for kind in ("x", "xn", "u", "w"):
        if len(a[kind]) != len(b[kind]):
            raise ValueError(f"subsystems {src.index} and {dst.index} differ in their {kind} digits")
        for da, db in zip(a[kind], b[kind]):
            if len(model.bits[da]) != len(model.bits[db]):
                raise ValueError(f"digits {da} and {db} differ in width")
            out.update({p: q for p, q in zip(model.bits[da], model.bits[db]) if p != q})
    return out


def subsystem_relations(
    model: SymbolicModel, relations: Mapping[str, SubsystemRelation], share: str = "rename", say: Say | None = None,
) -> tuple[list[Function], list[Function]]:
    """``T_i`` and ``NB_i`` of every subsystem, in network order.

    Parameters
    ----------
    relations : mapping of key to SubsystemRelation
    share : {'rename', 'build'}
        Identical subsystems share arrays; ``'rename'`` builds the BDDs of the first member and renames
        them (``let``) for the others, ``'build'`` builds each from the arrays.
    say : callable, optional
        Told how the construction goes, now and then (:data:`~.tree.Say`).
    """
    first: dict[str, tuple[SubsystemLayout, Function, Function]] = {}
    T: list[Function] = []
    NB: list[Function] = []
    for s in model.subsystems:
        if share == "rename" and s.key in first:
            t0 = time.perf_counter()
            src, t, nb = first[s.key]
            ren = renaming(model, src, s)
            with model.guard(f"renaming the relation of subsystem {src.index} to {s.index}"):
                t, nb = (model.bdd.let(ren, t), model.bdd.let(ren, nb)) if ren else (t, nb)
            model.build_seconds[f"T{s.index}"] = time.perf_counter() - t0
        else:
            t, nb = subsystem_relation(model, s, relations[s.key], say)
            first.setdefault(s.key, (s, t, nb))
        T.append(t)
        NB.append(nb)
    return T, NB


#: Input cells of a node relation built as one Shannon tree; larger nodes are built slice by slice along their first
#: input (:func:`node_relation`). The tree's index arrays cost ~130 bytes per cell: the 10 tanks at spacing 1.25
#: have a node over 80^4 = 41 M cells, which takes 5.2 GB in one tree and ~0.3 GB in slices.
NODE_SLICE_CELLS = 1 << 21


def _node_tree(model: SymbolicModel, inputs: Sequence[str], output: str, lo: np.ndarray, hi: np.ndarray) -> Function:
    """``R(inputs, output)`` for ranges ``lo``, ``hi`` over the full grid of ``inputs`` (shape = their sizes).

    Above :data:`NODE_SLICE_CELLS` cells the grid is cut along its first input: each slice (that input fixed) is
    a relation over the other inputs, built the same way, and the slices are the leaves of a tree over the first
    input. Both are exact (a row-major grid is the union of its slices), so the BDD is the same function as one
    tree over all cells; equal slices are built once each and shared.
    """
    shape = lo.shape
    N = int(np.prod(shape, dtype=np.int64))
    if not inputs:
        ids, leaves = range_leaves(model, [output], lo.reshape(N, 1), hi.reshape(N, 1))
        return leaves[int(ids[0])]
    if N > NODE_SLICE_CELLS and len(inputs) > 1:
        slices = [_node_tree(model, inputs[1:], output, lo[a], hi[a]) for a in range(shape[0])]
        return tree(model, [inputs[0]], np.arange(shape[0], dtype=np.int64).reshape(-1, 1),
                    np.arange(shape[0], dtype=np.int64), slices)
    ids, leaves = range_leaves(model, [output], lo.reshape(N, 1), hi.reshape(N, 1))
    values = np.stack(np.unravel_index(np.arange(N, dtype=np.int64), shape), axis=1)
    return tree(model, list(inputs), values, ids, leaves)


def node_relation(model: SymbolicModel, node: NodeRelation) -> Function:
    """``R_node(inputs, output)``: the output cell lies in the node's range for the input cell."""
    for name, g in zip(node.inputs, node.input_grids):
        if model.sizes.get(name) != g.size:
            raise ValueError(f"node {node.output}: input {name} has {g.size} cells, the model {model.sizes.get(name)}")
    if model.sizes.get(node.output) != node.output_grid.size:
        raise ValueError(f"node {node.output}: output grid does not match the model")
    return _node_tree(model, list(node.inputs), node.output, np.asarray(node.lo), np.asarray(node.hi))


def _tree_part(model: SymbolicModel, group: Sequence[NodeRelation]) -> Function:
    """``∃z. ∧ R_node`` over a tree of nodes (each ``z`` read once), one subtree at a time.

    Each node is conjoined with the relations of the subtrees it reads, whose ``z`` is then quantified: the
    cost of a node is that of its own subtrees. Conjoining in one running product instead costs the whole
    product at every node, quadratic in the number of nodes (a 1,024-coordinate reduction tree: 75 s).
    """
    done: dict[str, Function] = {}
    final = None
    for node in group:  # topological: a z's node comes before its reader
        f = node_relation(model, node)
        for name in node.inputs:
            if name.startswith("z"):
                if name not in done:
                    raise ValueError(f"node {node.output} reads {name}, which no earlier node produces or another "
                                     "node read already (MDec and reduction trees read each z once)")
                f = and_exists(f, done.pop(name), model.bits_of([name]))
        if node.output.startswith("z"):
            done[node.output] = f
        else:
            final = f
    if final is None or done:
        raise ValueError(f"intermediate variables {sorted(done)} feed no final node")
    return final


def interconnection_parts(model: SymbolicModel, nodes: Sequence[NodeRelation]) -> dict[int, Function]:
    """``M̂_j(x, w_j) = ∃z. ∧ R_node`` over the nodes of output ``j``'s tree (Sec. 4.2, Theorem 4.7).

    Nodes are grouped by the ``z`` they share (MDec's forest and the reduction trees have one tree per output,
    each ``z`` read once); each group is conjoined subtree by subtree, each ``z`` quantified once its reader
    holds it (:func:`_tree_part`).
    """
    t0 = time.perf_counter()
    groups: dict[int, list[NodeRelation]] = {}
    owners = tree_owners(nodes)
    for node in nodes:
        j = int(node.output[1:]) if node.output.startswith("w") else owners.get(node.output)
        if j is None:
            raise ValueError(f"intermediate {node.output} feeds no internal variable")
        groups.setdefault(j, []).append(node)
    parts: dict[int, Function] = {}
    with model.guard("building the interconnection relation"):
        for j, group in groups.items():
            parts[j] = _tree_part(model, group)
    missing = set(range(len(model.w_sizes))) - set(parts)
    if missing:
        raise ValueError(f"no node produces w{sorted(missing)}")
    model.build_seconds["interconnection"] = time.perf_counter() - t0
    return parts


def interconnection(model: SymbolicModel, nodes: Sequence[NodeRelation]) -> Function:
    """``M̂(x, w) = ∧_j M̂_j`` (each part with its ``z`` quantified).

    Only the shared-``w`` CPre needs this conjunction. Where each ``w_j`` has one reader keep the parts
    (docs/method.md §5: never build what the partitioned form makes unnecessary): for the 10 tanks in the interleaved
    order the conjunction has 25 M nodes and takes 57 s, the parts 59 k nodes in all and 1.3 s.
    """
    f = model.bdd.true
    with model.guard("conjoining the interconnection relation"):
        for part in interconnection_parts(model, nodes).values():
            f &= part
    return f


def region(model: SymbolicModel, boxes: AbstractRegion) -> Function:
    """A union of index boxes as a BDD over the current-state bits (box = ∧ per-coordinate intervals)."""
    f = model.bdd.false
    for first, last in boxes.boxes:
        box = model.bdd.true
        for i, (a, b) in enumerate(zip(np.asarray(first).tolist(), np.asarray(last).tolist())):
            box &= model.interval(f"x{i}", max(0, a), min(b, model.state_sizes[i] - 1))
        f |= box
    return f


def state_set(model: SymbolicModel, x_idx: np.ndarray, digits: Sequence[str] | None = None) -> Function:
    """The set of composed states given by per-coordinate indices, shape (B, n) (bulk, as a tree); with ``digits``
    (some current-state digits, e.g. one subsystem's), the cells of those digits, shape (B, len(digits))."""
    digits = model.x_digits() if digits is None else list(digits)
    x_idx = np.unique(np.asarray(x_idx, dtype=np.int64).reshape(-1, len(digits)), axis=0)
    if not len(x_idx):
        return model.bdd.false
    return tree(model, digits, x_idx, np.ones(x_idx.shape[0], dtype=np.int64), [model.bdd.false, model.bdd.true])


def pair_set(model: SymbolicModel, x_idx: np.ndarray, u_idx: np.ndarray) -> Function:
    """A set of (state, joint input) pairs: x shape (B, n), per-subsystem flat inputs shape (B, N)."""
    vals = np.concatenate([np.asarray(x_idx, np.int64), np.asarray(u_idx, np.int64)], axis=1)
    vals = np.unique(vals, axis=0)
    return tree(model, model.x_digits() + model.u_digits(), vals, np.ones(vals.shape[0], dtype=np.int64),
                [model.bdd.false, model.bdd.true])

