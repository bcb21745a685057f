"""Interconnection outputs declared ``max`` / ``min`` of what they read (pipelines/interconnection/reduction.py).

The scalability example's ``w = max(x)`` admits every cell of ``w`` at every state from N ~ 32 on under
``certify`` (no affine fit is close); declared ``error: max`` its abstraction is exact, sound and admits at most
3 of the 33 cells at any N. These tests draw concrete states against the node tables and the BDD, check the
declaration against the data, the variable order that keeps the BDD small, and a whole job.
"""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from pipelines.errors import CertificationError, SpecError
from pipelines.interconnection import abstract_interconnection
from pipelines.interconnection.reduction import reduction_nodes
from pipelines.network import Network, build_network
from pipelines.spec.model import parse_spec
from pipelines.symbolic.files import dump, load_all
from pipelines.symbolic.relations import interconnection_parts
from pipelines.symbolic.symbolic_model import SymbolicModel
from tests.test_interconnection import both_cells

from .conftest import EXAMPLES


def spec_text(N: int, op: str = "max", map_text: str | None = None, **changes) -> str:
    data = yaml.safe_load((EXAMPLES / "scalability.yaml").read_text())
    data["parameters"]["N"] = N
    data["interconnection"]["error"] = op
    data["interconnection"]["map"] = map_text or f"{op}(x)"
    for key, value in changes.items():
        data[key] = value
    return yaml.safe_dump(data)


def network(N: int, op: str = "max", map_text: str | None = None, **changes) -> Network:
    return build_network(parse_spec(spec_text(N, op, map_text, **changes)), allowed_modules=None)


def draws(net: Network, count: int, seed: int) -> np.ndarray:
    """Uniform states, a fifth of the coordinates snapped to cell boundaries and box edges, a third of the states
    with all coordinates close together (the reduction then sits near every coordinate)."""
    rng = np.random.default_rng(seed)
    n = net.composed_state_grid().dim
    x = rng.uniform(0, 32, (count, n))
    snap = rng.random(x.shape) < 0.2
    x = np.where(snap, np.clip(np.round(x) + rng.choice([-0.5, 0.0, 0.5], x.shape), 0, 32), x)
    near = rng.random(count) < 0.3
    x[near] = np.clip(rng.uniform(0, 32, (int(near.sum()), 1)) + rng.uniform(-1, 1, (int(near.sum()), n)), 0, 32)
    return x


@pytest.mark.parametrize("op", ["max", "min"])
@pytest.mark.parametrize("N", [1, 2, 3, 5, 8, 64, 300])
def test_reduction_abstraction_is_sound_exact_and_informative(op, N):
    """For every drawn ``x`` (either cell on a boundary) the cell(s) of ``op(x)`` are admitted, the admitted
    cells are exactly those meeting the clipped cell of ``op`` of the cell indices, and there are at most 3."""
    net = network(N, op)
    ia = abstract_interconnection(net, np.random.default_rng(N))
    assert ia.output_modes == (op,) and float(ia.error_bounds[0]) == 0.0
    assert len(ia.nodes) == max(N - 1, 1) and ia.nodes[-1].output == "w0"
    grid, wg = net.composed_state_grid(), net.internal_grids[0]
    x = draws(net, 3000, 7 * N)
    w = net.interconnection_map(x)
    x_up, x_low = both_cells(grid, x)
    w_up, w_low = both_cells(wg, w[:, :1])
    for xi in (x_up, x_low):
        for wi in (w_up, w_low):
            assert ia.contains(xi, wi).all()
        K = getattr(np, op)(xi, axis=1)
        lo, hi = grid.clipped_cells(np.stack([K] * grid.dim, axis=1))
        every = np.arange(wg.size)
        admitted = np.stack([ia.contains(xi, np.full((len(xi), 1), c)) for c in every], axis=1)
        c_lo, c_hi = wg.clipped_cells(every[:, None])
        meets = (c_lo[None, :, 0] <= hi[:, :1]) & (c_hi[None, :, 0] >= lo[:, :1])
        assert (admitted == meets).all()
        assert admitted.sum(axis=1).max() <= 3


