"""The worker's side of ``∃u.CPre`` in parts on Dask (:mod:`workers.dask_cpre` is the caller's side).

Each function below is a Dask task (or, :func:`forget`, run on every worker): it finds the CPre's problem (the
chain, the admissible pairs and ``M̂``) in its worker's memory (:data:`_HELD`, loaded from DDDMP bytes by the
worker's first part of that problem), computes its part in that worker's own CUDD manager and answers with a
:data:`Part`. Which part to compute, and why each is exact, is the caller's business and is said there.
"""

from __future__ import annotations

import os
import tempfile
import time
import uuid
from collections import OrderedDict
from collections.abc import Callable, Sequence
from typing import Any, NamedTuple

from pipelines.symbolic.files import model_from_header
from pipelines.symbolic.model import Function, SymbolicModel
from pipelines.synthesis.cpre import bad_inputs, predecessors_of, window_predecessors
from pipelines.synthesis.partition import admitting_below, lexicographic_part, lowest_code_states, w_window
from pipelines.synthesis.schedule import Chain
from pipelines.synthesis.symmetry import Symmetry, cached_symmetry

HELD_PROBLEMS = 2
"""Problems a worker keeps loaded (a safety loop's ``within`` problem and the plain one alternate in
Reach(Safe)); older ones are dropped with their CUDD manager when no other problem of theirs is held."""

SENT_PROBLEMS = 16
"""Problems a worker keeps as sent (:func:`receive`), to load again when :data:`HELD_PROBLEMS` pushed one out (jobs
sharing a cluster take turns on its workers). A CPre's problems go when it closes (:func:`forget`); the bound is
for those whose job's process died first."""


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


NOT_Z = "not Z"
"""What a task gets for ``outside`` when it is ``¬Z`` (the reach loop's, every call): the worker complements the
``Z`` it read (constant time in CUDD) instead of this process writing, sending and each part reading a second set."""

Outside = bytes | str | None
"""A task's ``outside``: DDDMP bytes, :data:`NOT_Z`, or ``None`` (none)."""

Problem = dict[str, Any] | None
"""What a task gets for its CPre's problem: the problem itself (:meth:`workers.dask_cpre.DaskPredecessors.problem`),
or ``None``: the one :func:`receive` kept under the task's key."""


class ProblemMissing(RuntimeError):
    """A part named a problem its worker was not sent (it joined the cluster, or restarted, after the sending)."""


class Held(NamedTuple):
    """A CPre's problem as a worker holds it, loaded into its CUDD manager (:func:`_problem`)."""

    model: SymbolicModel
    chain: Chain
    admissible: Function
    M: Function | None
    u_bits: Sequence[str]
    w_bits: Sequence[str]
    owner: str
    """The key of the CPre's model (shared by its problems)."""
    memo: dict[tuple, Function]
    """Sets every call of the problem's parts would compute again, computed once here (:func:`_care`,
    :func:`_below`): dropped with the problem."""


#: Per worker process: problem key -> the problem loaded, least recently used first.
_HELD: OrderedDict[str, Held] = OrderedDict()
#: Per worker process: problem key -> the problem as sent (:func:`receive`), newest last.
_SENT: OrderedDict[str, dict[str, Any]] = OrderedDict()
#: Per worker process: (model key, classes) -> the Symmetry on that model (dropped with the model's problems).
_SYMMETRIES: dict[tuple, Symmetry] = {}
#: Per worker process: the split cut's first-phase answers computed here, newest last, so that the second phase of
#: the same range (placed on the same worker) takes its own range's pairs as they are instead of reading their bytes
#: back: a third of the second phase's reading (the others' pairs come from other workers).
_KEPT: OrderedDict[str, Function] = OrderedDict()
#: How many :data:`_KEPT` holds (a join that ran elsewhere leaves its range's answer here until it is pushed out;
#: with several parts per worker a worker computes several first phases of a call before their joins).
KEPT_ANSWERS = 8


def _load(model: SymbolicModel, blob: bytes) -> Function:
    """A BDD from DDDMP bytes (``dd`` reads DDDMP from files only)."""
    fd, path = tempfile.mkstemp(suffix=".dddmp", prefix="compabs-part-")
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(blob)
        (root,) = model.bdd.load(path)
        return root
    finally:
        os.unlink(path)


def _dump(model: SymbolicModel, f: Function) -> bytes:
    fd, path = tempfile.mkstemp(suffix=".dddmp", prefix="compabs-part-")
    os.close(fd)
    try:
        model.bdd.dump(path, [f])
        with open(path, "rb") as fh:
            return fh.read()
    finally:
        os.unlink(path)


