"""The quotient game: the fixed points on blocks of ``2^k`` neighbouring cells per coordinate, a sound controller
for the fine abstraction when its exact fixed points are too large.

Issue 24 asks for the ten tanks at spacing 1.25 (``80^10`` cells) end to end within 12 GB. The exact safety fixed
point of Reach(Safe) there removes about 1 % of the target per iteration while its iterates grow past ``2·10^7``
BDD nodes (docs/benchmarks.md): hours, and more memory than that. This module gives up the *maximal* domain, not
soundness.

**The quotient.** Merge the cells of each state coordinate in blocks of ``2^k`` (the ``k`` lowest bits of its
code; cell codes are plain binary, most significant bit first) and let

    T^q_i = ∃ low(x̂), low(x̂'). T_i          adm^q = ∀ low(x̂). adm          M̂^q_j = ∃ low(x̂). M̂_j

(``T_i`` the chain's relations, ``T̃_i`` or ``T_i``; ``adm`` the admissible pairs of
:class:`~.cpre.ControllablePredecessor`; ``M̂`` the interconnection for the shared CPre). A block's successors are
every block some cell of it reaches, and an input counts at a block only where it is admissible at each of its
cells: the quotient abstraction (the coarse system's abstraction built from the fine one's transitions).

**Why the results are sound.** ``T_i ⊆ T^q_i``, ``M̂_j ⊆ M̂^q_j`` and ``adm^q ⊆ adm``, and the bad pairs
``∃ŵ. M̂ ∧ ∃x̂'.(∧_i T_i ∧ ¬Z')`` only grow with the relations, so for *every* set ``Z``

    CPre^q(Z)  ⊆  CPre(Z).

Every fixed point here is monotone in ``CPre``: the quotient's safety invariant is a controlled invariant of the
fine abstraction (``Z = S ∧ ∃u.CPre^q(Z) ⊆ S ∧ ∃u.CPre(Z)``), its attractors are attractors of the fine one
layer by layer, and so on for reach-avoid and both reach-and-stay forms. Each result's domain is a subset of the
fine abstraction's maximal domain, and an input the quotient's controller allows is one the fine abstraction's
allows (the layered controllers evaluate the *fine* ``CPre`` of each layer at run time, which holds at least the
quotient's inputs). By Theorem 4.2 they refine to the concrete network like any other controller of it.

**What it costs and what it gives** (the tanks at spacing 1.25, one process on a 2-core machine): the quotient of
level 1 (blocks of two cells) solves Reach(Safe) in 4 s (the local games' bound 0.8 s, 25 safety iterations 2.4 s,
10 reach iterations 0.8 s; without the bound 27 safety iterations, 15.5 s, iterates of at most 8.2·10^4 nodes)
where the exact safety fixed point does not converge within 25 iterations, hours and 8.5 GB, its iterates past
2·10^7 nodes. Its invariant holds 14 % of the target and its domain 2.7·10^14 cells; the job runs end to end in
34 s. The maximal domain lies between that and the outer bound of :mod:`~.domain_bound` (reported beside it): the
quotient is an *under*-approximation, and the report says so. Where the grid is not finer than the dynamics need
it gives little or nothing (the tanks at spacing 2.5, level 1: an empty domain).

``k = 0`` is the fine game itself (:func:`quotient` returns ``cpre``).
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

from pipelines.symbolic.counting import count_states
from pipelines.symbolic.symbolic_model import and_exists

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from pipelines.symbolic.symbolic_model import Function, SymbolicModel
    from pipelines.synthesis.cpre import ControllablePredecessor


def merged_bits(model: SymbolicModel, k: int) -> tuple[list[str], list[str]]:
    """The current- and next-state bits that the quotient of level ``k`` forgets: the ``k`` lowest bits of every
    state coordinate (all of a coordinate's bits where it has fewer)."""
    low: list[str] = []
    low_next: list[str] = []
    for x, xn in zip(model.x_digits(), model.xn_digits()):
        bits, bits_next = model.bits[x], model.bits[xn]
        take = min(k, len(bits))
        if take:
            low += bits[-take:]
            low_next += bits_next[-take:]
    return low, low_next


def quotient(cpre: ControllablePredecessor, k: int) -> ControllablePredecessor:
    """The :class:`~.cpre.ControllablePredecessor` of the quotient that merges ``2^k`` neighbouring cells per state
    coordinate (module docstring): the same model, variables and options, its relations, admissible pairs and
    interconnection parts replaced. Its parts (helper processes, the cluster) and its symmetry are its own; close
    it as well as ``cpre``. ``k = 0``: ``cpre`` itself.

    A block that the grid cuts short (a coordinate of 81 cells: the last block holds one code on the grid) stands
    for the cells it has: the relations are cut to the grid's codes before the merged bits are quantified and
    their successors after (the fine relations' successors are on the grid, so this keeps ``T ⊆ T^q``), and an
    input is admissible at a block where it is at each of its cells on the grid. Without it such a block would
    lose every input, and every state leading into it.
    """
    if k < 0:
        raise ValueError(f"the quotient's level must be at least 0, got {k}")
    if k == 0:
        return cpre
    m, bdd = cpre.model, cpre.bdd
    low, low_next = merged_bits(m, k)
    both = low + low_next
    owner = {b: d for d in [*m.x_digits(), *m.xn_digits()] for b in m.bits[d]}
    merged = {owner[b] for b in both}  # the coordinates with merged cells, current and next

    def on_grid(f, next_only=False):  # the grid's codes of the merged coordinates f reads
        digits = sorted({owner[b] for b in bdd.support(f) if b in owner} & merged)
        if next_only:
            digits = [d for d in digits if d.startswith("xn")]
        return m.domain(digits) if digits else bdd.true

    def merge(f):  # f's quotient: cut to the grid, merged bits quantified, successors cut to the grid again
        return bdd.exist(both, f & on_grid(f)) & on_grid(f, next_only=True)

    q = copy.copy(cpre)
    with m.guard(f"building the quotient of level {k}"):
        q.T = [merge(t) for t in cpre.T]
        q.NB = [bdd.forall(low, nb | ~on_grid(nb)) for nb in cpre.NB]
        q.parts = {j: merge(p) for j, p in cpre.parts.items()}
        q.M = None if cpre.M is None else merge(cpre.M)
        q.admissible = m.x_domain & bdd.forall(low, ~m.x_domain | cpre.admissible)
        q.chain = [(merge(rel), list(xn_bits)) for rel, xn_bits in cpre.chain]
    # A copy shares the fine game's parts and symmetry until reset: both are computed from the relations.
    q._pool, q._last_pool, q._pool_error = None, None, None
    q._symmetry = False
    q.level = k
    return q


def increment(model: SymbolicModel, digit: str, other: str) -> Function:
    """``code(other) = code(digit) + 1`` over the two digits' bits (most significant first): some bit of
    ``digit`` is 0 and 1 in ``other``, every lower bit 1 and 0, every higher bit the same."""
    bdd = model.bdd
    a, b = model.bits[digit], model.bits[other]
    out = bdd.false
    for i in range(len(a)):
        term = ~model.var(a[i]) & model.var(b[i])
        for j in range(i + 1, len(a)):
            term &= model.var(a[j]) & ~model.var(b[j])
        for j in range(i):
            term &= _same(model.var(a[j]), model.var(b[j]))
        out |= term
    return out


def _same(p: Function, q: Function) -> Function:
    return (p & q) | (~p & ~q)


def neighbours(model: SymbolicModel) -> list[tuple[Function, list[str]]]:
    """Per state coordinate, ``|code(x_i) - code(x'_i)| <= 1`` with both on the grid, and the next-state bits it
    lets quantify: :func:`dilate`'s chain."""
    out = []
    for x, xn in zip(model.x_digits(), model.xn_digits()):
        same = model.bdd.true
        for a, b in zip(model.bits[x], model.bits[xn]):
            same &= _same(model.var(a), model.var(b))
        near = same | increment(model, x, xn) | increment(model, xn, x)
        out.append((near & model.domain([x, xn]), list(model.bits[xn])))
    return out


def dilate(model: SymbolicModel, chain: list[tuple[Function, list[str]]], Z: Function) -> Function:
    """The states within one cell of ``Z`` in every coordinate (``chain``: :func:`neighbours`)."""
    acc = model.to_next(Z)
    for near, xn_bits in chain:
        acc = and_exists(acc, near, xn_bits)
    return acc


@dataclass
class Refinement:
    """Growing a quotient's safety invariant on the fine game (``fine``), ``rounds`` times at most.

    A round takes the fine safety fixed point inside ``S ∧ dilate(W)``, the safe set cut to the states within one
    cell of the invariant ``W``. ``W`` is a controlled invariant of the fine game inside that set (a quotient's
    invariant is one, and so is each round's result), so the round's greatest fixed point contains it: every round
    gives a controlled invariant of the fine game inside ``S`` at least as large as the last, and the rounds stop
    when one adds nothing. The controller of the grown invariant comes from the fine ``CPre``.

    On the tanks at spacing 1.25 one round from the quotient of level 1 runs 44 iterations (a quarter of an hour on
    two cores) and grows the invariant from 2.08·10^14 to 3.72·10^14 states (+79 %), 4·10^5 BDD nodes.
    """

    fine: ControllablePredecessor
    rounds: int

    def grow(self, W: Function, S: Function,
             progress: Callable[[int, str], None] | None = None) -> tuple[Function, dict[str, Any]]:
        """The grown invariant (``W ⊆ result ⊆ S``) and what each round did (JSON-ready)."""
        m = self.fine.model
        chain = neighbours(m)
        report: dict[str, Any] = {"rounds": [], "states_before": count_states(m, W)}
        iteration = 0
        for k in range(self.rounds):
            t0 = time.perf_counter()
            near = S & dilate(m, chain, W)
            inside = self.fine.within(near)
            Z, iterations = near, 0
            while True:
                Zn = Z & self.fine.predecessors(Z, within=inside)
                iterations += 1
                iteration += 1
                if progress is not None:
                    progress(iteration, f"refinement round {k + 1} iteration {iterations}")
                if Zn == Z:
                    break
                Z = Zn
            grew = Z != W
            W = Z
            report["rounds"].append({"iterations": iterations, "seconds": round(time.perf_counter() - t0, 3),
                                     "states": count_states(m, W), "nodes": W.dag_size})
            if not grew:
                break
        report["states_after"] = count_states(m, W)
        return W, report
