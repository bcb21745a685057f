"""Where the per-cell tasks of a job run: the pluggable half of the one orchestrator (:mod:`workers.job`).

An executor takes one batch of :class:`~pipelines.abstraction.cells.CellTask` (the chunks of one distinct
subsystem, computed with one set of constants) and yields their :class:`~pipelines.abstraction.relation.CellsResult`
as they complete, in any order. Two kinds:

- :class:`InProcess`: in this process, on threads or one task after another (tests, small jobs, ``compabs run
  --in-process``);
- :class:`OnDask`: one Dask task per chunk on a cluster (:mod:`workers.cluster`), each writing its chunk into the
  relation store (:mod:`workers.relation_store`) and returning its small done-marker.

Both go through the job's relation store when they have one: a chunk whose done-marker is there is read back
(*reused*) instead of computed, so a job that is run again resumes. A reused chunk is verified against the
checksum in its marker (:func:`workers.relation_store.check_chunks`, on one bulk read of the group); a damaged one
(missing, unreadable, or not matching) is logged as a warning naming its group and chunk, its marker cleared,
and it is recomputed like a chunk never done. Without a store (``InProcess()``) nothing is written. The chunk size is the executor's (:attr:`Executor.chunk_points`): a cluster task must be large enough
for its overhead (about 10 ms) not to count.
"""

from __future__ import annotations

import logging
import time
import uuid
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from pipelines.abstraction.cells import CellTask
from pipelines.abstraction.relation import DEFAULT_CHUNK_POINTS, CellsResult
from pipelines.errors import CompabsError
from workers.errors import ClusterError, StoreError, TaskTimeoutError
from workers.relation_store import ChunkCheck, RelationStore, chunk_place, group_name

log = logging.getLogger(__name__)

@dataclass(frozen=True)
class Execution:
    """Where a job's per-cell tasks (and its synthesis' parts) run, as :func:`workers.job.run_job` is asked.

    Attributes
    ----------
    client : distributed.Client, optional
        A long-lived client (the service's): used, never closed.
    scheduler : str, optional
        ``tls://HOST:PORT`` of a scheduler to connect to; ``None`` with no client: an embedded cluster.
    workers : int
        Worker processes of an embedded cluster.
    in_process : bool or None
        ``True``: no cluster, this process; ``None``: in this process when no cluster is given and the job is
        small (:func:`workers.job.runs_in_process`); ``False``: on a cluster.
    """

    client: Any = None
    scheduler: str | None = None
    workers: int = 2
    in_process: bool | None = False


#: Black-box evaluations per Dask task: a ~0.5 s task on the compiled per-cell pass, so the ~10 ms per task that
#: Dask, the store write and the read back cost stay a few per cent (``bench/runner.py`` measures it).
TASK_POINTS = 100_000_000


@dataclass
class ExecutorStats:
    """Counts for the report's ``runner`` section."""

    chunks_total: int = 0
    chunks_computed: int = 0
    chunks_reused: int = 0
    task_seconds: float = 0.0  # compute time inside computed tasks, summed

    def as_dict(self) -> dict[str, Any]:
        return {
            "chunks_total": self.chunks_total,
            "chunks_computed": self.chunks_computed,
            "chunks_reused": self.chunks_reused,
            "task_compute_seconds": self.task_seconds,
        }


class Executor(Protocol):
    """What :func:`workers.job.run_abstraction` needs of an executor."""

    #: Black-box evaluations per chunk when the spec does not set ``options.chunk_cells``.
    chunk_points: int
    stats: ExecutorStats

    def map_cells(self, tasks: Sequence[CellTask], members: Sequence[str]) -> Iterator[CellsResult]:
        """The results of ``tasks`` (the regular chunks of one subsystem, one set of constants), in any order.
        ``members`` names the subsystems the relation serves (for messages and the store)."""
        ...

    def describe(self) -> dict[str, Any]:
        """Where the chunks run, for the report's ``runner`` section (``scheduler``, ``workers``, ...)."""
        ...


def _chunk_size(tasks: Sequence[CellTask]) -> int:
    """The common chunk size of a subsystem's tasks, checking they tile its state cells regularly."""
    n_x = tasks[0].subsystem.state_grid.size
    c = tasks[0].stop - tasks[0].start
    for i, t in enumerate(tasks):
        if t.start != i * c or t.stop != min(t.start + c, n_x):
            # chunk_ranges makes regular chunks; a store chunk must be exactly one task's range.
            raise RuntimeError(f"chunk {i} = [{t.start}, {t.stop}) is not chunk {i} of {c} cells; the store needs "
                               "regular chunks")
    if tasks[-1].stop != n_x:
        raise RuntimeError(f"chunks end at {tasks[-1].stop}, not at {n_x}")
    return c


