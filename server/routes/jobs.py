"""/v1/jobs: status, progress as server-sent events, cancel."""

from __future__ import annotations

import asyncio
import json

from fastapi import APIRouter, HTTPException
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import Response, StreamingResponse

from cloudgraph_service.errors import shown

from ..deps import RedisDep
from ..errors import error_responses
from ..jobs import TERMINAL, cancel, describe, fetch
from ..schemas import JobPublic

router = APIRouter(prefix="/jobs", tags=["jobs"])


def _job(redis, job_id: str):
    job = fetch(redis, job_id)
    if job is None:
        raise HTTPException(404, f"no job {shown(job_id)}")
    return job


@router.get("/{job_id}", response_model=JobPublic, responses=error_responses(404, 422, 503))
def get_job(job_id: str, redis: RedisDep) -> JobPublic:
    return describe(_job(redis, job_id))


@router.get(
    "/{job_id}/events",
    response_class=Response,
    responses={
        200: {
            "description": "``event: progress`` and ``event: end``, each with a JobPublic as ``data``",
            "content": {"text/event-stream": {"schema": {"type": "string"}}},
        },
        **error_responses(404, 422, 503),
    },
)
async def job_events(job_id: str, redis: RedisDep):
    """Server-sent events: ``progress`` on every change, then one ``end`` with the final state."""
    job = _job(redis, job_id)

    async def stream():
        last = None
        while True:
            d = await run_in_threadpool(describe, job)
            body = d.model_dump(mode="json")
            state = (body["status"], body["stage"], body["fraction"])
            if state != last:
                last = state
                yield f"event: progress\ndata: {json.dumps(body)}\n\n"
            if d.status in TERMINAL:
                yield f"event: end\ndata: {json.dumps(body)}\n\n"
                return
            await asyncio.sleep(0.25)

    return StreamingResponse(
        stream(),
        media_type="text/event-stream",
        headers={"Cache-Control": "no-cache", "X-Accel-Buffering": "no"},
    )


@router.post(
    "/{job_id}/cancel",
    response_model=JobPublic,
    responses=error_responses(404, 409, 413, 422, 503, about={409: "The job has already ended"}),
)
def cancel_job(job_id: str, redis: RedisDep) -> JobPublic:
    """Cancels a queued or running job (and an animation's frame jobs)."""
    job = _job(redis, job_id)
    if describe(job).status in TERMINAL:
        raise HTTPException(409, f"job {job_id} has already ended ({describe(job).status.value})")
    cancel(redis, job)
    return describe(job)
