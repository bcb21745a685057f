"""Issue 48, the integration: 'ltl' specifications from the spec to the closed loop (docs/spec.md, "Temporal-logic
tasks"). The examples are solved on both back ends with the same domain and winning product states, their
controllers with memory saved, verified and loaded back, and run in closed loop on the concrete black boxes (>= 100
runs, every one accepted within its bound, none a violation). Spec errors are one line naming the field.
"""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import yaml

from pipelines.controller_integrity import ControllerIntegrityError
from pipelines.controller_loading import load_controller
from pipelines.errors import SpecError
from pipelines.product_controller import ProductController
from pipelines.spec.model import load_spec, parse_spec, spec_hash
from pipelines.spec.validate import validate_spec, with_options
from pipelines.verification.product_loop import simulate_product
from service.cli import main
from workers.control import run_synthesis
from workers.job import run_abstraction

from .conftest import EXAMPLES


def solve_both(example: str, tmp_path):
    """The example's abstraction (once), then synthesis on each back end into its own directory."""
    spec = with_options(load_spec(EXAMPLES / example), audit_transitions=0)
    abstraction = run_abstraction(spec)
    out = {}
    for backend in ("explicit", "bdd"):
        job = dataclasses.replace(abstraction, spec=with_options(spec, synthesis_backend=backend, audit_transitions=0))
        (tmp_path / backend).mkdir()
        (tmp_path / backend / "spec.json").write_text(json.dumps(job.spec.model_dump(mode="json")))
        out[backend] = (run_synthesis(job, tmp_path / backend), job)
    return out


def all_cells(controller) -> np.ndarray:
    grid = controller.state_grid
    return grid.unravel(np.arange(grid.size))


def check_both(solved, tmp_path) -> None:
    reports = {k: r for k, (r, _) in solved.items()}
    assert {r["synthesis"]["backend"] for r in reports.values()} == {"explicit", "bdd"}
    results = {k: r["synthesis"]["results"]["ltl"] for k, r in reports.items()}
    assert results["explicit"]["domain_states"] == results["bdd"]["domain_states"] > 0
    for key in ("winning_product_states", "product_states", "iterations", "automaton"):
        assert results["explicit"][key] == results["bdd"][key], key
    loaded = {k: load_controller(tmp_path / k) for k in reports}
    assert all(isinstance(c, ProductController) for c in loaded.values())
    assert not loaded["explicit"].is_symbolic and loaded["bdd"].is_symbolic
    cells = all_cells(loaded["explicit"])
    assert np.array_equal(loaded["explicit"].in_domain(cells), loaded["bdd"].in_domain(cells))
    for q in range(loaded["explicit"].automaton.n_states):
        assert np.array_equal(loaded["explicit"].winning(cells, q), loaded["bdd"].winning(cells, q)), q
    for report in reports.values():
        loop = report["closed_loop"]
        assert loop["runs"] >= 100 and loop["violations"] == 0, loop["first_violation"]
        assert loop["accepted"] == loop["runs"]
        assert report["controller"]["form"] == "product"
        assert report["closed_loop"]["initial_states"][0]["in_domain"]


def test_robot_ltl_on_both_back_ends(tmp_path):
    solved = solve_both("robot_ltl.yaml", tmp_path)
    check_both(solved, tmp_path)
    # The loaded controllers answer as the job's own: the same inputs at the same product states.
    report, job = solved["explicit"]
    ctrl = load_controller(tmp_path / "explicit")
    rng = np.random.default_rng(3)
    cells = ctrl.sample_cells(20, rng)
    x = ctrl.state_grid.points(cells)
    q = ctrl.initial_state(x)
    bdd = load_controller(tmp_path / "bdd")
    for k in range(x.shape[0]):
        a = {tuple(u) for u in ctrl.inputs(x[k], int(q[k])).round(9)}
        b = {tuple(u) for u in bdd.inputs(x[k], int(q[k])).round(9)}
        assert a == b and a
    # A loaded BDD form keeps its layers: it bounds every run as the arrays do, and runs accept within them.
    runs = simulate_product(job.network, bdd, x, None, rng)
    assert all(r.violation is None and r.settled_at is not None for r in runs)
    assert [r.extra["bound"] for r in runs] == [r.extra["bound"] for r in simulate_product(job.network, ctrl, x, None,
                                                                                             rng)]


