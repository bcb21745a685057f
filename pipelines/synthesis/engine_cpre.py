"""``∃u.CPre(Z)`` on another BDD engine: oxidd on several threads, the fixed points staying in CUDD (issue 49).

CUDD is single-threaded and, as ``dd``'s wheel bundles it, built without optimisation. oxidd (Rust) computes the
same relational products with complement edges on several threads. :class:`OxiddPredecessors` is what a
:class:`~.cpre.ControllablePredecessor` runs its whole ``∃u.CPre`` calls on when its job's engine is ``oxidd``
(:class:`OnOxidd`): it mirrors the CPre's ingredients into an oxidd manager once (the chain, the admissible
pairs, the shared ``M̂``; the sets of each ``within`` and of each symmetry the first time a call brings them),
and per call hands ``Z`` over, computes :func:`~.cpre.predecessors_of` there (the same code, on the
:class:`~pipelines.symbolic.oxidd_mirror.OxiddMirror`), closes the answer under the symmetry with oxidd's
substitution and hands it back (:mod:`pipelines.symbolic.oxidd_mirror`: a few milliseconds per 10^4 nodes).

The results are the same sets (BDDs are canonical; the tests compare them). The fixed points, the controllers and
everything else stay in CUDD. It comes in through :class:`~.cpre.ControllablePredecessor`'s ``partitioned`` seam
when :meth:`OnOxidd.starts` says, and any error in it (oxidd out of nodes, a failed transfer) is a
:class:`~.cpre.PartitionFailed`: the call and the later ones then run in CUDD, with the same answer.

On a 2-core machine, consensus N = 8's Reach(Safe): 153 s in one CUDD process, 96-104 s on two Dask workers, 71 s
in oxidd on one thread and 45 s on two (``python bench/synthesis.py``, docs/benchmarks.md).
"""

from __future__ import annotations

import time
from typing import TYPE_CHECKING, Any

from pipelines.synthesis.cpre import PartitionFailed, predecessors_of

if TYPE_CHECKING:  # pragma: no cover - imports for type hints only
    from pipelines.symbolic.symbolic_model import Function
    from pipelines.synthesis.cpre import ControllablePredecessor, Within
    from pipelines.synthesis.symmetry import Symmetry

#: A shared CPre with this many current-state bits or more goes to oxidd from its first call (consensus N = 5 on).
AT_ONCE_BITS = 30

ENGINES = ("auto", "cudd", "oxidd")
"""The BDD engines of ``∃u.CPre`` (``options.synthesis_engine``): ``auto`` is ``oxidd`` where it is installed."""


def resolve_engine(engine: str) -> str:
    """``'cudd'`` or ``'oxidd'`` for ``engine`` in :data:`ENGINES` (``auto``: oxidd where it can be imported).

    Raises
    ------
    ValueError
        ``engine`` unknown, or ``oxidd`` asked for and not installed.
    """
    from pipelines.symbolic.oxidd_mirror import oxidd_available

    if engine not in ENGINES:
        raise ValueError(f"the synthesis engine must be one of {', '.join(ENGINES)}, got {engine!r}")
    if engine == "auto":
        return "oxidd" if oxidd_available() else "cudd"
    if engine == "oxidd" and not oxidd_available():
        raise ValueError("the synthesis engine 'oxidd' is not installed (pip install oxidd)")
    return engine


class OnOxidd:
    """A ``partitioned`` factory of :class:`~.cpre.ControllablePredecessor` giving :class:`OxiddPredecessors` on
    ``threads`` threads (default :func:`~pipelines.spec.validate.usable_cpus`), an apply cache of ``cache`` entries and room for ``nodes``
    nodes (defaults :data:`~pipelines.symbolic.oxidd_mirror.OXIDD_CACHE` and ``OXIDD_NODES``).

    It starts (:meth:`starts`) with the first whole call of a shared CPre over at least 2^:data:`AT_ONCE_BITS` state
    codes, whose calls are nearly all of its synthesis, and otherwise once a call in CUDD took the CPre's
    ``parallel_after`` seconds: short calls (the tanks: 23 of 0.03-0.24 s; consensus N = 4) would pay more for the
    manager (0.9 s and 320 MB for its apply cache) and the hand-overs than oxidd saves.
    """

    def __init__(self, threads: int | None = None, cache: int | None = None, nodes: int | None = None) -> None:
        from pipelines.spec.validate import usable_cpus

        self.threads = usable_cpus() if threads is None else int(threads)
        if self.threads < 1:
            raise ValueError(f"oxidd needs at least one thread, got {threads}")
        self.cache, self.nodes = cache, nodes

    @staticmethod
    def starts(cpre: ControllablePredecessor, seconds: float | None) -> bool:
        """Whether to take ``cpre``'s calls now: before a whole call (``seconds`` None) or after one that took
        ``seconds`` in CUDD."""
        if seconds is None:
            return cpre.parallel_after <= 0 or (cpre.method == "shared" and len(cpre.model.x_bits) >= AT_ONCE_BITS)
        return seconds >= cpre.parallel_after

    def __call__(self, cpre: ControllablePredecessor, processes: int) -> OxiddPredecessors:
        return OxiddPredecessors(cpre, self.threads, self.cache, self.nodes)


