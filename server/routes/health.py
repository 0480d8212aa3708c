"""/healthz, /readyz and /metrics (Prometheus). No auth."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import Response
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Gauge, generate_latest
from rq import Worker

router = APIRouter(tags=["health"])

REGISTRY = CollectorRegistry()
REQUESTS = Counter(
    "cloudgraph_http_requests_total", "HTTP requests", ["method", "route", "status"], registry=REGISTRY
)
QUEUED = Gauge("cloudgraph_jobs_queued", "jobs waiting in the queue", registry=REGISTRY)
WAITING = Gauge("cloudgraph_jobs_waiting", "jobs waiting on other jobs", registry=REGISTRY)
RUNNING = Gauge("cloudgraph_jobs_running", "jobs being run", registry=REGISTRY)
FAILED = Gauge("cloudgraph_jobs_failed", "failed jobs kept", registry=REGISTRY)
WORKERS = Gauge("cloudgraph_workers", "live workers", registry=REGISTRY)


@router.get("/healthz")
def healthz() -> dict:
    """The API process is up."""
    return {"status": "ok"}


@router.get("/readyz")
def readyz(request: Request) -> dict:
    """Redis answers and at least one worker is alive."""
    redis, queue = request.app.state.redis, request.app.state.queue
    try:
        redis.ping()
    except Exception as err:
        raise HTTPException(503, f"redis is not reachable: {err}") from None
    workers = Worker.count(queue=queue)
    if workers < 1:
        raise HTTPException(503, "no worker is alive: start one with `python -m worker`")
    return {"status": "ready", "workers": workers}


@router.get("/metrics")
def metrics(request: Request) -> Response:
    queue = request.app.state.queue
    try:
        QUEUED.set(queue.count)
        WAITING.set(queue.deferred_job_registry.count)
        RUNNING.set(queue.started_job_registry.count)
        FAILED.set(queue.failed_job_registry.count)
        WORKERS.set(Worker.count(queue=queue))
    except Exception:  # Redis down: the request counters still come out
        pass
    return Response(generate_latest(REGISTRY), media_type=CONTENT_TYPE_LATEST)
