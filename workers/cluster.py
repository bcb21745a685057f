"""Connecting to a Dask cluster: an embedded ``LocalCluster`` by default, or an existing scheduler.

``connect()`` starts ``LocalCluster(n_workers=workers, threads_per_worker=1, processes=True)`` with the
dashboard bound to 127.0.0.1 on a free port. One thread per worker process because the per-cell work is numpy
plus Python that holds the GIL (ENGINEERING "Dask distributed"); parallelism comes from processes.
``connect("tcp://HOST:PORT")`` (or ``COMPABS_SCHEDULER=tcp://HOST:PORT``) joins a running scheduler instead.

The embedded cluster is owned by the client (``Client(n_workers=...)``), so closing the client closes the
cluster: ``client, info = connect(); ...; client.close()`` leaks nothing, and ``with connect() as (client,
info):`` closes it for you. A client of an external scheduler closes only its own connection.

Process workers are started with ``spawn``, so the calling program's ``__main__`` must be importable (a file or
``python -m``, not a script piped on stdin); the error message says so.
"""

from __future__ import annotations

import logging
import os
from pathlib import Path
from typing import Any

from workers.errors import ClusterError

logger = logging.getLogger(__name__)

#: Environment variable naming an external scheduler (``tcp://HOST:PORT``).
SCHEDULER_ENV = "COMPABS_SCHEDULER"
#: Seconds to wait for an external scheduler to answer and to have at least one worker.
CONNECT_TIMEOUT = 30.0
#: Dask configuration of compabs's workers (``workers/dask.yaml``; the image copies it to ``/etc/dask``): the
#: environment the nannies give the worker processes, glibc's malloc tuned for large numpy temporaries. Dask's own
#: default, MALLOC_TRIM_THRESHOLD_=65536, turns off glibc's dynamic mmap threshold, so every large temporary of a
#: task is mmapped and page-faulted afresh (tanks, one worker: task compute 3.75 s with it, 3.0 s without); the
#: file's settings go further (stress per-cell stage 95.8 s -> 57.1 s CPU). It also slows Dask's own periodic work
#: (profiler, event-loop ticks), which competes with the tasks for the cores. External workers: use the same file.
DASK_CONFIG_FILE = Path(__file__).with_name("dask.yaml")


def _config_tree() -> dict[str, Any]:
    """``workers/dask.yaml`` as the nested dict it is."""
    import yaml

    return yaml.safe_load(DASK_CONFIG_FILE.read_text())


def worker_environ() -> dict[str, str]:
    """The environment variables ``workers/dask.yaml`` has the nannies set in each worker process."""
    env = _config_tree()["distributed"]["nanny"]["pre-spawn-environ"]
    return {k: str(v) for k, v in env.items() if v is not None}


