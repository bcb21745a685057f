"""``∃u.CPre(Z)`` in parts on the job's Dask workers (issue 24: synthesis uses the cluster the job already has).

:class:`DaskPredecessors` is a ``partitioned`` factory for :class:`~pipelines.synthesis.cpre.ControllablePredecessor`
like :class:`workers.processes.partitioned_cpre.PartitionedPredecessors`, with the parts run as Dask tasks:

* **The problem lives on the workers.** The chain, the admissible pairs and (shared ``w``) ``M̂`` travel once per
  problem as DDDMP bytes, sent to every worker with ``client.run``, not as a dependency of the parts
  (:func:`workers.dask_parts.receive` says why; a worker that joined or restarted since gets it again); a
  worker's first part of a problem loads them into a CUDD manager of its own and keeps them for the later calls
  (:mod:`workers.dask_parts`, the tasks' side), so a call sends only ``Z`` (and ``outside``), once per worker,
  and gets back each part's result as DDDMP bytes.
* **Parts.** A call is cut into ``parts`` ranges (:mod:`pipelines.synthesis.partition`: exact, the union of the
  parts is the whole): for the shared CPre, ranges of the shared internal variable ``ŵ``, each part the
  ``∃u.CPre`` of the states whose lowest admissible ``ŵ`` lies in its range, the chain run on the ``ŵ`` cells
  those states admit (:func:`cut_digits` says why); from :data:`SPLIT_FROM` parts on, where those windows overlap
  much, in two phases (the split cut: :func:`core_part` runs the chain on each range's own cells once,
  :func:`join_part` answers a range's states from the ranges they reach, on a worker); else ranges of the top
  two current-state digits, each part its states' ``∃u.CPre``. Either way a part's answer is a set of states,
  final on its own: this process only ORs them. The cuts move after every call towards equal measured work
  (:func:`~pipelines.synthesis.partition.update_density`).
* **Parts handed out as workers free up** (:mod:`workers.dispatch`): each worker holds one part at a time, the
  largest predicted first; when its part ends this process submits the next one there (a join once the first
  phases it reads have ended), so with more parts than workers (``parts_for(client, per_worker)``) unequal parts
  even out.
* **The same answer in every mode.** Each part is ``part ∧ ∃u.CPre(Z)`` computed by
  :func:`~pipelines.synthesis.cpre.predecessors_of`, the function the one-process and helper-process modes run.

This process computes nothing while the parts run: CUDD holds the GIL for a whole operation, and the thread
that waits for the workers' answers must keep moving. A part that fails (its worker died more often than Dask
retries, or the cluster went away) is a :class:`DaskPartFailed`, after which the CPre goes on in this process;
CUDD out of memory in a part is a :class:`~pipelines.symbolic.model.BDDMemoryError`, raised to the caller.
"""

from __future__ import annotations

import logging
import math
import time
import uuid
import weakref
from typing import Any, cast

import numpy as np

from pipelines.symbolic.files import header
from pipelines.symbolic.model import BDDMemoryError, Function, and_exists
from pipelines.synthesis.cpre import ControllablePredecessor, PartitionFailed, Within
from pipelines.synthesis.partition import damped_cuts, equal_work_cuts, split_digits, update_density, w_window
from pipelines.synthesis.symmetry import Symmetry
from workers.dask_parts import (
    HELD_PROBLEMS,
    NOT_Z,
    Part,
    ProblemMissing,
    _dump,
    _load,
    bad_part,
    core_part,
    forget,
    join_part,
    predecessors_part,
    receive,
    window_part,
)
from workers.dispatch import Dispatch, Task

log = logging.getLogger(__name__)

PARTS_PER_WORKER = 1
"""Parts of one call per worker thread. More parts than workers are handed out as workers free up
(:mod:`workers.dispatch`), which evens out unequal parts, but each cut costs work the parts share or repeat: on
16 cores (consensus N = 7) two parts per worker bring the busiest worker of a call from 1.53x the mean to 1.24x,
but the parts' CPU grows 1.6x and the synthesis takes about 1.4x as long (8 workers: 1.06x)."""

SPLIT_FROM = 4
"""From this many parts of the shared CPre on, ``cut='auto'`` is the split cut, below it the window cut. Summed
seconds of the parts over a Reach(Safe) of consensus N = 6 (two workers), window against split: 2 parts 28.3 and
28.5 s, 4 parts 36.0 and 33.7, 8 parts 47.1 and 38.9, 16 parts 65.7 and 54.0: the windows overlap by ``M̂``'s
spread (1.12x the cells of ``ŵ`` at 2 parts, 2.7x at 16 on N = 7), the split cut's second phase costs a transfer."""

