"""The FastAPI application: /v1 routes, health, metrics, and the web page at /."""

from __future__ import annotations

import asyncio
import logging
import re
from collections.abc import Callable
from pathlib import Path

from fastapi import APIRouter, Depends, FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.openapi.utils import get_openapi
from fastapi.responses import JSONResponse, Response
from fastapi.staticfiles import StaticFiles
from redis import Redis
from redis.exceptions import ConnectionError as RedisConnectionError
from redis.exceptions import TimeoutError as RedisTimeoutError
from rq import Queue
from starlette.routing import compile_path

from cloudgraph.errors import CloudgraphError
from cloudgraph.store import EnvironmentStore, VolumeStore, sweep_temporaries
from cloudgraph_service.errors import scrub, storage_message
from cloudgraph_service.settings import Settings

from .deps import CHALLENGE, UNAUTHORIZED, key_is_valid, require_key
from .errors import BodyTooLarge, InputError, error_responses
from .routes import animations, caches, environments, health, jobs, renders, volumes

log = logging.getLogger("cloudgraph.api")
WEB = Path(__file__).resolve().parents[1] / "web"


def _field(loc) -> str:
    """A field's name as answers write it: ``keyframes[1].eye``."""
    return "".join(f"[{p}]" if isinstance(p, int) else f".{p}" for p in loc).lstrip(".")


def _message(err: RequestValidationError) -> str:
    parts = []
    for e in err.errors():
        if e.get("type") == "json_invalid":  # loc is ("body", character offset)
            why, at = e.get("ctx", {}).get("error", "decode error"), e.get("loc", ())[-1]
            parts.append(f"the body is not valid JSON: {why} at character {at}")
            continue
        loc = _field(p for p in e.get("loc", ()) if p != "body")
        msg = e.get("msg", "").removeprefix("Value error, ")
        if not loc and e.get("type") == "value_error":  # a body-wide rule: its message names fields
            parts.append(msg)
            continue
        parts.append(f"{loc or 'the request body'}: {msg}")
    return "; ".join(parts) or "invalid request"


class CountRequests:
    """Counts requests by method, route and status for /metrics. Plain ASGI (not
    BaseHTTPMiddleware), so that routes still see a client's disconnect."""

    def __init__(self, app):
        self.app = app

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        status = {"code": 500}

        async def send_counting(message):
            if message["type"] == "http.response.start":
                status["code"] = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_counting)
        finally:
            route = scope.get("route")
            health.REQUESTS.labels(
                scope["method"], getattr(route, "path", "unmatched"), str(status["code"])
            ).inc()


class LimitBody:
    """Refuses request bodies over their limit (413) before they are parsed: ``MAX_UPLOAD_MB``
    for volume uploads, ``MAX_BODY_KB`` for JSON. A declared Content-Length over the limit is
    answered at once (the body is read and dropped, up to ``DRAIN``, so the client sees the
    answer); a chunked body is counted as it arrives."""

    DRAIN = 4 * 2**20
    UPLOAD_SLACK = 2**20  # multipart boundaries and headers around the file

    def __init__(self, app, settings: Settings):
        self.app, self.settings = app, settings

    def limit(self, scope) -> tuple[int, str]:
        if scope["path"].rstrip("/") in ("/v1/volumes", "/v1/environments"):
            mb = self.settings.MAX_UPLOAD_MB
            return mb * 2**20 + self.UPLOAD_SLACK, f"upload is over the limit of {mb} MiB"
        kb = self.settings.MAX_BODY_KB
        return kb * 2**10, f"the request body is over the limit of {kb} KiB (MAX_BODY_KB)"

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http" or scope["method"] in ("GET", "HEAD", "OPTIONS", "DELETE"):
            return await self.app(scope, receive, send)
        limit, message = self.limit(scope)
        declared = dict(scope["headers"]).get(b"content-length", b"").decode()
        if declared.isdigit() and int(declared) > limit:
            if int(declared) <= self.DRAIN:
                while (await receive()).get("more_body"):
                    pass
            response = JSONResponse({"detail": message}, status_code=413, headers={"Connection": "close"})
            return await response(scope, receive, send)
        received = 0

        async def counted():
            nonlocal received
            msg = await receive()
            received += len(msg.get("body", b""))
            if received > limit:
                raise BodyTooLarge(message)
            return msg

        await self.app(scope, counted, send)


class RequireKey:
    """Answers a /v1 request without a valid API key (when the service has keys) with 401 before
    anything reads or parses its body: an unauthenticated upload is refused at its headers, and
    malformed JSON without a key is a 401, not a 422. A declared body up to ``LimitBody.DRAIN``
    is read and dropped after the answer, so that a client that sends it whole before reading
    sees the 401 on a connection that stays open; a larger one closes the connection."""

    def __init__(self, app, settings: Settings):
        self.app, self.keys = app, settings.API_KEYS

    async def __call__(self, scope, receive, send):
        path = scope.get("path", "")
        if scope["type"] != "http" or not self.keys or not (path == "/v1" or path.startswith("/v1/")):
            return await self.app(scope, receive, send)
        headers = dict(scope["headers"])
        if key_is_valid(headers.get(b"authorization", b"").decode("latin-1"), self.keys):
            return await self.app(scope, receive, send)
        await _answer(
            scope, receive, send, JSONResponse({"detail": UNAUTHORIZED}, status_code=401, headers=CHALLENGE)
        )


