"""Controller synthesis on the symbolic abstraction (Section 4.3, Algorithm 5; METHOD §6).

The controlled predecessor of a set ``Z`` of composed abstract states is

    CPre(Z)(x̂, û) = M̂(x̂) ≠ ∅  ∧  ∀ŵ ∈ M̂(x̂): ∧_i NB_i(x̂_i, û_i, ŵ_i)  ∧  ∀x̂'. ∧_i T_i(x̂_i, û_i, ŵ_i, x̂'_i) → Z(x̂')

(every admissible internal input lets every subsystem move, and all successors lie in ``Z``). The composed
transition relation is never built: the ``T_i`` stay partitioned and next-state variables are quantified one
subsystem at a time (``and_exists``), METHOD §5-6.

Two exact implementations, chosen automatically (:class:`Game`):

* ``per_subsystem`` (each internal variable is read by at most one subsystem, e.g. the tanks). Then
  ``M̂ = ∧_j M̂_j(x, w_j)`` with disjoint ``w_i`` per subsystem, and ``w`` is quantified before any fixed point:
  ``T̃_i = ∃w_i. M̂_i ∧ T_i``, ``NB'_i = ∀w_i. (M̂_i → NB_i)`` (kept separately: an input that blocks for one
  admissible ``w_i`` must not look admissible), and
  ``CPre(Z) = ∃w.M̂ ∧ ∧_i NB'_i ∧ ¬∃x'. (∧_i T̃_i ∧ ¬Z')``, chained subsystem by subsystem in a greedy
  early-quantification schedule (:func:`schedule`; it beat METHOD's "widest support last" by 2x). Exactness: ``∀w∀x'.(∧_i(M̂_i ∧ T_i) → Z') = ∀x'.(∧_i ∃w_i(M̂_i ∧ T_i) → Z')``
  because the ``w_i`` are disjoint.
* ``shared`` (an internal variable read by several subsystems, e.g. consensus): ``w`` stays shared (quantifying
  it per subsystem would let each subsystem see a different ``w``: sound but conservative, METHOD §6).
  ``CPre(Z) = ∃w.M̂ ∧ ¬BLK ∧ ¬∃w.[M̂ ∧ ∃x'.(∧_i T_i ∧ ¬Z')]`` with the blocking part
  ``BLK = ∨_i ∃w.(M̂ ∧ ¬NB_i)`` computed once (∃ distributes over ∨). The step ``∃w.[M̂ ∧ ...]`` is the known
  bottleneck (METHOD §6: 67 % of CPre time at N = 8).

Fixed points (the paper's Algorithm 5 uses them; METHOD §6): safety ``νZ. S ∧ ∃u.CPre(Z)``, reachability
``μZ. T ∨ ∃u.CPre(Z)``, reach-avoid ``μZ. (T ∨ ∃u.CPre(Z)) ∧ ¬A``, reach-and-stay both as the co-Büchi
``μX. νY. (φ ∧ ∃u.CPre(Y)) ∨ ∃u.CPre(X)`` and as ``Reach(Safe(φ))``. By the feedback refinement relation
(Theorem 4.2) and soundness of the abstraction (Theorem 4.8), the controllers refine to the concrete network.
Loops that need the controller only at convergence use :meth:`Game.predecessors` (``∃u.CPre`` in one
``and_exists``, never materialising ``CPre``).

Measured (2-core machine, dd 0.6.0 / CUDD 3.0.0): 10 tanks, scp bound, Reach(Safe(φ)) 102 s (safety 24
iterations, 100 s; widest-last schedule and materialised CPre: 340 s); hull bound 42 s. Then the safety loop
on relations restricted to the safe set (:meth:`Game.within`) and the blocks in :func:`~.symbolic.reader_order`:
safety 28-34 s, Reach(Safe(φ)) with its explicit controller ~32 s. Consensus with shared
``w``: N = 4 in 4.3 s, N = 6 in 56 s (1 GB); N = 8 safe + reach 404 s in one process, 320 s with the
``∃u.CPre`` split over two processes (:mod:`.parallel_cpre`, ``Game(processes=2)``).
"""

from __future__ import annotations

import functools
import logging
import os
import time
import warnings
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any, Callable, Mapping, NamedTuple, Sequence

from dd import cudd

from pipelines.symbolic.model import Function, SymbolicModel

if TYPE_CHECKING:  # pragma: no cover
    from workers.job import AbstractionResult

Chain = list[tuple[Function, list[str]]]  # (relation, next-state bits it quantifies), in schedule order


