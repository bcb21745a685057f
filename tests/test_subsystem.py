"""Soundness of subsystem abstractions (Algorithm 1): random concrete transitions against the relation."""

import hashlib
from dataclasses import replace

import numpy as np
import pytest

from pipelines.abstraction.block import STATISTICS_SAMPLE, statistics_sample
from pipelines.abstraction.cells import abstract_cells
from pipelines.abstraction.growth_bound import subgrid_counts
from pipelines.abstraction.relation import SubsystemRelation, assemble, chunk_ranges
from pipelines.network import build_network
from pipelines.spec.model import load_spec
from pipelines.verification.audit import audit_subsystem

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
    L_x, L_w = float(sub.spec.lipschitz.x), float(sub.spec.lipschitz.w)
    res = [abstract_cells(sub, a, b, L_x, L_w, "scp", "paper", full_statistics=True)
           for a, b in chunk_ranges(sub, None)]
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
    from pipelines.spec.model import parse_spec

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


# ----------------------------------------------------------------------------- against the implementation before
def _digest(rel) -> str:
    h = hashlib.sha256()
    for a in (rel.lo.astype(np.int32), rel.hi.astype(np.int32), rel.blocking.astype(bool)):
        h.update(str(a.shape).encode())
        h.update(np.ascontiguousarray(a).tobytes())
    return h.hexdigest()[:16]


#: Relations (digest of lo, hi, blocking) and successor statistics (sum, non-blocking triples) of every distinct
#: subsystem of the examples, computed by the implementation before the per-cell stage was rewritten (batch-first
#: samples, the SCP by enumerating all O(m^2) candidate slopes for both objectives). ``small`` has the consensus
#: agent. The rewrite must give the same bits: these are IEEE operations in the same order on the same values
#: (maxima and minima are exact in any order), and the SCP's theta is the same slope computed the same way.
BEFORE = {
    "consensus:agent[0]": {
        "digests": {"lipschitz": "51d54e76b3e19eac", "scp": "99c9431e4e866bbb", "scp_radius": "594dcf9fea45463c",
                    "hull": "831c13afce47224e"},
        "successors": {"lipschitz": (14951, 5269), "hull": (11341, 5445), "scp": (14535, 5445),
                       "scp_radius": (13839, 5445)},
    },
    "scalability:sys[0]": {
        "digests": {"lipschitz": "9f8e8be1deffcbe9", "scp": "bf2691569d2b8da9", "scp_radius": "2c987186745ba31f",
                    "hull": "8831e64616842b99"},
        "successors": {"lipschitz": (26815, 8646), "hull": (19537, 8679), "scp": (24238, 8646),
                       "scp_radius": (21983, 8679)},
    },
    "tanks:tank1": {
        "digests": {"lipschitz": "d4b2e8805de0e873", "scp": "d4b2e8805de0e873", "scp_radius": "d4b2e8805de0e873",
                    "hull": "4f188a810fe82ee4"},
        "successors": {"lipschitz": (558, 285), "hull": (552, 285), "scp": (558, 285), "scp_radius": (558, 285)},
    },
    "tanks:tank2": {
        "digests": {"lipschitz": "e9b97e2702675d76", "scp": "e9b97e2702675d76", "scp_radius": "e9b97e2702675d76",
                    "hull": "b4e6d24b7686abad"},
        "successors": {"lipschitz": (3499, 1750), "hull": (3468, 1752), "scp": (3499, 1750),
                       "scp_radius": (3499, 1750)},
    },
}


@pytest.mark.parametrize("key", sorted(BEFORE))
def test_relations_are_bit_identical_to_the_implementation_before(key):
    case, name = key.split(":")
    sub = next(s for s in _distinct(case) if s.name == name)
    L_x, L_w = float(sub.spec.lipschitz.x), float(sub.spec.lipschitz.w)
    for method, objective, chosen in (("lipschitz", "paper", "lipschitz"), ("scp", "paper", "scp"),
                                      ("scp", "radius", "scp_radius"), ("hull", "paper", "hull")):
        res = [abstract_cells(sub, a, b, L_x, L_w, method, objective, full_statistics=True)
               for a, b in chunk_ranges(sub, None)]
        rel = assemble(res, sub.state_grid.size, method, L_x, L_w)
        assert _digest(rel) == BEFORE[key]["digests"][chosen], (method, objective)
        tot = {}
        for r in res:
            for k, (a, c) in r.successors.items():
                t = tot.setdefault(k, [0, 0])
                t[0] += a
                t[1] += c
        assert {k: tuple(v) for k, v in tot.items()} == BEFORE[key]["successors"]