def test_negative_control_one_cell_short_is_caught():
    """The check above can fail: a final node one cell short at the top misses the cell of max(x)."""
    net = network(16)
    ia = abstract_interconnection(net, np.random.default_rng(0))
    final = ia.nodes[-1]
    short = final.hi - 1
    import dataclasses

    broken = dataclasses.replace(ia, nodes=(*ia.nodes[:-1], dataclasses.replace(final, hi=short)))
    grid = net.composed_state_grid()
    x = draws(net, 2000, 3)
    x_up, _ = both_cells(grid, x)
    w_up, _ = both_cells(net.internal_grids[0], net.interconnection_map(x)[:, :1])
    assert ia.contains(x_up, w_up).all()
    assert not broken.contains(x_up, w_up).all()


@pytest.mark.parametrize("order", ["shared_top", "interleaved"])
def test_bdd_equals_the_node_tables_and_zs_sit_below_their_coordinates(tmp_path, order):
    """``∃z. ∧ R_node`` as a BDD admits exactly what the node tables admit, on random cells; every ``z`` lies
    below the state bits under it (what keeps the conjunction a running maximum), and the order survives a
    header round trip."""
    N = 9
    net = network(N)
    ia = abstract_interconnection(net, np.random.default_rng(1))
    m = SymbolicModel.from_network(net, ia, order=order)
    level = {v: k for k, v in enumerate(m.variables)}
    under: dict[str, set[int]] = {}
    for node in ia.nodes:
        if node.output.startswith("z"):
            under[node.output] = set().union(*({int(v[1:])} if v.startswith("x") else under[v] for v in node.inputs))
            top_z = min(level[b] for b in m.bits[node.output])
            assert all(level[b] < top_z for i in under[node.output] for b in m.bits[f"x{i}"]), node.output
    M = interconnection_parts(m, ia.nodes)[0]
    rng = np.random.default_rng(2)
    cells = rng.integers(0, 33, (300, N))
    for xi in cells:
        point = m.state_assignment(list(xi))
        sub = m.bdd.let(point, M)
        for c in range(33):
            bits = m.bits["w0"]
            wpt = {b: bool((c >> (len(bits) - 1 - k)) & 1) for k, b in enumerate(bits)}
            got = m.bdd.let(wpt, sub) == m.bdd.true
            assert got == bool(ia.contains(xi[None, :], np.array([[c]]))[0])
    dump(m, tmp_path / "M", M)
    m2, (M2,), _ = load_all(tmp_path / "M")
    assert m2.variables == m.variables and m2.z_below == m.z_below and M2.dag_size == M.dag_size


@pytest.mark.slow
def test_bdd_of_a_thousand_coordinates_stays_linear():
    """N = 1024: 1,023 nodes; M̂ is a scan over the states (33 values of w, a running maximum), not a product."""
    net = network(1024)
    ia = abstract_interconnection(net, np.random.default_rng(3))
    m = SymbolicModel.from_network(net, ia, order="shared_top")
    M = interconnection_parts(m, ia.nodes)[0]
    assert M.dag_size < 400 * 1024  # ~ 33 x 2 x 6 bits per coordinate
    x = draws(net, 200, 5)
    x_up, _ = both_cells(net.composed_state_grid(), x)
    w_up, _ = both_cells(net.internal_grids[0], net.interconnection_map(x)[:, :1])
    assert ia.contains(x_up, w_up).all()


@pytest.mark.parametrize("map_text,match", [
    ("[0.99 * max(x)]", "is not the max of the coordinates it reads"),
    ("mean(x)", "is not the max of the coordinates it reads"),
])
def test_a_declaration_the_data_contradict_is_refused(map_text, match):
    net = network(6, "max", map_text)
    with pytest.raises(CertificationError, match=match):
        abstract_interconnection(net, np.random.default_rng(0))


def test_coordinates_on_different_grids_are_refused():
    data = yaml.safe_load(spec_text(3))
    sub = data["subsystems"][0]
    data["subsystems"] = [{**sub, "replicate": 2}, {**sub, "name": "other", "replicate": None,
                                                    "state": {"lb": 0, "ub": 32, "eta": 2}}]
    data["subsystems"][1].pop("replicate")
    net = build_network(parse_spec(yaml.safe_dump(data)), allowed_modules=None)
    with pytest.raises(SpecError, match="whose grids differ"):
        abstract_interconnection(net, np.random.default_rng(0))


def test_tree_is_in_post_order_with_in_degree_two():
    net = network(7)
    grid = net.composed_state_grid()
    from pipelines.interconnection.grids import axis_grid

    nodes, z = reduction_nodes("max", 0, range(7), [axis_grid(grid, i) for i in range(7)], net.internal_grids[0], 4)
    assert [n.output for n in nodes] == ["z4", "z5", "z6", "z7", "z8", "w0"]
    seen: set[str] = set()
    for node in nodes:
        assert len(node.inputs) <= 2
        assert all(v in seen for v in node.inputs if v.startswith("z"))
        seen.add(node.output)
    assert set(z) == {"z4", "z5", "z6", "z7", "z8"}


