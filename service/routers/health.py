"""``/health``: whether the API answers and its cluster has workers. Needs no token (for load balancers and
compose health checks) and tells nothing about jobs beyond two counts."""

from __future__ import annotations

from fastapi import APIRouter

from service.models import Health
from service.routers.common import Manager
from service.store import JobStatus

router = APIRouter(tags=["health"])


@router.get("/health", response_model=Health)
def health(manager: Manager) -> Health:
    """``{"status": "ok", "scheduler": ..., "workers": n}``: the API is up; ``workers`` is how many Dask workers
    are connected now (0 when jobs run in the API process)."""
    workers = 0
    if manager.client is not None:
        try:
            workers = len(manager.client.scheduler_info(n_workers=-1).get("workers", {}))
        except Exception:  # a scheduler that is gone: the API is still up, with no workers to offer
            workers = 0
    return Health(
        scheduler=manager.cluster.get("scheduler"), workers=workers, dashboard=manager.cluster.get("dashboard"),
        jobs_running=len(manager.running_ids), jobs_queued=manager.store.count((JobStatus.QUEUED,)),
    )
