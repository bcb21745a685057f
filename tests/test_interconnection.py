"""Interconnection abstraction (Section 4.2): lasso supports, MDec (Algorithm 2), error bounds, soundness.

The soundness property (the paper's Theorem thrm_inter, docs/method.md's "Theorem 4.7"): for every concrete ``x``,
every cell containing ``M(x)`` is in ``M̂(x̂)`` for every cell ``x̂`` containing ``x``. Draws put coordinates
exactly on cell boundaries, cell centres and box edges, and both neighbouring cells of a boundary point are
checked.
"""

from __future__ import annotations

import dataclasses
import itertools
import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipelines.errors import CertificationError, LipschitzError, SpecError
from pipelines.interconnection import InterconnectionAbstraction, abstract_interconnection
from pipelines.interconnection.mdec import decompose_row, mdec
from pipelines.network import Network, build_network
from pipelines.spec.model import parse_spec
from pipelines.verification.audit import audit_interconnection

TANK_MAP = (
    "[0, sqrt(x[0]), (sqrt(x[0])+sqrt(x[1]))/2, 0, sqrt(x[3]), "
    "(sqrt(x[2])+sqrt(x[3])+sqrt(x[4])+sqrt(x[6]))/4, sqrt(x[4]), sqrt(x[2]), "
    "(sqrt(x[5])+sqrt(x[7]))/2, (sqrt(x[7])+sqrt(x[8]))/2]"
)
TANK_SUPPORTS = ((), (0,), (0, 1), (), (3,), (2, 3, 4, 6), (4,), (2,), (5, 7), (7, 8))


def network(n: int, lb: float, ub: float, eta: float, **interconnection) -> Network:
    """A network of ``n`` scalar subsystems on ``[lb, ub]`` (spacing ``eta``) and the given interconnection."""
    spec = parse_spec(
        {
            "subsystems": [
                {
                    "name": "s",
                    "replicate": n,
                    "state": {"lb": lb, "ub": ub, "eta": eta},
                    "input": {"lb": 0, "ub": 0, "eta": 1},
                    "dynamics": "x[0]",
                    "lipschitz": {"x": 1.0},
                    # Reading w0 keeps the dynamics' w non-empty (the expression compiler wants dim >= 1).
                    "reads": [0],
                }
            ],
            "interconnection": interconnection,
            "specification": {"kind": "safe", "safe": {"boxes": [{"lb": lb, "ub": ub}]}},
        }
    )
    return build_network(spec, allowed_modules=None)


def consensus_network(**kw) -> Network:
    ic = {"map": "mean(x)", "internal": {"lb": 0, "ub": 32, "eta": 1}, "samples": 20, "sigma": 4, "error": "linear"}
    return network(8, 0, 32, 1, **{**ic, **kw})


def tank_network(error: str, **kw) -> Network:
    ic = {
        "map": TANK_MAP,
        "internal": {"lb": 0, "ub": 10.5, "eta": 0.25},
        "samples": 80,
        "alpha": "cv",
        "sigma": 4,
        "error": error,
        "lipschitz": 0.5,
    }
    return network(10, 1, 100, 2.5, **{**ic, **kw})


def max_network() -> Network:
    ic = {"map": "max(x)", "internal": {"lb": 0, "ub": 32, "eta": 1}, "samples": 200, "sigma": 4,
          "error": "certify", "lipschitz": 1.0}
    return network(6, 0, 32, 1, **ic)


# ============================================================================ the soundness property
def draw_states(net: Network, count: int, rng: np.random.Generator) -> np.ndarray:
    """Concrete states, shape (count, n): uniform, with a third of the coordinates snapped to a cell
    boundary (``k eta ± eta/2``), a cell centre or a box edge."""
    grid = net.composed_state_grid()
    lb, ub, eta = np.asarray(grid.lb), np.asarray(grid.ub), np.asarray(grid.eta)
    x = rng.uniform(lb, ub, (count, grid.dim))
    snap = rng.random(x.shape) < 1 / 3
    centre = np.asarray(grid.origin) + np.round((x - np.asarray(grid.origin)) / eta) * eta
    kind = rng.integers(0, 4, x.shape)
    special = np.select(
        [kind == 0, kind == 1, kind == 2],
        [centre - eta / 2, centre + eta / 2, centre],
        np.where(rng.random(x.shape) < 0.5, lb, ub),
    )
    return np.where(snap, np.clip(special, lb, ub), x)


