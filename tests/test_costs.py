"""The cost model (issue 23, defect 2): every knob that multiplies work or memory is bounded by a cap, checked
before anything runs, and a refusal names the knob (the spec's field), its value and the cap.

Each knob over its cap is refused by :func:`pipelines.spec.costs.check_costs` and by ``POST /jobs`` (422, no job
stored); the measured cases of the issue (``lipschitz`` 40 x 100,000 pairs, ``options.chunk_cells: 1`` on a
50,001-cell grid, ``audit_transitions: 1e8``, 10^10 closed-loop steps) are refused in well under a second with
a few MB allocated, and nothing of the job is run.
"""

from __future__ import annotations

import dataclasses
import re
import time
import tracemalloc
from collections.abc import Callable, Iterator
from typing import Any

import pytest
import yaml
from fastapi.testclient import TestClient

from pipelines.abstraction.relation import chunk_ranges
from pipelines.errors import SpecError
from pipelines.network import build_network
from pipelines.spec.costs import (
    CAP_NAMES,
    Caps,
    CostError,
    audit_evaluations,
    check_costs,
    check_spec,
    chunk_count,
    estimate_costs,
)
from pipelines.spec.model import load_spec, parse_spec
from service.app import create_app
from service.errors import CapExceeded
from service.settings import Settings, local_caps

from .conftest import EXAMPLES

TOKEN = "cost-token"
AUTH = {"Authorization": f"Bearer {TOKEN}"}


def small(**options: Any) -> dict[str, Any]:
    data = yaml.safe_load((EXAMPLES / "small.yaml").read_text())
    data["options"].update(options)
    return data


def agent(data: dict[str, Any]) -> dict[str, Any]:
    return data["subsystems"][0]


def with_n(n: int) -> Callable[[dict[str, Any]], None]:
    def mutate(d: dict[str, Any]) -> None:
        d["parameters"]["N"] = n
        d["options"]["initial_states"] = []

    return mutate


def measured_lipschitz(d: dict[str, Any]) -> None:  # issue 23: 1.7 GB in the API process
    agent(d)["lipschitz"] = {"x": "estimate", "batches": 40, "pairs": 100_000}


def measured_chunks(d: dict[str, Any]) -> None:  # issue 23: 50,001 tasks at once, API at 1.25 GB
    agent(d)["state"]["eta"] = 32 / 50_000
    d["options"]["chunk_cells"] = 1


def measured_audit(d: dict[str, Any]) -> None:  # issue 23: the only running slot for hours
    d["options"]["audit_transitions"] = 100_000_000


def measured_closed_loop(d: dict[str, Any]) -> None:  # 10^10 run-steps
    d["options"].update(closed_loop_runs=100_000, closed_loop_steps=100_000)


def huge_samples(d: dict[str, Any]) -> None:  # 1281 x 5 x 1281 triples (under max_cells) x 10^5 samples
    agent(d)["state"]["eta"] = 0.025
    d["interconnection"]["internal"]["eta"] = 0.025
    agent(d)["samples"] = 100_000


def big_holdout(d: dict[str, Any]) -> None:
    with_n(64)(d)
    d["interconnection"]["holdout"] = 1_000_000


def long_interconnection(d: dict[str, Any]) -> None:
    with_n(200)(d)
    d["interconnection"]["holdout"] = 50_000


