"""The API's own errors, each mapped to one status code by its type (``main.create_app``), and
the one body every error answer has (:class:`ErrorPublic`), documented route by route
(:func:`error_responses`)."""

from __future__ import annotations

from fastapi import HTTPException
from pydantic import BaseModel, Field


class InputError(Exception):
    """A request field out of its documented range (422). The message names the field."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field


class BodyTooLarge(HTTPException):
    """A request body over its size limit (413); raised while the body is being received."""

    def __init__(self, detail: str):
        super().__init__(413, detail)


class ErrorPublic(BaseModel):
    """The body of every error answer, 422 included: one sentence for a person, naming the field
    or the id at fault and what to do about it."""

    detail: str = Field(examples=["scene.camera: image 8192x8192 is over the limit of 2048 pixels a side"])


def _seconds(why: str) -> dict:
    return {"description": why, "schema": {"type": "integer", "minimum": 0}}


#: What each error status means on this API, and the headers it comes with. (A method that a
#: path does not take is 405 with ``Allow``, and a path that no route has 404, both from
#: ``main.AllowMethods``: no operation to document.)
ERRORS: dict[int, tuple[str, dict]] = {
    400: ("The body cannot be parsed: JSON that is not UTF-8, or a broken multipart form", {}),
    401: (
        "Missing or wrong API key (when the service has keys): send 'Authorization: Bearer <key>'",
        {"WWW-Authenticate": {"description": "Bearer", "schema": {"type": "string"}}},
    ),
    404: ("No such resource; the message names the id", {}),
    409: ("The resource exists but is not ready for this (its job has not finished)", {}),
    410: ("The resource's file is gone (evicted); ask for it again", {}),
    413: ("The request body is over its limit (MAX_UPLOAD_MB for uploads, MAX_BODY_KB for JSON)", {}),
    415: ("The body's Content-Type is not the one this operation reads (the message names it)", {}),
    422: ("A field is missing, malformed or out of its range; the message names it", {}),
    429: (
        "The render queue is full",
        {"Retry-After": _seconds("seconds to wait before trying again")},
    ),
    503: (
        "The job store (Redis) is not reachable",
        {"Retry-After": _seconds("seconds to wait before trying again")},
    ),
    507: ("A data volume that the request writes to is full, or not writable; the message says which", {}),
}


def error_responses(*codes: int, about: dict[int, str] | None = None) -> dict[int, dict]:
    """The OpenAPI ``responses`` of a route's error answers: each an :class:`ErrorPublic` body,
    described by :data:`ERRORS` or, for this route, by ``about``."""
    about = about or {}
    out = {}
    for code in codes:
        why, headers = ERRORS[code]
        out[code] = {"model": ErrorPublic, "description": about.get(code, why)}
        if headers:
            out[code]["headers"] = headers
    return out
