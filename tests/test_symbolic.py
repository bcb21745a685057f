"""The symbolic encoding (Algorithm 5, docs/method.md §5): bulk construction against naive per-point construction,
enumeration, regions, exact counting, variable order, DDDMP round trip, out-of-memory errors."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from pipelines.abstraction.relation import SubsystemRelation
from pipelines.spec.regions import AbstractRegion
from pipelines.symbolic.counting import count, count_states, enumerate_cells, inputs_at, sample
from pipelines.symbolic.files import dump, load
from pipelines.symbolic.order import SubsystemLayout, block_order, reader_order
from pipelines.symbolic.relations import (
    interconnection,
    node_relation,
    pair_set,
    region,
    state_set,
    subsystem_relation,
    subsystem_relations,
)
from pipelines.symbolic.symbolic_model import (
    GC_LOOSE_UP_TO,
    MAX_CACHE_ENTRIES,
    BDDMemoryError,
    SymbolicModel,
    bit_width,
)
from pipelines.symbolic.tree import factorize, unique_rows

from .strategies import random_node, random_relation


# ------------------------------------------------------------------------------------------- helpers
def cube(m: SymbolicModel, digit: str, value: int):
    """``code(digit) == value``, one bit at a time: the naive construction the bulk one must equal."""
    bits = m.bits[digit]
    f = m.bdd.true
    for k, b in enumerate(bits):
        v = m.var(b)
        f &= v if (value >> (len(bits) - 1 - k)) & 1 else ~v
    return f


def naive_relation(m: SymbolicModel, s: SubsystemLayout, rel: SubsystemRelation):
    """``T`` and ``NB`` by OR-ing one cube per (triple, successor): slow, obviously right."""
    dg = m.subsystem_digits(s)
    w_shape = tuple(m.w_sizes[j] for j in s.reads) or (1,)
    T = NB = m.bdd.false
    rows = []
    n_x, n_u, n_w = rel.blocking.shape
    for xi, u, wi in itertools.product(range(n_x), range(n_u), range(n_w)):
        xs = np.unravel_index(xi, s.state_shape)
        ws = np.unravel_index(wi, w_shape) if s.reads else ()
        pre = cube(m, dg["u"][0], u)
        for d, v in zip(dg["x"], xs):
            pre &= cube(m, d, int(v))
        for d, v in zip(dg["w"], ws):
            pre &= cube(m, d, int(v))
        if rel.blocking[xi, u, wi]:
            continue
        NB |= pre
        ranges = [range(rel.lo[xi, u, wi, d], rel.hi[xi, u, wi, d] + 1) for d in range(len(s.state_shape))]
        for succ in itertools.product(*ranges):
            post = pre
            for d, v in zip(dg["xn"], succ):
                post &= cube(m, d, v)
            T |= post
            rows.append([*map(int, xs), u, *map(int, ws), *succ])
    return T, NB, np.array(rows, dtype=np.int64).reshape(-1, len(dg["x"]) * 2 + 1 + len(dg["w"]))


def sorted_rows(a: np.ndarray) -> np.ndarray:
    return a[np.lexsort(a.T[::-1])] if a.size else a


LAYOUTS = [
    # (layouts, w_sizes): 1-D and 2-D states, no / one / two internal variables, non-powers of two
    ([SubsystemLayout(0, (5,), 3, (0,), "a", 0), SubsystemLayout(1, (3, 2), 2, (0, 1), "b", 1)], [3, 2]),
    ([SubsystemLayout(0, (4,), 2, (), "a", 0), SubsystemLayout(1, (7,), 3, (0,), "b", 1)], [5]),
    ([SubsystemLayout(0, (6,), 1, (1,), "a", 0), SubsystemLayout(1, (6,), 1, (0,), "b", 1)], [1, 9]),
]


# ------------------------------------------------------------------------------------------- encoding
def test_bit_widths():
    assert [bit_width(k) for k in (1, 2, 3, 4, 5, 8, 9, 41, 64, 65)] == [1, 1, 2, 2, 3, 3, 4, 6, 6, 7]


@pytest.mark.parametrize("bound", [1, 7, 1000, 1 << 40])
def test_factorize_matches_numpy_unique(bound):
    rng = np.random.default_rng(bound % 97)
    for n in (0, 1, 5, 3000):
        keys = rng.integers(0, bound, size=n, dtype=np.int64)
        uniq, inv = factorize(keys, bound)
        ref, ref_inv = np.unique(keys, return_inverse=True)
        np.testing.assert_array_equal(uniq, ref)
        np.testing.assert_array_equal(inv, ref_inv.reshape(-1))


def test_unique_rows_matches_numpy():
    rng = np.random.default_rng(0)
    for big in (False, True):
        rows = rng.integers(-3, 5, size=(500, 3))
        if big:
            rows[:, 0] *= 2**40  # spans too wide for one int64 key: the fallback path
            rows[:, 1] *= 2**30
        uniq, inv = unique_rows(rows)
        ref, ref_inv = np.unique(rows, axis=0, return_inverse=True)
        np.testing.assert_array_equal(uniq, ref)
        np.testing.assert_array_equal(inv, ref_inv.reshape(-1))


@pytest.mark.parametrize("order", ["interleaved", "shared_top"])
def test_variable_order_is_as_declared(order):
    layouts = [SubsystemLayout(0, (3,), 2, (1,), "a", 0), SubsystemLayout(1, (5,), 1, (0,), "b", 1)]
    m = SymbolicModel(layouts, [2, 4], {"z0": 3}, z_owner={"z0": 0}, order=order)
    if order == "interleaved":
        expected = ["w1_0", "w1_1", "u0_0", "x0_0", "xn0_0", "x0_1", "xn0_1",
                    "z0_0", "z0_1", "w0_0", "u1_0", "x1_0", "xn1_0", "x1_1", "xn1_1", "x1_2", "xn1_2"]
    else:
        expected = ["w0_0", "w1_0", "w1_1", "z0_0", "z0_1",
                    "x0_0", "x0_1", "u0_0", "xn0_0", "xn0_1", "x1_0", "x1_1", "x1_2", "u1_0", "xn1_0", "xn1_1",
                    "xn1_2"]
    assert m.variables == expected
    assert [m.bdd.var_at_level(k) for k in range(len(expected))] == expected
    assert m.bdd.configure()["reordering"] is False


@pytest.mark.parametrize("order", ["interleaved", "shared_top"])
def test_to_next_equals_renaming_and_refuses_next_state_bits(order):
    layouts = [SubsystemLayout(0, (6,), 3, (1,), "a", 0), SubsystemLayout(1, (5,), 2, (0,), "b", 1)]
    m = SymbolicModel(layouts, [6, 5], order=order)
    rng = np.random.default_rng(1)
    for _ in range(20):
        # random sets of states, and of states x inputs (the renaming must leave input bits alone)
        f = state_set(m, rng.integers(0, [6, 5], size=(rng.integers(1, 12), 2)))
        f |= f & m.var("u0_0") | (m.var("x1_2") & ~m.var("u1_0"))
        expected = m.bdd.let(dict(zip(m.x_bits, m.xn_bits)), f)
        assert m.to_next(f) == expected
        assert m.bdd.support(m.to_next(f)).isdisjoint(m.x_bits)
    with pytest.raises(ValueError, match="already reads next-state bits"):
        m.to_next(m.var("x0_0") & m.var("xn1_0"))


def test_cudd_keeps_its_tables_small():
    """Garbage collection and the computed table are bounded (``GC_LOOSE_UP_TO``, ``MAX_CACHE_ENTRIES``)."""
    m = SymbolicModel([SubsystemLayout(0, (8,), 1, (), "a", 0)], [], order="interleaved")
    cfg = m.bdd.configure()
    assert cfg["loose_up_to"] == GC_LOOSE_UP_TO and cfg["max_cache_hard"] == MAX_CACHE_ENTRIES


def test_unread_internal_variables_go_on_top_in_the_interleaved_order():
    layouts = [SubsystemLayout(0, (3,), 2, (0,), "a", 0)]
    m = SymbolicModel(layouts, [2, 3], order="interleaved")
    assert m.variables[:2] == ["w1_0", "w1_1"]


# ------------------------------------------------------------------------------------------- relations
@pytest.mark.parametrize("order", ["interleaved", "shared_top"])
@pytest.mark.parametrize("case", range(len(LAYOUTS)))
def test_bulk_relation_equals_naive_and_enumerates_back(case, order):
    layouts, w_sizes = LAYOUTS[case]
    rng = np.random.default_rng(10 * case + (order == "shared_top"))
    m = SymbolicModel(layouts, w_sizes, order=order)
    for s in layouts:
        n_w = math.prod(w_sizes[j] for j in s.reads) if s.reads else 1
        for p_block in (0.0, 0.3, 1.0):
            rel = random_relation(rng, s.state_shape, s.n_inputs, n_w, p_block)
            T, NB = subsystem_relation(m, s, rel)
            T_ref, NB_ref, rows = naive_relation(m, s, rel)
            assert T == T_ref
            assert NB == NB_ref
            dg = m.subsystem_digits(s)
            got = enumerate_cells(m, T, dg["x"] + dg["u"] + dg["w"] + dg["xn"])
            np.testing.assert_array_equal(got, sorted_rows(rows))
            assert count(m, T, dg["x"] + dg["u"] + dg["w"] + dg["xn"]) == rows.shape[0]
            assert count(m, NB, dg["x"] + dg["u"] + dg["w"]) == int((~rel.blocking).sum())


def test_identical_subsystems_rename_equals_build():
    layouts = [SubsystemLayout(i, (5,), 3, (i,), "same", i) for i in range(3)]
    rel = random_relation(np.random.default_rng(3), (5,), 3, 4)
    for order in ("interleaved", "shared_top"):
        m = SymbolicModel(layouts, [4, 4, 4], order=order)
        T1, NB1 = subsystem_relations(m, {"same": rel}, share="rename")
        T2, NB2 = subsystem_relations(m, {"same": rel}, share="build")
        assert T1 == T2 and NB1 == NB2
        assert len({int(t) for t in T1}) == 3  # each over its own variables


def explicit_node_sets(nodes, x: tuple[int, ...]) -> dict[str, set[int]]:
    """Allowed cells of every node output at composed state ``x`` (exact ∃z on a forest)."""
    env: dict[str, set[int]] = {f"x{i}": {v} for i, v in enumerate(x)}
    for node in nodes:
        cells: set[int] = set()
        for combo in itertools.product(*(sorted(env[n]) for n in node.inputs)):
            lo, hi = int(node.lo[combo]), int(node.hi[combo])
            cells.update(range(lo, hi + 1))
        env[node.output] = cells
    return env


@pytest.mark.parametrize("order", ["interleaved", "shared_top"])
def test_interconnection_bdd_equals_explicit_exists_z(order):
    rng = np.random.default_rng(5)
    layouts = [SubsystemLayout(i, (k,), 2, (0,), f"k{i}", i) for i, k in enumerate((3, 4, 5))]
    for _ in range(6):
        nodes = [
            random_node(rng, "z0", 3, ["x0", "x1"], [3, 4]),
            random_node(rng, "z1", 2, ["x2"], [5]),
            random_node(rng, "w0", 4, ["z0", "z1", "x1"], [3, 2, 4]),
            random_node(rng, "w1", 3, [], []),
        ]
        m = SymbolicModel(layouts, [4, 3], {"z0": 3, "z1": 2}, z_owner={"z0": 0, "z1": 0}, order=order)
        # Naive: R_node per point (cube by cube), conjunction, then ∃z.
        naive = m.bdd.true
        for node in nodes:
            r = m.bdd.false
            for combo in itertools.product(*(range(g.size) for g in node.input_grids)):
                pre = m.bdd.true
                for name, v in zip(node.inputs, combo):
                    pre &= cube(m, name, v)
                for c in range(node.lo[combo], node.hi[combo] + 1):
                    r |= pre & cube(m, node.output, c)
            assert node_relation(m, node) == r
            naive &= r
        naive = m.bdd.exist(m.z_bits, naive)
        M = interconnection(m, nodes)
        assert M == naive
        rows = []
        for x in itertools.product(range(3), range(4), range(5)):
            env = explicit_node_sets(nodes, x)
            rows += [[*x, a, b] for a in sorted(env["w0"]) for b in sorted(env["w1"])]
        got = enumerate_cells(m, M, m.x_digits() + m.w_digits())
        np.testing.assert_array_equal(got, sorted_rows(np.array(rows, dtype=np.int64).reshape(-1, 5)))


# ------------------------------------------------------------------------------------------- regions, counts
def test_region_bdd_counts_equal_abstract_region_states():
    rng = np.random.default_rng(11)
    sizes = (7, 5, 9)
    layouts = [SubsystemLayout(i, (k,), 2, (), f"k{i}", i) for i, k in enumerate(sizes)]
    m = SymbolicModel(layouts, [], order="interleaved")
    all_x = np.array(list(itertools.product(*(range(k) for k in sizes))))
    for _ in range(20):
        boxes = []
        for _ in range(rng.integers(1, 5)):
            a = rng.integers(0, sizes)
            b = a + rng.integers(-1, 4, size=3)  # sometimes empty, sometimes past the grid
            boxes.append((a, np.minimum(b, np.asarray(sizes) - 1)))
        abstract = AbstractRegion(tuple(boxes))
        f = region(m, abstract)
        assert count_states(m, f) == abstract.states
        np.testing.assert_array_equal(enumerate_cells(m, f, m.x_digits()), all_x[abstract.contains(all_x)])


def test_exact_count_beyond_double_precision():
    """41^12 ≈ 2.25e19 > 2^64: CUDD's double count cannot say this exactly; ours must."""
    layouts = [SubsystemLayout(i, (41,), 1, (), "t", i) for i in range(12)]
    m = SymbolicModel(layouts, [], order="interleaved")
    assert count_states(m, m.bdd.true) == 41**12
    first = np.full(12, 3)
    last = np.full(12, 19)
    second = (np.full(12, 10), np.full(12, 30))
    abstract = AbstractRegion(((first, last), second))
    assert count_states(m, region(m, abstract)) == abstract.states == 17**12 + 21**12 - 10**12
    assert count_states(m, ~region(m, abstract)) == 41**12 - abstract.states


