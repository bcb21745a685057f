"""An empty winning domain is explained from the job's data (pipelines/verification/empty_domain.py): small
systems whose empty domain has a known cause, and the report's warning names it."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from pipelines.controller_loading import load_controller
from pipelines.spec.model import parse_spec
from pipelines.spec.regions import spec_regions
from pipelines.verification.empty_domain import explain_empty_domain, local_game
from workers.executors import Execution
from workers.job import run_abstraction, run_job

from .conftest import EXAMPLES


def _spec(dynamics, lipschitz, specification, interconnection=None):
    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    data["subsystems"][0].update(dynamics=dynamics, lipschitz=lipschitz)
    data["interconnection"].update(interconnection or {})
    data["specification"] = specification
    data["options"] = {"audit_transitions": 1_000, "closed_loop_runs": 2}
    return parse_spec(data)


def safe(lb, ub):
    return {"kind": "safe", "safe": {"boxes": [{"lb": lb, "ub": ub}]}}


CASES = {
    # x+ = x + 3 + 0.1 u: no input of [-2, 2] keeps the state in one cell.
    "drift": (_spec("x[0] + 3 + 0.1 * u[0] + 0 * w[0]", {"x": 1.01, "w": 0.01}, safe(9.5, 10.5)),
              "cannot keep its state in its part of the safe set ([9.5, 10.5], 1 cell) even with the most favourable "
              "internal variables: the inputs cannot counter the drift",
              "at x ≈ 10 (cell [9.5, 10.5]) the closest successors of any input (u = -2) are [11.5, 13.5], outside"),
    # The same drift with the whole box safe: the top cells' successors leave the state box.
    "blocking": (_spec("x[0] + 3 + 0.1 * u[0] + 0 * w[0]", {"x": 1.01, "w": 0.01}, safe(-0.5, 32.5)),
                 "every input is blocking near the boundary, its successors leaving the state box",
                 "the successors of every input leave the state box [-0.5, 32.5]"),
    # L_x = 3: every image spans 4 cells, the safe set 2.
    "wide": (_spec("x[0] + 0.1 * u[0] + 0 * w[0]", {"x": 3, "w": 0.01}, safe(9.5, 11.5)),
             "every image of some cells is wider than a cell and spills out of the region, through the growth bound",
             "4 cells of x[0] where the region has 2"),
    # x+ = w + 0.1 u: the state follows w, which the interconnection knows within ±4.8 cells only.
    "interconnection": (_spec("w[0] + 0.1 * u[0]", {"x": 0.01, "w": 1.01}, safe(9.5, 12.5),
                              {"map": "mean(x) + 2 * sin(x[0])", "error": "certify", "lipschitz": 3,
                               "internal": {"lb": -5, "ub": 37, "eta": 1}}),
                        "keeps 3 cells of its part of the safe set ([9.5, 12.5], 3 cells) when the internal variables "
                        "are favourable, but none against every internal cell the interconnection admits",
                        "the interconnection's error bound"),
}


@pytest.mark.parametrize("case", list(CASES))
def test_the_report_names_the_cause_of_an_empty_domain(case, tmp_path):
    spec, cause, detail = CASES[case]
    report = run_job(spec, tmp_path / "job", execution=Execution(in_process=True))
    assert report["domain_states"] == 0
    (why,) = [w for w in report["warnings"] if w.startswith("why the winning domain is empty")]
    assert "subsystem 'agent[0]' (and 1 identical)" in why
    assert cause in why and detail in why, why


def test_a_target_outside_the_safe_set_is_named():
    spec = _spec("x[0] + 0.1 * u[0] + 0 * w[0]", {"x": 1.01, "w": 0.01},
                 {"kind": "reach", "target": {"boxes": [{"lb": 20.5, "ub": 25.5}]},
                  "safe": {"boxes": [{"lb": 0.5, "ub": 10.5}]}})
    a = run_abstraction(spec, audit=False)
    (why,) = explain_empty_domain(a.network, a.relations, a.interconnection, spec)
    assert "the target and the safe set share no whole cell" in why


def test_the_favourable_game_keeps_what_a_controller_keeps(tmp_path):
    """Where the domain is not empty, the favourable local game of each subsystem keeps the projection of the
    controller's domain (the argument that makes an empty favourable game a cause of an empty domain)."""
    spec = _spec("32 / (1 + exp(-0.2 * (x[0] + u[0] + 0.1 * (x[0] - w[0]) - 16)))", {"x": 1.76, "w": 0.16},
                 safe(5.5, 25.5))
    report = run_job(spec, tmp_path / "job", execution=Execution(in_process=True))
    assert report["domain_states"] > 0
    assert not any(w.startswith("why the winning domain is empty") for w in report.get("warnings", []))
    controller = load_controller(tmp_path / "job")
    a = run_abstraction(spec, audit=False)
    grid = a.network.composed_state_grid()
    cells = grid.unravel(np.arange(grid.size))
    domain = cells[controller.in_domain(cells)]
    region = spec_regions(spec, a.network)["safe"]
    for sub in a.network.subsystems:
        mask = np.zeros(sub.state_grid.shape, dtype=bool)
        mask[region.boxes[0][0][sub.state_offset]:region.boxes[0][1][sub.state_offset] + 1] = True
        game = local_game(sub, a.relations[sub.key], mask)
        assert game.favourable[domain[:, sub.state_offset]].all()
