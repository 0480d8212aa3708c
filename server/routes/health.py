"""/healthz, /readyz and /metrics (Prometheus). No auth."""

from __future__ import annotations

from datetime import UTC, datetime

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


def live_workers(request: Request) -> int:
    """Workers that have beaten within HEARTBEAT_S + 15 s. (RQ's worker registry keeps a killed
    worker until another worker's maintenance removes it: a lone worker's death never shows.)"""
    limit = request.app.state.settings.HEARTBEAT_S + 15
    now = datetime.now(UTC)
    return sum(
        1
        for w in Worker.all(queue=request.app.state.queue)
        if w.last_heartbeat is not None and (now - w.last_heartbeat).total_seconds() < limit
    )


@router.get("/healthz")
def healthz() -> dict:
    """The API process is up."""
    return {"status": "ok"}


@router.get("/readyz")
def readyz(request: Request) -> dict:
    """Redis answers and at least one worker is alive."""
    redis = request.app.state.redis
    try:
        redis.ping()
    except Exception as err:
        raise HTTPException(503, f"redis is not reachable: {err}") from None
    workers = live_workers(request)
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
        WORKERS.set(live_workers(request))
    except Exception:  # Redis down: the request counters still come out
        pass
    return Response(generate_latest(REGISTRY), media_type=CONTENT_TYPE_LATEST)