CUTS = ("auto", "window", "split", "w", "x")
"""What the parts of a call split (:func:`cut_digits`)."""


class DaskPartFailed(PartitionFailed):
    """A part of ``∃u.CPre`` failed on the cluster (the message says why); the CPre goes on in one process."""


# ====================================================================================== the caller's side
def _forget_everywhere(client: Any, model_key: str) -> None:
    try:
        client.run(forget, model_key)
    except Exception:  # the cluster is gone: so are the workers' copies
        pass


class DaskPredecessors:
    """``∃u.CPre(Z)`` of a :class:`.ControllablePredecessor` in ``parts`` parts on the workers of ``client``.

    Parameters
    ----------
    cpre : ControllablePredecessor
    parts : int
        Parts per call (>= 2), run as Dask tasks (:data:`PARTS_PER_WORKER` per worker is what
        :func:`parts_for` gives).
    client : distributed.Client
        The job's client (its workers import ``workers.dask_cpre``, as they import ``workers.tasks``).
    retries : int
        Dask retries of a part that raised (a worker's death is retried by Dask itself).
    cut : {'auto', 'window', 'split', 'w', 'x'}
        What the parts split (:func:`cut_digits`): ``x``, ranges of the top two current-state digits, each part
        ``part ∧ ∃u.CPre(Z)``; ``window``, ranges of the top shared internal variable, each part ``∃u.CPre(Z)``
        on the states whose lowest admissible ``ŵ`` lies in its range (:func:`window_part`); ``split``, the same
        answers in two phases, the bad inputs of each range's own ``ŵ`` cells (:func:`core_part`), then each
        range's states from the ranges they admit (:func:`join_part`), on the workers; ``w``, the first phase
        only, joined here before the one ``∃u`` step; ``auto``: for the shared CPre ``window`` below
        :data:`SPLIT_FROM` parts and ``split`` from there on, ``x`` otherwise.

    Call it like :meth:`.ControllablePredecessor.predecessors`; :meth:`close` drops the workers' copies.
    """

    on = "cluster"

    @property
    def takes_symmetry(self) -> bool:
        """Whether a call may pass ``symmetry=``: the window and state cuts close each part's answer on its worker;
        the ``w`` cut's parts are pairs of states and inputs, joined here (not supported)."""
        return self.cut != "w"

    def __init__(self, cpre: ControllablePredecessor, parts: int, *, client: Any, retries: int = 1,
                 cut: str = "auto") -> None:
        if parts < 2:
            raise ValueError(f"DaskPredecessors needs at least 2 parts, got {parts}")
        m = cpre.model
        self._cpre = weakref.ref(cpre)  # the CPre holds this object (no cycle through CUDD objects)
        self.client = client
        self.retries = retries
        self.cut, self.digits = cut_digits(cpre, cut)
        if cut == "auto" and self.cut == "window" and parts >= SPLIT_FROM:
            self.cut = "split"
        self.shape = tuple(int(m.sizes[d]) for d in self.digits)
        self.cells = math.prod(self.shape)
        self.parts = min(parts, self.cells)
        self._density = np.ones(self.cells)
        self._cuts = equal_work_cuts(self._density, self.parts)
        self._seconds: list[float] = []
        self._calls = 0
        #: Seconds summed over the calls: sending the sets, the slower part of each call (and the most CPU seconds a
        #: part of each call took: on a machine with fewer cores than workers, what the slower part would take on a core
        #: of its own), reading and joining the parts after it ended, the ∃u step of the w cut (what the job's process
        #: adds to the parts' time). Of ``after_parts``: ``last_start``, from sending the parts until the last of them
        #: began computing (Dask's dispatch, a worker's first loading of the problem, parts queued behind others), of
        #: which ``last_entered``, until the last part's task was entered on its worker (the loading not counted), and
        #: ``after_last``, from the end of the last part's computation until this process had joined every part (its
        #: bytes coming back and read here). Both from the workers' wall clocks: exact on one machine, off by the
        #: clocks' skew on a real cluster.
        self.timing = {"sending": 0.0, "slowest_part": 0.0, "slowest_part_cpu": 0.0, "after_parts": 0.0,
                       "exists_u": 0.0, "last_start": 0.0, "last_entered": 0.0, "after_last": 0.0}
        #: The same per call, with the call's wall seconds, its parts' summed seconds (wall and CPU), the most of
        #: its parts that ran on one worker (of the split cut, of its second phase), the most tasks submitted at once
        #: (``most_in_flight``: one per worker) and the seconds (and CPU seconds) of the busiest worker's tasks
        #: (``busiest_worker``: with more parts than workers, what the call waited for) against ``parts_span``, from
        #: sending the parts until the last ended (the difference: workers waiting, for the split cut's second phase
        #: of a range until every first phase it reads ended), in call order. With more parts than workers
        #: ``last_start`` is when the last part was handed out and began.
        self.history: list[dict[str, float]] = []
        self._model_key = uuid.uuid4().hex
        self._header = header(m)
        self._max_memory = m.max_memory
        self._problem: Any = None  # the Within (or "all") the workers hold
        self._problem_key = ""
        self._last_bounds: list[tuple[int, int]] | None = None  # the parts of the last call
        self._reach: np.ndarray | None = None  # the split cut's: highest ŵ admitted, by lowest (_reached)
        self._finalizer = weakref.finalize(self, _forget_everywhere, client, self._model_key)

    @property
    def cpre(self) -> ControllablePredecessor:
        cpre = self._cpre()
        if cpre is None:
            raise RuntimeError("the ControllablePredecessor of this DaskPredecessors is gone")
        return cpre

    @property
    def cuts(self) -> list[int]:
        return list(self._cuts)

    @property
    def cut_cells(self) -> list[tuple[int, ...]]:
        return [tuple(int(c) for c in np.unravel_index(k, self.shape)) for k in self._cuts]

    @property
    def seconds(self) -> list[float]:
        """Seconds each part took on its worker in the last call, in part order."""
        return list(self._seconds)

    @property
    def calls(self) -> int:
        return self._calls

    def _reached(self, k: int, bounds: list[tuple[int, int]]) -> list[int]:
        """Of the split cut: the ranges (indices into ``bounds``) of the ``ŵ`` cells that the states of range
        ``k`` admit, ``k`` first (:func:`join_part`)."""
        if self._reach is None:  # the highest ŵ a state admits, by its lowest: once, M̂ does not change
            self._reach = np.array([max(self._window_hits(c, c + 1), default=c) for c in range(self.cells)])
        lo, hi = bounds[k]
        top = int(self._reach[lo:hi + 1].max())
        return [k] + [j for j, (a, _) in enumerate(bounds) if j != k and a <= top and bounds[j][1] >= lo]

    def _window_hits(self, start: int, end: int | None) -> list[int]:
        """The ``ŵ`` cells admitted by the states whose lowest admissible ``ŵ`` lies in ``[start, end)``
        (:func:`~pipelines.synthesis.partition.w_window`'s window, cell by cell)."""
        g, m = self.cpre, self.cpre.model
        assert g.M is not None
        digit = self.digits[0]
        with m.guard("finding the cells of a window of ŵ"):
            _, window = w_window(m, g.M, digit, start, end)
            return [c for c in range(self.cells) if (window & m.interval(digit, c, c)) != m.bdd.false]

    @property
    def window_cells(self) -> list[int]:
        """Of the window and split cuts, the ``ŵ`` cells each part of the last call ran the chain on (a window
        reaches past its range by the spread of ``M̂``, so with many windows the chain runs on the same cells more
        than once: on consensus N = 7, 1.12x the 33 cells with 2 parts, 2.70x with 16; the split cut's first phase
        runs on each range's own cells); empty for the other cuts or before a call. Computed here when asked
        (reports), not during the calls."""
        bounds = self._last_bounds
        if self.cut not in ("window", "split") or bounds is None:
            return []
        if self.cut == "split":  # the first phase runs the chain on each range's own cells only
            return [b - a + 1 for a, b in bounds]
        # the last part has no upper end (as in the calls: codes past the grid belong to it)
        return [len(self._window_hits(a, None if k == len(bounds) - 1 else b + 1)) for k, (a, b) in enumerate(bounds)]

    def bounds(self) -> list[tuple[int, int]]:
        edges = [0, *self._cuts, self.cells]
        return [(a, b - 1) for a, b in zip(edges, edges[1:])]

    def _starts(self) -> list[tuple[int, ...] | None]:
        return [(0,) * len(self.shape), *self.cut_cells, None]

    def _scatter(self, data: Any) -> Any:
        """One future for ``data`` (a set of the call as DDDMP bytes), on every worker: each part depends on it. In a
        list, so that any ``data`` is one future (``scatter`` gives a collection's items a future each)."""
        (future,) = self.client.scatter([data], broadcast=True, hash=False)
        return future

    def _send_problem(self, within: Within | None) -> None:
        key = "all" if within is None else within
        if self._problem is key:
            return
        # Once to every worker: each part's task then finds it in its worker's memory (dask_parts.receive says why
        # not as a dependency of the parts).
        self._problem_key = f"{self._model_key}-{uuid.uuid4().hex}"
        self.client.run(receive, self._problem_key, self.problem(within))
        self._problem = key

    def problem(self, within: Within | None = None) -> dict[str, Any]:
        """What a worker loads once per problem (:func:`workers.dask_parts._problem`): the chain, the admissible
        pairs (of ``within``, if given) and ``M̂`` as DDDMP bytes, with the model's header and bits."""
        g = self.cpre
        chain, admissible = (g.chain, g.admissible) if within is None else within
        roots = [rel for rel, _ in chain] + [admissible] + ([] if g.M is None else [g.M])
        with g.model.guard("writing the CPre's relations for the Dask workers"):
            blobs = [_dump(g.model, f) for f in roots]
        return {"model": self._model_key, "header": self._header, "max_memory": self._max_memory,
                "roots": blobs, "xn": [list(xn) for _, xn in chain], "u_bits": list(g.u_bits),
                "w_bits": list(g.w_bits)}

    def _slots(self) -> list[str]:
        """The workers' addresses, one per thread, in a fixed order: part ``k`` of a call goes to slot ``k``
        (:meth:`_placed`)."""
        return [addr for addr, n in sorted(self.client.nthreads().items()) for _ in range(n)]

    @staticmethod
    def _placed(slots: list[str], slot: int) -> dict[str, Any]:
        """Where a task that :class:`~workers.dispatch.Dispatch` gave slot ``slot`` runs: that slot's worker, or
        another if that one is gone (a loose restriction).

        Why not leave it to Dask: its scheduler places the parts of a call by its estimates of their durations,
        and on 16 workers (consensus N = 5, split cut) it can put one call's 16 parts on 6 workers, five of them one
        after another on one worker, so that the call takes the time of five parts; pinned, each part has a worker
        of its own."""
        if not slots:
            return {}
        return {"workers": [slots[slot % len(slots)]], "allow_other_workers": True}

    def __call__(self, Z: Function, outside: Function | None = None, within: Within | None = None,
                 symmetry: Symmetry | None = None) -> Function:
        if symmetry is not None and not self.takes_symmetry:
            raise ValueError("the w cut does not take a symmetry")
        try:
            try:
                return self._call(Z, outside, within, symmetry)
            except ProblemMissing:  # a worker joined or restarted since the problem was sent: send it again, once
                self._problem = None
                return self._call(Z, outside, within, symmetry)
        except BDDMemoryError:
            raise
        except PartitionFailed:
            raise
        except Exception as exc:  # the cluster failed us: the CPre goes on in one process
            raise DaskPartFailed(f"a part of CPre failed on the Dask cluster: {type(exc).__name__}: {exc}") from None

    def _call(self, Z: Function, outside: Function | None, within: Within | None,
              symmetry: Symmetry | None) -> Function:
        from distributed import as_completed

        g, m = self.cpre, self.cpre.model
        t_start = time.perf_counter()
        self._send_problem(within)
        with m.guard("writing a set for the Dask workers"):
            z = self._scatter(_dump(m, Z))
            # the reach loop's outside is ¬Z: the workers complement their Z (dask_parts.NOT_Z)
            o = None if outside is None else NOT_Z if outside == ~Z else self._scatter(_dump(m, outside))
        bounds, starts = self.bounds(), self._starts()
        self._last_bounds = bounds
        slots = self._slots()
        ranges = [(list(a), None if b is None else list(b)) for a, b in zip(starts[:-1], starts[1:]) if a is not None]
        work = [float(self._density[lo:hi + 1].sum()) for lo, hi in bounds]
        # the split cut's: the ranges whose first phase each range's join reads, its own first
        reads = [self._reached(k, bounds) for k in range(len(bounds))] if self.cut == "split" else None
        dispatch = Dispatch(work, max(1, len(slots)), reads)
        first = {"w": bad_part, "window": window_part, "split": core_part}.get(self.cut, predecessors_part)
        extra = () if symmetry is None else (symmetry.classes,)
        classes = None if symmetry is None else symmetry.classes
        cores: dict[int, Any] = {}  # the split cut's first phases, which the joins depend on
        submitted: dict[str, Task] = {}
        # Where parts are handed out one by one this process waits for every task's end (fetching only the final
        # answers); else only for the final answers, which the client fetches in its own thread as each ends (one
        # round trip per part less).
        watch_first = self.cut == "split" and not dispatch.at_once
        ac = as_completed(with_results=not watch_first, raise_errors=False)

        def submit(tasks: list[Task]) -> None:
            for t in tasks:
                start, end = ranges[t.k]
                key = f"compabs-cpre-{self._calls}-{t.kind}-{t.k}-{uuid.uuid4().hex[:8]}"
                if t.kind == "join":  # each range's states from the pairs of the ranges they admit, own range first
                    assert reads is not None
                    args: tuple = (join_part, self._problem_key, None, list(self.digits), start, end, classes,
                                   *(cores[j] for j in reads[t.k]))
                else:
                    args = (first, self._problem_key, None, z, o, list(self.digits), start, end, *extra)
                fut = self.client.submit(*args, pure=False, retries=self.retries, key=key, **self._placed(slots, t.slot))
                if t.kind == "core":
                    cores[t.k] = fut
                submitted[key] = t
                if t.kind != "core" or watch_first:
                    ac.add(fut)

        seconds, cpu = [0.0] * len(bounds), [0.0] * len(bounds)
        t_sent, sent_at = time.perf_counter(), time.time()
        last_start = last_end = last_entered = sent_at
        ran_on: dict[str, int] = {}
        busy: dict[str, list[float]] = {}  # per worker: the seconds and CPU seconds of the tasks it ran in this call
        result = g.bdd.false
        live = []
        try:
            submit(dispatch.start())
            # A first phase's answer stays on its worker, where the joins that read it fetch it; only final answers
            # come here.
            for item in ac:
                fut, answer = (item, None) if watch_first else item  # (future, its Part)
                task = submitted[fut.key]
                live.append(fut)
                if fut.status == "error":
                    exc = fut.exception()
                    if isinstance(exc, BDDMemoryError):
                        raise BDDMemoryError(f"a synthesis part on a Dask worker: {exc}")
                    if isinstance(exc, ProblemMissing):  # a new one: raising exc itself would tie it to this frame
                        raise ProblemMissing(str(exc))
                    raise DaskPartFailed(f"a part of CPre failed on a Dask worker: {type(exc).__name__}: {exc}")
                if fut.status != "finished":  # cancelled under us (the cluster is closing)
                    raise DaskPartFailed(f"a part of CPre on a Dask worker ended {fut.status}")
                submit(dispatch.done(task))  # before reading the answer: the freed worker must not wait for this
                if task.kind == "core":
                    continue
                part = cast(Part, fut.result() if watch_first else answer)
                ran_on[part.where] = ran_on.get(part.where, 0) + 1
                for where, s, c in part.phases:
                    b = busy.setdefault(where, [0.0, 0.0])
                    b[0], b[1] = b[0] + s, b[1] + c
                with m.guard("reading a Dask worker's part of CPre"):
                    result |= _load(m, part.blob)
                seconds[task.k], cpu[task.k] = part.seconds, part.cpu
                last_start, last_end = max(last_start, part.began), max(last_end, part.ended)
                last_entered = max(last_entered, part.entered)
                fut.release()
            if not dispatch.finished:  # as_completed ran dry with parts still to run: nothing was lost silently
                raise DaskPartFailed("the Dask parts of a CPre call stopped before every part ran")
        finally:
            for fut in (*live, *cores.values(), *ac.futures):
                fut.cancel()
        t_parts, joined_at = time.perf_counter(), time.time()
        if self.cut == "w":  # the parts are the bad pairs: the one ∃u step, on the whole set, here
            admissible = g.admissible if within is None else within.admissible
            with m.guard("joining the parts of CPre"):
                result = and_exists(admissible, ~result, list(g.u_bits))
        self._seconds = seconds
        self._calls += 1
        t_end, slowest = time.perf_counter(), max(seconds, default=0.0)
        call = {"sending": t_sent - t_start, "slowest_part": slowest, "slowest_part_cpu": max(cpu, default=0.0),
                "after_parts": t_parts - t_sent - slowest,
                "exists_u": t_end - t_parts, "last_start": max(0.0, last_start - sent_at),
                "last_entered": max(0.0, last_entered - sent_at),
                "after_last": max(0.0, joined_at - last_end)}
        for key, value in call.items():
            self.timing[key] += value
        self.history.append({"wall": round(t_end - t_start, 3), "parts_sum": round(sum(seconds), 3),
                             "parts_cpu_sum": round(sum(cpu), 3),
                             "most_on_one_worker": max(ran_on.values(), default=0),
                             "most_in_flight": dispatch.most_in_flight,
                             "busiest_worker": round(max((b[0] for b in busy.values()), default=0.0), 3),
                             "busiest_worker_cpu": round(max((b[1] for b in busy.values()), default=0.0), 3),
                             "parts_span": round(max(0.0, last_end - sent_at), 3),
                             **{k: round(v, 3) for k, v in call.items()}})
        # the parts' CPU seconds are their work even where they share cores (a worker per core: about their seconds)
        self._density = update_density(self._density, bounds, cpu if all(cpu) else seconds)
        self._cuts = damped_cuts(self._cuts, equal_work_cuts(self._density, len(bounds)))
        log.info("CPre on the cluster: %d parts took %s s (sum %.2f); call %.2f s: sending %.2f, parts and "
                 "joining them %.2f (the last was entered after %.2f, began after %.2f, joined %.2f after the last "
                 "ended), the ∃u step %.2f", len(seconds), [round(s, 2) for s in seconds], sum(seconds),
                 t_end - t_start, t_sent - t_start, t_parts - t_sent, last_entered - sent_at, last_start - sent_at,
                 joined_at - last_end, t_end - t_parts)
        return result

    def close(self) -> None:
        """Drop the workers' copies of the problem (idempotent); the statistics stay readable."""
        self._problem = None
        self._finalizer()


