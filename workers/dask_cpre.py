"""The partitioned ``∃u.CPre`` with its parts on the job's Dask workers (issue 24: synthesis uses the cluster the
job already has).

:class:`DaskPredecessors` is a :class:`~pipelines.synthesis.partitioned.PartitionedCPre` (the plan of the parts,
the joining and the balancing: its cuts, ``window`` and ``split`` for the shared CPre, ``x`` otherwise) whose
transport is the job's Dask client:

* **The problem lives on the workers.** The chain, the admissible pairs and (shared ``w``) ``M̂`` travel once per
  problem as DDDMP bytes, sent to every worker with ``client.run``, not as a dependency of the parts
  (:func:`workers.dask_parts.receive` says why; a worker that joined or restarted since gets it again); a
  worker's first part of a problem loads them into a CUDD manager of its own and keeps them for the later calls
  (:mod:`workers.dask_parts`, the tasks' side), so a call sends only ``Z`` (and ``outside``), once per worker,
  and gets back each part's answer as DDDMP bytes.
* **Parts handed out as workers free up** (:mod:`workers.dispatch`): each worker holds one part at a time, the
  largest predicted first; when its part ends this process submits the next one there (the split cut's second
  phase of a range once the first phases it reads have ended, on a worker), so with more parts than workers
  (``parts_for(client, per_worker)``) unequal parts even out.

This process computes nothing while the parts run: CUDD holds the GIL for a whole operation, and the thread
that waits for the workers' answers must keep moving. A part that fails (its worker died more often than Dask
retries, or the cluster went away) is a :class:`DaskPartFailed`, after which the CPre goes on in this process;
CUDD out of memory in a part is a :class:`~pipelines.symbolic.symbolic_model.BDDMemoryError`, raised to the caller.
"""

from __future__ import annotations

import logging
import time
import uuid
import weakref
from collections.abc import Iterator
from typing import Any, cast

from pipelines.symbolic.files import from_bytes, to_bytes
from pipelines.symbolic.symbolic_model import BDDMemoryError
from pipelines.synthesis.cpre import ControllablePredecessor, PartitionFailed
from pipelines.synthesis.partitioned import Answer, Call, PartitionedCPre
from pipelines.synthesis.parts import NOT_Z, Problem, pack
from workers.dask_parts import Part, ProblemMissing, compute_part, forget, join_part, receive
from workers.dispatch import Dispatch, Task

log = logging.getLogger(__name__)

PARTS_PER_WORKER = 1
"""Parts of one call per worker thread. More parts than workers are handed out as workers free up
(:mod:`workers.dispatch`), which evens out unequal parts, but each cut costs work the parts share or repeat: on
16 cores (consensus N = 7) two parts per worker bring the busiest worker of a call from 1.53x the mean to 1.24x,
but the parts' CPU grows 1.6x and the synthesis takes about 1.4x as long (8 workers: 1.06x)."""

#: What :attr:`DaskPredecessors.timing` sums over the calls.
TIMING = ("sending", "slowest_part", "slowest_part_cpu", "after_parts", "exists_u", "last_start", "last_entered",
          "after_last")


class DaskPartFailed(PartitionFailed):
    """A part of ``∃u.CPre`` failed on the cluster (the message says why); the CPre goes on in one process."""


def _forget_everywhere(client: Any, model_key: str) -> None:
    try:
        client.run(forget, model_key)
    except Exception:  # the cluster is gone: so are the workers' copies
        pass