def test_state_set_and_pair_set():
    layouts = [SubsystemLayout(0, (3,), 2, (), "a", 0), SubsystemLayout(1, (5,), 3, (), "b", 1)]
    m = SymbolicModel(layouts, [], order="shared_top")
    xs = np.array([[0, 4], [2, 1], [2, 1], [1, 0]])
    np.testing.assert_array_equal(enumerate_cells(m, state_set(m, xs), m.x_digits()), np.unique(xs, axis=0))
    us = np.array([[1, 2], [0, 0], [0, 1], [1, 1]])
    C = pair_set(m, xs, us)
    np.testing.assert_array_equal(inputs_at(m, C, [2, 1]), [[0, 0], [0, 1]])
    assert inputs_at(m, C, [0, 0]).shape == (0, 2)


# ------------------------------------------------------------------------------------------- persistence
@pytest.mark.parametrize("order", ["interleaved", "shared_top"])
def test_dddmp_round_trip_of_a_controller(tmp_path, order):
    layouts, w_sizes = LAYOUTS[0]
    m = SymbolicModel(layouts, w_sizes, order=order, grids={"note": "synthetic"})
    rng = np.random.default_rng(2)
    xs = np.stack([rng.integers(0, k, 40) for k in m.state_sizes], axis=1)
    us = np.stack([rng.integers(0, s.n_inputs, 40) for s in layouts], axis=1)
    C = pair_set(m, xs, us)
    bdd_path, head_path = dump(m, tmp_path / "controller", C, meta={"kind": "reach", "domain_states": 7})
    assert bdd_path.suffix == ".dddmp" and head_path.suffix == ".json"
    m2, C2, meta = load(bdd_path)
    assert meta == {"kind": "reach", "domain_states": 7}
    assert m2.variables == m.variables
    assert [m2.bdd.var_at_level(k) for k in range(len(m2.variables))] == m.variables
    assert m2.bdd.configure()["reordering"] is False
    assert m2.grids == {"note": "synthetic"}
    digits = m.x_digits() + m.u_digits()
    np.testing.assert_array_equal(enumerate_cells(m2, C2, digits), enumerate_cells(m, C, digits))
    assert C2.dag_size == C.dag_size
    for x in xs[:5]:
        np.testing.assert_array_equal(inputs_at(m2, C2, x), inputs_at(m, C, x))
    # constants survive too
    dump(m, tmp_path / "empty", m.bdd.false)
    m3, F, _ = load(tmp_path / "empty")
    assert F == m3.bdd.false


