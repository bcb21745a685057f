"""Soundness of every relation kind on random small systems (hypothesis).

Each example draws a random system whose Lipschitz constants are known in closed form, abstracts it, and
audits random concrete transitions (a share on cell boundaries and box edges): the concrete successor's
cell must be in the abstract successor set (subsystems), the cell of ``M(x)`` in ``M̂(x̂)``
(interconnection). The batched SCP is compared with the reference LP on random data.
"""

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipelines.abstraction.cells import abstract_cells
from pipelines.abstraction.growth_bound import pair_maxima_scalar, scp_parameters_scalar, scp_reference, scp_rho
from pipelines.abstraction.relation import assemble, chunk_ranges
from pipelines.interconnection import abstract_interconnection
from pipelines.network import build_network
from pipelines.spec.model import parse_spec
from pipelines.verification.audit import audit_interconnection, audit_subsystem

from .strategies import scalar_systems

SETTINGS = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow])
def _network(sysd, map_="[x[0]]", error="linear", internal=None, n=1, lipschitz=None, sigma=4):
    spec = parse_spec({
        "subsystems": [{
            "name": "s", "replicate": n, "state": sysd["state"], "input": sysd["input"], "reads": [0],
            "dynamics": sysd["dynamics"], "lipschitz": {"x": sysd["L_x"], "w": sysd["L_w"]},
            "samples": sysd["samples"], "growth_bound": sysd["method"], "scp_objective": sysd["objective"],
        }],
        "interconnection": {"map": map_, "internal": internal or sysd["internal"], "error": error, "samples": 50, "alpha": 1e-4,
                            "lipschitz": lipschitz, "sigma": sigma, "holdout": 200},
        "specification": {"kind": "safe", "safe": {"boxes": [{"lb": sysd["state"]["lb"], "ub": sysd["state"]["ub"]}]}},
    })
    return build_network(spec, None)


@settings(max_examples=200, **SETTINGS)
@given(sysd=scalar_systems(), seed=st.integers(0, 2**31 - 1))
def test_subsystem_relations_are_sound(sysd, seed):
    sub = _network(sysd).subsystems[0]
    res = [abstract_cells(sub, a, b, sysd["L_x"], sysd["L_w"], sysd["method"], sysd["objective"])
           for a, b in chunk_ranges(sub, None)]
    rel = assemble(res, sub.state_grid.size, sysd["method"], sysd["L_x"], sysd["L_w"])
    result = audit_subsystem(sub, rel, 20_000, np.random.default_rng(seed))
    assert result.violations == 0, result.first_violation


@st.composite
def linear_maps(draw):
    n = draw(st.integers(2, 5))
    weights = [draw(st.sampled_from([0.0, 0.25, 0.5, -0.5, 1.0, 0.125])) for _ in range(n)]
    if not any(weights):
        weights[0] = 1.0
    return n, weights, draw(st.integers(2, 4))


@settings(max_examples=60, **SETTINGS)
@given(m=linear_maps(), seed=st.integers(0, 2**31 - 1))
def test_linear_interconnections_are_sound(m, seed):
    n, weights, sigma = m
    expr = " + ".join(f"{w} * x[{i}]" for i, w in enumerate(weights) if w)
    bound = sum(abs(w) for w in weights) * 4 + 1
    sysd = {"dynamics": "0.5 * x[0] + 0.1 * w[0]", "L_x": 0.5, "L_w": 0.1, "state": {"lb": -2, "ub": 2, "eta": 0.5},
            "internal": {"lb": -bound, "ub": bound, "eta": 0.5}, "input": {"lb": 0, "ub": 0, "eta": 1},
            "samples": 4, "method": "hull", "objective": "paper"}
    net = _network(sysd, map_=f"[{expr}]", error="linear", n=n, sigma=sigma)
    ia = abstract_interconnection(net, np.random.default_rng(seed))
    assert audit_interconnection(net, ia, 20_000, np.random.default_rng(seed)).violations == 0


@settings(max_examples=30, **SETTINGS)
@given(k=st.floats(0.2, 2.0), mode=st.sampled_from(["certify", "direct"]), seed=st.integers(0, 2**31 - 1))
def test_nonlinear_interconnections_are_sound(k, mode, seed):
    """M(x) = [tanh(k x0) + 0.5 sin(x1), 0.3 x2**2 / 4]: Lipschitz (inf-norm) k + 0.5 and 0.6 on [-2, 2]."""
    sysd = {"dynamics": "0.5 * x[0] + 0.1 * w[0]", "L_x": 0.5, "L_w": 0.1, "state": {"lb": -2, "ub": 2, "eta": 0.5},
            "internal": {"lb": -3, "ub": 3, "eta": 0.25}, "input": {"lb": 0, "ub": 0, "eta": 1},
            "samples": 4, "method": "hull", "objective": "paper"}
    net = _network(sysd, map_=f"[tanh({k} * x[0]) + 0.5 * sin(x[1]), 0.3 * x[2]**2 / 4]", error=mode, n=3,
                   lipschitz=max(k + 0.5, 0.6), internal=[sysd["internal"], sysd["internal"]])
    ia = abstract_interconnection(net, np.random.default_rng(seed))
    assert audit_interconnection(net, ia, 20_000, np.random.default_rng(seed)).violations == 0


@settings(max_examples=200, **SETTINGS)
@given(
    mx=st.integers(1, 9), mw=st.integers(1, 5), L=st.floats(0.05, 6.0), seed=st.integers(0, 2**31 - 1),
    radius=st.booleans(),
)
def test_batched_scp_equals_the_reference_lp(mx, mw, L, seed, radius):
    rng = np.random.default_rng(seed)
    V = rng.normal(0, rng.uniform(0.01, 3), (1, mx, mw)).cumsum(axis=1)
    h = np.array([rng.uniform(0.05, 1.0)])
    rho = scp_rho(h[:, None], np.array([[rng.uniform(0, 1)]]), L, rng.uniform(0, 2))
    weight = np.array([mx * h[0] / 2]) if radius else np.ones(1)
    t1, t2 = scp_parameters_scalar(pair_maxima_scalar(V), h, rho, L, weight)
    xs = np.repeat((np.arange(mx) + 0.5) * h[0], mw)[:, None]
    th1, th2 = scp_reference(xs, V[0].reshape(-1, 1), float(rho[0]), L, weight)
    assert abs((weight[0] * t1[0] + t2[0]) - (weight[0] * th1[0, 0] + th2[0])) <= 1e-9 * max(1.0, th2[0])
