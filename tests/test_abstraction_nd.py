"""Soundness of the per-cell stage for 2-D and 3-D subsystems (hypothesis), and its sampled statistics.

Each example draws a random map ``x' = A x + B u + C w + b`` (optionally with ``sin``/``tanh`` terms) whose
Lipschitz constants (infinity norm) are known in closed form, random boxes and spacings with a few cells per
dimension, with and without internal inputs, abstracts the whole grid with one growth bound, and audits random
concrete transitions (``audit_subsystem``: x drawn in cells, a share on cell boundaries and box edges, u on the
input grid, w in internal cells): the concrete successor's cell must lie in ``[lo, hi]`` of its triple and, for a
non-blocking triple, inside the state box.
"""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipelines.abstraction import cost
from pipelines.abstraction.block import statistics_sample
from pipelines.abstraction.cells import CellTask, abstract_cells
from pipelines.abstraction.cost import STATISTICS_SAMPLE, statistics_fraction, triple_cost
from pipelines.abstraction.relation import assemble, chunk_ranges
from pipelines.network import build_network
from pipelines.spec.model import parse_spec
from pipelines.verification.audit import audit_subsystem

from .strategies import systems

SETTINGS = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow])
GROWTH = [("lipschitz", "paper"), ("scp", "paper"), ("scp", "radius"), ("hull", "paper")]


def _subsystem(spec, internal):
    n = len(spec["state"]["lb"])
    p = len(spec.get("reads", []))
    job = parse_spec({
        "subsystems": [{**spec, "replicate": max(p, 1)}],
        "interconnection": {"map": "[" + ", ".join(f"x[{j}]" for j in range(max(p, 1))) + "]",
                            "internal": internal, "error": "linear"},
        "specification": {"kind": "safe", "safe": {"boxes": [{"lb": spec["state"]["lb"] * max(p, 1),
                                                               "ub": spec["state"]["ub"] * max(p, 1)}]}},
    })
    sub = build_network(job, None).subsystems[0]
    assert sub.n == n and sub.p == p
    return sub


def _check(sysd, method, objective, seed):
    sub = _subsystem(*sysd)
    L_x, L_w = float(sub.spec.lipschitz.x), float(sub.spec.lipschitz.w)
    res = [abstract_cells(sub, a, b, L_x, L_w, method, objective) for a, b in chunk_ranges(sub, 3)]
    rel = assemble(res, sub.state_grid.size, method, L_x, L_w)
    result = audit_subsystem(sub, rel, 4_000, np.random.default_rng(seed))
    assert result.violations == 0, result.first_violation
    return sub, rel


@pytest.mark.parametrize("method,objective", GROWTH)
@settings(max_examples=25, **SETTINGS)
@given(sysd=systems(2), seed=st.integers(0, 2**31 - 1))
def test_2d_relations_are_sound(sysd, method, objective, seed):
    _check(sysd, method, objective, seed)


@pytest.mark.parametrize("method,objective", GROWTH)
@settings(max_examples=12, **SETTINGS)
@given(sysd=systems(3), seed=st.integers(0, 2**31 - 1))
def test_3d_relations_are_sound(sysd, method, objective, seed):
    _check(sysd, method, objective, seed)


def _contractive(samples, p=0):
    """A contraction whose true constant (0.31) is well below the given one (0.9): with 8 sub-grid points per axis
    the data-driven SCP beats the Lipschitz radius (below about 5 per axis ``rho`` alone exceeds it)."""
    spec = {"name": "c", "state": {"lb": [-1, -1], "ub": [1, 1], "eta": [0.25, 0.25]},
            "input": {"lb": [-0.5], "ub": [0.5], "eta": [0.5]},
            "dynamics": "[0.2 * x[0] - 0.1 * x[1] + 0.1 * u[0]" + (" + 0.1 * w[0]" if p else "")
                        + ", 0.1 * x[0] + 0.15 * x[1] + 0.02 * sin(3 * x[0])]",
            "lipschitz": {"x": 0.9, "w": 0.1 if p else 0.0}, "samples": samples}
    if p:
        spec["reads"] = [0]
    return _subsystem(spec, [{"lb": -1, "ub": 1, "eta": 0.5}])


def _totals(results):
    tot = {}
    for r in results:
        for k, (s, c) in r.successors.items():
            t = tot.setdefault(k, [0, 0])
            t[0] += s
            t[1] += c
    return {k: tuple(v) for k, v in tot.items()}


