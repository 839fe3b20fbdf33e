"""A completed job's asset: the manifest with the file list, single files, and the zip; DELETE removes a finished
job's asset and work folder (its record stays)."""

from __future__ import annotations

import json

from fastapi import APIRouter
from fastapi.responses import FileResponse

from services import cleanup, crud
from services.errors import ApiError, not_found
from services.redact import redact_data
from services.routes.deps import SessionDep, TenantDep
from services.schemas import AssetManifest, Deleted
from services.storage import StorageError, get_storage

router = APIRouter(tags=["assets"])


def _asset_key(s: SessionDep, tenant_id: str, job_id: str) -> str:
    job = crud.job_of_tenant(s, tenant_id, job_id)
    if job is None:
        raise not_found("job", job_id)
    if job.state == "completed" and not job.asset_key:
        raise ApiError(410, f"the asset of job {job_id} was deleted")
    if job.state != "completed" or not job.asset_key:
        raise ApiError(409, f"job {job_id} is {job.state}; its asset exists once it has completed")
    return job.asset_key


@router.get("/jobs/{job_id}/asset", response_model=AssetManifest)
def asset_manifest(job_id: str, s: SessionDep, tenant: TenantDep) -> AssetManifest:
    storage = get_storage()
    key = _asset_key(s, tenant.id, job_id) + "/asset"
    files = storage.list(key)
    manifest = redact_data(json.loads(storage.path(key + "/manifest.json").read_text()))
    return AssetManifest(job_id=job_id, files=files, bytes=sum(storage.size(f"{key}/{f}") for f in files),
                         manifest=manifest)  # fmt: skip


@router.get("/jobs/{job_id}/asset.zip", response_class=FileResponse)
def asset_zip(job_id: str, s: SessionDep, tenant: TenantDep) -> FileResponse:
    path = get_storage().path(_asset_key(s, tenant.id, job_id) + "/asset.zip")
    return FileResponse(path, media_type="application/zip", filename=f"{job_id}.zip")


@router.get("/jobs/{job_id}/asset/files/{file_path:path}", response_class=FileResponse)
def asset_file(job_id: str, file_path: str, s: SessionDep, tenant: TenantDep) -> FileResponse:
    storage = get_storage()
    key = _asset_key(s, tenant.id, job_id) + "/asset"
    try:
        path = storage.path(f"{key}/{file_path}")
    except StorageError:
        raise not_found("asset file", file_path) from None
    if not path.is_file() or not path.is_relative_to(storage.path(key)):
        raise not_found("asset file", file_path)
    return FileResponse(path)


@router.delete("/jobs/{job_id}/asset", response_model=Deleted,
               summary="Delete a finished job's asset and work folder (409 while it is queued or running)")
def delete_asset(job_id: str, s: SessionDep, tenant: TenantDep) -> Deleted:
    job = crud.job_of_tenant(s, tenant.id, job_id)
    if job is None:
        raise not_found("job", job_id)
    freed = cleanup.delete_asset(s, job)
    s.commit()
    return Deleted(deleted=f"asset and work folder of job {job_id}", bytes_freed=freed)
