"""Connecting to a Dask cluster: an embedded ``LocalCluster`` by default, or an existing scheduler.

``connect()`` starts ``LocalCluster(n_workers=workers, threads_per_worker=1, processes=True)`` with the
dashboard bound to 127.0.0.1 on a free port. One thread per worker process because the per-cell work is numpy
plus Python that holds the GIL (ENGINEERING "Dask distributed"); parallelism comes from processes.
``connect("tls://HOST:PORT")`` (or ``COMPABS_SCHEDULER=tls://HOST:PORT``) joins a running scheduler instead.

The cluster is closed to anyone without its credentials (docs/security.md): whoever can talk to a Dask scheduler
can run any code on its workers (``Client(address).run(...)``), so every comm is TLS with client certificates
(Dask's ``Security``, ``require_encryption=True``). The embedded cluster runs on credentials generated for it
(:func:`write_credentials` into a private 0700 directory, removed when the connection closes), or on those that
``COMPABS_TLS_CA``/``COMPABS_TLS_CERT``/``COMPABS_TLS_KEY`` name; ``Connection.credentials.env()`` hands them
to child processes. An external scheduler must be ``tls://`` with credentials from those variables (or Dask's
``distributed.comm.tls.*`` config); a plain ``tcp://`` one is refused unless ``COMPABS_INSECURE_SCHEDULER=1``.

The embedded cluster is owned by the client (``Client(n_workers=...)``), so closing the client closes the
cluster: ``client, info = connect(); ...; client.close()`` leaks no process, and ``with connect() as (client,
info):`` (or ``conn.close()``) closes it for you and deletes its generated credentials at once (otherwise they go
when the client is collected or the process exits). A client of an external scheduler closes only its own
connection.

Process workers are started with ``spawn``, so the calling program's ``__main__`` must be importable (a file or
``python -m``, not a script piped on stdin); the error message says so.
"""

from __future__ import annotations

import logging
import os
import shutil
import time
import weakref
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from workers.errors import ClusterError
from workers.tls import (  # noqa: F401  (the credentials' names, as this module has always offered them)
    CREDENTIAL_FILES,
    TLS_ENV,
    TLS_TMP_PREFIX,
    Credentials,
    _temporary_credentials,
    remove_stale_credentials,
    write_credentials,
)
from workers.worker_signals import embedded_worker_config

logger = logging.getLogger(__name__)

#: Environment variable naming an external scheduler (``tls://HOST:PORT``).
SCHEDULER_ENV = "COMPABS_SCHEDULER"
#: Set to 1 to accept a plain ``tcp://`` scheduler (no encryption, no authentication: unsafe, docs/security.md).
INSECURE_ENV = "COMPABS_INSECURE_SCHEDULER"
#: Protocols of a Dask address that are TLS with client certificates.
SECURE_PROTOCOLS = ("tls", "wss")
#: Seconds to wait for an external scheduler to answer and to have at least one worker.
CONNECT_TIMEOUT = 30.0
#: Dask configuration of compabs's workers (``workers/dask.yaml``; the image copies it to ``/etc/dask``): the
#: environment the nannies give the worker processes, glibc's malloc tuned for large numpy temporaries. Dask's own
#: default, MALLOC_TRIM_THRESHOLD_=65536, turns off glibc's dynamic mmap threshold, so every large temporary of a
#: task is mmapped and page-faulted afresh (tanks, one worker: task compute 1.25x as long with it); the file's
#: settings go further (the stress per-cell stage in 0.6x the CPU). It also slows Dask's own periodic work
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


def _insecure_allowed(environ: Mapping[str, str]) -> bool:
    return environ.get(INSECURE_ENV, "").strip().lower() in ("1", "true", "yes")


def _external_security(scheduler: str, environ: Mapping[str, str]) -> tuple[Any, Credentials | None]:
    """Dask's ``Security`` for joining ``scheduler``, and the credentials it came from (``None``: Dask's config).

    Raises
    ------
    ClusterError
        ``scheduler`` is not TLS and ``COMPABS_INSECURE_SCHEDULER`` is not set, or it is TLS and no credentials
        are configured.
    """
    from distributed.security import Security

    protocol = scheduler.split("://", 1)[0].lower() if "://" in scheduler else "tcp"
    if protocol not in SECURE_PROTOCOLS:
        if _insecure_allowed(environ):
            logger.warning("joining the Dask scheduler at %s without TLS (%s is set): anyone who can reach it can "
                           "run code on its workers", scheduler, INSECURE_ENV)
            return Security(require_encryption=False), None  # over workers/dask.yaml in /etc/dask
        raise ClusterError(
            f"refusing the Dask scheduler at {scheduler}: {protocol}:// has no encryption and no authentication, "
            "and anyone who can reach such a scheduler can run code on its workers. Run it with TLS (`dask "
            "scheduler --protocol tls --tls-ca-file ca.pem --tls-cert cert.pem --tls-key key.pem`, see "
            f"docs/security.md) and connect to tls://HOST:PORT with {', '.join(TLS_ENV.values())} set, or set "
            f"{INSECURE_ENV}=1 to accept it anyway (unsafe)."
        )
    creds = Credentials.from_env(environ)
    if creds is not None:
        return creds.security(), creds
    security: Any = Security(require_encryption=True)  # Dask's own distributed.comm.tls.* settings, if any
    if security.tls_ca_file and security.tls_client_cert:
        return security, None
    raise ClusterError(
        f"the Dask scheduler at {scheduler} needs TLS credentials: set {', '.join(TLS_ENV.values())} to the "
        "files `compabs credentials DIR` wrote for the cluster (or Dask's distributed.comm.tls.* config)."
    )


