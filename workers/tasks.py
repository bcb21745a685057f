"""The task functions the cluster runs.

A task is pure given its arguments: it recomputes the same chunk bit for bit wherever and however often it
runs (Dask reruns the tasks of a killed worker), and its only effect is writing that chunk's region and marker
into the relation store. It returns the small marker dict, never arrays: results held in a worker's memory
are lost with the worker (ENGINEERING "Dask distributed"), the store is not.

The subsystem travels pickled; its black box pickles as its expression text (or ``module:function`` name) and
compiles again on the worker (:class:`pipelines.blackbox.BlackBox`), so no code object crosses the wire.
This module must be importable by the scheduler and the workers (it is part of the installed package).
"""

from __future__ import annotations

import contextvars
import ctypes
import threading
import time
from typing import Any

from pipelines.abstraction.cells import CellTask
from pipelines.abstraction.relation import CellsResult
from workers.errors import TaskTimeoutError
from workers.relation_store import write_chunk

#: Seconds a timed-out task waits for its thread to stop after asking it to.
STOP_GRACE = 1.0


def abstract_chunk(store_url: str, group: str, task: CellTask, timeout: float | None = None) -> dict[str, Any]:
    """Abstract state cells ``[start, stop)`` of a subsystem and write them into the store.

    Parameters
    ----------
    store_url : str
        The relation store (``DIR/relations.zarr``, a path or fsspec URL).
    group : str
        The store group of this subsystem and these constants (:func:`workers.relation_store.group_name`); it exists
        already, created by the runner.
    task : CellTask
        The chunk to compute; ``[task.start, task.stop)`` is exactly one chunk of the group.
    timeout : float, optional
        Seconds the computation may take (``options.task_timeout``); ``None``: no limit. See :func:`_watched`.

    Returns
    -------
    dict
        The chunk's done-marker (start, stop, successors, slope_x, slope_w, seconds of compute, all_fill, and
        sha256: the chunk's checksum, :func:`workers.relation_store.chunk_checksum`).

    Raises
    ------
    CompabsError
        Whatever the method raises (a BlackBoxError for a NaN, ...), unchanged: the runner re-raises it.
    TaskTimeoutError
        The computation ran longer than ``timeout``; nothing was written.
    """
    t0 = time.perf_counter()
    result = task.run() if timeout is None else _watched(task, timeout)
    seconds = time.perf_counter() - t0
    return write_chunk(store_url, group, result, seconds)


def _watched(task: CellTask, timeout: float) -> CellsResult:
    """``task.run()`` in a watched thread: its result, its exception, or a TaskTimeoutError.

    A thread cannot be killed. After ``timeout`` seconds the task asks it to stop (an asynchronous
    ``TaskTimeoutError`` delivered at its next Python bytecode: enough for a black box looping in Python), waits
    ``STOP_GRACE`` seconds, and raises. If the thread is still running (a black box blocked in C, e.g. a sleep),
    the error says ``stuck`` and the runner restarts the worker process to stop it. Nothing is written to the
    store either way: the data and marker writes happen only after a result.
    """
    sub, start, stop = task.subsystem, task.start, task.stop
    box: dict[str, Any] = {}

    def target() -> None:
        try:
            box["result"] = task.run()
        except BaseException as exc:  # handed to the task's thread below
            box["error"] = exc

    # The task's context variables go along (Dask's get_worker() reads one: a black box may ask where it runs).
    context = contextvars.copy_context()
    thread = threading.Thread(target=context.run, args=(target,), name=f"compabs-chunk-{sub.name}-{start}", daemon=True)
    thread.start()
    thread.join(timeout)
    if not thread.is_alive():
        if "error" in box:
            raise box["error"]
        return box["result"]
    assert thread.ident is not None  # set by start()
    ctypes.pythonapi.PyThreadState_SetAsyncExc(ctypes.c_ulong(thread.ident), ctypes.py_object(TaskTimeoutError))
    thread.join(STOP_GRACE)
    if not thread.is_alive() and "result" in box:  # it finished after all
        return box["result"]
    worker = None
    try:
        from distributed import get_worker

        worker = get_worker().address
    except (ImportError, ValueError):  # not inside a Dask worker (a direct call)
        pass
    raise TaskTimeoutError(
        f"subsystem '{sub.name}': the black box did not finish state cells {start}..{stop - 1} within "
        f"options.task_timeout = {timeout:g} s, so the job stops here (a hung or far too slow black box). "
        "Check the dynamics on those cells, or raise options.task_timeout (or lower options.chunk_cells); "
        "chunks already done are kept and running the job again resumes.",
        worker=worker,
        stuck=thread.is_alive(),
    )
