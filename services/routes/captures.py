"""Capture uploads: POST /v1/captures (a zip body, or a multi-file form whose file names are paths inside the
capture), and the NodeODM-style session POST /v1/uploads, POST /v1/uploads/{id}/files, POST
/v1/uploads/{id}/commit. A capture exists only once validated (see services/uploads.py)."""

from __future__ import annotations

import shutil
import time
from pathlib import Path
from typing import Annotated

import anyio
from fastapi import APIRouter, Query, Request, Response
from sqlalchemy import select
from starlette.datastructures import UploadFile

from services import uploads
from services.core.config import get_settings
from services.core.db import session_scope
from services.errors import ApiError, not_found
from services.models import Capture, Upload, new_id
from services.routes.deps import SessionDep, TenantDep
from services.schemas import CaptureOut, UploadInit, UploadOut
from services.storage import get_storage

router = APIRouter(tags=["captures"])


async def _form_files(request: Request, limit_files: int) -> list[UploadFile]:
    try:
        form = await request.form(max_files=limit_files + 1, max_fields=100)
    except Exception as exc:  # malformed multipart, or too many parts
        if "Too many files" in str(exc):
            raise ApiError(413, f"too many files in one request; at most {limit_files} are allowed") from None
        raise ApiError(400, f"could not read the multipart form ({exc})") from None
    files = [v for _, v in form.multi_items() if isinstance(v, UploadFile)]
    if not files:
        raise ApiError(422, "the form holds no files (send the capture's files as 'files' parts named by their "
                       "path inside the capture, or a zip as the request body)")
    return files


async def _receive(request: Request, dest: Path, budget: int) -> tuple[int, int]:
    """Save a zip body (unpacked safely) or form files under dest; returns (files, bytes received)."""
    st = get_settings()
    ctype = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if ctype == "multipart/form-data":
        files = await _form_files(request, st.max_files)
        try:
            return await uploads.save_form_files(files, dest, st, budget)
        finally:
            for f in files:
                await f.close()
    if ctype in ("application/zip", "application/x-zip-compressed", "application/octet-stream"):
        zip_path = dest.parent / f".{dest.name}.zip"
        t0 = time.perf_counter()
        received = await uploads.stream_to_file(request.stream(), zip_path, budget)
        t1 = time.perf_counter()
        await anyio.to_thread.run_sync(uploads.unpack_zip, zip_path, dest, st)
        request.state.timing = {"receive": t1 - t0, "unpack": time.perf_counter() - t1}
        return uploads.count_files(dest)[0], received
    raise ApiError(415, f"unsupported content type {ctype or 'none'!r}: send a zip (application/zip) or a "
                   "multipart/form-data form of files")


async def _commit(tenant_id: str, folder: Path, name: str, received: int) -> Capture:
    st, storage = get_settings(), get_storage()
    root, frames = await uploads.validate_folder(folder, st)
    files, size = uploads.count_files(root)
    capture_id = new_id("cap")
    key = uploads.commit_folder(storage, root, capture_id)
    try:
        with session_scope() as s:
            cap = Capture(id=capture_id, tenant_id=tenant_id, name=name or root.name, storage_key=key, files=files,
                          bytes=size, frames=frames)  # fmt: skip
            s.add(cap)
        return cap
    except BaseException:
        storage.delete(key)
        raise


@router.post("/captures", status_code=201, response_model=CaptureOut,
             summary="Upload a capture in one request (zip body or multi-file form)")
async def create_capture(request: Request, response: Response, tenant: TenantDep,
                         name: Annotated[str, Query(max_length=200)] = "") -> Capture:
    st, storage = get_settings(), get_storage()
    uploads.check_content_length(request, st.max_upload_bytes)
    upload_id = new_id("upl")
    base = storage.path(uploads.staging_key(upload_id))
    try:
        _files, received = await _receive(request, base / "files", st.max_upload_bytes)
        t0 = time.perf_counter()
        cap = await _commit(tenant.id, base / "files", name, received)
        timing = {**getattr(request.state, "timing", {}), "validate_commit": time.perf_counter() - t0}
        response.headers["Server-Timing"] = ", ".join(f"{k};dur={1e3 * v:.1f}" for k, v in timing.items())
        return cap
    finally:
        shutil.rmtree(base, ignore_errors=True)


