"""Assume-guarantee contracts (pipelines/synthesis/contracts.py): every controller they give wins the exact game.

The explicit solver of :mod:`tests.games` enumerates the composed game; the contracts' domain and controller are
checked against it as a closed loop (:func:`~tests.games.check_stay`: the domain is closed under the controller,
nothing blocks, no state outside the target lies on a cycle), so a contract that assumed something its neighbours
do not guarantee shows up as a successor outside the domain or a cycle outside the target.
"""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from pipelines.controller_loading import load_controller
from pipelines.errors import SpecError
from pipelines.spec.model import parse_spec
from pipelines.spec.validate import validate_spec
from pipelines.symbolic.relations import state_set
from pipelines.synthesis import contracts
from pipelines.synthesis.fixed_points import reach_and_stay
from service.cli import main
from workers.control import run_synthesis
from workers.job import run_abstraction

from .conftest import EXAMPLES
from .games import (
    Explicit,
    build,
    check_stay,
    controller_matrix,
    coupled_net,
    random_net,
    ring_integrators,
    ring_net,
    states_vector,
)

SEEDS = list(range(40))


def _product(rng: np.random.Generator, ex: Explicit, wide: bool) -> np.ndarray:
    """A random product of one interval per subsystem (``wide``: most of each grid), as a state vector."""
    keep = np.ones(ex.nX, dtype=bool)
    states = np.array(ex.states)
    for i, k in enumerate(ex.shape):
        width = int(rng.integers(max(1, k - 2) if wide else 1, k + 1))
        first = int(rng.integers(0, k - width + 1))
        keep &= (states[:, i] >= first) & (states[:, i] < first + width)
    return keep


def _net(seed: int):
    rng = np.random.default_rng(7000 + seed)
    kind = seed % 4
    net = [ring_net, lambda r: random_net(r, True), lambda r: coupled_net(r, True),
           lambda r: coupled_net(r, False)][kind](rng)
    return rng, net


@pytest.mark.parametrize("seed", SEEDS)
def test_contract_controllers_win_the_exact_game(seed):
    rng, net = _net(seed)
    ex = Explicit(net)
    game = build(net, "interleaved", "local")
    m = game.model
    phi, S = _product(rng, ex, False), _product(rng, ex, True)
    phi &= S
    if not phi.any():
        phi = S.copy()
    states = np.array(ex.states)
    r = contracts.solve(game, state_set(m, states[phi]), state_set(m, states[S]))
    dom = states_vector(m, r.domain, ex)
    assert r.domain_states == dom.sum()
    assert not np.any(dom & ~S), "a domain state outside the safe set"
    if dom.any():
        C = controller_matrix(m, r.controller, ex)
        check_stay(ex, C, dom, phi)
        exact = ex.cobuchi(phi, S)
        assert not np.any(dom & ~exact), "a domain state the exact game loses"
    else:
        assert r.controller == m.bdd.false and r.details["outcome"] != "won"


def test_a_ring_that_needs_two_levels():
    """Each integrator holds four cells whatever its neighbours do, two only beside calm neighbours: the chain
    shrinks to four cells, then to the target, and its controller wins from every state, as the exact game does."""
    net = ring_integrators(3, 9)
    ex = Explicit(net)
    game = build(net, "interleaved", "local")
    m = game.model
    states = np.array(ex.states)
    phi = np.all((states >= 4) & (states <= 5), axis=1)
    S = np.ones(ex.nX, dtype=bool)
    progress = []
    r = contracts.solve(game, state_set(m, states[phi]), None, lambda k, message: progress.append(message))
    assert r.details["outcome"] == "won" and r.details["levels"] == 2, r.details
    dom = states_vector(m, r.domain, ex)
    exact = ex.cobuchi(phi, S)
    assert np.array_equal(dom, exact) and dom.all()  # here the contracts lose nothing: every state wins
    check_stay(ex, controller_matrix(m, r.controller, ex), dom, phi)
    assert any("level 1" in line for line in progress)
    # the exact fixed points on the same game agree where the contracts win
    exact_game = build(net, "interleaved", "shared")
    rs = reach_and_stay(exact_game, state_set(exact_game.model, states[phi]), methods=("reach_safe",))
    assert np.array_equal(states_vector(exact_game.model, rs["reach_safe"].domain, ex), exact)


def rooms(N: int, eta: float, **options) -> str:
    """The rooms ring at spacing ``eta`` solved by contracts (examples/rooms.yaml's dynamics)."""
    data = yaml.safe_load((EXAMPLES / "rooms.yaml").read_text())
    data["parameters"]["N"] = N
    data["subsystems"][0]["state"]["eta"] = eta
    data["interconnection"]["internal"]["eta"] = eta
    data["options"].update({"fixed_points": ["contracts"], "controller": "contracts", "audit_transitions": 0,
                            "closed_loop_runs": 40, "initial_states": [[18.2, 22.8, 19.0][:N] + [20.0] * (N - 3)],
                            **options})
    return yaml.safe_dump(data)


