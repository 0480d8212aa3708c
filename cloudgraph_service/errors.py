"""Errors as people see them: what went wrong, never where (no server path, class name or
traceback). The full error stays in the log, under the job id."""

from __future__ import annotations

import re

from cloudgraph.errors import CloudgraphError

#: An absolute path: what a message must not show (the API's own routes, /v1/..., are fine).
_PATH = re.compile(r"(?<![\w.~:/])/(?!v1/)(?:[^\s'\"/,;:()]+/)*[^\s'\",;:()]+")
_VOLUME_FILE = re.compile(r"\.(vdb|vol)$")


class PayloadError(ValueError):
    """A job's payload that its job function refuses (a field missing, unknown or of the wrong
    type: a sender of another version, or a bug). Not the client's to fix: the log keeps this
    message, the client reads that an internal error ended the job (:func:`public_message`)."""


def scrub(text: str) -> str:
    """``text`` with every absolute path replaced: a volume file by "the volume", others by
    "a server file"."""

    def name(m: re.Match) -> str:
        return "the volume" if _VOLUME_FILE.search(m.group(0)) else "a server file"

    return _PATH.sub(name, text)


def shown(value: str, limit: int = 80) -> str:
    """A client's id or name as an answer may echo it: quoted, and cut short when long."""
    return (
        repr(value) if len(value) <= limit else repr(value[: limit // 2]) + f"... ({len(value)} characters)"
    )


def public_message(err: BaseException, job_id: str) -> str:
    """What a job's or request's error says to its client.

    Args:
        err: the exception.
        job_id: the job it ended, named so that the log's details can be found.

    Returns:
        The message of a domain error (the caller's to fix) without paths; for anything else, a
        sentence that names the job and points to the log.
    """
    if isinstance(err, CloudgraphError):
        return scrub(str(err))
    return f"an internal error ended job {job_id}; the service log has the details under that id"