class AllowMethods:
    """Answers what no route takes before anything reads the body: a method that a path does not
    take with 405 and ``Allow``, and OPTIONS with 204 and ``Allow`` (the methods that the OpenAPI
    document gives the path); a path under /v1 that no route has with 404; a body whose
    Content-Type the operation does not read with 415 naming the one it does (a JSON scene sent
    as ``curl -d``'s form encoding read as "not an object"). Without it the web page's mount at /
    would take such requests and answer for the API."""

    def __init__(self, app, openapi: Callable[[], dict]):
        self.app, self.openapi = app, openapi
        self.paths: list[tuple[re.Pattern, dict[str, set[str]]]] | None = None

    def operations(self, scope) -> dict[str, set[str]]:
        """The methods this path takes, each with the media types of its body (none: no body);
        empty where no route has the path."""
        if self.paths is None:  # the document is complete once the app serves requests
            paths = self.openapi()["paths"]
            self.paths = [
                (
                    compile_path(p)[0],
                    {m.upper(): set(op.get("requestBody", {}).get("content", {})) for m, op in ops.items()},
                )
                for p, ops in paths.items()
            ]
        for regex, operations in self.paths:
            if regex.match(scope["path"]):
                return operations
        return {}

    async def __call__(self, scope, receive, send):
        if scope["type"] != "http":
            return await self.app(scope, receive, send)
        path, method = scope["path"], scope["method"]
        operations = self.operations(scope)
        if not operations:
            if path == "/v1" or path.startswith("/v1/"):
                detail = f"no API route {path}; the routes are in api.md and at /docs"
                return await _answer(scope, receive, send, JSONResponse({"detail": detail}, status_code=404))
            return await self.app(scope, receive, send)
        if method in operations:
            accepted = operations[method]
            sent = (
                dict(scope["headers"])
                .get(b"content-type", b"")
                .decode("latin-1")
                .split(";")[0]
                .strip()
                .lower()
            )
            json_suffix = sent.endswith("+json") and "application/json" in accepted  # (FastAPI reads it)
            if not accepted or not sent or sent in accepted or json_suffix:
                return await self.app(scope, receive, send)
            want = " or ".join(sorted(accepted))
            detail = f"{method} {path} reads a body of Content-Type {want}, not {sent}"
            return await _answer(scope, receive, send, JSONResponse({"detail": detail}, status_code=415))
        allow = ", ".join(sorted(operations))
        if method == "OPTIONS":
            response = Response(status_code=204, headers={"Allow": f"{allow}, OPTIONS"})
        else:
            response = JSONResponse(
                {"detail": f"{method} is not allowed on {path}; it takes {allow}"},
                status_code=405,
                headers={"Allow": allow},
            )
        await response(scope, receive, send)


async def _answer(scope, receive, send, response: Response) -> None:
    """Sends ``response`` to a request whose body is left unread: a declared body up to
    ``LimitBody.DRAIN`` is read and dropped after it (a client that sends the body whole before
    reading sees the answer on a connection that stays open), a larger one closes the
    connection."""
    headers = dict(scope["headers"])
    declared = headers.get(b"content-length", b"").decode("latin-1")
    small = declared.isdigit() and int(declared) <= LimitBody.DRAIN
    chunked = b"chunked" in headers.get(b"transfer-encoding", b"").lower()
    if not small and (declared or chunked):
        response.headers["Connection"] = "close"
    await response(scope, receive, send)
    if small:
        while (await receive()).get("more_body"):
            pass


def _referenced(node, found: set[str]) -> set[str]:
    """The component schema names that ``node`` (part of an OpenAPI document) refers to."""
    if isinstance(node, dict):
        ref = node.get("$ref", "")
        if ref.startswith("#/components/schemas/"):
            found.add(ref.rsplit("/", 1)[1])
        for v in node.values():
            _referenced(v, found)
    elif isinstance(node, list):
        for v in node:
            _referenced(v, found)
    return found


def _settings_limits(schemas: dict, settings: Settings) -> None:
    """The bounds the server checks (settings and server/validation.py) written into the
    component schemas, where the scene spec's own are wider (the engine's, for the CLI)."""
    from .validation import MAX_COORD, MAX_DENSITY_SCALE, MIN_RADIUS, SCALE_RANGE

    def bound(schema: str, prop: str, **limits) -> None:
        node = schemas.get(schema, {}).get("properties", {}).get(prop)
        if node is None:
            return
        for target in [v for v in node.get("anyOf", []) if v.get("type") == "number"] or [node]:
            for key, value in limits.items():
                target.pop("exclusiveMinimum" if key == "minimum" else "exclusiveMaximum", None)
                target[key] = value

    side = float(settings.MAX_IMAGE_SIDE)
    bound("CameraSpec", "width", maximum=side)
    bound("CameraSpec", "height", maximum=side)
    bound("RenderSpec", "spp", maximum=float(settings.MAX_SPP))
    bound("RenderSpec", "max_depth", maximum=float(settings.MAX_DEPTH))
    bound("CacheCreate", "max_depth", maximum=float(settings.MAX_DEPTH))
    bound("AnimationCreate", "frames", maximum=float(settings.MAX_FRAMES))
    bound("MediumSpec", "density_scale", maximum=MAX_DENSITY_SCALE)
    bound("Orbit", "radius", minimum=MIN_RADIUS, maximum=MAX_COORD)
    bound("VolumeSpec", "scale", minimum=SCALE_RANGE[0], maximum=SCALE_RANGE[1])
    for prop in ("eye", "target"):
        for item in schemas.get("CameraSpec", {}).get("properties", {}).get(prop, {}).get("prefixItems", []):
            item.update(minimum=-MAX_COORD, maximum=MAX_COORD)


