"""Safety games on small groups of subsystems: a superset of the maximal controlled invariant to start from.

Issue 24 asks the fixed points to lower their total work. The safety fixed point ``νZ. S ∧ ∃u.CPre(Z)`` of the 10
tanks spends nearly all of its time in its middle iterates (1-3·10^5 BDD nodes, against 3.8·10^3 for the
invariant it converges to): they hold states that every tank's upstream neighbours already rule out, but only
many iterations later. Starting the same iteration from any set ``O`` with ``W ⊆ O ⊆ S`` (``W`` the maximal
invariant) gives the same ``W``: every iterate stays between ``W`` and the iterate started from ``S``. This module
computes such an ``O`` from *local games*.

**Local game.** For a set ``I`` of subsystems and a set ``O ⊇ W`` of composed states, the local game on ``I`` is
the safety game over the states ``x̂_I`` of ``I`` alone

    Y  ↦  Y ∧ ∃x̂_{-I}, û. [adm ∧ O ∧ ∀ŵ ∈ M̂_I(x̂), x̂'_I. (∧_{i∈I} T_i → Y(x̂'_I))]

(``adm`` the admissible pairs of :class:`~.cpre.ControllablePredecessor`, ``M̂_I`` the parts of ``M̂`` for the
internal variables ``I`` reads; for the per-subsystem CPre ``w`` is already inside the ``T̃_i``). The states of
the other subsystems are *angelic*: chosen once per state, inside ``O``. Its greatest fixed point ``Y*`` contains
the projection ``X = ∃x̂_{-I}. W``, so ``O ∧ Y*`` still contains ``W``:

    take ``x̂_I ∈ X``, ``x̂ ∈ W`` extending it and ``û`` an input that keeps ``x̂`` in ``W``; ``x̂ ∈ O`` and
    ``adm(x̂, û)``. For every admissible ``ŵ`` and every ``x̂'_I`` the subsystems of ``I`` allow, every other
    subsystem ``j`` has some successor ``x̂'_j`` (``adm`` contains ``∀ŵ ∈ M̂(x̂). NB_j``), so ``(x̂'_I, x̂'_{-I})``
    is a successor of ``(x̂, û)``, hence in ``W``, and ``x̂'_I ∈ X``. So ``X`` is a post-fixed point of the local
    game's map and lies in its greatest fixed point.

**Groups.** One per subsystem ``i``: ``i`` and the subsystems whose states its relation reads (its upstream
neighbours), at most half the network (a larger group costs nearly what the whole game does) and at most
:data:`MAX_GROUP_BITS` current-state bits (a game's cost grows with its state space; five tanks at spacing 1.25,
35 bits, still cost seconds for all the games of that case). The games run
round after round in network order, each conjoining its ``Y*`` into ``O`` at once (the next game starts from the
tighter ``O``), until a round changes nothing.

**Cost.** Every relation of a local game is conjoined with the projection of ``adm ∧ O`` on the state and input
bits it does not read (as :meth:`~.cpre.ControllablePredecessor.within` does): the bad pairs of a game then range
only over neighbours' states that ``O`` still allows. Without it the game of tank 9 (tanks 6, 8, 9, whose relations
read four more tanks) builds 8·10^4-node bad sets and a round takes about 14 times as long.

On the 10 tanks (safety part of Reach(Safe), one process, same invariant) the bound holds 7.9·10^11 of the safe
set's 2.0·10^12 states (the invariant 1.6·10^11) after 3 rounds of local games, and the fixed point from it takes
about a thirteenth of the time from the safe set (``bench/run.py``'s tanks case prints both). Local groups of two
levels of neighbours bound tighter (1.61·10^11) but cost more than the fixed point they shorten; single
subsystems bound nothing (every tank alone is safe when its neighbours are chosen for it).

**When the bound is used.** Only when it holds at most :data:`USE_BELOW` of ``S``'s states. A bound that removes
little still has many more BDD nodes than ``S`` and makes the first iterates larger: at the tanks' spacing 1.25 it
keeps 92 % of the target in 24,580 nodes, and the first iterations from it take several times as long as from the
target.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from pipelines.symbolic.counting import count_states
from pipelines.symbolic.symbolic_model import Function, and_exists
from pipelines.synthesis.cpre import bad_inputs
from pipelines.synthesis.schedule import Chain, schedule

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from pipelines.synthesis.cpre import ControllablePredecessor

#: Largest share of ``S``'s states a bound may keep and still be started from (module docstring).
USE_BELOW = 0.5
#: Most current-state bits a group may have (module docstring).
MAX_GROUP_BITS = 40


@dataclass(frozen=True)
class LocalGroup:
    """One local game's fixed ingredients: its subsystems (positions in ``model.subsystems``), their chain entries,
    for the shared CPre the parts of ``M̂`` they read and those parts' ``w`` bits (``None``/empty otherwise), the
    members' current-state bits, and every state and input bit the relations and ``M̂`` read."""

    members: tuple[int, ...]
    chain: Chain
    M: Function | None
    w_bits: tuple[str, ...]
    own: frozenset[str]
    support: frozenset[str]


