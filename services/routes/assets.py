"""A completed job's asset: the manifest with the file list, single files, and the zip; DELETE removes a finished
job's asset and work folder (its record stays)."""

from __future__ import annotations

import json
from collections.abc import Mapping

from fastapi import APIRouter
from fastapi.responses import FileResponse, StreamingResponse
from starlette.responses import Response

from services import cleanup, crud
from services.errors import ApiError, not_found
from services.redact import redact_data
from services.routes.deps import SessionDep, TenantDep
from services.schemas import AssetManifest, Deleted
from services.storage import NotStored, Storage, StorageError, check_key, get_storage

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


def stored_file(storage: Storage, folder: str, rel: str) -> str | None:
    """The key of the stored file `rel` inside the folder key `folder`, or None when `rel` is not one: a bad or
    climbing name, missing, a folder, or (local storage) a link that leads out of `folder`."""
    try:
        key = check_key(f"{folder}/{rel}")
        if not key.startswith(check_key(folder) + "/"):
            return None
        local = storage.local_path(key)
        if local is None:
            return key if storage.is_file(key) else None
        root = storage.local_path(folder)
    except StorageError:
        return None
    return key if root is not None and local.is_relative_to(root) and local.is_file() else None  # resolved paths


def file_response(storage: Storage, key: str, media_type: str | None = None,
                  headers: Mapping[str, str] | None = None, filename: str | None = None) -> Response:
    """The stored file `key` as a response: a FileResponse from the local folder (sendfile, ranges), else the
    object streamed from S3 in 1 MiB chunks with its Content-Length (never whole in memory)."""
    local = storage.local_path(key)
    if local is not None:
        if not local.is_file():
            raise NotStored(f"storage key {key!r} is not a stored file")
        return FileResponse(local, media_type=media_type, headers=headers, filename=filename)
    import mimetypes
    from urllib.parse import quote

    size, chunks = storage.read_chunks(key)
    out = {**(headers or {}), "Content-Length": str(size)}
    if filename is not None:
        out["Content-Disposition"] = f"attachment; filename*=utf-8''{quote(filename)}"
    media = media_type or mimetypes.guess_type(key)[0] or "application/octet-stream"
    return StreamingResponse(chunks, media_type=media, headers=out)


@router.get("/jobs/{job_id}/asset", response_model=AssetManifest)
def asset_manifest(job_id: str, s: SessionDep, tenant: TenantDep) -> AssetManifest:
    storage = get_storage()
    key = _asset_key(s, tenant.id, job_id) + "/asset"
    try:
        manifest = redact_data(json.loads(storage.read_bytes(key + "/manifest.json")))
    except NotStored:
        raise ApiError(410, f"the asset of job {job_id} is missing from the storage") from None
    sizes = storage.sizes(key)
    return AssetManifest(job_id=job_id, files=sorted(sizes), bytes=sum(sizes.values()), manifest=manifest)


@router.get("/jobs/{job_id}/asset.zip", response_class=FileResponse)
def asset_zip(job_id: str, s: SessionDep, tenant: TenantDep) -> Response:
    storage = get_storage()
    key = _asset_key(s, tenant.id, job_id) + "/asset.zip"
    try:
        return file_response(storage, key, "application/zip", filename=f"{job_id}.zip")
    except NotStored:
        raise ApiError(410, f"the asset of job {job_id} is missing from the storage") from None


@router.get("/jobs/{job_id}/asset/files/{file_path:path}", response_class=FileResponse)
def asset_file(job_id: str, file_path: str, s: SessionDep, tenant: TenantDep) -> Response:
    storage = get_storage()
    key = stored_file(storage, _asset_key(s, tenant.id, job_id) + "/asset", file_path)
    if key is None:
        raise not_found("asset file", file_path)
    return file_response(storage, key)


@router.delete("/jobs/{job_id}/asset", response_model=Deleted,
               summary="Delete a finished job's asset and work folder (409 while it is queued or running)")
def delete_asset(job_id: str, s: SessionDep, tenant: TenantDep) -> Deleted:
    job = crud.job_of_tenant(s, tenant.id, job_id)
    if job is None:
        raise not_found("job", job_id)
    freed = cleanup.delete_asset(s, job)
    s.commit()
    return Deleted(deleted=f"asset and work folder of job {job_id}", bytes_freed=freed)
