"""/v1/environments: upload, list, get, delete lat-long .exr environment maps (scene spec v1.1's
``envmap`` lights take them by id). Ids are sha256 of the file's bytes."""

from __future__ import annotations

from fastapi import APIRouter, HTTPException, Request, UploadFile

from cloudgraph_service.errors import shown

from ..deps import EnvironmentsDep, SettingsDep
from ..errors import error_responses
from ..schemas import EnvironmentPublic
from .volumes import LOCATION, receive_upload, upload_body

router = APIRouter(prefix="/environments", tags=["environments"])


@router.post(
    "",
    status_code=201,
    response_model=EnvironmentPublic,
    response_description="The environment map, stored",
    responses={
        201: {"headers": LOCATION},
        200: {
            "model": EnvironmentPublic,
            "description": "The same bytes were stored before",
            "headers": LOCATION,
        },
        **error_responses(
            400,
            413,
            415,
            422,
            507,
            about={
                422: "No file, an empty one, or not a lat-long OpenEXR image (width twice the height)",
                507: "The uploads volume is full, or not writable",
            },
        ),
    },
    openapi_extra={"requestBody": upload_body("a lat-long .exr file")},
)
async def upload_environment(
    request: Request, file: UploadFile | None = None, *, settings: SettingsDep, environments: EnvironmentsDep
):
    """Uploads a lat-long OpenEXR environment map (multipart field ``file``), read in a child
    process by Mitsuba's reader; the same bytes twice are one map."""
    return await receive_upload(request, file, settings, environments, "environment", "/v1/environments")


@router.get("", response_model=list[EnvironmentPublic])
def list_environments(environments: EnvironmentsDep) -> list[dict]:
    return environments.list()


@router.get("/{environment_id}", response_model=EnvironmentPublic, responses=error_responses(404, 422))
def get_environment(environment_id: str, environments: EnvironmentsDep) -> dict:
    info = environments.info(environment_id)
    if info is None:
        raise HTTPException(404, f"no environment map with id {shown(environment_id)}")
    return info


@router.delete("/{environment_id}", status_code=204, responses=error_responses(404, 422))
def delete_environment(environment_id: str, environments: EnvironmentsDep) -> None:
    if not environments.delete(environment_id):
        raise HTTPException(404, f"no environment map with id {shown(environment_id)}")