def test_out_of_memory_is_a_clear_error():
    layouts = [SubsystemLayout(i, (64,), 1, (), "t", i) for i in range(8)]
    m = SymbolicModel(layouts, [], order="interleaved", max_memory=8 << 20)
    rng = np.random.default_rng(0)
    with pytest.raises(BDDMemoryError, match="ran out of memory while stress"):
        with m.guard("stress"):
            f = m.bdd.false
            for _ in range(200):
                xs = rng.integers(0, 64, size=(2000, 8))
                f |= state_set(m, xs)


def test_block_order_minimises_the_linear_arrangement_of_coupled_subsystems():
    tanks = {(0, 1), (0, 2), (1, 2), (3, 4), (2, 5), (3, 5), (4, 5), (5, 6), (4, 6), (2, 7), (5, 8), (7, 8), (7, 9), (8, 9)}

    def length(order, edges):
        pos = {v: i for i, v in enumerate(order)}
        return sum(abs(pos[a] - pos[b]) for a, b in edges)

    order = block_order(10, tanks)
    assert sorted(order) == list(range(10))
    assert length(order, tanks) == 22 < length(range(10), tanks) == 26  # 22 is the optimum (exhaustive search)
    path = {(0, 5), (5, 2), (2, 7), (7, 1), (1, 6), (6, 3)}  # a path of 6 edges hidden in a permutation: optimum 6
    path = {(min(a, b), max(a, b)) for a, b in path}
    assert length(block_order(8, path), path) == 6
    assert block_order(5, set()) == list(range(5))
    ring = {(i, (i + 1) % 40) for i in range(40)}
    ring = {(min(a, b), max(a, b)) for a, b in ring}
    assert length(block_order(40, ring), ring) <= 2 * 39  # a ring laid out without long jumps


