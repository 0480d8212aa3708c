"""/healthz, /readyz and /metrics (Prometheus). No auth."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import PlainTextResponse, Response
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, Counter, Gauge, generate_latest

from ..errors import error_responses
from ..jobs import worker_health
from ..schemas import HealthPublic, ReadyPublic

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
STUCK = Gauge("cloudgraph_workers_stuck", "live workers past their job's budget", registry=REGISTRY)


@router.get("/healthz", response_model=HealthPublic)
def healthz() -> dict:
    """The API process is up."""
    return {"status": "ok"}


@router.get(
    "/readyz",
    response_model=ReadyPublic,
    responses=error_responses(503, about={503: "Redis is not reachable, or no worker is alive and free"}),
)
def readyz(request: Request) -> dict:
    """Redis answers and at least one worker is alive and not stuck past its job's budget."""
    redis = request.app.state.redis
    try:
        redis.ping()
    except Exception:
        raise HTTPException(503, "redis is not reachable", headers={"Retry-After": "5"}) from None
    live, stuck = worker_health(request.app.state.queue, request.app.state.settings)
    if live < 1:
        raise HTTPException(
            503, "no worker is alive: start one with `python -m worker`", headers={"Retry-After": "10"}
        )
    if stuck >= live:
        raise HTTPException(
            503,
            f"every worker ({live}) is stuck past its job's budget; see the worker log",
            headers={"Retry-After": "10"},
        )
    return {"status": "ready", "workers": live, "stuck": stuck}


@router.get(
    "/metrics",
    response_class=PlainTextResponse,
    response_description="Prometheus text exposition format",
)
def metrics(request: Request) -> Response:
    queue = request.app.state.queue
    try:
        QUEUED.set(queue.count)
        WAITING.set(queue.deferred_job_registry.count)
        RUNNING.set(queue.started_job_registry.count)
        FAILED.set(queue.failed_job_registry.count)
        live, stuck = worker_health(queue, request.app.state.settings)
        WORKERS.set(live)
        STUCK.set(stuck)
    except Exception:  # Redis down: the request counters still come out
        pass
    return Response(generate_latest(REGISTRY), media_type=CONTENT_TYPE_LATEST)
