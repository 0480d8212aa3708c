"""/v1/volumes: upload, list, get, delete. Ids are sha256 of the file's bytes."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import shutil
import sys
import time
from pathlib import Path

from fastapi import APIRouter, HTTPException, Request, UploadFile
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse

from cloudgraph.store import VolumeStore
from cloudgraph_service.errors import scrub, shown

from ..deps import SettingsDep, VolumesDep
from ..errors import error_responses
from ..schemas import VolumePublic

router = APIRouter(prefix="/volumes", tags=["volumes"])
log = logging.getLogger("cloudgraph.api")
ROOT = Path(__file__).resolve().parents[2]
LOCATION = {"Location": {"description": "the volume's URL", "schema": {"type": "string"}}}


#: The upload's body as OpenAPI has it. The route takes ``file`` as optional so that a form
#: without it is answered in words (422); the document says what a client must send. (``$ref``
#: None drops the schema FastAPI derives from the signature.)
def upload_body(what: str) -> dict:
    return {
        "required": True,
        "content": {
            "multipart/form-data": {
                "schema": {
                    "$ref": None,
                    "type": "object",
                    "required": ["file"],
                    "properties": {"file": {"type": "string", "format": "binary", "description": what}},
                }
            }
        },
    }


def _spool(file, store: VolumeStore) -> tuple[str, int]:
    """Copies the upload to a file of its own (the check reads it in another process), tagged
    with this process: if it dies, the next API process to start removes the file."""
    fd, tmp = store.temporary("incoming")
    try:
        with os.fdopen(fd, "wb") as out:
            shutil.copyfileobj(file, out, 1 << 20)
            size = out.tell()
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise
    return tmp, size


async def _check(tmp: str, name: str, timeout: float, request: Request, kind: str) -> dict | None:
    """Runs ``server.volume_check`` on the file (``kind``: volume or environment); its JSON
    answer, an error of our own, or None when the client went away first (the check is stopped:
    nothing is stored). The check dies with this process, too (it asks the kernel for that)."""
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "server.volume_check", tmp, name, str(os.getpid()), kind,
        cwd=ROOT, env=env, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    talk = asyncio.ensure_future(proc.communicate())
    end = time.monotonic() + timeout
    while not talk.done():
        await asyncio.wait({talk}, timeout=min(0.25, max(0.0, end - time.monotonic())))
        if talk.done():
            break
        gone = await request.is_disconnected()
        if gone or time.monotonic() >= end:
            proc.kill()
            await talk
            if gone:
                log.info("upload of %s: the client went away during the check; nothing stored", name)
                return None
            return {"error": f"{name} took over {timeout:g} s to read; is it a {kind}?", "status": 422}
    out, err = talk.result()
    try:
        return json.loads(out.decode().strip().splitlines()[-1])
    except (ValueError, IndexError):
        log.error("%s check of %s ended with %s: %s", kind, name, proc.returncode, err.decode()[-2000:])
        return {"error": f"{name} cannot be read as a {kind} (corrupt, or too large to read)", "status": 422}


async def receive_upload(request: Request, file: UploadFile | None, settings, store, kind: str, route: str):
    """An upload of ``kind`` (volume or environment) into ``store``: spooled, checked in a child
    process, stored under its bytes' sha256; 201 (200 when the same bytes were stored before)
    with its description and Location ``route``/<id>."""
    if file is None:
        raise HTTPException(422, f"send the {kind} as a multipart form field named 'file'")
    limit = settings.MAX_UPLOAD_MB * 2**20
    name = Path(file.filename or "").name or "the upload"
    tmp, size = await run_in_threadpool(_spool, file.file, store)
    try:
        if size > limit:
            raise HTTPException(413, f"upload is over the limit of {settings.MAX_UPLOAD_MB} MiB")
        if size == 0:
            raise HTTPException(422, f"upload is empty: send {store.WHAT} in the multipart field 'file'")
        async with request.app.state.upload_slots:
            answer = await _check(tmp, name, settings.UPLOAD_CHECK_S, request, kind)
    finally:
        Path(tmp).unlink(missing_ok=True)
    if answer is None:  # no one reads this answer
        raise HTTPException(400, f"the client went away before {name} was checked; nothing was stored")
    if "error" in answer:
        raise HTTPException(answer["status"], scrub(answer["error"]))
    info = answer["info"]
    return JSONResponse(
        info, status_code=201 if answer["created"] else 200, headers={"Location": f"{route}/{info['id']}"}
    )


@router.post(
    "",
    status_code=201,
    response_model=VolumePublic,
    response_description="The volume, stored",
    responses={
        201: {"headers": LOCATION},
        200: {"model": VolumePublic, "description": "The same bytes were stored before", "headers": LOCATION},
        **error_responses(
            400,
            413,
            415,
            422,
            507,
            about={
                422: "No file, an empty one, or one that is not a readable volume",
                507: "The uploads volume is full, or not writable",
            },
        ),
    },
    openapi_extra={"requestBody": upload_body("a .vdb or .vol file")},
)
async def upload_volume(
    request: Request, file: UploadFile | None = None, *, settings: SettingsDep, volumes: VolumesDep
):
    """Uploads a .vdb or .vol file (multipart field ``file``); the same bytes twice are one volume.
    The file is read, and densified, in a child process under a memory limit."""
    return await receive_upload(request, file, settings, volumes, "volume", "/v1/volumes")


@router.get("", response_model=list[VolumePublic])
def list_volumes(volumes: VolumesDep) -> list[dict]:
    return volumes.list()


@router.get("/{volume_id}", response_model=VolumePublic, responses=error_responses(404, 422))
def get_volume(volume_id: str, volumes: VolumesDep) -> dict:
    info = volumes.info(volume_id)
    if info is None:
        raise HTTPException(404, f"no volume with id {shown(volume_id)}")
    return info


@router.delete("/{volume_id}", status_code=204, responses=error_responses(404, 422))
def delete_volume(volume_id: str, volumes: VolumesDep) -> None:
    if not volumes.delete(volume_id):
        raise HTTPException(404, f"no volume with id {shown(volume_id)}")