@pytest.mark.slow
def test_scalability_job_with_a_declared_max_runs_and_audits_clean(tmp_path):
    """A whole job (embedded cluster, audit, synthesis) on the scalability example at N = 8 with error: max."""
    from pipelines.spec.model import parse_spec as parse
    from workers.executors import Execution
    from workers.job import run_job

    spec = parse(spec_text(8))
    report = run_job(spec, tmp_path / "job", execution=Execution(workers=2))
    parts = report["audit"]["parts"]
    assert parts["interconnection"]["violations"] == 0 and parts["interconnection"]["transitions_checked"] > 0
    assert parts["composition"]["violations"] == 0 and parts["composition"]["transitions_checked"] > 0
    assert report["interconnection"]["output_modes"] == ["max"]
    # The same job under the paper's certify: M̂ admits every w cell (no affine fit of max is close), so its
    # domain cannot be larger than the exact reduction's (the example's placeholder safety spec makes them equal).
    paper = run_job(parse(spec_text(8, "certify", "max(x)")), tmp_path / "paper", execution=Execution(workers=2))
    assert paper["interconnection"]["output_modes"] == ["certify"]
    assert 0 < paper["domain_states"] <= report["domain_states"]


def test_two_outputs_get_their_own_trees():
    """Two internal variables, each the min of its own coordinates (``reads: i % 2``): distinct z names, each
    tree sound on drawn states, and each ``M̂_j`` as a BDD admits what its tables admit."""
    data = yaml.safe_load(spec_text(7, "min", "[min(x[0], x[2], x[4], x[6]), min(x[1], x[3], x[5])]"))
    data["subsystems"][0]["reads"] = ["i % 2"]
    net = build_network(parse_spec(yaml.safe_dump(data)), allowed_modules=None)
    ia = abstract_interconnection(net, np.random.default_rng(4))
    assert ia.output_modes == ("min", "min") and ia.supports == ((0, 2, 4, 6), (1, 3, 5))
    names = [n.output for n in ia.nodes]
    assert len(names) == len(set(names)) == 5
    x = draws(net, 2000, 11)
    w = net.interconnection_map(x)
    x_up, x_low = both_cells(net.composed_state_grid(), x)
    for xi in (x_up, x_low):
        wi = np.stack([both_cells(g, w[:, j : j + 1])[0][:, 0] for j, g in enumerate(net.internal_grids)], axis=1)
        assert ia.contains(xi, wi).all()
    m = SymbolicModel.from_network(net, ia, order="shared_top")
    parts = interconnection_parts(m, ia.nodes)
    rng = np.random.default_rng(5)
    for xi in rng.integers(0, 33, (100, 7)):
        point = m.state_assignment(list(xi))
        for j, part in parts.items():
            sub = m.bdd.let(point, part)
            bits = m.bits[f"w{j}"]
            for c in (0, int(xi[j::2].min()), 32):
                wpt = {b: bool((c >> (len(bits) - 1 - k)) & 1) for k, b in enumerate(bits)}
                other = np.zeros((1, 2), dtype=np.int64)
                other[0, j] = c
                other[0, 1 - j] = int(xi[1 - j :: 2].min())  # a cell the other output admits
                assert (m.bdd.let(wpt, sub) == m.bdd.true) == bool(ia.contains(xi[None, :], other)[0])


@pytest.mark.parametrize("error,map_text,fragment", [
    ("max", "mean(x)", "is not the max of the coordinates it reads"),
    ("maximum", "max(x)", "interconnection.error"),
])
def test_the_cli_refuses_a_bad_declaration_in_one_line(tmp_path, capsys, error, map_text, fragment):
    """A declaration the samples contradict, and an unknown error mode: exit 2, one ``error:`` line."""
    from tests.test_cli_errors import assert_one_error, run_cli

    spec = tmp_path / "spec.yaml"
    data = yaml.safe_load((EXAMPLES / "scalability.yaml").read_text())
    data["interconnection"].update(error=error, map=map_text)
    spec.write_text(yaml.safe_dump(data))
    code, _, err = run_cli(capsys, "run", spec, "--out", tmp_path / "out", "--quiet")
    assert_one_error(code, err, fragment)
    assert fragment in err