def _dotted(tree: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """A nested config as ``{"a.b.c": value}``."""
    out: dict[str, Any] = {}
    for k, v in tree.items():
        if isinstance(v, dict) and v:
            out.update(_dotted(v, f"{prefix}{k}."))
        else:
            out[f"{prefix}{k}"] = v
    return out


def worker_config() -> dict[str, Any]:
    """Every setting of ``workers/dask.yaml`` as dotted keys for ``dask.config.set`` (a nested dict would replace
    whole sections of Dask's defaults)."""
    return _dotted(_config_tree())


#: The settings the embedded cluster starts under: its scheduler and nannies (in this process) read them at
#: start, and each nanny hands its config to its worker process.
EMBEDDED_CONFIG = worker_config()


class Connection(tuple):
    """``(client, info)``, closable and usable as a context manager.

    ``info`` is a dict: ``scheduler`` (address), ``workers`` (count at connection time), ``dashboard`` (URL, or
    ``None`` when bokeh is not installed and there is no dashboard page to show), ``embedded`` (whether this
    connection started the cluster).
    """

    def __new__(cls, client: Any, info: dict[str, Any]) -> Connection:
        return super().__new__(cls, (client, info))

    @property
    def client(self) -> Any:
        return self[0]

    @property
    def info(self) -> dict[str, Any]:
        return self[1]

    def close(self) -> None:
        """Close the client, and with it the embedded cluster if this connection started one."""
        self.client.close()

    def __enter__(self) -> Connection:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _tolerate_unknown_removals(cluster: Any) -> None:
    """Keep the embedded cluster's worker-status watcher alive when the scheduler removes a worker it never
    announced.

    A worker that dies while it registers (killed, out of memory at start) is announced to the LocalCluster as
    removed without ever having been added (the scheduler's WorkerStatusPlugin fails on its identity).
    distributed's handler then raises a KeyError that ends the watcher task, and ``cluster.close()`` re-raises
    it and leaves the cluster half closed (a later ``Client.__del__`` waits 60 s on it). Seen after five worker
    kills in quick succession (``tests/test_trust_cluster.py``). Such a removal changes nothing the cluster
    knows, so it is logged and skipped; every other message goes to distributed's handler.
    """
    update = cluster._update_worker_status

    def tolerant(op: str, msg: Any) -> None:
        if op == "remove" and msg not in cluster.scheduler_info.get("workers", {}):
            logger.warning("the Dask scheduler removed worker %s, which it never announced (a worker that died "
                           "while it registered); ignored", msg)
            return
        update(op, msg)

    cluster._update_worker_status = tolerant


def _dashboard(client: Any) -> str | None:
    # Without bokeh the scheduler still serves JSON routes on the port, but /status is a 404: report no URL
    # rather than a dead link.
    try:
        import bokeh  # noqa: F401
    except ImportError:
        return None
    return client.dashboard_link


def _check_imports(client: Any, scheduler: bool) -> None:
    """Import the task module on every worker (and the scheduler), or say what to install.

    An external scheduler must import it too (ENGINEERING "Dask distributed"). On workers this is also a
    warm-up: the first task would otherwise pay ~0.4 s of imports (numpy, zarr, the method) and ~0.3 s CPU of
    loading the compiled per-cell kernels from numba's disk cache inside the job (the scheduler runs no kernel).
    """

    def probe() -> str:
        import importlib

        importlib.import_module("workers.tasks")
        return "ok"

    def probe_and_warm() -> str:
        probe()
        import pipelines.abstraction.kernels as compiled

        compiled.warm_up()
        return "ok"

    try:
        if scheduler:
            client.run_on_scheduler(probe)
        client.run(probe_and_warm)
    except Exception as exc:  # anything from a remote import: name it and say what to install
        raise ClusterError(
            f"the Dask scheduler or a worker at {client.scheduler.address} cannot import compabs's task module "
            f"(workers.tasks): {type(exc).__name__}: {exc}. Install compabs (same version) in the scheduler's and "
            "the workers' environment."
        ) from None


def connect(scheduler: str | None = None, workers: int = 2) -> Connection:
    """Connect to a Dask cluster.

    Parameters
    ----------
    scheduler : str, optional
        ``tcp://HOST:PORT`` of a running scheduler. ``None`` reads ``COMPABS_SCHEDULER``; if that is unset too,
        an embedded ``LocalCluster`` with ``workers`` single-threaded worker processes is started.
    workers : int
        Worker processes of the embedded cluster (ignored for an external scheduler).

    Returns
    -------
    Connection
        ``(client, info)``; see :class:`Connection`.

    Raises
    ------
    ClusterError
        The scheduler cannot be reached, has no worker within ``CONNECT_TIMEOUT`` seconds, cannot import the
        task module, or the embedded cluster cannot start.
    """
    import dask
    from distributed import Client

    scheduler = scheduler or os.environ.get(SCHEDULER_ENV) or None
    if scheduler is None:
        if workers < 1:
            raise ClusterError(f"workers must be >= 1, got {workers}")
        try:
            with dask.config.set(EMBEDDED_CONFIG):
                client = Client(
                    n_workers=workers,
                    threads_per_worker=1,
                    processes=True,
                    dashboard_address="127.0.0.1:0",
                )
        except RuntimeError as exc:
            raise ClusterError(
                f"cannot start a local Dask cluster: {exc}. Worker processes are spawned and import the caller's "
                "__main__: run from a file or with `python -m`, not from a script piped on stdin."
            ) from None
        _tolerate_unknown_removals(client.cluster)
        # Read by the LocalCluster at each worker removal, after the `with` above ended (workers/dask.yaml).
        key = "distributed.deploy.lost-worker-timeout"
        dask.config.set({key: EMBEDDED_CONFIG[key]})
        embedded = True
    else:
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT)
        except (OSError, TimeoutError) as exc:
            raise ClusterError(
                f"cannot reach the Dask scheduler at {scheduler}: {exc}. Start one (`dask scheduler`), fix the "
                f"address, or leave --scheduler / {SCHEDULER_ENV} unset to run an embedded cluster."
            ) from None
        try:
            client.wait_for_workers(1, timeout=CONNECT_TIMEOUT)
        except TimeoutError:
            client.close()
            raise ClusterError(
                f"the Dask scheduler at {scheduler} has no worker after {CONNECT_TIMEOUT:g} s: start some "
                f"(`dask worker {scheduler}`)."
            ) from None
        embedded = False
    try:
        _check_imports(client, scheduler=not embedded)
    except ClusterError:
        client.close()
        raise
    info = {
        "scheduler": client.scheduler.address,
        "workers": len(client.nthreads()),
        "dashboard": _dashboard(client),
        "embedded": embedded,
    }
    return Connection(client, info)


def client_info(client: Any) -> dict[str, Any]:
    """What the report's ``runner`` section says of a cluster the caller connected to itself."""
    return {
        "scheduler": client.scheduler.address,
        "workers": len(client.nthreads()),
        "dashboard": _dashboard(client),
        "embedded": False,
    }