def test_reader_order_puts_every_block_below_what_it_reads_and_keeps_chains_together():
    # (reader, read) of the 10 tanks (positions 0..9 = tanks 1..10)
    tanks = {(1, 0), (2, 0), (2, 1), (4, 3), (5, 2), (5, 3), (5, 4), (5, 6), (6, 4), (7, 2), (8, 5), (8, 7),
             (9, 7), (9, 8)}
    order = reader_order(10, tanks)
    assert order == [0, 1, 2, 7, 3, 4, 6, 5, 8, 9]  # the chains 1-2-3-8 and 4-5-7-6, then 9 and 10
    pos = {v: i for i, v in enumerate(order)}
    assert all(pos[a] > pos[b] for a, b in tanks)
    assert reader_order(4, set()) == [0, 1, 2, 3]
    assert reader_order(3, {(0, 1), (1, 2), (2, 0)}) is None  # a cycle: no topological order
    rng = np.random.default_rng(0)
    for _ in range(20):  # random DAGs: always a topological permutation
        n = int(rng.integers(2, 12))
        perm = rng.permutation(n)
        arcs = {(int(perm[a]), int(perm[b])) for a in range(n) for b in range(a) if rng.random() < 0.3}
        order = reader_order(n, arcs)
        pos = {v: i for i, v in enumerate(order)}
        assert sorted(order) == list(range(n)) and all(pos[a] > pos[b] for a, b in arcs)