def _plan(store: RelationStore, tasks: Sequence[CellTask], members: Sequence[str]
          ) -> tuple[str, int, dict[int, dict[str, Any]], list[CellTask]]:
    """The store group of a batch, its chunk size, the markers of chunks marked done (chunk -> marker; their
    data not verified yet, see :func:`_verify`) and the tasks still to run."""
    first = tasks[0]
    if any(t.subsystem.key != first.subsystem.key or t.constants != first.constants for t in tasks):
        raise RuntimeError("a batch of cell tasks must be one subsystem with one set of constants")
    chunk_cells = _chunk_size(tasks)
    group = group_name(first.subsystem, first.L_x, first.L_w, first.method, first.objective, chunk_cells)
    store.prepare(group, first.subsystem, list(members), chunk_cells,
                  {"L_x": float(first.L_x), "L_w": float(first.L_w), "method": first.method,
                   "objective": first.objective})
    markers, bad = store.marker_state(group)
    reuse: dict[int, dict[str, Any]] = {}
    todo = []
    for i, t in enumerate(tasks):  # regular chunks: task i is chunk i
        if i in markers:
            reuse[i] = markers[i]
        else:
            if i in bad:
                _damaged(store, group, t, chunk_cells, bad[i])
            todo.append(t)
    return group, chunk_cells, reuse, todo


