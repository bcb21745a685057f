"""LTLf formulas (pipelines/temporal) and their automata (MONA, workers/automata.py): every random formula's
automaton accepts exactly the finite traces that an evaluator written from the semantics accepts; bad formulas get
one clear error naming the token and its position, the operator, the atom or the cap.
"""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from pipelines.errors import SpecError
from pipelines.temporal.automaton import Automaton, from_mona
from pipelines.temporal.formula import check_region_name, parse_formula
from workers.automata import translate

ATOMS = ("a", "b", "o")


# ============================================================================ the semantics, written out
def holds(f, trace: list[set[str]], i: int) -> bool:
    """Whether ``f`` (``ltlf2dfa``'s tree) holds at instant ``i`` of the finite ``trace`` (LTLf: strong next, F and
    G over the instants left)."""
    name, n = type(f).__name__, len(trace)
    if name == "LTLfTrue":
        return True
    if name == "LTLfFalse":
        return False
    if name == "LTLfAtomic":
        return str(f.s) in trace[i]
    if name == "LTLfNot":
        return not holds(f.f, trace, i)
    if name == "LTLfNext":
        return i + 1 < n and holds(f.f, trace, i + 1)
    if name == "LTLfEventually":
        return any(holds(f.f, trace, j) for j in range(i, n))
    if name == "LTLfAlways":
        return all(holds(f.f, trace, j) for j in range(i, n))
    parts = list(f.formulas)
    if name == "LTLfAnd":
        return all(holds(g, trace, i) for g in parts)
    if name == "LTLfOr":
        return any(holds(g, trace, i) for g in parts)
    if name == "LTLfImplies":  # right-associative: a -> b -> c is a -> (b -> c)
        value = holds(parts[-1], trace, i)
        for g in reversed(parts[:-1]):
            value = (not holds(g, trace, i)) or value
        return value
    if name == "LTLfEquivalence":
        values = [holds(g, trace, i) for g in parts]
        return all(v == values[0] for v in values)
    if name == "LTLfUntil":  # right-associative
        def until(k: int, at: int) -> bool:
            if k == len(parts) - 1:
                return holds(parts[k], trace, at)
            return any(until(k + 1, j) and all(holds(parts[k], trace, m) for m in range(at, j)) for j in range(at, n))
        return until(0, i)
    raise AssertionError(name)


def random_formula(rng: np.random.Generator, depth: int) -> str:
    if depth == 0 or rng.random() < 0.25:
        return str(rng.choice(list(ATOMS) + ["true", "false"], p=[0.3, 0.3, 0.3, 0.05, 0.05]))
    op = rng.choice(["!", "X", "F", "G", "&", "|", "->", "U", "<->"])
    if op in ("!", "X", "F", "G"):
        return f"{op}({random_formula(rng, depth - 1)})"
    return f"({random_formula(rng, depth - 1)} {op} {random_formula(rng, depth - 1)})"


def letter(atoms: tuple[str, ...], now: set[str]) -> int:
    return sum(1 << i for i, a in enumerate(atoms) if a in now)


@pytest.mark.parametrize("seed", range(6))
def test_the_automaton_accepts_exactly_the_traces_that_satisfy_the_formula(seed):
    rng = np.random.default_rng(seed)
    checked = 0
    for _ in range(10):
        f = parse_formula(random_formula(rng, 3), ATOMS)
        automaton = translate(f)
        for length in range(1, 5):
            for trace in itertools.islice(itertools.product(range(8), repeat=length), 0, None,
                                          max(1, 8**length // 60)):
                now = [{a for k, a in enumerate(ATOMS) if (s >> k) & 1} for s in trace]
                assert automaton.accepts([letter(f.atoms, t) for t in now]) == holds(f.tree, now, 0), (f.text, now)
                checked += 1
    assert checked > 1000


def test_a_sequencing_task_is_a_small_automaton():
    f = parse_formula("F(a & F b) & G !o", ATOMS)
    automaton = translate(f)
    assert f.atoms == ("a", "b", "o") and automaton.n_states == 4 and automaton.accepting.sum() == 1
    a, b, o = 1, 2, 4
    assert automaton.accepts([0, a, 0, b]) and automaton.accepts([a | b])
    assert not automaton.accepts([b, a]) and not automaton.accepts([a, o, b])


@pytest.mark.parametrize(("text", "message"), [
    ("F(a & ", "the formula ends too early: F(a & ⟨here⟩"),
    ("F A", "unexpected 'A' at position 3: F ⟨here⟩A"),
    ("a & (b | ) ", "unexpected ')' at position 10"),
    ("a R b", "'R' (release) is outside the supported fragment"),
    ("WX a", "'WX' (weak next) is outside the supported fragment"),
    ("F last", "'last' is outside the supported fragment"),
    ("F c", "atom 'c' names no region (the regions are: a, b, o)"),
    ("  ", "an empty formula"),
    ("F a" + " & F a" * 500, "characters; a formula has at most 2000"),
])
def test_a_bad_formula_is_one_clear_error(text, message):
    with pytest.raises(SpecError) as e:
        parse_formula(text, ATOMS)
    assert message in str(e.value) and str(e.value).startswith("specification.formula: ")


@pytest.mark.parametrize("name", ["A", "1a", "goal-1", "true", "last", "a b", ""])
def test_a_region_that_cannot_be_an_atom_is_refused(name):
    with pytest.raises(SpecError, match="cannot be an atom of a formula"):
        check_region_name(name, "specification.regions")


def test_the_state_cap_is_named():
    f = parse_formula("X X X X X a", ATOMS)
    with pytest.raises(SpecError, match="over the cap of 3 .options.max_automaton_states."):
        translate(f, max_states=3)
    assert translate(f, max_states=10).n_states <= 10


def test_damaged_mona_output_is_refused():
    good = "DFA for formula with free variables: A \nAccepting states: 1 \nAutomaton has 2 states\n" \
           "State 0: X -> state 1\nState 1: X -> state 1\n"
    assert from_mona(good, ("a",)).n_states == 1
    for bad in (good.replace("State 1: X -> state 1\n", ""), good.replace("state 1\nState 1", "state 7\nState 1"),
                "nothing", good.replace("A \n", "Q \n")):
        with pytest.raises(ValueError):
            from_mona(bad, ("a",))


def test_an_automaton_round_trips_through_json_and_a_damaged_one_is_refused():
    automaton = translate(parse_formula("a U b", ATOMS))
    again = Automaton.from_json(automaton.to_json())
    assert again.atoms == automaton.atoms and np.array_equal(again.delta, automaton.delta)
    assert np.array_equal(again.accepting, automaton.accepting) and again.initial == automaton.initial
    for damage in ({"initial": 99}, {"accepting": [5]}, {"delta": [[0, 1]]}, {"delta": [[0, 0, 0, 9]] * 3}):
        with pytest.raises(ValueError):
            Automaton.from_json({**automaton.to_json(), **damage})
