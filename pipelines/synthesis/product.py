"""The product of an abstraction with a formula's automaton, solved as reachability of its accepting states.

A product state ``(q, x̂)`` is a cell and the automaton's state after reading the letters of the run up to and
including ``x̂``'s (:mod:`pipelines.temporal`). From ``(q, x̂)`` an input ``û`` leads to every ``(q', x̂')`` with
``x̂'`` a successor of ``(x̂, û)`` and ``q' = δ(q, σ)`` for a letter ``σ`` that ``x̂'`` can carry: the environment
chooses the successor cell *and*, on a region's edge, the letter (docs/guarantees.md). The winning set is

    ``W = μY. Acc ∨ CPre_⊗(Y)``, with ``Acc = {(q, x̂) : q accepting}`` and
    ``CPre_⊗(Y) = {(q, x̂) : ∃û. every product successor of (q, x̂, û) lies in Y}``,

computed with its progress layers as :func:`.fixed_points.reach` (SCOTS's reachability game on the product):
a product state of layer ``k > 0`` allows the inputs all of whose product successors lie in layers ``< k``; an
accepting one allows every input (the formula holds on the trace so far). A cell is in the controller's domain iff
``(δ(q₀, σ), x̂) ∈ W`` for every letter ``σ`` it can carry.

Per automaton state the product's predecessor is the abstraction's own: with
``G_q(Y) = {x̂' : (δ(q, σ), x̂') ∈ Y for every letter σ of x̂'}``, ``(q, x̂) ∈ CPre_⊗(Y)`` iff
``x̂ ∈ ∃û.CPre(G_q(Y))``. The symbolic solver (:func:`reach_symbolic`) is that: one BDD per automaton state, any
network's controllable predecessor (:class:`~.cpre.ControllablePredecessor`). The explicit one
(:func:`reach_explicit`, single systems) runs the worklist on the product with a counter per (automaton state,
pair). Both compute the same layers; ``tests/test_ltl_product.py`` compares them with a product built state by
state.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np
from numba import njit

from pipelines.synthesis import results
from pipelines.temporal.automaton import Automaton

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from pipelines.symbolic.symbolic_model import Function, SymbolicModel
    from pipelines.synthesis.cpre import ControllablePredecessor
    from pipelines.synthesis.explicit import ExplicitGame
    from pipelines.temporal.labels import Labelling

#: A pair that can never be chosen (blocking): its counter never reaches 0.
NEVER = np.iinfo(np.int32).max // 2


@dataclass
class ProductResult:
    """The product game's winning set, layers and controller, as arrays (explicit back end).

    Attributes
    ----------
    automaton : Automaton
    layer : ndarray of int32, shape (n_states, n_x)
        Per product state the iteration at which it entered (``0``: accepting; ``-1``: losing).
    admissible : ndarray of bool, shape (n_states, n_x, n_u)
        The controller: the inputs allowed at each product state (none where losing).
    domain : ndarray of bool, shape (n_x,)
        The cells from which every run starts in the winning set, whatever letter its first state carries.
    iterations : int
    seconds : float
    details : dict
    """

    automaton: Automaton
    layer: np.ndarray
    admissible: np.ndarray
    domain: np.ndarray
    iterations: int
    seconds: float
    details: dict[str, Any] = field(default_factory=dict)

    kind = "ltl"
    inner_iterations = 0

    @property
    def winning(self) -> np.ndarray:
        return self.layer >= 0

    @property
    def domain_states(self) -> int:
        return int(self.domain.sum())

    def summary(self) -> dict[str, Any]:
        """JSON-ready numbers (:func:`.results.summary`): the automaton's and the product's sizes with them."""
        return results.summary(self, controller_form="product arrays",
                               controller_pairs=int(self.admissible[~self.automaton.accepting].sum()),
                               automaton=self.automaton.summary())


def first_states(automaton: Automaton, class_letters: np.ndarray) -> np.ndarray:
    """``F[c, q]``: whether the automaton can be in ``q`` after the first letter of a run starting in a cell of
    class ``c``."""
    out = np.zeros((class_letters.shape[0], automaton.n_states), dtype=bool)
    c, letter = np.nonzero(class_letters)
    out[c, automaton.delta[automaton.initial, letter]] = True
    return out


def reach_explicit(game: ExplicitGame, automaton: Automaton, classes: np.ndarray,
                   class_letters: np.ndarray) -> ProductResult:
    """The product game of a single system's explicit game (:class:`~.explicit.ExplicitGame`) with
    ``automaton``, cells labelled by ``classes`` (one class id per cell, indices into ``class_letters``, whose row
    says which letters a cell of that class can carry: :meth:`~pipelines.temporal.labels.Labelling.class_letters`).
    """
    from pipelines.temporal.labels import successor_states

    t0 = time.perf_counter()
    D = successor_states(automaton.delta, class_letters)
    layer, chosen = _product_reach(game.indptr, game.preds, game.blocking, game.n_u, np.asarray(classes, np.int64),
                                   D, automaton.accepting)
    admissible = chosen.reshape(automaton.n_states, game.n_x, game.n_u)
    admissible[automaton.accepting] = True  # the formula holds on the trace so far: any input (as reach's targets)
    first = first_states(automaton, class_letters)[classes]  # (n_x, n_states)
    domain = ~np.any(first & (layer.T < 0), axis=1)
    iterations = int(layer.max()) + 1 if (layer >= 0).any() else 1
    details = {"product_states": int(automaton.n_states * game.n_x), "winning_product_states": int((layer >= 0).sum())}
    return ProductResult(automaton, layer, admissible, domain, iterations, time.perf_counter() - t0, details)


@njit(cache=True, nogil=True)
def _product_reach(indptr: np.ndarray, preds: np.ndarray, blocking: np.ndarray, n_u: int, classes: np.ndarray,
                   D: np.ndarray, accepting: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Breadth-first attractor of the accepting product states, with a counter per (automaton state, pair) of its
    product successors not yet won (SCOTS's reachability worklist on the product). Returns the layers
    (n_states, n_x) and the progress controller's pairs (n_states * n_x * n_u,)."""
    n_q = D.shape[0]
    n_x = classes.size
    P = n_x * n_u
    n_succ = np.zeros((n_q, D.shape[1]), dtype=np.int32)
    for q in range(n_q):
        for c in range(D.shape[1]):
            n_succ[q, c] = np.sum(D[q, c])
    remaining = np.zeros((n_q, P), dtype=np.int32)
    for y in range(n_x):
        c = classes[y]
        for j in range(indptr[y], indptr[y + 1]):
            p = preds[j]
            for q in range(n_q):
                remaining[q, p] += n_succ[q, c]
    for p in range(P):
        if blocking[p]:
            for q in range(n_q):
                remaining[q, p] = NEVER
    layer = np.full((n_q, n_x), -1, dtype=np.int32)
    chosen = np.zeros(n_q * P, dtype=np.bool_)
    frontier = np.empty(n_q * n_x, dtype=np.int64)  # product state q * n_x + x
    size = 0
    for q in range(n_q):
        if accepting[q]:
            for x in range(n_x):
                layer[q, x] = 0
                frontier[size] = q * n_x + x
                size += 1
    nxt = np.empty(n_q * n_x, dtype=np.int64)
    k = 0
    while size > 0:
        new = 0
        for i in range(size):
            q2 = frontier[i] // n_x
            y = frontier[i] % n_x
            c = classes[y]
            for j in range(indptr[y], indptr[y + 1]):
                p = preds[j]
                x = p // n_u
                for q in range(n_q):
                    if not D[q, c, q2] or (layer[q, x] != -1 and layer[q, x] <= k):
                        continue
                    remaining[q, p] -= 1
                    if remaining[q, p] == 0:
                        chosen[q * P + p] = True
                        if layer[q, x] == -1:
                            layer[q, x] = k + 1
                            nxt[new] = q * n_x + x
                            new += 1
        frontier, nxt = nxt, frontier
        size = new
        k += 1
    return layer, chosen


