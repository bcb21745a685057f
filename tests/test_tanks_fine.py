"""The ten tanks at spacing 1.25 (examples/tanks_fine.yaml; issue 24): the spec's counts, and the sliced
construction of large interconnection nodes that keeps its BDD build small in memory.

The case itself runs for hours on a 2-core machine (its safety fixed point: tens of iterations over iterates of
millions of BDD nodes), so no test runs it end to end; what it takes is in the spec's header comment.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

import pipelines.symbolic.relations as relations
from pipelines.grid import UniformGrid
from pipelines.interconnection import NodeRelation
from pipelines.network import build_network
from pipelines.spec.model import load_spec
from pipelines.spec.regions import abstract_region
from pipelines.symbolic.order import SubsystemLayout
from pipelines.symbolic.relations import node_relation
from pipelines.symbolic.symbolic_model import SymbolicModel
from pipelines.symbolic.tree import range_leaves, tree

from .conftest import EXAMPLES


def test_fine_tank_spec_counts():
    """Spacing 1.25 on [1, 100]: the cell of 0 ([-0.625, 0.625]) misses the box, so 80 cells per tank (not 81);
    the target [8.75, 51.25] holds the 33 whole cells 10, 11.25, ..., 50; the input and internal grids are those
    of examples/tanks.yaml."""
    fine, coarse = load_spec(EXAMPLES / "tanks_fine.yaml"), load_spec(EXAMPLES / "tanks.yaml")
    net = build_network(fine, None)
    assert [s.state_grid.size for s in net.subsystems] == [80] * 10
    grid = net.composed_state_grid()
    assert abstract_region(fine.specification.target, grid, "target").states == 33**10
    base = build_network(coarse, None)
    assert [s.input_grid.size for s in net.subsystems] == [s.input_grid.size for s in base.subsystems]
    assert [g.size for g in net.internal_grids] == [g.size for g in base.internal_grids]
    assert fine.options.initial_states == coarse.options.initial_states


def grid(k: int) -> UniformGrid:
    return UniformGrid(origin=(0.0,), eta=(1.0,), k_lo=(0,), k_hi=(k - 1,), lb=(0.0,), ub=(float(k - 1),))


def one_tree(m: SymbolicModel, node: NodeRelation):
    """The node relation as one Shannon tree over all its input cells (the construction before slicing)."""
    shape = node.lo.shape
    N = int(np.prod(shape, dtype=np.int64))
    ids, leaves = range_leaves(m, [node.output], node.lo.reshape(N, 1), node.hi.reshape(N, 1))
    values = np.stack(np.unravel_index(np.arange(N, dtype=np.int64), shape), axis=1)
    return tree(m, list(node.inputs), values, ids, leaves)


@pytest.mark.parametrize("order", ["interleaved", "shared_top"])
@pytest.mark.parametrize("slice_cells", [1, 7, 40, 10**6])
def test_sliced_node_relation_is_the_one_tree_relation(monkeypatch, order, slice_cells):
    """Cutting a node's grid along its first inputs (slice by slice, recursively) gives the same BDD as one tree
    over every cell, with empty ranges (``lo > hi``), repeated slices and slices that are all empty."""
    rng = np.random.default_rng(24)
    sizes = (5, 4, 6)
    layouts = [SubsystemLayout(i, (k,), 2, (), f"k{i}", i) for i, k in enumerate(sizes)]
    m = SymbolicModel(layouts, [7], order=order)
    monkeypatch.setattr(relations, "NODE_SLICE_CELLS", slice_cells)
    for trial in range(4):
        lo = rng.integers(0, 7, size=sizes)
        hi = np.minimum(lo + rng.integers(-1, 3, size=sizes), 6)
        if trial == 1:
            lo[2], hi[2] = 3, 2  # one slice with no cell at all
        if trial == 2:
            lo[3], hi[3] = lo[1], hi[1]  # two equal slices
        node = NodeRelation("w0", grid(7), ("x0", "x1", "x2"), tuple(grid(k) for k in sizes), None,
                            lo.astype(np.int32), hi.astype(np.int32), 0.0)
        f = node_relation(m, node)
        assert f == one_tree(m, node)
        for x in itertools.product(*(range(k) for k in sizes)):
            for w in range(7):
                point = m.state_assignment(list(x))
                bits = m.bits["w0"]
                point.update({b: bool((w >> (len(bits) - 1 - k)) & 1) for k, b in enumerate(bits)})
                assert (m.bdd.let(point, f) == m.bdd.true) == (lo[x] <= w <= hi[x]), (x, w)


@pytest.mark.parametrize("order", ["interleaved", "shared_top"])
@pytest.mark.parametrize("max_bits", [3, 5, 8])
def test_tree_over_more_bits_than_a_key_is_split_by_digit(monkeypatch, order, max_bits):
    """A relation whose digits need more than ``MAX_TREE_BITS`` key bits (the ten tanks at 1.25: 10 x 7 state bits)
    is built one first-digit code at a time; it is the same function as the one-key tree, including sparse cells
    (codes absent from ``values`` are False) and leaves shared between subtrees."""
    import pipelines.symbolic.tree as tree_module

    rng = np.random.default_rng(7 + max_bits)
    sizes = (5, 4, 6)  # 3 + 2 + 3 = 8 bits
    layouts = [SubsystemLayout(i, (k,), 2, (), f"k{i}", i) for i, k in enumerate(sizes)]
    m = SymbolicModel(layouts, [7], order=order)
    digits = ["x0", "x1", "x2"]
    for _ in range(3):
        cells = np.array(list(itertools.product(*(range(k) for k in sizes))), dtype=np.int64)
        cells = cells[rng.random(len(cells)) < 0.6]
        lo = rng.integers(0, 7, size=len(cells))
        hi = np.minimum(lo + rng.integers(0, 3, size=len(cells)), 6)
        ids, leaves = range_leaves(m, ["w0"], lo.reshape(-1, 1), hi.reshape(-1, 1))
        whole = tree(m, digits, cells, ids, leaves)
        monkeypatch.setattr(tree_module, "MAX_TREE_BITS", max_bits)
        try:
            split = tree(m, digits, cells, ids, leaves)
        finally:
            monkeypatch.undo()
        assert split == whole
        member = {tuple(c): (a, b) for c, a, b in zip(cells.tolist(), lo, hi)}
        bits = m.bits["w0"]
        for x in itertools.product(*(range(k) for k in sizes)):
            for w in range(7):
                point = m.state_assignment(list(x))
                point.update({b: bool((w >> (len(bits) - 1 - k)) & 1) for k, b in enumerate(bits)})
                inside = x in member and member[x][0] <= w <= member[x][1]
                assert (m.bdd.let(point, split) == m.bdd.true) == inside, (x, w)


@pytest.mark.slow
def test_the_papers_initial_state_is_outside_the_fine_domain():
    """Issue 24's question, answered without the hours-long fixed point (pipelines/synthesis/domain_bound.py):
    tanks 4, 5 and 7 read no other tank, so the domain's projection on them lies in their own game's
    Reach(Safe), and from the paper's (7, 7.5, 8) that game cannot win. A state near the middle of the target
    is inside every group's game (the bound rules out only what it must)."""
    from pipelines.symbolic.relations import region, state_set
    from pipelines.synthesis.cpre import ControllablePredecessor
    from pipelines.synthesis.domain_bound import domain_bound
    from workers.job import run_abstraction

    spec = load_spec(EXAMPLES / "tanks_fine.yaml")
    r = run_abstraction(spec, audit=False)
    cpre = ControllablePredecessor.from_network(r.network, r.relations, r.interconnection)
    try:
        m = cpre.model
        grid = r.network.composed_state_grid()
        target = region(m, abstract_region(spec.specification.target, grid, "target"))
        bound = domain_bound(cpre, "reach_and_stay", target)
        x0 = np.array(spec.options.initial_states)
        first, last = grid.cells_touching(x0, x0)
        assert (first == last).all()  # the paper's state is on no cell boundary
        assert bound.ruled_out_by(state_set(m, first)) == (3, 4, 6)
        middle, _ = grid.cell_of(np.full((1, 10), 36.25))
        assert bound.ruled_out_by(state_set(m, middle)) is None
    finally:
        cpre.close()