class Within(NamedTuple):
    """The chain and the admissible pairs restricted to a set of states (:meth:`Game.within`)."""

    chain: Chain
    admissible: Function


METHODS = ("auto", "per_subsystem", "shared")
CHAIN_ORDERS = ("greedy", "widest_last", "network")
log = logging.getLogger(__name__)


@dataclass
class SynthesisResult:
    """A winning domain and a controller, with what it cost.

    Attributes
    ----------
    kind : str
        ``safe``, ``reach``, ``reach_avoid``, ``reach_and_stay/cobuchi`` or ``reach_and_stay/reach_safe``.
    domain : Function
        Winning states (current-state bits).
    controller : Function or None
        Pairs ``(x̂, û)`` over current-state and input bits; ``None`` for a layered result (see ``layers``).
    domain_states : int
        Exact number of abstract states in ``domain``.
    iterations : int
        Iterations of the (outer) fixed point.
    inner_iterations : int
        Iterations of inner fixed points (co-Büchi ``ν``; the safety part of Reach(Safe)); 0 if none.
    seconds : float
        Wall time of the fixed point(s), controller included.
    peak_nodes : int
        CUDD's peak of live nodes in the manager (``peak_live_nodes``) when the fixed point ended: since the
        manager was made, so it includes what came before in the same manager.
    details : dict
        Per-part counts and times (JSON-ready).
    layers : tuple of Function
        A layered controller instead of ``controller``: ``layers[0] ⊆ layers[1] ⊆ ... = domain`` over
        current-state bits. At a state first in ``layers[k]`` (``k > 0``) the admissible inputs are
        ``CPre(layers[k-1])``; in ``layers[0]`` they are ``CPre(layers[0])`` if ``stay`` else every valid input
        (the target of a reachability game). This is exactly the explicit progress controller, stored as the
        sets it is made of and evaluated at one state at a time (:meth:`Game.cpre_at`).
    stay : bool
        See ``layers``.
    """

    kind: str
    domain: Function
    controller: Function | None
    domain_states: int
    iterations: int
    inner_iterations: int
    seconds: float
    peak_nodes: int
    details: dict[str, Any] = field(default_factory=dict)
    layers: tuple[Function, ...] = ()
    stay: bool = False

    def summary(self) -> dict[str, Any]:
        """JSON-ready numbers (no BDDs)."""
        return {
            "kind": self.kind,
            "domain_states": self.domain_states,
            "iterations": self.iterations,
            "inner_iterations": self.inner_iterations,
            "seconds": self.seconds,
            "peak_nodes": self.peak_nodes,
            "controller_form": "layered" if self.layers else "explicit",
            "controller_nodes": self.controller.dag_size if self.controller is not None else None,
            "layer_nodes": [f.dag_size for f in self.layers],
            "domain_nodes": self.domain.dag_size,
            **self.details,
        }


def _peak_live_nodes(model: SymbolicModel) -> int:
    with warnings.catch_warnings():  # dd warns that 'mem' is now in bytes
        warnings.simplefilter("ignore")
        return int(model.bdd.statistics()["peak_live_nodes"])


class _Meter:
    """Iteration counter, timer and peak-node reader of one fixed point.

    ``len(bdd)`` (CUDD's live-node count) walks the unique table: once per iteration it was 5 % of the tanks'
    synthesis (bench/run.py profile), so the peak is CUDD's own counter, read at the end.
    """

    def __init__(self, model: SymbolicModel, kind: str) -> None:
        self.model = model
        self.kind = kind
        self.t0 = time.perf_counter()
        self.iterations = 0
        self.inner = 0
        self.peak = 0

    def tick(self, inner: bool = False) -> None:
        if inner:
            self.inner += 1
        else:
            self.iterations += 1
        if log.isEnabledFor(logging.INFO):
            log.info("%s: iteration %d (inner %d), %.2f s, %d live nodes", self.kind, self.iterations, self.inner,
                     self.seconds, len(self.model.bdd))

    @property
    def seconds(self) -> float:
        return time.perf_counter() - self.t0