def credentials_env(client: Any) -> dict[str, str]:
    """The environment variables that let a child process join ``client``'s cluster (``connect(address)``
    there), read from the client's ``Security``.

    Raises
    ------
    ClusterError
        The client has no TLS credentials in files.
    """
    security = client.security
    files = {role: getattr(security, f"tls_{attr}", None)
             for role, attr in (("ca", "ca_file"), ("cert", "client_cert"), ("key", "client_key"))}
    env = {TLS_ENV[role]: v for role, v in files.items() if isinstance(v, str) and v and "\n" not in v}
    if len(env) != len(files):
        raise ClusterError("this Dask client has no TLS credential files to hand to another process")
    return env


class Connection(tuple):
    """``(client, info)``, closable and usable as a context manager.

    ``info`` is a dict: ``scheduler`` (address), ``workers`` (count at connection time), ``dashboard`` (URL, or
    ``None`` when bokeh is not installed and there is no dashboard page to show), ``embedded`` (whether this
    connection started the cluster). ``credentials`` are the cluster's TLS credentials (``None`` for an
    external scheduler joined through Dask's own config, or without TLS): ``credentials.env()`` lets a child
    process join the cluster. Credentials generated for an embedded cluster are deleted when it closes.
    """

    credentials: Credentials | None
    _cleanup: Any

    def __new__(cls, client: Any, info: dict[str, Any], credentials: Credentials | None = None,
                cleanup: Any = None) -> Connection:
        conn = super().__new__(cls, (client, info))
        conn.credentials = credentials
        conn._cleanup = cleanup
        return conn

    @property
    def client(self) -> Any:
        return self[0]

    @property
    def info(self) -> dict[str, Any]:
        return self[1]

    def close(self) -> None:
        """Close the client, and with it the embedded cluster (and its generated credentials) if this connection
        started one."""
        try:
            self.client.close()
        finally:
            if self._cleanup is not None:
                self._cleanup()

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
    it and leaves the cluster half closed (a later ``Client.__del__`` waits 60 s on it). Five worker kills in quick
    succession bring it about (``tests/test_trust_cluster.py``). Such a removal changes nothing the cluster
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
    loading the compiled per-cell kernels from numba's disk cache inside the job (the scheduler runs no kernel),
    and the first partitioned CPre ~0.1 s more for the synthesis modules (``workers.dask_cpre``).
    """

    def probe() -> str:
        import importlib

        importlib.import_module("workers.tasks")
        return "ok"

    def probe_and_warm() -> str:
        probe()
        import pipelines.abstraction.kernels as compiled
        import workers.dask_cpre  # noqa: F401  (synthesis parts: imported here, not in the first call's parts)

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
        ``tls://HOST:PORT`` of a running scheduler (its credentials from ``COMPABS_TLS_CA``, ``COMPABS_TLS_CERT``,
        ``COMPABS_TLS_KEY``, or Dask's ``distributed.comm.tls.*`` config); ``tcp://`` only with
        ``COMPABS_INSECURE_SCHEDULER=1``. ``None`` reads ``COMPABS_SCHEDULER``; if that is unset too, an embedded
        ``LocalCluster`` with ``workers`` single-threaded worker processes is started, on TLS with the
        credentials ``COMPABS_TLS_*`` name or, when unset, fresh ones.
    workers : int
        Worker processes of the embedded cluster (ignored for an external scheduler).

    Returns
    -------
    Connection
        ``(client, info)`` and ``credentials``; see :class:`Connection`.

    Raises
    ------
    ClusterError
        The scheduler is not TLS (and not explicitly accepted), has no credentials configured, cannot be reached
        (or refused the credentials), has no worker within ``CONNECT_TIMEOUT`` seconds, cannot import the task
        module, or the embedded cluster cannot start.
    """
    from distributed import Client

    scheduler = scheduler or os.environ.get(SCHEDULER_ENV) or None
    credentials: Credentials | None
    cleanup = None
    if scheduler is None:
        if workers < 1:
            raise ClusterError(f"workers must be >= 1, got {workers}")
        client, credentials, cleanup = _start_embedded(workers)
        embedded = True
    else:
        security, credentials = _external_security(scheduler, os.environ)
        try:
            client = Client(scheduler, timeout=CONNECT_TIMEOUT, security=security)
        except (OSError, TimeoutError) as exc:
            raise ClusterError(
                f"cannot reach the Dask scheduler at {scheduler}: {exc}. Start one (`dask scheduler`), fix the "
                "address or the credentials (a TLS scheduler refuses credentials that are not its cluster's), or "
                f"leave --scheduler / {SCHEDULER_ENV} unset to run an embedded cluster."
            ) from None
        try:
            client.wait_for_workers(1, timeout=CONNECT_TIMEOUT)
        except TimeoutError:
            client.close()
            raise ClusterError(
                f"the Dask scheduler at {scheduler} has no worker after {CONNECT_TIMEOUT:g} s: start some "
                f"(`dask worker {scheduler}` with the cluster's --tls-* files, docs/security.md)."
            ) from None
        embedded = False
    conn = Connection(client, {}, credentials, cleanup)
    try:
        _check_imports(client, scheduler=not embedded)
    except ClusterError:
        conn.close()
        raise
    conn.info.update({
        "scheduler": client.scheduler.address,
        "workers": len(client.nthreads()),
        "dashboard": _dashboard(client),
        "embedded": embedded,
    })
    return conn