def openapi_document(app: FastAPI) -> dict:
    """FastAPI's OpenAPI document, less the component schemas that nothing refers to (as the
    form FastAPI derives from the upload's signature, which that route describes itself), with
    the bounds this server's settings put on the scene spec."""
    if app.openapi_schema is None:
        doc = get_openapi(
            title=app.title, version=app.version, description=app.description, routes=app.routes
        )
        schemas = doc.get("components", {}).get("schemas", {})
        used = _referenced(doc["paths"], set())
        while True:  # what the used schemas refer to is used too
            more = _referenced([schemas[n] for n in used if n in schemas], set()) - used
            if not more:
                break
            used |= more
        for name in set(schemas) - used:
            del schemas[name]
        _settings_limits(schemas, app.state.settings)
        app.openapi_schema = doc
    return app.openapi_schema


def create_app(settings: Settings | None = None) -> FastAPI:
    settings = settings or Settings.from_env()
    app = FastAPI(
        title="cloudgraph",
        version="1",
        description="Graph radiance cache rendering of clouds and smoke. See api.md.",
        generate_unique_id_function=lambda route: route.name,  # client functions: upload_volume, ...
    )
    app.openapi = lambda: openapi_document(app)
    app.state.settings = settings
    app.state.redis = Redis.from_url(settings.REDIS_URL, socket_timeout=10)
    app.state.queue = Queue(settings.QUEUE, connection=app.state.redis)
    app.state.volumes = VolumeStore(settings.volumes_dir)
    app.state.environments = EnvironmentStore(settings.environments_dir)
    app.state.upload_slots = asyncio.Semaphore(2)  # volume checks at once (each a child process)
    for folder in (settings.volumes_dir, settings.environments_dir):
        for p in sweep_temporaries(folder):  # uploads of an API process that died
            log.info("removed %s, left by an upload whose API process died", p.name)

    @app.exception_handler(RequestValidationError)
    async def validation_error(request: Request, err: RequestValidationError):
        return JSONResponse({"detail": _message(err)}, status_code=422)

    @app.exception_handler(InputError)
    async def input_error(request: Request, err: InputError):
        return JSONResponse({"detail": str(err)}, status_code=422)

    @app.exception_handler(CloudgraphError)
    async def domain_error(request: Request, err: CloudgraphError):
        return JSONResponse({"detail": scrub(str(err))}, status_code=422)

    # The data folders a request may write, by the name its errors give them
    data = {"uploads": settings.volumes_dir, "cache": settings.cache_dir, "outputs": settings.outputs_dir}

    @app.exception_handler(OSError)
    async def storage_error(request: Request, err: OSError):
        message = storage_message(err, data)
        log.error("%s %s failed", request.method, request.url.path, exc_info=err)
        if message is None:
            message, status = "internal error; the service log has the details", 500
        else:
            status = 507
        return JSONResponse({"detail": message}, status_code=status)

    @app.exception_handler(Exception)
    async def internal_error(request: Request, err: Exception):
        log.error("%s %s failed", request.method, request.url.path, exc_info=err)
        return JSONResponse({"detail": "internal error; the service log has the details"}, status_code=500)

    @app.exception_handler(RedisConnectionError)
    @app.exception_handler(RedisTimeoutError)
    async def redis_down(request: Request, err: Exception):
        log.warning("redis is not reachable: %s", err)
        return JSONResponse(
            {"detail": "the job store (Redis) is not reachable; try again shortly"},
            status_code=503,
            headers={"Retry-After": "5"},
        )

    # Outermost last: counted, then a method the path does not take (405, OPTIONS), then the key
    # (401), both before anything reads the body; then the body's limit
    app.add_middleware(LimitBody, settings=settings)
    app.add_middleware(RequireKey, settings=settings)
    app.add_middleware(AllowMethods, openapi=app.openapi)
    app.add_middleware(CountRequests)

    v1 = APIRouter(prefix="/v1", dependencies=[Depends(require_key)], responses=error_responses(401))
    for r in (volumes, environments, caches, renders, animations, jobs):
        v1.include_router(r.router)
    app.include_router(v1)
    app.include_router(health.router)
    if WEB.is_dir():
        app.mount("/", StaticFiles(directory=WEB, html=True), name="web")
    return app