class Game:
    """The control problem on the abstraction: ``CPre`` with partitioned relations (METHOD §6).

    Parameters
    ----------
    model : SymbolicModel
    transitions, nonblocking : sequence of Function, one per subsystem (network order)
        ``T_i(x_i, u_i, w_i, x'_i)`` and ``NB_i(x_i, u_i, w_i)`` (:meth:`SymbolicModel.subsystem_relations`).
    interconnection : mapping of int to Function
        ``M̂_j(x, w_j)`` per internal variable (:meth:`SymbolicModel.interconnection_parts`).
    method : {'auto', 'per_subsystem', 'shared'}
        ``auto`` picks ``per_subsystem`` exactly when every internal variable is read by at most one
        subsystem. Both are exact; ``shared`` is valid for every network.
    chain_order : {'greedy', 'widest_last', 'network'}
        Order in which the relations are conjoined into ``¬Z'`` (see :func:`schedule`).
    processes : int or 'auto'
        Processes for :meth:`predecessors` (this one included); ``1``: no helper processes; ``'auto'``:
        :func:`resolve_processes` for the shared CPre, 1 for the per-subsystem one (the 10 tanks: each half of
        a split CPre took as long as the whole, since the halves share most sub-results that one process
        computes once; the safety loop gained nothing, 33.3 s vs 33.4 s).
    parallel_after : float
        Seconds one single-process :meth:`predecessors` call must take before the helpers start (starting
        one costs ~0.5 s; small games never need them). ``0``: from the second call on.
    """

    def __init__(
        self,
        model: SymbolicModel,
        transitions: Sequence[Function],
        nonblocking: Sequence[Function],
        interconnection: Mapping[int, Function],
        method: str = "auto",
        chain_order: str = "greedy",
        processes: int | str = 1,
        parallel_after: float = 1.0,
    ) -> None:
        if isinstance(processes, int) and processes < 1:
            raise ValueError(f"processes must be at least 1, got {processes}")
        self.parallel_after = float(parallel_after)
        self._pool: Any = None
        self._last_pool: Any = None
        self._pool_error: str | None = None  # why the helpers stopped, if a helper failed
        if chain_order not in CHAIN_ORDERS:
            raise ValueError(f"chain_order must be one of {CHAIN_ORDERS}, got {chain_order!r}")
        self.chain_order = chain_order
        if method not in METHODS:
            raise ValueError(f"method must be one of {METHODS}, got {method!r}")
        if len(transitions) != len(model.subsystems) or len(nonblocking) != len(model.subsystems):
            raise ValueError("one transition relation and one non-blocking set per subsystem")
        self.model = model
        self.bdd = model.bdd
        self.T = list(transitions)
        self.NB = list(nonblocking)
        self.parts = dict(interconnection)
        readers: dict[int, int] = {}
        for s in model.subsystems:
            for j in s.reads:
                readers[j] = readers.get(j, 0) + 1
        separable = all(c <= 1 for c in readers.values())
        if method == "auto":
            method = "per_subsystem" if separable else "shared"
        elif method == "per_subsystem" and not separable:
            raise ValueError("per_subsystem CPre needs every internal variable read by at most one subsystem")
        self.method = method
        self.processes = 1 if processes == "auto" and method == "per_subsystem" else resolve_processes(processes)
        self.u_bits = model.u_bits
        self.setup_seconds = 0.0
        t0 = time.perf_counter()
        with model.guard(f"preparing the {method} CPre"):
            if method == "per_subsystem":
                self._prepare_per_subsystem()
            else:
                self._prepare_shared()
        self.setup_seconds = time.perf_counter() - t0

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_abstraction(
        cls,
        abstraction: "AbstractionResult",
        *,
        order: str | None = None,
        method: str = "auto",
        max_memory: int | None = None,
        share: str = "rename",
        chain_order: str = "greedy",
        processes: int | str = 1,
        parallel_after: float = 1.0,
    ) -> "Game":
        """Build the model, the relations and the interconnection of an abstraction job.

        ``order`` defaults to ``interleaved`` where each internal variable has one reader and ``shared_top``
        otherwise (the orders METHOD §6 measured best for the tanks and consensus).
        """
        net = abstraction.network
        if order is None:
            counts: dict[int, int] = {}
            for s in net.subsystems:
                for j in s.reads:
                    counts[j] = counts.get(j, 0) + 1
            order = "interleaved" if all(c <= 1 for c in counts.values()) else "shared_top"
        model = SymbolicModel.from_network(net, abstraction.interconnection, order=order, max_memory=max_memory)
        T, NB = model.subsystem_relations(abstraction.relations, share=share)
        parts = model.interconnection_parts(abstraction.interconnection.nodes)
        return cls(model, T, NB, parts, method, chain_order, processes, parallel_after)

    def _prepare_per_subsystem(self) -> None:
        m, bdd = self.model, self.bdd
        self.admissible = m.x_domain & m.u_domain
        for j, part in self.parts.items():  # M̂(x̂) ≠ ∅: every w_j has some admissible cell
            self.admissible &= bdd.exist(m.bits[f"w{j}"], part)
        chain: list[tuple[Function, list[str]]] = []
        for s, t, nb in zip(m.subsystems, self.T, self.NB):
            wb = m.bits_of([f"w{j}" for j in s.reads])
            Mi = bdd.true
            for j in s.reads:
                Mi &= self.parts[j]
            t_tilde = cudd.and_exists(Mi, t, wb)  # T̃_i = ∃w_i. M̂_i ∧ T_i
            nb_prime = ~cudd.and_exists(Mi, ~nb, wb)  # NB'_i = ∀w_i. (M̂_i → NB_i)
            self.admissible &= nb_prime
            chain.append((t_tilde, m.bits_of(m.subsystem_digits(s)["xn"])))
        self.chain = schedule(chain, set(m.xn_bits), bdd, self.chain_order)
        self.M, self.w_bits = None, []  # w is quantified inside the chain

    def _prepare_shared(self) -> None:
        m, bdd = self.model, self.bdd
        M = bdd.true
        for part in self.parts.values():
            M &= part
        self.M = M
        self.w_bits = m.w_bits
        blocked = bdd.false
        for nb in self.NB:  # ∃w.(M̂ ∧ ¬∧NB_i) = ∨_i ∃w.(M̂ ∧ ¬NB_i)
            blocked |= cudd.and_exists(M, ~nb, self.w_bits)
        self.admissible = m.x_domain & m.u_domain & bdd.exist(self.w_bits, M) & ~blocked
        chain = [(t, m.bits_of(m.subsystem_digits(s)["xn"])) for s, t in zip(m.subsystems, self.T)]
        self.chain = schedule(chain, set(m.xn_bits), bdd, self.chain_order)

    # ------------------------------------------------------------------ CPre
    def within(self, S: Function) -> Within:
        """``CPre`` ingredients restricted to the current states of ``S`` (exact on ``S`` only).

        Each relation is conjoined with ``S`` projected on the current-state coordinates it reads: for a state
        ``x̂ ∈ S`` those coordinates are the ones of some state of ``S``, so ``∧_i (R_i ∧ ∃(x̂ ∉ supp R_i). S) =
        ∧_i R_i`` there, and the admissible pairs are conjoined with ``S``. Every ``CPre`` and predecessor
        computed with the result is exact on ``S`` and empty outside it. Loops whose iterates stay inside ``S``
        (the safety fixed point) pass it: on the 10 tanks the safety fixed point went 58 s -> 33 s (the
        projections of a box are boxes; restricting to the projections of each iterate instead measured 44 s;
        restricting the admissible pairs too is within the noise, 30-34 s either way).
        """
        bdd, m = self.bdd, self.model
        x_bits = set(m.x_bits)
        chain = []
        for rel, xn_bits in self.chain:
            outside_support = sorted(x_bits - set(bdd.support(rel)))
            chain.append((rel & bdd.exist(outside_support, S), xn_bits))
        return Within(chain, self.admissible & S)

    def cpre(self, Z: Function, within: Within | None = None) -> Function:
        """``CPre(Z)`` over current-state and input bits (see the module docstring).

        ``within``: :meth:`within` ``(S)`` to compute it on ``S`` only (default: everywhere).
        """
        chain, admissible = (self.chain, self.admissible) if within is None else within
        with self.model.guard("computing CPre"):
            return admissible & ~bad_inputs(self.model, chain, self.M, self.w_bits, Z)

    def cpre_at(self, state: Mapping[str, bool], Z_next: Function) -> Function:
        """``CPre(Z)`` at one state: a function of the input bits only.

        Parameters
        ----------
        state : dict of str to bool
            Values of all current-state bits (:meth:`SymbolicModel.state_assignment`).
        Z_next : Function
            ``Z`` over next-state bits (``model.to_next(Z)``; callers cache it per set).

        Every ingredient is cofactored at the state first, so the chain runs on BDDs over ``u``, ``w`` and one
        subsystem's ``x'`` at a time: milliseconds where the full ``CPre`` of a consensus network is minutes.
        ``¬Z'`` is first cut down to the product of the subsystems' possible next cells from this state
        (``∧_i ∃u,w. T_i``, which every successor lies in, so the result is the same): consensus N = 8, 40
        states of the reach layers, 5.7 ms against 17.1 ms per state.
        """
        bdd = self.bdd
        with self.model.guard("computing CPre at a state"):
            good = bdd.let(state, self.admissible)
            if good == bdd.false:
                return good
            chain = [(bdd.let(state, rel), xn_bits) for rel, xn_bits in self.chain]
            reachable = bdd.true
            for rel, xn_bits in chain:
                quantified = set(xn_bits)
                reachable &= bdd.exist([v for v in bdd.support(rel) if v not in quantified], rel)
            acc = ~Z_next & reachable
            for rel, xn_bits in chain:
                acc = cudd.and_exists(acc, rel, xn_bits)
            if self.method == "shared":
                acc = cudd.and_exists(bdd.let(state, self.M), acc, self.w_bits)
            return good & ~acc

    def pre(self, cpre: Function) -> Function:
        """``∃u. cpre``: states with some good input."""
        return self.bdd.exist(self.u_bits, cpre)

    def predecessors(
        self, Z: Function, outside: Function | None = None, within: Within | None = None,
        part: Function | None = None,
    ) -> Function:
        """``∃u. CPre(Z)`` without materialising ``CPre(Z)`` (one ``and_exists`` over the inputs).

        Fixed points that need the controller only at convergence use this in their loop. With ``outside``
        the result is exact only on states in ``outside`` (a reach loop passes ``¬Z``: states already won need
        no answer); the shared ``∃w.M̂ ∧ ...`` step then works on ``M̂ ∧ outside``, which measured 20 % less
        time on consensus N = 5. ``within``: as in :meth:`cpre`. ``part``: a set of current states; the
        result is ``part ∧ ∃u.CPre(Z)``, computed on that part only.

        With ``processes > 1`` a call that is not given a ``part`` runs in parts in several processes
        (:class:`~.parallel_cpre.PartitionedPredecessors`) once one call here took ``parallel_after`` seconds.
        If a helper dies or fails, that call and the later ones run in this process (``parallel["stopped"]``
        says why); CUDD running out of memory in a helper is raised, as it would be here.
        """
        if part is None and self._pool is not None:
            from workers.processes.partitioned_cpre import HelperError

            try:
                return self._pool(Z, outside, within)
            except HelperError as exc:
                # A helper died or failed (killed, out of memory in its process): its part is recomputed here,
                # and so is everything after; the answer is the same, only slower. The report says why.
                self._drop_pool(one_process=True)
                self._pool_error = str(exc)
                log.warning("partitioned CPre stopped (%s); going on in one process", exc)
            except BaseException:
                # The error closed the pool; later calls run here, and no new helpers start.
                self._drop_pool(one_process=True)
                raise
        chain, admissible = (self.chain, self.admissible) if within is None else within
        t0 = time.perf_counter()
        with self.model.guard("computing CPre"):
            result = predecessors_of(self.model, chain, admissible, self.M, self.w_bits, self.u_bits, Z, outside,
                                     part)
        if part is None and self.processes > 1 and time.perf_counter() - t0 >= self.parallel_after:
            from workers.processes.partitioned_cpre import PartitionedPredecessors

            self._pool = PartitionedPredecessors(self, self.processes)
        return result

    def close(self) -> None:
        """Stop the helper processes of the partitioned ``∃u.CPre``, if any were started (idempotent)."""
        if self._pool is not None:
            self._pool.close()
            self._drop_pool(one_process=False)

    def _drop_pool(self, one_process: bool) -> None:
        """Forget the (closed) pool, keeping it for :attr:`parallel`; ``one_process``: start no helpers again."""
        self._last_pool, self._pool = self._pool, None
        if one_process:
            self.processes = 1

    @property
    def parallel(self) -> dict[str, Any]:
        """How the partitioned ``∃u.CPre`` ran (empty if it never started): calls, the digits it cuts along, the
        cuts (each the first cell ``[code of digits[0], code of digits[1]]`` of a part), seconds per part,
        and ``stopped`` (why) if a helper failed and the game went on in one process."""
        p = self._pool if self._pool is not None else self._last_pool
        if p is None:
            return {}
        out = {"processes": len(p.cuts) + 1, "calls": p.calls, "digits": list(p.digits),
               "cuts": [list(c) for c in p.cut_cells],
               "last_seconds": [round(s, 3) for s in p.seconds]}
        if self._pool_error is not None:
            out["stopped"] = f"{self._pool_error}; the later calls ran in one process"
        return out


