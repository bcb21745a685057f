"""The product of an abstraction with an automaton (pipelines/synthesis/product.py) against a product built state by
state: random small abstractions (single n-D systems and 1-D networks), random complete automata, random cell
classes (an atom surely true, surely false, or on an edge). The explicit and symbolic solvers give the reference's
layers, domain and controller exactly.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from pipelines.abstraction.relation import SubsystemRelation
from pipelines.interconnection import NodeRelation
from pipelines.symbolic.order import SubsystemLayout
from pipelines.symbolic.relations import state_set
from pipelines.synthesis.explicit import ExplicitGame
from pipelines.synthesis.product import reach_explicit, reach_symbolic
from pipelines.temporal.automaton import Automaton

from .games import Explicit, Net, build, controller_matrix, random_net, states_vector
from .strategies import grid


# ============================================================================ random automata and labels
def random_automaton(rng: np.random.Generator, atoms: int) -> Automaton:
    n_q = int(rng.integers(2, 6))
    delta = rng.integers(0, n_q, size=(n_q, 2**atoms)).astype(np.int32)
    accepting = rng.random(n_q) < 0.3
    accepting[rng.integers(1, n_q)] = True  # reachable or not: the solvers must agree either way
    return Automaton(tuple(f"a{i}" for i in range(atoms)), delta, 0, accepting)


def random_classes(rng: np.random.Generator, n_x: int, atoms: int) -> tuple[np.ndarray, np.ndarray]:
    """Per cell a class id, and per class the letters it admits (each atom: 0 false, 1 true, 2 either)."""
    n_classes = 3**atoms
    classes = rng.integers(0, n_classes, size=n_x)
    admits = np.zeros((n_classes, 2**atoms), dtype=bool)
    for c, letter in itertools.product(range(n_classes), range(2**atoms)):
        digits = [(c // 3**i) % 3 for i in range(atoms)]
        admits[c, letter] = all(d == 2 or d == (letter >> i) & 1 for i, d in enumerate(digits))
    return classes, admits


# ============================================================================ the reference
def reference(rows: list[tuple[int, int, bool, list[int]]], n_x: int, n_u: int, has_inputs: np.ndarray,
              automaton: Automaton, classes: np.ndarray, admits: np.ndarray):
    """The product built state by state: ``rows`` are (x, u, blocked, successor cells) of the abstraction (several
    per pair for a network's internal inputs). Returns layers (n_q, n_x), controller (n_q, n_x, n_u), domain."""
    n_q = automaton.n_states
    by_pair: dict[tuple[int, int], list[tuple[bool, list[int]]]] = {}
    for x, u, blocked, cells in rows:
        by_pair.setdefault((x, u), []).append((blocked, cells))
    successors = {}  # (q, x, u) -> set of product successors, or None if blocking
    for (x, u), group in by_pair.items():
        for q in range(n_q):
            if any(b for b, _ in group):
                successors[q, x, u] = None
                continue
            successors[q, x, u] = {(int(automaton.delta[q, s]), y) for _, cells in group for y in cells
                                   for s in np.flatnonzero(admits[classes[y]])}
    layer = np.full((n_q, n_x), -1)
    layer[automaton.accepting] = 0
    controller = np.zeros((n_q, n_x, n_u), dtype=bool)
    controller[automaton.accepting] = True
    k = 0
    while True:
        won = {(q, x) for q in range(n_q) for x in range(n_x) if 0 <= layer[q, x] <= k}
        entering = []
        for q, x in itertools.product(range(n_q), range(n_x)):
            if layer[q, x] >= 0 or not has_inputs[x]:
                continue
            good = [u for u in range(n_u) if (q, x, u) in successors and successors[q, x, u] is not None
                    and successors[q, x, u] <= won]
            if good:
                entering.append((q, x))
                controller[q, x, good] = True
        if not entering:
            break
        for q, x in entering:
            layer[q, x] = k + 1
        k += 1
    first = [{int(automaton.delta[automaton.initial, s]) for s in np.flatnonzero(admits[classes[x]])}
             for x in range(n_x)]
    domain = np.array([all(layer[q, x] >= 0 for q in first[x]) for x in range(n_x)])
    return layer, controller, domain


def single_system(rng: np.random.Generator, shape: tuple[int, ...], n_u: int) -> SubsystemRelation:
    """A random n-D relation with successor boxes near the cell (drift -1..1, width 1-2 per coordinate)."""
    n_x, n = math.prod(shape), len(shape)
    here = np.stack(np.unravel_index(np.arange(n_x), shape), axis=1)[:, None, None, :]
    size = np.asarray(shape)
    lo = np.clip(here + rng.integers(-1, 2, size=(n_x, n_u, 1, n)), 0, size - 1)
    hi = np.minimum(lo + rng.integers(0, 2, size=lo.shape), size - 1)
    blocking = rng.random((n_x, n_u, 1)) < 0.05
    lo[blocking], hi[blocking] = 0, -1
    return SubsystemRelation("test", lo.astype(np.int32), hi.astype(np.int32), blocking, 1, 1)


def rows_of(relation: SubsystemRelation, shape: tuple[int, ...]):
    n_x, n_u = relation.blocking.shape[:2]
    rows = []
    for x, u in itertools.product(range(n_x), range(n_u)):
        lo, hi = relation.lo[x, u, 0], relation.hi[x, u, 0]
        blocked = bool(relation.blocking[x, u, 0])
        cells = [] if blocked else [int(np.ravel_multi_index(c, shape))
                                    for c in itertools.product(*(range(a, b + 1) for a, b in zip(lo, hi)))]
        rows.append((x, u, blocked, cells))
    return rows


def single_net(relation: SubsystemRelation, shape: tuple[int, ...]) -> Net:
    """The single system as a network for the symbolic solver (one internal variable nobody reads)."""
    n_u = relation.blocking.shape[1]
    node = NodeRelation("w0", grid(1), ("x0",), (grid(shape[0]),), None, np.zeros(shape[0], np.int32),
                        np.zeros(shape[0], np.int32), 0.0)
    return Net([SubsystemLayout(0, shape, n_u, (), "k0", 0)], {"k0": relation}, [1], [node], shape, (n_u,))


def letter_sets(cpre, classes: np.ndarray, admits: np.ndarray, shape: tuple[int, ...]):
    cells = np.stack(np.unravel_index(np.arange(classes.size), shape), axis=1)
    return [state_set(cpre.model, cells[admits[classes, s]]) for s in range(admits.shape[1])]


def symbolic_arrays(result, cpre, ex_like, n_q: int):
    W = np.stack([states_vector(cpre.model, w, ex_like) for w in result.winning])
    C = np.stack([controller_matrix(cpre.model, c, ex_like) for c in result.controller])
    layer = np.full(W.shape, -1)
    for q in range(n_q):
        for k, Wk in enumerate(result.layers[q]):
            here = states_vector(cpre.model, Wk, ex_like) & (layer[q] < 0)
            layer[q, here] = k
    return W, C, layer


class _Grid:
    """What states_vector and controller_matrix need of an Explicit game, for a single n-D system."""

    def __init__(self, shape, n_u):
        self.shape, self.N, self.nX, self.nU = shape, len(shape), math.prod(shape), n_u
        self.net = type("N", (), {"n_u": (n_u,)})


# ============================================================================ tests
@pytest.mark.parametrize("seed", range(12))
def test_explicit_and_symbolic_products_of_a_single_system_equal_the_reference(seed):
    rng = np.random.default_rng(seed)
    shape = tuple(int(k) for k in rng.integers(3, 6, size=int(rng.integers(1, 3))))
    n_u, atoms = int(rng.integers(2, 4)), int(rng.integers(1, 3))
    relation = single_system(rng, shape, n_u)
    automaton = random_automaton(rng, atoms)
    classes, admits = random_classes(rng, math.prod(shape), atoms)
    n_x = math.prod(shape)
    layer, controller, domain = reference(rows_of(relation, shape), n_x, n_u, np.ones(n_x, bool), automaton,
                                          classes, admits)

    ex = reach_explicit(ExplicitGame.from_relation(relation, shape), automaton, classes, admits)
    np.testing.assert_array_equal(ex.layer, layer)
    np.testing.assert_array_equal(ex.admissible, controller)
    np.testing.assert_array_equal(ex.domain, domain)

    cpre = build(single_net(relation, shape), "interleaved")
    sym = reach_symbolic(cpre, automaton, letter_sets(cpre, classes, admits, shape))
    W, C, sym_layer = symbolic_arrays(sym, cpre, _Grid(shape, n_u), automaton.n_states)
    np.testing.assert_array_equal(W, layer >= 0)
    np.testing.assert_array_equal(sym_layer, layer)
    np.testing.assert_array_equal(C, controller)
    np.testing.assert_array_equal(states_vector(cpre.model, sym.domain, _Grid(shape, n_u)), domain)
    assert sym.domain_states == int(domain.sum()) == ex.domain_states
    assert sym.iterations == ex.iterations


@pytest.mark.parametrize("shared", [True, False], ids=["shared_w", "per_subsystem_w"])
@pytest.mark.parametrize("seed", range(8))
def test_symbolic_product_of_a_network_equals_the_reference(seed, shared):
    rng = np.random.default_rng(100 + seed)
    net = random_net(rng, shared)
    ex = Explicit(net)
    atoms = int(rng.integers(1, 3))
    automaton = random_automaton(rng, atoms)
    classes, admits = random_classes(rng, ex.nX, atoms)
    rows = []
    for r in range(ex.rx.size):
        cells = [int(np.ravel_multi_index(c, ex.shape))
                 for c in itertools.product(*(range(a, b + 1) for a, b in zip(ex.lo[r], ex.hi[r])))]
        rows.append((int(ex.rx[r]), int(ex.ru[r]), bool(ex.blocked[r]), cells))
    layer, controller, domain = reference(rows, ex.nX, ex.nU, ex.has_w, automaton, classes, admits)

    cpre = build(net, "interleaved")
    sym = reach_symbolic(cpre, automaton, letter_sets(cpre, classes, admits, ex.shape))
    W, C, sym_layer = symbolic_arrays(sym, cpre, ex, automaton.n_states)
    np.testing.assert_array_equal(sym_layer, layer)
    np.testing.assert_array_equal(C & ex.has_w[None, :, None], controller & ex.has_w[None, :, None])
    np.testing.assert_array_equal(states_vector(cpre.model, sym.domain, ex), domain)


def test_an_automaton_that_never_accepts_wins_nowhere_and_one_that_always_accepts_everywhere():
    rng = np.random.default_rng(7)
    shape, n_u = (5, 4), 2
    relation = single_system(rng, shape, n_u)
    classes, admits = random_classes(rng, 20, 1)
    game = ExplicitGame.from_relation(relation, shape)
    never = Automaton(("a0",), np.zeros((1, 2), np.int32), 0, np.array([False]))
    assert not reach_explicit(game, never, classes, admits).domain.any()
    always = Automaton(("a0",), np.array([[1, 1], [1, 1]], np.int32), 0, np.array([False, True]))
    result = reach_explicit(game, always, classes, admits)
    # The first letter already accepts: every cell is in the domain, whatever its class.
    assert result.domain.all() and result.winning[1].all() and (result.layer[1] == 0).all()
