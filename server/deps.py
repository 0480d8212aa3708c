"""Dependencies as Annotated aliases: settings, Redis, the queue, stores, auth."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, HTTPException, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from redis import Redis
from rq import Queue

from cloudgraph.store import VolumeStore
from cloudgraph_service.settings import Settings


def get_settings(request: Request) -> Settings:
    return request.app.state.settings


def get_redis(request: Request) -> Redis:
    return request.app.state.redis


def get_queue(request: Request) -> Queue:
    return request.app.state.queue


def get_volumes(request: Request) -> VolumeStore:
    return request.app.state.volumes


#: Declares the Bearer scheme in the OpenAPI document; :func:`require_key` gives the 401 itself.
bearer = HTTPBearer(
    auto_error=False, description="an API key of CLOUDGRAPH_API_KEYS (needed when the service has keys)"
)


def require_key(
    request: Request, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(bearer)]
) -> None:
    """With CLOUDGRAPH_API_KEYS set, every /v1 route needs ``Authorization: Bearer <key>``."""
    keys = request.app.state.settings.API_KEYS
    if not keys:
        return
    token = (credentials.credentials.strip() if credentials is not None else "").encode()
    if not any(hmac.compare_digest(token, k.encode()) for k in keys):  # bytes: any header is comparable
        raise HTTPException(
            401,
            "missing or wrong API key: send 'Authorization: Bearer <key>'",
            headers={"WWW-Authenticate": "Bearer"},
        )


SettingsDep = Annotated[Settings, Depends(get_settings)]
RedisDep = Annotated[Redis, Depends(get_redis)]
QueueDep = Annotated[Queue, Depends(get_queue)]
VolumesDep = Annotated[VolumeStore, Depends(get_volumes)]