def resolve_processes(processes: int | str) -> int:
    """``'auto'``: the CPUs this process may use, at most 4 (each part adds ~5-15 % work); else the int itself."""
    if processes == "auto":
        try:
            cpus = len(os.sched_getaffinity(0))
        except AttributeError:  # pragma: no cover - not Linux
            cpus = os.cpu_count() or 1
        return max(1, min(cpus, 4))
    if isinstance(processes, bool) or not isinstance(processes, int) or processes < 1:
        raise ValueError(f"processes must be 'auto' or a positive int, got {processes!r}")
    return processes


def bad_inputs(
    model: SymbolicModel, chain: Chain, M: Function | None, w_bits: Sequence[str], Z: Function,
    outside: Function | None = None, part: Function | None = None,
) -> Function:
    """State-input pairs with a successor outside ``Z``: ``part ∧ ∃w.[M̂ ∧ outside ∧ ∃x'.(∧_i R_i ∧ ¬Z')]``.

    The chain (``R_i`` = T̃_i or T_i) is conjoined one subsystem at a time; ``M`` is ``None`` for the
    per-subsystem CPre (``w`` already quantified in the chain), else the shared ``∃w`` step follows, the
    bottleneck of METHOD §6. ``part`` (current states) is conjoined into the chain's first operand; it reads
    current-state bits only, so it commutes with ``∃x'`` and ``∃w`` and the result is exact on it.
    """
    acc = ~model.to_next(Z)
    if part is not None:
        acc &= part
    for rel, xn_bits in chain:
        acc = cudd.and_exists(acc, rel, xn_bits)
    if M is not None:
        care = M if outside is None else M & outside
        if part is not None:
            care &= part
        acc = cudd.and_exists(care, acc, list(w_bits))
    return acc