#: (name, caps given, spec mutation, knob in the message, cap name, cap value, value in the message)
CASES: list[tuple[str, dict[str, int], Callable[[dict[str, Any]], None] | None, str, str, int, int]] = [
    ("subsystems", {}, with_n(10**9), "subsystems[0].replicate", "max_subsystems", 256, 10**9),
    ("expression", {"max_expression_length": 20}, None, "subsystems[0].dynamics", "max_expression_length", 20, 63),
    ("cells", {"max_cells": 5000}, None, "subsystems[0].state × subsystems[0].input × interconnection.internal", "max_cells", 5000, 5445),
    ("evaluations", {}, huge_samples, "subsystems[*].samples × (x, u, w) triples", "max_evaluations", 10**11,
     1281 * 5 * 1281 * 100_000),
    ("tasks", {}, measured_chunks, "options.chunk_cells", "max_tasks", 10_000, 50_001),
    ("lipschitz", {}, measured_lipschitz, "subsystems[0].lipschitz.batches × subsystems[0].lipschitz.pairs",
     "max_lipschitz_pairs", 2_000_000, 40 * 100_000 * 5),
    ("sample array", {}, big_holdout, "interconnection.holdout × state dimension", "max_sample_values", 20_000_000,
     64 * 10**6),
    ("interconnection", {}, long_interconnection, "interconnection.samples, interconnection.holdout",
     "max_interconnection_values", 10**9, 200 * (20 * 2 + 50_000 * (200 + 2 + 4))),
    ("audit", {}, measured_audit, "options.audit_transitions", "max_audit_evaluations", 10**8,
     audit_evaluations(10**8, 1, 2)),
    ("closed loop", {}, measured_closed_loop, "options.closed_loop_runs × options.closed_loop_steps",
     "max_closed_loop_steps", 10**7, (100_000 + 1) * 100_000 * 2),
]
IDS = [c[0] for c in CASES]
MEASURED = ["tasks", "lipschitz", "audit", "closed loop"]


def case_spec(mutate: Callable[[dict[str, Any]], None] | None) -> dict[str, Any]:
    data = small()
    if mutate:
        mutate(data)
    return data


def check(data: dict[str, Any], caps: Caps) -> None:
    spec = parse_spec(data)
    check_spec(spec, caps)
    check_costs(spec, build_network(spec, ()), caps)


# ====================================================================================== the Python function
@pytest.mark.parametrize("name,given,mutate,knob,cap_name,cap,value", CASES, ids=IDS)
def test_each_knob_over_its_cap_is_refused_naming_knob_value_and_cap(name, given, mutate, knob, cap_name, cap, value):
    caps = dataclasses.replace(Caps(), **given)
    with pytest.raises(CostError) as err:
        check(case_spec(mutate), caps)
    e = err.value
    assert isinstance(e, SpecError)
    assert (e.knob.startswith(knob), e.value, e.cap, e.cap_name) == (True, value, cap, cap_name)
    message = str(e)
    assert knob in message and str(value) in message and f"this server's cap {cap_name} is {cap}" in message
    assert f"COMPABS_{cap_name.upper()}" in message
    # and the same spec under a cap just above it passes that knob (the value is what is compared)
    roomy = dataclasses.replace(Caps.local(), **{cap_name: value})
    try:
        check(case_spec(mutate), roomy)
    except SpecError as other:  # another cap, or the network's own bound (replicate <= 100,000)
        assert getattr(other, "cap_name", None) != cap_name


