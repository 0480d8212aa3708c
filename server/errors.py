"""The API's own errors, each mapped to one status code by its type (``main.create_app``)."""

from __future__ import annotations

from fastapi import HTTPException


class InputError(Exception):
    """A request field out of its documented range (422). The message names the field."""

    def __init__(self, field: str, message: str):
        super().__init__(f"{field}: {message}")
        self.field = field


class BodyTooLarge(HTTPException):
    """A request body over its size limit (413); raised while the body is being received."""

    def __init__(self, detail: str):
        super().__init__(413, detail)