def predecessors_of(
    model: SymbolicModel, chain: Chain, admissible: Function, M: Function | None, w_bits: Sequence[str],
    u_bits: Sequence[str], Z: Function, outside: Function | None = None, part: Function | None = None,
) -> Function:
    """``part ∧ ∃u.CPre(Z)`` from the CPre ingredients (:meth:`Game.predecessors`; ``M`` for the shared method).

    ``part`` restricts :func:`bad_inputs` and the admissible pairs, so the result is exact on it. A function of
    the ingredients (not a method) because helper processes (:mod:`.parallel_cpre`) run it on their own copies.
    """
    if part is not None:
        admissible = admissible & part
    bad = bad_inputs(model, chain, M, w_bits, Z, outside, part)
    return cudd.and_exists(admissible, ~bad, list(u_bits))


def schedule(
    chain: Sequence[tuple[Function, list[str]]], start: set[str], bdd, how: str = "greedy"
) -> list[tuple[Function, list[str]]]:
    """Order the relational products of ``∃x'. (∧_i R_i ∧ ¬Z')`` (early-quantification scheduling).

    ``greedy`` picks next the relation that leaves the intermediate result with the fewest support variables
    (its support united with the running support, minus the next-state bits it lets us quantify), ties by
    narrower support, then network order: the classic heuristic for partitioned image computation.
    ``widest_last`` sorts by support size (METHOD §6's advice); ``network`` keeps the given order.

    Measured on the 10 tanks (scp bound), one CPre at safety iteration 3: greedy 2.3 s (peak 0.41 M nodes =
    the result), network order 4.1 s (0.85 M), widest last 5.7 s (2.0 M); reverse network order did not finish
    in 12 minutes (7.5 GB). The whole safety fixed point: widest last 339 s, greedy 175 s.
    """
    supports = [set(bdd.support(rel)) for rel, _ in chain]
    if how == "network":
        return list(chain)
    if how == "widest_last":
        return [chain[k] for k in sorted(range(len(chain)), key=lambda k: len(supports[k]))]
    left = list(range(len(chain)))
    running = set(start)
    out = []
    while left:
        def cost(k: int) -> tuple[int, int, int]:
            return (len((running | supports[k]) - set(chain[k][1])), len(supports[k]), k)

        k = min(left, key=cost)
        left.remove(k)
        running = (running | supports[k]) - set(chain[k][1])
        out.append(chain[k])
    return out