class _Round:
    """The parts of one call on the cluster: submitted as :class:`~workers.dispatch.Dispatch` hands them out, their
    answers as they end, and when each began and ended (:meth:`DaskPredecessors._parts`)."""

    def __init__(self, pool: DaskPredecessors, call: Call, z: Any, outside: Any) -> None:
        from distributed import as_completed

        self.pool, self.call, self.z, self.outside = pool, call, z, outside
        self.slots = pool.slots()
        self.dispatch = Dispatch(call.work, max(1, len(self.slots)), call.reads)
        self.classes = None if call.symmetry is None else call.symmetry.classes
        self.cores: dict[int, Any] = {}  # the split cut's first phases, which the joins depend on
        self.submitted: dict[str, Task] = {}
        self.live: list[Any] = []
        # Where parts are handed out one by one this process waits for every task's end (fetching only the final
        # answers); else only for the final answers, which the client fetches in its own thread as each ends (one
        # round trip per part less).
        self.watch_first = pool.cut == "split" and not self.dispatch.at_once
        self.ac = as_completed(with_results=not self.watch_first, raise_errors=False)
        self.sent_at, self.t_sent = time.time(), time.perf_counter()
        self.last_start = self.last_end = self.last_entered = self.sent_at
        self.ran_on: dict[str, int] = {}
        self.busy: dict[str, list[float]] = {}  # per worker: the seconds and CPU seconds of its tasks in this call
        self.joined_at = 0.0

    def submit(self, tasks: list[Task]) -> None:
        pool, call = self.pool, self.call
        for t in tasks:
            spec = call.specs[t.k]
            key = f"compabs-cpre-{pool.calls}-{t.kind}-{t.k}-{uuid.uuid4().hex[:8]}"
            if t.kind == "join":  # each range's states from the pairs of the ranges they admit, own range first
                assert call.reads is not None
                args: tuple = (join_part, pool.problem_key, spec, self.classes,
                               *(self.cores[j] for j in call.reads[t.k]))
            else:
                args = (compute_part, pool.problem_key, spec, self.z, self.outside, self.classes, t.kind == "core")
            fut = pool.client.submit(*args, pure=False, retries=pool.retries, key=key,
                                     **pool.placed(self.slots, t.slot))
            if t.kind == "core":
                self.cores[t.k] = fut
            self.submitted[key] = t
            if t.kind != "core" or self.watch_first:
                self.ac.add(fut)

    def answers(self) -> Iterator[tuple[int, Part]]:
        """The final answers as they end, by range (a first phase's answer stays on its worker, where the joins that
        read it fetch it); every part handed out as a worker frees up."""
        self.submit(self.dispatch.start())
        for item in self.ac:
            fut, answer = (item, None) if self.watch_first else item
            task = self.submitted[fut.key]
            self.live.append(fut)
            if fut.status == "error":
                exc = fut.exception()
                if isinstance(exc, BDDMemoryError):
                    raise BDDMemoryError(f"a synthesis part on a Dask worker: {exc}")
                if isinstance(exc, ProblemMissing):  # a new one: raising exc itself would tie it to this frame
                    raise ProblemMissing(str(exc))
                raise DaskPartFailed(f"a part of CPre failed on a Dask worker: {type(exc).__name__}: {exc}")
            if fut.status != "finished":  # cancelled under us (the cluster is closing)
                raise DaskPartFailed(f"a part of CPre on a Dask worker ended {fut.status}")
            self.submit(self.dispatch.done(task))  # before reading the answer: the freed worker must not wait
            if task.kind == "core":
                continue
            part = cast(Part, fut.result() if self.watch_first else answer)
            self._account(part)
            yield task.k, part
            fut.release()
        if not self.dispatch.finished:  # as_completed ran dry with parts still to run: nothing was lost silently
            raise DaskPartFailed("the Dask parts of a CPre call stopped before every part ran")
        self.joined_at = time.time()

    def _account(self, part: Part) -> None:
        self.ran_on[part.where] = self.ran_on.get(part.where, 0) + 1
        for where, s, c in part.phases:
            b = self.busy.setdefault(where, [0.0, 0.0])
            b[0], b[1] = b[0] + s, b[1] + c
        self.last_start, self.last_end = max(self.last_start, part.began), max(self.last_end, part.ended)
        self.last_entered = max(self.last_entered, part.entered)

    def cancel(self) -> None:
        for fut in (*self.live, *self.cores.values(), *self.ac.futures):
            fut.cancel()


