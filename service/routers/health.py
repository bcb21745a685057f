"""``/health``: whether the API answers and its cluster has workers. Needs no token (for load balancers and
compose health checks), so it tells nothing about jobs beyond two counts and nothing that locates the cluster:
no scheduler address, no dashboard URL (docs/security.md). A job's record (behind the token) links the dashboard."""

from __future__ import annotations

from fastapi import APIRouter

from service.job_store import JobStatus
from service.models import Health
from service.routers.common import Manager

router = APIRouter(tags=["health"])


@router.get("/health", response_model=Health)
def health(manager: Manager) -> Health:
    """``{"status": "ok", "workers": n, ...}``: the API is up; ``workers`` is how many Dask workers are connected
    now (0 when jobs run in the API process)."""
    workers = 0
    if manager.client is not None:
        try:
            workers = len(manager.client.scheduler_info(n_workers=-1).get("workers", {}))
        except Exception:  # a scheduler that is gone: the API is still up, with no workers to offer
            workers = 0
    return Health(
        workers=workers, jobs_running=len(manager.running_ids), jobs_queued=manager.store.count((JobStatus.QUEUED,)),
    )