# ====================================================================================== fixed points
def _guarded(fn: Callable[..., Any]) -> Callable[..., Any]:
    """Run a fixed point inside :meth:`SymbolicModel.guard`: CUDD running out of memory becomes a clear error."""

    @functools.wraps(fn)
    def run(game: Game, *args: Any, **kwargs: Any) -> Any:
        with game.model.guard(f"computing the {fn.__name__} fixed point"):
            return fn(game, *args, **kwargs)

    return run


def _result(
    game: Game, kind: str, domain: Function, controller: Function | None, meter: _Meter,
    layers: Sequence[Function] = (), stay: bool = False, **details: Any,
) -> SynthesisResult:
    meter.peak = max(meter.peak, _peak_live_nodes(game.model))
    return SynthesisResult(
        kind=kind,
        domain=domain,
        controller=controller,
        domain_states=game.model.count_states(domain),
        iterations=meter.iterations,
        inner_iterations=meter.inner,
        seconds=meter.seconds,
        peak_nodes=meter.peak,
        details={"method": game.method, "order": game.model.order, **details},
        layers=tuple(layers),
        stay=stay,
    )


@_guarded
def safe(game: Game, S: Function, *, layered: bool = False) -> SynthesisResult:
    """``νZ. S ∧ ∃u.CPre(Z)``; the controller allows every input that keeps the state in the invariant.

    ``layered``: return the invariant as a one-layer controller (``stay``) instead of ``Z ∧ CPre(Z)``.
    """
    meter = _Meter(game.model, "safe")
    S = S & game.model.x_domain
    inside = game.within(S)  # every iterate is inside S
    Z = S
    while True:
        Zn = S & game.predecessors(Z, within=inside)
        meter.tick()
        if Zn == Z:
            break
        Z = Zn
    if layered:
        return _result(game, "safe", Z, None, meter, layers=(Z,), stay=True)
    return _result(game, "safe", Z, Z & game.cpre(Z, inside), meter)


