"""Running a job on a Dask cluster, resumable through the relation store.

:func:`run_job` runs the one definition of the stages (:func:`workers.job.run_abstraction`) with a mapper,
:class:`StoreMapper`, that sends the per-cell chunks to the cluster: for each chunk whose done-marker is in the
store it reads the chunk back (*reused*); every other chunk becomes one :func:`workers.tasks.abstract_chunk`
task (*computed*), which writes the chunk and its marker. Results are rebuilt from the store and yielded as
tasks complete (``as_completed``), so progress events are live and a crash loses only the running chunks.

Chunk size
----------
A task is one chunk of state cells: ``options.chunk_cells`` if the spec sets it, else ``TASK_POINTS`` = 1e8
black-box evaluations per task (the in-process default is 2e6). Measured with
``bench/runner.py`` on this kind of loaded 2-core machine (LocalCluster, 2 single-threaded worker processes;
trust ratios, not absolute times):

* one task, one at a time, round trip minus the compute the task timed itself: median 15-18 ms, of which
  ~10-11 ms is Dask (submit -> result of a no-op), ~3.5 ms writing lo/hi/blocking + the marker, ~2.4 ms
  reading the chunk back in the runner.
* pipelined (82 one-cell tasks on 2 workers; worker time not spent computing, per task): 24-28 ms. On 2 cores
  the scheduler and the runner share the CPUs with the workers.

The per-cell stage then cost 130-360 ns per evaluation and 4e6 evaluations per task kept the overhead <= 5 %.
Since the closed-form SCP (11-23 ns per evaluation, ``bench/run.py --cases floor``) a 4e6-evaluation task took
~0.05-0.1 s, a quarter to a half of it overhead: on ``examples/stress.yaml`` (2026-11-23, same machine and hour)
two workers were 1.55x one worker with 4e6 and 1.69x with 2e7 (per-cell stage 95.0 s vs 56.2 s; CPU 104 s vs
108 s, so nearly CPU-bound), at a peak RSS of 1.02 GB (one worker) and 1.72 GB (two workers, process tree)
against 0.65 and 1.08 GB: ~30 MB per 1e6 evaluations of a 1-D state, ~600 MB per task. Smaller
chunks (``options.chunk_cells``) cost proportionally more: a one-cell task of ~2-30 ms is mostly overhead. A
subsystem smaller than one chunk (the tank case: 41 state cells, ~0.03 s) is one task. Since then a task's
temporaries are bounded by ``subsystem.BLOCK_POINTS``, not by its chunk, so a chunk's size costs memory only
for its results (a few bytes per triple).

With the compiled per-cell pass (~5 ns per evaluation) a 2e7 task is ~0.1 s, and the overhead per task (Dask,
the store write, the runner's read back: ~7 ms of CPU, more while both cores compute) was again a tenth of
the stage. On ``examples/stress.yaml`` (2.2e7 evaluations per state cell, 513 cells; 2026-11-25, runs
alternated, per-cell stage wall / its CPU / compute timed inside the tasks):

=====================  ===============================  ===============================
cells per task (tasks)  one worker                       two workers
=====================  ===============================  ===============================
1 (513), 2e7            53.7 s / 59.2 s / 50.2 s          31.0, 32.8 s / 61.1, 64.7 s / 58.1, 60.8 s
4 (129), 1e8            52.1 s / 55.2 s / 50.9 s          29.1, 28.2, 27.0, 29.4 s / 57.3, 55.8, 53.4, 57.9 s
8 (65), 2e8             51.0 s / 53.5 s / 50.3 s          26.9, 28.0 s / 53.3, 55.2 s
=====================  ===============================  ===============================

Four cells per task left ~1 s of the one-worker stage to overhead (against ~3.5 s); with two workers the CPU
beyond the tasks' compute went from 3-4 s to ~1 s. Eight cells were no better than four, within the noise; a
task of ~0.5 s keeps the imbalance at the end of a stage and the work lost with a killed worker small. (One
earlier pair of runs, 2026-11-24, had found 8e7 no better than 2e7: 34.7 s against 32.9 and 36.0 s, in an
hour whose noise was as large as the difference.) ``examples/stress.yaml`` has 3600 samples per cell since
(3.1e7 evaluations per cell: 3 cells per task).

Failures
--------
A task that raises a :class:`~pipelines.errors.CompabsError` (a BlackBoxError for a NaN, ...) fails the job
with that error, same type and message, without the remote traceback. A task whose workers keep dying
(``KilledWorker`` after ``distributed.scheduler.allowed-failures`` restarts) becomes a :class:`ClusterError`
naming the subsystem and the chunk. A worker killed once is restarted by its nanny and its task reruns; the
job goes on. When the job fails, its outstanding tasks are cancelled; chunks already marked done are kept, so
running the job again resumes. A task running longer than ``options.task_timeout`` seconds (a hung black box)
fails the job with a :class:`TaskTimeoutError` naming the subsystem and the cells; if its thread cannot be
stopped, the worker that ran it is restarted (:func:`workers.tasks._watched`). The stages that run in the
runner's own process (Lipschitz estimation, interconnection, audit, synthesis, closed loop) have no such limit.
"""

