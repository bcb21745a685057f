"""An outer bound of a specification's domain from the network's upstream-closed groups, in seconds.

Issue 24 asks whether the paper's initial state of the tanks is in the domain at spacing 1.25, where the fixed
point takes hours. The answer does not need the fixed point when the state is *outside*: a set of subsystems
that reads no state outside itself (an **upstream-closed group** ``I``: tanks 4, 5 and 7 of the cascade) is a
game of its own, and the domain's projection on ``I`` lies in that game's winning set.

**Why.** Let ``D`` be the winning domain of ``◇□φ`` (``□S ∧ ◇□φ`` with a safe set) on the whole network, ``φ``
a union of boxes and ``I`` upstream-closed: the relations of ``I``'s members and the parts of ``M̂`` they read
depend on ``x̂_I`` and ``û_I`` only, and the successors of the members are chosen independently of the others'
(the CPre's successor set is a product over subsystems). Take ``x̂ ∈ D`` with a winning strategy and fix any
resolution of the other subsystems' successors (a function of the history): the others' states are then a
function of ``I``'s history, so the strategy becomes one of ``I``'s game (with memory) under which every run of
``I`` stays, from some step on, in the projection ``φ_I = ∃x̂_{-I}. φ`` (and always in ``S_I``). The winning
set of ``◇□φ_I`` in ``I``'s game, for any strategy with memory, is ``Reach_I(Safe_I(φ_I))`` (co-Büchi games are
won by memoryless strategies, and their winning set is the attractor of the safety game's: docs/method.md §6). So
``x̂_I ∈ Reach_I(Safe_I(φ_I))`` for every ``x̂ ∈ D``. The two fixed points of ``I``'s game run over ``I``'s own
state bits: the tanks' groups of three and four tanks take under two seconds at spacing 1.25.

The bound is the conjunction of those sets over the upstream-closed groups other than the whole network (none
for a network whose subsystems all read each other, such as consensus). It is an *outer* bound: a state inside
it may still be outside ``D``; a state outside it is certainly outside, and :meth:`DomainBound.ruled_out_by`
names the group that rules it out. :func:`domain_bound` computes it, and makes the same argument for the other
kinds (safety, reachability, reach-avoid).
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from pipelines.symbolic.symbolic_model import Function, and_exists
from pipelines.synthesis.cpre import bad_inputs
from pipelines.synthesis.local_games import (
    MAX_GROUP_BITS,
    LocalGroup,
    game_care,
    group_bits,
    local_game,
    make_group,
    own_projection,
    reading,
    restricted,
)

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from pipelines.synthesis.cpre import ControllablePredecessor


@dataclass
class DomainBound:
    """What :func:`domain_bound` found: ``bound`` (``D ⊆ bound``), per group its members and the local
    ``Reach(Safe)`` over the members' state bits, and the time it took."""

    bound: Function
    groups: list[tuple[int, ...]] = field(default_factory=list)
    winning: list[Function] = field(default_factory=list)
    seconds: float = 0.0

    def ruled_out_by(self, state: Function) -> tuple[int, ...] | None:
        """The first group whose local game cannot win from ``state`` (a set of states; ``None``: none can be
        ruled out, the state may be in the domain)."""
        for members, won in zip(self.groups, self.winning):
            if state & won == state.bdd.false:
                return members
        return None

    def summary(self) -> dict[str, Any]:
        """JSON-ready (no BDDs)."""
        return {"groups": [list(g) for g in self.groups], "seconds": round(self.seconds, 3)}


def upstream_closed(reads_of: dict[int, set[int]]) -> list[tuple[int, ...]]:
    """Each subsystem with everything it reads, directly or through others (its upstream closure), once each,
    smallest first; the whole network left out."""
    n = len(reads_of)
    out: set[tuple[int, ...]] = set()
    for k in range(n):
        closure, todo = {k}, [k]
        while todo:
            for j in reads_of[todo.pop()]:
                if j not in closure:
                    closure.add(j)
                    todo.append(j)
        if len(closure) < n:
            out.add(tuple(sorted(closure)))
    return sorted(out, key=lambda g: (len(g), g))


def local_reach(cpre: ControllablePredecessor, group: LocalGroup, start: Function, keep: Function) -> Function:
    """``μY. start ∨ (keep_I ∧ ∃û. CPre_I(Y))`` in ``group``'s own game, over its members' current-state bits:
    the attractor of ``start`` while staying in the projection of ``keep`` (the state space, or the safe set).
    Inputs count where some state of the others makes them admissible (an over-approximation of what the whole
    network allows, as a bound needs)."""
    m = cpre.model
    care = game_care(cpre, group, keep)
    keep_I = own_projection(cpre, group, keep)
    chain, M, angelic = restricted(cpre, group, care)
    Y = start
    while True:
        bad = bad_inputs(m, chain, M, group.w_bits, Y)
        Yn = Y | (keep_I & and_exists(care, ~bad, angelic))
        if Yn == Y:
            return Y
        Y = Yn


#: The specification kinds :func:`domain_bound` bounds, and what each group's game is.
KINDS = ("safe", "reach", "reach_avoid", "reach_and_stay")


def domain_bound(cpre: ControllablePredecessor, kind: str, region: Function, *, safe: Function | None = None,
                 avoid: Function | None = None) -> DomainBound:
    """An outer bound of the domain of any specification kind, from the upstream-closed groups (module docstring;
    the argument is the same for each, the projection of a run winning the whole game winning the group's):

    * ``safe`` (``region`` the safe set ``S``): the group's ``Safe_I(S_I)``;
    * ``reach``, ``reach_avoid`` (``region`` the target ``T``; ``safe``, ``avoid`` optional): the group's
      attractor of ``T_I`` while staying in the projection of ``S ∧ ¬A`` (a run that never enters ``A`` has a
      projection that never leaves the projection of ``¬A``);
    * ``reach_and_stay`` (``region`` ``φ``): ``Reach_I(Safe_I(φ_I))`` inside the projection of ``S``.
    """
    if kind not in KINDS:
        raise ValueError(f"no domain bound for a {kind!r} specification (one of {', '.join(KINDS)})")
    t0 = time.perf_counter()
    m = cpre.model
    keep = m.x_domain
    if safe is not None:
        keep &= safe
    if avoid is not None:
        keep &= ~avoid
    out = DomainBound(bound=m.bdd.true)
    entry, reads_of = reading(cpre)
    if not entry:
        return out
    for members in upstream_closed(reads_of):
        if group_bits(cpre, members) > MAX_GROUP_BITS:
            continue
        group = make_group(cpre, members, entry)
        if kind == "safe":
            won, _ = local_game(cpre, group, region & keep)
        elif kind == "reach_and_stay":
            invariant, _ = local_game(cpre, group, region & keep)
            won = local_reach(cpre, group, invariant, keep)
        else:
            start = own_projection(cpre, group, region & keep)
            won = local_reach(cpre, group, start, keep)
        out.groups.append(members)
        out.winning.append(won)
        out.bound &= won
    out.seconds = time.perf_counter() - t0
    return out
