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

import time
from typing import Any

from pipelines.network import Subsystem
from pipelines.subsystem import abstract_cells

from .store import write_chunk


def abstract_chunk(
    store_url: str,
    group: str,
    sub: Subsystem,
    start: int,
    stop: int,
    L_x: float,
    L_w: float,
    method: str,
    objective: str,
) -> dict[str, Any]:
    """Abstract state cells ``[start, stop)`` of a subsystem and write them into the store.

    Parameters
    ----------
    store_url : str
        The relation store (``DIR/relations.zarr``, a path or fsspec URL).
    group : str
        The store group of this subsystem and these constants (:func:`workers.store.group_name`); it exists
        already, created by the runner.
    sub, start, stop, L_x, L_w, method, objective
        As :func:`pipelines.subsystem.abstract_cells`; ``[start, stop)`` is exactly one chunk of the group.

    Returns
    -------
    dict
        The chunk's done-marker (start, stop, successors, slope_x, slope_w, seconds of compute).

    Raises
    ------
    CompabsError
        Whatever the method raises (a BlackBoxError for a NaN, ...), unchanged: the runner re-raises it.
    """
    t0 = time.perf_counter()
    result = abstract_cells(sub, start, stop, L_x, L_w, method, objective)
    seconds = time.perf_counter() - t0
    return write_chunk(store_url, group, result, seconds)