def cut_digits(cpre: ControllablePredecessor, cut: str = "auto") -> tuple[str, tuple[str, ...]]:
    """The cut (``'window'``, ``'w'`` or ``'x'``) and the digits it splits, for ``cut`` in ``auto``, ``window``,
    ``w``, ``x``.

    Why along ``ŵ`` for the shared CPre: ``w`` sits above the states in its variable order and the chain's cost
    is spread over its cells, so ranges of ``ŵ`` split the work where CUDD's recursion splits it (on the largest
    call of consensus N = 6, in CUDD cache lookups, two ``ŵ`` halves summed to 1.04x the whole, two state halves
    to 1.31x). ``window`` (the default there) gives each part the states whose admissible ``ŵ`` start in its
    range, so each part's answer is final and the parts are only OR-ed; ``w`` leaves the bad pairs of every part
    to be joined and one ``∃u`` step to run in the job's process, a quarter of consensus N = 8's time on two
    workers, while the workers wait.
    """
    if cut not in CUTS:
        raise ValueError(f"cut must be one of {CUTS}, got {cut!r}")
    m = cpre.model
    w_digits = [d for d in dict.fromkeys(v.rsplit("_", 1)[0] for v in m.variables)
                if d.startswith("w") and m.sizes[d] > 1]
    if cut in ("w", "window", "split") or (cut == "auto" and cpre.M is not None and w_digits):
        if cpre.M is None or not w_digits:
            raise ValueError(f"the {cut} cut needs the shared CPre (a shared internal variable)")
        return ("window" if cut == "auto" else cut), (w_digits[0],)
    return "x", split_digits(m)


def parts_for(client: Any, per_worker: int = PARTS_PER_WORKER) -> int:
    """Parts of a call on the cluster of ``client``: ``per_worker`` per worker thread, at least 2."""
    return max(2, per_worker * sum(client.nthreads().values()))


def on_cluster(client: Any, retries: int = 1, cut: str = "auto"):
    """A ``partitioned`` factory (``factory(cpre, parts)``) running the parts on ``client``'s workers."""

    def factory(cpre: ControllablePredecessor, parts: int) -> DaskPredecessors:
        return DaskPredecessors(cpre, parts, client=client, retries=retries, cut=cut)

    return factory


__all__ = ["CUTS", "HELD_PROBLEMS", "PARTS_PER_WORKER", "SPLIT_FROM", "DaskPartFailed", "DaskPredecessors", "bad_part",
           "core_part", "cut_digits", "forget", "join_part", "on_cluster", "parts_for", "predecessors_part",
           "window_part"]
