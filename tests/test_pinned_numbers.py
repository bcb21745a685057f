"""Every example's numbers, pinned: abstract, region and domain counts and a hash of every relation.

The values were computed before the code was reorganised into subpackages and must never change by accident:
a restructuring, a faster kernel or a new executor gives the same bits. A change that is *meant* to change a
relation (a tighter growth bound, a new grid rule) updates the pin in the same commit and says why. The
consensus case is pinned at N = 4 for synthesis (N = 8 synthesizes in minutes; ``bench/run.py`` reports it:
14,475,269,953 states).
"""

from __future__ import annotations

import hashlib

import numpy as np
import pytest

from pipelines.spec.model import load_spec
from pipelines.synthesis.options import SynthesisOptions
from pipelines.synthesis.synthesize import synthesize
from workers.executors import Execution
from workers.job import abstract_job, run_abstraction

from .conftest import EXAMPLES

PINNED = {
    "small": dict(example="small", set={}, abstract=1089, regions={"target": 277},
                  relations=["34e4a074e43de1f3"], nodes={"w0": "b1b4a90dac33203a"},
                  domains={"cobuchi": 629, "reach_safe": 629}),
    "scalability": dict(example="scalability", set={}, abstract=1185921, regions={"safe": 923521},
                        relations=["8726a7d90e4710a2"], nodes={"w0": "9943d99045f7e382"}, domains={"safe": 923521}),
    "consensus_n4": dict(example="consensus", set={"N": 4}, abstract=1185921, regions={"target": 10957},
                         relations=["34e4a074e43de1f3"], nodes={"w0": "1b9f14b3dbd40f03"},
                         domains={"reach_safe": 191493}),
    "consensus": dict(example="consensus", set={}, abstract=1406408618241, regions={"target": 9493117},
                      relations=["34e4a074e43de1f3"],
                      nodes={"z0": "e191dd6c8f7135f0", "z1": "e191dd6c8f7135f0", "w0": "44326aee78e83765"}),
    "tanks": dict(example="tanks", set={}, abstract=13422659310152401, regions={"target": 2015993900449},
                  relations=["3eac0671eb477515", "df73639abb713302"],
                  nodes={"w0": "f0f3966fe56e373c", "w1": "74a7db93d998c9ec", "w2": "69542c95cdb13c23",
                         "w3": "f0f3966fe56e373c", "w4": "74a7db93d998c9ec", "w5": "6272d9b4d02698fe",
                         "w6": "74a7db93d998c9ec", "w7": "74a7db93d998c9ec", "w8": "69542c95cdb13c23",
                         "w9": "69542c95cdb13c23"},
                  domains={"reach_safe": 217735106888}),
    "stress": dict(example="stress", set={}, abstract=263169, regions={"target": 67743},
                   relations=["14fe56f09910fd6c"], nodes={"w0": "49cf419a0c2affe8"}),
}
SLOW = {"consensus", "tanks", "stress"}
#: Abstracted on the two-worker cluster (a real store), not in this process: the stress case's per-cell stage is the
#: suite's heaviest (about 10^9 black-box evaluations, 150 s in one process), and its bits must not depend on where
#: the cells ran.
ON_CLUSTER = {"stress"}


def digest(*arrays: np.ndarray) -> str:
    """A hash of arrays' dtypes, shapes and bytes."""
    d = hashlib.sha256()
    for a in arrays:
        a = np.ascontiguousarray(a)
        d.update(str((a.dtype.str, a.shape)).encode())
        d.update(a.tobytes())
    return d.hexdigest()[:16]


@pytest.mark.parametrize("case", [pytest.param(c, marks=pytest.mark.slow) if c in SLOW else c for c in PINNED])
def test_the_numbers_of_every_example_are_pinned(case, request, tmp_path):
    pin = PINNED[case]
    spec = load_spec(EXAMPLES / f"{pin['example']}.yaml", pin["set"])
    if case in ON_CLUSTER:
        r, info = abstract_job(spec, tmp_path, execution=Execution(client=request.getfixturevalue("client")), audit=False)
        assert info["workers"] == 2 and info["chunks_computed"] == info["chunks_total"] > 1
    else:
        r = run_abstraction(spec, audit=False)
    assert r.report["abstract_states"] == pin["abstract"]
    assert {k: v["states"] for k, v in r.report["regions"].items()} == pin["regions"]
    assert sorted(digest(rel.lo, rel.hi, rel.blocking) for rel in r.relations.values()) == sorted(pin["relations"])
    assert {n.output: digest(n.lo, n.hi) for n in r.interconnection.nodes} == pin["nodes"]
    if "domains" in pin:
        _, results, _ = synthesize(r.network, r.relations, r.interconnection, spec.specification,
                                   SynthesisOptions(reach_and_stay_methods=tuple(spec.options.fixed_points)))
        assert {k: res.domain_states for k, res in results.items()} == pin["domains"]