class OxiddPredecessors:
    """:meth:`~.cpre.ControllablePredecessor.predecessors` of ``cpre`` computed in oxidd on ``threads`` threads
    (module docstring); the :class:`~.cpre.Partitioned` protocol."""

    takes_symmetry = True

    def __init__(self, cpre: ControllablePredecessor, threads: int, cache: int | None = None,
                 nodes: int | None = None) -> None:
        from pipelines.symbolic.oxidd_mirror import OXIDD_CACHE, OXIDD_NODES, OxiddMirror

        t0 = time.perf_counter()
        try:
            self.mirror = OxiddMirror(cpre.model, threads, nodes=OXIDD_NODES if nodes is None else int(nodes),
                                      cache=OXIDD_CACHE if cache is None else int(cache))
            put = self.mirror.put
            self._whole = ([(put(rel), list(bits)) for rel, bits in cpre.chain], put(cpre.admissible))
            self._M = None if cpre.M is None else put(cpre.M)
        except Exception as exc:  # noqa: BLE001 - any failure of the other engine: the CPre stays in CUDD
            raise PartitionFailed(f"oxidd could not take the CPre ({type(exc).__name__}: {exc})") from exc
        self.threads = threads
        self._bits = (list(cpre.w_bits), list(cpre.u_bits))  # not cpre itself: it holds this object
        self._within: dict[int, tuple[Within, tuple[list[tuple[Any, list[str]]], Any]]] = {}
        self._symmetry: dict[int, tuple[Symmetry, Any, list[Any]]] = {}
        self.calls, self.seconds, self.transfer_seconds = 0, 0.0, time.perf_counter() - t0
        self.per_call: list[float] = []

    def __call__(self, Z: Function, outside: Function | None = None, within: Within | None = None,
                 symmetry: Symmetry | None = None) -> Function:
        t0 = time.perf_counter()
        try:
            result = self._call(Z, outside, within, symmetry)
        except Exception as exc:  # noqa: BLE001 - as above
            self.close()  # the CPre goes on in CUDD: oxidd's nodes are not needed again
            raise PartitionFailed(f"oxidd failed in a CPre ({type(exc).__name__}: {exc})") from exc
        self.calls += 1
        self.per_call.append(round(time.perf_counter() - t0, 3))
        self.seconds += self.per_call[-1]
        return result

    def _call(self, Z: Function, outside: Function | None, within: Within | None,
              symmetry: Symmetry | None) -> Function:
        m, (w_bits, u_bits) = self.mirror, self._bits
        t0 = time.perf_counter()
        Zo = m.put(Z)
        out = None if outside is None else ~Zo if outside == ~Z else m.put(outside)
        chain, admissible = self._mirrored(within)
        R, word = self._symmetric(symmetry) if symmetry is not None else (None, [])
        self.transfer_seconds += time.perf_counter() - t0
        result = predecessors_of(m, chain, admissible, self._M, w_bits, u_bits, Zo, out, None, R)
        for swap in word:  # G · result, as Symmetry.close
            result = result | m.substitute(result, swap)
        t0 = time.perf_counter()
        answer = m.get(result)
        self.transfer_seconds += time.perf_counter() - t0
        return answer

    def _mirrored(self, within: Within | None) -> tuple[list[tuple[Any, list[str]]], Any]:
        """The chain and the admissible pairs (of ``within`` if given) in oxidd; a ``within`` mirrored once."""
        if within is None:
            return self._whole
        kept = self._within.get(id(within))
        if kept is None or kept[0] is not within:
            put = self.mirror.put
            kept = (within, ([(put(rel), list(bits)) for rel, bits in within.chain], put(within.admissible)))
            self._within = {**dict(list(self._within.items())[-3:]), id(within): kept}  # the loops use few
        return kept[1]

    def _symmetric(self, symmetry: Symmetry) -> tuple[Any, list[Any]]:
        """The orbit representatives and the closing word's renamings of ``symmetry``, in oxidd, made once."""
        kept = self._symmetry.get(id(symmetry))
        if kept is None or kept[0] is not symmetry:
            m = self.mirror
            kept = (symmetry, m.put(symmetry.representatives), [m.renaming(pairs) for pairs in symmetry.word_pairs])
            self._symmetry = {id(symmetry): kept}
        return kept[1], kept[2]

    def close(self) -> None:
        """Drop the mirrored functions and the manager with its nodes (idempotent; :meth:`report` stays): the CPre
        keeps a closed object for its report while the job goes on to its controllers and closed loops."""
        self._whole, self._M, self._within, self._symmetry = ([], None), None, {}, {}
        mirror = self.__dict__.pop("mirror", None)
        if mirror is not None:
            mirror.close()

    def report(self) -> dict[str, Any]:
        """Where the calls ran (``ControllablePredecessor.parallel``)."""
        return {"on": f"oxidd, {self.threads} thread{'s' if self.threads > 1 else ''}", "processes": 1,
                "threads": self.threads, "calls": self.calls, "call_seconds": round(self.seconds, 3),
                "transfer_seconds": round(self.transfer_seconds, 3), "per_call_seconds": self.per_call}