def test_block_order_is_kept_in_the_header(tmp_path):
    lay = [SubsystemLayout(i, (3,), 2, (), f"k{i}", i, f"s{i}") for i in range(3)]
    m = SymbolicModel(lay, [], order="interleaved", blocks=[2, 0, 1])
    assert m.variables[0].startswith("u2") or m.variables[0].startswith("x2")
    dump(m, tmp_path / "f", m.bdd.true)
    m2, f, _ = load(tmp_path / "f")
    assert m2.blocks == (2, 0, 1) and m2.variables == m.variables
    with pytest.raises(ValueError, match="not a permutation"):
        SymbolicModel(lay, [], blocks=[0, 0, 1])


@pytest.mark.parametrize("seed", range(4))
def test_sample_draws_members_uniformly_and_first_is_deterministic(seed):
    rng = np.random.default_rng(seed)
    lay = [SubsystemLayout(i, (5,), 3, (), f"k{i}", i, f"s{i}") for i in range(3)]  # 5 cells: codes 5..7 invalid
    m = SymbolicModel(lay, [], order="interleaved", blocks=[2, 0, 1] if seed % 2 else None)
    members = rng.random((5, 5, 5)) < 0.3
    members[0, 0, 0] = True
    cells = np.argwhere(members)
    f = state_set(m, cells)
    draws = sample(m, f, m.x_digits(), rng, size=6000)
    assert draws.shape == (6000, 3)
    assert members[tuple(draws.T)].all()  # only members, never an invalid code
    hist = np.zeros(members.shape)
    np.add.at(hist, tuple(draws.T), 1)
    expected = 6000 / len(cells)
    assert (hist[members] > 0).all()
    assert np.abs(hist[members] - expected).max() < 6 * math.sqrt(expected)  # uniform: every member near 6000/|f|
    first = sample(m, f, m.x_digits(), None)
    assert members[tuple(first)] and np.array_equal(first, sample(m, f, m.x_digits(), None))
    assert sample(m, m.bdd.false, m.x_digits(), rng) is None
    assert sample(m, m.bdd.false, m.x_digits(), rng, size=3).shape == (0, 3)
