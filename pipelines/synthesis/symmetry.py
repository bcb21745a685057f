"""Interchangeable subsystems: ``∃u.CPre`` computed on one state of each orbit and closed under the swaps.

Issue 24 asks synthesis to exploit identical subsystems and symmetric interconnections. Two subsystems ``a`` and
``b`` are *interchangeable* when swapping their state, next-state and input digits leaves every ingredient of the
controllable predecessor unchanged: the chain's relations as a set (``swap(T_a) = T_b`` and every other relation
fixed), the shared ``M̂`` and the admissible pairs. The consensus agents are (within each group of the MDec tree:
``M̂`` built through ``z0 = f(x0 … x3)`` is invariant under permutations of ``x0 … x3`` only).

Let ``G`` be the group the accepted swaps generate. If ``Z`` is ``G``-invariant, so is ``∃u.CPre(Z)``: for
``π ∈ G``, ``CPre(Z)(πx̂, πû) = CPre(Z)(x̂, û)`` because every ingredient and ``Z'`` are invariant, and ``∃û``
ranges over all inputs. So it suffices to compute it on a set ``R`` holding one state of every orbit and close
the result under ``G``:

    ∃u.CPre(Z) = G · (R ∧ ∃u.CPre(Z)).

Swaps that connect a set of subsystems generate every permutation of it, so ``R`` = the states whose codes
increase along each connected set (:attr:`Symmetry.representatives`). ``R`` is taken where the result is read (the
``states`` of :func:`~.cpre.predecessors_of`: ``M̂ ∧ outside`` at the ``∃w`` step and the admissible pairs), not
in the chain's first operand: it cuts across every agent's block, and there it blows the chain's intermediate
products up (one process, consensus N = 8, Reach(Safe): about 1.6x the time of taking it where the result is
read). Parts running elsewhere (helper processes, the cluster's workers) each take the representatives of their
own states and close their own answer, since closing distributes over the union of the parts. What the symmetry
buys, one process and the cluster, is what ``bench/synthesis.py --no-symmetry`` prints (docs/benchmarks.md).

Only subsystems with a one-dimensional state grid are considered (their codes compare as numbers). Every set a
call takes must be invariant: the iterates a fixed point builds from invariant sets are recognised as such
(:class:`InvariantSets`), any other set is checked with :meth:`Symmetry.invariant`, and where it says no
the call is the plain CPre.
"""

from __future__ import annotations

from collections.abc import Sequence

from pipelines.symbolic.symbolic_model import Function, SymbolicModel
from pipelines.synthesis.schedule import Chain

Swap = dict[str, Function]