def both_cells(grid, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Upper and lower cells containing each point (the same cell unless it is on a boundary), on the grid."""
    up, up_in = grid.cell_of(values, "upper")
    low, low_in = grid.cell_of(values, "lower")
    # At a box edge that is a cell boundary the outer cell is off the grid; the inner one holds the point.
    up = np.where(up_in[:, None], up, low)
    low = np.where(low_in[:, None], low, up)
    return up, low


def violations(net: Network, ia: InterconnectionAbstraction, count: int, seed: int) -> int:
    """Number of draws ``x`` for which some cell of ``M(x)`` is missing from ``M̂`` of some cell of ``x``."""
    rng = np.random.default_rng(seed)
    x = draw_states(net, count, rng)
    w = net.interconnection_map(x)
    grid = net.composed_state_grid()
    x_up, x_low = both_cells(grid, x)
    w_cells = [both_cells(g, w[:, j : j + 1]) for j, g in enumerate(net.internal_grids)]
    w_up = np.concatenate([u for u, _ in w_cells], axis=1)
    w_low = np.concatenate([lo for _, lo in w_cells], axis=1)
    # Every cell must be on the grid: the map stays in the internal boxes.
    for j, g in enumerate(net.internal_grids):
        assert np.all((w_up[:, j] >= 0) & (w_up[:, j] < g.size))
    bad = np.zeros(count, dtype=bool)
    for xi in (x_up, x_low):
        for wi in (w_up, w_low):
            bad |= ~ia.contains(xi, wi)
    return int(bad.sum())


@pytest.fixture(scope="module")
def consensus():
    net = consensus_network()
    return net, abstract_interconnection(net, np.random.default_rng(0))


@pytest.fixture(scope="module")
def tanks_direct():
    net = tank_network("direct")
    return net, abstract_interconnection(net, np.random.default_rng(1))


@pytest.fixture(scope="module")
def tanks_certify():
    net = tank_network("certify")
    return net, abstract_interconnection(net, np.random.default_rng(2))


def test_consensus_is_sound(consensus):
    net, ia = consensus
    assert ia.output_modes == ("linear",)
    assert violations(net, ia, 120_000, seed=10) == 0


def test_tanks_direct_is_sound(tanks_direct):
    net, ia = tanks_direct
    assert set(ia.output_modes) == {"direct"}
    assert violations(net, ia, 120_000, seed=11) == 0


def test_tanks_certify_is_sound(tanks_certify):
    net, ia = tanks_certify
    assert set(ia.output_modes) == {"certify"}
    assert violations(net, ia, 120_000, seed=12) == 0


@pytest.mark.parametrize("cap", [50_000, 1])
def test_max_certify_coarse_and_global_is_sound(cap):
    net = max_network()
    ia = abstract_interconnection(net, np.random.default_rng(3), max_certify_cells=cap)
    res = ia.details["certify_resolution"]["w0"]
    assert res["source"] == "uniform partition"
    assert res["cells"] <= cap and res["cells"] == (6 ** 6 if cap == 50_000 else 1)
    if cap == 50_000:
        # MDec: six inputs, sigma 4 -> z0 = x0..x3, z1 = x4..x5, w0 = z0 + z1.
        assert [n.inputs for n in ia.nodes] == [("x0", "x1", "x2", "x3"), ("x4", "x5"), ("z0", "z1")]
        assert ia.details["whole_box_outputs"] == []
    else:
        # On one cell eps covers the whole internal box: one node without inputs, the relation of the tree.
        assert [n.inputs for n in ia.nodes] == [()] and ia.details["whole_box_outputs"] == [0]
        assert_tree_allows_every_cell(net, ia, 0)
    assert violations(net, ia, 100_000, seed=13) == 0


def assert_tree_allows_every_cell(net: Network, ia: InterconnectionAbstraction, j: int) -> None:
    """The MDec tree of output ``j`` (built as if the whole-box shortcut were not there) allows every cell of
    ``w_j`` for every combination of its inputs: the box node is the same relation."""
    from pipelines.interconnection.grids import axis_grid
    from pipelines.interconnection.nodes import intermediate_grid, linear_node

    grid = net.composed_state_grid()
    z_grids: dict = {}
    for plan in mdec(ia.M_bar, ia.supports, ia.details["sigma"]):
        if plan.target != j:
            continue
        in_grids = [axis_grid(grid, int(v[1:])) if v.startswith("x") else z_grids[v] for v in plan.inputs]
        if plan.is_final:
            node = linear_node(plan, net.internal_grids[j], in_grids, ia.offsets[j], ia.error_bounds[j])
            assert node.lo.size > 1 and (node.lo == 0).all() and (node.hi == net.internal_grids[j].size - 1).all()
            box = ia.final_node(j)
            assert int(box.lo) == 0 and int(box.hi) == net.internal_grids[j].size - 1
            return
        z_grids[plan.output] = intermediate_grid(plan, [(g.lb[0], g.ub[0]) for g in in_grids], 1.0)
    raise AssertionError(f"no final node for w{j}")


def test_direct_is_tighter_than_certify_on_the_tanks(tanks_direct, tanks_certify):
    """Beyond the paper: abstracting rows straight from the black box allows fewer cells than M̄ ± eps."""
    _, d = tanks_direct
    _, c = tanks_certify
    for j in range(10):
        assert d.final_node(j).mean_cells() <= c.final_node(j).mean_cells()
    assert d.final_node(5).mean_cells() < c.final_node(5).mean_cells() / 2


def _corrupt(ia: InterconnectionAbstraction, output: str) -> InterconnectionAbstraction:
    nodes = tuple(
        dataclasses.replace(n, hi=(n.hi - 1).astype(np.int32)) if n.output == output else n for n in ia.nodes
    )
    return dataclasses.replace(ia, nodes=nodes)


@pytest.mark.parametrize("output", ["w0", "z0"])
def test_negative_control_a_node_one_cell_short_is_caught(consensus, output):
    """Lowering one node's upper cell by one must make the property test fail (it can fail)."""
    net, ia = consensus
    assert violations(net, _corrupt(ia, output), 20_000, seed=14) > 0


def test_negative_control_on_a_direct_node(tanks_direct):
    net, ia = tanks_direct
    assert violations(net, _corrupt(ia, "w2"), 20_000, seed=15) > 0


# ============================================================================ MDec (Algorithm 2)
def _expand(nodes, j: int) -> dict[int, float]:
    """The linear form of output j in the state coordinates, by substituting the z nodes."""
    forms: dict[str, dict[int, float]] = {}
    for node in nodes:
        form: dict[int, float] = {}
        for name, a in zip(node.inputs, node.weights):
            sub = {int(name[1:]): 1.0} if name.startswith("x") else forms[name]
            for i, c in sub.items():
                assert i not in form, "a coordinate reaches an output twice"
                form[i] = a * c
        forms[node.output] = form
    return forms[f"w{j}"]


@settings(max_examples=150, deadline=None)
@given(
    p=st.integers(1, 5),
    n=st.integers(1, 24),
    sigma=st.integers(1, 4),
    density=st.floats(0.0, 1.0),
    seed=st.integers(0, 2**31),
)
def test_mdec_bounds_in_degree_and_preserves_the_map(p, n, sigma, density, seed):
    rng = np.random.default_rng(seed)
    M = np.where(rng.random((p, n)) < density, rng.normal(size=(p, n)), 0.0)
    supports = [tuple(np.flatnonzero(row)) for row in M]
    if sigma == 1 and any(len(s) > 1 for s in supports):
        with pytest.raises(SpecError, match="sigma must be >= 2 when an output depends on more than one"):
            mdec(M, supports, sigma)
        return
    nodes = mdec(M, supports, sigma)
    assert all(len(node.inputs) <= sigma for node in nodes)
    # Exactly one final node per output; every z read once, after it is produced.
    assert sorted(node.output for node in nodes if node.is_final) == sorted(f"w{j}" for j in range(p))
    produced: list[str] = []
    reads: list[str] = []
    for node in nodes:
        for name in node.inputs:
            if name.startswith("z"):
                assert name in produced
                reads.append(name)
        produced.append(node.output)
    assert sorted(reads) == sorted(name for name in produced if name.startswith("z"))
    # Substituting the z back gives the row of M exactly (same weights, each coordinate once).
    for j in range(p):
        assert _expand(nodes, j) == {int(i): M[j, i] for i in supports[j]}


def test_mdec_gives_the_papers_consensus_shape():
    nodes = mdec(np.full((1, 8), 1 / 8), [tuple(range(8))], 4)
    assert [(n.output, n.inputs) for n in nodes] == [
        ("z0", ("x0", "x1", "x2", "x3")),
        ("z1", ("x4", "x5", "x6", "x7")),
        ("w0", ("z0", "z1")),
    ]
    assert nodes[0].weights == (0.125,) * 4 and nodes[2].weights == (1.0, 1.0)


def test_mdec_layers_when_one_pass_is_not_enough():
    # 20 inputs, sigma 2: 10 z; 5 z; [z,z][z,z][z] -> 2 z + a singleton; [z,z][z] -> 1 z + a singleton;
    # the final node reads those 2.
    nodes = decompose_row(0, range(20), [1.0] * 20, 2, 0)
    assert len(nodes) - 1 == 10 + 5 + 2 + 1 and len(nodes[-1].inputs) == 2
    assert [n.output for n in nodes[:-1]] == [f"z{k}" for k in range(18)]


def test_sigma_one_is_fine_for_outputs_of_one_variable():
    nodes = mdec(np.eye(3), [(0,), (1,), (2,)], 1)
    assert [n.inputs for n in nodes] == [("x0",), ("x1",), ("x2",)]


def test_consensus_nodes_and_intermediate_grids(consensus):
    _, ia = consensus
    assert [n.output for n in ia.nodes] == ["z0", "z1", "w0"]
    for name in ("z0", "z1"):
        g = ia.intermediate_grids[name]
        assert g.size == 17 and g.eta == (1.0,)
        assert g.axis_points(0)[0] == 0 and g.axis_points(0)[-1] == 16
    w0 = ia.final_node(0)
    assert w0.lo.shape == (17, 17) and w0.input_grids[0] is ia.intermediate_grids["z0"]
    np.testing.assert_allclose(ia.M_bar, np.full((1, 8), 1 / 8), atol=1e-12)
    assert ia.error_bounds[0] < 1e-9
    d = ia.describe()
    assert d["supports"] == [list(range(8))] and len(d["nodes"]) == 3


def _allowed_by_enumeration(ia: InterconnectionAbstraction, x: np.ndarray) -> list[set[int]]:
    """``M̂(x̂)`` per output for one row, by enumerating every intermediate cell (``∃z. ∧ R_node``)."""
    allowed: dict[str, set[int]] = {}
    for node in ia.nodes:
        choices = [[int(x[int(name[1:])])] if name.startswith("x") else sorted(allowed[name]) for name in node.inputs]
        cells: set[int] = set()
        for combo in itertools.product(*choices):
            lo, hi = int(node.lo[combo]), int(node.hi[combo])
            cells.update(range(lo, hi + 1))
        allowed[node.output] = cells
    return [allowed[f"w{j}"] for j in range(ia.p)]


@pytest.mark.parametrize("case", ["consensus", "tanks_direct"])
def test_allowed_cells_equal_an_enumeration_of_the_node_relations(case, request):
    """The vectorised masks (difference arrays over intermediate cells, range compares for x-only nodes) against
    a per-row enumeration of every intermediate cell."""
    net, ia = request.getfixturevalue(case)
    rng = np.random.default_rng(21)
    x_idx = np.column_stack([rng.integers(0, k, 150) for k in net.composed_state_grid().shape])
    masks = ia.allowed_cells(x_idx)
    for b in range(x_idx.shape[0]):
        expect = _allowed_by_enumeration(ia, x_idx[b])
        for j in range(ia.p):
            assert set(np.flatnonzero(masks[j][b]).tolist()) == expect[j], (b, j)


def test_describe_is_json_and_allowed_cells_agree_with_contains(consensus):
    net, ia = consensus
    json.dumps(ia.describe())
    rng = np.random.default_rng(5)
    x_idx = rng.integers(0, 33, (500, 8))
    masks = ia.allowed_cells(x_idx)
    assert masks[0].shape == (500, 33) and masks[0].any(axis=1).all()
    w_idx = rng.integers(-1, 34, (500, 1))
    expect = np.array([0 <= w < 33 and masks[0][b, w] for b, w in enumerate(w_idx[:, 0])])
    np.testing.assert_array_equal(ia.contains(x_idx, w_idx), expect)
    with pytest.raises(ValueError, match="off the state grid"):
        ia.contains(np.full((1, 8), 33), np.zeros((1, 1), dtype=int))


def test_progress_is_reported():
    net = network(2, 0, 32, 1, map="x[0] + x[1]", internal={"lb": 0, "ub": 64, "eta": 1}, samples=10,
                  error="linear")
    events = []
    ia = abstract_interconnection(net, np.random.default_rng(0), lambda *e: events.append(e))
    assert events[0][:2] == ("interconnection", 0) and events[-1][1] == events[-1][2]
    assert ia.supports == ((0, 1),) and [n.inputs for n in ia.nodes] == [("x0", "x1")]


def test_sigma_one_with_a_sum_is_refused():
    net = consensus_network(sigma=1)
    with pytest.raises(SpecError, match="sigma must be >= 2"):
        abstract_interconnection(net, np.random.default_rng(0))


def test_constant_outputs_have_no_inputs(tanks_certify):
    _, ia = tanks_certify
    for j in (0, 3):
        node = ia.final_node(j)
        assert node.inputs == () and node.lo.shape == () and int(node.lo) == 0 == int(node.hi)
        assert ia.supports[j] == () and not ia.M_bar[j].any() and ia.offsets[j] == 0


# ============================================================================ lasso supports
def test_lasso_cv_recovers_the_tank_supports_from_80_samples(tanks_certify):
    _, ia = tanks_certify
    assert ia.supports == TANK_SUPPORTS
    # Lasso's candidates never miss a true coordinate; the extra ones are pruned by the dependence test.
    for cand, true in zip(ia.details["lasso_supports"], TANK_SUPPORTS):
        assert set(true) <= set(cand)


def test_a_coordinate_lasso_missed_is_added_by_the_dependence_test():
    net = network(2, 0, 32, 1, map="x[0] + 1e-3*x[1]", internal={"lb": 0, "ub": 40, "eta": 1}, samples=50,
                  alpha=5.0, error="linear")
    ia = abstract_interconnection(net, np.random.default_rng(0))
    assert ia.details["lasso_supports"] == [[0]]
    assert ia.supports == ((0, 1),)
    assert ia.details["support_added_by_dependence_test"] == [[1]]
    assert audit_interconnection(net, ia, 50_000, np.random.default_rng(1)).violations == 0


def test_an_even_function_lasso_cannot_see_is_in_the_support():
    net = network(3, -2, 2, 0.5, map="[0.3 * x[2]**2 / 4 + 0.1 * x[0]]", internal={"lb": -1, "ub": 1, "eta": 0.25},
                  samples=50, error="certify", lipschitz=0.5)
    ia = abstract_interconnection(net, np.random.default_rng(0))
    assert ia.supports == ((0, 2),)
    assert audit_interconnection(net, ia, 50_000, np.random.default_rng(1)).violations == 0


# ============================================================================ errors
def test_a_map_declared_linear_that_is_not_is_refused():
    net = network(2, 1, 100, 2.5, map="sqrt(x[0]) + x[1]", internal={"lb": 0, "ub": 120, "eta": 1}, samples=50,
                  error="linear")
    with pytest.raises(CertificationError, match="not linear"):
        abstract_interconnection(net, np.random.default_rng(0))


def test_a_map_leaving_its_internal_box_is_refused():
    net = network(2, 0, 32, 1, map="[x[0], 2*x[1]]", internal={"lb": 0, "ub": 32, "eta": 1}, samples=50,
                  error="linear")
    with pytest.raises(SpecError, match=r"w1 = .* outside its box .*interconnection\.internal\[1\]"):
        abstract_interconnection(net, np.random.default_rng(0))


@pytest.mark.parametrize("error", ["certify", "direct"])
def test_certify_and_direct_need_a_lipschitz_constant(error):
    net = consensus_network(error=error)
    with pytest.raises(SpecError, match="needs interconnection.lipschitz"):
        abstract_interconnection(net, np.random.default_rng(0))


def test_the_papers_consensus_lipschitz_constant_is_refuted():
    """The paper's L_M = 1/8 for the mean is below its infinity-norm constant 1: unsound, so refused."""
    net = consensus_network(error="certify", lipschitz=0.125)
    with pytest.raises(LipschitzError, match="exceeds the given Lipschitz constant"):
        abstract_interconnection(net, np.random.default_rng(0))


def test_direct_falls_back_to_certify_above_sigma():
    net = consensus_network(error="direct", lipschitz=1.0)
    ia = abstract_interconnection(net, np.random.default_rng(0), max_certify_cells=5_000)
    assert ia.output_modes == ("certify",) and [n.output for n in ia.nodes] == ["z0", "z1", "w0"]
    assert violations(net, ia, 20_000, seed=16) == 0


# ============================================================================ many coordinates, one output alone
def test_unravel_beyond_numpys_64_axes():
    from pipelines.interconnection.grids import unravel

    for shape in [(3,), (4, 1, 5), (2, 3, 4, 5), (1,) * 5]:
        flat = np.arange(int(np.prod(shape)))
        got = unravel(flat, shape)
        assert all(np.array_equal(a, b) for a, b in zip(got, np.unravel_index(flat, shape)))
    shape = (1,) * 40 + (3,) + (1,) * 40 + (2,)
    got = unravel(np.arange(6), shape)
    assert len(got) == 82 and got[40].tolist() == [0, 0, 1, 1, 2, 2] and got[81].tolist() == [0, 1] * 3
    assert unravel(np.arange(1), ()) == ()


def test_max_of_70_states_is_certified_on_one_cell():
    """The scalability example's map at N = 70: a support of 70 coordinates (more axes than numpy allows)."""
    net = network(70, 0, 32, 1, map="max(x)", internal={"lb": 0, "ub": 32, "eta": 1}, samples=200,
                  alpha=1e-6, sigma=4, error="certify", lipschitz=1.0)
    ia = abstract_interconnection(net, np.random.default_rng(0))
    assert ia.supports == (tuple(range(70)),)
    res = ia.details["certify_resolution"]["w0"]
    assert res["cells_per_axis"] == [1] * 70 and res["cells"] == 1
    assert np.isfinite(ia.error_bounds[0])
    assert violations(net, ia, 2_000, seed=70) == 0


SPLIT_MAP = "[sqrt(x[0]), (sqrt(x[0]) + exp(-x[1] / 50)) / 2, 0, tanh(x[2] / 40) + sqrt(x[3]) / 4]"


def split_network() -> Network:
    return network(4, 1, 100, 2.5, map=SPLIT_MAP, internal={"lb": 0, "ub": 10.5, "eta": 0.25}, samples=80,
                   alpha="cv", sigma=4, error="direct", lipschitz=0.5)


def test_direct_nodes_evaluate_one_output_alone_and_are_unchanged(monkeypatch):
    """Entry j of a list map evaluated by itself gives the node that evaluating the whole map gives."""
    from pipelines.interconnection.sampling import Sampler

    net = split_network()
    alone = abstract_interconnection(net, np.random.default_rng(3))
    sampler = Sampler(net)
    assert all(sampler.column(j)[1] for j in range(4))
    monkeypatch.setattr(Sampler, "_entry", lambda self, j: None)
    assert not Sampler(net).column(1)[1]
    whole = abstract_interconnection(net, np.random.default_rng(3))
    assert alone.output_modes == whole.output_modes == ("direct",) * 4
    for a, b in zip(alone.nodes, whole.nodes):
        assert a.output == b.output and a.inputs == b.inputs
        np.testing.assert_array_equal(a.lo, b.lo)
        np.testing.assert_array_equal(a.hi, b.hi)
        assert a.error_bound == b.error_bound
    assert alone.details["evaluations"] == whole.details["evaluations"]
    assert violations(net, alone, 20_000, seed=5) == 0


@pytest.mark.parametrize("map_,p", [("x[0:2]", 2), ("[x[0:2], x[2]]", 3), ("mean(x)", 1)])
def test_maps_that_are_not_a_list_of_entries_are_evaluated_whole(map_, p):
    net = network(4, 0, 32, 1, map=map_, internal={"lb": 0, "ub": 32, "eta": 1}, samples=20, error="linear")
    from pipelines.interconnection.sampling import Sampler

    sampler = Sampler(net)
    for j in range(p):
        evaluate, alone = sampler.column(j)
        assert not alone
        xt = np.full((4, 3), 7.0)
        np.testing.assert_array_equal(evaluate(xt), net.interconnection_map(xt.T)[:, j])


def test_an_output_evaluated_alone_is_checked_like_the_whole_map():
    from pipelines.errors import BlackBoxError
    from pipelines.interconnection.sampling import Sampler

    net = network(2, 0, 32, 1, map="[x[0] / 2, 2 * sqrt(x[1])]", internal={"lb": 0, "ub": 32, "eta": 1},
                  samples=50, error="direct", lipschitz=2.0)
    evaluate, alone = Sampler(net).column(1)
    assert alone
    np.testing.assert_array_equal(evaluate(np.array([[3.0, 3.0], [4.0, 16.0]])), [4.0, 8.0])
    with pytest.raises(SpecError, match=r"w1 = 34\.0 at x = \[3\.0, 289\.0\] lies outside its box"):
        evaluate(np.array([[3.0, 3.0], [4.0, 289.0]]))
    with pytest.raises(BlackBoxError, match=r"output w1.*not finite"):
        evaluate(np.array([[3.0], [-1.0]]))


@pytest.mark.parametrize("case", ["consensus", "tanks_direct"])
def test_contains_agrees_with_allowed_cells(case, request):
    """``contains`` compares ranges directly where every node reads states only (the tanks), and reads the masks of
    the MDec tree otherwise (consensus): the same answer as ``allowed_cells``, off-grid ``ŵ`` never contained."""
    net, ia = request.getfixturevalue(case)
    assert any(not i.startswith("x") for n in ia.nodes for i in n.inputs) == (case == "consensus")
    rng = np.random.default_rng(8)
    x_idx = np.column_stack([rng.integers(0, k, 400) for k in net.composed_state_grid().shape])
    masks = ia.allowed_cells(x_idx)
    sizes = [m.shape[1] for m in masks]
    # an allowed cell of each ŵ_j (its highest), then in about half of the rows one ŵ_j anywhere, off the grid too
    w_idx = np.column_stack([m.shape[1] - 1 - np.argmax(m[:, ::-1], axis=1) for m in masks])
    moved = np.flatnonzero(rng.random(400) < 0.5)
    cols = rng.integers(0, len(sizes), moved.size)
    w_idx[moved, cols] = [rng.integers(-1, sizes[c] + 1) for c in cols]
    expect = np.ones(400, dtype=bool)
    for j, m in enumerate(masks):
        w = w_idx[:, j]
        expect &= (w >= 0) & (w < sizes[j]) & m[np.arange(400), np.clip(w, 0, sizes[j] - 1)]
    assert 0 < expect.sum() < 400
    np.testing.assert_array_equal(ia.contains(x_idx, w_idx), expect)
