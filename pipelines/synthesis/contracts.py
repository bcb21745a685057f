"""Reach-and-stay by assume-guarantee contracts: one small game per subsystem, a chain of shrinking boxes
(docs/method.md §6, "Contracts").

The exact fixed points solve one game over the composed state. Where subsystems share internal variables around a
cycle (a ring of rooms each reading both neighbours) their iterates stop being products long before they converge,
and every ``CPre`` then builds a product over all states, inputs and open ``ŵ``: the ring of six rooms at spacing
0.1 does not finish. Contracts solve, for each subsystem alone, a game whose environment is the cells of the
subsystems it reads, *assumed* to lie in a given set, and chain such games so that each guarantees what the next
assumes. Every game is over one subsystem's states, so the cost grows with the number of subsystems, not with
the product of their sizes. The domain is a product of per-subsystem sets inside the exact game's domain: sound,
not maximal.

**Local game.** For subsystem ``i`` with the relation ``T̃_i(x̂_R, x̂_i, û_i, x̂'_i) = ∃ŵ_i. M̂_i ∧ T_i`` (``R`` the
subsystems whose states its internal inputs are computed from; each reader sees its own ``ŵ``, as the
``per_reader`` CPre) and admissible pairs ``adm_i`` (``M̂_i(x̂) ≠ ∅`` and no admissible ``ŵ_i`` blocks), a set
``Y`` of its own cells and an assumption ``A = ∏_{j∈R} B_j`` on the others,

    pre_i(Y)(x̂_i) = ∀x̂_R ∈ A. ∃û_i. adm_i ∧ ∀x̂'_i. T̃_i → Y(x̂'_i).

The input may depend on the neighbours' cells (the composed controller sees the whole state); the neighbours'
next cells are not the local game's business, the contract is. ``Inv_i(K, A) = νY. K ∧ pre_i(Y)`` and
``Reach_i(C, K, A) = μY. C ∨ (K ∧ pre_i(Y))``.

**Chain of contracts.** Let ``S = ∏ S_i`` and ``φ = ∏ φ_i`` be the safe set and the target (both must be products of
per-subsystem sets).

1. Safety contract: ``B_i ← Inv_i(B_i, ∏_{j∈R_i} B_j)`` from ``B = S``, for every ``i`` in turn until nothing
   changes; this is ``B^0``. Induction on time: if every subsystem is in ``B^0`` now, each local controller keeps
   its own in ``B^0`` whatever its neighbours do inside ``B^0``.
2. Level ``k`` (all subsystems in ``B^k``): each subsystem ``i`` takes the smallest ``d`` for which
   ``C_i = Inv_i(φ_i^{+d} ∩ B^k_i, A(B^k))`` (``φ_i^{+d}``: the cells within ``d`` cells of ``φ_i`` along every axis)
   is reached from all of ``B^k_i`` inside ``B^k_i`` under ``A(B^k)``; ``B^{k+1} = ∏ C_i``. A subsystem that cannot
   shrink keeps ``C_i = B^k_i``. The chain ends when ``B^{k+1} ⊆ φ`` (won) or no subsystem shrinks (lost: an empty
   domain). At level 0 the basin may be smaller than ``B^0_i``; the domain is the product of those basins.
3. The controller at a composed state of level ``k`` (in ``B^k``, not in ``B^{k+1}``) gives each subsystem the input
   of its level-``k`` game: the reach layers outside ``C_i``, the invariance of ``C_i`` inside it; at the last level
   the invariance of ``B^K_i``.

Why it wins: at level ``k`` every subsystem stays in ``B^k_i`` (the reach game keeps it there) so every assumption
holds, each subsystem reaches ``C_i`` within its number of layers and stays (``C_i`` is invariant under
``A(B^k)``), so the level rises within finitely many steps and never falls (``B^{k+1} ⊆ B^k``), until the last
level, inside ``φ`` and ``S``, is kept forever. No level assumes what a later level guarantees, so the liveness
argument is not circular.

The rooms ring reads its neighbours at 18 C while holding 19.5 C: no room can hold the comfort band while its
neighbours may be anywhere in the safe set (the heater's equilibrium with both neighbours at 18 C is 19.42 C), but
every room can reach and hold a band a few cells wider, and once all have, the band itself.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from pipelines.errors import CompabsError
from pipelines.symbolic.counting import count_states, enumerate_cells
from pipelines.symbolic.relations import state_set
from pipelines.symbolic.symbolic_model import Function, SymbolicModel, and_exists
from pipelines.synthesis.fixed_points import SynthesisResult, peak_live_nodes

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from pipelines.synthesis.cpre import ControllablePredecessor


class NotAProduct(CompabsError):
    """A specification set is not the product of per-subsystem sets, which contracts need; the message says
    which set and where to change it."""


@dataclass
class LocalGame:
    """Subsystem ``index``'s game (module docstring): its relation with ``ŵ`` quantified, its admissible pairs, the
    bits of its own current and next states and inputs, and the current-state bits of the subsystems it reads."""

    index: int
    model: SymbolicModel
    t_tilde: Function
    admissible: Function
    x_digits: list[str]
    x_bits: list[str]
    xn_bits: list[str]
    u_bits: list[str]
    reads: tuple[int, ...]
    read_bits: list[str]
    #: ``(r, renaming)`` where this game is subsystem ``r``'s with its bits renamed (:func:`_correspondence`)
    image_of: tuple[int, dict[str, str]] | None = None

    def good(self, Y: Function) -> Function:
        """``adm_i ∧ ∀x̂'_i. T̃_i → Y'``: the pairs (neighbours' cells, own cell, input) that keep ``i`` in ``Y``."""
        bad = and_exists(self.t_tilde, ~self.model.to_next(Y), self.xn_bits)
        return self.admissible & ~bad

    def pre(self, Y: Function, keep: Function, A: Function) -> Function:
        """``keep ∧ ∀x̂_R ∈ A. ∃û_i. good(Y)`` over ``i``'s own bits."""
        bdd = self.model.bdd
        some = bdd.exist(self.u_bits, self.good(Y))
        return keep & ~and_exists(A, ~some, self.read_bits)

    def invariant(self, keep: Function, A: Function) -> Function:
        """``Inv_i(keep, A)``."""
        Y = keep
        while True:
            nxt = self.pre(Y, keep, A)
            if nxt == Y:
                return Y
            Y = nxt

    def reach(self, C: Function, keep: Function, A: Function) -> list[Function]:
        """The layers of ``Reach_i(C, keep, A)``: ``layers[0] = C``, each the previous one and its predecessors."""
        layers = [C]
        while True:
            nxt = layers[-1] | self.pre(layers[-1], keep, A)
            if nxt == layers[-1]:
                return layers
            layers.append(nxt)


def local_games(cpre: ControllablePredecessor) -> list[LocalGame]:
    """One :class:`LocalGame` per subsystem from the relations, non-blocking sets and interconnection parts of
    ``cpre`` (any CPre method: the per-reader relations are built here). A subsystem identical to an earlier one
    whose neighbours correspond as well (:func:`_correspondence`: the rooms of a ring, the cars of a platoon) gets
    that one's game renamed, which costs a fraction of building it (a ring of 100 rooms: one build)."""
    m, bdd = cpre.model, cpre.bdd
    own = {b: i for i, s in enumerate(m.subsystems) for b in m.bits_of(m.subsystem_digits(s)["x"])}
    games: list[LocalGame] = []
    first: dict[str, int] = {}
    for i, (s, t, nb) in enumerate(zip(m.subsystems, cpre.T, cpre.NB)):
        dg = m.subsystem_digits(s)
        rep = first.setdefault(s.key, i)
        ren = _correspondence(cpre, own, rep, i) if rep != i else None
        if ren is not None:
            g = games[rep]
            t_tilde, adm = bdd.let(ren, g.t_tilde), bdd.let(ren, g.admissible)
        else:
            Mi, wb = cpre.read_part(s)
            t_tilde = and_exists(Mi, t, wb)
            adm = bdd.exist(wb, Mi) & ~and_exists(Mi, ~nb, wb) & m.domain(dg["u"])
        support = bdd.support(t_tilde) | bdd.support(adm)
        reads = tuple(sorted({own[b] for b in support if b in own} - {i}))
        read_bits = [b for j in reads for b in m.bits_of(m.subsystem_digits(m.subsystems[j])["x"])]
        games.append(LocalGame(i, m, t_tilde, adm, dg["x"], m.bits_of(dg["x"]), m.bits_of(dg["xn"]),
                               m.bits_of(dg["u"]), reads, read_bits, None if ren is None else (rep, ren)))
    return games


def _correspondence(cpre: ControllablePredecessor, own: dict[str, int], a: int, b: int) -> dict[str, str] | None:
    """The renaming of bits that maps subsystem ``a``'s local game onto ``b``'s, or ``None``.

    Identical subsystems (one key) have relations that are renamings of each other; their local games are too when
    every internal variable ``b`` reads is computed from one subsystem, as the matching one of ``a`` is, by the
    same relation up to renaming (checked: ``M̂`` parts, ``T`` and ``NB``, each a BDD comparison).
    """
    m, bdd = cpre.model, cpre.bdd
    sa, sb = m.subsystems[a], m.subsystems[b]
    if len(sa.reads) != len(sb.reads):
        return None
    sigma = {a: b}
    for ja, jb in zip(sa.reads, sb.reads):
        pa = {own[x] for x in bdd.support(cpre.parts[ja]) if x in own}
        pb = {own[x] for x in bdd.support(cpre.parts[jb]) if x in own}
        if len(pa) != 1 or len(pb) != 1:
            return None
        p, q = pa.pop(), pb.pop()
        if sigma.setdefault(p, q) != q:
            return None
    if len(set(sigma.values())) != len(sigma):
        return None
    ren: dict[str, str] = {}

    def pair(da: list[str], db: list[str]) -> None:
        for x, y in zip(m.bits_of(da), m.bits_of(db)):
            if x != y:
                ren[x] = y

    for p, q in sigma.items():
        dp, dq = m.subsystem_digits(m.subsystems[p]), m.subsystem_digits(m.subsystems[q])
        if len(m.bits_of(dp["x"])) != len(m.bits_of(dq["x"])):
            return None
        pair(dp["x"], dq["x"])
        pair(dp["xn"], dq["xn"])
    pair(m.subsystem_digits(sa)["u"], m.subsystem_digits(sb)["u"])
    pair([f"w{j}" for j in sa.reads], [f"w{j}" for j in sb.reads])
    same = all(bdd.let(ren, cpre.parts[ja]) == cpre.parts[jb] for ja, jb in zip(sa.reads, sb.reads))
    if not same or bdd.let(ren, cpre.T[a]) != cpre.T[b] or bdd.let(ren, cpre.NB[a]) != cpre.NB[b]:
        return None
    return ren


def factors(model: SymbolicModel, games: Sequence[LocalGame], f: Function, name: str) -> list[Function]:
    """``f`` as the product of its projections on the subsystems' states; :class:`NotAProduct` if it is not one."""
    bdd = model.bdd
    out = []
    product = bdd.true
    for g in games:
        own = set(g.x_bits)
        p = bdd.exist([b for b in model.x_bits if b not in own], f)
        out.append(p)
        product &= p
    if product != f:
        raise NotAProduct(f"specification.{name}: contracts need a set that is a product of one set per subsystem "
                          "(one box, or boxes that differ in one subsystem's coordinates only); leave contracts out "
                          "of options.fixed_points for this one")
    return out


def _cells(model: SymbolicModel, g: LocalGame, f: Function) -> np.ndarray:
    """Subsystem ``g``'s cells in ``f`` (over its own bits) as a boolean array of its grid's shape."""
    shape = tuple(model.sizes[d] for d in g.x_digits)
    mask = np.zeros(shape, dtype=bool)
    cells = enumerate_cells(model, f, g.x_digits)
    if len(cells):
        mask[tuple(cells.T)] = True
    return mask


def _set(model: SymbolicModel, g: LocalGame, mask: np.ndarray) -> Function:
    """The inverse of :func:`_cells`."""
    return state_set(model, np.argwhere(mask), g.x_digits)


def _inflated(mask: np.ndarray, d: int) -> np.ndarray:
    """Cells within ``d`` cells of ``mask`` along every axis (Chebyshev distance in cells)."""
    out = mask.copy()
    for axis in range(mask.ndim):
        grown = out.copy()
        for step in range(1, min(d, mask.shape[axis] - 1) + 1):
            lo = [slice(None)] * mask.ndim
            hi = [slice(None)] * mask.ndim
            lo[axis], hi[axis] = slice(step, None), slice(None, -step)
            grown[tuple(lo)] |= out[tuple(hi)]
            grown[tuple(hi)] |= out[tuple(lo)]
        out = grown
    return out


@dataclass
class Level:
    """One level of the chain: the boxes ``B`` all subsystems are in, per subsystem the set ``C_i`` it reaches and
    holds, its reach layers (``layers[0] = C_i``) and the inflation ``d`` it took."""

    B: list[Function]
    C: list[Function]
    layers: list[list[Function]]
    inflation: list[int]
    #: per subsystem, the one whose link it took renamed (``None``: its own game was solved)
    shared: list[int | None]


class ContractResult:
    """What :func:`chain` found: the levels (none if lost), the domain's factors, and a JSON-ready account."""

    def __init__(self, games: list[LocalGame], levels: list[Level], domain_factors: list[Function],
                 details: dict[str, Any]) -> None:
        self.games, self.levels, self.domain_factors, self.details = games, levels, domain_factors, details

    @property
    def steps(self) -> int:
        """A bound on the steps from the domain into the last level's sets: every level's longest reach."""
        return sum(max(len(layers) for layers in level.layers) for level in self.levels)


def _assumption(model: SymbolicModel, g: LocalGame, B: Sequence[Function]) -> Function:
    A = model.bdd.true
    for j in g.reads:
        A &= B[j]
    return A


def _shrink(model: SymbolicModel, g: LocalGame, B: Sequence[Function], phi: Function, first: bool
            ) -> tuple[Function, list[Function], int]:
    """Subsystem ``g``'s link at one level (module docstring, step 2): ``C_i``, its reach layers and the inflation.

    Both ``C_i`` and its basin grow with the inflation ``d``, so bisections find the smallest ``d`` whose basin is
    the goal: all of ``B_i``, or at level 0 (``first``) the basin of the widest ``C_i`` short of ``B_i`` itself (the
    domain may shrink there: a cell its neighbours can hold down forever is not in it). A ``d`` as wide as the grid
    gives ``C_i = B_i``: no progress, but a subsystem already held.
    """
    keep = B[g.index]
    A = _assumption(model, g, B)
    b_mask = _cells(model, g, keep)
    phi_mask = _cells(model, g, phi) & b_mask
    d_max = max(b_mask.shape)
    tried: dict[int, tuple[Function, list[Function]]] = {}

    def attempt(d: int) -> tuple[Function, list[Function]]:
        if d not in tried:
            start = _set(model, g, _inflated(phi_mask, d) & b_mask) if d < d_max else keep
            inv = g.invariant(start, A)
            tried[d] = (inv, g.reach(inv, keep, A) if inv != model.bdd.false else [inv])
        return tried[d]

    def smallest(lo: int, hi: int, holds: Callable[[int], bool]) -> int:
        while lo < hi:
            mid = (lo + hi) // 2
            lo, hi = (lo, mid) if holds(mid) else (mid + 1, hi)
        return lo

    goal = keep
    if first:
        whole = smallest(0, d_max, lambda d: attempt(d)[0] == keep)
        if whole > 0:
            goal = attempt(whole - 1)[1][-1]
    d = smallest(0, d_max, lambda d: attempt(d)[1][-1] == goal)
    return attempt(d)[0], attempt(d)[1], d


def _level(model: SymbolicModel, games: Sequence[LocalGame], B: list[Function], phi: list[Function],
           first: bool) -> Level:
    """Level ``k`` of the chain from the boxes ``B`` (module docstring, step 2). A game that is another's renamed,
    in a situation that is that one's renamed (its own set, its assumption and its target), takes that one's link
    renamed."""
    bdd = model.bdd
    links: list[tuple[Function, list[Function], int]] = []
    shared: list[int | None] = []
    for g in games:
        if g.image_of is not None:
            r, ren = g.image_of
            rep = games[r]
            if (bdd.let(ren, B[r]) == B[g.index] and bdd.let(ren, phi[r]) == phi[g.index]
                    and bdd.let(ren, _assumption(model, rep, B)) == _assumption(model, g, B)):
                C, layers, d = links[r]
                links.append((bdd.let(ren, C), [bdd.let(ren, f) for f in layers], d))
                shared.append(r)
                continue
        links.append(_shrink(model, g, B, phi[g.index], first))
        shared.append(None)
    return Level(list(B), [c for c, _, _ in links], [lay for _, lay, _ in links], [d for _, _, d in links],
                 shared)


def _unread_defined(cpre: ControllablePredecessor, games: Sequence[LocalGame], B: Sequence[Function]) -> None:
    """Refuse a safe set on which an internal variable that no subsystem reads has no cell (``M̂(x̂) = ∅``: the
    exact game loses there, and no local game sees it)."""
    m = cpre.model
    read = {j for s in m.subsystems for j in s.reads}
    box = m.bdd.true
    for b in B:
        box &= b
    for j, part in cpre.parts.items():
        if j not in read and (box & ~m.bdd.exist(m.bits[f"w{j}"], part)) != m.bdd.false:
            raise CompabsError(f"contracts: the internal variable w{j}, which no subsystem reads, has no cell at some "
                               "states of the safe set (its interconnection map leaves the internal grid there); "
                               "widen options.interconnection.internal or use the exact fixed points")


def chain(
    cpre: ControllablePredecessor, target: Function | None, safe: Function | None = None,
    progress: Callable[[int, str], None] | None = None, max_levels: int = 64,
) -> ContractResult:
    """``□S ∧ ◇□φ`` by a chain of contracts (module docstring, steps 1-2): the levels and the domain. Without a
    target, ``□S``: the safety contract alone, one level whose sets are held."""
    t0 = time.perf_counter()
    m = cpre.model
    games = local_games(cpre)
    phi = None if target is None else factors(m, games, target & m.x_domain, "target")
    B = factors(m, games, (m.x_domain if safe is None else safe & m.x_domain), "safe")
    rounds, changed = 0, True
    while changed:  # step 1, the safety contract
        changed, rounds = False, rounds + 1
        for g in games:
            inv = g.invariant(B[g.index], _assumption(m, g, B))
            if inv != B[g.index]:
                B[g.index], changed = inv, True
    if progress is not None:
        progress(rounds, f"contracts: safety contract in {rounds} rounds, {_sizes(m, games, B)}")
    levels: list[Level] = []
    empty = [m.bdd.false] * len(games)
    outcome = "won"
    lost = [m.subsystems[i].name or str(i) for i, b in enumerate(B) if b == m.bdd.false]
    if lost:
        outcome = (f"no safety contract: {_named(lost)} cannot stay safe while its neighbours roam their safe "
                   "sets")
    else:
        _unread_defined(cpre, games, B)
    if phi is None and outcome == "won":
        levels.append(Level(list(B), list(B), [[b] for b in B], [0] * len(games), [None] * len(games)))
    while outcome == "won" and phi is not None:
        level = _level(m, games, B, phi, first=not levels)
        levels.append(level)
        if progress is not None:
            low, high = min(level.inflation), max(level.inflation)
            progress(rounds + len(levels), f"contracts: level {len(levels) - 1}: inflation "
                     f"{low if low == high else f'{low}-{high}'} cells, {_sizes(m, games, level.C)}")
        stuck = [m.subsystems[i].name or str(i) for i, lay in enumerate(levels[0].layers) if lay[-1] == m.bdd.false]
        if stuck:
            outcome = f"{_named(stuck)} reaches and holds no set smaller than its safe set from any cell"
        elif all((c & ~p) == m.bdd.false for c, p in zip(level.C, phi)):
            break
        elif all(c == b for c, b in zip(level.C, B)):
            outcome = f"no subsystem can shrink its set at level {len(levels) - 1}"
        elif len(levels) >= max_levels:
            outcome = f"still outside the target after {max_levels} levels"
        B = level.C
    domain = [layers[-1] for layers in levels[0].layers] if outcome == "won" else empty
    details = {"outcome": outcome, "levels": len(levels) if outcome == "won" else 0,
               "inflation": [lv.inflation for lv in levels], "safety_rounds": rounds,
               "local_game_subsystems": len(games), "seconds": time.perf_counter() - t0}
    return ContractResult(games, levels if outcome == "won" else [], domain, details)


def _named(names: Sequence[str]) -> str:
    return f"subsystem '{names[0]}'" + (f" (and {len(names) - 1} more)" if len(names) > 1 else "")


def _sizes(model: SymbolicModel, games: Sequence[LocalGame], sets: Sequence[Function]) -> str:
    counts = [int(_cells(model, g, f).sum()) for g, f in zip(games, sets)]
    return f"cells per subsystem {min(counts)}-{max(counts)}" if min(counts) != max(counts) else \
        f"{counts[0]} cells per subsystem"


def controller(model: SymbolicModel, result: ContractResult) -> Function:
    """The composed controller over current-state and input bits (module docstring, step 3), on the domain."""
    bdd = model.bdd
    out = bdd.false
    levels = result.levels
    for k, level in enumerate(levels):
        here = bdd.true
        for b in level.B:
            here &= b
        if k < len(levels) - 1:  # not yet in the next level's boxes
            above = bdd.true
            for c in level.C:
                above &= c
            here &= ~above
        local: list[Function] = []
        for g in result.games:
            r = level.shared[g.index]
            if r is not None and g.image_of is not None:
                local.append(bdd.let(g.image_of[1], local[r]))
            else:
                local.append(_local_controller(g, level.layers[g.index], _assumption(model, g, level.B)))
        for f in local:
            here &= f
        out |= here
    for f in result.domain_factors:
        out &= f
    return out


def _local_controller(g: LocalGame, layers: Sequence[Function], A: Function) -> Function:
    """One subsystem's inputs at one level: inside ``C_i = layers[0]`` those that hold it, at a cell first in layer
    ``k`` those into layer ``k - 1`` (the progress controller of a reachability game, as SCOTS's)."""
    out = layers[0] & _simplest(g, g.good(layers[0]), A)
    for k in range(1, len(layers)):
        out |= (layers[k] & ~layers[k - 1]) & _simplest(g, g.good(layers[k - 1]), A)
    return out


def _simplest(g: LocalGame, good: Function, A: Function) -> Function:
    """``good`` with the neighbours' cells left out where one input serves all of them: at a cell where some input
    is good for every neighbour cell in ``A``, those inputs alone (a function of the own cell); elsewhere ``good``
    itself. The composed controller is a conjunction around the network's cycles: inputs that read neighbours make
    it a product over all of them, inputs that do not keep it a product."""
    bdd = g.model.bdd
    blind = ~and_exists(A, ~good, g.read_bits)
    served = bdd.exist(g.u_bits, blind)
    return blind | (~served & good)


def solve(cpre: ControllablePredecessor, target: Function | None, safe: Function | None = None,
          progress: Callable[[int, str], None] | None = None) -> SynthesisResult:
    """The ``contracts`` fixed point of a reach-and-stay (``target``) or safety (``target`` ``None``) specification as
    the synthesis reports it: the chain (:func:`chain`), its composed controller (:func:`controller`) and the domain,
    a product of per-subsystem sets."""
    t0 = time.perf_counter()
    m = cpre.model
    result = chain(cpre, target, safe, progress)
    domain = m.bdd.true
    for f in result.domain_factors:
        domain &= f
    ctrl = controller(m, result)
    return SynthesisResult(
        kind="safe/contracts" if target is None else "reach_and_stay/contracts", domain=domain, controller=ctrl,
        domain_states=count_states(m, domain), iterations=result.steps, inner_iterations=result.details["safety_rounds"],
        seconds=time.perf_counter() - t0, peak_nodes=peak_live_nodes(m),
        details={"method": "contracts", "order": m.order, **result.details})