def _damaged(store: RelationStore, group: str, t: CellTask, chunk_cells: int, reason: str) -> None:
    """A chunk marked done that cannot be reused: say so, and clear its marker before it is recomputed."""
    place = chunk_place(group, t.start // chunk_cells, chunk_cells, t.subsystem.state_grid.size)
    log.warning("relation store %s: %s is damaged: %s; it is recomputed, not reused", store.url, place, reason)
    store.clear_marker(group, t.start // chunk_cells)


def _verify(store: RelationStore, group: str, chunk_cells: int, reuse: dict[int, dict[str, Any]],
            tasks: Sequence[CellTask]) -> tuple[ChunkCheck, list[dict[str, Any]], list[CellTask]]:
    """Read the chunks marked done (one bulk read when there are several) and check each against its marker's
    checksum: what was read, the markers of the chunks to reuse, and the tasks of the damaged ones."""
    check = store.check(group, reuse)
    redo = []
    for i, reason in sorted(check.damaged.items()):
        _damaged(store, group, tasks[i], chunk_cells, reason)
        redo.append(tasks[i])
    return check, [m for i, m in sorted(reuse.items()) if i not in check.damaged], redo


def _reused(store: RelationStore, group: str, check: ChunkCheck, good: list[dict[str, Any]], stats: ExecutorStats
            ) -> Iterator[CellsResult]:
    for m in good:
        stats.chunks_reused += 1
        yield store.read(group, m, check)


class InProcess:
    """Every task in this process: one after another, or on ``threads`` threads (the compiled black box and
    numpy's loops release the interpreter, so threads share the cores without a cluster's start-up); through
    ``store`` if given (resumable), else in memory."""

    def __init__(self, store: RelationStore | None = None, chunk_points: int = DEFAULT_CHUNK_POINTS,
                 threads: int = 1) -> None:
        self.store = store
        self.chunk_points = chunk_points
        self.threads = max(1, int(threads))
        self.stats = ExecutorStats()

    def map_cells(self, tasks: Sequence[CellTask], members: Sequence[str]) -> Iterator[CellsResult]:
        if not tasks:
            return
        self.stats.chunks_total += len(tasks)
        if self.store is None:
            todo: Sequence[CellTask] = tasks
            group = ""
        else:
            group, chunk_cells, reuse, todo = _plan(self.store, tasks, members)
            check, good, redo = _verify(self.store, group, chunk_cells, reuse, tasks)
            todo = sorted([*todo, *redo], key=lambda t: t.start)
            yield from _reused(self.store, group, check, good, self.stats)
        if self.threads == 1 or len(todo) < 2:
            for t in todo:
                yield self._count(*self._compute(group, t))
            return
        from concurrent.futures import ThreadPoolExecutor, as_completed

        with ThreadPoolExecutor(min(self.threads, len(todo)), thread_name_prefix="compabs-cells") as pool:
            futures = [pool.submit(self._compute, group, t) for t in todo]
            try:
                for fut in as_completed(futures):
                    yield self._count(*fut.result())
            finally:  # an error, or an abandoned generator: what has not started does not start
                for fut in futures:
                    fut.cancel()

    def _compute(self, group: str, t: CellTask) -> tuple[CellsResult, float]:
        t0 = time.perf_counter()
        result = t.run()
        seconds = time.perf_counter() - t0
        if self.store is not None:
            self.store.write(group, result, seconds)
        return result, seconds

    def _count(self, result: CellsResult, seconds: float) -> CellsResult:
        self.stats.chunks_computed += 1
        self.stats.task_seconds += seconds
        return result

    def describe(self) -> dict[str, Any]:
        return {"scheduler": None, "workers": 0, "threads": self.threads, "dashboard": None, "embedded": True,
                "in_process": True}


class OnDask:
    """One Dask task per chunk (:func:`workers.tasks.abstract_chunk`), each writing its chunk and marker into
    ``store``; results are read back from the store as tasks complete (``as_completed``), so progress is live and
    a crash loses only the running chunks.

    A task that raises a :class:`~pipelines.errors.CompabsError` (a BlackBoxError for a NaN, ...) fails the job
    with that error, same type and message, without the remote traceback. A task whose workers keep dying
    (``KilledWorker`` after ``distributed.scheduler.allowed-failures`` restarts) becomes a :class:`ClusterError`
    naming the subsystem and the chunk. When the job fails, its outstanding tasks are cancelled; chunks already
    marked done are kept. A task running longer than ``options.task_timeout`` (a hung black box) fails the job
    with a :class:`TaskTimeoutError`; if its thread cannot be stopped, its worker is restarted.
    """

    def __init__(self, client: Any, store: RelationStore, info: dict[str, Any], task_timeout: float | None,
                 chunk_points: int = TASK_POINTS) -> None:
        self.client = client
        self.store = store
        self.info = info
        self.task_timeout = task_timeout
        self.chunk_points = chunk_points
        self.stats = ExecutorStats()

    def describe(self) -> dict[str, Any]:
        return dict(self.info)

    def map_cells(self, tasks: Sequence[CellTask], members: Sequence[str]) -> Iterator[CellsResult]:
        if not tasks:
            return
        from distributed import as_completed

        from workers.tasks import abstract_chunk

        group, chunk_cells, reuse, todo = _plan(self.store, tasks, members)
        self.stats.chunks_total += len(tasks)
        # Unique keys: a task must run again when resubmitted, never resolve to a finished task of an earlier
        # run that the scheduler has not forgotten yet (its marker may have been deleted since).
        run = uuid.uuid4().hex[:8]

        def submit(batch: list[CellTask]) -> None:
            for t in batch:
                fut = self.client.submit(abstract_chunk, self.store.url, group, t, self.task_timeout,
                                         key=f"abstract_chunk-{group}-{t.start // chunk_cells}-{run}", pure=False)
                futures[fut] = t
                submitted.append(fut)

        futures: dict[Any, CellTask] = {}
        submitted: list[Any] = []
        try:
            submit(todo)
            # Verified while the cluster computes; a damaged chunk is one more task.
            check, good, redo = _verify(self.store, group, chunk_cells, reuse, tasks)
            submit(redo)
            yield from _reused(self.store, group, check, good, self.stats)
            for fut in as_completed(futures):
                t = futures.pop(fut)
                meta = self._outcome(fut, t, members, chunk_cells)
                self.stats.chunks_computed += 1
                self.stats.task_seconds += float(meta.get("seconds", 0.0))
                yield self.store.read(group, meta)
        finally:
            # On an error (or an abandoned generator) stop what is still queued; finished chunks stay marked.
            # Release the finished and failed ones too: the caller may keep the error's traceback, and with
            # it these Future objects, which would otherwise pin their tasks on the scheduler.
            if submitted:
                self.client.cancel(submitted)

    def _outcome(self, fut: Any, t: CellTask, members: Sequence[str], chunk_cells: int) -> dict[str, Any]:
        """A finished task's marker, or the task's error in the form the caller can act on."""
        from distributed import KilledWorker

        where = (f"subsystem '{', '.join(members)}', chunk {t.start // chunk_cells} "
                 f"(state cells {t.start}..{t.stop - 1})")
        try:
            return fut.result()
        except TaskTimeoutError as exc:
            if exc.stuck and exc.worker:
                # Its thread is still running on that worker (blocked in C): restart the process to stop it. Dask
                # reruns whatever else that worker was running; other jobs carry on.
                try:
                    self.client.restart_workers([exc.worker], timeout=60, raise_for_error=False)
                except Exception:  # best effort: the job fails with the timeout either way
                    pass
            raise TaskTimeoutError(f"{where}: {exc}") from None
        except CompabsError as exc:
            # The method's own error, same type and message; the worker's traceback says nothing more.
            raise exc.with_traceback(None) from None
        except KilledWorker:
            import dask

            tries = int(dask.config.get("distributed.scheduler.allowed-failures", 3)) + 1
            raise ClusterError(
                f"{where}: the task died with its worker {tries} times (KilledWorker): its black box crashes "
                "the process or exhausts its memory. Run the job without a cluster (compabs run --in-process) "
                "to see the error, give workers more memory, or lower options.chunk_cells. Chunks already done "
                "are kept; running the job again resumes."
            ) from None
        except OSError as exc:
            raise StoreError(
                f"{where}: writing the relation store {self.store.url} failed: {exc}. Chunks already done are "
                "kept; fix the store location and run the job again to resume."
            ) from None


__all__ = ["TASK_POINTS", "Executor", "ExecutorStats", "InProcess", "OnDask"]
