"""Soundness of subsystem abstractions (Algorithm 1): random concrete transitions against the relation."""

import numpy as np
import pytest

from pipelines.audit import audit_subsystem
from pipelines.network import build_network
from pipelines.spec import load_spec
from pipelines.subsystem import SubsystemRelation, abstract_cells, assemble, chunk_ranges

from .conftest import EXAMPLES


def _relation(sub, method, objective="paper", chunk_cells=None):
    L_x, L_w = float(sub.spec.lipschitz.x), float(sub.spec.lipschitz.w)
    res = [abstract_cells(sub, a, b, L_x, L_w, method, objective) for a, b in chunk_ranges(sub, chunk_cells)]
    return assemble(res, sub.state_grid.size, method, L_x, L_w), res


def _distinct(name):
    net = build_network(load_spec(EXAMPLES / f"{name}.yaml"), None)
    return [g[0] for g in net.unique_subsystems().values()]


CASES = [(name, i) for name, k in (("tanks", 2), ("consensus", 1), ("scalability", 1)) for i in range(k)]


@pytest.mark.parametrize("method,objective", [("lipschitz", "paper"), ("scp", "paper"), ("scp", "radius"), ("hull", "paper")])
@pytest.mark.parametrize("case,which", CASES)
def test_every_concrete_transition_is_in_the_abstraction(case, which, method, objective):
    sub = _distinct(case)[which]
    rel, _ = _relation(sub, method, objective)
    result = audit_subsystem(sub, rel, 200_000, np.random.default_rng(7))
    assert result.transitions_checked > 50_000
    assert result.violations == 0, result.first_violation


def test_the_audit_catches_a_relation_one_cell_too_small():
    """Negative control: shrinking every successor range by one cell must be detected."""
    sub = _distinct("consensus")[0]
    rel, _ = _relation(sub, "hull")
    live = ~rel.blocking
    hi = rel.hi.copy()
    hi[live] = np.maximum(rel.lo[live], hi[live] - 1)
    broken = SubsystemRelation(rel.method, rel.lo, hi, rel.blocking, rel.L_x, rel.L_w)
    result = audit_subsystem(sub, broken, 100_000, np.random.default_rng(1))
    assert result.violations > 0


def test_chunking_does_not_change_the_relation():
    sub = _distinct("tanks")[1]
    whole, _ = _relation(sub, "scp", chunk_cells=10_000)
    parts, _ = _relation(sub, "scp", chunk_cells=3)
    for a in ("lo", "hi", "blocking"):
        np.testing.assert_array_equal(getattr(whole, a), getattr(parts, a))


def test_growth_bounds_are_ordered_as_the_method_says():
    """hull <= scp (radius objective) <= scp (paper objective) <= lipschitz, in mean successors."""
    sub = _distinct("consensus")[0]
    _, res = _relation(sub, "scp")
    tot = {}
    for r in res:
        for k, (s, c) in r.successors.items():
            tot.setdefault(k, [0, 0])
            tot[k][0] += s
            tot[k][1] += c
    mean = {k: s / c for k, (s, c) in tot.items()}
    assert mean["hull"] <= mean["scp_radius"] <= mean["scp"] <= mean["lipschitz"]
    assert mean["scp"] < mean["lipschitz"]  # the SCP buys something on this case


def test_blocking_means_the_box_leaves_the_state_set():
    """A tank at level 1 with no inflow drains below 1: that input must be blocking there."""
    sub = _distinct("tanks")[1]  # input set {0}
    rel, _ = _relation(sub, "scp")
    w0 = 0  # internal cell of w = 0 (no inflow)
    assert rel.blocking[0, 0, w0]
    assert not rel.blocking[20, 0, 10]


def test_a_subsystem_without_internal_inputs():
    """reads: [] gives a relation with one (empty) internal cell, sound like the others."""
    from pipelines.spec import parse_spec

    spec = parse_spec({
        "subsystems": [{"name": "leaky", "state": {"lb": 0, "ub": 10, "eta": 0.5}, "input": {"lb": 0, "ub": 1, "eta": 0.5},
                        "dynamics": "0.9 * x[0] + u[0]", "lipschitz": {"x": 0.9}, "samples": 20}],
        "interconnection": {"map": "[x[0]]", "internal": {"lb": 0, "ub": 10, "eta": 1}, "error": "linear"},
        "specification": {"kind": "safe", "safe": {"boxes": [{"lb": 0, "ub": 10}]}},
    })
    sub = build_network(spec, None).subsystems[0]
    assert sub.internal_grid is None and sub.n_w_cells == 1
    for method in ("lipschitz", "scp", "hull"):
        rel, _ = _relation(sub, method)
        assert rel.blocking.shape == (21, 3, 1)
        assert audit_subsystem(sub, rel, 50_000, np.random.default_rng(0)).violations == 0