@router.get("/captures", response_model=list[CaptureOut])
def list_captures(s: SessionDep, tenant: TenantDep, limit: Annotated[int, Query(ge=1, le=500)] = 100,
                  offset: Annotated[int, Query(ge=0)] = 0) -> list[Capture]:
    q = select(Capture).where(Capture.tenant_id == tenant.id).order_by(Capture.created_at.desc())
    return list(s.scalars(q.limit(limit).offset(offset)))


@router.get("/captures/{capture_id}", response_model=CaptureOut)
def get_capture(capture_id: str, s: SessionDep, tenant: TenantDep) -> Capture:
    cap = s.get(Capture, capture_id)
    if cap is None or cap.tenant_id != tenant.id:
        raise not_found("capture", capture_id)
    return cap


# -- NodeODM-style sessions -----------------------------------------------------------------------------------
@router.post("/uploads", status_code=201, response_model=UploadOut, summary="Start a multi-request upload")
def init_upload(body: UploadInit, s: SessionDep, tenant: TenantDep) -> Upload:
    up = Upload(tenant_id=tenant.id, name=body.name)
    s.add(up)
    s.flush()
    get_storage().path(uploads.staging_key(up.id) + "/files").mkdir(parents=True, exist_ok=True)
    return up


def _upload_of(s: SessionDep, tenant_id: str, upload_id: str) -> Upload:
    up = s.get(Upload, upload_id)
    if up is None or up.tenant_id != tenant_id:
        raise not_found("upload", upload_id)
    return up


@router.post("/uploads/{upload_id}/files", response_model=UploadOut, summary="Add files (form or zip) to an upload")
async def upload_files(upload_id: str, request: Request, tenant: TenantDep) -> Upload:
    st, storage = get_settings(), get_storage()
    with session_scope() as s:
        up = _upload_of(s, tenant.id, upload_id)
        budget = st.max_upload_bytes - up.bytes
    uploads.check_content_length(request, budget)
    files_dir = storage.path(uploads.staging_key(upload_id) + "/files")
    part = files_dir.parent / new_id("part")  # this request's files, merged only when all arrived
    try:
        files, received = await _receive(request, part, budget)
        if up.files + files > st.max_files:
            raise ApiError(413, f"the upload would hold {up.files + files} files; at most {st.max_files} are allowed")
        clashes = [p.relative_to(part).as_posix() for p in part.rglob("*")
                   if p.is_file() and (files_dir / p.relative_to(part)).exists()]  # fmt: skip
        if clashes:
            raise ApiError(409, f"{len(clashes)} file(s) were already uploaded", [{"file": c, "message": "already "
                           "uploaded"} for c in clashes[:50]])  # fmt: skip
        for p in sorted(part.rglob("*")):
            if p.is_file():
                (files_dir / p.relative_to(part)).parent.mkdir(parents=True, exist_ok=True)
                p.rename(files_dir / p.relative_to(part))
    finally:
        shutil.rmtree(part, ignore_errors=True)
    with session_scope() as s:
        up = _upload_of(s, tenant.id, upload_id)
        up.files += files
        up.bytes += received
        return up


@router.post("/uploads/{upload_id}/commit", status_code=201, response_model=CaptureOut,
             summary="Validate the uploaded files and create the capture")
async def commit_upload(upload_id: str, tenant: TenantDep) -> Capture:
    storage = get_storage()
    with session_scope() as s:
        up = _upload_of(s, tenant.id, upload_id)
        name, received = up.name, up.bytes
    base = storage.path(uploads.staging_key(upload_id))
    cap = await _commit(tenant.id, base / "files", name, received)  # on error the files stay staged (DELETE it)
    shutil.rmtree(base, ignore_errors=True)
    with session_scope() as s:
        up2 = s.get(Upload, upload_id)
        if up2 is not None:
            s.delete(up2)
    return cap


@router.delete("/uploads/{upload_id}", status_code=204, summary="Abandon an upload")
def delete_upload(upload_id: str, s: SessionDep, tenant: TenantDep) -> None:
    up = _upload_of(s, tenant.id, upload_id)
    shutil.rmtree(get_storage().path(uploads.staging_key(upload_id)), ignore_errors=True)
    s.delete(up)