@_guarded
def reach(
    game: Game, T: Function, avoid: Function | None = None, *, kind: str = "reach", layered: bool = False
) -> SynthesisResult:
    """``μZ. (T ∨ ∃u.CPre(Z)) ∧ ¬A`` (``A`` empty for plain reachability) with a progress controller.

    An input counts at ``x̂`` only in the iteration where ``x̂`` entered the attractor (SCOTS keeps it that way):
    it then leads into the previous iterate, so every closed-loop run reaches ``T`` within as many steps as
    there were iterations. Target states get every (valid) input: the specification is met on arrival.

    ``layered``: keep the iterates instead of the controller (:class:`SynthesisResult` ``layers``); each
    iteration is then one ``∃u.CPre`` without materialising ``CPre`` over states and inputs, which on the
    consensus network is most of the time and nearly all of the memory of the explicit controller.
    """
    m = game.model
    meter = _Meter(m, kind)
    keep = m.x_domain if avoid is None else m.x_domain & ~avoid
    Z = T & keep
    if layered:
        layers = [Z]
        while True:
            new = game.predecessors(Z, outside=~Z) & keep & ~Z
            meter.tick()
            if new == game.bdd.false:
                break
            Z |= new
            layers.append(Z)
        return _result(game, kind, Z, None, meter, layers=layers)
    controller = Z & m.u_domain
    while True:
        C = game.cpre(Z)
        new = game.pre(C) & keep & ~Z
        meter.tick()
        if new == game.bdd.false:
            break
        controller |= C & new
        Z |= new
    return _result(game, kind, Z, controller, meter)


@_guarded
def reach_avoid(game: Game, T: Function, A: Function, *, layered: bool = False) -> SynthesisResult:
    """``μZ. (T ∨ ∃u.CPre(Z)) ∧ ¬A``."""
    return reach(game, T, A, kind="reach_avoid", layered=layered)


@_guarded
def cobuchi(game: Game, phi: Function) -> SynthesisResult:
    """``◇□φ`` as ``μX. νY. (φ ∧ ∃u.CPre(Y)) ∨ ∃u.CPre(X)`` (METHOD §6).

    Controller: a state that enters at outer iteration ``k+1`` (``X_{k+1} \\ X_k``) gets the inputs ``û`` with
    ``(φ(x̂) ∧ CPre(X_{k+1})(x̂, û)) ∨ CPre(X_k)(x̂, û)``. Along a closed-loop run the rank ``k`` never increases,
    and while it stays constant only the first disjunct can hold, so from some time on every state is in ``φ``.
    """
    m = game.model
    meter = _Meter(m, "cobuchi")
    phi = phi & m.x_domain
    on_phi = game.within(phi)  # the ν part is needed on φ only
    X = game.bdd.false
    controller = game.bdd.false
    while True:
        CX = game.cpre(X)
        preX = game.pre(CX)
        Y = m.x_domain
        while True:
            Yn = game.predecessors(Y, within=on_phi) | preX
            meter.tick(inner=True)
            if Yn == Y:
                break
            Y = Yn
        meter.tick()
        if Y != X:
            controller |= (Y & ~X) & (game.cpre(Y, on_phi) | CX)
        if Y == X:
            break
        X = Y
    return _result(game, "reach_and_stay/cobuchi", X, controller, meter)


