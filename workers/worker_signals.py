"""A Dask preload for the worker processes of an embedded cluster: they leave ``SIGTERM``, ``SIGHUP`` and
``SIGINT`` to the process that started them.

``timeout 600 compabs run …`` (or a terminal's Ctrl-C, or a closed terminal) signals the command's whole process
group, the embedded cluster's worker processes included. Ended by the signal at once, a worker leaves its
``multiprocessing`` semaphores behind (``resource_tracker: There appear to be N leaked semaphore objects``) and its
nanny starts a new one while the job is being stopped. Ignoring the signal, it is stopped by its nanny when the
job's process, which the signal unwinds (:mod:`service.termination`), closes the cluster: through the nanny's
stop queue, else ``SIGKILL``. Only workers the job's own process spawned load this (:func:`embedded_worker_config`),
never a cluster's workers that ``dask worker`` started, whose ``SIGTERM`` is theirs to handle.
"""

from __future__ import annotations

import signal
import threading
from typing import Any

__all__ = ["IGNORED", "dask_setup", "embedded_worker_config"]

#: The signals an embedded cluster's worker processes ignore.
IGNORED = (signal.SIGTERM, signal.SIGHUP, signal.SIGINT)


def dask_setup(worker: Any) -> None:
    """Dask's preload hook, run in the worker process when it starts."""
    if threading.current_thread() is threading.main_thread():
        for s in IGNORED:
            signal.signal(s, signal.SIG_IGN)


def embedded_worker_config() -> dict[str, Any]:
    """The Dask configuration under which an embedded cluster is started for its workers to load this module."""
    return {"distributed.worker.preload": [__name__]}
