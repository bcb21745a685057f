"""Lipschitz constants: contradicted ones are refused (or raised on request); estimates bound the data."""

import numpy as np
import pytest
import yaml

from pipelines.abstraction.lipschitz import estimate_lipschitz, resolve_constant
from pipelines.errors import BlackBoxError, LipschitzError
from pipelines.network import build_network
from pipelines.spec.model import parse_spec
from workers.executors import InProcess
from workers.job import _abstract_subsystem

from .conftest import EXAMPLES


def _consensus_agent(lipschitz, dynamics=None):
    data = yaml.safe_load((EXAMPLES / "consensus.yaml").read_text())
    data["subsystems"][0]["lipschitz"] = lipschitz
    if dynamics:
        data["subsystems"][0]["dynamics"] = dynamics
    net = build_network(parse_spec(data), None)
    return net.subsystems[0], list(net.subsystems)


def _run(sub, members):
    rng = np.random.default_rng(0)
    consts = {arg: resolve_constant(sub, arg, rng) for arg in ("x", "w")}
    return _abstract_subsystem(members, consts, InProcess(), None, lambda *a: None, 0, 1)


def test_the_papers_consensus_constant_is_rejected():
    sub, members = _consensus_agent({"x": 1.599, "w": 1.599})
    with pytest.raises(LipschitzError) as exc:
        _run(sub, members)
    msg = str(exc.value)
    assert "L_x = 1.599" in msg and "slope 1.7" in msg and "state cell" in msg


def test_a_contradicted_constant_is_raised_when_asked():
    sub, members = _consensus_agent({"x": 1.599, "w": 1.599, "on_violation": "raise", "safety_factor": 1.05})
    _, info = _run(sub, members)
    lx = info["lipschitz"]["x"]
    assert lx["source"] == "raised" and lx["given"] == 1.599
    assert 1.7 < lx["observed_max_slope"] <= 1.76
    assert lx["value"] == pytest.approx(lx["observed_max_slope"] * 1.05)
    assert info["lipschitz"]["w"]["source"] == "given"  # 1.599 >= 0.16: not contradicted


def test_estimated_constants_bound_every_observed_slope():
    sub, _ = _consensus_agent({"x": "estimate", "w": "estimate"})
    est = estimate_lipschitz(sub, "x", np.random.default_rng(3), batches=30, pairs=100)
    assert est.value >= est.max_slope
    assert 1.6 < est.location < 2.0  # the true sup is 1.76
    est_w = estimate_lipschitz(sub, "w", np.random.default_rng(3), batches=30, pairs=100)
    assert 0.12 < est_w.value < 0.25  # the true sup is 0.16


def test_estimated_constants_give_a_sound_abstraction():
    sub, members = _consensus_agent({"x": "estimate", "w": "estimate"})
    rel, info = _run(sub, members)
    assert info["lipschitz"]["x"]["source"].startswith("estimated")
    from pipelines.verification.audit import audit_subsystem

    assert audit_subsystem(sub, rel, 100_000, np.random.default_rng(0)).violations == 0


@pytest.mark.parametrize("dyn,match", [
    ("log(x[0] - 16)", "not finite"),
    ("x[0] / (x[0] - x[0])", "not finite"),
    ("where(x[0] > 31.9, exp(1000*x[0]), x[0])", "not finite"),
])
def test_a_black_box_returning_nan_or_inf_names_the_subsystem_and_cell(dyn, match):
    sub, members = _consensus_agent({"x": 1.76, "w": 0.16}, dynamics=dyn)
    with pytest.raises(BlackBoxError) as exc:
        _run(sub, members)
    assert match in str(exc.value) and "agent[0]" in str(exc.value) and "cell" in str(exc.value)
