"""/v1/volumes: upload, list, get, delete. Ids are sha256 of the file's bytes."""

from __future__ import annotations

import asyncio
import json
import logging
import os
import shutil
import sys
import tempfile
from pathlib import Path

from fastapi import APIRouter, HTTPException, Request, UploadFile
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse

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
UPLOAD_BODY = {
    "required": True,
    "content": {
        "multipart/form-data": {
            "schema": {
                "$ref": None,
                "type": "object",
                "required": ["file"],
                "properties": {
                    "file": {"type": "string", "format": "binary", "description": "a .vdb or .vol file"}
                },
            }
        }
    },
}


def _spool(file, folder: Path, limit: int) -> tuple[str, int]:
    """Copies the upload to a file of its own (the check reads it in another process)."""
    folder.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(dir=folder, prefix=".incoming.", suffix=".tmp")
    with os.fdopen(fd, "wb") as out:
        shutil.copyfileobj(file, out, 1 << 20)
        size = out.tell()
    return tmp, size


async def _check(tmp: str, name: str, timeout: float) -> dict:
    """Runs ``server.volume_check`` on the file; its JSON answer, or an error of our own."""
    env = {**os.environ, "OPENBLAS_NUM_THREADS": "1", "OMP_NUM_THREADS": "1"}
    proc = await asyncio.create_subprocess_exec(
        sys.executable, "-m", "server.volume_check", tmp, name,
        cwd=ROOT, env=env, stdout=asyncio.subprocess.PIPE, stderr=asyncio.subprocess.PIPE,
    )  # fmt: skip
    try:
        out, err = await asyncio.wait_for(proc.communicate(), timeout)
    except TimeoutError:
        proc.kill()
        await proc.wait()
        return {"error": f"{name} took over {timeout:g} s to read; is it a volume?", "status": 422}
    try:
        return json.loads(out.decode().strip().splitlines()[-1])
    except (ValueError, IndexError):
        log.error("volume check of %s ended with %s: %s", name, proc.returncode, err.decode()[-2000:])
        return {"error": f"{name} cannot be read as a volume (corrupt, or too large to read)", "status": 422}


@router.post(
    "",
    status_code=201,
    response_model=VolumePublic,
    response_description="The volume, stored",
    responses={
        201: {"headers": LOCATION},
        200: {"model": VolumePublic, "description": "The same bytes were stored before", "headers": LOCATION},
        **error_responses(
            400, 413, 422, about={422: "No file, an empty one, or one that is not a readable volume"}
        ),
    },
    openapi_extra={"requestBody": UPLOAD_BODY},
)
async def upload_volume(
    request: Request, file: UploadFile | None = None, *, settings: SettingsDep, volumes: VolumesDep
):
    """Uploads a .vdb or .vol file (multipart field ``file``); the same bytes twice are one volume.
    The file is read, and densified, in a child process under a memory limit."""
    if file is None:
        raise HTTPException(422, "send the volume as a multipart form field named 'file'")
    limit = settings.MAX_UPLOAD_MB * 2**20
    name = Path(file.filename or "").name or "the upload"
    tmp, size = await run_in_threadpool(_spool, file.file, settings.volumes_dir, limit)
    try:
        if size > limit:
            raise HTTPException(413, f"upload is over the limit of {settings.MAX_UPLOAD_MB} MiB")
        if size == 0:
            raise HTTPException(
                422, "upload is empty: send a .vdb or .vol file in the multipart field 'file'"
            )
        async with request.app.state.upload_slots:
            answer = await _check(tmp, name, settings.UPLOAD_CHECK_S)
    finally:
        Path(tmp).unlink(missing_ok=True)
    if "error" in answer:
        raise HTTPException(answer["status"], scrub(answer["error"]))
    info = answer["info"]
    return JSONResponse(
        info, status_code=201 if answer["created"] else 200, headers={"Location": f"/v1/volumes/{info['id']}"}
    )


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
