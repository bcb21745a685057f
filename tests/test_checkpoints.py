"""Resumable safety fixed points (pipelines/synthesis/checkpoints.py, workers/checkpoint_store.py).

A job stopped in the middle of its safety fixed point resumes from the last stored iterate and ends with the
same domain as a run that was never stopped; a damaged store is named and ignored; even a forged iterate can only
make the domain smaller, never the controller wrong. The tanks (the paper's Sec. 5.3, spacing 2.5) have a safety
part of 23 iterations after their local games, in a few seconds.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest

from pipelines.spec.model import load_spec
from pipelines.spec.regions import abstract_region
from pipelines.symbolic.files import file_sha256
from pipelines.symbolic.relations import region
from pipelines.synthesis.cpre import ControllablePredecessor
from pipelines.synthesis.fixed_points import safe
from workers import checkpoint_store, jobdir
from workers.checkpoint_store import DirectoryCheckpoints, problem_key
from workers.control import run_synthesis
from workers.job import run_abstraction

from .conftest import ROOT

pytestmark = pytest.mark.slow  # a dozen syntheses of the tanks: about a minute

STOP_AT = "reach_safe/safe iteration 10:"


class _Stopped(Exception):
    """What the progress callback raises to stop a synthesis in the middle (a job cancelled, a session ended)."""


@pytest.fixture(scope="module")
def tanks():
    spec = load_spec(ROOT / "examples" / "tanks.yaml")
    return run_abstraction(spec, audit=False)


@pytest.fixture(scope="module")
def fresh(tanks, tmp_path_factory):
    """The synthesis never stopped (its own directory)."""
    return run_synthesis(tanks, tmp_path_factory.mktemp("fresh"), runs=20)


@pytest.fixture
def every_iterate(monkeypatch):
    """Store every iterate (the default waits a minute between writes); monkeypatch undoes it."""
    monkeypatch.setattr(checkpoint_store, "EVERY", 0.0)


def _stop_at(message: str):
    def progress(stage: str, done: int, total: int, text: str = "") -> None:
        if text.startswith(message):
            raise _Stopped(text)
    return progress


@pytest.fixture(scope="module")
def stopped(tanks, tmp_path_factory):
    """A directory whose synthesis stopped at the tenth safety iteration, every iterate stored (made once: each
    test works on a copy, :func:`_stopped_run`)."""
    out = tmp_path_factory.mktemp("stopped")
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(checkpoint_store, "EVERY", 0.0)
        with pytest.raises(_Stopped):
            run_synthesis(tanks, out, runs=0, progress=_stop_at(STOP_AT))
    return out


def _stopped_run(stopped: Path, out: Path) -> dict:
    """``out`` as the synthesis left it when stopped at the tenth safety iteration; the stored header."""
    shutil.copytree(stopped, out, dirs_exist_ok=True)
    return json.loads((out / jobdir.CHECKPOINTS / "reach_safe-safe.json").read_text())


def _result(report: dict) -> dict:
    return report["synthesis"]["results"]["reach_safe"]


def test_a_stopped_safety_fixed_point_resumes_where_it_stopped(tanks, fresh, stopped, tmp_path, every_iterate):
    head = _stopped_run(stopped, tmp_path)
    assert head["iteration"] == 9  # the tenth iteration's progress event came before its iterate was stored
    assert (tmp_path / jobdir.CHECKPOINTS / "reach_safe-safe.dddmp").stat().st_size > 0

    again = run_synthesis(tanks, tmp_path, runs=20)
    res, was = _result(again), _result(fresh)
    assert res["resumed_at_iteration"] == 9
    assert again["synthesis"]["checkpoints"]["resumed_at_iteration"] == {"reach_safe/safe": 9}
    assert "local_games" not in res  # the stored iterate replaces the games' bound
    # the same invariant and the same domain as the run that was never stopped, in as many safety iterations
    assert (res["safe_states"], res["domain_states"], res["inner_iterations"]) == \
        (was["safe_states"], was["domain_states"], was["inner_iterations"])
    assert again["closed_loop"]["violations"] == 0 and again["closed_loop"]["runs"] > 0
    assert not (tmp_path / jobdir.CHECKPOINTS).exists()  # cleared once the controller is written
    assert again["warnings"] == fresh["warnings"]  # (the paper's initial state, outside at this spacing)


def test_a_damaged_checkpoint_is_named_and_the_run_starts_afresh(tanks, fresh, stopped, tmp_path, every_iterate):
    _stopped_run(stopped, tmp_path)
    stored = tmp_path / jobdir.CHECKPOINTS / "reach_safe-safe.dddmp"
    data = bytearray(stored.read_bytes())
    data[len(data) // 2] ^= 0x20
    stored.write_bytes(bytes(data))

    again = run_synthesis(tanks, tmp_path, runs=5)
    assert "resumed_at_iteration" not in _result(again)
    assert any("does not match the SHA-256" in w and "started afresh" in w for w in again["warnings"])
    assert _result(again)["domain_states"] == _result(fresh)["domain_states"]


def test_a_forged_checkpoint_never_reaches_cudd(tanks, fresh, stopped, tmp_path, every_iterate):
    """A node line changed and the checksum recomputed (a forger's move): the file's structure is checked before
    CUDD reads it, the iterate refused by name and the run started afresh."""
    head = _stopped_run(stopped, tmp_path)
    stored = tmp_path / jobdir.CHECKPOINTS / "reach_safe-safe.dddmp"
    lines = stored.read_text().split("\n")
    k = lines.index(".nodes") + 2
    ident, name, var, then, other = lines[k].split()
    lines[k] = f"{ident} {name} {var} {ident} {other}"  # a node that is its own child
    stored.write_text("\n".join(lines))
    head["sha256"] = file_sha256(stored)
    (tmp_path / jobdir.CHECKPOINTS / "reach_safe-safe.json").write_text(json.dumps(head))

    again = run_synthesis(tanks, tmp_path, runs=5)
    assert "resumed_at_iteration" not in _result(again)
    assert any("not a DDDMP file" in w and "started afresh" in w for w in again["warnings"]), again["warnings"]
    assert _result(again)["domain_states"] == _result(fresh)["domain_states"]


@pytest.mark.parametrize("edit, why", [
    (lambda head: {**head, "iteration": -3}, "no iteration count"),
    (lambda head: {**head, "format": "something-else"}, "is not a compabs checkpoint"),
    (lambda head: "[1, 2", "is not readable JSON"),
])
def test_a_header_that_cannot_be_trusted_is_named(tanks, fresh, stopped, tmp_path, every_iterate, edit, why):
    head = _stopped_run(stopped, tmp_path)
    path = tmp_path / jobdir.CHECKPOINTS / "reach_safe-safe.json"
    new = edit(head)
    path.write_text(new if isinstance(new, str) else json.dumps(new))

    again = run_synthesis(tanks, tmp_path, runs=5)
    assert "resumed_at_iteration" not in _result(again)
    assert any(why in w for w in again["warnings"]), again["warnings"]
    assert _result(again)["domain_states"] == _result(fresh)["domain_states"]


def test_another_problems_checkpoint_is_replaced_silently(tanks, fresh, stopped, tmp_path, every_iterate):
    """What a changed spec leaves behind in the directory: not used, not worth a warning."""
    head = _stopped_run(stopped, tmp_path)
    path = tmp_path / jobdir.CHECKPOINTS / "reach_safe-safe.json"
    path.write_text(json.dumps({**head, "problem": "0" * 40}))

    again = run_synthesis(tanks, tmp_path, runs=5)
    assert "resumed_at_iteration" not in _result(again)
    assert again["warnings"] == fresh["warnings"]
    assert _result(again)["domain_states"] == _result(fresh)["domain_states"]


def test_the_problem_key_follows_the_relations_and_the_specification(tanks):
    spec = tanks.spec.specification.model_dump(mode="json")
    nodes = tanks.interconnection.nodes
    key = problem_key(spec, tanks.relations, nodes)
    assert key == problem_key(spec, dict(reversed(list(tanks.relations.items()))), nodes)
    other = {**spec, "target": {"boxes": [{"lb": 11.0, "ub": 50.0}]}}
    assert problem_key(other, tanks.relations, nodes) != key
    name, rel = next(iter(tanks.relations.items()))
    hi = rel.hi.copy()
    hi.reshape(-1)[0] += 1
    changed = {**tanks.relations, name: type(rel)(rel.method, rel.lo, hi, rel.blocking, rel.L_x, rel.L_w)}
    assert problem_key(spec, changed, nodes) != key


class _Forged:
    """A store that hands back a set it was given (the Checkpoints protocol, in memory)."""

    def __init__(self, Z, iteration: int) -> None:
        self.Z, self.iteration = Z, iteration

    def resume(self, model, name):
        return self.Z, self.iteration

    def iterate(self, model, name, Z, iteration):
        pass

    def converged(self, model, name, Z, iteration):
        pass


def test_even_a_forged_iterate_gives_a_controlled_invariant_inside_the_safe_set(tanks):
    """Started from any set, the safety loop ends at a controlled invariant inside ``S`` (smaller than the
    maximal one when the start misses some of it); started from a superset of the invariant, at the invariant."""
    net = tanks.network
    cpre = ControllablePredecessor.from_network(net, tanks.relations, tanks.interconnection)
    try:
        m = cpre.model
        S = region(m, abstract_region(tanks.spec.specification.target, net.composed_state_grid(), "target"))
        W = safe(cpre, S).domain
        half = m.interval("x0", 0, 12)  # tank 1 in its lower cells only
        for start, expect in ((W, W), (W | (S & half), W), (W & half, None), (~S, None)):
            Z = safe(cpre, S, checkpoints=_Forged(start, 4)).domain
            assert Z & ~S == m.bdd.false
            assert Z & ~cpre.pre(cpre.cpre(Z)) == m.bdd.false  # every state keeps some input inside Z
            assert Z & ~W == m.bdd.false
            if expect is not None:
                assert Z == expect
    finally:
        cpre.close()


def test_the_store_writes_at_most_every_so_often(tanks, tmp_path):
    net = tanks.network
    cpre = ControllablePredecessor.from_network(net, tanks.relations, tanks.interconnection)
    try:
        m = cpre.model
        S = region(m, abstract_region(tanks.spec.specification.target, net.composed_state_grid(), "target"))
        store = DirectoryCheckpoints(tmp_path, "k", every=3600.0)
        done = safe(cpre, S, checkpoints=store).iterations
        assert store.written == {"safe": [done]}  # only the converged iterate: the hour never passed
        assert store.resume(m, "safe")[1] == done
        assert DirectoryCheckpoints(tmp_path, "another key").resume(m, "safe") is None
    finally:
        cpre.close()