def _start_embedded(workers: int) -> tuple[Any, Credentials, weakref.finalize | None]:
    """The embedded cluster's client (which owns the cluster) on TLS, its credentials, and what deletes them
    (``None``: they are the operator's, from ``COMPABS_TLS_*``)."""
    import dask
    from distributed import Client

    credentials = Credentials.from_env()
    directory = None
    if credentials is None:
        credentials, directory = _temporary_credentials()
    try:
        # The client, the LocalCluster, its scheduler and its nannies each make their Security() from this
        # config while they start (Client(n_workers=...) does not hand a security argument on to the cluster); the
        # nannies pass theirs to their worker processes.
        # Its workers leave SIGTERM/SIGHUP/SIGINT to this process, which unwinds and closes them (worker_signals).
        with dask.config.set({**EMBEDDED_CONFIG, **embedded_worker_config(), **credentials.dask_config()}):
            client = Client(
                n_workers=workers,
                threads_per_worker=1,
                processes=True,
                protocol="tls://",
                dashboard_address="127.0.0.1:0",
            )
    except RuntimeError as exc:
        if directory is not None:
            shutil.rmtree(directory, ignore_errors=True)
        raise ClusterError(
            f"cannot start a local Dask cluster: {exc}. Worker processes are spawned and import the caller's "
            "__main__: run from a file or with `python -m`, not from a script piped on stdin."
        ) from None
    except BaseException:
        if directory is not None:
            shutil.rmtree(directory, ignore_errors=True)
        raise
    # Generated credentials are deleted by Connection.close(), or when the client is collected or the process ends.
    cleanup = None if directory is None else weakref.finalize(client, shutil.rmtree, str(directory), True)
    cluster_security = client.cluster.security
    if not (client.security.require_encryption and cluster_security.require_encryption
            and cluster_security.tls_ca_file == str(credentials.ca)
            and client.scheduler.address.startswith("tls://")):
        client.close()
        if cleanup is not None:
            cleanup()
        raise ClusterError("the embedded Dask cluster did not start with TLS; refusing to run an open cluster")
    _tolerate_unknown_removals(client.cluster)
    # Read by the LocalCluster at each worker removal, after the `with` above ended (workers/dask.yaml).
    key = "distributed.deploy.lost-worker-timeout"
    dask.config.set({key: EMBEDDED_CONFIG[key]})
    return client, credentials, cleanup


def client_info(client: Any) -> dict[str, Any]:
    """What the report's ``runner`` section says of a cluster the caller connected to itself."""
    return {
        "scheduler": client.scheduler.address,
        "workers": len(client.nthreads()),
        "dashboard": _dashboard(client),
        "embedded": False,
    }


def _released_running(dask_worker: Any) -> int:
    """Tasks this worker is still running although no client wants their result any more (state ``cancelled``:
    Dask cannot interrupt a running task, it lets it finish and drops the result)."""
    state = dask_worker.state
    return sum(1 for ts in (*state.executing, *state.long_running) if ts.state == "cancelled")


def stop_released_tasks(client: Any, grace: float = 5.0, poll: float = 0.25, settle: float = 1.0) -> list[str]:
    """Restart the workers that still run released tasks after ``grace`` seconds; returns their addresses.

    A job process that is stopped (killed, or its futures cancelled) releases its tasks, but a task already running
    on a worker runs on: a long synthesis part would hold its worker for minutes after the job is gone. Dask reruns
    what else a restarted worker was running (other jobs lose time, never results). Best effort: a cluster that
    does not answer is left alone. The first ``settle`` seconds are the scheduler's, to notice the job's client is
    gone and tell the workers.
    """
    start = time.monotonic()
    deadline = start + grace
    busy: list[str] = []
    while True:
        try:
            busy = sorted(a for a, n in client.run(_released_running, on_error="ignore").items() if n)
        except Exception:  # the cluster is closing or unreachable: nothing to stop here
            return []
        now = time.monotonic()
        if (not busy and now - start >= settle) or now >= deadline:
            break
        time.sleep(poll)
    if busy:
        try:
            client.restart_workers(busy, timeout=60, raise_for_error=False)
        except Exception:
            logger.warning("could not restart workers %s, which still run a stopped job's tasks", busy)
    return busy
