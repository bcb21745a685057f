"""The exact-image-box reference of a linear single system (bench/reference.py): the tightest interval abstraction.

On small affine maps with anisotropic matrices (a shear, a rotation), each growth bound's relation contains the
reference's (every reference box inside compabs's box, compabs blocking wherever the reference does), so compabs's
winning domain lies in the reference's; every concrete successor of random points (a share on cell boundaries)
lies in the reference's successor box; a map that is not affine, and a network, are refused.
"""

from __future__ import annotations

import numpy as np
import pytest

from bench.reference import NotAffine, exact_reference, identify_affine, reference_relation, single_system
from pipelines.network import build_network
from pipelines.spec.model import parse_spec
from pipelines.spec.regions import never_winning, spec_regions
from pipelines.synthesis import explicit

#: x+ = A x + B u: a shear from the last coordinate into the first two, a rotation of the first two by 0.5 rad,
#: scaled by 0.95.
A = np.array([[0.95 * np.cos(0.5), -0.95 * np.sin(0.5), 0.6],
              [0.95 * np.sin(0.5), 0.95 * np.cos(0.5), -0.3],
              [0.0, 0.0, 0.9]])
B = np.array([[0.25, 0.0], [0.0, 0.25], [0.1, -0.1]])


def _row(i: int) -> str:
    terms = [f"{float(A[i, j])!r} * x[{j}]" for j in range(3) if A[i, j]] + [f"{float(B[i, k])!r} * u[{k}]" for k in range(2)
                                                                     if B[i, k]]
    return " + ".join(terms)


def spec_of(growth_bound: str = "hull", lipschitz: object = None, dynamics: str | None = None,
            samples: int = 27) -> dict:
    """A 3-D affine system on 11 x 11 x 5 cells with 9 inputs, reaching a box around the origin."""
    entries = (np.abs(A) * 1.001 + 1e-9).round(9).tolist()
    return {
        "name": "affine",
        "subsystems": [{
            "name": "plant",
            "state": {"lb": [-1.1, -1.1, -0.5], "ub": [1.1, 1.1, 0.5], "eta": [0.2, 0.2, 0.2]},
            "input": {"lb": [-1, -1], "ub": [1, 1], "eta": 1},
            "dynamics": dynamics or "[" + ", ".join(_row(i) for i in range(3)) + "]",
            "lipschitz": {"x": entries if lipschitz is None else lipschitz},
            "samples": samples,
            "growth_bound": growth_bound,
        }],
        "specification": {"kind": "reach_avoid",
                          "target": {"boxes": [{"lb": [-0.3, -0.3, -0.5], "ub": [0.3, 0.3, 0.5]}]},
                          "avoid": {"boxes": [{"lb": [0.45, -1.1, -0.5], "ub": [0.7, 0.2, 0.5]}]}},
        "options": {"audit_transitions": 0, "closed_loop_runs": 0},
    }


def reference_of(data: dict):
    spec = parse_spec(data)
    network = build_network(spec, None)
    sub = single_system(network)
    affine = identify_affine(sub)
    dead = never_winning(spec, network, spec_regions(spec, network))
    return spec, network, sub, affine, reference_relation(sub, affine, dead)


def test_the_affine_map_is_read_off_the_black_box():
    _, _, _, affine, _ = reference_of(spec_of())
    assert np.allclose(affine.A, A, rtol=0, atol=1e-12) and np.allclose(affine.B, B, rtol=0, atol=1e-12)
    assert np.allclose(affine.c, 0, atol=1e-12) and affine.residual < 1e-12


@pytest.mark.parametrize("growth_bound,lipschitz", [("hull", None), ("lipschitz", None), ("scp", None),
                                                    ("hull", 1.9)])
def test_every_growth_bound_contains_the_reference_and_wins_no_more(growth_bound, lipschitz):
    """With the entries ``|A_ij|`` (a hair above), and with one constant at least the map's infinity norm (1.889)."""
    from workers.job import run_abstraction

    data = spec_of(growth_bound, lipschitz)
    spec, network, _, _, ref = reference_of(data)
    (ours,) = run_abstraction(spec, audit=False).relations.values()
    assert ours.lo.shape == ref.lo.shape and ours.blocking.shape == ref.blocking.shape
    live = ~ref.blocking
    assert ours.blocking[ref.blocking].all()  # a box leaving X is in every box that contains it
    both = live & ~ours.blocking
    assert (ours.lo[both] <= ref.lo[both]).all() and (ours.hi[both] >= ref.hi[both]).all()
    assert explicit.transitions(ref) > 0 and not ref.blocking.all()

    grid = network.composed_state_grid()
    domain = {}
    for name, rel in (("ours", ours), ("reference", ref)):
        (result,) = explicit.solve(explicit.ExplicitGame.from_relation(rel, grid.shape), spec.specification,
                                   grid).values()
        domain[name] = result.domain
    assert domain["reference"].any() and not (domain["ours"] & ~domain["reference"]).any()
    if growth_bound == "hull" and lipschitz is None:  # exact entries: the hull is the image box (docs/method.md §2)
        assert domain["ours"].sum() == domain["reference"].sum()