from __future__ import annotations

import os
import uuid
from dataclasses import dataclass
from typing import Any, Callable, Iterable, Iterator, Sequence

from pipelines.errors import CompabsError
from workers.job import AbstractionResult, Progress, run_abstraction
from pipelines.network import Network, Subsystem, build_network
from pipelines.spec.model import JobSpec
from pipelines.abstraction.cells import CellsResult, abstract_cells

from workers.cluster import connect
from workers.errors import ClusterError, StoreError, TaskTimeoutError
from workers.store import RelationStore, group_name
from workers.tasks import abstract_chunk

#: Black-box evaluations per task (see "Chunk size" above).
TASK_POINTS = 100_000_000


@dataclass
class RunnerStats:
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


def _chunk_size(args: Sequence[tuple], n_x: int) -> int:
    """The common chunk size of a subsystem's argument tuples, checking they tile ``[0, n_x)`` regularly."""
    c = args[0][2] - args[0][1]
    for i, a in enumerate(args):
        start, stop = a[1], a[2]
        if start != i * c or stop != min(start + c, n_x):
            # chunk_ranges makes regular chunks; a store chunk must be exactly one task's range.
            raise RuntimeError(f"chunk {i} = [{start}, {stop}) is not chunk {i} of {c} cells; the store needs regular chunks")
    if args[-1][2] != n_x:
        raise RuntimeError(f"chunks end at {args[-1][2]}, not at {n_x}")
    return c


class StoreMapper:
    """The ``mapper`` given to :func:`workers.job.run_abstraction`.

    ``mapper(abstract_cells, args)`` yields :class:`CellsResult` objects, reused chunks first, then computed
    ones in completion order. Any other function is mapped over the cluster plainly, with its results returned
    through the scheduler (no stage does that today; it keeps the mapper a general one).
    """

    def __init__(self, client: Any, store: RelationStore, network: Network) -> None:
        self._client = client
        self._store = store
        self._members = {k: [m.name for m in ms] for k, ms in network.unique_subsystems().items()}
        self._timeout = network.spec.options.task_timeout  # seconds per task (workers.tasks._watched)
        self.stats = RunnerStats()

    def __call__(self, fn: Callable[..., Any], args: Sequence[tuple]) -> Iterable[Any]:
        if fn is abstract_cells:
            return self._cells(args)
        return self._plain(fn, args)

    # ---------------------------------------------------------------- the per-cell stage
    def _cells(self, args: Sequence[tuple]) -> Iterator[CellsResult]:
        if not args:
            return
        sub: Subsystem = args[0][0]
        _, _, _, L_x, L_w, method, objective = args[0]
        if any(a[0].key != sub.key or tuple(a[3:]) != (L_x, L_w, method, objective) for a in args):
            raise RuntimeError("a StoreMapper batch must be one subsystem with one set of constants")
        n_x = sub.state_grid.size
        chunk_cells = _chunk_size(args, n_x)
        group = group_name(sub, L_x, L_w, method, objective, chunk_cells)
        members = self._members.get(sub.key, [sub.name])
        self._store.prepare(
            group, sub, members, chunk_cells,
            {"L_x": float(L_x), "L_w": float(L_w), "method": method, "objective": objective},
        )
        markers = self._store.markers(group)
        reuse, todo = [], []
        for a in args:
            m = markers.get(a[1] // chunk_cells)
            if m is not None and (m.get("start"), m.get("stop")) == (a[1], a[2]):
                reuse.append(m)
            else:
                todo.append(a)
        self.stats.chunks_total += len(args)

        from distributed import as_completed

        # Unique keys: a task must run again when resubmitted, never resolve to a finished task of an earlier
        # run that the scheduler has not forgotten yet (its marker may have been deleted since).
        run = uuid.uuid4().hex[:8]
        futures = {
            self._client.submit(
                abstract_chunk, self._store.url, group, *a, self._timeout,
                key=f"abstract_chunk-{group}-{a[1] // chunk_cells}-{run}", pure=False,
            ): a
            for a in todo
        }
        submitted = list(futures)
        try:
            if reuse:
                # One read of the whole arrays beats one read per chunk when many chunks are reused.
                arrays = self._store.read_all(group) if len(reuse) > 1 else None
                for m in reuse:
                    self.stats.chunks_reused += 1
                    yield self._store.read(group, m, arrays)
            for fut in as_completed(futures):
                a = futures.pop(fut)
                meta = self._outcome(fut, a, members, chunk_cells)
                self.stats.chunks_computed += 1
                self.stats.task_seconds += float(meta.get("seconds", 0.0))
                yield self._store.read(group, meta)
        finally:
            # On an error (or an abandoned generator) stop what is still queued; finished chunks stay marked.
            # Release the finished and failed ones too: the caller may keep the error's traceback, and with
            # it these Future objects, which would otherwise pin their tasks on the scheduler.
            if submitted:
                self._client.cancel(submitted)

    def _outcome(self, fut: Any, a: tuple, members: list[str], chunk_cells: int) -> dict[str, Any]:
        """A finished task's marker, or the task's error in the form the caller can act on."""
        from distributed import KilledWorker

        start, stop = a[1], a[2]
        where = f"subsystem '{', '.join(members)}', chunk {start // chunk_cells} (state cells {start}..{stop - 1})"
        try:
            return fut.result()
        except TaskTimeoutError as exc:
            if exc.stuck and exc.worker:
                # Its thread is still running on that worker (blocked in C): restart the process to stop it. Dask
                # reruns whatever else that worker was running; other jobs carry on.
                try:
                    self._client.restart_workers([exc.worker], timeout=60, raise_for_error=False)
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
                "the process or exhausts its memory. Run the job without a cluster (compabs run without "
                "--scheduler/--workers) to see the error, give workers more memory, or lower options.chunk_cells. "
                "Chunks already done are kept; running the job again resumes."
            ) from None
        except OSError as exc:
            raise StoreError(
                f"{where}: writing the relation store {self._store.url} failed: {exc}. Chunks already done are "
                "kept; fix the store location and run the job again to resume."
            ) from None

    # ---------------------------------------------------------------- anything else
    def _plain(self, fn: Callable[..., Any], args: Sequence[tuple]) -> Iterator[Any]:
        from distributed import as_completed

        futures = [self._client.submit(fn, *a, pure=False) for a in args]
        try:
            for fut in as_completed(futures):
                try:
                    yield fut.result()
                except CompabsError as exc:
                    raise exc.with_traceback(None) from None
        finally:
            self._client.cancel(futures)