@_guarded
def reach_safe(game: Game, phi: Function, *, layered: bool = False) -> SynthesisResult:
    """``◇□φ`` as ``Reach(Safe(φ))``: inside the safe set the safety controller, outside the reach controller.

    ``layered``: the reach iterates over the safe set, with ``stay`` (layer 0 is the invariant).
    """
    meter = _Meter(game.model, "reach_safe")
    s = safe(game, phi, layered=layered)
    r = reach(game, s.domain, layered=layered)
    meter.iterations = r.iterations
    meter.inner = s.iterations
    meter.peak = max(s.peak_nodes, r.peak_nodes)
    extra = dict(safe_states=s.domain_states, safe_seconds=s.seconds, reach_seconds=r.seconds)
    if layered:
        return _result(game, "reach_and_stay/reach_safe", r.domain, None, meter, layers=r.layers, stay=True, **extra)
    controller = (s.domain & s.controller) | (~s.domain & r.controller)
    return _result(game, "reach_and_stay/reach_safe", r.domain, controller, meter, **extra)


REACH_AND_STAY = {"cobuchi": cobuchi, "reach_safe": reach_safe}


def reach_and_stay(
    game: Game, phi: Function, methods: Sequence[str] = ("cobuchi", "reach_safe"), *, layered: bool = False
) -> dict[str, SynthesisResult]:
    """``◇□φ`` by each of ``methods`` (METHOD §6 asks for both domains to be reported).

    ``layered`` applies to ``reach_safe``; the co-Büchi controller is always explicit.
    """
    return {name: reach_safe(game, phi, layered=layered) if name == "reach_safe" else REACH_AND_STAY[name](game, phi)
            for name in methods}


# ====================================================================================== a job's synthesis
def synthesize(
    abstraction: "AbstractionResult",
    *,
    order: str | None = None,
    method: str = "auto",
    max_memory: int | None = None,
    reach_and_stay_methods: Sequence[str] = ("cobuchi", "reach_safe"),
    chain_order: str = "greedy",
    controller_form: str = "auto",
    processes: int | str = 1,
) -> tuple[Game, dict[str, SynthesisResult], dict[str, Any]]:
    """Encode an abstraction, solve its specification, and report.

    ``processes``: for the fixed points' ``∃u.CPre`` (:meth:`Game.predecessors`), an int or ``'auto'`` (see
    :class:`Game`; consensus N = 8 safe + reach 404 s -> 320 s with 2); the helper processes stop before this
    returns.

    ``controller_form``: ``explicit`` (a BDD over states and inputs), ``layered`` (:class:`SynthesisResult`
    ``layers``) or ``auto``, which is ``layered`` for the shared-``w`` CPre: there the explicit controller is
    the largest BDD of the job (consensus N = 8: 2.4 GB as DDDMP, most of the synthesis time).

    Returns
    -------
    game : Game
    results : dict of str to SynthesisResult
        One entry (``safe``, ``reach``, ``reach_avoid``) or one per reach-and-stay method.
    report : dict
        JSON-ready: build times and node counts, per-result summaries.
    """
    from pipelines.spec.regions import abstract_region

    t0 = time.perf_counter()
    game = Game.from_abstraction(abstraction, order=order, method=method, max_memory=max_memory,
                                 chain_order=chain_order, processes=processes)
    build = time.perf_counter() - t0
    m = game.model
    spec = abstraction.spec.specification
    grid = abstraction.network.composed_state_grid()

    def region(name: str) -> Function:
        return m.region(abstract_region(getattr(spec, name), grid, f"specification.{name}"))

    if controller_form not in ("auto", "explicit", "layered"):
        raise ValueError(f"controller_form must be auto, explicit or layered, got {controller_form!r}")
    layered = controller_form == "layered" or (controller_form == "auto" and game.method == "shared")
    try:
        if spec.kind == "safe":
            results = {"safe": safe(game, region("safe"), layered=layered)}
        elif spec.kind == "reach":
            results = {"reach": reach(game, region("target"), layered=layered)}
        elif spec.kind == "reach_avoid":
            results = {"reach_avoid": reach_avoid(game, region("target"), region("avoid"), layered=layered)}
        else:
            results = reach_and_stay(game, region("target"), reach_and_stay_methods, layered=layered)
    finally:
        game.close()
    stats = m.stats()
    report = {
        "order": m.order,
        "method": game.method,
        "chain_order": game.chain_order,
        "build_seconds": build,
        "relation_seconds": dict(m.build_seconds),
        "cpre_setup_seconds": game.setup_seconds,
        "relation_nodes": [t.dag_size for t in game.T],
        "interconnection_nodes": {f"w{j}": p.dag_size for j, p in game.parts.items()},
        "results": {k: r.summary() for k, r in results.items()},
        "parallel": game.parallel,
        "bdd": stats,
    }
    return game, results, report
