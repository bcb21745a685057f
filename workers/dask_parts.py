"""The worker's side of the partitioned ``∃u.CPre`` on Dask (:mod:`workers.dask_cpre` is the caller's side).

:func:`receive` (run on every worker) keeps a CPre's problem as sent; :func:`compute_part` and :func:`join_part` are
the Dask tasks: each finds the problem in its worker's memory (:data:`_HELD`, loaded by the worker's first part of
that problem into a CUDD manager of its own), computes its part there by :mod:`pipelines.synthesis.parts` and
answers with a :class:`Part`. :func:`forget` drops a CPre's problems when it closes. Which parts a call has, and
why each is exact, is :mod:`pipelines.synthesis.partitioned`'s business.
"""

from __future__ import annotations

import time
import uuid
from collections import OrderedDict
from collections.abc import Iterator, Sequence
from typing import Any, NamedTuple

from pipelines.symbolic.files import from_bytes, to_bytes
from pipelines.symbolic.symbolic_model import Function
from pipelines.synthesis.parts import Outside, PartSpec, Problem, join, solve, symmetry, unpack

HELD_PROBLEMS = 2
"""Problems a worker keeps loaded (a safety loop's ``within`` problem and the plain one alternate in
Reach(Safe)); older ones are dropped with their CUDD manager when no other problem of theirs is held."""

SENT_PROBLEMS = 16
"""Problems a worker keeps as sent (:func:`receive`), to load again when :data:`HELD_PROBLEMS` pushed one out (jobs
sharing a cluster take turns on its workers). A CPre's problems go when it closes (:func:`forget`); the bound is
for those whose job's process died first."""

KEPT_ANSWERS = 8
"""How many first-phase answers of the split cut a worker keeps (:data:`_KEPT`; a join that ran elsewhere leaves
its range's answer here until it is pushed out; with several parts per worker a worker computes several first
phases of a call before their joins)."""


class Part(NamedTuple):
    """What a part's task returns."""

    blob: bytes
    """Its answer as DDDMP bytes."""
    seconds: float
    """The seconds it computed (wall), the problem's loading not counted."""
    began: float
    """The wall-clock time (``time.time()``) it began computing, after its worker loaded the problem."""
    entered: float
    """The wall-clock time its task was entered on the worker (before the loading)."""
    where: str
    """The worker's address (empty outside a Dask task)."""
    cpu: float
    """The CPU seconds of its computing thread: what the part costs whatever else shares the machine's cores (on
    a machine with fewer cores than workers its wall seconds are mostly waiting for one)."""
    kept: str = ""
    """Of the split cut's first phase: the key under which its worker keeps the answer (:data:`_KEPT`)."""
    ended: float = 0.0
    """The wall-clock time it ended computing (of the split cut's second phase, the second phase's end: the two
    phases may be apart, the second waiting for the first phases of other ranges)."""
    phases: tuple[tuple[str, float, float], ...] = ()
    """Where each phase of the answer ran, with its seconds and CPU seconds, in order (one for a one-phase part, two
    for the split cut's second phase): what each worker was busy with in a call (``DaskPredecessors.history``)."""


class ProblemMissing(RuntimeError):
    """A part named a problem its worker was not sent (it joined the cluster, or restarted, after the sending)."""


class Held(NamedTuple):
    """A CPre's problem as a worker holds it."""

    problem: Problem
    owner: str
    """The key of the CPre's model (shared by its problems)."""


#: Per worker process: problem key -> the problem loaded, least recently used first.
_HELD: OrderedDict[str, Held] = OrderedDict()
#: Per worker process: problem key -> the problem as sent (:func:`receive`), newest last.
_SENT: OrderedDict[str, dict[str, Any]] = OrderedDict()
#: Per worker process: the split cut's first-phase answers computed here, newest last, so that the second phase of
#: the same range (placed on the same worker) takes its own range's pairs as they are instead of reading their bytes
#: back: a third of the second phase's reading (the others' pairs come from other workers).
_KEPT: OrderedDict[str, Function] = OrderedDict()


def receive(key: str, payload: dict[str, Any]) -> None:
    """Keep a CPre's problem (:func:`~pipelines.synthesis.parts.pack`), sent to every worker at once
    (``client.run``), until its first part here loads it (:func:`held`), and after, to load again:
    :data:`SENT_PROBLEMS` at most, the newest last.

    Why not a scattered future that the parts depend on: Dask brings every dependency to a task's worker before it
    runs, and its active memory manager drops the replicas no waiting task needs a few seconds after a call, so at
    each call every worker would fetch the whole problem again from the one worker left holding it, though it keeps
    the problem loaded all along. On 16 workers (consensus N = 7) that delays the last part of each call by several
    times what it waits with the memory manager stopped, seconds summed over the calls.
    """
    _SENT[key] = payload
    _SENT.move_to_end(key)
    while len(_SENT) > SENT_PROBLEMS:
        _SENT.popitem(last=False)