@dataclass
class SymbolicProductResult:
    """The product game's winning set and controller as BDDs, one per automaton state (symbolic back end).

    Attributes
    ----------
    automaton : Automaton
    winning : list of Function
        Per automaton state, the cells ``x̂`` with ``(q, x̂)`` winning.
    controller : list of Function
        Per automaton state, the progress controller's pairs ``(x̂, û)`` (every valid input where ``q`` accepts).
    layers : list of list of Function
        Per automaton state, its winning set after each iteration (``layers[q][k]``: layers ``≤ k``).
    domain : Function
        The cells from which every run starts in the winning set.
    domain_states : int
    iterations : int
    seconds : float
    """

    automaton: Automaton
    winning: list[Function]
    controller: list[Function]
    layers: list[list[Function]]
    domain: Function
    domain_states: int
    iterations: int
    seconds: float
    details: dict[str, Any] = field(default_factory=dict)

    kind = "ltl"
    inner_iterations = 0

    def summary(self) -> dict[str, Any]:
        """JSON-ready numbers (:func:`.results.summary`), as :meth:`ProductResult.summary`'s."""
        return results.summary(self, controller_form="product BDDs",
                               controller_nodes=sum(c.dag_size for c in self.controller),
                               automaton=self.automaton.summary())


def letter_sets(model: SymbolicModel, labelling: Labelling) -> list[Function]:
    """Per letter ``σ``, the cells that can carry it: ``∧_i (σ_i ? meets_i : ¬inside_i) ∧ x_domain``
    (:class:`~pipelines.temporal.labels.Labelling`: an atom surely holds inside its region, surely fails outside the
    cells that meet it)."""
    from pipelines.symbolic.relations import region

    inside = [region(model, r) for r in labelling.inside]
    meets = [region(model, r) for r in labelling.meets]
    out = []
    for sigma in range(labelling.n_letters):
        cells = model.x_domain
        for i in range(len(labelling.atoms)):
            cells &= meets[i] if (sigma >> i) & 1 else ~inside[i]
        out.append(cells)
    return out