class _Recorder:
    """Wraps a black box and keeps the arrays of its first call (the samples of ``abstract_cells``)."""

    def __init__(self, box):
        self.box, self.args, self.out = box, None, None

    def __call__(self, *arrays, describe=None):
        out = self.box(*arrays, describe=describe)
        if self.args is None:
            self.args, self.out = arrays, out
        return out


@pytest.mark.parametrize("case", ["consensus", "tanks", "scalability"])
def test_the_samples_reach_the_black_box_row_major(case):
    """The internal-input samples are passed row-major and the successors come back row-major: a ufunc lays its
    output out like its inputs, and a transposed layout made the sample pass 3x slower (the values would be the
    same, so only this test sees it)."""
    for sub in _distinct(case):
        L_x, L_w = float(sub.spec.lipschitz.x), float(sub.spec.lipschitz.w)
        rec = _Recorder(sub.dynamics)
        abstract_cells(replace(sub, dynamics=rec), 0, 2, L_x, L_w, "lipschitz", "paper")
        assert rec.args[2].flags.c_contiguous and rec.out.flags.c_contiguous


@pytest.mark.parametrize("case,which", [("consensus", 0), ("scalability", 0), ("tanks", 0), ("tanks", 1),
                                        ("small", 0)])
def test_scp_relation_matches_the_reference_lp_on_real_cells(case, which, monkeypatch):
    """On a subset of the triples of each example: theta from the reference LP (HiGHS, every sample pair) on
    the pipeline's own samples, the box C +- min(radius, Lipschitz radius) snapped to cells, must give the
    relation's lo/hi/blocking exactly; the radii agree to 1e-9."""
    import pipelines.abstraction.cells as subsystem

    monkeypatch.setattr(subsystem, "BLOCK_POINTS", 1 << 40)  # the chunk's samples in one call, recorded below
    from pipelines.abstraction.growth_bound import (
        lipschitz_radius,
        pair_maxima_scalar,
        scp_parameters_scalar,
        scp_reference,
        scp_rho,
        subgrid_counts,
        widen,
    )

    sub = _distinct(case)[which]
    L_x, L_w = float(sub.spec.lipschitz.x), float(sub.spec.lipschitz.w)
    xg, ug, wg = sub.state_grid, sub.input_grid, sub.internal_grid
    a, b = chunk_ranges(sub, None)[0]
    counts = subgrid_counts(sub.spec.samples, sub.n + sub.p)
    Sx, Sw = counts[0], int(np.prod(counts[1:]))
    n_u, n_w = ug.size, wg.size
    B = (b - a) * n_u * n_w
    rng = np.random.default_rng(len(case) + which)
    triples = rng.choice(B, size=min(B, 12), replace=False)
    ci, ui, wi = np.unravel_index(triples, (b - a, n_u, n_w))
    x_lo, x_hi = xg.clipped_cells(xg.unravel(a + ci))
    w_lo, w_hi = wg.clipped_cells(wg.unravel(wi))
    rx, rw = (x_hi - x_lo) / 2, (w_hi - w_lo) / 2
    hx, hw = 2 * rx / counts[0], 2 * rw / np.asarray(counts[1:], dtype=float)
    rho = scp_rho(hx, hw, L_x, L_w)
    lip = lipschitz_radius(rx, rw, L_x, L_w)
    u = ug.points(ug.unravel(ui))
    C = sub.dynamics((x_lo + x_hi) / 2, u, (w_lo + w_hi) / 2)[:, 0]
    for objective in ("paper", "radius"):
        rec = _Recorder(sub.dynamics)
        res = abstract_cells(replace(sub, dynamics=rec), a, b, L_x, L_w, "scp", objective)
        X = np.broadcast_to(rec.args[0], (Sx, Sw, B, 1)).reshape(Sx, Sw, B)  # (Sx, 1, B, 1) state samples
        V = rec.out.reshape(Sx, Sw, B)
        for k, t in enumerate(triples):
            w = np.array([1.0 if objective == "paper" else rx[k, 0]])
            th1, th2 = scp_reference(X[:, :, t].reshape(-1, 1), V[:, :, t].reshape(-1, 1), float(rho[k]), L_x, w)
            t1, t2 = scp_parameters_scalar(pair_maxima_scalar(V[None, :, :, t]), hx[k], rho[k : k + 1], L_x, w)
            assert abs((t1[0] - th1[0, 0]) * rx[k, 0] + t2[0] - th2[0]) <= 1e-9 * max(1.0, th2[0])
            rad = min(th1[0, 0] * rx[k, 0] + th2[0], lip[k])
            lo, hi = widen(np.array([[C[k] - rad]]), np.array([[C[k] + rad]]))
            blocked = bool(lo[0, 0] < xg.lb[0] or hi[0, 0] > xg.ub[0])
            first, last = xg.cells_touching(lo, hi)
            assert res.blocking[ci[k], ui[k], wi[k]] == blocked, (objective, t)
            if not blocked:
                assert res.lo[ci[k], ui[k], wi[k], 0] == max(first[0, 0], 0), (objective, t)
                assert res.hi[ci[k], ui[k], wi[k], 0] == min(last[0, 0], xg.size - 1), (objective, t)


