"""The FastAPI application: /v1 routes, health, metrics, and the web page at /."""

from __future__ import annotations

from pathlib import Path

from fastapi import APIRouter, Depends, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from fastapi.staticfiles import StaticFiles
from redis import Redis
from rq import Queue

from cloudgraph.errors import CloudgraphError
from cloudgraph.store import VolumeStore

from .deps import require_key
from .routes import animations, caches, health, jobs, renders, volumes
from .settings import Settings

WEB = Path(__file__).resolve().parents[1] / "web"


def _message(err: RequestValidationError) -> str:
    parts = []
    for e in err.errors():
        loc = ".".join(str(p) for p in e.get("loc", ()) if p != "body")
        parts.append(f"{loc}: {e.get('msg', '').removeprefix('Value error, ')}" if loc else e.get("msg", ""))
    return "; ".join(parts) or "invalid request"


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings.from_env()
    app = FastAPI(
        title="cloudgraph",
        version="1",
        description="Graph radiance cache rendering of clouds and smoke. See api.md.",
    )
    app.state.settings = settings
    app.state.redis = Redis.from_url(settings.REDIS_URL, socket_timeout=10)
    app.state.queue = Queue(settings.QUEUE, connection=app.state.redis)
    app.state.volumes = VolumeStore(settings.volumes_dir)

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, err: RequestValidationError):
        return JSONResponse({"detail": _message(err)}, status_code=422)

    @app.exception_handler(CloudgraphError)
    async def domain_error(request: Request, err: CloudgraphError):
        return JSONResponse({"detail": str(err)}, status_code=422)

    @app.middleware("http")
    async def count_requests(request: Request, call_next):
        response = await call_next(request)
        route = request.scope.get("route")
        health.REQUESTS.labels(
            request.method, getattr(route, "path", "unmatched"), str(response.status_code)
        ).inc()
        return response

    v1 = APIRouter(prefix="/v1", dependencies=[Depends(require_key)])
    for r in (volumes, caches, renders, animations, jobs):
        v1.include_router(r.router)
    app.include_router(v1)
    app.include_router(health.router)
    if WEB.is_dir():
        app.mount("/", StaticFiles(directory=WEB, html=True), name="web")
    return app