def _problem(key: str, problem: Problem) -> Held:
    held = _HELD.get(key)
    if held is not None:
        _HELD.move_to_end(key)
        return held
    if problem is None:
        problem = _SENT.get(key)
        if problem is None:
            raise ProblemMissing(f"this worker was not sent the CPre problem {key} (it joined or restarted since)")
        _SENT.move_to_end(key)
    # A model is shared by the problems of one CPre (same header): a new manager per problem would reload the
    # variables and leave the older problems' nodes in another manager.
    model = next((h.model for h in _HELD.values() if h.owner == problem["model"]), None)
    if model is None:
        model = model_from_header(problem["header"], problem["max_memory"])
    with model.guard("loading the CPre's relations on a worker"):
        roots = [_load(model, b) for b in problem["roots"]]
    n = len(problem["xn"])
    chain = list(zip(roots[:n], problem["xn"]))
    M = roots[n + 1] if len(roots) > n + 1 else None
    held = Held(model, chain, roots[n], M, problem["u_bits"], problem["w_bits"], problem["model"], {})
    _HELD[key] = held
    while len(_HELD) > HELD_PROBLEMS:
        _HELD.popitem(last=False)
    return held


def _care(held: Held, sym: Symmetry | None) -> Function:
    """``M̂`` on the orbit representatives of ``sym`` (``M̂`` itself without one), computed once per problem and
    symmetry instead of by each part of each call. With the order of :func:`~pipelines.synthesis.cpre.bad_inputs`'
    conjunctions (the part first), the parts' ``M̂ ∧ reps ∧ outside`` over a Reach(Safe) of consensus N = 6 on 16
    workers is 1 % of their CPU this way, 14 % computed by each part (one process computes it once per call)."""
    assert held.M is not None
    if sym is None:
        return held.M
    key = ("care", tuple(tuple(c) for c in sym.classes))
    care = held.memo.get(key)
    if care is None:
        care = held.memo[key] = held.M & sym.representatives
    return care


def _below(held: Held, digit: str) -> Callable[[int], Function]:
    """:func:`~pipelines.synthesis.partition.admitting_below` on the problem's ``M̂``, each code's set computed once
    per problem (a part's range moves between calls, but its ends are among the cells of ``ŵ``)."""
    assert held.M is not None
    M = held.M

    def below(c: int) -> Function:
        key = ("below", digit, c)
        f = held.memo.get(key)
        if f is None:
            f = held.memo[key] = admitting_below(held.model, M, digit, c)
        return f

    return below


def receive(key: str, problem: dict[str, Any]) -> None:
    """Keep a CPre's problem, sent to every worker at once (``client.run``), until its first part here loads it
    (:func:`_problem`), and after, to load again: :data:`SENT_PROBLEMS` at most, the newest last.

    Why not a scattered future that the parts depend on: Dask brings every dependency to a task's worker before it
    runs, and its active memory manager drops the replicas no waiting task needs a few seconds after a call, so at
    each call every worker would fetch the whole problem again from the one worker left holding it, though it keeps
    the problem loaded all along. On 16 workers (consensus N = 7) that delays the last part of each call by several
    times what it waits with the memory manager stopped, seconds summed over the calls.
    """
    _SENT[key] = problem
    _SENT.move_to_end(key)
    while len(_SENT) > SENT_PROBLEMS:
        _SENT.popitem(last=False)


def _where() -> str:
    """The address of the Dask worker running this task, ``""`` outside one (a part called directly)."""
    try:
        from distributed import get_worker

        return str(get_worker().address)
    except ValueError:
        return ""


def _outside(model: SymbolicModel, z: Function, outside: Outside) -> Function | None:
    """A task's ``outside`` as a set of its worker's manager (``z``: its ``Z`` there)."""
    if outside is None:
        return None
    if isinstance(outside, bytes):
        return _load(model, outside)
    if outside != NOT_Z:
        raise ValueError(f"a part's outside is DDDMP bytes, {NOT_Z!r} or None, not {outside!r}")
    return ~z