# ----------------------------------------------------------------------------- sampled statistics
def test_the_other_scp_objective_is_counted_on_a_fixed_sample():
    """The objective that does not build the relation is counted on ~STATISTICS_SAMPLE of the triples, the same
    triples however the cells are chunked; every other count is exact; the estimate is close."""
    sub = _distinct("consensus")[0]
    L_x, L_w = float(sub.spec.lipschitz.x), float(sub.spec.lipschitz.w)

    def totals(chunk_cells, full):
        tot = {}
        for a, b in chunk_ranges(sub, chunk_cells):
            r = abstract_cells(sub, a, b, L_x, L_w, "scp", "paper", full_statistics=full)
            for k, (s, c) in r.successors.items():
                t = tot.setdefault(k, [0, 0])
                t[0] += s
                t[1] += c
        return tot

    full, sampled, chunked = totals(None, True), totals(None, False), totals(5, False)
    assert sampled == chunked
    for k in ("lipschitz", "hull", "scp"):
        assert sampled[k] == full[k]
    s, c = sampled["scp_radius"]
    assert abs(c - STATISTICS_SAMPLE * sub.triples) < 0.1 * STATISTICS_SAMPLE * sub.triples
    exact = full["scp_radius"][0] / full["scp_radius"][1]
    assert abs(s / c - exact) < 0.02 * exact
    picked = statistics_sample(0, sub.triples)
    T = sub.triples
    assert np.array_equal(np.concatenate([statistics_sample(a, min(100, T - a)) + a for a in range(0, T, 100)]), picked)


def _planar() -> list:
    """A subsystem with a 2-D state and a 2-D internal input (the per-triple LP path, multi-axis slopes)."""
    from pipelines.spec.model import parse_spec

    spec = parse_spec({
        "subsystems": [{"name": "p", "replicate": 2, "reads": [0, 1],
                        "state": {"lb": [0, 0], "ub": [2, 2], "eta": [1, 1]}, "input": {"lb": -1, "ub": 1, "eta": 1},
                        "dynamics": "[0.5 * x[0] + 0.2 * u[0] + 0.1 * w[1], 0.4 * x[1] + 0.1 * sin(w[0])]",
                        "lipschitz": {"x": 0.5, "w": 0.1}, "samples": 16, "growth_bound": "scp"}],
        "interconnection": {"map": "[x[0], x[1]]", "internal": [{"lb": 0, "ub": 2, "eta": 1}] * 2,
                            "error": "linear"},
        "specification": {"kind": "safe", "safe": {"boxes": [{"lb": [0, 0, 0, 0], "ub": [2, 2, 2, 2]}]}},
    })
    return [m[0] for m in build_network(spec, None).unique_subsystems().values()]


@pytest.mark.parametrize("case", ["consensus", "scalability", "tanks", "small", "planar"])
def test_blocks_of_triples_give_the_same_bits_as_one_pass(case, monkeypatch):
    """abstract_cells in blocks of a few triples (block edges inside a state cell and inside an input's row)
    equals one pass over the chunk: relation, successor counts (the sampled statistics too) and the slope
    records, whose ties keep the first triple."""
    import pipelines.abstraction.cells as subsystem

    for sub in _planar() if case == "planar" else _distinct(case):
        L_x, L_w = float(sub.spec.lipschitz.x), float(sub.spec.lipschitz.w)
        a, b = chunk_ranges(sub, None)[0]
        b = min(b, a + 3)
        samples = int(np.prod(subgrid_counts(sub.spec.samples, sub.n + sub.p)))
        out = []
        for block in (1 << 40, 7 * samples, samples):  # one block; 7 triples per block; one triple per block
            monkeypatch.setattr(subsystem, "BLOCK_POINTS", block)
            out.append(abstract_cells(sub, a, b, L_x, L_w, "scp", "paper", full_statistics=False))
        for r in out[1:]:
            for f in ("lo", "hi", "blocking"):
                np.testing.assert_array_equal(getattr(r, f), getattr(out[0], f))
            assert r.successors == out[0].successors
            assert r.slope_x == out[0].slope_x and r.slope_w == out[0].slope_w
