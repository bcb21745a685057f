"""The deterministic finite automaton of an LTLf formula, as a transition table over letters.

A letter is the set of atoms that hold at one instant, written as a bit vector over the formula's atoms
(:attr:`Automaton.atoms`, sorted): bit ``i`` of letter ``σ`` says whether atom ``i`` holds. ``delta[q, σ]`` is the
state after reading ``σ`` in ``q``. A finite trace ``σ_0 … σ_t`` satisfies the formula iff the run from
:attr:`Automaton.initial` ends in an accepting state.

MONA writes its automaton as guarded transitions over its free variables (one ``0``/``1``/``X`` per atom, in its
own order), with one extra first transition out of its state 0 that reads no letter of the trace (the position
that its encoding of LTLf reserves). :func:`from_mona` expands the guards into the table, takes that first
transition as the start, and keeps the states reachable from it.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from pipelines.errors import SpecError

#: The most atoms a formula may use: the table has ``2^atoms`` letters per state.
MAX_ATOMS = 12
#: The default cap on the automaton's states (a spec may lower it; ``options.max_automaton_states``).
MAX_STATES = 1000

_TRANSITION = re.compile(r"^State (\d+): ([01X]*) -> state (\d+)\s*$")


@dataclass(frozen=True)
class Automaton:
    """A complete DFA over the letters of ``atoms``.

    Attributes
    ----------
    atoms : tuple of str
        Bit ``i`` of a letter is atom ``atoms[i]``.
    delta : ndarray of int32, shape (n_states, 2 ** len(atoms))
    initial : int
        The state before the first letter.
    accepting : ndarray of bool, shape (n_states,)
    """

    atoms: tuple[str, ...]
    delta: np.ndarray
    initial: int
    accepting: np.ndarray

    @property
    def n_states(self) -> int:
        return int(self.delta.shape[0])

    @property
    def n_letters(self) -> int:
        return 2 ** len(self.atoms)

    def run(self, letters: Sequence[int] | np.ndarray, start: int | None = None) -> np.ndarray:
        """The states after each letter of a trace (``start``: default :attr:`initial`)."""
        q = self.initial if start is None else int(start)
        out = np.empty(len(letters), dtype=np.int32)
        for t, sigma in enumerate(letters):  # a trace is read letter by letter: each state depends on the last
            q = int(self.delta[q, int(sigma)])
            out[t] = q
        return out

    def accepts(self, letters: Sequence[int] | np.ndarray) -> bool:
        """Whether the non-empty finite trace ``letters`` satisfies the formula."""
        return bool(len(letters)) and bool(self.accepting[self.run(letters)[-1]])

    def to_json(self) -> dict[str, Any]:
        return {"atoms": list(self.atoms), "initial": self.initial,
                "accepting": [int(q) for q in np.flatnonzero(self.accepting)], "delta": self.delta.tolist()}

    @classmethod
    def from_json(cls, data: dict[str, Any]) -> Automaton:
        """An automaton written by :meth:`to_json`, checked (shape, ranges).

        Raises
        ------
        ValueError
        """
        atoms = tuple(str(a) for a in data["atoms"])
        delta = np.asarray(data["delta"], dtype=np.int64)
        n = delta.shape[0] if delta.ndim == 2 else 0
        if delta.ndim != 2 or n == 0 or delta.shape[1] != 2 ** len(atoms) or delta.min() < 0 or delta.max() >= n:
            raise ValueError("the automaton's table is not a complete table over its states and letters")
        initial = int(data["initial"])
        accepting_states = [int(q) for q in data["accepting"]]
        if not 0 <= initial < n or any(not 0 <= q < n for q in accepting_states):
            raise ValueError("the automaton's initial or accepting states are outside its states")
        accepting = np.zeros(n, dtype=bool)
        accepting[accepting_states] = True
        return cls(atoms, delta.astype(np.int32), initial, accepting)

    def summary(self) -> dict[str, Any]:
        return {"states": self.n_states, "atoms": list(self.atoms), "letters": self.n_letters,
                "accepting_states": int(self.accepting.sum())}


def from_mona(text: str, atoms: Sequence[str], max_states: int = MAX_STATES) -> Automaton:
    """The automaton of MONA's answer (``mona -q -u -w``) to a program over ``atoms`` (their MONA names are the
    upper-case atoms, as ``ltlf2dfa`` writes them).

    Raises
    ------
    SpecError
        More than ``max_states`` states (the cap named), more than :data:`MAX_ATOMS` atoms.
    ValueError
        Text that is not a complete MONA automaton.
    """
    atoms = tuple(atoms)
    if len(atoms) > MAX_ATOMS:
        raise SpecError(f"specification.formula: {len(atoms)} atoms; a formula uses at most {MAX_ATOMS}")
    head = re.search(r"DFA for formula with free variables:([^\n]*)\n", text)
    size = re.search(r"Automaton has (\d+) states?", text)
    accept = re.search(r"Accepting states:([^\n]*)\n", text)
    if head is None or size is None or accept is None:
        raise ValueError("not a MONA automaton (no header)")
    n = int(size.group(1))
    if n - 1 > max_states:  # MONA's state 0 is dropped below
        raise SpecError(f"specification.formula: its automaton has {n - 1} states, over the cap of {max_states} "
                        "(options.max_automaton_states)")
    by_name = {a.upper(): i for i, a in enumerate(atoms)}
    free = head.group(1).split()
    unknown = [v for v in free if v not in by_name]
    if unknown:
        raise ValueError(f"MONA's automaton has variables {unknown} that are no atom")
    bit_of = [by_name[v] for v in free]
    k = len(atoms)
    letters = np.arange(2**k, dtype=np.int64)
    delta = np.full((n, 2**k), -1, dtype=np.int64)
    for line in text.splitlines():
        m = _TRANSITION.match(line.strip())
        if m is None:
            continue
        src, guard, dst = int(m.group(1)), m.group(2), int(m.group(3))
        if len(guard) != len(free) or not (0 <= src < n and 0 <= dst < n):
            raise ValueError(f"MONA transition {line.strip()!r} does not fit its automaton")
        match = np.ones(2**k, dtype=bool)
        for pos, value in enumerate(guard):
            if value != "X":
                match &= ((letters >> bit_of[pos]) & 1) == int(value)
        delta[src, match] = dst
    if (delta < 0).any():
        raise ValueError("MONA's automaton is not complete")
    first = np.unique(delta[0])
    if first.size != 1:
        raise ValueError("MONA's first transition depends on a letter")
    accepting = np.zeros(n, dtype=bool)
    accepting[[int(q) for q in accept.group(1).split()]] = True
    return _reachable(atoms, delta, int(first[0]), accepting)


def _reachable(atoms: tuple[str, ...], delta: np.ndarray, initial: int, accepting: np.ndarray) -> Automaton:
    """The automaton restricted to the states reachable from ``initial``, renumbered in order of discovery."""
    order = [initial]
    index = {initial: 0}
    i = 0
    while i < len(order):  # states, not cells: a handful
        for q in np.unique(delta[order[i]]).tolist():
            if q not in index:
                index[q] = len(order)
                order.append(q)
        i += 1
    renumber = np.full(delta.shape[0], -1, dtype=np.int64)
    renumber[order] = np.arange(len(order))
    return Automaton(atoms, renumber[delta[order]].astype(np.int32), 0, accepting[order].copy())