@dataclass
class InvariantBound:
    """What :func:`invariant_bound` found: ``bound`` (``W ⊆ bound ⊆ S``), the share of ``S``'s states it keeps,
    whether to start from it (``start``: the bound if ``used``, else ``S``) and how it got there."""

    bound: Function
    start: Function
    share: float = 1.0
    used: bool = False
    groups: list[tuple[int, ...]] = field(default_factory=list)
    rounds: int = 0
    iterations: int = 0
    seconds: float = 0.0

    def summary(self) -> dict[str, Any]:
        """JSON-ready (no BDDs)."""
        return {"groups": [list(g) for g in self.groups], "rounds": self.rounds, "iterations": self.iterations,
                "seconds": round(self.seconds, 3), "share_of_safe_set": self.share, "used": self.used}


def reading(cpre: ControllablePredecessor) -> tuple[dict[int, tuple[Function, list[str]]], dict[int, set[int]]]:
    """Each subsystem's chain entry (its relation and next-state bits) and the other subsystems whose states it
    reads (its relation's support, and for the shared CPre the parts of ``M̂`` it reads); two empty dicts when the
    chain is not one relation per subsystem (never seen)."""
    m, bdd = cpre.model, cpre.bdd
    subs = m.subsystems
    owner_of_x = {b: k for k, s in enumerate(subs) for b in m.bits_of(m.subsystem_digits(s)["x"])}
    next_bits = [set(m.bits_of(m.subsystem_digits(s)["xn"])) for s in subs]
    owner_of_xn = {b: k for k, bits in enumerate(next_bits) for b in bits}
    entry = {}
    # the chained CPre's chain also holds the parts of M̂ (and quantifies ŵ along it): its games take the relations
    chain = cpre.chain if cpre.method != "chained" else [(t, m.bits_of(m.subsystem_digits(s)["xn"]))
                                                         for s, t in zip(subs, cpre.T)]
    for rel, xn_bits in chain:
        k = owner_of_xn.get(xn_bits[0]) if xn_bits else None
        if k is not None and set(xn_bits) == next_bits[k]:
            entry[k] = (rel, list(xn_bits))
    if len(entry) != len(subs):
        return {}, {}
    reads_of: dict[int, set[int]] = {}
    for k, s in enumerate(subs):
        support = set(bdd.support(entry[k][0]))
        if cpre.M is not None or cpre.method == "chained":  # ŵ shared: k is coupled through the parts it reads
            for j in s.reads:
                support |= set(bdd.support(cpre.parts[j]))
        reads_of[k] = {owner_of_x[b] for b in support if b in owner_of_x} - {k}
    return entry, reads_of


def make_group(cpre: ControllablePredecessor, members: tuple[int, ...],
               entry: dict[int, tuple[Function, list[str]]]) -> LocalGroup:
    """The fixed ingredients of the local game of ``members`` (positions in ``model.subsystems``)."""
    m, bdd = cpre.model, cpre.bdd
    subs = m.subsystems
    xu = frozenset([*m.x_bits, *m.u_bits])
    xn_start = set(m.bits_of([d for i in members for d in m.subsystem_digits(subs[i])["xn"]]))
    chain = schedule([entry[i] for i in members], xn_start, bdd, cpre.chain_order)
    M: Function | None = None
    w_bits: tuple[str, ...] = ()
    read: set[str] = set().union(*(bdd.support(rel) for rel, _ in chain))
    if cpre.M is not None or cpre.method == "chained":
        reads = sorted({j for i in members for j in subs[i].reads})
        M = bdd.true
        for j in reads:
            M &= cpre.parts[j]
        w_bits = tuple(m.bits_of([f"w{j}" for j in reads]))
        read |= set(bdd.support(M))
    own = frozenset(m.bits_of([d for i in members for d in m.subsystem_digits(subs[i])["x"]]))
    return LocalGroup(members, chain, M, w_bits, own, frozenset(read) & xu)


def group_bits(cpre: ControllablePredecessor, members: tuple[int, ...]) -> int:
    """Current-state bits of a group's members."""
    m = cpre.model
    return sum(len(m.bits_of(m.subsystem_digits(m.subsystems[i])["x"])) for i in members)