class Symmetry:
    """Interchangeable subsystems of a CPre (:func:`find_symmetry`).

    Parameters
    ----------
    model : SymbolicModel
    classes : sequence of sequence of int
        Sets of interchangeable subsystems (positions in ``model.subsystems``), each of at least two, in network
        order; every permutation of a set is a symmetry.

    Attributes
    ----------
    swaps : list of dict
        One renaming per adjacent pair of each set (``bdd.let`` substitutions exchanging the pair's current-state,
        next-state and input bits): they generate the group.
    state_swaps : list of dict
        The same exchanging current-state bits only (enough for sets of states: cheaper substitutions).
    representatives : Function
        The cells (codes inside the grid) whose codes do not decrease along each set: one state of every orbit of
        the grid's states, the only ones ``∃u.CPre`` can hold (its admissible pairs lie in the state domain).
        Leaving the codes past the grid out keeps them out of the chain's intermediate products (with them, and the
        closing swapping input and next-state bits too, consensus N = 8 takes about 1.8x as long).
    """

    def __init__(self, model: SymbolicModel, classes: Sequence[Sequence[int]]) -> None:
        self.model = model
        self.classes = [list(c) for c in classes]
        bdd = model.bdd
        self.swaps = [swap_of(model, a, b) for c in self.classes for a, b in zip(c, c[1:])]
        self.state_swaps = [swap_of(model, a, b, kinds=("x",)) for c in self.classes for a, b in zip(c, c[1:])]
        # Bubble sort's adjacent swaps, s_1 … s_{n-1}, s_1 … s_{n-2}, …, s_1 per set: a reduced word of the
        # permutation that reverses the set, of which every permutation is a subword (the subword property of the
        # Bruhat order), so one pass of f ∪ s(f) along it is the closure (:meth:`close`).
        self._word: list[Swap] = []
        first = 0
        for c in self.classes:
            n = len(c) - 1  # this set's adjacent swaps are state_swaps[first : first + n]
            self._word += [self.state_swaps[first + j] for top in range(n, 0, -1) for j in range(top)]
            first += n
        #: The same word as pairs of exchanged state bits, for another engine's substitution (:mod:`.engine_cpre`).
        self.word_pairs: list[list[tuple[str, str]]] = [
            [(a, str(v.var)) for a, v in swap.items() if a < str(v.var)] for swap in self._word]
        R = bdd.true
        for c in self.classes:
            digits = [state_digit(model, i) for i in c]
            for lo, hi in zip(digits, digits[1:]):
                R &= at_most(model, lo, hi)
        self.representatives = R

    def invariant(self, f: Function) -> bool:
        """Whether ``f`` is unchanged by every permutation of the sets (it is by each generating swap)."""
        bdd = self.model.bdd
        return all(bdd.let(s, f) == f for s in self.swaps)

    def close(self, f: Function) -> Function:
        """``G · f``: the union of ``f``'s images under the group, in one pass of ``f ∪ s(f)`` over bubble sort's
        swaps (``n(n-1)/2`` per set of ``n``). Passes over the ``n - 1`` adjacent swaps until nothing changes need
        up to ``n`` of them and one more over the whole closed set to see it: on the sets a Reach(Safe) of
        consensus N = 8 closes, about 2.4x the time of one pass."""
        bdd = self.model.bdd
        for s in self._word:
            f = f | bdd.let(s, f)
        return f

    def describe(self) -> list[list[str]]:
        """The sets by subsystem name (for the report)."""
        subs = self.model.subsystems
        return [[subs[i].name or str(subs[i].index) for i in c] for c in self.classes]


class InvariantSets:
    """Which sets a fixed point hands :meth:`.cpre.ControllablePredecessor.predecessors` are known invariant under its
    symmetry without checking them (:meth:`Symmetry.invariant`: one substitution per generating swap, seconds of
    a consensus N = 8 Reach(Safe) on the cluster, where the job's process does it alone between the calls).

    Sets combined from invariant sets are invariant. A call computed with the symmetry returns a closed set, so
    after a call on ``Z`` with answer ``P`` (both invariant), the safety loop's next iterate ``Z ∧ P`` and the
    reach loop's ``Z ∨ (P ∧ K)``, for a set ``K`` the loop restricts to (a :meth:`~.cpre.ControllablePredecessor.within`
    set, checked once), are known to be invariant once recognised: BDDs are canonical, so recognising is one or
    two operations whose operands the loop has just combined, where the check is ``n - 1`` substitutions. Any
    other set is checked. Exact either way: a set is taken as invariant only if it is.
    """

    def __init__(self, limit: int = 4) -> None:
        self._limit = limit
        self._sym: Symmetry | None = None  # what the sets below are invariant under
        self._last: tuple[Function, Function] | None = None  # the last call's Z and answer, both invariant
        self._candidates: list[Function] = []  # within() sets, not yet checked
        self._sets: list[Function] = []  # within() sets found invariant

    def may_join(self, S: Function) -> None:
        """``S`` is a set the loops may restrict their iterates to (checked when first needed)."""
        if all(S != c for c in self._candidates + self._sets):
            self._candidates = [S, *self._candidates][: self._limit]

    def step(self, sym: Symmetry, Z: Function, answer: Function) -> None:
        """A call on the invariant ``Z`` gave ``answer``, closed under ``sym``."""
        self._under(sym)
        self._last = (Z, answer)

    def forget(self) -> None:
        """Drop every set held (their BDD nodes with them)."""
        self._sym, self._last, self._candidates, self._sets = None, None, [], []

    def holds(self, sym: Symmetry, f: Function) -> bool:
        """Whether ``f`` is invariant under ``sym``: recognised from the last call, or checked."""
        self._under(sym)
        if self._last is not None:
            Z, P = self._last
            if f == Z or f == P or f == Z & P:
                return True
            for K in self._invariant_sets(sym):
                if f == Z | (P & K):
                    return True
        return sym.invariant(f)

    def _under(self, sym: Symmetry) -> None:
        """Another symmetry than the one the sets were found invariant under: nothing is known of it."""
        if sym is not self._sym:
            self._sym, self._last = sym, None
            self._candidates, self._sets = [*self._candidates, *self._sets][: self._limit], []

    def _invariant_sets(self, sym: Symmetry) -> list[Function]:
        while self._candidates:
            S = self._candidates.pop(0)
            if sym.invariant(S):
                self._sets = [S, *self._sets][: self._limit]
        return self._sets