@pytest.mark.parametrize("name", MEASURED)
def test_measured_cases_are_refused_at_once_with_nothing_run(name, monkeypatch):
    """The issue's cases: refused in well under a second, a few MB allocated, no black box evaluated beyond the
    expressions' one-point probe, nothing estimated, no task made."""
    import pipelines.abstraction.lipschitz as lipschitz
    import pipelines.blackbox as blackbox

    def forbidden(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("ran before the caps were checked")

    monkeypatch.setattr(lipschitz, "estimate_lipschitz", forbidden)
    monkeypatch.setattr("pipelines.abstraction.relation.chunk_ranges", forbidden)
    calls = []
    original = blackbox.BlackBox.__call__
    monkeypatch.setattr(blackbox.BlackBox, "__call__", lambda self, *a: calls.append(a) or original(self, *a))
    data = case_spec(dict((c[0], c[2]) for c in CASES)[name])
    tracemalloc.start()
    t0 = time.perf_counter()
    try:
        with pytest.raises(CostError):
            check(data, Caps())
        seconds = time.perf_counter() - t0
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert seconds < 2.0 and peak < 20 * 2**20, (seconds, peak)
    assert calls == []


def test_the_spec_own_max_cells_is_named_when_smaller():
    spec = parse_spec(small(max_cells=5000))
    with pytest.raises(CostError, match=r"the spec's cap options\.max_cells is 5000: coarsen") as err:
        check_costs(spec, build_network(spec, ()), Caps())
    assert (err.value.cap_name, err.value.cap, err.value.value) == ("options.max_cells", 5000, 5445)


def test_every_example_is_within_the_server_caps():
    for path in sorted(EXAMPLES.glob("*.yaml")):
        spec = load_spec(path)
        line = check_costs(spec, build_network(spec, None), Caps())
        assert line.startswith("every knob within this server's caps; nearest: "), (path, line)


def test_chunk_count_is_the_runner_chunking():
    for path in sorted(EXAMPLES.glob("*.yaml")):
        spec = load_spec(path)
        for sub in build_network(spec, None).subsystems:
            for chunk_cells in (None, 1, 7, 10**6):
                for points in (1, 2_000_000, 100_000_000):
                    assert chunk_count(sub, chunk_cells, points)[0] == len(chunk_ranges(sub, chunk_cells, points))


def test_default_chunking_counts_the_executor_tasks():
    """A cluster task holds 50x the evaluations of an in-process one: fewer tasks for the same spec."""
    data = small()
    agent(data)["state"]["eta"] = 32 / 50_000  # 50,001 cells, 16,500 evaluations each: 1 cell per 121 tasks ...
    agent(data)["samples"] = 100_000  # ... and 1.65e7 evaluations per cell: one cell a task either way
    spec = parse_spec(data)
    network = build_network(spec, ())
    tasks = {c.cap_name: c.value for c in estimate_costs(spec, network, task_points=100_000_000)}["max_tasks"]
    # 6 cells per cluster task by evaluations alone; 5 with the growth bound's own work per triple (the SCP's pair
    # maxima over 316 state samples, the hull's extremes), which sizes tasks by their real cost (triple_cost)
    assert tasks == 50_001 // 5 + 1
    in_process = {c.cap_name: c.value for c in estimate_costs(spec, network)}["max_tasks"]
    assert in_process == 50_001  # 2.5e7 per in-process chunk: one cell a task
    with pytest.raises(CostError, match=r"set options\.chunk_cells to at least \d+"):
        check_costs(spec, network, dataclasses.replace(Caps.local(), max_tasks=100, max_evaluations=10**14))


def test_fixes_name_values_under_the_cap():
    spec = parse_spec(case_spec(measured_audit))
    network = build_network(spec, ())
    with pytest.raises(CostError, match=r"at most (\d+)") as err:
        check_costs(spec, network, Caps())
    most = int(err.value.message.rsplit("at most ", 1)[1].split()[0])
    assert audit_evaluations(most, 1, 2) <= 10**8 < audit_evaluations(most + 1, 1, 2)
    check_costs(parse_spec(small(audit_transitions=most)), network, Caps())

    spec = parse_spec(case_spec(measured_lipschitz))
    with pytest.raises(CostError, match=r"pairs to at most 10000 with 40 batches"):
        check_costs(spec, build_network(spec, ()), Caps())


def test_caps_local_are_larger_and_caps_positive():
    server, local = Caps(), Caps.local()
    assert all(getattr(local, n) >= getattr(server, n) for n in CAP_NAMES)
    assert local.owner == "the local" and server.owner == "this server's"
    with pytest.raises(SpecError, match="max_tasks"):
        Caps(max_tasks=0)
    # caps=None is the local caps: the measured audit (2.3e8 evaluations) is within them, 10^10 closed-loop
    # steps are not
    spec = parse_spec(case_spec(measured_audit))
    assert check_costs(spec, build_network(spec, ())).startswith("every knob within the local caps")
    spec = parse_spec(case_spec(measured_closed_loop))
    with pytest.raises(CostError, match="the local cap max_closed_loop_steps is 100000000: lower") as err:
        check_costs(spec, build_network(spec, ()))  # no COMPABS_ variable named: Caps.local() reads none
    with pytest.raises(CostError, match=r"the local cap max_closed_loop_steps is 1000 \(COMPABS_MAX_CLOSED_LOOP_STEPS\)"):
        check_costs(spec, build_network(spec, ()), local_caps({"COMPABS_MAX_CLOSED_LOOP_STEPS": "1000"}))
    assert err.value.cap == 10**8


def test_closed_loop_is_counted_only_with_synthesis_and_auto_steps_at_their_least():
    spec = parse_spec(small(synthesis=False, closed_loop_runs=100_000, closed_loop_steps=100_000))
    assert "max_closed_loop_steps" not in {c.cap_name for c in estimate_costs(spec, build_network(spec, ()))}
    spec = parse_spec(small(closed_loop_runs=100_000))
    cost = {c.cap_name: c for c in estimate_costs(spec, build_network(spec, ()))}["max_closed_loop_steps"]
    assert cost.value == (100_000 + 1) * 30 * 2 and "automatic" in cost.what


def test_settings_carry_every_cap_from_the_environment():
    s = Settings.from_env({"COMPABS_MAX_TASKS": "77", "COMPABS_MAX_LIPSCHITZ_PAIRS": "5"})
    caps = s.caps()
    assert (caps.max_tasks, caps.max_lipschitz_pairs, caps.max_cells) == (77, 5, 10_000_000)
    assert caps.values() == {n: getattr(Settings(), n) if n not in ("max_tasks", "max_lipschitz_pairs") else
                             {"max_tasks": 77, "max_lipschitz_pairs": 5}[n] for n in CAP_NAMES}
    assert Settings().caps() == Caps()
    with pytest.raises(ValueError, match="COMPABS_MAX_AUDIT_EVALUATIONS"):
        Settings.from_env({"COMPABS_MAX_AUDIT_EVALUATIONS": "0"})


def test_local_caps_read_the_same_variables():
    assert local_caps({}) == dataclasses.replace(Caps.local(), env_hint=True)
    caps = local_caps({"COMPABS_MAX_CELLS": "1000", "COMPABS_TOKEN": "x"})
    assert caps.max_cells == 1000 and caps.max_tasks == Caps.local().max_tasks
    for bad in ("-3", "lots", "9" * 40):
        with pytest.raises(SpecError, match="COMPABS_MAX_TASKS: must be a positive integer"):
            local_caps({"COMPABS_MAX_TASKS": bad})


def test_validate_hook_applies_the_cost_model():
    """``compabs validate`` / ``run`` (pipelines.spec.validate) call check_costs with the caps they are given."""
    from pipelines.spec.validate import validate_spec

    with pytest.raises(CostError, match="options.chunk_cells"):
        validate_spec(parse_spec(case_spec(measured_chunks)), caps=Caps())
    result = validate_spec(parse_spec(small()), caps=Caps())
    assert any(line.startswith("caps: every knob within this server's caps") for line in result.lines)


# ====================================================================================== the API
@pytest.fixture
def make_client(tmp_path) -> Iterator[Callable[..., TestClient]]:
    clients = []

    def make(**overrides: Any) -> TestClient:
        values = {"data_dir": tmp_path / "data", "in_process": True, "token": TOKEN, **overrides}
        c = TestClient(create_app(Settings(**values)))
        c.__enter__()
        clients.append(c)
        return c

    yield make
    for c in reversed(clients):
        c.__exit__(None, None, None)


@pytest.mark.parametrize("name,given,mutate,knob,cap_name,cap,value", CASES, ids=IDS)
def test_post_jobs_refuses_each_knob_over_its_cap(make_client, monkeypatch, name, given, mutate, knob, cap_name, cap,
                                                 value):
    import service.manager as manager

    def forbidden(*args: Any, **kwargs: Any) -> Any:
        raise AssertionError("a job ran")

    monkeypatch.setattr(manager, "JobProcess", forbidden)
    c = make_client(**given)
    t0 = time.perf_counter()
    r = c.post("/jobs", json=case_spec(mutate), headers=AUTH)
    assert r.status_code == 422, r.text
    assert time.perf_counter() - t0 < 5
    detail = r.json()["detail"]
    assert knob in detail and str(value) in detail and f"this server's cap {cap_name} is {cap}" in detail
    assert c.get("/jobs", headers=AUTH).json()["jobs"] == []


def test_a_raised_cap_lets_the_same_spec_through_validation():
    """An operator who raises a cap (COMPABS_MAX_LIPSCHITZ_PAIRS) gets the spec accepted (validated, not run)."""
    from service.manager import validate_spec

    spec = parse_spec(case_spec(measured_lipschitz))
    with pytest.raises(CapExceeded) as err:
        validate_spec(spec, Settings())
    assert (err.value.cap, err.value.limit) == ("max_lipschitz_pairs", 2_000_000)
    validate_spec(spec, Settings(max_lipschitz_pairs=20_000_000))


def test_astronomical_knobs_are_refused_not_500(make_client):
    """Python integers do not overflow: 10^300 pairs is a refusal naming the cap (not an OverflowError)."""
    data = small()
    agent(data)["lipschitz"] = {"x": "estimate", "batches": 10**300, "pairs": 10**300}
    with pytest.raises(CostError, match="max_lipschitz_pairs") as err:
        check(data, Caps())
    assert "more than a petabyte" in err.value.message
    r = make_client().post("/jobs", json=data, headers=AUTH)
    assert 400 <= r.status_code < 500, r.text


@pytest.mark.parametrize("example", ["small", "vehicle"])
def test_an_astronomical_grid_is_refused_not_500(make_client, example):
    """A box of 10^306 cells (small.yaml's input box, found by the trust campaign's mutated specs) or more than a
    float holds (vehicle.yaml's three state coordinates) is a refusal naming the cells cap, not an OverflowError
    when the default chunk size is worked out."""
    data = yaml.safe_load((EXAMPLES / f"{example}.yaml").read_text())
    sub = data["subsystems"][0]
    if example == "small":
        sub["input"] = {"lb": -5.44755495412823e306, "ub": 2, "eta": 1}
    else:
        sub["state"]["lb"][0] = -5.4e306
    with pytest.raises(CostError, match="max_cells"):
        check(data, Caps())
    r = make_client().post("/jobs", json=data, headers=AUTH)
    assert 400 <= r.status_code < 500, r.text


# ====================================================================================== ODE sub-steps (issue 47)
def ode(substeps: int, estimate: bool = False, **options: Any) -> dict[str, Any]:
    """small.yaml's agent as an ODE of ``substeps`` Runge-Kutta 4 steps per period (its L_x estimated if
    ``estimate``)."""
    data = small(**options)
    sub = agent(data)
    sub["ode"] = sub.pop("dynamics")
    sub.update(sampling_time=0.1, substeps=substeps)
    if estimate:
        sub["lipschitz"]["x"] = "estimate"
    return data


def knob_values(data: dict[str, Any]) -> dict[str, int]:
    spec = parse_spec(data)
    return {c.cap_name: c.value for c in estimate_costs(spec, build_network(spec, ()))}


@pytest.mark.parametrize("cap_name", ["max_evaluations", "max_lipschitz_pairs", "max_audit_evaluations",
                                      "max_closed_loop_steps"])
def test_every_cost_that_evaluates_the_black_box_counts_the_sub_steps(cap_name):
    """An ODE step is 4 x substeps evaluations of its right-hand side: substeps 1000 costs about 1000 times
    substeps 1 in each knob that evaluates the black box (the audit of 1000 substeps took 94 s against 0.7 s and
    was counted the same)."""
    one, many = knob_values(ode(1, estimate=True)), knob_values(ode(1000, estimate=True))
    mapped = small()
    agent(mapped)["lipschitz"]["x"] = "estimate"
    base = knob_values(mapped)  # the same dynamics as a map: one evaluation per step
    assert one[cap_name] > base[cap_name]
    if cap_name == "max_audit_evaluations":  # the interconnection's map is one evaluation either way
        assert 500 * one[cap_name] < many[cap_name] < 1000 * one[cap_name]
    else:
        assert many[cap_name] == 1000 * one[cap_name]


def test_an_audit_of_many_sub_steps_is_refused_naming_them():
    data = ode(1000, audit_transitions=1_000_000, synthesis=False)
    check(ode(1, audit_transitions=1_000_000, synthesis=False), Caps())  # one substep: within the cap
    with pytest.raises(CostError) as err:
        check(data, Caps())
    e = err.value
    assert e.cap_name == "max_audit_evaluations" and "4 x substeps evaluations ('agent': 4000)" in e.message
    assert "options.audit_transitions" in e.message and "lower options.audit_transitions to at most" in e.message
    limit = int(re.search(r"at most (\d+)", e.message).group(1))
    check(ode(1000, audit_transitions=limit, synthesis=False), Caps())  # the fix it names is within the cap
    with pytest.raises(CostError):
        check(ode(1000, audit_transitions=limit + 1, synthesis=False), Caps())


def test_a_closed_loop_of_many_sub_steps_is_refused_naming_them():
    data = ode(1000, audit_transitions=0, closed_loop_runs=10_000, closed_loop_steps=100)
    check(ode(1, audit_transitions=0, closed_loop_runs=10_000, closed_loop_steps=100), Caps())
    with pytest.raises(CostError) as err:
        check(data, Caps())
    assert err.value.cap_name == "max_closed_loop_steps" and "4 x substeps" in err.value.message


# ====================================================================================== per-entry estimates (issue 46)
def estimated(example: str, pairs: int = 200) -> dict[str, Any]:
    """An example whose L_x is a matrix, estimated from data instead (Algorithm 4 per entry)."""
    data = yaml.safe_load((EXAMPLES / example).read_text())
    data["subsystems"][0]["lipschitz"] = {"x": "estimate", "batches": 40, "pairs": pairs}
    return data


def test_a_matrix_estimate_counts_a_round_per_coordinate_and_is_refused_with_its_fix():
    """A 4-D state's matrix is estimated in 1 + 4 rounds of 40 x pairs x 16 inputs: at 1,000 pairs one round
    (640,000) is within the server's cap and the five rounds (3.2 M) are not; the fix it names passes."""
    assert knob_values(estimated("double_integrator.yaml"))["max_lipschitz_pairs"] == 40 * 200 * 16 * 5
    with pytest.raises(CostError) as err:
        check(estimated("double_integrator.yaml", 1000), Caps())
    e = err.value
    assert (e.cap_name, e.value, e.cap) == ("max_lipschitz_pairs", 40 * 1000 * 16 * 5, 2_000_000)
    assert "40 x 1000 x 16 = 640000 pairs at once" in e.message
    assert "in 5 rounds (the norm, then each of the 4 coordinates of x for the 4 x 4 entries) = 3200000 pairs" in e.message
    assert ("lower subsystems[0].lipschitz.pairs to at most 625 with 40 batches (the defaults are 40 x 200), or give "
            "L_x as a number or a matrix") in e.message
    check(estimated("double_integrator.yaml", 625), Caps())
    with pytest.raises(CostError, match="max_lipschitz_pairs"):
        check(estimated("double_integrator.yaml", 626), Caps())


def test_a_matrix_estimate_of_an_ode_counts_its_sub_steps_in_every_round():
    """The vehicle: 3 coordinates (1 + 3 rounds), 49 inputs, 10 RK4 sub-steps (40 evaluations per step)."""
    values = knob_values(estimated("vehicle.yaml", 10))
    assert values["max_lipschitz_pairs"] == 40 * 10 * 49 * 4 * 40
    with pytest.raises(CostError) as err:
        check(estimated("vehicle.yaml"), Caps())
    assert "in 4 rounds" in err.value.message and "x 40 evaluations per step (4 x subsystems[0].substeps)" in \
        err.value.message