def _answer(key: str, problem: Problem, Z: bytes, outside: Outside,
            compute: Callable[[Held, Function, Function | None, Symmetry | None], Function],
            classes: Sequence[Sequence[int]] | None = None, close: bool = True, keep: bool = False) -> Part:
    """What every task does around its part: the held problem, ``Z`` and ``outside`` read, ``compute(held, Z,
    outside, symmetry)`` run under CUDD's memory guard, its result as DDDMP bytes, the seconds it took
    (the problem's loading not counted: it happens once per worker) and the wall-clock time it began (after the
    loading). With the ``classes`` of interchangeable subsystems (the sets of the call invariant under them)
    ``symmetry`` is their :class:`Symmetry` (else ``None``), the part is computed on its orbit representatives
    and the result is closed under it here, on the worker (unless ``close`` is false: the split cut's first phase,
    whose pairs are read on the representatives only). With ``keep`` the worker also keeps the result (:data:`_KEPT`)."""
    entered = time.time()
    held = _problem(key, problem)
    model = held.model
    sym = None if classes is None else cached_symmetry(_SYMMETRIES, model, classes, owner=held.owner)
    began = time.time()
    t0, c0 = time.perf_counter(), time.thread_time()
    with model.guard("computing a part of CPre on a Dask worker"):
        z = _load(model, Z)
        out = _outside(model, z, outside)
        result = compute(held, z, out, sym)
        if sym is not None and close:
            result = sym.close(result)
        blob = _dump(model, result)
    kept = ""
    if keep:
        kept = uuid.uuid4().hex
        _KEPT[kept] = result
        while len(_KEPT) > KEPT_ANSWERS:
            _KEPT.popitem(last=False)
    del z, out, result
    seconds, cpu, where = time.perf_counter() - t0, time.thread_time() - c0, _where()
    return Part(blob, seconds, began, entered, where, cpu, kept, time.time(), ((where, seconds, cpu),))


def predecessors_part(key: str, problem: Problem, Z: bytes, outside: Outside, digits: Sequence[str],
                      start: Sequence[int], end: Sequence[int] | None,
                      classes: Sequence[Sequence[int]] | None = None) -> Part:
    """A Dask task: ``part ∧ ∃u.CPre(Z)`` for the part ``[start, end)`` of ``digits``, as a :data:`Part`. With the
    ``classes`` of interchangeable subsystems (the sets of the call invariant under them): the closure of the
    answer on the part's representatives (the parts' closures overlap; their union is the whole, since closing
    distributes over unions)."""

    def compute(held: Held, z: Function, out: Function | None, sym: Symmetry | None) -> Function:
        model, chain, admissible, M, u_bits, w_bits, *_ = held
        part = lexicographic_part(model, digits, start, end)
        return predecessors_of(model, chain, admissible, M, w_bits, u_bits, z, out, part,
                               None if sym is None else sym.representatives)

    return _answer(key, problem, Z, outside, compute, classes)


def bad_part(key: str, problem: Problem, Z: bytes, outside: Outside, digits: Sequence[str],
             start: Sequence[int], end: Sequence[int] | None) -> Part:
    """A Dask task of the ``w`` cut: the pairs ``(x̂, û)`` with a successor outside ``Z`` for some admissible
    ``ŵ`` whose code of ``digits`` lies in ``[start, end)`` (:func:`~pipelines.synthesis.cpre.bad_inputs` with
    that range of ``ŵ`` as its part), as a :data:`Part`."""

    def compute(held: Held, z: Function, out: Function | None, _sym: Symmetry | None) -> Function:
        model, chain, _, M, _, w_bits, *_ = held
        return bad_inputs(model, chain, M, w_bits, z, out, lexicographic_part(model, digits, start, end))

    return _answer(key, problem, Z, outside, compute)


def window_part(key: str, problem: Problem, Z: bytes, outside: Outside, digits: Sequence[str],
                start: Sequence[int], end: Sequence[int] | None,
                classes: Sequence[Sequence[int]] | None = None) -> Part:
    """A Dask task of the window cut: ``states ∧ ∃u.CPre(Z)`` for the states whose lowest admissible code of
    the internal variable ``digits[0]`` lies in ``[start, end)``, with the chain run on the ``ŵ`` cells those
    states admit (:func:`~pipelines.synthesis.partition.w_window`,
    :func:`~pipelines.synthesis.cpre.window_predecessors`), as a :data:`Part`.

    With the ``classes`` of interchangeable subsystems: computed on the window's representatives and closed. A
    window is invariant (``M̂`` is), so the closures of the parts stay disjoint. The representatives go where
    the states go (the ``∃w`` step and the admissible pairs), not into the chain's first operand: on consensus
    N = 6, over a Reach(Safe), the two windows' slower parts take 1.07x as long with them in the chain too and
    1.46x without the representatives."""

    def compute(held: Held, z: Function, out: Function | None, sym: Symmetry | None) -> Function:
        model, chain, admissible, M, u_bits, w_bits, *_ = held
        states, window = w_window(model, M, digits[0], start[0], None if end is None else end[0],
                                  _below(held, digits[0]))
        if sym is not None:
            states &= sym.representatives
        return window_predecessors(model, chain, admissible, M, w_bits, u_bits, z, states, window, out)

    return _answer(key, problem, Z, outside, compute, classes)