def cached_symmetry(cache: dict[tuple, Symmetry], model: SymbolicModel, classes: Sequence[Sequence[int]],
                    owner: object = None) -> Symmetry:
    """The :class:`Symmetry` of ``classes`` on ``model``, built once per ``(owner, classes)`` in ``cache``.

    For the processes that compute parts (helper processes, Dask workers): a call ships only the classes, and each
    process keeps the representatives and swaps it built (a worker holding several models passes each model's key
    as ``owner``).
    """
    key = (owner, tuple(tuple(c) for c in classes))
    sym = cache.get(key)
    if sym is None:
        sym = cache[key] = Symmetry(model, classes)
    return sym


def state_digit(model: SymbolicModel, i: int) -> str:
    """The one current-state digit of subsystem ``i`` (a one-dimensional state grid)."""
    (d,) = model.subsystem_digits(model.subsystems[i])["x"]
    return d


def swap_of(model: SymbolicModel, a: int, b: int, kinds: Sequence[str] = ("x", "xn", "u")) -> Swap:
    """The renaming that exchanges subsystems ``a`` and ``b`` (their ``kinds`` of bits: current, next, input)."""
    da, db = model.subsystem_digits(model.subsystems[a]), model.subsystem_digits(model.subsystems[b])
    bdd = model.bdd
    sub: Swap = {}
    for kind in kinds:
        for va, vb in zip(model.bits_of(da[kind]), model.bits_of(db[kind])):
            sub[va], sub[vb] = bdd.var(vb), bdd.var(va)
    return sub


def at_most(model: SymbolicModel, lo: str, hi: str) -> Function:
    """``code(lo) <= code(hi)``, both codes cells of the grid (the two digits have the same number of cells)."""
    last = int(model.sizes[hi]) - 1
    f = model.bdd.false
    for c in range(last + 1):
        f |= model.interval(lo, c, c) & model.interval(hi, c, last)
    return f


def find_symmetry(model: SymbolicModel, chain: Chain, M: Function | None, admissible: Function) -> Symmetry | None:
    """The interchangeable subsystems of a CPre (module docstring), or ``None`` if there are none.

    Candidates are subsystems with the same relation key, internal inputs, input grid and one-dimensional state
    grid of the same size; each pair of candidates next to each other in network order is accepted when its swap
    maps the chain's relations onto themselves and fixes ``M̂`` and the admissible pairs (checked on the BDDs).
    """
    bdd = model.bdd
    subs = model.subsystems
    groups: dict[tuple, list[int]] = {}
    for i, s in enumerate(subs):
        if len(s.state_shape) == 1:
            groups.setdefault((s.key, s.reads, s.state_shape, s.n_inputs), []).append(i)
    relations = {rel for rel, _ in chain}
    parent = list(range(len(subs)))

    def root(i: int) -> int:
        while parent[i] != i:
            i = parent[i]
        return i

    for members in groups.values():
        for a, b in zip(members, members[1:]):
            sub = swap_of(model, a, b)
            if M is not None and bdd.let(sub, M) != M:
                continue
            if bdd.let(sub, admissible) != admissible:
                continue
            if {bdd.let(sub, r) for r in relations} == relations:  # the swap maps the chain onto itself
                parent[root(b)] = root(a)
    classes: dict[int, list[int]] = {}
    for i in range(len(subs)):
        classes.setdefault(root(i), []).append(i)
    found = [c for c in classes.values() if len(c) > 1]
    return Symmetry(model, found) if found else None