def test_the_scp_beats_the_lipschitz_bound_and_is_sound():
    """With enough samples per axis the LPs run (the skip test does not settle every row) and tighten boxes."""
    sub = _contractive(64)
    L_x = float(sub.spec.lipschitz.x)
    for objective in ("paper", "radius"):
        res = [abstract_cells(sub, a, b, L_x, 0.0, "scp", objective, full_statistics=True)
               for a, b in chunk_ranges(sub, None)]
        tot = _totals(res)
        mean = {k: s / c for k, (s, c) in tot.items()}
        assert mean["hull"] <= mean["scp_radius"] <= mean["scp"] < mean["lipschitz"]
        rel = assemble(res, sub.state_grid.size, "scp", L_x, 0.0)
        assert audit_subsystem(sub, rel, 20_000, np.random.default_rng(2)).violations == 0


@pytest.mark.parametrize("method,objective", GROWTH)
def test_sampled_statistics_are_fixed_and_cheaper_than_the_chosen_bound(method, objective):
    """For dim(x) > 1 the objectives that do not build the relation, and the Lipschitz bound when the hull builds it
    (no centres then beyond the sample's), are counted on a fixed sample (at most STATISTICS_SAMPLE, the same
    whatever the chunking), the others on every triple; True counts every one."""
    sub = _contractive(64, p=1)
    L_x, L_w = float(sub.spec.lipschitz.x), float(sub.spec.lipschitz.w)
    chosen = "scp_radius" if (method == "scp" and objective == "radius") else method
    full = _totals([abstract_cells(sub, a, b, L_x, L_w, method, objective, full_statistics=True)
                    for a, b in chunk_ranges(sub, None)])
    by_default = _totals([abstract_cells(sub, a, b, L_x, L_w, method, objective) for a, b in chunk_ranges(sub, None)])
    chunked = _totals([abstract_cells(sub, a, b, L_x, L_w, method, objective) for a, b in chunk_ranges(sub, 5)])
    assert by_default == chunked
    fraction = statistics_fraction(sub, method, objective)
    assert 0 < fraction <= STATISTICS_SAMPLE
    picked = statistics_sample(0, sub.triples, fraction)
    for name in ("lipschitz", "hull", "scp", "scp_radius"):
        if name == "hull" or name == chosen or (name == "lipschitz" and method != "hull"):
            assert by_default[name] == full[name], name
        else:
            assert by_default[name][1] <= picked.size < sub.triples, name
    # the sampled SCP work is at most STATISTICS_BUDGET of the chosen bound's (the cost model's estimate)
    base, pairs, lp, _ = cost._work(sub)
    chosen_work = base + pairs + lp if method == "scp" else base
    sampled = triple_cost(sub, method, objective)
    assert chosen_work < sampled <= (1 + cost.STATISTICS_BUDGET) * chosen_work
    assert sampled < triple_cost(sub, method, objective, full_statistics=True)


def test_triple_cost_grows_with_the_work():
    small, large = _contractive(9), _contractive(64)
    for method, objective in GROWTH:
        assert triple_cost(small, method, objective) < triple_cost(large, method, objective)
        assert triple_cost(large, method, objective) >= 65  # at least the samples and the centre
    assert triple_cost(large, "hull", "paper") < triple_cost(large, "scp", "paper")
    task = CellTask(large, 0, 10, 0.9, 0.0, "scp", "paper")
    assert task.cost == pytest.approx(10 * large.input_grid.size * triple_cost(large, "scp", "paper"))


def test_the_audit_catches_a_2d_relation_one_cell_too_small():
    """Negative control for the audits above: shrinking each non-blocking range by one cell in one dimension."""
    from pipelines.abstraction.relation import SubsystemRelation

    sub = _contractive(64)
    res = [abstract_cells(sub, a, b, 0.9, 0.0, "scp", "radius") for a, b in chunk_ranges(sub, None)]
    rel = assemble(res, sub.state_grid.size, "scp", 0.9, 0.0)
    hi = rel.hi.copy()
    live = ~rel.blocking
    hi[live, 1] = np.maximum(rel.lo[live, 1], hi[live, 1] - 1)
    broken = SubsystemRelation(rel.method, rel.lo, hi, rel.blocking, rel.L_x, rel.L_w)
    assert audit_subsystem(sub, broken, 20_000, np.random.default_rng(1)).violations > 0