def local_groups(cpre: ControllablePredecessor) -> list[LocalGroup]:
    """One group per subsystem: it and the subsystems whose state its relation reads (module docstring), groups of
    more than half the network or more than :data:`MAX_GROUP_BITS` state bits left out, repeated groups once, in
    network order."""
    entry, reads_of = reading(cpre)
    if not entry:  # not one relation per subsystem: no local games
        return []
    n = len(cpre.model.subsystems)
    groups: list[LocalGroup] = []
    seen: set[tuple[int, ...]] = set()
    for k in range(n):
        members = tuple(sorted({k} | reads_of[k]))
        if 2 * len(members) > n or group_bits(cpre, members) > MAX_GROUP_BITS or members in seen:
            continue
        seen.add(members)
        groups.append(make_group(cpre, members, entry))
    return groups


def own_projection(cpre: ControllablePredecessor, group: LocalGroup, f: Function) -> Function:
    """``f`` projected on the group's own state bits (the other subsystems' states quantified existentially)."""
    return cpre.bdd.exist([b for b in cpre.model.x_bits if b not in group.own], f)


def game_care(cpre: ControllablePredecessor, group: LocalGroup, within: Function) -> Function:
    """The pairs of the members' states and inputs a local game may use: ``adm ∧ within`` projected on what the
    group reads (some state and input of the others makes them admissible)."""
    m = cpre.model
    return cpre.bdd.exist([b for b in [*m.x_bits, *m.u_bits] if b not in group.support], cpre.admissible & within)


def restricted(cpre: ControllablePredecessor, group: LocalGroup,
               care: Function) -> tuple[list[tuple[Function, list[str]]], Function | None, list[str]]:
    """A local game's chain and ``M̂`` part, each conjoined with the projection of ``care`` on the state and input
    bits it does not read (module docstring, "Cost"), and the bits the game quantifies existentially (the
    members' inputs and the others' states it reads)."""
    m, bdd = cpre.model, cpre.bdd
    xu = [*m.x_bits, *m.u_bits]
    chain = [(rel & bdd.exist([b for b in xu if b not in bdd.support(rel)], care), xn) for rel, xn in group.chain]
    M = group.M
    if M is not None:
        M &= bdd.exist([b for b in xu if b not in bdd.support(M)], care)
    angelic = [b for b in xu if b in group.support and b not in group.own]
    return chain, M, angelic


def local_game(cpre: ControllablePredecessor, group: LocalGroup, bound: Function,
               memo: dict[tuple[int, ...], tuple[Function, Function, Function]] | None = None) -> tuple[Function, int]:
    """The greatest fixed point of the local game of ``group`` inside ``bound`` (``O`` of the module docstring), over
    the current-state bits of its members, and the iterations it took (1: the projection of ``bound`` was one).

    ``memo``: the game's inputs (the admissible pairs and the start, both cut down by ``bound``) and answer from an
    earlier call, by group; a call whose inputs are the same returns that answer (0 iterations). A round after the
    bound changed elsewhere then costs each group two quantifications.
    """
    m = cpre.model
    care = game_care(cpre, group, bound)
    Y = start = own_projection(cpre, group, bound)
    if memo is not None and group.members in memo:
        was_care, was_start, answer = memo[group.members]
        if was_care == care and was_start == start:
            return answer, 0
    chain, M, angelic = restricted(cpre, group, care)
    iterations = 0
    while True:
        bad = bad_inputs(m, chain, M, group.w_bits, Y)
        Yn = Y & and_exists(care, ~bad, angelic)
        iterations += 1
        if Yn == Y:
            if memo is not None:
                memo[group.members] = (care, start, Y)
            return Y, iterations
        Y = Yn


def invariant_bound(
    cpre: ControllablePredecessor, S: Function, progress: Callable[[str], None] | None = None,
) -> InvariantBound:
    """A set ``O`` with ``W ⊆ O ⊆ S`` (``W`` the maximal controlled invariant inside ``S``) from local games, round
    after round until one changes nothing (module docstring), and whether to start from it (at most
    :data:`USE_BELOW` of ``S``'s states). ``S`` itself where the network has no group of at most half its
    subsystems. ``progress(message)``: one line per round."""
    t0 = time.perf_counter()
    groups = local_groups(cpre)
    out = InvariantBound(S, S, groups=[g.members for g in groups])
    bound = S
    memo: dict[tuple[int, ...], tuple[Function, Function, Function]] = {}
    while groups:
        before = bound
        for group in groups:
            Y, iterations = local_game(cpre, group, bound, memo)
            out.iterations += iterations
            bound &= Y
        out.rounds += 1
        if progress is not None:
            progress(f"local games round {out.rounds}: bound of {bound.dag_size:,} BDD nodes")
        if bound == before:
            break
    out.bound = bound
    if bound != S:
        total = count_states(cpre.model, S)
        out.share = count_states(cpre.model, bound) / total if total else 0.0
        out.used = out.share <= USE_BELOW
        out.start = bound if out.used else S
    out.seconds = time.perf_counter() - t0
    return out