def test_a_damaged_product_controller_is_one_clear_error(tmp_path):
    spec = load_spec(EXAMPLES / "robot_ltl.yaml")
    spec = with_options(spec, audit_transitions=0, closed_loop_runs=0, synthesis_backend="explicit")
    (tmp_path / "spec.json").write_text(json.dumps(spec.model_dump(mode="json")))
    run_synthesis(run_abstraction(spec), tmp_path)
    payload = tmp_path / "controller.npz"
    good = payload.read_bytes()
    payload.write_bytes(good[:-5] + b"xxxxx")
    with pytest.raises(ControllerIntegrityError, match="controller.npz: its checksum differs"):
        load_controller(tmp_path)
    payload.write_bytes(good)
    assert isinstance(load_controller(tmp_path), ProductController)
    other = with_options(spec, seed=9)
    (tmp_path / "spec.json").write_text(json.dumps(other.model_dump(mode="json")))
    assert spec_hash(other) != spec_hash(spec)
    with pytest.raises(ControllerIntegrityError, match="belongs to another job"):
        load_controller(tmp_path)


# ============================================================================================ the spec
ROBOT = yaml.safe_load((EXAMPLES / "robot_ltl.yaml").read_text())


def robot(**specification) -> dict:
    data = json.loads(json.dumps(ROBOT))
    data["specification"].update(specification)
    return {**data, "specification": {k: v for k, v in data["specification"].items() if v is not None}}


@pytest.mark.parametrize("change,message", [
    ({"target": {"boxes": [{"lb": 0, "ub": 1}]}}, r"specification: .*has no 'target': name the region in 'regions' "
                                                  r"and write it in the formula"),
    ({"formula": None}, "an 'ltl' specification needs 'formula'"),
    ({"regions": {"A": {"boxes": [{"lb": 0, "ub": 1}]}}}, "region name 'A' cannot be an atom"),
    ({"kind": "reach", "target": {"boxes": [{"lb": 0, "ub": 1}]}}, "'formula' and 'regions' belong to kind 'ltl'"),
])
def test_spec_fields_of_ltl_are_checked(change, message):
    with pytest.raises(SpecError, match=message):
        parse_spec(robot(**change))


@pytest.mark.parametrize("formula,message", [
    ("F(a & F b", "the formula ends too early"),
    ("F a & G !c", "atom 'c' names no region"),
    ("a R b & G !o", "'R' \\(release\\) is outside the supported fragment"),
    ("F(a & F b)", "specification.regions.o: the formula does not use this region"),
])
def test_a_bad_formula_is_refused_at_validation(formula, message):
    spec = parse_spec(robot(formula=formula))
    with pytest.raises(SpecError, match=message):
        validate_spec(spec, allowed_modules=None)


def test_the_api_refuses_a_bad_formula_before_it_is_queued(tmp_path):
    from fastapi.testclient import TestClient

    from service.app import create_app
    from service.settings import Settings

    auth = {"Authorization": "Bearer ltl-token"}
    with TestClient(create_app(Settings(data_dir=tmp_path / "data", in_process=True, token="ltl-token"))) as client:
        client.app.state.manager._kick = lambda: None  # type: ignore[attr-defined]  # queued jobs never start
        r = client.post("/jobs", json=robot(formula="F(a & X) & G !o"), headers=auth)
        assert r.status_code == 422, r.text
        assert "specification.formula: unexpected ')' at position 8" in r.json()["detail"]
        assert client.post("/jobs", json=robot(), headers=auth).status_code in (200, 201, 202)


def test_validate_translates_and_names_the_automaton_cap(tmp_path, capsys):
    data = robot()
    data["options"]["max_automaton_states"] = 3
    path = tmp_path / "spec.yaml"
    path.write_text(yaml.safe_dump(data))
    assert main(["validate", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "over the cap of 3 (options.max_automaton_states)" in err and "\n" not in err
    assert main(["validate", str(EXAMPLES / "robot_ltl.yaml")]) == 0
    assert "specification.automaton: 5 states (1 accepting)" in capsys.readouterr().out


def test_the_other_kinds_dump_and_hash_as_before():
    spec = load_spec(EXAMPLES / "vehicle.yaml")
    dumped = spec.model_dump(mode="json")
    assert not {"formula", "regions"} & set(dumped["specification"])
    assert "max_automaton_states" not in dumped["options"]
    assert spec_hash(spec) == "72aa26fe4f3f6986"
    assert spec_hash(with_options(spec, max_automaton_states=10)) == spec_hash(spec)