def test_every_concrete_successor_lies_in_the_reference_box():
    _, _, sub, _, ref = reference_of(spec_of())
    xg, ug = sub.state_grid, sub.input_grid
    rng = np.random.default_rng(46)
    count = 200_000
    x = rng.uniform(xg.lb, xg.ub, (count, 3))
    # a third of the points on a cell boundary along one coordinate: they belong to both cells
    on = rng.random(count) < 1 / 3
    axis = rng.integers(0, 3, count)
    k = rng.integers(0, np.asarray(xg.shape)[axis])
    eta = np.asarray(xg.eta_array)
    edge = np.asarray(xg.origin)[axis] + (np.asarray(xg.k_lo)[axis] + k + 0.5) * eta[axis]
    x[on, axis[on]] = np.clip(edge[on], np.asarray(xg.lb)[axis[on]], np.asarray(xg.ub)[axis[on]])
    u = rng.integers(0, ug.size, count)
    f = sub.dynamics(x, ug.all_points()[u], np.zeros((count, 0)))
    checked = 0
    for tie in ("upper", "lower"):
        idx, inside = xg.cell_of(x, tie)
        cells = xg.ravel(np.clip(idx, 0, np.asarray(xg.shape) - 1))
        lo, hi, blocking = ref.lo[cells, u, 0], ref.hi[cells, u, 0], ref.blocking[cells, u, 0]
        live = inside & ~blocking
        assert live.sum() > count // 4
        assert np.all((f[live] >= np.asarray(xg.lb)) & (f[live] <= np.asarray(xg.ub)))
        for succ_tie in ("upper", "lower"):
            succ, on_grid = xg.cell_of(f[live], succ_tie)
            assert on_grid.all()
            assert np.all((succ >= lo[live]) & (succ <= hi[live]))
        checked += int(live.sum())
    assert checked > count // 2


def test_a_map_that_is_not_affine_is_refused_naming_the_point():
    rows = [_row(0) + " + 0.01 * x[2] * x[2]", _row(1), _row(2)]
    with pytest.raises(NotAffine, match=r"subsystem 'plant' is not affine: at x = .* component 0 of f .*relative "
                                        r"deviation .*linear \(affine\) dynamics"):
        reference_of(spec_of(dynamics="[" + ", ".join(rows) + "]"))


def test_a_network_is_refused():
    data = spec_of()
    sub = data["subsystems"][0]
    sub["dynamics"] = "[" + ", ".join([_row(0) + " + 0.1 * w[0]", _row(1), _row(2)]) + "]"
    sub["reads"] = [0]
    sub["lipschitz"]["w"] = [[0.1], [0], [0]]
    data["interconnection"] = {"map": "[x[0]]", "internal": {"lb": -1.1, "ub": 1.1, "eta": 0.2}, "error": "linear"}
    with pytest.raises(NotAffine, match="single system without internal inputs"):
        exact_reference(parse_spec(data), None)


def test_a_single_constant_below_the_maps_norm_is_refused_by_the_data():
    """1.6 bounds every entry's slope (at most 0.95 along an axis) but not the norm, 1.889: diagonal neighbours of
    the sample sub-grid, which move every coordinate at once, show a slope above it."""
    from pipelines.errors import LipschitzError
    from workers.job import run_abstraction

    data = spec_of("hull", 1.6)
    data["subsystems"][0]["lipschitz"]["on_violation"] = "fail"
    with pytest.raises(LipschitzError, match=r"L_x = 1.6 is contradicted by the data: slope 1\.[789]"):
        run_abstraction(parse_spec(data), audit=False)


@pytest.mark.parametrize("seed", range(6))
def test_the_diagonal_pass_finds_the_largest_difference_of_diagonal_neighbours(seed):
    """Against every pair of samples whose indices differ by exactly one along every moving axis and not at all
    along the others."""
    import itertools

    from pipelines.abstraction.kernels import diagonal_pass

    rng = np.random.default_rng(seed)
    counts = tuple(int(c) for c in rng.integers(1, 4, size=int(rng.integers(2, 5))))
    moving = [a for a in range(len(counts)) if counts[a] >= 2][: int(rng.integers(2, 4))]
    if len(moving) < 2:
        counts, moving = (2, 3) + counts[2:], [0, 1]
    B, n = 5, 3
    V = rng.normal(size=(int(np.prod(counts)), B, n))
    expected = np.zeros(B)
    points = list(itertools.product(*(range(c) for c in counts)))
    for p, q in itertools.product(points, points):
        delta = np.subtract(q, p)
        if all(abs(delta[a]) == 1 for a in moving) and all(delta[a] == 0 for a in range(len(counts))
                                                           if a not in moving):
            i, j = np.ravel_multi_index(p, counts), np.ravel_multi_index(q, counts)
            expected = np.maximum(expected, np.abs(V[j] - V[i]).max(axis=1))
    got = diagonal_pass(V, np.asarray(counts, dtype=np.int64), np.asarray(moving, dtype=np.int64))
    np.testing.assert_array_equal(got, expected)