def held(key: str) -> Problem:
    """The problem ``key`` in this worker's CUDD manager: loaded once from what :func:`receive` kept (a
    :class:`ProblemMissing` if nothing was), then kept among the :data:`HELD_PROBLEMS` most recently used."""
    h = _HELD.get(key)
    if h is not None:
        _HELD.move_to_end(key)
        return h.problem
    payload = _SENT.get(key)
    if payload is None:
        raise ProblemMissing(f"this worker was not sent the CPre problem {key} (it joined or restarted since)")
    _SENT.move_to_end(key)
    # A model is shared by the problems of one CPre (same header): a new manager per problem would reload the
    # variables and leave the older problems' nodes in another manager.
    model = next((h.problem.model for h in _HELD.values() if h.owner == payload["model"]), None)
    problem = unpack(payload, model)
    _HELD[key] = Held(problem, payload["model"])
    while len(_HELD) > HELD_PROBLEMS:
        _HELD.popitem(last=False)
    return problem


def _where() -> str:
    """The address of the Dask worker running this task, ``""`` outside one (a part called directly)."""
    try:
        from distributed import get_worker

        return str(get_worker().address)
    except ValueError:
        return ""


def compute_part(key: str, spec: PartSpec, Z: bytes, outside: Outside,
                 classes: Sequence[Sequence[int]] | None = None, keep: bool = False) -> Part:
    """A Dask task: the part ``spec`` of ``∃u.CPre(Z)`` (:func:`~pipelines.synthesis.parts.solve`, with the
    symmetry of ``classes`` if given) of the problem ``key``, as a :class:`Part`: its answer as DDDMP bytes, the
    seconds it took (the problem's loading not counted: it happens once per worker) and the wall-clock time it
    began (after the loading). With ``keep`` the worker also keeps the answer (:data:`_KEPT`: the split cut's first
    phase, which :func:`join_part` reads)."""
    entered = time.time()
    problem = held(key)
    began = time.time()
    t0, c0 = time.perf_counter(), time.thread_time()
    result = solve(problem, spec, Z, outside, classes)
    blob = to_bytes(problem.model, result, "writing a part of CPre on a Dask worker")
    kept = ""
    if keep:
        kept = uuid.uuid4().hex
        _KEPT[kept] = result
        while len(_KEPT) > KEPT_ANSWERS:
            _KEPT.popitem(last=False)
    del result
    seconds, cpu, where = time.perf_counter() - t0, time.thread_time() - c0, _where()
    return Part(blob, seconds, began, entered, where, cpu, kept, time.time(), ((where, seconds, cpu),))


def join_part(key: str, spec: PartSpec, classes: Sequence[Sequence[int]] | None, own: Part, *others: Part) -> Part:
    """The split cut's second phase, a Dask task: :func:`~pipelines.synthesis.parts.join` of the range ``spec``
    from the first phases of the ranges its states admit: ``own`` (its own range, kept on this worker if it ran
    here) and ``others`` (which Dask brings from the workers that computed them). Returns its answer (closed under
    the ``classes``, if given), the seconds of both phases of its own range, when its first phase began and was
    entered, and where it ran."""
    problem = held(key)
    model = problem.model

    def bad() -> Iterator[Function]:  # own's answer is done with here once read (others' may serve a later join)
        for part in (own, *others):
            kept = (_KEPT.pop if part is own else _KEPT.get)(part.kept, None) if part.kept else None
            yield kept if kept is not None and kept.bdd is model.bdd else from_bytes(model, part.blob)

    t0, c0 = time.perf_counter(), time.thread_time()
    with model.guard("joining a part of CPre on a Dask worker"):
        result = join(problem, spec, bad(), symmetry(problem, classes))
        blob = to_bytes(model, result)
    del result
    seconds, cpu, where = time.perf_counter() - t0, time.thread_time() - c0, _where()
    return Part(blob, own.seconds + seconds, own.began, own.entered, where, own.cpu + cpu, "", time.time(),
                (*own.phases, (where, seconds, cpu)))


def forget(model_key: str) -> int:
    """Drop every problem of one CPre this worker holds (run on every worker when the CPre closes)."""
    keys = [k for k, h in _HELD.items() if h.owner == model_key]
    for k in keys:
        del _HELD[k]
    for sent in [k for k, p in _SENT.items() if p["model"] == model_key]:
        del _SENT[sent]
    _KEPT.clear()
    return len(keys)


__all__ = ["HELD_PROBLEMS", "KEPT_ANSWERS", "SENT_PROBLEMS", "Held", "Part", "ProblemMissing", "compute_part",
           "forget", "held", "join_part", "receive"]