def core_part(key: str, problem: Problem, Z: bytes, outside: Outside, digits: Sequence[str],
              start: Sequence[int], end: Sequence[int] | None,
              classes: Sequence[Sequence[int]] | None = None) -> Part:
    """The split cut's first phase, a Dask task: the pairs ``(x̂, û)`` with a successor outside ``Z`` for some
    admissible ``ŵ`` whose code of ``digits[0]`` lies in ``[start, end)`` exactly (the chain runs on those cells
    only: no window reaches past them), as a :data:`Part`. With the ``classes`` of interchangeable subsystems, on
    their representatives only (the second phase reads them there), not closed."""

    def compute(held: Held, z: Function, out: Function | None, sym: Symmetry | None) -> Function:
        # M̂ on the representatives in place of M̂: bad_inputs reads M̂ only where it conjoins it with ``out``
        return bad_inputs(held.model, held.chain, _care(held, sym), held.w_bits, z, out,
                          lexicographic_part(held.model, digits, start, end))

    return _answer(key, problem, Z, outside, compute, classes, close=False, keep=True)


def join_part(key: str, problem: Problem, digits: Sequence[str], start: Sequence[int],
              end: Sequence[int] | None, classes: Sequence[Sequence[int]] | None, own: Part, *others: Part) -> Part:
    """The split cut's second phase, a Dask task: ``states ∧ ∃u.CPre(Z)`` for the states whose lowest admissible
    code of ``digits[0]`` lies in ``[start, end)`` (:func:`~pipelines.synthesis.partition.w_window`), from the first
    phase's bad pairs of the ranges of ``ŵ`` those states admit: ``own`` (the part's own range) and ``others`` (the
    ranges its window reaches into), which Dask brings from the workers that computed them.

    Exact: a state ``x̂`` of the part admits only ``ŵ`` of its window, so the pairs bad for ``x̂`` come from the
    ranges the window meets, and ``∃u. adm ∧ states ∧ ¬(∨ bad)`` is the window cut's answer on these states.
    Returns its answer (closed under the ``classes``, if given), the seconds of both phases of its own range,
    when its first phase began and was entered, and where it ran."""
    held = _problem(key, problem)
    model, _, admissible, M, u_bits, *_ = held
    sym = None if classes is None else cached_symmetry(_SYMMETRIES, model, classes, owner=held.owner)
    t0, c0 = time.perf_counter(), time.thread_time()
    with model.guard("joining a part of CPre on a Dask worker"):
        assert M is not None
        states = lowest_code_states(model, M, digits[0], start[0], None if end is None else end[0],
                                    _below(held, digits[0]))
        if sym is not None:
            states &= sym.representatives
        # the good pairs of the part's states, cut down by each range's bad ones in turn: every operand stays within
        # the part's states. The disjunction of the bad pairs spans every state of those ranges: over a Reach(Safe)
        # of consensus N = 6 on 16 workers, OR-ing them and one ∃u costs the parts about 3x the CPU of this
        good = admissible & states
        for part in (own, *others):  # own's answer is done with here once read (others' may serve a later join)
            kept = (_KEPT.pop if part is own else _KEPT.get)(part.kept, None) if part.kept else None
            good &= ~(kept if kept is not None and kept.bdd is model.bdd else _load(model, part.blob))
        result = model.bdd.exist(list(u_bits), good)
        if sym is not None:
            result = sym.close(result)
        blob = _dump(model, result)
    del states, good, result
    seconds, cpu, where = time.perf_counter() - t0, time.thread_time() - c0, _where()
    return Part(blob, own.seconds + seconds, own.began, own.entered, where, own.cpu + cpu, "", time.time(),
                (*own.phases, (where, seconds, cpu)))


def forget(model_key: str) -> int:
    """Drop every problem of one CPre this worker holds (run on every worker when the CPre closes)."""
    keys = [k for k, h in _HELD.items() if h.owner == model_key]
    for k in keys:
        del _HELD[k]
    for sym_key in [k for k in _SYMMETRIES if k[0] == model_key]:
        del _SYMMETRIES[sym_key]
    for sent in [k for k, p in _SENT.items() if p["model"] == model_key]:
        del _SENT[sent]
    _KEPT.clear()
    return len(keys)


__all__ = ["HELD_PROBLEMS", "SENT_PROBLEMS", "Held", "Part", "ProblemMissing", "bad_part", "core_part", "forget", "join_part",
           "predecessors_part", "receive", "window_part"]
