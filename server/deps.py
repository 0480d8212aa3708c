"""Dependencies as Annotated aliases: settings, Redis, the queue, stores, auth."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, HTTPException, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from redis import Redis
from rq import Queue

from cloudgraph.store import EnvironmentStore, VolumeStore
from cloudgraph_service.settings import Settings


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_redis(request: Request) -> Redis:
    return request.app.state.redis


def get_queue(request: Request) -> Queue:
    return request.app.state.queue


def get_volumes(request: Request) -> VolumeStore:
    return request.app.state.volumes


def get_environments(request: Request) -> EnvironmentStore:
    return request.app.state.environments


#: Declares the Bearer scheme in the OpenAPI document; ``main.RequireKey`` gives the 401 itself,
#: before a body is read, and :func:`require_key` checks again where the route is called.
bearer = HTTPBearer(
    auto_error=False, description="an API key of CLOUDGRAPH_API_KEYS (needed when the service has keys)"
)
#: The 401's words and header, the same from the middleware and from the dependency.
UNAUTHORIZED = "missing or wrong API key: send 'Authorization: Bearer <key>'"
CHALLENGE = {"WWW-Authenticate": "Bearer"}


def key_is_valid(authorization: str | None, keys: tuple[str, ...]) -> bool:
    """Whether an ``Authorization`` header holds one of ``keys`` as a Bearer token (any key when
    the service has none). Constant-time comparisons, on bytes: any header is comparable."""
    if not keys:
        return True
    scheme, _, token = (authorization or "").partition(" ")
    token = token.strip().encode() if scheme.lower() == "bearer" else b""
    return any(hmac.compare_digest(token, k.encode()) for k in keys)


def require_key(
    request: Request, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]
) -> None:
    """With CLOUDGRAPH_API_KEYS set, every /v1 route needs ``Authorization: Bearer <key>``."""
    if not key_is_valid(request.headers.get("authorization"), request.app.state.settings.API_KEYS):
        raise HTTPException(401, UNAUTHORIZED, headers=CHALLENGE)


SettingsDep = Annotated[Settings, Depends(get_settings)]
RedisDep = Annotated[Redis, Depends(get_redis)]
QueueDep = Annotated[Queue, Depends(get_queue)]
VolumesDep = Annotated[VolumeStore, Depends(get_volumes)]
EnvironmentsDep = Annotated[EnvironmentStore, Depends(get_environments)]
