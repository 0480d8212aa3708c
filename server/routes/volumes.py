"""/v1/volumes: upload, list, get, delete. Ids are sha256 of the file's bytes."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Request, UploadFile
from fastapi.concurrency import run_in_threadpool
from fastapi.responses import JSONResponse

from cloudgraph.errors import VolumeError

from ..deps import SettingsDep, VolumesDep

router = APIRouter(prefix="/volumes", tags=["volumes"])


@router.post("", status_code=201)
async def upload_volume(
    request: Request, file: UploadFile | None = None, *, settings: SettingsDep, volumes: VolumesDep
):
    """Uploads a .vdb or .vol file (multipart field ``file``); the same bytes twice are one volume."""
    if file is None:
        raise HTTPException(422, "send the volume as a multipart form field named 'file'")
    try:
        info, created = await run_in_threadpool(
            volumes.put, file.file, settings.MAX_UPLOAD_MB * 2**20, file.filename or ""
        )
    except VolumeError as err:
        code = 413 if "over the limit" in str(err) else 422
        raise HTTPException(code, str(err).replace(str(settings.volumes_dir) + "/", "")) from None
    return JSONResponse(
        info, status_code=201 if created else 200, headers={"Location": f"/v1/volumes/{info['id']}"}
    )


@router.get("")
def list_volumes(volumes: VolumesDep) -> list[dict]:
    return volumes.list()


@router.get("/{volume_id}")
def get_volume(volume_id: str, volumes: VolumesDep) -> dict:
    info = volumes.info(volume_id)
    if info is None:
        raise HTTPException(404, f"no volume with id {volume_id!r}")
    return info


@router.delete("/{volume_id}", status_code=204)
def delete_volume(volume_id: str, volumes: VolumesDep) -> None:
    if not volumes.delete(volume_id):
        raise HTTPException(404, f"no volume with id {volume_id!r}")