@pytest.mark.slow
def test_the_rooms_ring_by_contracts(tmp_path):
    """The ring of rooms at spacing 0.1 (its exact game takes minutes per iteration at N = 3) through `compabs run`:
    the contracts' domain is the whole safe set, the closed loops on the concrete rooms are clean, the controller
    file loads back with the same domain, and `compabs audit` re-checks the job (its closed loop draws inputs from a
    permissive controller of thousands of joint inputs per state)."""
    spec = tmp_path / "rooms.yaml"
    spec.write_text(rooms(3, 0.1, audit_transitions=20_000))
    out = tmp_path / "job"
    assert main(["run", str(spec), "--out", str(out), "--quiet", "--in-process"]) == 0
    report = json.loads((out / "report.json").read_text())
    result = report["synthesis"]["results"]["contracts"]
    assert result["outcome"] == "won" and result["levels"] >= 2
    assert report["domain_states"] == 49 ** 3  # every cell of [18, 23]^3: the exact domain can be no larger
    loop = report["closed_loop"]
    assert loop["runs"] >= 40 and loop["violations"] == 0
    assert all(rec["in_domain"] and rec["violation"] is None for rec in loop["initial_states"])
    controller = load_controller(out)
    grid = controller.state_grid
    cells = grid.unravel(np.arange(0, grid.size, 97))
    inside = np.all((cells >= 1) & (cells <= 49), axis=1)
    assert np.array_equal(controller.in_domain(cells), inside)
    assert main(["audit", str(out), "--transitions", "20000", "--seed", "3"]) == 0
    audit = json.loads((out / "audit.json").read_text())
    assert audit["closed_loop"]["runs"] > 0 and audit["closed_loop"]["violations"] == 0


def test_contracts_refuse_what_they_cannot_split():
    with pytest.raises(SpecError, match=r"specification.target: 'contracts' need a set that is a product"):
        data = yaml.safe_load(rooms(3, 0.25))
        data["specification"]["target"] = {"boxes": [{"lb": [19.5, 19.5, 19.5], "ub": [21.5, 21.5, 21.5]},
                                                     {"lb": [18.5, 18.5, 18.5], "ub": [19.5, 19.5, 19.5]}]}
        validate_spec(parse_spec(yaml.safe_dump(data)))
    with pytest.raises(SpecError, match="options.synthesis_quotient: 'contracts'"):
        validate_spec(parse_spec(rooms(3, 0.25, synthesis_quotient=1)))
    data = yaml.safe_load(rooms(3, 0.25))
    data["parameters"]["N"] = 1
    data["subsystems"][0]["reads"] = []
    data["subsystems"][0]["dynamics"] = "x[0] + gamma*(T_h - x[0])*u[0]"
    data["subsystems"][0]["lipschitz"] = {"x": 1.0}
    del data["interconnection"]
    data["options"]["initial_states"] = []
    with pytest.raises(SpecError, match="options.fixed_points: 'contracts' split a network"):
        validate_spec(parse_spec(yaml.safe_dump(data)))
    lines = validate_spec(parse_spec(rooms(3, 0.25))).lines
    assert any("contracts, 3 local games" in line for line in lines)


def test_the_local_method_prepares_no_composed_cpre():
    game = build(ring_integrators(3, 5), "interleaved", "local")
    with pytest.raises(ValueError, match="prepares no composed CPre"):
        game.predecessors(game.model.x_domain)
    with pytest.raises(ValueError, match="prepares no composed CPre"):
        game.cpre(game.model.x_domain)


@pytest.mark.parametrize("seed", SEEDS[:20])
def test_safety_contracts_are_invariant_in_the_exact_game(seed):
    """Without a target, the safety contract: its domain is closed under its controller in the exact game (and so
    inside the exact game's maximal invariant), nothing blocks."""
    rng, net = _net(seed)
    ex = Explicit(net)
    game = build(net, "interleaved", "local")
    m = game.model
    S = _product(rng, ex, True)
    r = contracts.solve(game, None, state_set(m, np.array(ex.states)[S]))
    assert r.kind == "safe/contracts"
    dom = states_vector(m, r.domain, ex)
    assert not np.any(dom & ~ex.safe(S))
    if dom.any():
        C = controller_matrix(m, r.controller, ex)
        assert np.all(C.any(axis=1)[dom])
        adj, blocks = ex.successors(C)
        assert not np.any(blocks[dom]) and not np.any(adj[dom][:, ~dom])


def test_a_ring_holds_its_safety_contract():
    net = ring_integrators(3, 9)
    ex = Explicit(net)
    game = build(net, "interleaved", "local")
    states = np.array(ex.states)
    S = np.all((states >= 2) & (states <= 6), axis=1)
    r = contracts.solve(game, None, state_set(game.model, states[S]))
    dom = states_vector(game.model, r.domain, ex)
    assert np.array_equal(dom, S) and np.array_equal(dom, ex.safe(S))


def test_a_platoon_loses_by_contracts_and_says_why(tmp_path):
    """A follower cannot keep its gap to a predecessor that may change speed anywhere in its box: the safety
    contract is empty, and the warning names the follower and the exact fixed points as the way out."""
    data = yaml.safe_load((EXAMPLES / "platoon.yaml").read_text())
    data["options"].update({"fixed_points": ["contracts"], "controller": "contracts", "audit_transitions": 0,
                            "closed_loop_runs": 5})
    report = run_synthesis(run_abstraction(parse_spec(yaml.safe_dump(data)), audit=False), tmp_path)
    assert report["domain_states"] == 0
    why = [w for w in report["warnings"] if w.startswith("contracts:")]
    assert len(why) == 1 and "subsystem 'follower[0]'" in why[0] and "left out of options.fixed_points" in why[0]