def letter_moves(automaton: Automaton, letter_sets: Sequence[Function], false: Function) -> list[list[Function]]:
    """``M[q][q']``: the cells on which the automaton can move from ``q`` to ``q'`` (the union of the cells of the
    letters that lead there; ``letter_sets[σ]``: the cells that can carry ``σ``)."""
    moves = [[false] * automaton.n_states for _ in range(automaton.n_states)]
    for q in range(automaton.n_states):
        for sigma, cells in enumerate(letter_sets):
            q2 = int(automaton.delta[q, sigma])
            moves[q][q2] = moves[q][q2] | cells
    return moves


def _safe_after(moves_from_q: list[Function], Y: Sequence[Function], top: Function) -> Function:
    """``G_q(Y)``: the cells every move of the automaton out of ``q`` takes into ``Y``."""
    G = top
    for q2, cells in enumerate(moves_from_q):
        G &= ~cells | Y[q2]
    return G


def reach_symbolic(cpre: ControllablePredecessor, automaton: Automaton, letter_sets: Sequence[Function],
                   progress: Any = None) -> SymbolicProductResult:
    """The product game on any network's controllable predecessor, one BDD per automaton state, iterated in
    lockstep so that its layers are :func:`reach_explicit`'s (``letter_sets[σ]``: the cells that can carry
    letter ``σ``, over current-state bits; ``progress(iteration, message)`` as :data:`.fixed_points.IterationProgress`).
    """
    t0 = time.perf_counter()
    m = cpre.model
    top, false = m.x_domain, cpre.bdd.false
    moves = letter_moves(automaton, letter_sets, false)
    n_q = automaton.n_states
    W = [top if automaton.accepting[q] else false for q in range(n_q)]
    controller = [top & m.u_domain if automaton.accepting[q] else false for q in range(n_q)]
    layers = [[w] for w in W]
    iterations = 0
    while True:
        iterations += 1
        grown = list(W)
        for q in range(n_q):
            if automaton.accepting[q]:
                continue
            C = cpre.cpre(_safe_after(moves[q], W, top))
            new = cpre.pre(C) & top & ~W[q]
            if new != false:
                controller[q] |= C & new
                grown[q] = W[q] | new
        changed = any(g != w for g, w in zip(grown, W))
        W = grown
        for q in range(n_q):
            layers[q].append(W[q])
        if progress is not None:
            progress(iterations, f"ltl iteration {iterations}")
        if not changed:
            break
    domain = _safe_after(moves[automaton.initial], W, top)
    from pipelines.symbolic.counting import count_states

    details = {"product_states": n_q * count_states(m, top), "winning_product_states": sum(count_states(m, w)
                                                                                          for w in W)}
    return SymbolicProductResult(automaton, W, controller, layers, domain, count_states(m, domain), iterations,
                                 time.perf_counter() - t0, details)