def _client_info(client: Any) -> dict[str, Any]:
    from workers.cluster import _dashboard

    return {
        "scheduler": client.scheduler.address,
        "workers": len(client.nthreads()),
        "dashboard": _dashboard(client),
        "embedded": False,
    }


def run_job(
    spec: JobSpec,
    out_dir: str | os.PathLike[str],
    *,
    scheduler: str | None = None,
    workers: int = 2,
    progress: Progress | None = None,
    allowed_modules: Sequence[str] | None = None,
    audit: bool = True,
    overwrite: bool = False,
    client: Any = None,
    audit_beside: bool = False,
) -> tuple[AbstractionResult, dict[str, Any]]:
    """Run a job's abstraction stages with the per-cell stage on a Dask cluster.

    Parameters
    ----------
    spec : JobSpec
    out_dir : str or path
        Output directory or fsspec URL; the relation store is ``out_dir/relations.zarr``. Chunks marked done
        there by an earlier run of the same spec are reused.
    scheduler : str, optional
        ``tcp://HOST:PORT`` of a running scheduler (default: ``COMPABS_SCHEDULER``, else an embedded cluster).
    workers : int
        Worker processes of an embedded cluster.
    progress : callable, optional
        ``progress(stage, done, total, message)``, as for ``run_abstraction``.
    allowed_modules, audit, audit_beside
        As for ``run_abstraction`` (with ``audit_beside`` the caller finishes or cancels the audit).
    overwrite : bool
        If the store holds another spec's relations, delete it instead of refusing.
    client : distributed.Client, optional
        Use this client (a service's long-lived one) instead of connecting; it is not closed.

    Returns
    -------
    result : AbstractionResult
    runner_info : dict
        ``scheduler``, ``workers``, ``dashboard``, ``embedded``, ``store``, ``chunks_total``,
        ``chunks_computed``, ``chunks_reused``, ``task_compute_seconds``; the caller puts it in the report as
        ``runner``.

    Raises
    ------
    CompabsError
        As ``run_abstraction``; :class:`StoreMismatchError` for a store of another spec; :class:`ClusterError`
        when the cluster cannot be reached or a task keeps killing its workers; :class:`StoreError`.
    """
    # Resolve the spec and open the store before starting a cluster: a bad spec or a stale store fails at once.
    network = build_network(spec, allowed_modules)
    store = RelationStore.open(out_dir, spec, network, overwrite=overwrite)
    conn = None
    if client is None:
        conn = connect(scheduler, workers)
        client, info = conn
    else:
        info = _client_info(client)
    try:
        mapper = StoreMapper(client, store, network)
        kwargs = {} if progress is None else {"progress": progress}
        result = run_abstraction(
            spec, mapper=mapper, allowed_modules=allowed_modules, audit=audit, chunk_points=TASK_POINTS,
            audit_beside=audit_beside, **kwargs
        )
        try:
            store.consolidate()
            if "://" not in os.fspath(out_dir):  # the audit reads it back (workers.jobdir)
                from workers.jobdir import save_interconnection

                save_interconnection(result.interconnection, out_dir, spec)
        except OSError as exc:
            raise StoreError(
                f"writing the job's files in {os.fspath(out_dir)} failed: {exc}. Every chunk is stored; free space or "
                "fix the permissions and run the job again to finish it."
            ) from None
        except BaseException:
            result.cancel_audit()
            raise
    finally:
        if conn is not None:
            conn.close()
    runner_info = {**info, "store": store.url, **mapper.stats.as_dict()}
    return result, runner_info
