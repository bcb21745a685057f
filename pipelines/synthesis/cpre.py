"""The controllable predecessor of the composed abstraction (Section 4.3, Algorithm 5; docs/method.md §6).

The controlled predecessor of a set ``Z`` of composed abstract states is

    CPre(Z)(x̂, û) = M̂(x̂) ≠ ∅  ∧  ∀ŵ ∈ M̂(x̂): ∧_i NB_i(x̂_i, û_i, ŵ_i)  ∧  ∀x̂'. ∧_i T_i(x̂_i, û_i, ŵ_i, x̂'_i) → Z(x̂')

(every admissible internal input lets every subsystem move, and all successors lie in ``Z``). The composed
transition relation is never built: the ``T_i`` stay partitioned and next-state variables are quantified one
subsystem at a time (``and_exists``), docs/method.md §5-6.

Two exact implementations, chosen automatically (:class:`ControllablePredecessor`):

* ``per_subsystem`` (each internal variable is read by at most one subsystem, e.g. the tanks). Then
  ``M̂ = ∧_j M̂_j(x, w_j)`` with disjoint ``w_i`` per subsystem, and ``w`` is quantified before any fixed point:
  ``T̃_i = ∃w_i. M̂_i ∧ T_i``, ``NB'_i = ∀w_i. (M̂_i → NB_i)`` (kept separately: an input that blocks for one
  admissible ``w_i`` must not look admissible), and
  ``CPre(Z) = ∃w.M̂ ∧ ∧_i NB'_i ∧ ¬∃x'. (∧_i T̃_i ∧ ¬Z')``, chained subsystem by subsystem in a greedy
  early-quantification schedule (:func:`schedule`). Exactness: ``∀w∀x'.(∧_i(M̂_i ∧ T_i) → Z') =
  ∀x'.(∧_i ∃w_i(M̂_i ∧ T_i) → Z')`` because the ``w_i`` are disjoint.
* ``shared`` (an internal variable read by several subsystems, e.g. consensus): ``w`` stays shared (quantifying
  it per subsystem would let each subsystem see a different ``w``: sound but conservative, docs/method.md §6).
  ``CPre(Z) = ∃w.M̂ ∧ ¬BLK ∧ ¬∃w.[M̂ ∧ ∃x'.(∧_i T_i ∧ ¬Z')]`` with the blocking part
  ``BLK = ∨_i ∃w.(M̂ ∧ ¬NB_i)`` computed once (∃ distributes over ∨). The step ``∃w.[M̂ ∧ ...]`` is the known
  bottleneck (docs/method.md §6: 67 % of CPre time at N = 8).

Two more, chosen by name only:

* ``chained`` (exact, any network): the parts ``M̂_j`` join the chain as links of their own and each ``ŵ_j`` is
  quantified right after the last link that reads it (:func:`~.schedule.schedule_joint`), instead of carrying every
  ``ŵ`` to one ``∃w`` step at the end. Exact because ``M̂ = ∧_j M̂_j`` and a variable is quantified only once no
  later link reads it; the blocking part is taken per subsystem over the parts it reads (the others' parts are
  non-empty in the admissible pairs already). On the rooms ring (N = 3, spacing 0.1) a reach step takes 0.6-0.9x
  the shared one's time: the chain's largest product, over all ``x``, ``u`` and the ``ŵ`` still open, remains.
* ``per_reader`` (sound, not exact, for shared ``w``): the per-subsystem form on a network whose internal variables
  have several readers, each reader seeing its own ``ŵ``. The environment gets more choices, so its ``CPre`` lies
  inside the exact one, its domains inside the exact domains and its controllers win the exact game; with one
  reader per variable it is ``per_subsystem``. On the rooms ring (N = 3) its iterates equalled the exact ones at
  spacing 0.25 (all 7) and 0.1 (the 3 the exact solver reached), 10x faster at 0.25.

And ``local`` prepares no composed ``CPre`` at all: only the subsystems' relations, non-blocking sets and
interconnection parts, from which :mod:`.contracts` builds one game per subsystem; every composed ``CPre`` call then
refuses.

The fixed points (:mod:`.fixed_points`) that need the controller only at convergence use
:meth:`ControllablePredecessor.predecessors` (``∃u.CPre`` in one ``and_exists``, never materialising ``CPre``).
That call may run elsewhere through a ``partitioned`` factory the caller injects: in parts at once
(:mod:`.partitioned`; helper processes and Dask workers live in ``workers``) or on oxidd's threads
(:mod:`.engine_cpre`); :class:`PartitionFailed` is the failure after which the object goes on in one process.
The free functions :func:`bad_inputs`, :func:`predecessors_of` and :func:`~.at_state.cpre_at_state` take the
ingredients (the chain, the admissible pairs, the shared ``M̂``): the parts and oxidd run them on their own copies,
and a layered controller read back from its files evaluates them at one state.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable, Mapping, Sequence
from typing import TYPE_CHECKING, Any, NamedTuple, Protocol, TypedDict

from pipelines.errors import CompabsError
from pipelines.symbolic.order import default_order
from pipelines.symbolic.relations import interconnection_parts, subsystem_relations
from pipelines.symbolic.symbolic_model import Function, Relational, SymbolicModel, and_exists
from pipelines.symbolic.tree import Say
from pipelines.synthesis.at_state import ChainAtStates, cpre_at_state
from pipelines.synthesis.schedule import Chain, schedule, schedule_joint
from pipelines.synthesis.symmetry import InvariantSets, Symmetry, find_symmetry

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from typing_extensions import Unpack

    from pipelines.abstraction.relation import SubsystemRelation
    from pipelines.interconnection import InterconnectionAbstraction
    from pipelines.network import Network
    from pipelines.symbolic.order import SubsystemLayout


METHODS = ("auto", "per_subsystem", "shared", "chained", "per_reader", "local")
#: Networks above this many subsystems are not searched for interchangeable ones (each candidate pair renames the
#: relations, ``M̂`` and the admissible pairs once; the scalability case's ``M̂`` has 10^5 nodes at N = 1024).
SYMMETRY_MAX_SUBSYSTEMS = 64
CHAIN_ORDERS = ("greedy", "widest_last", "network")
log = logging.getLogger(__name__)


class Within(NamedTuple):
    """The chain and the admissible pairs restricted to a set of states (:meth:`ControllablePredecessor.within`)."""

    chain: Chain
    admissible: Function


class PartitionFailed(CompabsError):
    """A part of a partitioned ``∃u.CPre`` could not be computed (its process died or failed); the message says
    which and why. :meth:`ControllablePredecessor.predecessors` then goes on in one process."""


class Partitioned(Protocol):
    """``∃u.CPre(Z)`` computed in parts at once (what a ``partitioned`` factory returns;
    :class:`~.partitioned.PartitionedCPre`).

    Calls like :meth:`ControllablePredecessor.predecessors` without ``part``; raises :class:`PartitionFailed`
    when a part fails (no answer of that call is read later); :meth:`close` stops it (idempotent); :meth:`report` says how the parts
    ran. One whose attribute ``takes_symmetry`` is true also takes ``symmetry=`` (a :class:`~.symmetry.Symmetry`
    the sets of the call are invariant under): each part then works on the representatives of its states and
    closes its own answer.
    """

    takes_symmetry: bool

    def __call__(self, Z: Function, outside: Function | None, within: Within | None,
                 symmetry: Symmetry | None = None) -> Function: ...

    def close(self) -> None: ...

    def report(self) -> dict[str, Any]:
        """Where the parts ran, calls, the cuts, seconds per part (``ControllablePredecessor.parallel``)."""


PartitionedFactory = Callable[["ControllablePredecessor", int], Partitioned]
"""``factory(cpre, processes)``: a :class:`Partitioned` ``∃u.CPre`` of ``cpre`` in ``processes`` parts (>= 2)."""


class Options(TypedDict, total=False):
    """The keywords of :class:`ControllablePredecessor` beside its relations, as
    :meth:`ControllablePredecessor.from_network` passes them on (the constructor documents each)."""

    method: str
    chain_order: str
    processes: int | str
    parallel_after: float
    partitioned: PartitionedFactory | None
    auto_parts: int | None
    symmetry: bool


def resolve_processes(processes: int | str) -> int:
    """``'auto'``: the CPUs this process may use, at most 4 (each part adds ~5-15 % work); else the int itself."""
    if processes == "auto":
        from pipelines.spec.validate import usable_cpus

        return min(usable_cpus(), 4)
    if isinstance(processes, bool) or not isinstance(processes, int) or processes < 1:
        raise ValueError(f"processes must be 'auto' or a positive int, got {processes!r}")
    return processes


# ====================================================================================== CPre of the ingredients
def bad_inputs(
    model: Relational, chain: Chain, M: Function | None, w_bits: Sequence[str], Z: Function,
    outside: Function | None = None, part: Function | None = None,
) -> Function:
    """State-input pairs with a successor outside ``Z``: ``part ∧ ∃w.[M̂ ∧ outside ∧ ∃x'.(∧_i R_i ∧ ¬Z')]``.

    The chain (``R_i`` = T̃_i or T_i) is conjoined one subsystem at a time; ``M`` is ``None`` for the
    per-subsystem CPre (``w`` already quantified in the chain), else the shared ``∃w`` step follows, the
    bottleneck of docs/method.md §6. ``part`` is conjoined into the chain's first operand and into ``M̂``; it reads no
    next-state bit, so it commutes with ``∃x'``. A set of current states commutes with ``∃w`` too, and the result
    is exact on it; a set of ``ŵ`` cells (the ``w`` and split cuts' ranges, :mod:`.parts`) gives the pairs bad for
    some admissible ``ŵ`` among them. ``M`` may come already conjoined with what the caller keeps (a Dask
    worker's ``M̂`` on the representatives).
    """
    acc = ~model.to_next(Z)
    if part is not None:
        acc &= part
    for rel, xn_bits in chain:
        acc = model.and_exists(acc, rel, xn_bits)
    if M is not None:
        # the part first: a range of ŵ (a cluster's part) cuts M̂ down to its cells before the larger product with
        # ``outside`` (16 parts of consensus N = 6, a Reach(Safe): the other way costs the parts 10x the CPU)
        care = M if part is None else M & part
        if outside is not None:
            care &= outside
        acc = model.and_exists(care, acc, list(w_bits))
    return acc


def predecessors_of(
    model: Relational, chain: Chain, admissible: Function, M: Function | None, w_bits: Sequence[str],
    u_bits: Sequence[str], Z: Function, outside: Function | None = None, part: Function | None = None,
    states: Function | None = None,
) -> Function:
    """``part ∧ states ∧ ∃u.CPre(Z)`` from the CPre ingredients (:meth:`ControllablePredecessor.predecessors`).

    ``M`` for the shared method, else ``None``. ``part`` restricts :func:`bad_inputs` (the chain's first operand
    too) and the admissible pairs; ``states`` only where the result is read (``M̂ ∧ outside`` at ``∃w``, the
    admissible pairs), as the windows take theirs: the orbit representatives in the chain blow it up (the largest
    call of consensus N = 8 takes about 2.7x as long with them there as at ``∃w``).
    """
    if states is not None and M is None:  # the per-subsystem chain has no later step to take them
        part, states = (states if part is None else part & states), None
    if states is not None:
        admissible, outside = admissible & states, (states if outside is None else outside & states)
    if part is not None:
        admissible = admissible & part
    bad = bad_inputs(model, chain, M, w_bits, Z, outside, part)
    return model.and_exists(admissible, ~bad, list(u_bits))


# ====================================================================================== the object
class ControllablePredecessor:
    """``CPre`` of the composed abstraction with partitioned relations (module docstring; docs/method.md §6).

    Parameters
    ----------
    model : SymbolicModel
    transitions, nonblocking : sequence of Function, one per subsystem (network order)
        ``T_i(x_i, u_i, w_i, x'_i)`` and ``NB_i(x_i, u_i, w_i)`` (:func:`~.symbolic.relations.subsystem_relations`).
    interconnection : mapping of int to Function
        ``M̂_j(x, w_j)`` per internal variable (:func:`~.symbolic.relations.interconnection_parts`).
    method : {'auto', 'per_subsystem', 'shared', 'chained', 'per_reader', 'local'}
        ``auto`` picks ``per_subsystem`` exactly when every internal variable is read by at most one
        subsystem. Both are exact; ``shared`` and ``chained`` are exact for every network; ``per_reader`` is sound
        and exact only where ``per_subsystem`` applies; ``local`` prepares no composed CPre (module docstring).
    chain_order : {'greedy', 'widest_last', 'network'}
        Order in which the relations are conjoined into ``¬Z'`` (see :func:`schedule`).
    processes : int or 'auto'
        Parts of :meth:`predecessors` run at once by ``partitioned`` (this process included); ``1``: one
        process; ``'auto'``: :func:`resolve_processes` for the shared CPre, 1 for the others (on the
        10 tanks each half of a split CPre takes as long as the whole, since the halves share most sub-results
        that one process computes once).
    parallel_after : float
        Seconds one single-process :meth:`predecessors` call must take before ``partitioned`` is started
        (starting helper processes costs ~0.5 s; small games never need them). ``0``: from the first call on (where
        many workers make the whole synthesis short, one process's first call is a large share of it: about an
        eighth for consensus N = 7 on 16 workers).
    partitioned : callable, optional
        ``partitioned(cpre, processes)`` -> :class:`Partitioned`: how to run :meth:`predecessors` in parts
        (:class:`~.partitioned.PartitionedCPre`; ``workers.processes.partitioned_cpre.PartitionedPredecessors``
        runs them in helper processes, ``workers.dask_cpre.on_cluster`` on the job's Dask workers).
        Without it every call runs in this process, whatever ``processes`` says.
    auto_parts : int, optional
        What ``processes='auto'`` means for the shared CPre when the parts do not run on this machine's CPUs
        (the job's Dask cluster: :func:`workers.dask_cpre.parts_for`); default :func:`resolve_processes`.
    symmetry : bool
        Compute :meth:`predecessors` of invariant sets on one state per orbit of the interchangeable subsystems
        and close the result (:mod:`.symmetry`; exact). Looked for at the first call, for networks of at most
        :data:`SYMMETRY_MAX_SUBSYSTEMS` subsystems.

    Attributes
    ----------
    chain : list of (Function, list of str)
        The relations ``T̃_i`` (per-subsystem) or ``T_i`` (shared) in schedule order, each with the next-state
        bits it lets quantify.
    admissible : Function
        Pairs ``(x̂, û)`` with ``M̂(x̂) ≠ ∅`` at which no admissible ``ŵ`` blocks a subsystem.
    M : Function or None
        ``M̂(x, w)`` for the shared CPre, ``None`` for the others (``w`` is inside the chain).
    level : int
        0; ``k`` for the game on blocks of ``2^k`` cells per coordinate (:func:`~.quotient.quotient`).
    """

    level: int = 0

    def __init__(
        self,
        model: SymbolicModel,
        transitions: Sequence[Function],
        nonblocking: Sequence[Function],
        interconnection: Mapping[int, Function],
        method: str = "auto",
        chain_order: str = "greedy",
        *,
        processes: int | str = 1,
        parallel_after: float = 1.0,
        partitioned: PartitionedFactory | None = None,
        auto_parts: int | None = None,
        symmetry: bool = True,
    ) -> None:
        if isinstance(processes, int) and processes < 1:
            raise ValueError(f"processes must be at least 1, got {processes}")
        self.parallel_after = float(parallel_after)
        self.partitioned = partitioned
        self._pool: Partitioned | None = None
        self._last_pool: Partitioned | None = None
        self._pool_error: str | None = None  # why the parts stopped, if one failed
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
        if processes == "auto" and method in ("per_subsystem", "chained", "per_reader", "local"):
            self.processes = 1
        elif processes == "auto" and auto_parts is not None:
            self.processes = max(1, int(auto_parts))
        else:
            self.processes = resolve_processes(processes)
        self.u_bits = model.u_bits
        self.use_symmetry = symmetry
        self._symmetry: Symmetry | None | bool = False  # False: not looked for yet
        self._invariant = InvariantSets()
        self._at: ChainAtStates | None = None  # the chain's cofactors at the states cpre_at met
        self.M: Function | None = None
        self.w_bits: list[str] = []
        self.setup_seconds = 0.0
        t0 = time.perf_counter()
        with model.guard(f"preparing the {method} CPre"):
            if method in ("per_subsystem", "per_reader"):
                self._prepare_per_subsystem()
            elif method == "chained":
                self._prepare_chained()
            elif method == "local":
                self.chain: Chain = []
                self.admissible = model.x_domain & model.u_domain
            else:
                self._prepare_shared()
        self.setup_seconds = time.perf_counter() - t0

    @classmethod
    def from_network(
        cls,
        network: Network,
        relations: Mapping[str, SubsystemRelation],
        interconnection: InterconnectionAbstraction,
        *,
        order: str | None = None,
        max_memory: int | None = None,
        share: str = "rename",
        say: Say | None = None,
        **options: Unpack[Options],
    ) -> ControllablePredecessor:
        """Encode an abstraction (its network, subsystem relations and interconnection) and prepare its CPre.

        ``order`` defaults to :func:`~.symbolic.order.default_order` (``interleaved`` where each internal
        variable has one reader, ``shared_top`` otherwise: the orders docs/method.md §6 found best for the tanks and
        consensus); ``max_memory`` is CUDD's (:class:`~.symbolic.symbolic_model.SymbolicModel`), ``share`` how identical
        subsystems share their relations (:func:`~.symbolic.relations.subsystem_relations`), ``say`` is told how
        building them goes (:data:`~.symbolic.tree.Say`); ``options`` are the
        constructor's (:class:`Options`).
        """
        if order is None:  # the chained CPre's products and the local games follow the couplings: the blocks' order
            order = "interleaved" if options.get("method") in ("chained", "local") else default_order(network.subsystems)
        model = SymbolicModel.from_network(network, interconnection, order=order, max_memory=max_memory)
        T, NB = subsystem_relations(model, relations, share=share, say=say)
        parts = interconnection_parts(model, interconnection.nodes)
        return cls(model, T, NB, parts, **options)

    def _prepare_per_subsystem(self) -> None:
        m, bdd = self.model, self.bdd
        self.admissible = m.x_domain & m.u_domain
        for j, part in self.parts.items():  # M̂(x̂) ≠ ∅: every w_j has some admissible cell
            self.admissible &= bdd.exist(m.bits[f"w{j}"], part)
        chain: Chain = []
        for s, t, nb in zip(m.subsystems, self.T, self.NB):
            Mi, wb = self.read_part(s)
            t_tilde = and_exists(Mi, t, wb)  # T̃_i = ∃w_i. M̂_i ∧ T_i
            nb_prime = ~and_exists(Mi, ~nb, wb)  # NB'_i = ∀w_i. (M̂_i → NB_i)
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
        # ∃w.(M̂ ∧ ¬∧NB_i) in one step: the disjunction of the small ¬NB_i first. One ∃w per subsystem instead
        # walks M̂ N times (the 1,024-coordinate max tree: M̂ 328 k nodes; at N = 256 13.3 s against 0.4 s).
        some_blocks = bdd.false
        for nb in self.NB:
            some_blocks |= ~nb
        blocked = and_exists(M, some_blocks, self.w_bits)
        self.admissible = m.x_domain & m.u_domain & bdd.exist(self.w_bits, M) & ~blocked
        chain = [(t, m.bits_of(m.subsystem_digits(s)["xn"])) for s, t in zip(m.subsystems, self.T)]
        self.chain = schedule(chain, set(m.xn_bits), bdd, self.chain_order)

    def _prepare_chained(self) -> None:
        m, bdd = self.model, self.bdd
        readers_of: dict[int, list[int]] = {}
        for k, s in enumerate(m.subsystems):
            for j in s.reads:
                readers_of.setdefault(j, []).append(k)
        # M̂(x̂) ≠ ∅ part by part (the w_j are disjoint); a subsystem blocks for some admissible ŵ exactly when it
        # does for some admissible ŵ of the variables it reads, the others' parts being non-empty already.
        admissible = m.x_domain & m.u_domain
        for j, part in self.parts.items():
            admissible &= bdd.exist(m.bits[f"w{j}"], part)
        for s, nb in zip(m.subsystems, self.NB):
            Mi, wb = self.read_part(s)
            admissible &= ~and_exists(Mi, ~nb, wb)
        self.admissible = admissible
        items: list[tuple[Function, list[str]]] = [
            (t, m.bits_of(m.subsystem_digits(s)["xn"])) for s, t in zip(m.subsystems, self.T)]
        items += [(self.parts[j], []) for j in sorted(readers_of)]  # an unread ŵ_j is only M̂(x̂) ≠ ∅
        w_of = {b: j for j in readers_of for b in m.bits[f"w{j}"]}
        self.chain = schedule_joint(items, set(m.xn_bits), set(w_of), bdd, self.chain_order)
        self.M, self.w_bits = None, []  # w is quantified inside the chain

    def read_part(self, s: SubsystemLayout) -> tuple[Function, list[str]]:
        """``M̂_s``: the parts of ``M̂`` for the internal variables subsystem ``s`` reads, conjoined, and their ``w``
        bits (``true`` and none for a subsystem that reads none)."""
        Mi = self.bdd.true
        for j in s.reads:
            Mi &= self.parts[j]
        return Mi, self.model.bits_of([f"w{j}" for j in s.reads])

    # ------------------------------------------------------------------ CPre
    def within(self, S: Function) -> Within:
        """``CPre`` ingredients restricted to the current states of ``S`` (exact on ``S`` only).

        Each relation is conjoined with ``S`` projected on the current-state coordinates it reads: for a state
        ``x̂ ∈ S`` those coordinates are the ones of some state of ``S``, so ``∧_i (R_i ∧ ∃(x̂ ∉ supp R_i). S) =
        ∧_i R_i`` there, and the admissible pairs are conjoined with ``S``. Every ``CPre`` and predecessor
        computed with the result is exact on ``S`` and empty outside it. Loops whose iterates stay inside ``S``
        (the safety fixed point) pass it: on the 10 tanks it made the safety fixed point nearly twice as fast
        (the projections of a box are boxes; restricting to the projections of each iterate instead was slower).
        """
        self._composed()
        bdd, m = self.bdd, self.model
        x_bits = set(m.x_bits)
        chain = []
        for rel, xn_bits in self.chain:
            outside_support = sorted(x_bits - set(bdd.support(rel)))
            chain.append((rel & bdd.exist(outside_support, S), xn_bits))
        self._invariant.may_join(S)
        return Within(chain, self.admissible & S)

    def cpre(self, Z: Function, within: Within | None = None) -> Function:
        """``CPre(Z)`` over current-state and input bits (see the module docstring).

        ``within``: :meth:`within` ``(S)`` to compute it on ``S`` only (default: everywhere).
        """
        self._composed()
        chain, admissible = (self.chain, self.admissible) if within is None else within
        with self.model.guard("computing CPre"):
            return admissible & ~bad_inputs(self.model, chain, self.M, self.w_bits, Z)

    def cpre_at(self, state: Mapping[str, bool], Z_next: Function) -> Function:
        """``CPre(Z)`` at one state, a function of the input bits only (:func:`cpre_at_state`).

        ``state``: values of all current-state bits (:meth:`SymbolicModel.state_assignment`); ``Z_next``: ``Z``
        over next-state bits (``model.to_next(Z)``; callers cache it per set). The chain's cofactors are kept
        across calls (:class:`~.at_state.ChainAtStates`) until :meth:`close`.
        """
        self._composed()
        if self._at is None:
            self._at = ChainAtStates(self.model, self.chain)
        return cpre_at_state(self.model, self.chain, self.admissible, self.M, state, Z_next, self._at)

    def _composed(self) -> None:
        if self.method == "local":
            raise ValueError("the 'local' method prepares no composed CPre (module docstring): build the "
                             "ControllablePredecessor with another method")

    def pre(self, cpre: Function) -> Function:
        """``∃u. cpre``: states with some good input."""
        return self.bdd.exist(self.u_bits, cpre)

    def predecessors(
        self, Z: Function, outside: Function | None = None, within: Within | None = None,
        part: Function | None = None, states: Function | None = None,
    ) -> Function:
        """``∃u. CPre(Z)`` without materialising ``CPre(Z)`` (one ``and_exists`` over the inputs).

        Fixed points that need the controller only at convergence use this in their loop. With ``outside``
        the result is exact only on states in ``outside`` (a reach loop passes ``¬Z``: states already won need
        no answer); the shared ``∃w.M̂ ∧ ...`` step then works on ``M̂ ∧ outside``, which takes about 20 % less
        time on consensus N = 5. ``within``: as in :meth:`cpre`. ``part``: a set of current states; the
        result is ``part ∧ ∃u.CPre(Z)``, computed on that part only, in this process (and ``states``, with a
        ``part``: see :func:`predecessors_of`).

        Without ``part``, when the network has interchangeable subsystems (:attr:`symmetry`) and ``Z``,
        ``outside`` and ``within`` are invariant under them, the call is computed on one state per orbit and closed
        (:mod:`.symmetry`): the same result, also in the parts and on oxidd when they take the symmetry. A
        ``partitioned`` factory takes the calls without ``part`` when :meth:`_start_pool` says. If it fails
        (:class:`PartitionFailed`), this call and the later ones run here (:attr:`parallel` ``["stopped"]`` says
        why); any other error (CUDD out of memory in a part: a BDDMemoryError) is raised, as it would be here."""
        self._composed()
        if states is not None and part is None:  # a whole call finds its own symmetry
            raise ValueError("predecessors: states are taken with a part only")
        if part is None and self._pool is None:
            self._start_pool(None)
        sym = self._symmetry_for(Z, outside, within) if part is None else None
        result = self._predecessors(Z, outside, within, part, whole=part is None, symmetry=sym, states=states)
        if sym is not None:
            self._invariant.step(sym, Z, result)  # closed under the symmetry: invariant by construction
        return result

    def _predecessors(self, Z: Function, outside: Function | None, within: Within | None, part: Function | None,
                      whole: bool, symmetry: Symmetry | None = None, states: Function | None = None) -> Function:
        """:meth:`predecessors` on ``part`` (all states if ``None``); ``whole``: this call stands for a whole one
        (the parts may run it, and may start after it); ``symmetry``: computed on its representatives and closed
        (``part`` is then ``None``), by the parts too when they take it; ``states``: as in :meth:`predecessors`."""
        if part is None and self._pool is not None:
            try:
                return self._pool(Z, outside, within, symmetry)
            except PartitionFailed as exc:
                # A part died or failed (killed, out of memory in its process): it is recomputed here, and so is
                # everything after; the answer is the same, only slower. The report says why.
                self._drop_pool(one_process=True)
                self._pool_error = str(exc)
                log.warning("partitioned CPre stopped (%s); going on in one process", exc)
            except BaseException:
                # The error closed the parts; later calls run here, and no new parts start.
                self._drop_pool(one_process=True)
                raise
        chain, admissible = (self.chain, self.admissible) if within is None else within
        t0 = time.perf_counter()
        with self.model.guard("computing CPre"):
            result = predecessors_of(self.model, chain, admissible, self.M, self.w_bits, self.u_bits, Z, outside,
                                     part, symmetry.representatives if symmetry is not None else states)
            if symmetry is not None:
                result = symmetry.close(result)
        if whole:
            self._start_pool(time.perf_counter() - t0)
        return result

    def _start_pool(self, seconds: float | None) -> None:
        """Start ``partitioned`` before a whole call (``seconds`` None) or after one that took ``seconds`` here, if
        it says so (another engine: ``starts``, :mod:`.engine_cpre`) or, for parts, from ``parallel_after``."""
        p = self.partitioned
        if p is not None and hasattr(p, "starts"):
            wanted = p.starts(self, seconds)
        else:
            late_enough = self.parallel_after <= 0 if seconds is None else seconds >= self.parallel_after
            wanted = self.processes > 1 and late_enough
        if p is None or not wanted:
            return
        try:
            self._pool = p(self, self.processes)
        except PartitionFailed as exc:  # e.g. the other engine could not take the CPre: this process goes on
            self._pool_error, self.partitioned = str(exc), None
            log.warning("partitioned CPre not started (%s); going on in one process", exc)

    # ------------------------------------------------------------------ symmetry
    @property
    def symmetry(self) -> Symmetry | None:
        """The interchangeable subsystems (:func:`~.symmetry.find_symmetry`), looked for once; ``None`` if there are
        none, if ``symmetry=False``, or above :data:`SYMMETRY_MAX_SUBSYSTEMS` subsystems."""
        if self._symmetry is False:
            found = None
            if self.use_symmetry and len(self.model.subsystems) <= SYMMETRY_MAX_SUBSYSTEMS:
                with self.model.guard("looking for interchangeable subsystems"):
                    found = find_symmetry(self.model, self.chain, self.M, self.admissible)
            self._symmetry = found
        return self._symmetry if isinstance(self._symmetry, Symmetry) else None

    def _symmetry_for(self, Z: Function, outside: Function | None, within: Within | None) -> Symmetry | None:
        """The symmetry to compute ``∃u.CPre(Z)`` with, if every set of the call is invariant under it and the
        running parts (if any) take it along (:attr:`Partitioned.takes_symmetry`); else ``None`` (the plain
        computation)."""
        sym = self.symmetry
        if sym is None or (self._pool is not None and not self._pool.takes_symmetry):
            return None
        # a permutation maps ¬Z to ¬(its image of Z): the reach loop's ``outside`` needs no check of its own
        if not self._invariant.holds(sym, Z) or (outside is not None and outside != ~Z
                                                 and not self._invariant.holds(sym, outside)):
            return None
        if within is not None and not sym.invariant(within.admissible):  # 0.03 s on consensus N = 8
            return None
        return sym

    # ------------------------------------------------------------------ the parts
    def close(self) -> None:
        """Stop the partitioned ``∃u.CPre``, if one was started, and drop the sets known invariant and the chain's
        kept cofactors (idempotent)."""
        self._invariant.forget()
        self._at = None
        if self._pool is not None:
            self._pool.close()
            self._drop_pool(one_process=False)

    def _drop_pool(self, one_process: bool) -> None:
        """Forget the (closed) parts, keeping them for :attr:`parallel`; ``one_process``: start none again."""
        self._last_pool, self._pool = self._pool, None
        if one_process:
            self.processes, self.partitioned = 1, None

    @property
    def parallel(self) -> dict[str, Any]:
        """How the partitioned ``∃u.CPre`` ran (empty if it never started): :meth:`Partitioned.report` (where, calls,
        the digits it cuts along, the cuts, seconds per part, ...), and ``stopped`` (why) if it failed, even to start,
        and the CPre went on in one process."""
        p = self._pool if self._pool is not None else self._last_pool
        out = {} if p is None else p.report()
        if self._pool_error is not None:
            out["stopped"] = f"{self._pool_error}; the later calls ran in one process"
        return out