class DaskPredecessors(PartitionedCPre):
    """``∃u.CPre(Z)`` of a :class:`~pipelines.synthesis.cpre.ControllablePredecessor` in ``parts`` parts on the
    workers of ``client`` (module docstring).

    Parameters
    ----------
    cpre : ControllablePredecessor
    parts : int
        Parts per call (>= 2), run as Dask tasks (:data:`PARTS_PER_WORKER` per worker is what :func:`parts_for`
        gives).
    client : distributed.Client
        The job's client (its workers import ``workers.dask_cpre``, as they import ``workers.tasks``).
    retries : int
        Dask retries of a part that raised (a worker's death is retried by Dask itself).
    cut : {'auto', 'window', 'split', 'w', 'x'}
        What the parts split (:func:`~pipelines.synthesis.partitioned.cut_digits`).

    Call it like :meth:`~pipelines.synthesis.cpre.ControllablePredecessor.predecessors`; :meth:`close` drops the
    workers' copies.

    Attributes
    ----------
    timing : dict of str to float
        Seconds summed over the calls: sending the sets, the slower part of each call (and the most CPU seconds a
        part of each call took: on a machine with fewer cores than workers, what the slower part would take on a
        core of its own), reading and joining the parts after it ended, the ∃u step of the w cut (what the job's
        process adds to the parts' time). Of ``after_parts``: ``last_start``, from sending the parts until the last
        of them began computing (Dask's dispatch, a worker's first loading of the problem, parts queued behind
        others), of which ``last_entered``, until the last part's task was entered on its worker (the loading not
        counted), and ``after_last``, from the end of the last part's computation until this process had joined
        every part (its bytes coming back and read here). Both from the workers' wall clocks: exact on one
        machine, off by the clocks' skew on a real cluster.
    history : list of dict
        The same per call, with the call's wall seconds, its parts' summed seconds (wall and CPU), the most of its
        parts that ran on one worker (of the split cut, of its second phase), the most tasks submitted at once
        (``most_in_flight``: one per worker) and the seconds (and CPU seconds) of the busiest worker's tasks
        (``busiest_worker``: with more parts than workers, what the call waited for) against ``parts_span``, from
        sending the parts until the last ended (the difference: workers waiting, for the split cut's second phase
        of a range until every first phase it reads ended), in call order. With more parts than workers
        ``last_start`` is when the last part was handed out and began.
    """

    on = "cluster"

    def __init__(self, cpre: ControllablePredecessor, parts: int, *, client: Any, retries: int = 1,
                 cut: str = "auto") -> None:
        super().__init__(cpre, parts, cut)
        self.client = client
        self.retries = retries
        self.timing = dict.fromkeys(TIMING, 0.0)
        self.history: list[dict[str, float]] = []
        self.model_key = uuid.uuid4().hex
        self.problem_key = ""
        self._payload: dict[str, Any] | None = None
        self._round: _Round | None = None
        self._finalizer = weakref.finalize(self, _forget_everywhere, client, self.model_key)

    # ------------------------------------------------------------------ moving problems and parts
    def _send(self, problem: Problem) -> None:
        # Once to every worker: each part's task then finds it in its worker's memory (dask_parts.receive says why
        # not as a dependency of the parts).
        self._payload = pack(problem, self.model_key)
        self._resend()

    def _resend(self) -> None:
        self.problem_key = f"{self.model_key}-{uuid.uuid4().hex}"
        self.client.run(receive, self.problem_key, self._payload)

    def _run(self, call: Call) -> Iterator[Answer]:
        try:
            yield from self._parts(call)
        except ProblemMissing:  # a worker joined or restarted since the problem was sent: send it again, once
            self._resend()
            yield from self._parts(call)

    def _parts(self, call: Call) -> Iterator[Answer]:
        m = call.problem.model
        z = self._scatter(to_bytes(m, call.Z, "writing a set for the Dask workers"))
        # the reach loop's outside is ¬Z: the workers complement their Z (parts.NOT_Z)
        o = None if call.outside is None else NOT_Z if call.not_z else self._scatter(to_bytes(m, call.outside))
        self._round = rnd = _Round(self, call, z, o)
        try:
            for k, part in rnd.answers():
                result = from_bytes(m, part.blob, "reading a Dask worker's part of CPre")
                yield Answer(k, result, part.seconds, part.cpu)
                del result
        finally:
            rnd.cancel()

    def _scatter(self, data: Any) -> Any:
        """One future for ``data`` (a set of the call as DDDMP bytes), on every worker: each part depends on it. In a
        list, so that any ``data`` is one future (``scatter`` gives a collection's items a future each)."""
        (future,) = self.client.scatter([data], broadcast=True, hash=False)
        return future

    def slots(self) -> list[str]:
        """The workers' addresses, one per thread, in a fixed order: part ``k`` of a call goes to slot ``k``
        (:meth:`placed`)."""
        return [addr for addr, n in sorted(self.client.nthreads().items()) for _ in range(n)]

    @staticmethod
    def placed(slots: list[str], slot: int) -> dict[str, Any]:
        """Where a task that :class:`~workers.dispatch.Dispatch` gave slot ``slot`` runs: that slot's worker, or
        another if that one is gone (a loose restriction).

        Why not leave it to Dask: its scheduler places the parts of a call by its estimates of their durations,
        and on 16 workers (consensus N = 5, split cut) it can put one call's 16 parts on 6 workers, five of them one
        after another on one worker, so that the call takes the time of five parts; pinned, each part has a worker
        of its own."""
        if not slots:
            return {}
        return {"workers": [slots[slot % len(slots)]], "allow_other_workers": True}

    def _stop(self) -> None:
        self._round = None
        self._finalizer()

    def _abandon(self) -> None:
        # Not close(): forgetting the problem runs on every worker's event loop, which a worker still inside a
        # cancelled part's CUDD operation answers only when that operation ends. The workers keep their copies
        # until close() or garbage collection; the next call sends the problem again.
        self._problem, self._held, self._round = None, None, None

    def _failure(self, exc: Exception) -> PartitionFailed:
        return DaskPartFailed(f"a part of CPre failed on the Dask cluster: {type(exc).__name__}: {exc}")

    # ------------------------------------------------------------------ accounting
    def _record(self, call: Call, seconds: list[float], cpu: list[float], joined: float, ended: float) -> None:
        rnd = self._round
        assert rnd is not None
        slowest = max(seconds, default=0.0)
        after = {"sending": rnd.t_sent - call.started, "slowest_part": slowest,
                 "slowest_part_cpu": max(cpu, default=0.0), "after_parts": joined - rnd.t_sent - slowest,
                 "exists_u": ended - joined,
                 "last_start": max(0.0, rnd.last_start - rnd.sent_at),
                 "last_entered": max(0.0, rnd.last_entered - rnd.sent_at),
                 "after_last": max(0.0, rnd.joined_at - rnd.last_end)}
        for key, value in after.items():
            self.timing[key] += value
        busy = rnd.busy.values()
        self.history.append({"wall": round(ended - call.started, 3), "parts_sum": round(sum(seconds), 3),
                             "parts_cpu_sum": round(sum(cpu), 3),
                             "most_on_one_worker": max(rnd.ran_on.values(), default=0),
                             "most_in_flight": rnd.dispatch.most_in_flight,
                             "busiest_worker": round(max((b[0] for b in busy), default=0.0), 3),
                             "busiest_worker_cpu": round(max((b[1] for b in busy), default=0.0), 3),
                             "parts_span": round(max(0.0, rnd.last_end - rnd.sent_at), 3),
                             **{k: round(v, 3) for k, v in after.items()}})
        self._round = None
        log.info("CPre on the cluster: %d parts took %s s (sum %.2f); call %.2f s: sending %.2f, parts and joining "
                 "them %.2f (the last was entered after %.2f, began after %.2f, joined %.2f after the last ended), "
                 "the ∃u step %.2f", len(seconds), [round(s, 2) for s in seconds], sum(seconds), ended - call.started,
                 after["sending"], after["after_parts"] + slowest, after["last_entered"], after["last_start"],
                 after["after_last"], after["exists_u"])

    def _report(self) -> dict[str, Any]:
        return {"seconds": {k: round(v, 2) for k, v in self.timing.items()}, "per_call": list(self.history)}


def parts_for(client: Any, per_worker: int = PARTS_PER_WORKER) -> int:
    """Parts of a call on the cluster of ``client``: ``per_worker`` per worker thread, at least 2."""
    return max(2, per_worker * sum(client.nthreads().values()))


def on_cluster(client: Any, retries: int = 1, cut: str = "auto"):
    """A ``partitioned`` factory (``factory(cpre, parts)``) running the parts on ``client``'s workers."""

    def factory(cpre: ControllablePredecessor, parts: int) -> DaskPredecessors:
        return DaskPredecessors(cpre, parts, client=client, retries=retries, cut=cut)

    return factory


__all__ = ["PARTS_PER_WORKER", "TIMING", "DaskPartFailed", "DaskPredecessors", "on_cluster", "parts_for"]
